"""The float64 area-light reference (torchraster.testing.reference_area) against closed
forms: form factors of parallel rectangles and discs, the point-light limit of the BRDF
integral, one- / two-sided emission, occlusion by ray-traced casters and convergence."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import pytest
import torch

from torchraster.testing import reference_area as ra
from torchraster.testing.reference_brdf import heitz_v, walter_ggx

F64 = torch.float64


def _rotation(seed: int = 3) -> torch.Tensor:
    """A fixed random rotation ``(3, 3)`` (det +1)."""
    q, _ = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(seed),
                                       dtype=F64))
    return q * torch.linalg.det(q)


def _corner(a: float, b: float, h: float) -> float:
    """Form factor from a point to the parallel rectangle ``[0, a] x [0, b]`` at height ``h``
    above it (the point under a corner), signed by the orientation of ``a`` and ``b``."""
    if a == 0 or b == 0:
        return 0.0
    x, y = abs(a) / h, abs(b) / h
    f = (x / math.sqrt(1 + x * x) * math.atan(y / math.sqrt(1 + x * x))
         + y / math.sqrt(1 + y * y) * math.atan(x / math.sqrt(1 + y * y))) / (2 * math.pi)
    return math.copysign(1.0, a) * math.copysign(1.0, b) * f


def _rect_ff(px: float, py: float, x0: float, x1: float, y0: float, y1: float,
             h: float) -> float:
    """Form factor from the point ``(px, py, 0)`` facing +z to ``[x0, x1] x [y0, y1]`` at
    height ``h`` (inclusion-exclusion of corner rectangles)."""
    return (_corner(x1 - px, y1 - py, h) - _corner(x0 - px, y1 - py, h)
            - _corner(x1 - px, y0 - py, h) + _corner(x0 - px, y0 - py, h))


def _receivers(xy: list[tuple[float, float]]) -> tuple[torch.Tensor, torch.Tensor]:
    pts = torch.tensor([(x, y, 0.0) for x, y in xy], dtype=F64)
    return pts, torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand_as(pts)


def test_rectangle_form_factor_closed_form():
    # a 1.2 x 0.8 light at height 0.7 facing down (u x v = -z), in a rotated frame
    rot = _rotation()
    xy = [(0.0, 0.0), (0.3, -0.2), (0.55, 0.35), (1.5, 0.1), (-0.9, 0.8)]
    pts, nrm = _receivers(xy)
    u, v = torch.tensor([0.0, 0.4, 0.0], dtype=F64), torch.tensor([0.6, 0.0, 0.0], dtype=F64)
    centre = torch.tensor([0.0, 0.0, 0.7], dtype=F64)
    got = ra.form_factor_reference(pts @ rot.T, nrm @ rot.T, rot @ centre, rot @ u, rot @ v)
    want = torch.tensor([_rect_ff(x, y, -0.6, 0.6, -0.4, 0.4, 0.7) for x, y in xy],
                        dtype=F64)
    assert torch.allclose(got, want, rtol=1e-4, atol=0), (got, want)
    assert ra.light_area(rot @ u, rot @ v) == pytest.approx(4 * 0.24, rel=1e-12)


def test_disc_form_factor_closed_forms():
    h, r = 0.8, 0.5
    # circle: on the axis r^2 / (h^2 + r^2); off the axis (parallel planes, offset rho)
    # (1 - (h^2 + rho^2 - r^2) / sqrt((h^2 + rho^2 + r^2)^2 - 4 r^2 rho^2)) / 2
    rhos = [0.0, 0.3, 0.7, 1.5]
    pts, nrm = _receivers([(rho, 0.0) for rho in rhos])
    got = ra.form_factor_reference(pts, nrm, (0.0, 0.0, h), (0.0, r, 0.0), (r, 0.0, 0.0),
                                   disc=True)
    want = [(1 - (h * h + p * p - r * r)
             / math.sqrt((h * h + p * p + r * r) ** 2 - 4 * r * r * p * p)) / 2 for p in rhos]
    assert want[0] == pytest.approx(r * r / (h * h + r * r), rel=1e-14)
    assert torch.allclose(got, torch.tensor(want, dtype=F64), rtol=1e-4, atol=0)
    # an ellipse from non-orthogonal u, v, seen from its centre's axis: with semi-axes
    # a, b (the singular values of [u v]) the form factor is a b / sqrt((h^2+a^2)(h^2+b^2))
    u, v = torch.tensor([0.2, 0.5, 0.0], dtype=F64), torch.tensor([0.6, 0.1, 0.0], dtype=F64)
    a, b = torch.linalg.svdvals(torch.stack([u[:2], v[:2]], 1)).tolist()
    got = ra.form_factor_reference(pts[:1], nrm[:1], (0.0, 0.0, h), u, v, disc=True)
    assert got.item() == pytest.approx(a * b / math.sqrt((h * h + a * a) * (h * h + b * b)),
                                       rel=1e-4)
    assert ra.light_area(u, v, disc=True) == pytest.approx(math.pi * a * b, rel=1e-12)


def _shade(pts, nrm, eye, **kw):
    n = pts.shape[0]
    albedo = torch.tensor([0.9, 0.5, 0.2], dtype=F64).expand(n, 3)
    return ra.area_light_radiance(pts, nrm, eye, albedo, torch.full((n,), 0.3),
                                  torch.full((n,), 0.4), **kw)


@pytest.mark.parametrize("disc", [False, True])
def test_one_sided_and_mirrored_two_sided(disc):
    light = {"position": (0.2, 0.1, 1.0), "u": (0.0, 0.5, 0.0), "v": (0.4, 0.0, 0.0),
             "radiance": (2.0, 1.0, 0.5), "disc": disc, "samples": 24 * 24}  # emits to -z
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.3, 0.1]], dtype=F64)
    nrm = torch.tensor([[0.0, 0.0, 1.0], [0.3, 0.2, 1.0]], dtype=F64)
    eye = torch.tensor([-1.0, 0.5, 0.2], dtype=F64)
    front = _shade(pts, nrm, eye, **light)
    assert bool((front > 0).all())
    # mirror everything through the light's plane z = 1: the light is the same set
    mirror = torch.tensor([1.0, 1.0, -1.0], dtype=F64)
    shift = torch.tensor([0.0, 0.0, 2.0], dtype=F64)
    pts_m, nrm_m, eye_m = pts * mirror + shift, nrm * mirror, eye * mirror + shift
    assert bool((_shade(pts_m, nrm_m, eye_m, **light) == 0).all())
    back = _shade(pts_m, nrm_m, eye_m, two_sided=True, **light)
    assert torch.allclose(back, front, rtol=1e-12, atol=0)
    assert torch.equal(_shade(pts, nrm, eye, two_sided=True, **light), front)


def test_small_far_light_is_a_point_light():
    # a 1 cm tilted panel 3 m away: L = f(l) Le A cos_L cos / d^2 (BRDF written out here)
    centre = torch.tensor([1.0, 0.5, 2.7], dtype=F64)
    normal = torch.tensor([-0.3, -0.1, -1.0], dtype=F64)
    normal = normal / normal.norm()
    t1 = torch.linalg.cross(normal, torch.tensor([0.0, 1.0, 0.0], dtype=F64))
    t1 = t1 / t1.norm()
    t2 = torch.linalg.cross(normal, t1)  # t1 x t2 = normal
    u, v = 0.006 * t1, 0.004 * t2
    le = torch.tensor([3.0, 2.0, 1.0], dtype=F64)
    x = torch.tensor([[0.0, 0.0, 0.0]], dtype=F64)
    n = torch.tensor([[0.1, 0.0, 1.0]], dtype=F64)
    eye = torch.tensor([-1.5, 0.2, 2.0], dtype=F64)
    albedo = torch.tensor([[0.8, 0.6, 0.3]], dtype=F64)
    metallic, rough = 0.4, 0.5
    for disc in (False, True):
        got = ra.area_light_radiance(x, n, eye, albedo, torch.tensor([metallic]),
                                     torch.tensor([rough]), position=centre, u=u, v=v,
                                     radiance=le, disc=disc, samples=8 * 8)[0]
        nn = n[0] / n[0].norm()
        d = centre - x[0]
        dist = d.norm()
        l = d / dist
        w = (eye - x[0]) / (eye - x[0]).norm()
        h = (l + w) / (l + w).norm()
        a = rough**2
        f0 = 0.04 * (1 - metallic) + albedo[0] * metallic
        fres = f0 + (1 - f0) * (1 - w @ h) ** 5
        f = (1 - metallic) * albedo[0] / math.pi + walter_ggx(nn @ h, a) * heitz_v(
            nn @ w, nn @ l, a) * fres
        area = ra.light_area(u, v, disc)
        want = f * le * area * (-(normal @ l)) * (nn @ l) / dist**2
        assert torch.allclose(got, want, rtol=2e-4, atol=0), (disc, got, want)


def test_lambert_part_is_albedo_times_form_factor():
    # metallic 0: the radiance is affine in the albedo, the albedo part exactly
    # albedo * Le * (form factor) (plain Lambert, no (1 - F) factor), checked in closed form
    xy = [(0.0, 0.0), (0.4, 0.3), (1.1, -0.2)]
    pts, nrm = _receivers(xy)
    light = {"position": (0.0, 0.0, 0.9), "u": (0.0, 0.5, 0.0), "v": (0.5, 0.0, 0.0),
             "radiance": (1.5, 1.0, 0.5)}
    eye = (0.3, -2.0, 1.5)
    m, r = torch.zeros(3), torch.full((3,), 0.6)
    albedo = torch.tensor([[0.9, 0.5, 0.1]], dtype=F64).expand(3, 3)
    diff = (ra.area_light_radiance(pts, nrm, eye, albedo, m, r, **light)
            - ra.area_light_radiance(pts, nrm, eye, torch.zeros(3, 3), m, r, **light))
    ff = torch.tensor([_rect_ff(x, y, -0.5, 0.5, -0.5, 0.5, 0.9) for x, y in xy], dtype=F64)
    want = albedo * torch.tensor(light["radiance"], dtype=F64) * ff[:, None]
    assert torch.allclose(diff, want, rtol=1e-4, atol=0)


def _slab(x0: float, x1: float, z: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Two triangles covering ``[x0, x1] x [-10, 10]`` at height ``z``."""
    pos = torch.tensor([[x0, -10, z], [x1, -10, z], [x1, 10, z], [x0, 10, z]], dtype=F64)
    return pos, torch.tensor([[0, 1, 2], [0, 2, 3]])


