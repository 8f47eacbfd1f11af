"""Half-precision renders: float16 / bfloat16 inputs rendered in float32, results cast back.

The policy of :mod:`torchraster.numerics` (evaluate half precision in float32, saturate on
output) applied to a whole :class:`~torchraster.Renderer` call. Each low-precision input
tensor (vertex data, cameras, lights, other frames, material tensors that require grad) is
lifted once with :func:`~torchraster.numerics.to_compute`, the render runs in float32, and
the image, alpha and floating G-buffer channels are cast back to the positions' dtype,
saturated to its finite range.

Why the whole call and not op by op: a gradient can only be saturated where it is cast.
Inside a half-precision graph autograd *accumulates* the gradients of a tensor read by
several passes (positions feed the rasterizer, the normals, the position channel and the
shadow maps) in that tensor's dtype: two saturated float16 gradients sum to Inf, and the
next product with 0 is NaN. Lifted once at the entry, every such sum happens in float32 and
each leaf receives one gradient, saturated once (``scripts/stress.py`` kind ``half``: 3,197
non-finite values and gradients from bright environment maps before, none after).
"""

from __future__ import annotations

import dataclasses

import torch

from .gbuffer import GBuffer
from .material import Material
from .motion import OtherFrame
from .numerics import LOW_PRECISION, finish_low_precision, to_compute
from .scene import RenderScene
from .shading.lights import LIGHT_KINDS, Lights

_VERTEX_FIELDS = ("positions", "normals", "uvs", "tangents", "object_coords")


def _low(t: object) -> bool:
    return isinstance(t, torch.Tensor) and t.dtype in LOW_PRECISION


def lift(t: object) -> object:
    """``t`` in float32 if it is a float16 / bfloat16 tensor (gradient saturated back), else
    ``t``."""
    return to_compute(t) if _low(t) else t


def _light_parts(lights: Lights) -> list[object]:
    return [lights.ambient] + [getattr(part, f.name) for part in (
        getattr(lights, kind) for kind in LIGHT_KINDS) if part is not None
        for f in dataclasses.fields(part) if f.name != "shadow"]


def _material_tensors(m: Material) -> list[torch.Tensor]:
    """Low-precision tensors of ``m`` that autograd tracks (the others are only read by
    lookups that already evaluate in float32, and their cached mip chains stay valid)."""
    return [v for v in (getattr(m, f.name) for f in dataclasses.fields(m))
            if _low(v) and v.requires_grad]


def needs_lift(scene: RenderScene, view: torch.Tensor, proj: torch.Tensor,
               lights: object, frames: dict[str, object]) -> bool:
    """Whether any input of a render is float16 / bfloat16 (see the module docstring)."""
    tensors = [getattr(scene, n) for n in _VERTEX_FIELDS] + [view, proj]
    if isinstance(lights, Lights):
        tensors += _light_parts(lights)
    for f in frames.values():
        if isinstance(f, OtherFrame):
            tensors += [f.positions, f.view, f.proj]
    if any(_low(t) for t in tensors):
        return True
    return any(_material_tensors(m) for m in scene.materials if m is not None)


def lift_scene(scene: RenderScene) -> RenderScene:
    """The scene with low-precision vertex data (and tracked material tensors) in float32;
    each gradient returns saturated to its input's dtype."""
    fields = {n: lift(getattr(scene, n)) for n in _VERTEX_FIELDS}
    mats = [m if m is None or not _material_tensors(m) else dataclasses.replace(m, **{
        f.name: lift(getattr(m, f.name)) for f in dataclasses.fields(m)
        if _low(getattr(m, f.name)) and getattr(m, f.name).requires_grad})
        for m in scene.materials]
    return dataclasses.replace(scene, **fields, materials=mats)


def lift_lights(lights: object) -> object:
    """``lights`` with every low-precision tensor in float32 (other objects unchanged)."""
    if not isinstance(lights, Lights):
        return lights  # None, or a wrong type that forward rejects by name
    parts = {}
    for name in LIGHT_KINDS:
        part = getattr(lights, name)
        if part is not None:
            part = dataclasses.replace(part, **{
                f.name: lift(getattr(part, f.name)) for f in dataclasses.fields(part)
                if f.name != "shadow"})
        parts[name] = part
    return dataclasses.replace(lights, ambient=lift(lights.ambient), **parts)


def lift_frame(frame: object) -> object:
    """An :class:`OtherFrame` with float32 positions and cameras (its depth kept)."""
    if not isinstance(frame, OtherFrame):
        return frame
    return OtherFrame(lift(frame.positions), lift(frame.view), lift(frame.proj), frame.depth)


def finish(image: torch.Tensor, alpha: torch.Tensor, gbuffer: GBuffer, dtype: torch.dtype
           ) -> tuple[torch.Tensor, torch.Tensor, GBuffer]:
    """Image ``(B, 3, H, W)``, alpha ``(B, 1, H, W)`` and the floating G-buffer channels
    cast to ``dtype``, saturated to its finite range (integer channels unchanged)."""
    channels = {ch: finish_low_precision(v, dtype) for ch, v in gbuffer.items()
                if v.is_floating_point()}
    return (finish_low_precision(image, dtype), finish_low_precision(alpha, dtype),
            gbuffer.replace(**channels))


__all__ = ["finish", "lift", "lift_frame", "lift_lights", "lift_scene", "needs_lift"]
