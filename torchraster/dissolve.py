"""The dissolve effect: surfaces burn away where a noise texture falls below a threshold,
with a glowing band at the edge.

    renderer = Renderer(256, dissolve=Dissolve(threshold=0.4, edge_color=(1.0, 0.35, 0.05)))

Per covered pixel with world position ``p``:

* ``noise = fbm(scale * p)`` in [0, 1): seeded 3-D value noise (trilinear interpolation of
  lattice values, 256 equally spaced levels in random order, with the quintic fade
  ``6t^5 - 15t^4 + 10t^3``, Perlin 2002), summed over ``octaves`` (frequency x2, amplitude
  x0.5 each), normalised, then mapped through the Gaussian CDF of its measured spread so it
  is ~uniform: ``t`` is about the fraction of the surface dissolved. Deterministic for a
  ``seed`` on every device. World space, so the pattern sticks to a static object.
* **discard** where ``noise < threshold``: the surface gets opacity 0 like a glTF ``MASK``
  cut-out, so what lies behind shows (the renderer rasterizes depth layers for it).
* **edge glow** on the kept surface, added to its radiance:
  ``edge_color * edge_intensity * (1 - smoothstep((noise - t) / edge_width)) * ramp`` with
  ``ramp = min(t / edge_width, 1)`` (no glow at t = 0: the intact object). The band is
  smooth in ``t``, so ``d image / d threshold`` is finite and non-zero across the glowing
  band ("differentiable where it can be"); the discard itself is a hard test (zero
  gradient), as a cut-out is.

t = 0 keeps everything, t = 1 discards everything. Shadow maps ignore the effect (dissolved
parts still cast shadows, as cut-outs do).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch

#: Lattice period of the noise (a 256-entry permutation table, as Perlin's).
PERIOD: int = 256
#: Largest number of fBm octaves.
MAX_OCTAVES: int = 8
#: Standard deviation of the raw fBm (mean 0.5) for 1..MAX_OCTAVES octaves, measured over
#: 250,000 random points and 4 seeds (spread between seeds < 0.002): the Gaussian CDF of
#: this spread maps the noise to ~uniform on [0, 1), so t is ~ the fraction dissolved.
NOISE_STD: tuple[float, ...] = (0.1995, 0.1487, 0.1305, 0.1226, 0.1188, 0.1170, 0.1161,
                                0.1156)


@dataclass(frozen=True, eq=False)  # eq=False: a tensor threshold has no truth value
class Dissolve:
    """Settings of the dissolve effect (module docstring).

    Attributes:
        threshold: t in [0, 1]: a float, a 0-dim tensor or a ``(B,)`` tensor (one per batch
            item, e.g. frames of an animation); may require grad.
        edge_width: width of the glowing band in noise units, >= 0 (0: no glow).
        edge_color: linear RGB of the glow, 3 non-negative floats.
        edge_intensity: multiplies ``edge_color`` (radiance, nits), >= 0.
        scale: noise frequency: lattice cells per world unit, > 0.
        octaves: fBm octaves, 1 to :data:`MAX_OCTAVES`.
        seed: the noise pattern, an int in [0, 2**63).
    """

    threshold: float | torch.Tensor = 0.5
    edge_width: float = 0.05
    edge_color: Sequence[float] = field(default=(1.0, 0.35, 0.05))
    edge_intensity: float = 4.0
    scale: float = 4.0
    octaves: int = 3
    seed: int = 0

    def __post_init__(self) -> None:
        t = self.threshold
        if isinstance(t, torch.Tensor):
            if t.dim() > 1 or not t.is_floating_point():
                raise ValueError(f"threshold: expected a float, a 0-dim or (B,) float tensor, "
                                 f"got {tuple(t.shape)} {t.dtype}")
            values = t.detach()
        else:
            if isinstance(t, bool) or not isinstance(t, (int, float)):
                raise TypeError(f"threshold: expected a float in [0, 1], got {t!r}")
            values = torch.tensor(float(t))
        if not bool(torch.isfinite(values).all()) or bool(((values < 0) | (values > 1)).any()):
            raise ValueError(f"threshold: expected values in [0, 1], got {t!r}")
        for name, lo in (("edge_width", 0.0), ("edge_intensity", 0.0)):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v < lo:
                raise ValueError(f"{name}: expected a finite float >= {lo}, got {v!r}")
        if not isinstance(self.scale, (int, float)) or not (math.isfinite(self.scale)
                                                            and self.scale > 0):
            raise ValueError(f"scale: expected a finite float > 0, got {self.scale!r}")
        color = list(self.edge_color) if not isinstance(self.edge_color, str) else []
        if len(color) != 3 or not all(isinstance(c, (int, float)) and math.isfinite(c)
                                      and c >= 0 for c in color):
            raise ValueError(f"edge_color: expected 3 finite floats >= 0, got "
                             f"{self.edge_color!r}")
        if isinstance(self.octaves, bool) or not isinstance(self.octaves, int) or not (
                1 <= self.octaves <= MAX_OCTAVES):
            raise ValueError(f"octaves: expected an int in [1, {MAX_OCTAVES}], got "
                             f"{self.octaves!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or not (
                0 <= self.seed < 2**63):
            raise ValueError(f"seed: expected an int in [0, 2**63), got {self.seed!r}")

    def noise(self, position: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """:func:`value_noise` of this effect at world positions ``(B, 3, H, W)`` ->
        ``(B, 1, H, W)``; with ``mask`` ``(B, 1, H, W)``, evaluated where ``mask > 0`` only
        (0 elsewhere)."""
        if mask is None:
            return value_noise(position, self.scale, self.octaves, self.seed)
        b, _, h, w = position.shape
        covered = (mask > 0).expand(b, 1, h, w).reshape(-1)
        points = position.permute(0, 2, 3, 1).reshape(-1, 3)[covered]  # (N, 3)
        values = value_noise(points.T.reshape(1, 3, 1, -1), self.scale, self.octaves,
                             self.seed).reshape(-1)
        out = position.new_zeros(b * h * w).masked_scatter(covered, values)
        return out.view(b, 1, h, w)

    def terms(self, position: torch.Tensor, mask: torch.Tensor | None = None
              ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(keep, glow)`` at world positions ``(B, 3, H, W)`` (where ``mask > 0`` if
        given): keep ``(B, 1, H, W)`` 0 / 1 (the surface's opacity factor) and the glow
        radiance ``(B, 3, H, W)``."""
        t = torch.as_tensor(self.threshold, dtype=position.dtype, device=position.device)
        keep, weight = dissolve_weights(self.noise(position, mask), t.reshape(-1, 1, 1, 1),
                                        self.edge_width)
        color = torch.tensor(self.edge_color, dtype=position.dtype, device=position.device)
        return keep, weight * (color * self.edge_intensity).view(1, 3, 1, 1)


