"""Warnings during a render are printed above the progress bar, never onto its line
(issue 22): log records and Python warnings go through tqdm's ``write``."""

from __future__ import annotations

import logging
import re
import sys
import warnings
from pathlib import Path

import pytest
import trimesh

from torchraster import pipeline
from torchraster.cli import main
from torchraster.distributed import GlobalProgress, World

CONFIG = """\
scene:
  mesh: ball.obj
cameras:
  - random_orbits: {count: 3, seed: 1}
render:
  resolution: 8
outputs:
  channels: [color]
  formats: [npy]
"""


def _segments(text: str) -> list[str]:
    """The terminal's lines as drawn: split on newlines and carriage returns."""
    return [s for s in re.split(r"[\r\n]", text) if s.strip()]


def _assert_off_the_bar(err: str, *messages: str) -> None:
    for msg in messages:
        hits = [s for s in _segments(err) if msg in s]
        assert hits, f"{msg!r} not printed:\n{err!r}"
        for s in hits:  # alone on its line: no bar drawn before it on the same line
            assert "%|" not in s and "view/s" not in s and "it/s" not in s, (
                f"{msg!r} landed on the progress bar's line: {s!r}")


class _Console(logging.StreamHandler):
    """A console handler that writes to whatever ``sys.stderr`` is now (pytest swaps it)."""

    @property
    def stream(self):  # noqa: ANN201
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # noqa: ANN001
        pass


@pytest.fixture()
def console_logging(capsys):
    """A console handler on the root logger writing to (captured) stderr, as the CLI's
    logging.basicConfig installs outside pytest."""
    handler = _Console()
    logging.root.addHandler(handler)
    yield
    logging.root.removeHandler(handler)


def test_global_progress_redirects_logging_and_warnings(capsys, console_logging) -> None:
    bar = GlobalProgress(World(), total=4, done=0, steps=4)
    with bar.redirect_output():
        bar.step()
        logging.getLogger("torchraster.test").warning("log-message-one")
        bar.step()
        warnings.warn("python-warning-two", UserWarning, stacklevel=1)
        bar.step()
    bar.step()
    bar.finish()
    err = capsys.readouterr().err
    assert "%|" in err  # the bar was drawn
    _assert_off_the_bar(err, "log-message-one", "python-warning-two")


def test_render_dataset_warnings_above_the_bar(tmp_path: Path, capsys, console_logging,
                                               monkeypatch) -> None:
    """Through the CLI: a warning logged and one warned while each view is written."""
    trimesh.creation.icosphere(1).export(tmp_path / "ball.obj")
    (tmp_path / "set.yaml").write_text(CONFIG)
    write = pipeline.write_outputs

    def noisy_write(*args, **kwargs):  # noqa: ANN002, ANN003
        logging.getLogger("torchraster.pipeline").warning("clamped-radiance-note")
        warnings.warn("render-warning-note", UserWarning, stacklevel=1)
        return write(*args, **kwargs)

    monkeypatch.setattr(pipeline, "write_outputs", noisy_write)
    assert main(["render", str(tmp_path / "set.yaml"), "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert "%|" in err
    _assert_off_the_bar(err, "clamped-radiance-note", "render-warning-note")
