"""The surface a shading step reads: material inputs (:class:`Surface`) and, for the lighting
pass, the per-pixel values every light needs, built once per frame (:class:`PixelSurface`,
Filament's ``PixelParams``: "Physically Based Rendering in Filament", section 4.4).

The lighting pass builds one :class:`PixelSurface` from the G-buffer and hands it by name to
the stylised shading models (which read ``albedo``, ``metallic``, ``roughness``), the ambient
light and the image-based-lighting hook, so the f0 / diffuse colour / energy terms are
computed once, and no step can take metallic for roughness by position.

Example:
    >>> one = torch.ones(1, 1, 1, 1)
    >>> s = pixel_surface(torch.tensor([0.0, 0, 1]).view(1, 3, 1, 1),
    ...                   torch.tensor([0.0, 0.6, 0.8]).view(1, 3, 1, 1),
    ...                   albedo=0.5 * torch.ones(1, 3, 1, 1), metallic=0 * one,
    ...                   roughness=one)
    >>> s.n_dot_v.flatten(), s.f0.flatten(), s.diffuse.flatten()
    (tensor([0.8000]), tensor([0.0400, 0.0400, 0.0400]), tensor([0.5000, 0.5000, 0.5000]))
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from torchraster.numerics import diffuse_color, dot, specular_f0
from torchraster.shading.brdf import MIN_COS, MIN_ROUGHNESS
from torchraster.shading.energy import energy_terms


@dataclass(frozen=True)
class Surface:
    """Per-pixel material inputs of a shading model (metallic-roughness, glTF semantics).

    Attributes:
        albedo: base colour, linear RGB in [0, 1], ``(..., 3, H, W)``.
        metallic: in [0, 1], ``(..., 1, H, W)``.
        roughness: perceptual roughness in [0, 1], ``(..., 1, H, W)``.
    """

    albedo: torch.Tensor
    metallic: torch.Tensor
    roughness: torch.Tensor


@dataclass(frozen=True)
class PixelSurface(Surface):
    """A :class:`Surface` with the view-dependent values of the lighting pass (make one with
    :func:`pixel_surface`). Every field is ``(B, C, H, W)``; the Schlick ``f90`` is 1.

    Attributes:
        n: unit shading normal (0 where the pixel has none), C = 3.
        v: unit direction from the surface to the eye, C = 3.
        n_dot_v: ``dot(n, v)`` (not clamped), C = 1.
        f0: specular reflectance at normal incidence, ``mix(0.04, albedo, metallic)``, C = 3.
        diffuse: Lambert colour ``(1 - metallic) * albedo``, C = 3.
    """

    n: torch.Tensor
    v: torch.Tensor
    n_dot_v: torch.Tensor
    f0: torch.Tensor
    diffuse: torch.Tensor

    def energy(self, lut: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Multiple-scattering ``(specular scale (B, 3, H, W), diffuse scale (B, 3, H, W))``
        of :func:`~torchraster.shading.energy.energy_terms`, read from the DFG table
        ``lut`` at ``n.v`` and roughness clamped as the Cook-Torrance lobe clamps them."""
        return energy_terms(self.f0, self.n_dot_v.clamp(MIN_COS, 1.0),
                            self.roughness.clamp(MIN_ROUGHNESS, 1.0), lut)


def pixel_surface(n: torch.Tensor, v: torch.Tensor, *, albedo: torch.Tensor,
                  metallic: torch.Tensor, roughness: torch.Tensor) -> PixelSurface:
    """The :class:`PixelSurface` of unit ``n``, ``v`` ``(B, 3, H, W)``, ``albedo``
    ``(B, 3, H, W)``, ``metallic`` and ``roughness`` ``(B, 1, H, W)``."""
    return PixelSurface(albedo=albedo, metallic=metallic, roughness=roughness, n=n, v=v,
                        n_dot_v=dot(n, v), f0=specular_f0(albedo, metallic),
                        diffuse=diffuse_color(albedo, metallic))


__all__ = ["PixelSurface", "Surface", "pixel_surface"]
