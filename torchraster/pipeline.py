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
import logging
import os
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from . import camera
from .config import (
    CameraConfig,
    ConfigError,
    RenderFile,
    SceneObjects,
    build_camera,
    build_setup,
    check_config,
    expand_cameras,
    is_mesh_set,
    mesh_set,
    object_config,
    object_name,
    scene_variants,
    view_names,
)
from .config import build_scene as build_scene  # re-exported: scripts and examples use it
from .labels import object_records
from .motion import OtherFrame
from .post import EncodeSRGB
from .renderer import RenderPlan

#: Linear colour channels: encoded to sRGB for PNG.
_SRGB_CHANNELS = {"albedo", "emissive", "radiance"}
#: Integer ids written exactly (16-bit PNG, int32 npy).
_ID_CHANNELS = {"instance", "semantic"}
#: Flow fields drawn with the colour wheel in PNG.
_FLOW_CHANNELS = {"flow_forward", "flow_backward", "motion"}
#: Marker in the names of our temporary files (swept when found at start).
TEMP_MARKER = ".trtmp-"
log = logging.getLogger("torchraster")


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
        frame, time: the frame index and its time in seconds.
        objects: the manifest's per-object records of this view
            (:func:`torchraster.labels.object_records`: ids, categories, poses, boxes).
        categories: the category names (id i + 1 = ``categories[i]``).
    """

    name: str
    images: dict[str, torch.Tensor]
    plan: RenderPlan
    mask: torch.Tensor = field(repr=False, default_factory=lambda: torch.ones(1, 1, 1))
    view: torch.Tensor | None = field(repr=False, default=None)
    proj: torch.Tensor | None = field(repr=False, default=None)
    frame: int = 0
    time: float = 0.0
    objects: list[dict] | None = field(repr=False, default=None)
    categories: list[str] | None = field(repr=False, default=None)


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
        frame: the frame index (``frames.count`` > 1 adds ``/<frame:05d>`` to the folder).
    """

    object: str
    camera: str
    folder: str
    seed: int
    camera_config: CameraConfig = field(repr=False)
    frame: int = 0


@dataclass
class ObjectPlan:
    """The views of one object of a config.

    Attributes:
        name: the object's name.
        mesh: its mesh file (None for a scene of ``scene.objects`` only).
        config: the config of this object alone (its mesh, its concrete cameras).
        views: one :class:`ViewSpec` per camera and frame, in order.
        drawn: a randomised scene's draws (:class:`~torchraster.config.Variant`), else None.
    """

    name: str
    mesh: Path | None
    config: RenderFile = field(repr=False)
    views: list[ViewSpec]
    drawn: dict | None = field(repr=False, default=None)


def plan_objects(cfg: RenderFile, seed: int = 0) -> list[ObjectPlan]:
    """Every object of a config with its views, in a fixed order (the same in every
    process): mesh set entries sorted (glob) or in list order, cameras in config order.

    Args:
        cfg: a validated config.
        seed: mixed into every view's seed (``RenderDataset(seed=...)``; 0 for the CLI).
    """
    in_set = is_mesh_set(cfg)
    variants = scene_variants(cfg, seed)
    if in_set:
        objects = [(e.name, e.path, cfg, None) for e in mesh_set(cfg)]
        several = True
    elif variants:
        objects = [(v.name, cfg.scene.mesh, v.config, v.drawn) for v in variants]
        in_set = several = True  # <variant>/<camera>/...
    else:
        objects = [(object_name(cfg), cfg.scene.mesh, cfg, None)]
        several = sum(len(names) for names in view_names(cfg)) > 1
    frames = cfg.frames.count
    plans = []
    for name, mesh, source, drawn in objects:
        cams = expand_cameras(source, name, seed)
        views = []
        for c in cams:
            base = f"{name}/{c.name}" if in_set else (c.name if several else "")
            for f in range(frames):
                folder = "/".join(p for p in (base, f"{f:05d}" if frames > 1 else "") if p)
                views.append(ViewSpec(name, c.name, folder, c.seed, c.camera, f))
        plans.append(ObjectPlan(name, None if mesh is None else Path(mesh),
                                object_config(source, mesh, [c.camera for c in cams]), views,
                                drawn))
    return plans


