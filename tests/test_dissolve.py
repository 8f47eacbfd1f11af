"""The dissolve effect: the noise against a point-by-point reference written out here, the
threshold / glow band formulas, gradients in the threshold (gradcheck, finite differences
through the renderer), MASK-like discarding through depth layers, the plan, stress inputs,
errors and YAML."""

from __future__ import annotations

import math

import pytest
import torch

import torchraster as tr
from torchraster import camera
from torchraster.dissolve import NOISE_STD, Dissolve, dissolve_weights, value_noise

VIEW = camera.look_at(torch.tensor([0.3, 0.2, 4.0], dtype=torch.float64),
                      torch.zeros(3, dtype=torch.float64))
PROJ = camera.perspective(40.0, 1.0, 0.1).double()


def _reference_noise(p: list[float], scale: float, octaves: int, seed: int) -> float:
    """The noise at one point, loop by loop (lattice: a seeded permutation hash and 256
    equally spaced levels in a seeded order; quintic fade; octaves x2 / x0.5; Gaussian
    CDF of the measured spread)."""
    g = torch.Generator().manual_seed(seed)
    perm = torch.randperm(256, generator=g).tolist()
    levels = [(v + 0.5) / 256 for v in torch.randperm(256, generator=g).tolist()]
    total, norm, amp = 0.0, 0.0, 1.0
    for k in range(octaves):
        q = [c * scale * 2**k + 17.0 * k for c in p]
        cell = [math.floor(c) for c in q]
        f = [c - i for c, i in zip(q, cell, strict=True)]
        fade = [t**3 * (t * (6 * t - 15) + 10) for t in f]
        val = 0.0
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    h = perm[(perm[(perm[(cell[0] + dx) % 256] + cell[1] + dy) % 256]
                              + cell[2] + dz) % 256]
                    w = ((fade[0] if dx else 1 - fade[0]) * (fade[1] if dy else 1 - fade[1])
                         * (fade[2] if dz else 1 - fade[2]))
                    val += w * levels[h]
        total += amp * val
        norm += amp
        amp *= 0.5
    raw = total / norm
    return 0.5 * (1 + math.erf((raw - 0.5) / (NOISE_STD[octaves - 1] * math.sqrt(2))))


def test_noise_matches_the_reference_point_by_point():
    pts = torch.tensor([[0.1, 0.2, 0.3], [-1.7, 2.25, 0.0], [5.5, -3.1, 7.9], [0, 0, 0]],
                       dtype=torch.float64)
    for scale, octaves, seed in ((4.0, 3, 0), (1.3, 1, 7), (0.5, 5, 123)):
        got = value_noise(pts.T.reshape(1, 3, 1, 4), scale, octaves, seed).flatten()
        want = torch.tensor([_reference_noise(p, scale, octaves, seed) for p in pts.tolist()],
                            dtype=torch.float64)
        torch.testing.assert_close(got, want, rtol=0, atol=1e-12)


def test_noise_is_seeded_uniform_and_below_one():
    g = torch.Generator().manual_seed(3)
    p = torch.rand(1, 3, 100, 100, generator=g, dtype=torch.float64) * 20 - 10
    a, b = value_noise(p, 2.0, 3, 0), value_noise(p, 2.0, 3, 1)
    assert torch.equal(a, value_noise(p, 2.0, 3, 0)) and not torch.equal(a, b)
    assert float(a.min()) >= 0 and float(a.max()) < 1
    for t in (0.1, 0.25, 0.5, 0.75, 0.9):  # t ~ the fraction dissolved
        assert abs(float((a < t).double().mean()) - t) < 0.03
    torch.testing.assert_close(value_noise(p.float(), 2.0, 3, 0), a.float(), rtol=0, atol=1e-5)
    # extreme values stay strictly below 1 (t = 1 dissolves everything)
    assert float(value_noise(torch.full((1, 3, 1, 1), 1e3), 1.0, 1, 0).max()) < 1.0