def test_occluders():
    # a 2 x 2 light at height 2 over the receiver at the origin; occluders at height 1
    pts, nrm = _receivers([(0.0, 0.0)])
    light = {"position": (0.0, 0.0, 2.0), "u": (0.0, 1.0, 0.0), "v": (1.0, 0.0, 0.0)}
    free = ra.form_factor_reference(pts, nrm, **light)
    assert free.item() == pytest.approx(_rect_ff(0, 0, -1, 1, -1, 1, 2.0), rel=1e-4)
    # a half-plane x > 0 whose edge is above the receiver hides exactly the x > 0 half
    half = ra.form_factor_reference(pts, nrm, **light, casters=_slab(0.0, 10.0, 1.0))
    assert half.item() == pytest.approx(free.item() / 2, rel=1e-12)
    # edge at x = 0.15: the visible part is x < 0.3 on the light (a cell boundary at k = 80)
    part = ra.form_factor_reference(pts, nrm, **light, casters=_slab(0.15, 10.0, 1.0))
    assert part.item() == pytest.approx(_rect_ff(0, 0, -1, 0.3, -1, 1, 2.0), rel=1e-4)
    assert ra.form_factor_reference(pts, nrm, **light, casters=_slab(-5, 5, 1.0)).item() == 0
    # the light's own triangles among the casters do not shadow it (t_max = d - eps)
    own = _slab(-1.0, 1.0, 2.0)
    own[0][:, 1] = own[0][:, 1].clamp(-1, 1)
    assert ra.form_factor_reference(pts, nrm, **light, casters=own).item() == free.item()
    # the same through the shading entry point, in small chunks: the Lambert part halves
    eye, one, r = (0.5, 0.3, 3.0), torch.ones(1, 3), torch.ones(1)
    kw = {"radiance": (1.0, 1.0, 1.0), "samples": 16 * 16, **light}
    lit = ra.area_light_radiance(pts, nrm, eye, one, 0 * r, r, **kw)
    dark = ra.area_light_radiance(pts, nrm, eye, 0 * one, 0 * r, r, **kw)
    cast = _slab(0.0, 10.0, 1.0)
    lit_s = ra.area_light_radiance(pts, nrm, eye, one, 0 * r, r, casters=cast, max_rays=100,
                                   **kw)
    dark_s = ra.area_light_radiance(pts, nrm, eye, 0 * one, 0 * r, r, casters=cast, **kw)
    assert torch.allclose(lit_s - dark_s, (lit - dark) / 2, rtol=1e-12, atol=0)


