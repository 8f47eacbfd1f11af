"""From a validated render config to images on disk.

    import torchraster as tr
    cfg = tr.load_config("configs/quickstart.yaml")
    tr.render_to_files(cfg, "out/")          # or: views = tr.render_config(cfg)

Every file is written atomically (a temporary file ``.<name>.trtmp-XXXX<suffix>`` in the
same folder, then a rename) with the permissions a plain ``open()`` would give under the
user's umask, so a crash never leaves a half-written image behind; temporary files left by
a killed run are swept from a folder before it is written again.

A config describes a list of views (:func:`plan_objects`): its objects (one mesh, or a mesh
set: a glob or a list file) times its cameras (``random_orbits`` drawn per object). This
module plans views, renders them and writes files; everything built from the config (scene,
cameras, lights, renderer, post chain) comes from :mod:`torchraster.config.build`. Sharded,
resumable rendering of many configs to a folder is :func:`torchraster.distributed.render_dataset`.
"""

from __future__ import annotations

import errno
import importlib.util
import os
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from .config import (
    CameraConfig,
    ConfigError,
    RenderFile,
    build_camera,
    build_setup,
    check_config,
    expand_cameras,
    is_mesh_set,
    mesh_set,
    object_config,
    object_name,
    view_names,
)
from .config import build_scene as build_scene  # re-exported: scripts and examples use it
from .post import EncodeSRGB
from .renderer import RenderPlan

#: Linear colour channels: encoded to sRGB for PNG.
_SRGB_CHANNELS = {"albedo", "emissive", "radiance"}
#: Marker in the names of our temporary files (swept when found at start).
TEMP_MARKER = ".trtmp-"


@dataclass
class ViewResult:
    """One rendered camera.

    Attributes:
        name: the camera's output name (sanitised, unique in its config).
        images: ``{channel: (C, H, W) float tensor}``: ``color`` display-encoded in
            [0, 1], ``radiance`` linear HDR, G-buffer channels raw.
        plan: the :class:`~torchraster.RenderPlan` that ran.
        mask: ``(1, H, W)`` coverage > 0, for the display encodings.
        view: ``(4, 4)`` world -> view matrix (OpenGL convention) of the camera.
        proj: ``(4, 4)`` projection matrix (view -> clip).
    """

    name: str
    images: dict[str, torch.Tensor]
    plan: RenderPlan
    mask: torch.Tensor = field(repr=False, default_factory=lambda: torch.ones(1, 1, 1))
    view: torch.Tensor | None = field(repr=False, default=None)
    proj: torch.Tensor | None = field(repr=False, default=None)


@dataclass(frozen=True)
class ViewSpec:
    """One view of a config: which object, which camera, where its files go.

    Attributes:
        object: the object's name (the mesh set entry's, else :func:`object_name`).
        camera: the view's name (unique per object).
        folder: the view's folder relative to the config's output folder, POSIX style:
            ``<object>/<camera>`` for a mesh set, ``<camera>`` when the config has several
            views, ``""`` (the folder itself) for one.
        seed: the view's seed (:func:`~torchraster.config.stable_seed`).
        camera_config: the concrete camera (named; ``random_orbits`` drawn).
    """

    object: str
    camera: str
    folder: str
    seed: int
    camera_config: CameraConfig = field(repr=False)


@dataclass
class ObjectPlan:
    """The views of one object of a config.

    Attributes:
        name: the object's name.
        mesh: its mesh file (None for a scene of ``scene.objects`` only).
        config: the config of this object alone (its mesh, its concrete cameras).
        views: one :class:`ViewSpec` per camera, in order.
    """

    name: str
    mesh: Path | None
    config: RenderFile = field(repr=False)
    views: list[ViewSpec]


def plan_objects(cfg: RenderFile, seed: int = 0) -> list[ObjectPlan]:
    """Every object of a config with its views, in a fixed order (the same in every
    process): mesh set entries sorted (glob) or in list order, cameras in config order.

    Args:
        cfg: a validated config.
        seed: mixed into every view's seed (``RenderDataset(seed=...)``; 0 for the CLI).
    """
    in_set = is_mesh_set(cfg)
    if in_set:
        objects = [(e.name, e.path) for e in mesh_set(cfg)]
        several = True
    else:
        objects = [(object_name(cfg), cfg.scene.mesh)]
        several = sum(len(names) for names in view_names(cfg)) > 1
    plans = []
    for name, mesh in objects:
        cams = expand_cameras(cfg, name, seed)
        views = [ViewSpec(name, c.name, f"{name}/{c.name}" if in_set else (
            c.name if several else ""), c.seed, c.camera) for c in cams]
        plans.append(ObjectPlan(name, None if mesh is None else Path(mesh),
                                object_config(cfg, mesh, [c.camera for c in cams]), views))
    return plans