def _encode(name: str, img: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Display encoding of a channel ``(C, H, W)`` in [0, 1] for PNG (see the README)."""
    if name in _SRGB_CHANNELS:
        return EncodeSRGB()(img.clamp(0, 1)[None])[0]
    if name == "normal":
        return (img * 0.5 + 0.5) * mask
    if name in ("depth", "distance"):  # near = bright, far = dark, empty = black
        valid = mask[0] > 0
        if not bool(valid.any()):
            return torch.zeros_like(img)
        d = img[0][valid]
        lo, hi = float(d.min()), float(d.max())
        return ((hi - img) / max(hi - lo, 1e-12)).clamp(0, 1) * mask
    if name == "face_id":
        return ((img + 1) % 65536).float() / 65535.0
    if name in _ID_CHANNELS:  # exact 16-bit ids
        return img.double() / 65535.0
    if name == "uv":
        return torch.cat([img.clamp(0, 1), torch.zeros_like(img[:1])])
    if name in _FLOW_CHANNELS:
        return flow_to_color(img) * mask
    if name == "object_coords":
        return img.clamp(0, 1) * mask
    return img.clamp(0, 1)


#: The Middlebury colour wheel (Baker et al., "A Database and Evaluation Methodology for
#: Optical Flow", IJCV 2011): hue segments red-yellow 15, yellow-green 6, green-cyan 4,
#: cyan-blue 11, blue-magenta 13, magenta-red 6.
_WHEEL_SEGMENTS = ((15, (1, 0, 0), (1, 1, 0)), (6, (1, 1, 0), (0, 1, 0)),
                   (4, (0, 1, 0), (0, 1, 1)), (11, (0, 1, 1), (0, 0, 1)),
                   (13, (0, 0, 1), (1, 0, 1)), (6, (1, 0, 1), (1, 0, 0)))


def _color_wheel() -> torch.Tensor:
    rows = []
    for n, a, b in _WHEEL_SEGMENTS:
        s = torch.arange(n, dtype=torch.float64)[:, None] / n
        rows.append(torch.tensor(a, dtype=torch.float64) * (1 - s)
                    + torch.tensor(b, dtype=torch.float64) * s)
    return torch.cat(rows)  # (55, 3)


def flow_to_color(flow: torch.Tensor, max_norm: float | None = None) -> torch.Tensor:
    """Colour-wheel picture of a flow field: hue = direction, saturation = length (white =
    no motion), as in the Middlebury benchmark.

    Args:
        flow: ``(2, H, W)`` (x right, y down; pixels or any unit).
        max_norm: the length drawn fully saturated (default: the field's largest).

    Returns:
        ``(3, H, W)`` float in [0, 1].
    """
    f = flow.detach().double().cpu()
    u, v = f[0], f[1]
    norm = (u * u + v * v).sqrt()
    top = float(norm.max()) if max_norm is None else max_norm
    radius = (norm / top).clamp(max=1) if top > 0 else torch.zeros_like(norm)
    wheel = _color_wheel()
    n = wheel.shape[0]
    angle = torch.atan2(-v, -u) / torch.pi  # in [-1, 1]
    k = (angle + 1) / 2 * (n - 1)
    k0 = k.floor().long().clamp(0, n - 1)
    k1 = (k0 + 1) % n
    w = (k - k0)[..., None]
    col = wheel[k0] * (1 - w) + wheel[k1] * w
    col = 1 - radius[..., None] * (1 - col)
    return col.permute(2, 0, 1).float()


def id_preview(ids: torch.Tensor) -> torch.Tensor:
    """Distinct colours for integer ids (0 = black): ``(1, H, W)`` -> ``(3, H, W)`` in
    [0, 1], the same colour for an id in every view (golden-ratio hues)."""
    i = ids[0].long().cpu()
    hue = (i.double() * 0.618033988749895) % 1.0
    h6 = hue * 6
    c = [((h6 - k) % 6 - 3).abs().sub(1).clamp(0, 1) for k in (0, 4, 2)]  # HSV, s = v = 1
    rgb = torch.stack(c) * 0.85 + 0.15
    return torch.where(i[None] > 0, rgb, 0.0).float()


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
        NotImplementedError: for ``post.auto_exposure.rate`` (see :func:`view_renderer`).
    """
    for obj in plan_objects(cfg):
        render = view_renderer(obj.config, device)
        for v in obj.views:
            yield lambda v=v, render=render: render(v.camera_config, v.folder or v.camera,
                                                    v.frame)


def view_renderer(cfg: RenderFile, device: str | torch.device = "cpu"
                  ) -> Callable[..., ViewResult]:
    """Build what a config's views share (scene, lights, environment, renderer, post chain:
    :func:`torchraster.config.build_setup`) once; returns ``render(camera, name, frame=0)
    -> ViewResult`` for any concrete camera of it and any frame.

    Frame ``i`` is at time ``i / frames.fps``: objects and cameras are posed there. Flow
    and motion channels use the scene and camera one frame later (``flow_forward``) or
    earlier (``flow_backward``, ``motion``); animations hold their end keys outside their
    key times, so the first frame's backward and the last frame's forward flow are defined
    too. Every view also gets its per-object records (:attr:`ViewResult.objects`).

    The renderer keeps the poses and other frames of its last few frames: rendering the
    frames of a camera in order, each frame poses the scene and rasterizes the depth of
    flow validity once (not three and two times); the images are the same in any order.

    Args:
        cfg: a config of one object (not a mesh set; see :func:`plan_objects`).
        device: where to render.
    """
    if cfg.post is not None and "rate" in cfg.post.auto_exposure.model_fields_set:
        raise NotImplementedError(
            "post.auto_exposure.rate: a render config renders every view fully adapted (frames "
            "may render in any order, on any rank), so rate would have no effect. Remove it "
            "(AutoExposure(rate=...) in Python adapts across the frames you feed it).")
    setup = build_setup(cfg, device)
    objects, renderer, post = setup.objects, setup.renderer, setup.post
    lights, env, res = setup.lights, setup.environment, cfg.render.size
    frame_framing = setup.scene.positions.cpu()  # orbits frame the scene at time 0
    wanted = set(cfg.outputs.channels)
    channels = set(setup.channels) | {"instance"}  # the per-object records need it
    if any(k is not None for k in objects.keypoints):
        channels.add("depth")
    dt = 1.0 / cfg.frames.fps
    objects.prepare([f * dt for f in range(-1, cfg.frames.count + 1)])  # frames, neighbours

    # the other frames of the last few renders by (camera, frame): frame f's next frame is
    # frame f + 2's previous one, so its depth (rasterized for flow validity and stored on
    # the OtherFrame by the renderer) is reused when the frames of a camera render in order
    others: dict[tuple[str, int], OtherFrame] = {}

    def other(cam: CameraConfig, frame: int) -> OtherFrame:
        key = (cam.model_dump_json(), frame)
        found = others.pop(key, None)
        if found is None:
            t = frame * dt
            view, proj = build_camera(cam, frame_framing, res, t)
            found = OtherFrame(objects.positions_at(t).to(device), view.to(device),
                               proj.to(device))
            while len(others) >= 6:  # frame f - 1 was made by frame f - 2: keep 3 frames
                others.pop(next(iter(others)))  # the least recently used
        others[key] = found
        return found

    def render_view(cam: CameraConfig, name: str, frame: int = 0) -> ViewResult:
        t = frame * dt
        view, proj = build_camera(cam, frame_framing, res, t)
        scene = objects.at(t)
        motion = {}
        if channels & {"flow_forward", "flow_forward_valid"}:
            motion["next_frame"] = other(cam, frame + 1)
        if channels & {"flow_backward", "flow_backward_valid", "motion"}:
            motion["previous_frame"] = other(cam, frame - 1)
        with torch.no_grad():
            out = renderer(scene, view.to(device), proj.to(device), lights, env, channels,
                           **motion)
            depth = out.gbuffer.get("depth") if post.dof.enabled else None
            if depth is not None:  # the background is far away for depth of field
                far = depth.amax().clamp(min=1.0) * 100
                depth = torch.where(out.alpha > 0, depth, far)
            radiance = post.hdr(out.image, depth=depth)
            color = post.display(radiance.clamp(min=0) if post.tonemap.enabled
                                 else radiance.clamp(0, 1))
        if not bool((out.alpha > 0).any()):
            log.warning("%s: the camera sees nothing of the scene (an empty image); check "
                        "its placement", name)
        images = {"color": color[0], "radiance": radiance[0], "alpha": out.alpha[0]}
        images.update({k: v[0] for k, v in out.gbuffer.items()})
        records = _object_records(objects, t, images, view[0], proj[0], res)
        images = {k: v for k, v in images.items() if k in wanted}
        return ViewResult(name, images, out.plan, (out.alpha[0] > 0).to(color.dtype),
                          view[0], proj[0], frame, t, records, objects.category_names)

    return render_view


def _object_records(objects: SceneObjects, t: float, images: dict[str, torch.Tensor],
                    view: torch.Tensor, proj: torch.Tensor, res: tuple[int, int]) -> list[dict]:
    """The per-object records of one view (see :func:`torchraster.labels.object_records`)."""
    perspective = float(proj[3, 3]) == 0.0
    k = camera.intrinsics_from_projection(proj.double().cpu(), res) if perspective else None
    gl_to_cv = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))
    depth = images.get("depth")
    return object_records(
        instance=images["instance"][0].cpu(), object_to_world=objects.object_to_world(t),
        box_center=objects.box_center, box_size=objects.box_size, names=objects.names,
        categories=objects.categories, category_ids=objects.category_ids,
        world_to_camera=gl_to_cv @ view.double().cpu(), k=k,
        amodal=images["amodal"].cpu() if "amodal" in images else None,
        depth=depth[0].cpu() if depth is not None else None, keypoints=objects.keypoints)


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


