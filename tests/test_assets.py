"""The optional asset folder: $TORCHRASTER_DATA first, else the development layout."""

from __future__ import annotations

from pathlib import Path

from torchraster.testing import assets


def test_data_dir_follows_the_environment(monkeypatch, tmp_path: Path) -> None:
    monkeypatch.setenv(assets.ENV_VAR, str(tmp_path))
    assert assets.data_dir() == tmp_path.resolve()
    monkeypatch.delenv(assets.ENV_VAR)
    checkout = Path(assets.__file__).resolve().parents[2]
    assert assets.data_dir() == checkout.parent / "shared" / "data"
