"""Pins of formulas that other tests reached only indirectly (issue 22): cascade selection
and the blend band of directional shadow maps, Schlick's Fresnel and the ACES fit at several
points against their closed forms, and the fused Cook-Torrance of the lighting pass against
the BRDF of ``brdf.py`` (one GGX / Schlick code path)."""

from __future__ import annotations

import math

import pytest
import torch

from torchraster.post.tonemap import tone_curve
from torchraster.shading import brdf
from torchraster.shading.lighting import cook_torrance_lights
from torchraster.shading.lights import DirectionalLights
from torchraster.shading.shadows import (
    ShadowSettings,
    cascade_splits,
    directional_views,
    shadow_visibility,
)

F64 = torch.float64


# ------------------------------------------------------------------------------ cascades


def test_cascade_splits_closed_form() -> None:
    """Zhang et al. 2006: C_i = lam n (f/n)^(i/C) + (1 - lam) (n + (f - n) i/C)."""
    n, f = torch.tensor([0.5, 2.0], dtype=F64), torch.tensor([100.0, 10.0], dtype=F64)
    for count in (1, 2, 3, 4):
        for lam in (0.0, 0.3, 1.0):
            got = cascade_splits(n, f, count, lam)
            for b in range(2):
                want = [lam * n[b] * (f[b] / n[b]) ** (i / count)
                        + (1 - lam) * (n[b] + (f[b] - n[b]) * i / count)
                        for i in range(count + 1)]
                torch.testing.assert_close(got[b], torch.stack(want), rtol=1e-12, atol=0)


def _cascade_setup(cascades: int, blend: float, max_distance: float | None = None):
    """A camera at the origin looking down -z over a large caster box, a sun straight down;
    its cascaded maps (not rendered: the test fills them). No depth bias: a receiver is
    behind a texel of depth 0 in every cascade, however coarse."""
    st = ShadowSettings(map_size=64, filter="hard", cascades=cascades, cascade_blend=blend,
                        max_distance=max_distance, bias=0.0, slope_bias=0.0)
    view = torch.eye(4)[None]
    f = 1.0 / math.tan(math.radians(30.0))  # 60 degree perspective, near 0.5, far inf
    proj = torch.tensor([[[f, 0, 0, 0], [0, f, 0, 0], [0, 0, -1, -1.0], [0, 0, -1, 0]]])
    bounds = torch.tensor([[[-40.0, -1.0, -60.0], [40.0, 1.0, -1.0]]])
    g = directional_views(torch.tensor([[[0.0, -1.0, 0.0]]]), st, bounds, view, proj)
    assert bool(g.rendered.all())
    return g, view


def _visibility_at(g, view, depths: torch.Tensor, occluded: int) -> torch.Tensor:
    """Visibility of receivers on the camera axis at camera depths ``depths`` when only
    cascade ``occluded`` holds an occluder (depth 0 everywhere: in front of every receiver);
    the other cascades are empty (+inf)."""
    nv, s = g.view.shape[2], g.settings.map_size
    g.depth = torch.full((1, 1, nv, s, s), math.inf)
    g.depth[:, :, occluded] = 0.0
    n = depths.numel()
    pos = torch.stack([torch.zeros(n), torch.zeros(n), -depths.float()])[None, :, None]
    normal = torch.tensor([0.0, 1.0, 0.0])[None, :, None, None].expand(1, 3, 1, n)
    receive = torch.ones(1, 1, 1, n, dtype=torch.bool)
    return shadow_visibility(g, pos, normal, receive, view)[0, 0, 0, 0]  # (n,)


@pytest.mark.parametrize("cascades,blend", [(2, 0.1), (3, 0.2), (4, 0.1), (4, 0.0)])
def test_cascade_selection_and_blend_band(cascades: int, blend: float) -> None:
    """A receiver at camera depth z uses cascade k for s_k <= z < s_(k+1); over the last
    ``cascade_blend`` of cascade k's range (all but the last cascade) it fades linearly into
    cascade k + 1. Occluding one cascade at a time reads each cascade's weight."""
    g, view = _cascade_setup(cascades, blend)
    s = g.splits[0, 0].double()
    probes, want = [], []  # (depth, {cascade: weight})
    for k in range(cascades):
        lo, hi = float(s[k]), float(s[k + 1])
        band = blend * (hi - lo)
        probes.append(lo + 0.3 * (hi - lo) if k else lo + 0.5 * (hi - lo))
        want.append({k: 1.0})  # well inside: cascade k only
        if k < cascades - 1 and band > 0:
            for frac in (0.25, 0.5, 0.75):  # inside the band: weight frac on the next
                probes.append(hi - band + frac * band)
                want.append({k: 1.0 - frac, k + 1: frac})
        if k < cascades - 1:
            probes.append(hi * (1 + 1e-4))  # just past the split: the next cascade
            want.append({k + 1: 1.0})
    depths = torch.tensor(probes, dtype=F64)
    for c in range(cascades):
        vis = _visibility_at(g, view, depths, occluded=c)
        expect = torch.tensor([1.0 - w.get(c, 0.0) for w in want])
        torch.testing.assert_close(vis, expect, atol=2e-3, rtol=0,
                                   msg=lambda m, c=c: f"cascade {c} weights: {m}")


