"""From a validated render config to images on disk.

    import torchraster as tr
    cfg = tr.load_config("configs/quickstart.yaml")
    tr.render_to_files(cfg, "out/")          # or: views = tr.render_config(cfg)

Every file is written atomically (a temporary file ``.<name>.trtmp-XXXX<suffix>`` in the
same folder, then a rename) with the permissions a plain ``open()`` would give under the
user's umask, so a crash never leaves a half-written image behind; temporary files left by
a killed run are swept from a folder before it is written again.

A config describes a list of views (:func:`plan_objects`): its objects (one mesh, or a mesh
set: a glob or a list file) times its cameras (``random_orbits`` drawn per object). Sharded,
resumable rendering of many configs to a folder is :func:`torchraster.distributed.render_dataset`.
"""

from __future__ import annotations

import errno
import importlib.util
import math
import os
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from . import camera
from .config import (
    CameraConfig,
    ConfigError,
    ObjectConfig,
    ObjectMaterialConfig,
    RenderFile,
    TransformConfig,
    build_post_chain,
    build_renderer,
    check_config,
    expand_cameras,
    is_mesh_set,
    lights_from_config,
    mesh_set,
    object_config,
    object_name,
    view_names,
)
from .hdr_io import read_hdr
from .io import load_scene, load_texture
from .material import Material
from .mesh import Mesh, vertex_normals
from .mesh import flat as flat_mesh
from .post import EncodeSRGB, PostChain
from .renderer import RenderPlan
from .scene import RenderScene
from .shading.ibl import Environment

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
        mesh = cfg.resolve(cfg.scene.mesh) if cfg.scene.mesh is not None else None
        objects = [(object_name(cfg), mesh)]
        several = sum(len(names) for names in view_names(cfg)) > 1
    plans = []
    for name, mesh in objects:
        cams = expand_cameras(cfg, name, seed)
        views = [ViewSpec(name, c.name, f"{name}/{c.name}" if in_set else (
            c.name if several else ""), c.seed, c.camera) for c in cams]
        plans.append(ObjectPlan(name, mesh, object_config(cfg, mesh, [c.camera for c in cams]),
                                views))
    return plans


def _transform_matrix(t: TransformConfig) -> torch.Tensor:
    """(4, 4) model -> world: scale, then rotations about x, y, z (degrees), then translate."""
    import kornia

    scale = torch.tensor(t.scale if isinstance(t.scale, list) else [t.scale] * 3)
    angles = torch.deg2rad(torch.tensor(t.rotate_deg))[None]
    rx, ry, rz = (kornia.geometry.conversions.axis_angle_to_rotation_matrix(
        torch.eye(3)[i:i + 1] * angles[0, i]) for i in range(3))
    m = torch.eye(4)
    m[:3, :3] = (rz @ ry @ rx)[0] * scale
    m[:3, 3] = torch.tensor(t.translate)
    return m


def build_scene(cfg: RenderFile) -> RenderScene:
    """Load and transform the config's scene (the main mesh and every entry of
    ``scene.objects``) into one :class:`RenderScene` with per-face materials and shadow
    flags (names the file on error)."""
    parts: list[_Part] = []
    sc = cfg.scene
    if sc.mesh is not None:
        parts.append(_file_part(cfg, sc.mesh, sc.transform, sc.normals, sc.cast_shadows,
                                sc.receive_shadows))
    for i, obj in enumerate(sc.objects):
        if obj.mesh is not None:
            parts.append(_file_part(cfg, obj.mesh, obj.transform, "auto", obj.cast_shadows,
                                    obj.receive_shadows))
        else:
            parts.append(_primitive_part(obj, obj.name or f"{obj.primitive}{i}",
                                         cfg.resolve("."), sc.max_texture_size))
    for part in parts:
        part.materials = [_override(mat, cfg) for mat in part.materials]
    return _merge(parts)


@dataclass
class _Part:
    """One object of a config's scene, in world space."""

    positions: torch.Tensor
    faces: torch.Tensor
    normals: torch.Tensor | None
    uvs: torch.Tensor | None
    tangents: torch.Tensor | None
    face_material: torch.Tensor
    materials: list
    cast: torch.Tensor
    receive: torch.Tensor


def _file_part(cfg: RenderFile, relative: str, transform: TransformConfig, normals_mode: str,
               cast: bool, receive: bool) -> _Part:
    scene = load_scene(cfg.resolve(relative), max_texture_size=cfg.scene.max_texture_size,
                       allow_missing_textures=cfg.scene.allow_missing_textures)
    mesh, face_material, materials = scene.flatten()
    node_cast, node_receive = scene.face_shadow_flags()
    if normals_mode == "flat":
        mesh = flat_mesh(mesh)
    m = _transform_matrix(transform)
    positions = mesh.positions @ m[:3, :3].T + m[:3, 3]
    normals = None
    if mesh.normals is not None and normals_mode != "smooth":
        normals = torch.nn.functional.normalize(mesh.normals @ torch.linalg.inv(m[:3, :3]), dim=-1)
    return _Part(positions, mesh.faces, normals, mesh.uvs, mesh.tangents, face_material,
                 list(materials), node_cast & cast, node_receive & receive)