def _encode(name: str, img: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Display encoding of a channel ``(C, H, W)`` in [0, 1] for PNG (see the README)."""
    if name in _SRGB_CHANNELS:
        return EncodeSRGB()(img.clamp(0, 1)[None])[0]
    if name == "normal":
        return (img * 0.5 + 0.5) * mask
    if name == "depth":  # near = bright, far = dark, empty = black
        valid = mask[0] > 0
        if not bool(valid.any()):
            return torch.zeros_like(img)
        d = img[0][valid]
        lo, hi = float(d.min()), float(d.max())
        return ((hi - img) / max(hi - lo, 1e-12)).clamp(0, 1) * mask
    if name == "face_id":
        return ((img + 1) % 65536).float() / 65535.0
    if name == "uv":
        return torch.cat([img.clamp(0, 1), torch.zeros_like(img[:1])])
    return img.clamp(0, 1)


def render_config(cfg: RenderFile, device: str | torch.device = "cpu") -> list[ViewResult]:
    """Render every view of a config. Returns one :class:`ViewResult` per view."""
    return [render() for render in iter_render(cfg, device)]


def iter_render(cfg: RenderFile, device: str | torch.device = "cpu"
                ) -> Iterator[Callable[[], ViewResult]]:
    """The views of a config, lazily: each object's scene, lights and environment are
    loaded once (when its first view is reached), then each yielded callable renders one
    view (so a caller can report a failing view and carry on with the next).

    Yields:
        Callables returning a :class:`ViewResult`, one per view of :func:`plan_objects`, in
        order; its ``name`` is the view's folder (``<object>/<camera>`` in a mesh set) or
        its camera's name.

    Raises:
        NotImplementedError: for ``post.auto_exposure.rate``: adaptation over time needs a
            sequence of frames, and a config renders independent stills.
    """
    if cfg.post is not None and "rate" in cfg.post.auto_exposure.model_fields_set:
        raise NotImplementedError(
            "post.auto_exposure.rate: adaptation over time needs a sequence of frames; a "
            "render config renders independent stills (fully adapted), so rate would have no "
            "effect. Remove it (AutoExposure(rate=...) in Python adapts across frames).")
    for obj in plan_objects(cfg):
        render = view_renderer(obj.config, device)
        for v in obj.views:
            yield lambda v=v, render=render: render(v.camera_config, v.folder or v.camera)


def view_renderer(cfg: RenderFile, device: str | torch.device = "cpu"
                  ) -> Callable[[CameraConfig, str], ViewResult]:
    """Build what a config's views share (scene, lights, environment, renderer, post chain:
    :func:`torchraster.config.build_setup`) once; returns ``render(camera, name) ->
    ViewResult`` for any concrete camera of it.

    Args:
        cfg: a config of one object (not a mesh set; see :func:`plan_objects`).
        device: where to render.
    """
    setup = build_setup(cfg, device)
    scene, renderer, post, channels = setup.scene, setup.renderer, setup.post, setup.channels
    lights, env, res = setup.lights, setup.environment, cfg.render.size

    def render_view(cam: CameraConfig, name: str) -> ViewResult:
        view, proj = build_camera(cam, scene.positions.cpu(), res)
        with torch.no_grad():
            out = renderer(scene, view.to(device), proj.to(device), lights, env, channels)
            depth = out.gbuffer.get("depth")
            if depth is not None:  # the background is far away for depth of field
                far = depth.amax().clamp(min=1.0) * 100
                depth = torch.where(out.alpha > 0, depth, far)
            radiance = post.hdr(out.image, depth=depth)
            color = post.display(radiance.clamp(min=0) if post.tonemap.enabled
                                 else radiance.clamp(0, 1))
        images = {"color": color[0], "radiance": radiance[0], "alpha": out.alpha[0]}
        images.update({k: v[0] for k, v in out.gbuffer.items()})
        images = {k: v for k, v in images.items() if k in cfg.outputs.channels}
        return ViewResult(name, images, out.plan, (out.alpha[0] > 0).to(color.dtype),
                          view[0], proj[0])

    return render_view


def _umask_mode() -> int:
    """The mode a plain ``open(path, "w")`` gives a new file: 0o666 minus the umask."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


class OutputError(OSError):
    """Writing an output file failed; the message names the file and the reason."""


