"""Lights: falloff laws at known distances / angles, SH irradiance, YAML schema, gradients."""

from __future__ import annotations

import math

import pydantic
import pytest
import torch
import yaml

from torchraster.config import lights_from_config, parse_lights
from torchraster.shading.lights import (
    MIN_LIGHT_DISTANCE,
    DirectionalLights,
    Lights,
    PointLights,
    SpotLights,
    directional_incidence,
    point_incidence,
    sh_basis,
    sh_from_color,
    sh_irradiance,
    spot_incidence,
)

F64 = torch.float64


def points_on_x(xs: list[float]) -> torch.Tensor:
    """(1, 3, 1, N) world positions (x, 0, 0)."""
    p = torch.zeros(1, 3, 1, len(xs), dtype=F64)
    p[0, 0, 0] = torch.tensor(xs, dtype=F64)
    return p


def test_directional() -> None:
    lights = DirectionalLights(
        direction=torch.tensor([[[0.0, -2.0, 0.0], [1.0, 1.0, 0.0]]], dtype=F64),
        color=torch.tensor([[[1.0, 0.5, 0.25], [0.0, 1.0, 0.0]]], dtype=F64),
        intensity=torch.tensor([[4.0, 2.0]], dtype=F64),
    )
    l, e = directional_incidence(lights)
    assert l.shape == (1, 2, 3, 1, 1) and e.shape == (1, 2, 3, 1, 1)
    torch.testing.assert_close(l[0, 0, :, 0, 0], torch.tensor([0.0, 1.0, 0.0], dtype=F64))
    s = -1 / math.sqrt(2)
    torch.testing.assert_close(l[0, 1, :, 0, 0], torch.tensor([s, s, 0.0], dtype=F64))
    torch.testing.assert_close(e[0, 0, :, 0, 0], torch.tensor([4.0, 2.0, 1.0], dtype=F64))
    assert lights.cast_shadows.dtype == torch.bool and not lights.cast_shadows.any()


def test_point_inverse_square_and_range_window() -> None:
    xs = [0.5, 1.0, 2.0, 3.0, 3.9, 4.0, 6.0]
    pos = points_on_x(xs)
    rng = 4.0
    lights = PointLights(
        position=torch.zeros(1, 2, 3, dtype=F64),
        color=torch.tensor([[[1.0, 1.0, 1.0], [0.2, 0.4, 0.6]]], dtype=F64),
        intensity=torch.tensor([[10.0, 10.0]], dtype=F64),
        range=torch.tensor([[math.inf, rng]], dtype=F64),
    )
    l, e = point_incidence(lights, pos)
    assert l.shape == (1, 2, 3, 1, len(xs)) and e.shape == (1, 2, 3, 1, len(xs))
    for i, d in enumerate(xs):
        assert e[0, 0, 0, 0, i].item() == pytest.approx(10.0 / d**2, rel=1e-12)
        window = max(0.0, 1.0 - (d / rng) ** 4) ** 2  # Karis 2013
        for c, col in enumerate((0.2, 0.4, 0.6)):
            assert e[0, 1, c, 0, i].item() == pytest.approx(col * 10.0 * window / d**2, abs=1e-12)
        torch.testing.assert_close(l[0, :, :, 0, i], torch.tensor([[-1.0, 0, 0]] * 2, dtype=F64))
    # at the light itself: distance floored at MIN_LIGHT_DISTANCE, l = 0, all finite
    l0, e0 = point_incidence(lights, points_on_x([0.0]))
    assert e0[0, 0, 0, 0, 0].item() == pytest.approx(10.0 / MIN_LIGHT_DISTANCE**2)
    assert (l0 == 0).all()


def test_spot_cone_falloff_at_known_angles() -> None:
    inner, outer = math.radians(20), math.radians(40)
    lights = SpotLights(
        position=torch.tensor([[[0.0, 0.0, 1.0]]], dtype=F64),
        direction=torch.tensor([[[0.0, 0.0, -3.0]]], dtype=F64),  # not unit on purpose
        color=torch.ones(1, 1, 3, dtype=F64),
        intensity=torch.tensor([[5.0]], dtype=F64),
        inner_cone_angle=torch.tensor([[inner]], dtype=F64),
        outer_cone_angle=torch.tensor([[outer]], dtype=F64),
    )
    angles = [0, 10, 19.9, 25, 30, 35, 40, 50, 89]
    xs = [math.tan(math.radians(a)) for a in angles]  # points on the plane z = 0
    _, e = spot_incidence(lights, points_on_x(xs))
    for i, a in enumerate(angles):
        t = (math.cos(math.radians(a)) - math.cos(outer)) / (math.cos(inner) - math.cos(outer))
        cone = min(max(t, 0.0), 1.0) ** 2  # glTF KHR_lights_punctual
        d2 = 1.0 + xs[i] ** 2
        assert e[0, 0, 1, 0, i].item() == pytest.approx(5.0 * cone / d2, abs=1e-12), a
    # inner == outer: a hard edge, still finite
    hard = SpotLights(
        position=lights.position, direction=lights.direction, color=lights.color,
        intensity=lights.intensity, inner_cone_angle=lights.outer_cone_angle,
        outer_cone_angle=lights.outer_cone_angle,
    )
    _, e = spot_incidence(hard, points_on_x(xs))
    assert torch.isfinite(e).all() and e[0, 0, 0, 0, 0] > 0 and e[0, 0, 0, 0, -2] == 0


