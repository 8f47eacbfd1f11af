"""Camera-relative rendering: far-away worlds rendered in coordinates centred near the camera.

A float32 world coordinate of 1e6 is rounded to 1/16, and ``proj @ view`` applied to it
cancels two numbers of that size into one near the camera: a scene 1e6 from the world
origin renders with vertices jittered by centimetres and, worse, sheared silhouettes and
collapsed shadow cascades (issue 22). The cure of every large-world engine (Unreal's
large world coordinates, Cesium's relative-to-eye rendering): move the world origin to a
point near the camera *before* anything is rounded to the compute precision:

    origin   = the batch's mean eye (float64, from the view matrices)
    position = float64(position) - origin, then cast to the compute dtype
    view     = view @ translate(origin)  (float64 product; same camera, small translation)

and shift everything else that lives in world space alike: point / spot light positions,
the other frames of motion (``OtherFrame``), the fog's ``base_height``; the dissolve's
noise is evaluated at ``relative + (origin mod its period)``, which is the same pattern;
directions (sun, environment, normals) and view-space channels do not move. The
``position`` G-buffer channel is returned in world space (origin added back, in the
compute dtype: float32 world positions far from the origin carry float32's absolute
rounding there; the relative positions used for shading do not).

Precision only improves if the input still holds it: float64 positions (geospatial data,
objects with float64 transforms) render at float32 relative precision; float32 positions
far from the origin are rounded already (a warning names ``positions`` and the rounding),
and camera-relative rendering removes only the cancellation in ``proj @ view``.

Compute dtype (the dtype of the results): the positions' dtype, except float64 positions
with a non-float64 projection, which render in float32 when camera-relative (float64
positions and a float64 projection: a float64 render, the reference path).

``RasterSettings(camera_relative=None)`` decides per call (:func:`plan_shift`): it applies when
float64 positions would render in float32, when the view's dtype differs from the
projection's (a float64 view of a far camera with a float32 projection; without the shift
``proj @ view`` refuses mixed dtypes), or when the farthest eye is more than
:data:`FAR_RATIO` times the largest of the scene's extent, the distance from the eye to the
scene's bounding box and the near plane from the world origin (the float32 error of the
direct path relative to what the camera sees); never otherwise, so a scene near the origin
renders bit-identically.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import warnings
from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch

from .dissolve import PERIOD, Dissolve
from .gbuffer import GBuffer
from .motion import OtherFrame
from .scene import RenderScene
from .shading.lights import LIGHT_KINDS, Lights
from .shading.volumetric import Fog

if TYPE_CHECKING:  # the renderer calls this module; only its types are named here
    from .renderer import Renderer, RenderOutput
    from .shading.ibl import Environment

#: Automatic camera-relative rendering when the farthest eye is further than this many
#: scene extents (or distances from the eye to the scene, or near-plane distances, if
#: larger) from the world origin.
FAR_RATIO: float = 256.0
#: Warn about low-precision positions whose rounding exceeds this fraction of the extent,
#: when their largest coordinate is more than FAR_WARN extents from the origin (a scene
#: far away, not one in half precision near the origin).
ROUNDING_WARN: float = 1e-4
FAR_WARN: float = 16.0
#: Coordinates (world units) beyond which the config layer keeps world positions and cameras
#: in float64 (float32 rounds 1024 to 6e-5; 1e6 to 0.03).
FAR_COORDINATE: float = 1024.0


@dataclass(frozen=True)
class Shift:
    """A camera-relative frame: world = relative + ``origin``.

    Attributes:
        origin: ``(3,)`` float64 world point near the cameras.
        dtype: the compute dtype the relative positions are cast to.
    """

    origin: torch.Tensor
    dtype: torch.dtype


def eyes(view: torch.Tensor) -> torch.Tensor:
    """Float64 eye positions ``(B, 3)`` of world -> view matrices ``(B, 4, 4)``
    (``-R^T t``)."""
    v = view.detach().to(torch.float64)
    return -(v[:, :3, :3].transpose(1, 2) @ v[:, :3, 3:]).squeeze(-1)


def _near(proj: torch.Tensor) -> float:
    """The smallest near-plane distance of OpenGL perspective projections ``(B, 4, 4)``
    (``P[2, 3] / (P[2, 2] - 1)``), 0 for orthographic ones."""
    p = proj.detach().to(torch.float64)
    persp = p[:, 3, 2] != 0
    if not bool(persp.any()):
        return 0.0
    near = (p[:, 2, 3] / (p[:, 2, 2] - 1)).abs()[persp]
    near = near[torch.isfinite(near)]  # a projection without a near plane: none
    return float(near.min()) if near.numel() else 0.0


def compute_dtype(positions: torch.Tensor, proj: torch.Tensor) -> torch.dtype:
    """The dtype a camera-relative render computes in (module docstring)."""
    if positions.dtype == torch.float64 and proj.dtype != torch.float64:
        return torch.promote_types(proj.dtype, torch.float32)
    return positions.dtype


def plan_shift(mode: bool | None, positions: torch.Tensor, view: torch.Tensor,
               proj: torch.Tensor) -> Shift | None:
    """Whether (and how) to render camera-relative.

    Args:
        mode: ``RasterSettings(camera_relative=...)``: True, False or None (automatic, module
            docstring).
        positions: ``(B, V, 3)`` or ``(V, 3)`` world positions of the scene.
        view: ``(B, 4, 4)`` world -> view; proj: ``(B, 4, 4)``.

    Returns:
        The :class:`Shift`, or None to render as given. Warns (UserWarning naming
        ``positions``) when low-precision positions are rounded by more than
        :data:`ROUNDING_WARN` of the scene's size (the largest of its extent, the distance
        from the eyes to it and the near plane) and lie more than :data:`FAR_WARN` sizes
        from the origin.
    """
    if mode is False:
        return None
    dtype = compute_dtype(positions, proj)
    with torch.no_grad():
        eye = eyes(view)
        p = positions.detach().reshape(-1, 3)
        origin = eye.mean(0)
        if p.shape[0]:
            lo, hi = p.amin(0).to(torch.float64), p.amax(0).to(torch.float64)
            extent = float((hi - lo).norm())
            big = float(torch.maximum(lo.abs(), hi.abs()).max())
            gap = float((torch.minimum(torch.maximum(origin, lo), hi) - origin).norm())
        else:
            extent = big = gap = 0.0
        reach = float(eye.abs().max())
    # the size that matters: the scene's extent, or what the camera sees of it
    scale = max(extent, gap, _near(proj), 1e-30)
    if positions.dtype != torch.float64 and big > FAR_WARN * scale:  # far, not just coarse
        rounding = 0.5 * _spacing(big, positions.dtype)
        if rounding > ROUNDING_WARN * scale:
            warnings.warn(
                f"positions: {positions.dtype} world coordinates up to {big:.3g} are rounded "
                f"to +-{rounding:.2g} ({rounding / scale:.2%} of the scene's size "
                f"{scale:.3g}); camera-relative rendering cannot restore it: pass "
                "float64 positions (and OtherFrame positions) for scenes far from the origin",
                UserWarning, stacklevel=5)  # the caller of Renderer(...)(...)
    if mode is None:
        far = reach > FAR_RATIO * scale
        if not (far or dtype != positions.dtype or view.dtype != proj.dtype):
            return None
    return Shift(origin=origin, dtype=dtype)


def _spacing(x: float, dtype: torch.dtype) -> float:
    """Distance between consecutive floats of ``dtype`` at magnitude ``x``."""
    info = torch.finfo(dtype)
    return info.eps * 2.0 ** math.floor(math.log2(max(x, info.tiny)))


def _points(p: torch.Tensor, shift: Shift, dtype: torch.dtype) -> torch.Tensor:
    """``p - origin`` in float64, cast to ``dtype`` (differentiable in ``p``)."""
    return (p.to(torch.float64) - shift.origin.to(p.device)).to(dtype)


def _translated(m: torch.Tensor, shift: Shift, dtype: torch.dtype) -> torch.Tensor:
    """``m @ translate(origin)`` ``(B, 4, 4)`` in float64, cast to ``dtype``."""
    t = torch.eye(4, dtype=torch.float64, device=m.device)
    t[:3, 3] = shift.origin.to(m.device)
    return (m.to(torch.float64) @ t).to(dtype)


def shift_scene(scene: RenderScene, shift: Shift) -> RenderScene:
    """The scene with relative positions; float64 vertex data (normals, uvs, tangents, NOCS)
    cast to the compute dtype when it is narrower."""
    fields = {"positions": _points(scene.positions, shift, shift.dtype)}
    if shift.dtype != torch.float64:
        for name in ("normals", "uvs", "tangents", "object_coords"):
            t = getattr(scene, name)
            if t is not None and t.dtype == torch.float64:
                fields[name] = t.to(shift.dtype)
    return dataclasses.replace(scene, **fields)


def shift_view(view: torch.Tensor, proj: torch.Tensor, shift: Shift) -> torch.Tensor:
    """``view @ translate(origin)`` ``(B, 4, 4)`` in ``proj``'s dtype (the same camera)."""
    return _translated(view, shift, proj.dtype)


