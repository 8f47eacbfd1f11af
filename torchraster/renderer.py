"""The renderer module: plans the passes a scene needs, runs only those, and returns images,
G-buffer channels and the plan it ran.

    scene = tr.RenderScene.from_mesh(tr.io.load_spot())
    renderer = tr.Renderer((512, 512), shading="pbr")
    out = renderer(scene, view, proj, lights=lights, environment=env)
    out.image  # (B, 3, H, W) linear HDR radiance;  out.alpha (B, 1, H, W);  out.plan

Passes: rasterize -> geometry (G-buffer channels that shading or the caller read) ->
lighting (only the light types present; image-based lighting only with an environment) ->
background. Shading models: ``"pbr"`` (Cook-Torrance with the given lights / environment),
``"headlight"`` (Lambert lit from the camera, E = pi, so a white surface facing the camera
is 1.0; needs no lights), ``"unlit"`` (albedo + emissive). Post-processing is a separate
``torchraster.post.PostChain`` applied by the caller (the CLI does).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from ._validate import check_resolution, check_tensor
from .gbuffer import CHANNELS, _normalize, check_channels, geometry_pass
from .material import Material
from .mesh import Mesh, transform_points, vertex_normals
from .raster import rasterize
from .shading.ibl import Environment, shade_ibl
from .shading.lighting import shade
from .shading.lights import Lights

log = logging.getLogger("torchraster")

SHADING = ("pbr", "headlight", "unlit")
_SHADING_NEEDS = {
    "pbr": {"position", "normal", "albedo", "metallic", "roughness", "ao", "emissive", "mask"},
    "headlight": {"position", "normal", "albedo", "mask"},
    "unlit": {"albedo", "emissive", "mask"},
}


@dataclass
class RenderScene:
    """Scene tensors. positions (B, V, 3) or (V, 3) world space; faces (F, 3) int64;
    normals like positions (None: smooth normals are computed); uvs (V, 2) or (B, V, 2);
    tangents (V, 4) or (B, V, 4); face_material (F,) int64 into ``materials``."""

    positions: torch.Tensor
    faces: torch.Tensor
    normals: torch.Tensor | None = None
    uvs: torch.Tensor | None = None
    tangents: torch.Tensor | None = None
    face_material: torch.Tensor | None = None
    materials: list[Material | None] = field(default_factory=list)

    @classmethod
    def from_mesh(cls, mesh: Mesh, face_material: torch.Tensor | None = None,
                  materials: Sequence[Material | None] | None = None) -> RenderScene:
        """From a :class:`~torchraster.mesh.Mesh` (e.g. ``io.load_mesh`` or ``Scene.flatten``)."""
        mats = list(materials) if materials is not None else [mesh.material]
        return cls(mesh.positions, mesh.faces, mesh.normals, mesh.uvs, mesh.tangents,
                   face_material, mats)


@dataclass
class RenderOutput:
    """image (B, 3, H, W) linear radiance incl. background; alpha (B, 1, H, W) coverage;
    gbuffer {channel: (B, C, H, W)} for the requested channels; plan: the passes that ran."""

    image: torch.Tensor
    alpha: torch.Tensor
    gbuffer: dict[str, torch.Tensor]
    plan: list[str]


def camera_position(view: torch.Tensor) -> torch.Tensor:
    """Eye positions (B, 3) of world -> view matrices (B, 4, 4): -R^T t."""
    rot, t = view[:, :3, :3], view[:, :3, 3:]
    return -(rot.transpose(1, 2) @ t).squeeze(-1)


def view_rays(view: torch.Tensor, proj: torch.Tensor, resolution: tuple[int, int]) -> torch.Tensor:
    """Unit world-space directions (B, 3, H, W) from the eye through each pixel centre."""
    h, w = resolution
    dtype, device = proj.dtype, proj.device
    xs = (2 * torch.arange(w, dtype=dtype, device=device) + 1) / w - 1
    ys = 1 - (2 * torch.arange(h, dtype=dtype, device=device) + 1) / h
    y, x = torch.meshgrid(ys, xs, indexing="ij")
    inv = torch.linalg.inv(proj.to(torch.float64)).to(dtype)  # (B, 4, 4)

    def unproject(z: float) -> torch.Tensor:
        p = torch.stack([x, y, torch.full_like(x, z), torch.ones_like(x)]).view(4, -1)
        q = inv @ p  # (B, 4, HW)
        return q[:, :3] / q[:, 3:]

    d = unproject(-0.5) - unproject(-1.0)  # view space, both points in front of the eye
    d = view[:, :3, :3].transpose(1, 2).to(dtype) @ d
    return _normalize(d.view(-1, 3, h, w), dim=1)


class Renderer(nn.Module):
    """Differentiable deferred renderer (see the module docstring).

    resolution: (H, W). shading: "pbr" | "headlight" | "unlit". supersample: render at
    s x the resolution and box-filter down (anti-aliasing). background: RGB for empty
    pixels (replaced by the environment when ``environment_background``).
    texture_filter: "trilinear" | "bilinear" | "nearest".
    ssao: an enabled ``torchraster.post.SSAO`` module: its AO (from depth and view-space
    normals) multiplies the material AO before lighting ("pbr" shading only).
    """

    def __init__(
        self,
        resolution: tuple[int, int] | int,
        *,
        shading: str = "pbr",
        supersample: int = 1,
        cull_backfaces: bool = False,
        background: Sequence[float] = (0.0, 0.0, 0.0),
        environment_background: bool = True,
        texture_filter: str = "trilinear",
        ssao: nn.Module | None = None,
    ) -> None:
        super().__init__()
        self.resolution = check_resolution(resolution)
        if shading not in SHADING:
            raise ValueError(f"shading: expected one of {SHADING}, got {shading!r}")
        if int(supersample) < 1:
            raise ValueError(f"supersample: expected an int >= 1, got {supersample}")
        if texture_filter not in ("trilinear", "bilinear", "nearest"):
            raise ValueError(f"texture_filter: expected trilinear|bilinear|nearest, got "
                             f"{texture_filter!r}")
        self.shading = shading
        self.supersample = int(supersample)
        self.cull_backfaces = cull_backfaces
        self.register_buffer("background", torch.tensor(list(background), dtype=torch.float32),
                             persistent=False)
        self.environment_background = environment_background
        self.texture_filter = texture_filter
        self.ssao = ssao if ssao is not None and getattr(ssao, "enabled", True) else None
        self._texture_cache: dict = {}

    def plan(self, scene: RenderScene, lights: Lights | None, environment: Environment | None,
             channels: Iterable[str] = ()) -> tuple[list[str], set[str]]:
        """The passes this call will run, and the G-buffer channels it computes."""
        channels = check_channels(channels)
        needed = set(channels) | _SHADING_NEEDS[self.shading] | {"mask"}
        if self.shading == "pbr" and lights is None and environment is None:
            needed = set(channels) | {"albedo", "emissive", "mask"}
        if self.ssao is not None and self.shading == "pbr" and (
                lights is not None or environment is not None):
            needed |= {"depth"}
        passes = [f"rasterize {self.resolution[0] * self.supersample}x"
                  f"{self.resolution[1] * self.supersample}"]
        passes.append("gbuffer " + ",".join(sorted(needed)))
        if self.shading == "pbr":
            if lights is not None:
                for kind in ("ambient", "directional", "point", "spot"):
                    group = getattr(lights, kind, None)
                    if group is not None:
                        count = getattr(group, "count", None)
                        passes.append(f"light {kind}" + (f" x{count}" if count else ""))
            if "depth" in needed and self.ssao is not None:
                passes.append("ssao")
            if environment is not None:
                passes.append("ibl")
            if lights is None and environment is None:
                passes.append("unlit (no lights, no environment)")
        else:
            passes.append(self.shading)
        if environment is not None and self.environment_background:
            passes.append("background environment")
        elif bool((self.background != 0).any()):
            passes.append("background colour")
        if self.supersample > 1:
            passes.append(f"downsample {self.supersample}x")
        return passes, needed

    def forward(
        self,
        scene: RenderScene,
        view: torch.Tensor,
        proj: torch.Tensor,
        lights: Lights | None = None,
        environment: Environment | None = None,
        channels: Iterable[str] = (),
    ) -> RenderOutput:
        """Render. view, proj: (B, 4, 4) (or (4, 4)); scene positions (V, 3) or (B, V, 3).

        channels: extra G-buffer channels to return (see ``torchraster.gbuffer.CHANNELS``).
        """
        if not isinstance(scene, RenderScene):
            raise TypeError(f"scene: expected a RenderScene, got {type(scene).__name__}")
        view = view.unsqueeze(0) if view.dim() == 2 else view
        proj = proj.unsqueeze(0) if proj.dim() == 2 else proj
        check_tensor("view", view, ("B", 4, 4), floating=True, finite=True)
        check_tensor("proj", proj, ("B", 4, 4), floating=True, finite=True)
        requested = check_channels(channels)
        plan, needed = self.plan(scene, lights, environment, requested)
        log.info("torchraster plan: %s", "; ".join(plan))

        positions = scene.positions
        b = max(view.shape[0], proj.shape[0], positions.shape[0] if positions.dim() == 3 else 1)
        view, proj = view.expand(b, 4, 4), proj.expand(b, 4, 4)
        res = (self.resolution[0] * self.supersample, self.resolution[1] * self.supersample)
        clip = transform_points(positions, (proj @ view).to(positions.dtype))
        if clip.shape[0] != b:
            clip = clip.expand(b, -1, -1)
        textured = any(m is not None and any(getattr(m, s) is not None for s in (
            "base_color_texture", "metallic_roughness_texture", "normal_texture",
            "occlusion_texture", "emissive_texture")) for m in scene.materials)
        frags = rasterize(clip, scene.faces, res, cull_backfaces=self.cull_backfaces,
                          derivatives=textured and self.texture_filter == "trilinear")
        normals = scene.normals
        if "normal" in needed and normals is None:
            normals = vertex_normals(positions, scene.faces)
        gb = geometry_pass(frags, needed, positions, view, normals, scene.uvs, scene.tangents,
                           scene.face_material, scene.materials, self.texture_filter,
                           self._texture_cache)
        mask = gb["mask"]
        eye = camera_position(view.to(positions.dtype))
        if self.shading == "headlight":
            to_eye = _normalize(eye[:, :, None, None] - gb["position"], dim=1)
            cos = (gb["normal"] * to_eye).sum(1, keepdim=True).clamp(min=0)
            radiance = gb["albedo"] * cos
        elif self.shading == "unlit" or (lights is None and environment is None):
            radiance = gb["albedo"] + gb["emissive"]
        else:
            ibl = None
            if environment is not None:
                def ibl(n, v, a, m, r):
                    return shade_ibl(n, v, a, m, r, None, environment)
            if lights is None:
                lights = Lights()
            if self.ssao is not None:
                normal_view = torch.einsum("bij,bjhw->bihw", view[:, :3, :3].to(
                    gb["normal"].dtype), gb["normal"])
                depth = torch.where(mask > 0, gb["depth"], torch.zeros_like(gb["depth"]))
                gb["ao"] = gb["ao"] * self.ssao(depth, normal_view, projection=proj.to(
                    depth.dtype))
            radiance = shade(gb["position"], gb["normal"], gb["albedo"], gb["metallic"],
                             gb["roughness"], gb["ao"], gb["emissive"], mask, eye, lights,
                             ibl=ibl)
        radiance = radiance * mask
        if environment is not None and self.environment_background:
            rays = view_rays(view, proj, res).to(radiance.dtype)
            background = environment.background(rays)
        else:
            background = self.background.to(radiance).view(1, 3, 1, 1)
        image = radiance + (1 - mask) * background
        alpha = mask * gb["alpha"] if "alpha" in gb else mask
        outputs = {ch: gb[ch] for ch in requested}
        if self.supersample > 1:
            s = self.supersample
            image, alpha = F.avg_pool2d(image, s), F.avg_pool2d(alpha, s)
            outputs = {k: (v[:, :, ::s, ::s] if not v.is_floating_point()
                           else F.avg_pool2d(v, s)) for k, v in outputs.items()}
        return RenderOutput(image=image, alpha=alpha, gbuffer=outputs, plan=plan)


__all__ = ["CHANNELS", "RenderOutput", "RenderScene", "Renderer", "camera_position",
           "view_rays"]