def test_sh_constant_and_brute_force_irradiance() -> None:
    c = torch.tensor([[0.3, 0.6, 0.9]], dtype=F64)
    n = torch.randn(1, 3, 4, 5, dtype=F64)
    n = n / n.norm(dim=1, keepdim=True)
    torch.testing.assert_close(sh_irradiance(sh_from_color(c), n),
                               (math.pi * c)[:, :, None, None].expand(1, 3, 4, 5))

    # A band-limited radiance L(w) = 1 + 0.5 w_x + 0.3 w_y w_z (exactly order 2): project it
    # by quadrature, then compare E(n) with the brute-force integral of L max(n.w, 0).
    def radiance(w):
        return 1.0 + 0.5 * w[0] + 0.3 * w[1] * w[2]

    th = (torch.arange(400, dtype=F64) + 0.5) * math.pi / 400
    ph = (torch.arange(800, dtype=F64) + 0.5) * 2 * math.pi / 800
    T, P = torch.meshgrid(th, ph, indexing="ij")
    w = torch.stack([T.sin() * P.cos(), T.sin() * P.sin(), T.cos()])  # (3, 400, 800)
    dw = T.sin() * (math.pi / 400) * (2 * math.pi / 800)
    Lw = radiance(w)
    coeff = (sh_basis(w) * Lw * dw).sum(dim=(-2, -1))  # (9,)
    sh = coeff[None, :, None].expand(1, 9, 3).contiguous()
    normals = torch.tensor([[0, 0, 1.0], [1, 0, 0], [0.3, -0.5, 0.8], [-1, 0, 0]], dtype=F64)
    normals = normals / normals.norm(dim=1, keepdim=True)
    e = sh_irradiance(sh, normals.T.reshape(1, 3, 1, 4))[0, 0, 0]
    for i, nn in enumerate(normals):
        cos = (w * nn.view(3, 1, 1)).sum(0).clamp_min(0)
        ref = (Lw * cos * dw).sum().item()
        assert e[i].item() == pytest.approx(ref, rel=1e-4)


YAML = """
- {type: ambient, color: [0.1, 0.2, 0.3], intensity: 2.0}
- {type: directional, direction: [0, -1, 0], color: [1, 1, 1], intensity: 3.0, cast_shadows: true}
- {type: point, position: [0, 2, 0], intensity: 50.0, range: 10.0}
- {type: point, name: fill, position: [1, 2, 0]}
- type: spot
  position: [0, 3, 0]
  direction: [0, -1, 0]
  intensity: 100.0
  inner_cone_angle: 0.2
  outer_cone_angle: 0.5
"""


def test_config_to_tensors() -> None:
    cfgs = parse_lights(yaml.safe_load(YAML))
    lights = lights_from_config(cfgs, batch=2, dtype=F64)
    assert lights.batch_size == 2
    assert lights.ambient.shape == (2, 9, 3)
    # ambient colour * intensity is the constant radiance: E = pi * c on every normal
    n = torch.tensor([0.0, 1.0, 0.0], dtype=F64).view(1, 3, 1, 1).expand(2, 3, 1, 1)
    torch.testing.assert_close(
        sh_irradiance(lights.ambient, n)[:, :, 0, 0],
        math.pi * 2.0 * torch.tensor([[0.1, 0.2, 0.3]] * 2, dtype=F64),
    )
    assert lights.directional.count == 1 and bool(lights.directional.cast_shadows.all())
    assert lights.point.count == 2 and lights.point.position.shape == (2, 2, 3)
    assert lights.point.range[0].tolist() == [10.0, math.inf]
    assert lights.spot.count == 1 and not lights.spot.cast_shadows.any()
    assert lights.spot.outer_cone_angle[0, 0].item() == pytest.approx(0.5)
    only_dir = lights_from_config([cfgs[1]])
    assert only_dir.point is None and only_dir.spot is None and only_dir.ambient is None


@pytest.mark.parametrize(
    "bad, where",
    [
        ({"type": "spot", "inner_cone_angle": 0.6, "outer_cone_angle": 0.5}, "0.spot"),
        ({"type": "spot", "outer_cone_angle": 2.0}, "0.spot.outer_cone_angle"),
        ({"type": "point", "range": 0.0}, "0.point.range"),
        ({"type": "point", "intensity": -1.0}, "0.point.intensity"),
        ({"type": "directional", "direction": [0, 0, 0]}, "0.directional.direction"),
        ({"type": "directional", "direction": [0, 1]}, "0.directional.direction"),
        ({"type": "point", "colour": [1, 1, 1]}, "0.point.colour"),
        ({"type": "ambient", "cast_shadows": True}, "0.ambient.cast_shadows"),
        ({"type": "laser"}, "0"),
        ({"type": "area", "shape": "disc", "size": [1, 1]}, "0.area"),
        ({"type": "area", "radius": 0.2}, "0.area"),
        ({"type": "area", "size": [1, 0]}, "0.area.size.1"),
        ({"type": "area", "direction": [0, -1, 0], "up": [0, 2, 0]}, "0.area"),
        ({"type": "area", "shadows": {"light_size": 0.2}}, "0.area"),
        ({"type": "area", "shadows": {"cascades": 2}}, "0.area"),
    ],
)
def test_config_errors_name_the_key(bad: dict, where: str) -> None:
    with pytest.raises(pydantic.ValidationError) as info:
        parse_lights([bad])
    assert where in str(info.value)