def _primitive_part(obj: ObjectConfig, name: str, base_dir: Path,
                    max_texture: int | None) -> _Part:
    """A plane, box or sphere of ``obj.size`` with its material, in world space."""
    import trimesh

    s = float(obj.size)
    if obj.primitive == "plane":
        h = s / 2
        positions = torch.tensor([[-h, 0, -h], [h, 0, -h], [h, 0, h], [-h, 0, h]])
        faces = torch.tensor([[0, 2, 1], [0, 3, 2]])  # counter-clockwise seen from +Y
        normals = torch.tensor([[0.0, 1.0, 0.0]]).expand(4, 3)
        uvs = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    else:
        tm = (trimesh.creation.box(extents=[s, s, s]) if obj.primitive == "box"
              else trimesh.creation.icosphere(subdivisions=3, radius=s / 2))
        mesh = Mesh(torch.tensor(tm.vertices, dtype=torch.float32),
                    torch.tensor(tm.faces, dtype=torch.int64))
        if obj.primitive == "box":
            mesh = flat_mesh(mesh)  # sharp edges: one normal per face
            positions, faces, normals = mesh.positions, mesh.faces, mesh.normals
            # each face projected along its axis: [0, 1]^2 over the face
            axis = normals.abs().argmax(-1, keepdim=True)
            keep = torch.tensor([[1, 2], [0, 2], [0, 1]]).index_select(0, axis.flatten())
            uvs = torch.gather(positions, 1, keep) / s + 0.5
        else:
            positions, faces = mesh.positions, mesh.faces
            normals = torch.nn.functional.normalize(positions, dim=-1)
            # latitude-longitude
            uvs = torch.stack([0.5 + torch.atan2(normals[:, 0], normals[:, 2]) / (2 * math.pi),
                               0.5 + torch.asin(normals[:, 1].clamp(-1, 1)) / math.pi], -1)
    m = _transform_matrix(obj.transform)
    positions = positions.float() @ m[:3, :3].T + m[:3, 3]
    normals = torch.nn.functional.normalize(normals.float() @ torch.linalg.inv(m[:3, :3]),
                                            dim=-1)
    mc = obj.material or ObjectMaterialConfig()
    rgba = list(mc.base_color) + ([1.0] if len(mc.base_color) == 3 else [])
    texture = None
    if mc.base_color_texture is not None:
        texture = load_texture(base_dir.joinpath(mc.base_color_texture), max_size=max_texture)
    material = Material(name=mc.name or f"object:{name}", base_color_factor=torch.tensor(rgba),
                        base_color_texture=texture, metallic_factor=mc.metallic,
                        roughness_factor=mc.roughness, emissive_factor=torch.tensor(mc.emissive),
                        alpha_mode=mc.alpha_mode, alpha_cutoff=mc.alpha_cutoff,
                        double_sided=obj.primitive == "plane" or mc.alpha_mode != "OPAQUE")
    n_faces = faces.shape[0]
    return _Part(positions, faces, normals, uvs, None,
                 torch.zeros(n_faces, dtype=torch.int64), [material],
                 torch.full((n_faces,), obj.cast_shadows), torch.full((n_faces,),
                                                                      obj.receive_shadows))


def _merge(parts: list[_Part]) -> RenderScene:
    """One RenderScene of all parts (missing normals computed, missing UVs / tangents
    zero-filled where another part has them)."""
    if len(parts) == 1 and bool(parts[0].cast.all()) and bool(parts[0].receive.all()):
        p = parts[0]
        return RenderScene(p.positions, p.faces, p.normals, p.uvs, p.tangents, p.face_material,
                           p.materials)
    any_uv = any(p.uvs is not None for p in parts)
    any_tan = any(p.tangents is not None for p in parts)
    pos, faces, nrm, uvs, tan, fmat, mats = [], [], [], [], [], [], []
    offset = 0
    for p in parts:
        n_vert = p.positions.shape[0]
        pos.append(p.positions)
        faces.append(p.faces + offset)
        nrm.append(p.normals if p.normals is not None
                   else vertex_normals(p.positions, p.faces).reshape(-1, 3))
        if any_uv:
            uvs.append(p.uvs if p.uvs is not None else p.positions.new_zeros(n_vert, 2))
        if any_tan:
            tan.append(p.tangents if p.tangents is not None else p.positions.new_zeros(n_vert, 4))
        fmat.append(p.face_material + len(mats))
        mats += p.materials
        offset += n_vert
    cast = torch.cat([p.cast for p in parts])
    receive = torch.cat([p.receive for p in parts])
    return RenderScene(torch.cat(pos), torch.cat(faces), torch.cat(nrm),
                       torch.cat(uvs) if any_uv else None, torch.cat(tan) if any_tan else None,
                       torch.cat(fmat), mats, cast_shadows=None if bool(cast.all()) else cast,
                       receive_shadows=None if bool(receive.all()) else receive)


