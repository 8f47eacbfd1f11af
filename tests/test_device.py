"""Device-agnostic code: every tensor factory the engine calls on the render path names a
device, and the core runs on every available device (kornia-style ``device``/``dtype``
fixtures from conftest.py; ``pytest --device all`` adds CUDA where it exists)."""

import importlib
import inspect
from pathlib import Path

import pytest
import torch
from torch.overrides import TorchFunctionMode

import torchraster as tr
from torchraster import camera

PACKAGE = str(Path(tr.__file__).resolve().parent)
FACTORIES = {torch.arange, torch.zeros, torch.ones, torch.full, torch.empty, torch.tensor,
             torch.linspace, torch.eye, torch.as_tensor, torch.rand, torch.randn}


class _FactoriesWithoutDevice(TorchFunctionMode):
    """Records (file, line) of torchraster's tensor factory calls that name no device (called
    by torchraster's own code: factories inside other libraries, e.g. kornia, are theirs)."""

    def __init__(self) -> None:
        super().__init__()
        self.found: set[tuple[str, int]] = set()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in FACTORIES and "device" not in kwargs:
            frame = inspect.currentframe().f_back
            if frame is not None and frame.f_code.co_filename.startswith(PACKAGE):
                self.found.add((frame.f_code.co_filename.removeprefix(PACKAGE),
                                frame.f_lineno))
        return func(*args, **kwargs)


def _scene(device, dtype):
    mesh = tr.load_spot()
    pos = mesh.positions.to(device, dtype)
    scene = tr.RenderScene(pos, mesh.faces.to(device), mesh.normals.to(device, dtype),
                           mesh.uvs.to(device, dtype), materials=[mesh.material.to(device)])
    view = camera.orbit(torch.tensor([30.0, 200.0]), 15.0, 3.0).to(device, dtype)
    proj = camera.perspective(45.0, 1.0, 0.1).to(device, dtype)
    return scene, view, proj


def test_render_path_factories_name_their_device():
    scene, view, proj = _scene("cpu", torch.float32)
    lights = tr.Lights(ambient=tr.sh_from_color(torch.full((1, 3), 0.3)),
                       point=tr.PointLights(torch.tensor([[[2.0, 2, 3]]]), torch.ones(1, 1, 3),
                                            torch.tensor([[5.0]])))
    mode = _FactoriesWithoutDevice()
    with mode:
        for shading in ("pbr", "headlight", "unlit"):
            out = tr.Renderer(64, shading=shading)(scene, view, proj, lights,
                                                   channels={"depth", "uv", "face_id"})
        # large triangles go through the tile binning path
        quad = torch.tensor([[[-1, -1, 0, 1], [1, -1, 0, 1], [1, 1, 0, 1], [-1, 1, 0, 1.0]]])
        tr.rasterize(quad, torch.tensor([[0, 1, 2], [0, 2, 3]]), (128, 128))
        # the occlusion test of back faces (tile maxima, tested boxes), forced on
        raster = importlib.import_module("torchraster.raster.rasterize")
        saved, raster.OCCLUSION_MIN_WORK = raster.OCCLUSION_MIN_WORK, 0
        try:
            clip = tr.mesh.transform_points(scene.positions, proj @ view)
            keys = raster.resolve_keys(clip, scene.faces, (96, 80), False, None, 16, 2**20, 320)
        finally:
            raster.OCCLUSION_MIN_WORK = saved
    assert out.image.shape == (2, 3, 64, 64) and (keys != raster.EMPTY_KEY).any()
    assert not mode.found, "factories without device=: " + ", ".join(
        f"{f}:{n}" for f, n in sorted(mode.found))


def test_core_runs_on_device(device, dtype):
    scene, view, proj = _scene(device, dtype)
    out = tr.Renderer(32, shading="headlight")(scene, view, proj, channels={"normal"})
    assert out.image.device.type == torch.device(device).type and out.image.dtype == dtype
    assert torch.isfinite(out.image).all() and out.alpha.sum() > 50


def test_meta_shapes():
    """Shape checks with no data: the camera and transform layer run on 'meta' tensors."""
    pos = torch.empty(5, 100, 3, device="meta")
    view = camera.look_at([0.0, 0.0, 3.0], [0.0, 0.0, 0.0]).to("meta").expand(5, 4, 4)
    clip = tr.mesh.transform_points(pos, view)
    assert clip.shape == (5, 100, 4) and clip.device.type == "meta"
    # rasterize needs data-dependent sizes (nonzero, searchsorted) and says so clearly
    with pytest.raises((NotImplementedError, RuntimeError, ValueError)):
        tr.rasterize(clip, torch.zeros(1, 3, dtype=torch.long, device="meta"), (8, 8))