def test_chunks_do_not_change_the_result():
    gen = torch.Generator().manual_seed(5)
    pts = torch.rand(7, 3, generator=gen, dtype=F64) * torch.tensor([2.0, 2.0, 0.0], dtype=F64)
    nrm = torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand(7, 3)
    kw = {"position": (0.5, 0.5, 1.0), "u": (0.3, 0.0, 0.0), "v": (0.0, -0.2, 0.0),
          "radiance": (1.0, 1.0, 1.0), "samples": 10 * 10, "disc": True,
          "casters": _slab(0.7, 3.0, 0.5)}
    args = (pts, nrm, (0.0, -1.0, 2.0), torch.rand(7, 3, generator=gen),
            torch.rand(7, generator=gen), torch.rand(7, generator=gen))
    big = ra.area_light_radiance(*args, **kw)
    small = ra.area_light_radiance(*args, max_rays=150, **kw)
    assert torch.allclose(big, small, rtol=1e-13, atol=1e-300)
    assert big.dtype == F64 and big.shape == (7, 3) and bool((big[:, 0] > 0).any())


def test_convergence_at_roughness_0_3():
    # a glossy metal near its highlight (the first two receivers see it at the light's edge,
    # the worst case of a 11 x 6 grid): 40^2 vs the default 80^2 samples (measured: 3.7e-4
    # rectangle, 6.1e-4 disc)
    xy = [(-0.25, 0.4), (0.0, 0.4), (0.4, 0.0), (1.0, 0.1)]
    pts, nrm = _receivers(xy)
    kw = {"position": (1.0, 0.0, 1.5), "u": (0.5, 0.0, 0.0), "v": (0.0, -0.5, 0.0),
          "radiance": (1.0, 1.0, 1.0)}
    n = len(xy)
    args = (pts, nrm, (-2.0, 0.0, 3.0), torch.full((n, 3), 0.7), torch.ones(n),
            torch.full((n,), 0.3))
    for disc in (False, True):
        coarse = ra.area_light_radiance(*args, samples=40 * 40, disc=disc, **kw)
        fine = ra.area_light_radiance(*args, disc=disc, **kw)
        assert torch.allclose(coarse, fine, rtol=1e-3, atol=0), (disc, coarse / fine - 1)