def _override(mat: Material | None, cfg: RenderFile) -> Material | None:
    """Apply the config's material overrides (in order) to one material."""
    for o in cfg.materials:
        if o.match != "*" and (mat is None or mat.name != o.match):
            continue
        mat = mat if mat is not None else Material()
        changes = {}
        if o.base_color is not None:
            rgba = list(o.base_color) + ([1.0] if len(o.base_color) == 3 else [])
            changes["base_color_factor"] = torch.tensor(rgba)
        if o.metallic is not None:
            changes["metallic_factor"] = o.metallic
        if o.roughness is not None:
            changes["roughness_factor"] = o.roughness
        if o.emissive is not None:
            changes["emissive_factor"] = torch.tensor(o.emissive)
        if o.base_color_texture is not None:
            changes["base_color_texture"] = load_texture(
                cfg.resolve(o.base_color_texture), max_size=cfg.scene.max_texture_size)
        mat = replace(mat, **changes)
    return mat


def build_camera(cam: CameraConfig, positions: torch.Tensor, resolution: tuple[int, int]
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """World -> view and projection matrices ``(1, 4, 4)`` of one camera, framing the
    scene's bounding sphere where distances or planes are left out.

    Args:
        cam: the camera's config.
        positions: ``(V, 3)`` world positions of the scene.
        resolution: ``(H, W)``.
    """
    h, w = resolution
    lo, hi = positions.amin(0), positions.amax(0)
    center = (lo + hi) / 2
    radius = float((positions - center).norm(dim=-1).max().clamp(min=1e-6))
    if cam.look_at is not None:
        view = camera.look_at(cam.look_at.eye, cam.look_at.target, cam.look_at.up)
        distance = float((torch.tensor(cam.look_at.eye) - torch.tensor(cam.look_at.target)).norm())
    else:
        o = cam.orbit
        target = o.target if o.target is not None else center.tolist()
        fov = math.radians(cam.fov_deg)
        distance = o.distance or radius / math.sin(min(fov, fov * w / h) / 2) * 1.05
        view = camera.orbit(o.azimuth_deg, o.elevation_deg, distance, target)
    near = cam.near or max(distance - 2 * radius, distance * 1e-3, 1e-4)
    far = cam.far or math.inf
    if cam.projection == "orthographic":
        half_h = (cam.ortho_height or 2.2 * radius) / 2
        half_w = half_h * w / h
        far = cam.far or distance + 4 * radius
        near = cam.near or max(distance - 4 * radius, 1e-4)
        proj = camera.orthographic(-half_w, half_w, -half_h, half_h, near, far)
    elif cam.intrinsics is not None:
        k = cam.intrinsics
        proj = camera.from_intrinsics(k.fx, k.fy, k.cx, k.cy, w, h, near, far, cam.reverse_z)
    else:
        proj = camera.perspective(cam.fov_deg, w / h, near, far, cam.reverse_z)
    return view, proj


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
    """Load what a config's views share (scene, lights, environment, renderer, post chain)
    once; returns ``render(camera, name) -> ViewResult`` for any concrete camera of it.

    Args:
        cfg: a config of one object (not a mesh set; see :func:`plan_objects`).
        device: where to render.
    """
    scene = build_scene(cfg).to(device)
    res = cfg.render.size
    lights = lights_from_config(cfg.lights, 1, device) if cfg.lights else None
    env = None
    if cfg.environment is not None:
        radiance = read_hdr(cfg.resolve(cfg.environment.path)).to(device)
        env = Environment(radiance, yaw=math.radians(cfg.environment.rotation_deg),
                          intensity=cfg.environment.intensity,
                          specular=cfg.environment.specular,
                          importance_samples=cfg.environment.importance_samples)
    # Without a post section: no tone mapping, sRGB encoding only (the linear image clipped).
    post = build_post_chain(cfg.post) if cfg.post is not None else PostChain(
        encode=EncodeSRGB())
    renderer = build_renderer(cfg, env is not None)
    channels = set(cfg.outputs.channels) - {"color", "radiance", "alpha"}
    if post.dof.enabled:
        channels.add("depth")

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