def atomic_write(path: Path, write: Callable[[str], None]) -> None:
    """Write through a temporary file in the same folder, then rename over ``path``.

    Args:
        path: the file to write.
        write: writes the content to the temporary path it is given.

    Raises:
        OutputError: naming ``path`` (the temporary file is removed).
    """
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}{TEMP_MARKER}",
                                   suffix=path.suffix)
        os.close(fd)
    except OSError as e:
        raise OutputError(f"{path}: cannot write ({e.strerror or e})") from None
    try:
        write(tmp)
        os.chmod(tmp, _umask_mode())
        os.replace(tmp, path)
    except BaseException as e:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(e, OSError):
            reason = "disk full" if e.errno == errno.ENOSPC else (e.strerror or str(e))
            raise OutputError(f"{path}: cannot write ({reason})") from None
        raise


def sweep_temp_files(folder: Path) -> list[Path]:
    """Delete temporary files a killed run left in ``folder`` (our naming pattern only)."""
    removed = []
    if folder.is_dir():
        for p in folder.glob(f".*{TEMP_MARKER}*"):
            if p.is_file():
                p.unlink(missing_ok=True)
                removed.append(p)
    return removed


def write_outputs(result: ViewResult, out_dir: str | Path, formats: list[str]) -> list[Path]:
    """Write a view's channels as ``<out_dir>/<channel>.<fmt>``; returns the written paths.

    Raises:
        OutputError: naming the file that could not be written.
    """
    from skimage import io as skio

    out_dir = Path(out_dir)
    sweep_temp_files(out_dir)
    written = []
    for name, img in result.images.items():
        img = img.detach().float().cpu()
        raw = img.numpy()
        if "png" in formats:
            enc = _encode(name, img.to(torch.float64) if name == "face_id" else img, result.mask)
            bits16 = name in ("depth", "face_id")
            arr = enc.clamp(0, 1).permute(1, 2, 0).numpy()
            arr = (arr * (65535 if bits16 else 255) + 0.5).astype(np.uint16 if bits16 else np.uint8)
            arr = arr[..., 0] if arr.shape[-1] == 1 else arr
            path = out_dir / f"{name}.png"
            atomic_write(path, lambda p, a=arr: skio.imsave(p, a, check_contrast=False))
            written.append(path)
        if "npy" in formats:
            path = out_dir / f"{name}.npy"
            atomic_write(path, lambda p, a=raw: np.save(p, a))
            written.append(path)
        if "exr" in formats:
            path = out_dir / f"{name}.exr"
            atomic_write(path, lambda p, a=raw: _write_exr(p, a))
            written.append(path)
    return written


def _write_exr(path: str, image: np.ndarray) -> None:
    import OpenEXR

    names = {1: ["Y"], 2: ["U", "V"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}[image.shape[0]]
    channels = {n: np.ascontiguousarray(image[i].astype(np.float32)) for i, n in enumerate(names)}
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, channels) as f:
        f.write(path)


def check_formats(cfg: RenderFile, source: str) -> None:
    """Fail before rendering if an output format needs a package that is missing."""
    if "exr" in cfg.outputs.formats and importlib.util.find_spec("OpenEXR") is None:
        raise ConfigError(f"{source}: outputs.formats: 'exr' needs the OpenEXR package "
                          "(pip install 'torchraster[exr]')")


def check_output_dir(out_dir: Path) -> None:
    """Fail before rendering if ``out_dir`` cannot hold outputs (a file, or not writable).

    Raises:
        OutputError: naming the folder.
    """
    probe = out_dir
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        raise OutputError(f"{probe}: --out must be a folder, but this is a file")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise OutputError(f"{probe}: output folder is not writable")


def view_folder(out_dir: Path, cfg: RenderFile, name: str) -> Path:
    """The folder of one view: ``out_dir`` (a config of one view) or ``out_dir/<name>``
    (``name`` from :class:`ViewResult`), checked to stay inside ``out_dir``."""
    several = is_mesh_set(cfg) or sum(len(names) for names in view_names(cfg)) > 1
    folder = out_dir / name if several else out_dir
    root = out_dir.resolve()
    if folder.resolve() != root and root not in folder.resolve().parents:
        raise OutputError(f"{folder}: outside the output folder {out_dir}")
    return folder


def render_to_files(cfg: RenderFile, out_dir: str | Path, device: str = "cpu") -> list[Path]:
    """Render every view of ``cfg`` into ``out_dir`` (one sub-folder per camera when there
    are several, ``<object>/<camera>`` for a mesh set). Returns the written paths. No
    manifest, no resume: see :func:`torchraster.distributed.render_dataset` for those.

    Raises:
        ConfigError: every missing file / degenerate camera, before rendering.
        OutputError: an unwritable output.
    """
    out_dir = Path(out_dir)
    check_config(cfg)
    check_formats(cfg, "config")
    check_output_dir(out_dir)
    written = []
    for render in iter_render(cfg, device):
        r = render()
        written += write_outputs(r, view_folder(out_dir, cfg, r.name), cfg.outputs.formats)
    return written