@pytest.mark.slow
def test_default_samples_accuracy_at_roughness_0_2():
    """The documented accuracy of the default samples: ~1e-3 relative at roughness 0.2 for
    a light ~30 deg across (measured max over the receivers brighter than 10 % of the
    brightest: 9.3e-4 rectangle, 1.2e-3 disc, against 320^2 samples)."""
    xs, ys = torch.linspace(-0.5, 2.0, 11).tolist(), torch.linspace(-0.2, 0.8, 6).tolist()
    xy = [(x, y) for x in xs for y in ys]
    pts, nrm = _receivers(xy)
    kw = {"position": (1.0, 0.0, 1.5), "u": (0.5, 0.0, 0.0), "v": (0.0, -0.5, 0.0),
          "radiance": (1.0, 1.0, 1.0)}
    n = len(xy)
    args = (pts, nrm, (-2.0, 0.0, 3.0), torch.full((n, 3), 0.7), torch.ones(n),
            torch.full((n,), 0.2))
    for disc in (False, True):
        ref = ra.area_light_radiance(*args, samples=320 * 320, disc=disc, **kw)[:, 0]
        got = ra.area_light_radiance(*args, disc=disc, **kw)[:, 0]
        sel = ref > 0.1 * ref.max()
        assert float(((got - ref).abs() / ref)[sel].max()) < 1.5e-3


def test_reference_is_independent_of_the_engine():
    tree = ast.parse(Path(ra.__file__).read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            names.add(node.module or "")
    allowed = {"__future__", "math", "collections.abc", "torch",
               "torchraster.testing.raytrace", "torchraster.testing.reference_brdf"}
    assert names <= allowed, names - allowed