def test_cascades_end_at_max_distance() -> None:
    """Receivers at or beyond max_distance are unshadowed whatever the maps hold."""
    g, view = _cascade_setup(3, 0.1, max_distance=20.0)
    depths = torch.tensor([5.0, 19.0, 20.5, 40.0], dtype=F64)
    s = g.splits[0, 0]
    assert float(s[-1]) == pytest.approx(20.0)
    occluded_all = torch.ones(4)
    for c in range(3):
        occluded_all = occluded_all * _visibility_at(g, view, depths, c)
    assert occluded_all[:2].tolist() == [0.0, 0.0] and occluded_all[2:].tolist() == [1.0, 1.0]


# ------------------------------------------------------------------- Schlick, ACES, GGX


def test_schlick_closed_form_points() -> None:
    """F = f0 + (f90 - f0)(1 - cos)^5 at hand-evaluated points (Schlick 1994)."""
    cos = torch.tensor([0.0, 0.1, 0.25, 0.5, 0.8, 1.0, -0.3, 1.5], dtype=F64)
    for f0, f90 in ((0.04, 1.0), (0.9, 1.0), (0.5, 0.2)):
        m = [1.0, 0.9, 0.75, 0.5, 0.2, 0.0, 1.0, 0.0]  # 1 - clamp(cos, 0, 1)
        want = torch.tensor([f0 + (f90 - f0) * x ** 5 for x in m], dtype=F64)
        torch.testing.assert_close(brdf.f_schlick(cos, f0, f90), want, rtol=1e-14, atol=0)
    # 0.04 + 0.96 * 0.5^5 = 0.07, written out
    assert float(brdf.f_schlick(torch.tensor([0.5], dtype=F64), 0.04)) == pytest.approx(0.07)


def test_aces_closed_form_points() -> None:
    """Narkowicz 2015: (x (2.51 x + 0.03)) / (x (2.43 x + 0.59) + 0.14), clamped to [0, 1]."""
    xs = [0.0, 0.01, 0.1, 0.18, 0.5, 1.0, 2.0, 4.0, 10.0, 1e3]
    got = tone_curve(torch.tensor(xs, dtype=F64).view(1, 1, 1, -1), "aces").flatten()
    want = [min(1.0, max(0.0, x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14)))
            for x in xs]
    torch.testing.assert_close(got, torch.tensor(want, dtype=F64), rtol=1e-12, atol=1e-15)
    # at x = 1: 2.54 / 3.16
    assert float(got[5]) == pytest.approx(2.54 / 3.16, rel=1e-12)


def test_fused_lighting_matches_brdf_cook_torrance() -> None:
    """The lighting pass's fused Cook-Torrance (lights as a matmul dimension) equals
    ``brdf.cook_torrance`` times the illuminance and n.l, per light, in float64."""
    gen = torch.Generator().manual_seed(3)
    m, n_lights = 200, 3
    normal = torch.nn.functional.normalize(torch.randn(3, m, generator=gen, dtype=F64), dim=0)
    normal[2] = normal[2].abs() + 0.2
    normal = torch.nn.functional.normalize(normal, dim=0)
    view = torch.nn.functional.normalize(
        normal + 0.8 * torch.randn(3, m, generator=gen, dtype=F64), dim=0)
    albedo = torch.rand(3, m, generator=gen, dtype=F64)
    metallic = torch.rand(1, m, generator=gen, dtype=F64)
    roughness = torch.rand(1, m, generator=gen, dtype=F64) * 0.95 + 0.05
    direction = torch.randn(1, n_lights, 3, generator=gen, dtype=F64)
    direction[..., 2] = -direction[..., 2].abs() - 0.3  # coming from +z, towards the surface
    color = torch.rand(1, n_lights, 3, generator=gen, dtype=F64)
    intensity = torch.rand(1, n_lights, generator=gen, dtype=F64) * 3
    lights = DirectionalLights(direction=direction, color=color, intensity=intensity)
    got = cook_torrance_lights(DirectionalLights, lights, 0, torch.zeros(3, m, dtype=F64),
                               normal, view, albedo, metallic, roughness, multiscatter=False)
    want = torch.zeros(3, m, dtype=F64)
    for i in range(n_lights):
        ldir = -torch.nn.functional.normalize(direction[0, i], dim=0)[:, None].expand(3, m)
        f = brdf.cook_torrance(*(t[None, :, None] for t in (normal, view, ldir, albedo,
                                                            metallic, roughness)))
        f = f[0, :, 0]  # (3, M), times n.l
        want += f * (color[0, i] * intensity[0, i])[:, None]
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)