#: zlib level of the PNGs the batch command writes (``outputs.png_compression``): level 1
#: writes a labelled 256² view's files in ~55 % of level 6's time for ~35 % more PNG bytes
#: (docs/benchmarks.md, dataset-png); PNG is lossless at every level.
PNG_COMPRESSION = 1


def write_png(path: Path, image: np.ndarray, compression: int = PNG_COMPRESSION) -> None:
    """Write a ``(H, W)`` or ``(H, W, 3 | 4)`` uint8 / ``(H, W)`` uint16 array as PNG at
    zlib level ``compression`` (0-9), atomically (:func:`atomic_write`)."""
    from PIL import Image

    if image.dtype == np.uint16 and image.ndim != 2:
        raise ValueError(f"{path}: 16-bit PNGs are written single-channel, got shape "
                         f"{image.shape}")
    atomic_write(Path(path), lambda tmp: Image.fromarray(np.ascontiguousarray(image)).save(
        tmp, format="PNG", compress_level=int(compression)))


def write_outputs(result: ViewResult, out_dir: str | Path, formats: list[str],
                  previews: bool = False, png_compression: int = PNG_COMPRESSION) -> list[Path]:
    """Write a view's channels as ``<out_dir>/<channel>.<fmt>``; returns the written paths.
    ``amodal`` is always one ``amodal.npy`` ``(N, H, W)`` uint8 stack; ``instance`` and
    ``semantic`` are exact (16-bit PNG, int32 npy), with ``previews`` also
    ``<channel>_preview.png`` in distinct colours; PNGs at zlib level ``png_compression``.

    Raises:
        OutputError: naming the file that could not be written.
    """
    out_dir = Path(out_dir)
    sweep_temp_files(out_dir)
    written = []
    for name, img in result.images.items():
        if name == "amodal":  # (N, H, W) masks: one npy stack whatever the formats
            path = out_dir / "amodal.npy"
            masks = img.detach().cpu().to(torch.uint8).numpy()
            atomic_write(path, lambda p, a=masks: np.save(p, a))
            written.append(path)
            continue
        ids = name in _ID_CHANNELS
        raw = img.detach().cpu().to(torch.int32 if ids else torch.float32).numpy()
        img = img.detach().float().cpu()
        if ids and previews:  # previews are PNGs whatever the formats
            path = out_dir / f"{name}_preview.png"
            rgb = (id_preview(img).permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)
            write_png(path, rgb, png_compression)
            written.append(path)
        if "png" in formats:
            exact = name == "face_id" or ids
            enc = _encode(name, result.images[name].detach().cpu().double() if exact else img,
                          result.mask)
            bits16 = name in ("depth", "distance", "face_id") or ids
            arr = enc.clamp(0, 1).permute(1, 2, 0).numpy()
            arr = (arr * (65535 if bits16 else 255) + 0.5).astype(np.uint16 if bits16 else np.uint8)
            arr = arr[..., 0] if arr.shape[-1] == 1 else arr
            path = out_dir / f"{name}.png"
            write_png(path, arr, png_compression)
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
    several = (is_mesh_set(cfg) or cfg.randomize is not None or cfg.frames.count > 1
               or sum(len(names) for names in view_names(cfg)) > 1)
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
        written += write_outputs(r, view_folder(out_dir, cfg, r.name), cfg.outputs.formats,
                                 cfg.outputs.previews, cfg.outputs.png_compression)
    return written