def test_container_validation() -> None:
    one = torch.ones(1, 1)
    vec = torch.ones(1, 1, 3)
    with pytest.raises(ValueError, match="range"):
        PointLights(position=vec, color=vec, intensity=one, range=torch.zeros(1, 1))
    with pytest.raises(ValueError, match="cone"):
        SpotLights(position=vec, direction=vec, color=vec, intensity=one,
                   inner_cone_angle=one, outer_cone_angle=0.5 * one)
    with pytest.raises(ValueError, match="DirectionalLights.color"):
        DirectionalLights(direction=vec, color=torch.ones(1, 1, 4), intensity=one)
    with pytest.raises(ValueError, match="intensity"):
        DirectionalLights(direction=vec, color=vec, intensity=-one)
    with pytest.raises(ValueError, match="batch sizes differ"):
        Lights(ambient=torch.zeros(2, 9, 3),
               directional=DirectionalLights(direction=vec, color=vec, intensity=one))
    with pytest.raises(ValueError, match="batch"):
        lights_from_config([], batch=0)


def test_gradcheck_light_parameters() -> None:
    g = torch.Generator().manual_seed(5)
    pos = torch.randn(1, 3, 2, 2, generator=g, dtype=F64) * 0.3
    pos[:, 2] = 0.0

    def rq(*shape, lo=0.2, hi=0.8):
        return (torch.rand(*shape, generator=g, dtype=F64) * (hi - lo) + lo).requires_grad_()

    def dir_fn(direction, color, intensity):
        return directional_incidence(DirectionalLights(direction, color, intensity))

    def point_fn(light_pos, color, intensity, range_, surface_pos):
        return point_incidence(PointLights(light_pos, color, intensity, range_), surface_pos)

    def spot_fn(light_pos, direction, color, intensity, inner, outer, surface_pos):
        lights = SpotLights(light_pos, direction, color, intensity, None, inner, outer)
        return spot_incidence(lights, surface_pos)

    light_pos = torch.tensor([[[0.1, -0.2, 1.0], [0.3, 0.2, 0.8]]], dtype=F64)
    assert torch.autograd.gradcheck(dir_fn, (rq(1, 2, 3), rq(1, 2, 3), rq(1, 2)))
    assert torch.autograd.gradcheck(
        point_fn,
        (light_pos.clone().requires_grad_(), rq(1, 2, 3), rq(1, 2), rq(1, 2, lo=1.5, hi=2.0),
         pos.clone().requires_grad_()),
    )
    direction = torch.tensor([[[0.0, 0.1, -1.0], [0.1, 0.0, -1.0]]], dtype=F64)
    # cone angles chosen so the points fall inside the smooth part of the falloff
    inner = torch.tensor([[0.05, 0.1]], dtype=F64, requires_grad=True)
    outer = torch.tensor([[1.2, 1.3]], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(
        spot_fn,
        (light_pos.clone().requires_grad_(), direction.requires_grad_(), rq(1, 2, 3), rq(1, 2),
         inner, outer, pos.clone().requires_grad_()),
    )


def test_hostile_light_values_finite_gradients() -> None:
    # surface point at the light, tiny direction, black light, 1e6 cd, range window edge
    pos = points_on_x([0.0, 1.0, 2.0]).float().requires_grad_()
    light_pos = torch.zeros(1, 3, 3, requires_grad=True)
    direction = torch.tensor([[[0.0, 0.0, 1e-7], [1.0, 0, 0], [1.0, 0, 0]]], requires_grad=True)
    color = torch.tensor([[[0.0, 0, 0], [1, 1, 1], [1, 1, 1]]], requires_grad=True)
    intensity = torch.tensor([[0.0, 1e6, 1.0]], requires_grad=True)
    rng = torch.tensor([[1.0, 2.0, math.inf]], requires_grad=True)
    outer = torch.tensor([[0.0, 0.5, math.pi / 2]], requires_grad=True)
    inner = torch.tensor([[0.0, 0.5, 0.0]], requires_grad=True)
    spot = SpotLights(light_pos, direction, color, intensity, rng, inner, outer)
    l, e = spot_incidence(spot, pos)
    assert torch.isfinite(l).all() and torch.isfinite(e).all()
    (l.sum() + e.sum()).backward()
    for t in (pos, light_pos, direction, color, intensity, rng, outer, inner):
        assert torch.isfinite(t.grad).all()
