"""Energy of the Cook-Torrance BRDF: multiple-scattering compensation of the specular lobe
and the diffuse / specular split, one convention for every light type.

A single-scattering GGX lobe loses the energy of light that bounces more than once between
microfacets: a rough metal is too dark (a white metal at roughness 1 reflects 31 % of the
light at normal incidence, 45 % at n.v = 0.5; tests/test_energy.py checks the table against
Monte Carlo). Following Kulla & Conty 2017 ("Revisiting Physically Based
Shading at Imageworks"), in the cheap form of Fdez-Agüera 2019 ("A Multiple-Scattering
Microfacet Model for Real-Time Image-Based Lighting") used by Filament (section 5.3.4.7),
the specular lobe is scaled by

    spec_scale = 1 + f0 (1 / E_ss(n.v, r) - 1)

where ``E_ss = A + B`` is the single-scattering directional albedo for f0 = 1 (the split-sum
DFG table of :func:`torchraster.shading.ibl.dfg_lut`), so a white metal (f0 = 1) reflects
all light. The diffuse term then gets what the specular does not reflect (Fdez-Agüera's
``kD = 1 - E_spec``)::

    E_spec        = (f0 A + f90 B) * spec_scale        # specular directional albedo at n.v
    diffuse_scale = 1 - E_spec

so a white dielectric (albedo 1) reflects all light as well. The convention is the same for
punctual, ambient and image-based light (it depends on the view only, like the split-sum
terms; it is not reciprocal, as in Filament and Unreal). With ``multiscatter=False`` no
term is applied: the textbook single-scattering BRDF of
:func:`torchraster.shading.brdf.cook_torrance` (Lambert + GGX: a white dielectric reflects up to
14 % more than it receives, a rough white metal less than half; docs/benchmarks.md,
section energy).
"""

from __future__ import annotations

import torch

from torchraster.numerics import compute_dtype, finish_low_precision, grid_sample

__all__ = ["DFG_LUT_SAMPLES", "DFG_LUT_SIZE", "MIN_DFG_ALBEDO", "dfg_terms",
           "energy_terms"]

#: Floor on the directional albedo A + B in the energy compensation ``1 / (A + B)``. The
#: smallest value in the table is ~0.4 (rough, grazing), so this only guards hostile LUTs.
MIN_DFG_ALBEDO: float = 1e-4

#: Size and samples of the split-sum DFG table (``ibl.dfg_lut``) the lighting pass reads for
#: the energy terms of punctual and ambient light and the ambient specular. Finer than
#: ``shade_ibl``'s 16 x 32 (``ibl.IBL_LUT_SIZE``): the ambient specular has no
#: prefiltered-map error to hide the table's, and 32 x 96 brings its mean error from 0.58 %
#: to 0.13 % (docs/benchmarks.md, "DFG LUT").
DFG_LUT_SIZE: int = 32
DFG_LUT_SAMPLES: int = 96


def dfg_terms(
    lut: torch.Tensor, n_dot_v: torch.Tensor, roughness: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear lookup of the DFG table at any broadcastable shape.

    Args:
        lut: ``(2, S, S)`` table of :func:`~torchraster.shading.ibl.dfg_lut` (rows =
            roughness, columns = n.v, both 0..1 with nodes at the ends).
        n_dot_v: cosines, any shape; clamped to [0, 1].
        roughness: perceptual roughness, broadcastable with ``n_dot_v``; clamped to [0, 1].

    Returns:
        ``(A, B)``: the f0 scale and bias of the split-sum table, each the broadcast shape.
        Differentiable in both inputs.
    """
    nv, rough = torch.broadcast_tensors(n_dot_v, roughness)
    shape = nv.shape
    grid = torch.stack((nv.reshape(-1).clamp(0.0, 1.0) * 2.0 - 1.0,
                        rough.reshape(-1).clamp(0.0, 1.0) * 2.0 - 1.0), -1)
    ab = grid_sample(lut.to(compute_dtype(nv))[None], grid.view(1, 1, -1, 2), mode="bilinear",
                     padding_mode="border", align_corners=True)  # (1, 2, 1, N), float32 for half
    ab = finish_low_precision(ab, nv.dtype)
    return ab[0, 0, 0].view(shape), ab[0, 1, 0].view(shape)


def energy_terms(
    f0: torch.Tensor,
    n_dot_v: torch.Tensor,
    roughness: torch.Tensor,
    lut: torch.Tensor,
    f90: float | torch.Tensor = 1.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Multiple-scattering specular scale and diffuse scale (see the module docstring).

    Args:
        f0: specular colour at normal incidence, e.g. ``(B, 3, H, W)`` or ``(3, M)``.
        n_dot_v: cosine of the view angle, e.g. ``(B, 1, H, W)`` or ``(1, M)``
            (broadcastable with ``f0``); use the same floor as the lobe it scales.
        roughness: perceptual roughness, broadcastable like ``n_dot_v``.
        lut: the ``(2, S, S)`` DFG table of :func:`torchraster.shading.ibl.dfg_lut`.
        f90: Schlick reflectance at grazing incidence (1 for the punctual BRDF).

    Returns:
        ``(spec_scale, diffuse_scale)`` in the broadcast shape of ``f0`` and ``n_dot_v``:
        multiply the single-scattering specular radiance by the first and the Lambert
        diffuse by the second. ``spec_scale >= 1``, ``diffuse_scale`` in [0, 1].
    """
    a, b = dfg_terms(lut, n_dot_v, roughness)
    spec_scale = 1.0 + f0 * (1.0 / (a + b).clamp_min(MIN_DFG_ALBEDO) - 1.0)
    e_spec = (f0 * a + f90 * b) * spec_scale
    return spec_scale, (1.0 - e_spec).clamp_min(0.0)
