"""Shared pytest fixtures: the optional asset folder (``torchraster.testing.assets``:
``$TORCHRASTER_DATA``; tests using it are skipped cleanly when it is absent)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from torchraster.testing.assets import ENV_VAR, data_dir

SHARED_DATA = data_dir()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path to the asset folder; tests using it are skipped on machines without it."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"no asset folder ({SHARED_DATA}); set {ENV_VAR} to use one")
    return SHARED_DATA


@pytest.fixture(autouse=True)
def _seed_and_one_thread():
    """Seeded, single-threaded tests: test tensors are small, and intra-op threads only add
    overhead there (measured up to 50x slower per op on a loaded 2-core machine)."""
    torch.manual_seed(0)
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def pytest_addoption(parser):
    parser.addoption("--device", default="cpu",
                     help="device(s) for the device-parametrised tests: cpu, cuda or all")


def _devices(config) -> list[str]:
    choice = config.getoption("--device")
    if choice == "all":
        return ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    return [choice]


def pytest_generate_tests(metafunc):
    """kornia-style ``device`` and ``dtype`` fixtures: the test runs once per device (from
    ``--device``) and per dtype (float32, float64)."""
    explicit = {name.strip() for m in metafunc.definition.iter_markers("parametrize")
                for name in (m.args[0].split(",") if isinstance(m.args[0], str) else m.args[0])}
    if "device" in metafunc.fixturenames and "device" not in explicit:
        metafunc.parametrize("device", _devices(metafunc.config))
    if "dtype" in metafunc.fixturenames and "dtype" not in explicit:
        metafunc.parametrize("dtype", [torch.float32, torch.float64],
                             ids=["float32", "float64"])
