"""Texture sampling, mip pyramids, lat-long and cube lookups.

References are independent: grid_sample on the unpadded texture, hand-computed texel
values, analytic directions, a supersampled checkerboard, and float64 gradcheck.
"""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from torchraster.texture import (
    CUBE_FACES,
    MipTexture,
    build_mip_pyramid,
    compute_lod,
    cube_directions,
    cube_uv,
    latlong_directions,
    latlong_solid_angles,
    latlong_to_cube,
    latlong_uv,
    mip_sizes,
    sample_cube,
    sample_latlong,
    sample_texture,
)

D64 = torch.float64


def _ref_grid_sample(tex: torch.Tensor, uv: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """The documented UV convention written directly with grid_sample (x = 2u-1, y = 1-2v)."""
    grid = torch.stack((2 * uv[:, 0] - 1, 1 - 2 * uv[:, 1]), -1)
    return F.grid_sample(tex, grid, mode=mode, padding_mode="border", align_corners=False)


# ------------------------------------------------------------------------ basic sampling


@pytest.mark.parametrize("address", ["wrap", "clamp", "mirror"])
@pytest.mark.parametrize("mode", ["nearest", "bilinear"])
def test_inside_unit_square_matches_grid_sample(address: str, mode: str) -> None:
    tex = torch.rand(2, 3, 5, 7, dtype=D64)  # non-power-of-two
    uv = torch.rand(2, 2, 4, 6, dtype=D64) * 0.8 + 0.1
    out = sample_texture(tex, uv, filter=mode, address=address)
    assert out.shape == (2, 3, 4, 6)
    torch.testing.assert_close(out, _ref_grid_sample(tex, uv, mode))


def test_uv_convention_origin_bottom_left() -> None:
    tex = torch.zeros(1, 1, 4, 4, dtype=D64)
    tex[0, 0, 3, 0] = 1.0  # bottom-left texel (last row, first column)
    tex[0, 0, 0, 3] = 2.0  # top-right texel
    uv = torch.tensor([[0.125, 0.125], [0.875, 0.875]], dtype=D64).T.reshape(1, 2, 1, 2)
    out = sample_texture(tex, uv, filter="nearest")
    assert out.flatten().tolist() == [1.0, 2.0]


def test_wrap_mirror_clamp_outside() -> None:
    tex = torch.rand(1, 2, 6, 5, dtype=D64)
    uv = torch.rand(1, 2, 3, 3, dtype=D64) * 0.8 + 0.1
    inside = _ref_grid_sample(tex, uv)
    # wrap: shifting by integers changes nothing
    torch.testing.assert_close(sample_texture(tex, uv + torch.tensor([3.0, -2.0], dtype=D64)
                                              .view(1, 2, 1, 1), address="wrap"), inside)
    # mirror: u -> 2 - u and v -> -v sample the same texels
    mirrored = torch.stack((2 - uv[:, 0], -uv[:, 1]), 1)
    torch.testing.assert_close(sample_texture(tex, mirrored, address="mirror"), inside)
    # clamp: far outside = edge texel
    far = torch.tensor([[5.0], [-4.0]], dtype=D64).view(1, 2, 1, 1)
    torch.testing.assert_close(sample_texture(tex, far, address="clamp")[0, :, 0, 0],
                               tex[0, :, -1, -1])
    # per-axis address: wrap in u, clamp in v
    mixed = sample_texture(tex, uv + torch.tensor([1.0, 0.0], dtype=D64).view(1, 2, 1, 1),
                           address=("wrap", "clamp"))
    torch.testing.assert_close(mixed, inside)


def test_wrap_seam_blends_first_and_last_column() -> None:
    tex = torch.rand(1, 3, 4, 6, dtype=D64)
    uv = torch.tensor([0.0, 1 - 1.5 / 4], dtype=D64).view(1, 2, 1, 1)  # row 1 centre
    out = sample_texture(tex, uv, address="wrap")[0, :, 0, 0]
    torch.testing.assert_close(out, 0.5 * (tex[0, :, 1, 0] + tex[0, :, 1, -1]))
    out_c = sample_texture(tex, uv, address="clamp")[0, :, 0, 0]
    torch.testing.assert_close(out_c, tex[0, :, 1, 0])


def test_shared_texture_batch_one() -> None:
    tex = torch.rand(1, 3, 8, 8, dtype=D64)
    uv = torch.rand(3, 2, 2, 5, dtype=D64)
    out = sample_texture(tex, uv)
    ref = sample_texture(tex.expand(3, -1, -1, -1), uv)
    torch.testing.assert_close(out, ref)


# -------------------------------------------------------------------------------- mips


def test_mip_sizes_npot() -> None:
    assert mip_sizes(5, 12) == [(5, 12), (2, 6), (1, 3), (1, 1)]
    assert mip_sizes(1, 1) == [(1, 1)]
    levels = build_mip_pyramid(torch.rand(2, 3, 6, 10))
    assert [tuple(x.shape[-2:]) for x in levels] == mip_sizes(6, 10)


def test_box_pyramid_values() -> None:
    tex = torch.arange(16, dtype=D64).view(1, 1, 4, 4)
    lv = build_mip_pyramid(tex)
    torch.testing.assert_close(lv[1][0, 0], torch.tensor([[2.5, 4.5], [10.5, 12.5]], dtype=D64))
    torch.testing.assert_close(lv[2][0, 0, 0, 0], tex.mean())
    g = build_mip_pyramid(torch.rand(1, 3, 16, 24), pyramid="gaussian")
    assert [tuple(x.shape[-2:]) for x in g] == mip_sizes(16, 24)


def test_compute_lod_matches_opengl_formula() -> None:
    dx = torch.tensor([0.01, 0.0], dtype=D64).view(1, 2, 1, 1)
    dy = torch.tensor([0.0, 0.03], dtype=D64).view(1, 2, 1, 1)
    lod = compute_lod(dx, dy, (64, 256), lod_bias=0.5)  # rho = max(2.56, 1.92)
    assert abs(float(lod) - (math.log2(2.56) + 0.5)) < 1e-12
    zero = compute_lod(torch.zeros(1, 2, 1, 1), torch.zeros(1, 2, 1, 1), (8, 8))
    assert bool(torch.isfinite(zero).all())


@pytest.mark.parametrize("level", [0, 1, 2, 3])
def test_trilinear_integer_lod_equals_bilinear_on_level(level: int) -> None:
    tex = torch.rand(1, 3, 16, 24, dtype=D64)
    uv = torch.rand(1, 2, 5, 5, dtype=D64) * 3 - 1
    d = 2.0**level / 24  # exactly `level` texel-doublings along u
    dx = torch.zeros_like(uv)
    dx[:, 0] = d
    out = sample_texture(tex, uv, filter="trilinear", duv_dx=dx, duv_dy=torch.zeros_like(uv))
    ref = sample_texture(build_mip_pyramid(tex)[level], uv, filter="bilinear")
    torch.testing.assert_close(out, ref)


def test_trilinear_blends_levels_and_clamps() -> None:
    tex = torch.rand(1, 2, 8, 8, dtype=D64)
    lv = build_mip_pyramid(tex)
    uv = torch.rand(1, 2, 3, 3, dtype=D64)
    lod = torch.full((1, 1, 3, 3), 1.25, dtype=D64)
    out = sample_texture(tex, uv, filter="trilinear", lod=lod)
    ref = 0.75 * sample_texture(lv[1], uv) + 0.25 * sample_texture(lv[2], uv)
    torch.testing.assert_close(out, ref)
    top = sample_texture(tex, uv, filter="trilinear", lod=lod + 100)
    torch.testing.assert_close(top, tex.mean((2, 3), keepdim=True).expand_as(top))


def test_mip_texture_reuses_pyramid() -> None:
    tex = torch.rand(2, 3, 12, 20, dtype=D64)
    mt = MipTexture(tex, address="mirror")
    assert mt.num_levels == len(mip_sizes(12, 20))
    uv = torch.rand(2, 2, 4, 4, dtype=D64)
    dx, dy = torch.rand_like(uv) * 0.2, torch.rand_like(uv) * 0.2
    ref = sample_texture(tex, uv, filter="trilinear", address="mirror", duv_dx=dx, duv_dy=dy)
    torch.testing.assert_close(mt.sample(uv, dx, dy), ref)
    torch.testing.assert_close(mt.sample(uv, dx, dy, lod_bias=-30.0), sample_texture(
        tex, uv, address="mirror"))


# ------------------------------------------------------- steep plane (filter quality)


def _plane_uv(h: int, w: int, tilt_deg: float = 60.0, jitter: torch.Tensor | None = None):
    """Camera 1 above the plane y=0, pitched (90 - tilt) degrees below the horizon (50 deg
    vertical fov, so the top row looks 5 deg down at tilt 60: a steep, minified plane);
    uv = (x, z) of the ray hit / 4. Returns uv and analytic d(uv)/dx, d(uv)/dy per pixel.

    Pixel (i, j) + offset (a, b) -> camera ray (X, Y, -1) with X = (2 (j + a) / w - 1) f,
    Y = (1 - 2 (i + b) / h) f; rotated by the pitch p: d = (X, Y c - s, -Y s - c).
    Hit t = 1 / -d_y, x = X / -d_y, z = (-Y s - c) / -d_y. Derivatives by the quotient rule.
    """
    f = math.tan(math.radians(25))
    p = math.radians(90 - tilt_deg)  # pitch down from the horizon
    c, s = math.cos(p), math.sin(p)
    i = torch.arange(h, dtype=D64).view(h, 1) + 0.5
    j = torch.arange(w, dtype=D64).view(1, w) + 0.5
    if jitter is not None:
        i = i + jitter[0]
        j = j + jitter[1]
    X = (2 * j / w - 1) * f + 0 * i
    Y = (1 - 2 * i / h) * f + 0 * j
    ny = -(Y * c - s)  # -d_y > 0 for rays going down
    dz = -Y * s - c
    x, z = X / ny, dz / ny
    dX_dj, dY_di = 2 * f / w, -2 * f / h
    # d/dj: only X changes; d/di: Y changes (ny' = -c Y', dz' = -s Y')
    dx_dj, dz_dj = dX_dj / ny, torch.zeros_like(x)
    dny_di = -c * dY_di
    dx_di = -X * dny_di / ny**2
    dz_di = (-s * dY_di * ny - dz * dny_di) / ny**2
    uv = torch.stack((x, z), 0)[None] / 4
    duv_dx = torch.stack((dx_dj, dz_dj), 0)[None] / 4
    duv_dy = torch.stack((dx_di, dz_di), 0)[None] / 4
    return uv, duv_dx, duv_dy


def _checker(n: int = 128, checks: int = 16) -> torch.Tensor:
    k = torch.arange(n) * checks // n
    return ((k.view(-1, 1) + k.view(1, -1)) % 2).to(D64).view(1, 1, n, n)


def test_plane_derivatives_match_finite_differences() -> None:
    h, w = 12, 16
    uv, dx, dy = _plane_uv(h, w)
    e = 1e-6
    up_j = _plane_uv(h, w, jitter=torch.tensor([0.0, e], dtype=D64))[0]
    up_i = _plane_uv(h, w, jitter=torch.tensor([e, 0.0], dtype=D64))[0]
    torch.testing.assert_close((up_j - uv) / e, dx, rtol=1e-4, atol=1e-7)
    torch.testing.assert_close((up_i - uv) / e, dy, rtol=1e-4, atol=1e-7)


def test_trilinear_beats_bilinear_on_minified_checkerboard() -> None:
    h, w, k = 48, 64, 6
    tex = _checker()
    uv, dx, dy = _plane_uv(h, w)
    ref = torch.zeros(1, 1, h, w, dtype=D64)
    for a in range(k):
        for b in range(k):
            jit = torch.tensor([(a + 0.5) / k - 0.5, (b + 0.5) / k - 0.5], dtype=D64)
            ref += sample_texture(tex, _plane_uv(h, w, jitter=jit)[0], filter="nearest")
    ref /= k * k
    err = {
        m: float((sample_texture(tex, uv, filter=m, duv_dx=dx, duv_dy=dy) - ref).abs().mean())
        for m in ("nearest", "bilinear", "trilinear")
    }
    assert err["trilinear"] < 0.6 * err["bilinear"], err
    assert err["bilinear"] <= err["nearest"] * 1.05, err


# ------------------------------------------------------------------------- gradients


@pytest.mark.parametrize("address", ["wrap", "clamp", "mirror"])
def test_gradcheck_bilinear(address: str) -> None:
    tex = torch.rand(1, 2, 4, 5, dtype=D64, requires_grad=True)
    # keep away from texel centres / integer seams where the kinks are
    uv = (torch.rand(1, 2, 2, 3, dtype=D64) * 2.6 - 1.3).requires_grad_()
    torch.autograd.gradcheck(
        lambda t, c: sample_texture(t, c, filter="bilinear", address=address), (tex, uv)
    )


def test_gradcheck_nearest_texture() -> None:
    tex = torch.rand(1, 2, 4, 5, dtype=D64, requires_grad=True)
    uv = torch.rand(1, 2, 2, 3, dtype=D64)
    torch.autograd.gradcheck(lambda t: sample_texture(t, uv, filter="nearest"), (tex,))


def test_gradcheck_trilinear() -> None:
    tex = torch.rand(1, 2, 8, 6, dtype=D64, requires_grad=True)
    uv = torch.rand(1, 2, 2, 3, dtype=D64).requires_grad_()
    dx = (torch.rand(1, 2, 2, 3, dtype=D64) * 0.3 + 0.05).requires_grad_()
    dy = (torch.rand(1, 2, 2, 3, dtype=D64) * 0.1).requires_grad_()
    torch.autograd.gradcheck(
        lambda t, c, a, b: sample_texture(t, c, filter="trilinear", duv_dx=a, duv_dy=b),
        (tex, uv, dx, dy),
    )


def test_gradients_finite_for_degenerate_derivatives() -> None:
    tex = torch.rand(1, 3, 8, 8, requires_grad=True)
    uv = torch.rand(1, 2, 3, 3, requires_grad=True)
    dx = torch.zeros(1, 2, 3, 3, requires_grad=True)
    dy = torch.full((1, 2, 3, 3), 1e6, requires_grad=True)
    out = sample_texture(tex, uv, filter="trilinear", duv_dx=dx, duv_dy=dy)
    out.sum().backward()
    for g in (tex.grad, uv.grad, dx.grad, dy.grad):
        assert g is not None and bool(torch.isfinite(g).all())


# ------------------------------------------------------------------- lat-long and cube


def test_latlong_layout() -> None:
    d = torch.tensor([[0, 0, -1], [1, 0, 0], [0, 0, 1], [0, 1, 0], [0, -2, 0]], dtype=D64)
    uv = latlong_uv(d.T.reshape(1, 3, 1, 5))[0, :, 0].T
    torch.testing.assert_close(uv[:3], torch.tensor([[0.5, 0.5], [0.75, 0.5], [1.0, 0.5]],
                                                    dtype=D64))
    assert float(uv[3, 1]) == 1.0 and float(uv[4, 1]) == 0.0
    assert abs(float(latlong_solid_angles(16, 32).sum()) * 32 - 4 * math.pi) < 1e-5


def test_latlong_texel_centres_roundtrip() -> None:
    env = torch.rand(2, 3, 8, 16, dtype=D64)
    d = latlong_directions(8, 16, dtype=D64).expand(2, -1, -1, -1) * 3.0  # not unit
    torch.testing.assert_close(sample_latlong(env, d), env)


def test_latlong_gradients_at_poles_and_zero() -> None:
    env = torch.rand(1, 3, 8, 16, dtype=D64, requires_grad=True)
    d = torch.tensor([[0, 1, 0], [0, -1, 0], [0, 0, 0], [1e-30, 1, 0], [0.3, 0.2, -0.5]],
                     dtype=D64).T.reshape(1, 3, 1, 5).requires_grad_()
    out = sample_latlong(env, d)
    out.sum().backward()
    assert bool(torch.isfinite(out).all())
    assert bool(torch.isfinite(d.grad).all()) and bool(torch.isfinite(env.grad).all())


def test_gradcheck_latlong() -> None:
    env = torch.rand(1, 2, 6, 12, dtype=D64, requires_grad=True)
    d = torch.randn(1, 3, 2, 3, dtype=D64).requires_grad_()
    torch.autograd.gradcheck(sample_latlong, (env, d))


def test_cube_face_orientation() -> None:
    dirs = cube_directions(2, dtype=D64)
    centre = dirs.mean((2, 3))
    torch.testing.assert_close(centre, torch.tensor(
        [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=D64))
    assert CUBE_FACES[0] == "+X"
    # side faces: row 0 is up (+y); +X face column 0 points towards +z (OpenGL sc = -z)
    assert float(dirs[0, 1, 0, 0]) > 0 and float(dirs[0, 2, 0, 0]) > 0
    assert float(dirs[4, 0, 0, 0]) < 0  # +Z face: column 0 towards -x
    face, st = cube_uv(dirs.permute(1, 0, 2, 3).reshape(1, 3, 12, 2))
    assert face.view(6, 4).tolist() == [[f] * 4 for f in range(6)]
    torch.testing.assert_close(st.view(2, 6, 2, 2)[0, :, 0], torch.tensor([0.25, 0.75],
                                                                          dtype=D64).expand(6, 2))


def test_latlong_to_cube_smooth_env() -> None:
    dirs = latlong_directions(64, 128, dtype=D64)
    env = 0.5 + 0.5 * dirs  # radiance = direction: analytic everywhere
    cube = latlong_to_cube(env, 16)
    assert cube.shape == (1, 6, 3, 16, 16)
    d = torch.randn(1, 3, 20, 20, dtype=D64)
    expect = 0.5 + 0.5 * F.normalize(d, dim=1)
    assert float((sample_cube(cube, d) - expect).abs().max()) < 0.01
    assert float((sample_cube(cube, d, filter="nearest") - expect).abs().max()) < 0.08


def test_gradcheck_cube() -> None:
    cube = torch.rand(1, 6, 2, 3, 3, dtype=D64, requires_grad=True)
    d = torch.randn(1, 3, 2, 3, dtype=D64).requires_grad_()
    torch.autograd.gradcheck(sample_cube, (cube, d))


# ------------------------------------------------------------------------ validation


def test_bad_inputs_raise_clear_errors() -> None:
    tex = torch.rand(1, 3, 4, 4)
    uv = torch.rand(1, 2, 2, 2)
    with pytest.raises(ValueError, match="uv"):
        sample_texture(tex, torch.rand(1, 3, 2, 2))
    with pytest.raises(TypeError, match="texture"):
        sample_texture(tex.numpy(), uv)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="filter"):
        sample_texture(tex, uv, filter="cubic")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="address"):
        sample_texture(tex, uv, address="border")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="duv_dx"):
        sample_texture(tex, uv, filter="trilinear")
    with pytest.raises(ValueError, match="duv_dy"):
        sample_texture(tex, uv, filter="trilinear", duv_dx=uv, duv_dy=uv[:, :1])
    with pytest.raises(ValueError, match="duv_dx.*NaN"):
        sample_texture(tex, uv, filter="trilinear", duv_dx=uv * float("nan"), duv_dy=uv)
    with pytest.raises(ValueError, match="batch"):
        sample_texture(torch.rand(2, 3, 4, 4), torch.rand(3, 2, 2, 2))
    with pytest.raises(ValueError, match="cube"):
        sample_cube(torch.rand(1, 5, 3, 4, 4), torch.rand(1, 3, 2, 2))
    with pytest.raises(ValueError, match="direction"):
        sample_latlong(torch.rand(1, 3, 4, 8), torch.rand(1, 2, 2, 2))