def shift_lights(lights: Lights | None, shift: Shift) -> Lights | None:
    """Point / spot / area light positions made relative (float64 lights cast to the compute
    dtype when it is narrower); directions and ambient light do not move."""
    if not isinstance(lights, Lights):
        return lights  # None, or a wrong type that forward rejects by name
    parts = {}
    for name in ("point", "spot", "area"):
        part = getattr(lights, name)
        if part is not None:
            dt = part.position.dtype
            dt = shift.dtype if dt == torch.float64 and shift.dtype != dt else dt
            part = dataclasses.replace(part, position=_points(part.position, shift, dt))
        parts[name] = part
    out = dataclasses.replace(lights, **parts)
    if shift.dtype != torch.float64 and _has_float64(out):
        out = out.to(dtype=shift.dtype)
    return out


def _has_float64(lights: Lights) -> bool:
    """Whether any tensor of ``lights`` is float64."""
    tensors = [lights.ambient]
    for part in (getattr(lights, kind) for kind in LIGHT_KINDS):
        if part is not None:
            tensors += [getattr(part, f.name) for f in dataclasses.fields(part)]
    return any(isinstance(t, torch.Tensor) and t.dtype == torch.float64 for t in tensors)


def shift_frame(frame: OtherFrame | None, shift: Shift) -> OtherFrame | None:
    """The other frame in the same relative coordinates (its depth, view-space, kept)."""
    if not isinstance(frame, OtherFrame):
        return frame  # None, or a wrong type that forward rejects by name
    dt = frame.positions.dtype
    dt = shift.dtype if dt == torch.float64 and shift.dtype != dt else dt
    view = frame.view if frame.view.dim() == 3 else frame.view[None]
    return OtherFrame(_points(frame.positions, shift, dt), _translated(view, shift,
                                                                       frame.proj.dtype),
                      frame.proj, frame.depth)