def test_threshold_and_band_formulas():
    noise = torch.tensor([0.0, 0.29, 0.3, 0.325, 0.35, 0.5], dtype=torch.float64)
    keep, glow = dissolve_weights(noise, torch.tensor(0.3, dtype=torch.float64), 0.05)
    assert keep.tolist() == [0, 0, 1, 1, 1, 1]
    x = (noise - 0.3) / 0.05
    band = 1 - x * x * (3 - 2 * x)  # smoothstep from the definition
    torch.testing.assert_close(glow, torch.tensor([0, 0, 1, float(band[3]), 0, 0],
                                                  dtype=torch.float64))
    assert float(glow[3]) == pytest.approx(0.5)
    # t = 0: the intact object, no glow; edge_width 0: no glow
    keep, glow = dissolve_weights(noise, 0.0, 0.05)
    assert bool((keep == 1).all()) and bool((glow == 0).all())
    assert bool((dissolve_weights(noise, 0.3, 0.0)[1] == 0).all())


def test_gradcheck_of_the_glow_in_the_threshold():
    noise = torch.tensor([0.31, 0.33, 0.36, 0.6], dtype=torch.float64)  # none at t

    def glow(t: torch.Tensor) -> torch.Tensor:
        return dissolve_weights(noise, t, 0.08)[1]

    t = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(glow, (t,))
    t = torch.tensor(0.03, dtype=torch.float64, requires_grad=True)  # inside the ramp
    assert torch.autograd.gradcheck(lambda t: dissolve_weights(noise - 0.29, t, 0.08)[1], (t,))


def _quad(z: float, color: list[float]) -> tuple[torch.Tensor, torch.Tensor, tr.Material]:
    pos = torch.tensor([[-1, -1, z], [1, -1, z], [1, 1, z], [-1, 1, z]], dtype=torch.float64)
    return pos, torch.tensor([[0, 1, 2], [0, 2, 3]]), tr.Material(
        base_color_factor=torch.tensor(color + [1.0]), double_sided=True)


def _two_quads() -> tr.RenderScene:
    p0, f0, m0 = _quad(0.5, [1.0, 0.0, 0.0])
    p1, f1, m1 = _quad(-0.5, [0.0, 0.0, 1.0])
    return tr.RenderScene(torch.cat([p0, p1]), torch.cat([f0, f1 + 4]),
                          face_material=torch.tensor([0, 0, 1, 1]), materials=[m0, m1])


def _layer_positions(scene_quad: tuple) -> tuple[torch.Tensor, torch.Tensor]:
    pos, faces, mat = scene_quad
    out = tr.Renderer(24, shading="unlit")(tr.RenderScene(pos, faces, materials=[mat]), VIEW,
                                           PROJ, channels={"position"})
    return out.gbuffer["position"], out.alpha


def test_discarded_surfaces_show_what_is_behind():
    """Front quad red, back quad blue (unlit), both dissolving: each pixel shows the nearest
    surface whose noise is >= t, plus its glow; checked against each quad alone."""
    d = Dissolve(threshold=0.45, edge_width=0.1, edge_color=(0.0, 1.0, 0.0),
                 edge_intensity=2.0, scale=3.0)
    out = tr.Renderer(24, shading="unlit", dissolve=d)(_two_quads(), VIEW, PROJ)
    assert out.plan.alpha == "mask" and "dissolve t=0.45 edge 0.1" in out.plan
    front, a_front = _layer_positions(_quad(0.5, [1.0, 0.0, 0.0]))
    back, a_back = _layer_positions(_quad(-0.5, [0.0, 0.0, 1.0]))
    want = torch.zeros(1, 3, 24, 24, dtype=torch.float64)
    alpha = torch.zeros(1, 1, 24, 24, dtype=torch.float64)
    hidden = torch.ones_like(alpha)  # nothing nearer kept yet
    for pos, cov, color in ((front, a_front, [1.0, 0.0, 0.0]), (back, a_back, [0.0, 0.0, 1.0])):
        noise = _noise_by_hand(pos, d)
        keep = (noise >= d.threshold) & (cov > 0)
        x = ((noise - d.threshold) / d.edge_width).clamp(0, 1)
        glow = (1 - x * x * (3 - 2 * x)) * keep * torch.tensor([0.0, 2.0, 0.0]).view(1, 3, 1, 1)
        shown = keep * hidden
        want += shown * (torch.tensor(color).view(1, 3, 1, 1) + glow)
        alpha += shown
        hidden = hidden * ~keep
    assert 20 < int((alpha * (a_front > 0) * (a_back > 0)).sum())  # the back shows through
    assert int(((a_front > 0) & (alpha == 0)).sum()) > 5  # and holes go through both
    torch.testing.assert_close(out.alpha, alpha)
    torch.testing.assert_close(out.image, want)


