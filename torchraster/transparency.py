"""glTF alpha modes over depth layers: ``MASK`` (alpha cut-outs) and ``BLEND`` (front-to-back
"over" compositing).

The renderer rasterizes K depth layers (``rasterize(..., layers=K)``, nearest first) when a
scene has a material whose ``alpha_mode`` is not ``OPAQUE``, computes a G-buffer per layer,
and turns each layer's material alpha into a *layer opacity* ``a_k``:

* ``OPAQUE``: 1 where the layer is covered;
* ``MASK``: 1 where ``alpha >= alpha_cutoff``, else 0 (the pixel shows the next layer);
* ``BLEND``: ``alpha`` (base-colour factor alpha x texture alpha), differentiable.

``a_k`` is 0 where the layer is empty. Front-to-back compositing (Porter & Duff 1984,
"over") then gives ``C = sum_k T_k a_k c_k`` with transmittance ``T_0 = 1``,
``T_{k+1} = T_k (1 - a_k)``; what lies behind the K-th layer is not seen (the documented
limit: K = ``RasterSettings(alpha_layers=...)``), and ``T_K`` weights the background. With only
``MASK`` materials every ``a_k`` is 0 or 1, so this equals shading the first layer with
``a_k = 1``: :func:`first_opaque` selects it and one shading pass suffices.
"""

from __future__ import annotations

import torch

from .gbuffer import GBuffer
from .material import Material

OPAQUE, MASK, BLEND = 0, 1, 2
_CODES = {"OPAQUE": OPAQUE, "MASK": MASK, "BLEND": BLEND}


def face_alpha_modes(materials: list[Material | None], face_material: torch.Tensor | None,
                     n_faces: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-face alpha mode code ``(F,)`` int64 (:data:`OPAQUE`, :data:`MASK`,
    :data:`BLEND`) and cut-off ``(F,)`` float32, from the faces' materials (no material:
    opaque)."""
    codes = torch.tensor([_CODES[m.alpha_mode] if m is not None else OPAQUE
                          for m in materials] or [OPAQUE], device=device)
    cutoffs = torch.tensor([m.alpha_cutoff if m is not None else 0.5 for m in materials]
                           or [0.5], device=device)
    index = (face_material.to(device) if face_material is not None
             else torch.zeros(n_faces, dtype=torch.int64, device=device))
    return codes.index_select(0, index), cutoffs.index_select(0, index)


def layer_opacity(gb: GBuffer, face_id: torch.Tensor, modes: torch.Tensor,
                  cutoffs: torch.Tensor) -> torch.Tensor:
    """Opacity ``a`` ``(B, 1, H, W)`` of one layer (see the module docstring).

    Args:
        gb: the layer's G-buffer with ``alpha`` (material alpha) and ``mask``.
        face_id: ``(B, H, W)`` the layer's face ids (-1 = empty).
        modes, cutoffs: ``(F,)`` from :func:`face_alpha_modes`.
    """
    fid = face_id.clamp_min(0).unsqueeze(1)
    mode = modes[fid]
    alpha = gb.alpha.clamp(0, 1)
    cut = (alpha >= cutoffs[fid].to(alpha.dtype)).to(alpha.dtype)
    a = torch.where(mode == OPAQUE, torch.ones_like(alpha),
                    torch.where(mode == MASK, cut, alpha))
    return torch.where(face_id.unsqueeze(1) >= 0, a, torch.zeros_like(a))


def first_opaque(opacities: list[torch.Tensor]) -> torch.Tensor:
    """Index ``(B, 1, H, W)`` int64 of the first layer with opacity > 0 (the last layer
    where none has)."""
    stacked = torch.stack(opacities) > 0  # (K, B, 1, H, W)
    k = stacked.shape[0]
    order = torch.arange(k, device=stacked.device).view(k, 1, 1, 1, 1)
    return torch.where(stacked, order, k - 1).amin(0)


def select_layers(layers: list[GBuffer], index: torch.Tensor) -> GBuffer:
    """Per pixel, the channels of layer ``index`` ``(B, 1, H, W)`` (differentiable)."""
    out = {}
    for name, first in layers[0].as_dict().items():
        stacked = torch.stack([getattr(g, name) for g in layers])  # (K, B, C, H, W)
        idx = index.unsqueeze(0).expand(1, *first.shape)
        out[name] = torch.gather(stacked, 0, idx)[0]
    return GBuffer(**out)


def composite_over(colors: list[torch.Tensor], opacities: list[torch.Tensor], *,
                   like: tuple[torch.Tensor, torch.Tensor] | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Front-to-back "over": ``(sum_k T_k a_k c_k, T_K)``, each ``(B, C, H, W)`` /
    ``(B, 1, H, W)``; ``colors[k]`` is the shaded radiance of layer k.

    With no layer (nothing opaque in view: an empty frame, or alpha 0 everywhere) the
    result is no radiance and full transmittance, shaped like ``like`` = ``(a colour
    (B, C, H, W), an opacity (B, 1, H, W))`` (e.g. the first layer's, unshaded).
    """
    if len(colors) != len(opacities):
        raise ValueError(f"colors, opacities: expected one colour per opacity, got "
                         f"{len(colors)} and {len(opacities)}")
    if not colors:
        if like is None:
            raise ValueError("colors: empty (no layer to composite); pass like=(colour, "
                             "opacity) tensors to get the empty result's shape")
        return torch.zeros_like(like[0]), torch.ones_like(like[1])
    total = torch.zeros_like(colors[0])
    transmittance = torch.ones_like(opacities[0])
    for color, a in zip(colors, opacities, strict=True):
        total = total + transmittance * a * color
        transmittance = transmittance * (1 - a)
    return total, transmittance


__all__ = ["BLEND", "MASK", "OPAQUE", "composite_over", "face_alpha_modes", "first_opaque",
           "layer_opacity", "select_layers"]