def shift_fog(fog: Fog | None, shift: Shift) -> Fog | None:
    """The fog with ``base_height`` relative to the origin's height."""
    if fog is None:
        return None
    y = float(shift.origin[1])
    base = fog.base_height
    base = base.to(torch.float64) - y if isinstance(base, torch.Tensor) else float(base) - y
    return dataclasses.replace(fog, base_height=base)


@dataclass(frozen=True, eq=False)
class _ShiftedDissolve(Dissolve):
    """A :class:`Dissolve` whose noise is evaluated at ``relative + offset``: with
    ``offset = origin mod the noise period`` the pattern of the world positions."""

    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def noise(self, position: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        off = torch.tensor(self.offset, dtype=position.dtype, device=position.device)
        return super().noise(position + off.view(1, 3, 1, 1), mask)


def shift_dissolve(dissolve: Dissolve | None, shift: Shift) -> Dissolve | None:
    """The dissolve of the same world pattern in relative coordinates: the value noise
    repeats every ``PERIOD / scale`` world units (every octave's lattice too), so the
    origin enters modulo that period."""
    if dissolve is None:
        return None
    period = PERIOD / dissolve.scale
    o = shift.origin
    offset = tuple(float(v) for v in o - period * torch.floor(o / period))
    fields = {f.name: getattr(dissolve, f.name) for f in dataclasses.fields(Dissolve)}
    return _ShiftedDissolve(**fields, offset=offset)


def world_position(outputs: GBuffer, mask: torch.Tensor, origin: torch.Tensor) -> GBuffer:
    """The output G-buffer with its ``position`` channel ``(B, 3, H, W)`` back in world
    space: ``relative + origin`` where covered (``mask`` ``(B, 1, H, W)``), 0 elsewhere."""
    if outputs.position is None:
        return outputs
    o = origin.to(device=outputs.position.device, dtype=outputs.position.dtype)
    return outputs.replace(position=outputs.position + o.view(1, 3, 1, 1) * mask.to(o.dtype))


def render(renderer: Renderer, shift: Shift, scene: RenderScene, view: torch.Tensor,
           proj: torch.Tensor, lights: Lights | None, environment: Environment | None,
           channels: Iterable[str], next_frame: OtherFrame | None,
           previous_frame: OtherFrame | None) -> RenderOutput:
    """``renderer.forward`` of the shifted inputs (view and proj ``(B, 4, 4)``, checked by
    the caller), run by a shallow copy of ``renderer`` that shares its modules and caches,
    with the fog and dissolve shifted and the origin recorded for the ``position`` channel
    and in ``out.plan.origin``; other frames' rasterized depths are stored back on the
    caller's frames."""
    inner = copy.copy(renderer)
    inner.raster_settings = replace(renderer.raster_settings, camera_relative=False)
    inner.world_origin = shift.origin
    inner.fog = shift_fog(renderer.fog, shift)
    inner.dissolve = shift_dissolve(renderer.dissolve, shift)
    frames = {"next_frame": next_frame, "previous_frame": previous_frame}
    moved = {k: shift_frame(f, shift) for k, f in frames.items()}
    out = inner.forward(shift_scene(scene, shift), shift_view(view, proj, shift), proj,
                        shift_lights(lights, shift), environment, channels, **moved)
    for k, f in frames.items():
        if isinstance(f, OtherFrame) and f.depth is None:
            f.depth = moved[k].depth
    out.plan = dataclasses.replace(out.plan, origin=tuple(float(v) for v in shift.origin))
    return out


__all__ = ["FAR_COORDINATE", "FAR_RATIO", "FAR_WARN", "ROUNDING_WARN", "Shift", "compute_dtype",
           "eyes", "plan_shift", "render", "shift_dissolve", "shift_fog", "shift_frame",
           "shift_lights", "shift_scene", "shift_view", "world_position"]