def _noise_by_hand(position: torch.Tensor, d: Dissolve) -> torch.Tensor:
    flat = position[0].reshape(3, -1).T.tolist()
    vals = [_reference_noise(p, d.scale, d.octaves, d.seed) for p in flat]
    return torch.tensor(vals, dtype=torch.float64).view(1, 1, *position.shape[-2:])


def test_zero_keeps_the_render_and_one_removes_everything():
    scene = _two_quads()
    lights = tr.Lights(directional=tr.DirectionalLights(
        direction=torch.tensor([[[0.2, -0.3, -1.0]]], dtype=torch.float64),
        color=torch.ones(1, 1, 3, dtype=torch.float64),
        intensity=torch.tensor([[2.0]], dtype=torch.float64)))
    plain = tr.Renderer(16, background=(0.1, 0.2, 0.3))(scene, VIEW, PROJ, lights)
    assert plain.plan.dissolve == "" and plain.plan.layers == 1  # skipped when not asked
    assert not any("dissolve" in s for s in plain.plan)
    zero = tr.Renderer(16, background=(0.1, 0.2, 0.3), dissolve=Dissolve(threshold=0.0))(
        scene, VIEW, PROJ, lights)
    torch.testing.assert_close(zero.image, plain.image, rtol=1e-12, atol=1e-12)
    one = tr.Renderer(16, background=(0.1, 0.2, 0.3), dissolve=Dissolve(threshold=1.0))(
        scene, VIEW, PROJ, lights)
    assert float(one.alpha.abs().max()) == 0.0
    torch.testing.assert_close(one.image, torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
                               .view(1, 3, 1, 1).expand_as(one.image))


def test_image_gradient_in_the_threshold_matches_finite_differences():
    scene = _two_quads()

    def render(t: torch.Tensor) -> torch.Tensor:
        d = Dissolve(threshold=t, edge_width=0.15, scale=2.0)
        return tr.Renderer(20, shading="unlit", dissolve=d)(scene, VIEW, PROJ).image.sum()

    t = torch.tensor(0.4, dtype=torch.float64, requires_grad=True)
    (g,) = torch.autograd.grad(render(t), t)
    eps = 1e-7
    with torch.no_grad():
        fd = (render(t + eps) - render(t - eps)) / (2 * eps)
    assert bool(torch.isfinite(g)) and abs(float(g)) > 1.0
    assert float(g) == pytest.approx(float(fd), rel=1e-4)


def test_batched_thresholds_and_float32():
    s64 = _two_quads()
    scene = tr.RenderScene(s64.positions.float(), s64.faces, face_material=s64.face_material,
                           materials=s64.materials)
    t = torch.tensor([0.2, 0.7])
    out = tr.Renderer(16, shading="unlit", dissolve=Dissolve(threshold=t))(
        scene, VIEW.float().expand(2, 4, 4), PROJ.float())
    assert out.image.dtype == torch.float32 and "dissolve t=2 values edge 0.05" in out.plan
    assert float(out.alpha[0].sum()) > float(out.alpha[1].sum()) > 0


def test_hostile_inputs_stay_finite():
    scene = _two_quads()
    away = camera.look_at([0.0, 0.0, -4.0], [0.0, 0.0, -8.0]).double()
    for t in (0.0, 1e-9, 0.5, 1.0):
        for view in (VIEW, away):
            tt = torch.tensor(t, dtype=torch.float64, requires_grad=True)
            d = Dissolve(threshold=tt, edge_width=1e-6, edge_intensity=1e30, scale=1e3)
            out = tr.Renderer(12, shading="unlit", dissolve=d)(scene, view, PROJ)
            assert bool(torch.isfinite(out.image).all())
            (g,) = torch.autograd.grad(out.image.sum(), tt, allow_unused=True)
            assert g is None or bool(torch.isfinite(g))


@pytest.mark.parametrize("kwargs, match", [
    ({"threshold": 1.5}, "threshold"), ({"threshold": float("nan")}, "threshold"),
    ({"threshold": torch.zeros(2, 2)}, "threshold"), ({"edge_width": -0.1}, "edge_width"),
    ({"edge_color": (1.0, 0.0)}, "edge_color"), ({"edge_intensity": -1.0}, "edge_intensity"),
    ({"scale": 0.0}, "scale"), ({"octaves": 0}, "octaves"), ({"octaves": 9}, "octaves"),
    ({"seed": -1}, "seed")])