def dissolve_weights(noise: torch.Tensor, threshold: torch.Tensor | float,
                     edge_width: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Opacity factor and glow weight of the dissolve (module docstring).

    Args:
        noise: ``(B, 1, H, W)`` noise values in [0, 1).
        threshold: t, broadcastable to ``noise`` (e.g. ``(B, 1, 1, 1)``), in [0, 1].
        edge_width: width of the band in noise units (>= 0).

    Returns:
        ``keep`` (1 where ``noise >= t``, else 0; no gradient) and the glow weight in
        [0, 1] (0 where discarded), both shaped like ``noise``; the weight is smooth in
        ``t`` and ``noise`` inside the band.
    """
    keep = (noise >= threshold).to(noise.dtype)
    if edge_width <= 0:
        return keep, torch.zeros_like(noise)
    x = ((noise - threshold) / edge_width).clamp(0.0, 1.0)
    band = 1.0 - x * x * (3.0 - 2.0 * x)  # 1 - smoothstep
    ramp = (torch.as_tensor(threshold, dtype=noise.dtype) / edge_width).clamp(max=1.0)
    return keep, keep * band * ramp


def _lattice(seed: int, device: torch.device, dtype: torch.dtype
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """Permutation ``(2 PERIOD,)`` int64 and lattice values ``(PERIOD,)`` in [0, 1) of a
    seed (drawn on the CPU, so every device gets the same pattern)."""
    g = torch.Generator().manual_seed(seed)
    perm = torch.randperm(PERIOD, generator=g)
    # equally spaced levels in random order: mean and spread exact for every seed
    values = (torch.randperm(PERIOD, generator=g).to(torch.float64) + 0.5) / PERIOD
    return perm.repeat(2).to(device), values.to(device=device, dtype=dtype)


def value_noise(position: torch.Tensor, scale: float = 4.0, octaves: int = 3,
                seed: int = 0, uniform: bool = True) -> torch.Tensor:
    """Seeded fBm of 3-D value noise in [0, 1) (module docstring).

    Args:
        position: ``(B, 3, H, W)`` points (world units).
        scale: lattice cells per unit.
        octaves: number of octaves (frequency x2, amplitude x0.5 each).
        seed: the pattern.
        uniform: map the fBm (mean 0.5, spread :data:`NOISE_STD`) through its Gaussian
            CDF to ~uniform values; False: the raw fBm.

    Returns:
        ``(B, 1, H, W)`` noise, differentiable with respect to ``position``.
    """
    perm, values = _lattice(seed, position.device, position.dtype)
    d = torch.tensor([0, 1], device=position.device)  # the two lattice corners per axis
    total = torch.zeros_like(position[:, :1])
    amplitude, norm = 1.0, 0.0
    for k in range(octaves):
        p = position * (scale * 2.0**k) + 17.0 * k  # each octave its own part of the lattice
        cell = torch.floor(p.detach())
        f = p - cell
        fade = f * f * f * (f * (f * 6.0 - 15.0) + 10.0)  # Perlin 2002 quintic
        i = (cell.to(torch.int64) % PERIOD).unsqueeze(-1)  # (B, 3, H, W, 1)
        # hash of the 8 corners, Perlin's nested permutation (indices stay < 2 PERIOD)
        hx = perm[i[:, 0] + d]  # (B, H, W, 2)
        hy = perm[hx[..., :, None] + i[:, 1, ..., None] + d]  # (B, H, W, 2, 2)
        h = perm[hy[..., None] + i[:, 2, ..., None, None] + d]  # (B, H, W, 2, 2, 2)
        w = torch.stack([1 - fade, fade], -1)  # (B, 3, H, W, 2): weights of the corners
        corner = (w[:, 0, ..., :, None, None] * w[:, 1, ..., None, :, None]
                  * w[:, 2, ..., None, None, :])
        total = total + amplitude * (corner * values[h]).sum((-3, -2, -1)).unsqueeze(1)
        norm += amplitude
        amplitude *= 0.5
    raw = total / norm
    if not uniform:
        return raw
    u = 0.5 * (1.0 + torch.erf((raw - 0.5) / (NOISE_STD[octaves - 1] * math.sqrt(2.0))))
    return u.clamp(0.0, 1.0 - torch.finfo(u.dtype).eps)  # < 1: t = 1 discards everything


__all__ = ["MAX_OCTAVES", "PERIOD", "Dissolve", "dissolve_weights", "value_noise"]