def test_bad_settings_name_the_field(kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        Dissolve(**kwargs)
    with pytest.raises(TypeError, match="dissolve: expected"):
        tr.Renderer(8, dissolve={"threshold": 0.5})


YAML = """
scene:
  objects:
    - primitive: sphere
      material: {base_color: [0.8, 0.8, 0.8]}
cameras:
  - orbit: {azimuth_deg: 0, elevation_deg: 0, distance: 3.0}
render:
  resolution: 20
  shading: unlit
  dissolve: {threshold: 0.5, edge_width: 0.1, edge_color: [0, 1, 0], scale: 3.0, seed: 4}
outputs: {channels: [radiance, alpha]}
"""


def test_yaml_dissolve_end_to_end(tmp_path):
    (view,) = tr.render_config(tr.parse_config(YAML, "d.yaml", base_dir=tmp_path))
    assert "dissolve t=0.5 edge 0.1" in view.plan
    alpha = view.images["alpha"]
    (whole,) = tr.render_config(tr.parse_config(YAML.replace("threshold: 0.5", "threshold: 0"),
                                                "d.yaml", base_dir=tmp_path))
    covered = float((whole.images["alpha"] > 0).sum())
    kept = float((alpha > 0).sum())
    assert 0.2 * covered < kept < 0.9 * covered  # about half of the sphere is gone
    assert float(view.images["radiance"][1].max()) > 1.0  # the green glow
    with pytest.raises(tr.ConfigError, match="render.dissolve.threshold"):
        tr.parse_config(YAML.replace("threshold: 0.5", "threshold: 2"), "d.yaml")


def test_the_shipped_config_renders_from_a_fresh_clone():
    """configs/dissolve.yaml (small): the mesh, texture and background image ship."""
    from pathlib import Path

    cfg = tr.load_config(Path(__file__).resolve().parents[1] / "configs" / "dissolve.yaml")
    tr.config.check_config(cfg)
    cfg.render.resolution, cfg.render.supersample = 24, 1
    (view,) = tr.render_config(cfg)
    assert "background image cover" in view.plan and any("dissolve" in s for s in view.plan)
    assert bool(torch.isfinite(view.images["color"]).all())


def test_dissolve_over_blended_layers():
    """A half-transparent (BLEND) front quad over an opaque back quad, both dissolving:
    front-to-back "over" of the kept layers, each with its glow."""
    d = Dissolve(threshold=0.4, edge_width=0.1, edge_color=(0.0, 1.0, 0.0),
                 edge_intensity=2.0, scale=3.0)
    p0, f0, _ = _quad(0.5, [1.0, 0.0, 0.0])
    p1, f1, m1 = _quad(-0.5, [0.0, 0.0, 1.0])
    glass = tr.Material(base_color_factor=torch.tensor([1.0, 0.0, 0.0, 0.5]),
                        alpha_mode="BLEND", double_sided=True)
    scene = tr.RenderScene(torch.cat([p0, p1]), torch.cat([f0, f1 + 4]),
                           face_material=torch.tensor([0, 0, 1, 1]), materials=[glass, m1])
    out = tr.Renderer(24, shading="unlit", dissolve=d)(scene, VIEW, PROJ)
    assert out.plan.alpha == "blend"
    color, transmittance = torch.zeros(1, 3, 24, 24, dtype=torch.float64), 1.0
    for (pos, cov), rgb, alpha in (
            (_layer_positions(_quad(0.5, [1.0, 0.0, 0.0])), [1.0, 0.0, 0.0], 0.5),
            (_layer_positions(_quad(-0.5, [0.0, 0.0, 1.0])), [0.0, 0.0, 1.0], 1.0)):
        noise = _noise_by_hand(pos, d)
        keep = ((noise >= d.threshold) & (cov > 0)).double()
        x = ((noise - d.threshold) / d.edge_width).clamp(0, 1)
        glow = (1 - x * x * (3 - 2 * x)) * keep * torch.tensor([0.0, 2.0, 0.0]).view(1, 3, 1, 1)
        a = alpha * keep
        color = color + transmittance * a * (torch.tensor(rgb).view(1, 3, 1, 1) + glow)
        transmittance = transmittance * (1 - a)
    torch.testing.assert_close(out.image, color)
    torch.testing.assert_close(out.alpha, 1 - transmittance)
