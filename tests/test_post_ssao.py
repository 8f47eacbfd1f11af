"""SSAO: flat surfaces unoccluded, concave corners occluded, camera conventions, edge cases."""

from __future__ import annotations

import math

import pytest
import torch

from torchraster.post import SSAO, projection_to_intrinsics

N = 48
F_PX = N / 2 / math.tan(math.radians(30))  # 60 degree horizontal field of view
K = torch.tensor([F_PX, F_PX, (N - 1) / 2, (N - 1) / 2], dtype=torch.float64)


def _rays() -> tuple[torch.Tensor, torch.Tensor]:
    """View-space ray slopes (x/d, y/d) of every pixel centre (row 0 at the top, y up)."""
    j = torch.arange(N, dtype=torch.float64).reshape(1, N).expand(N, N)
    i = torch.arange(N, dtype=torch.float64).reshape(N, 1).expand(N, N)
    return (j - K[2]) / F_PX, -(i - K[3]) / F_PX


def _plane(normal: tuple[float, float, float], point: tuple[float, float, float]):
    """Analytic linear depth and normals of the plane through ``point`` with ``normal``."""
    rx, ry = _rays()
    n = torch.tensor(normal, dtype=torch.float64)
    n = n / n.norm()
    # ray P = d (rx, ry, -1): n . P = n . point
    denom = n[0] * rx + n[1] * ry - n[2]
    d = (n @ torch.tensor(point, dtype=torch.float64)) / denom
    d = torch.where(d > 0, d, torch.full_like(d, math.inf))
    return d.reshape(1, 1, N, N), n.reshape(1, 3, 1, 1).expand(1, 3, N, N).clone()


def test_flat_plane_facing_camera_is_unoccluded() -> None:
    d, n = _plane((0, 0, 1), (0, 0, -3))
    ao = SSAO()(d, n, intrinsics=K)
    assert float(ao.min()) > 0.999


def test_tilted_plane_is_unoccluded() -> None:
    d, n = _plane((0, 1, 1), (0, 0, -3))
    ao = SSAO()(d, n, intrinsics=K)
    assert float(ao.min()) > 0.98


def test_concave_corner_is_occluded() -> None:
    floor_d, floor_n = _plane((0, 1, 0), (0, -1, 0))
    wall_d, wall_n = _plane((0, 0, 1), (0, 0, -4))
    is_floor = floor_d < wall_d
    d = torch.where(is_floor, floor_d, wall_d)
    n = torch.where(is_floor, floor_n, wall_n)
    ao = SSAO(radius=1.0)(d, n, intrinsics=K)[0, 0]
    crease_row = int(round(float(K[3]) + F_PX * 1 / 4))  # floor meets wall at y=-1, d=4
    near_crease = ao[crease_row - 2 : crease_row + 2, 8:-8]
    # exactly at a 90 degree crease half the hemisphere is inside the wall (AO 0.5); the
    # pixel centres sit 0.05-0.1 m from it and the 4x4 blur mixes in open pixels: ~0.82
    assert float(near_crease.min()) < 0.85
    assert float(ao[crease_row - 5, 24]) > float(ao[crease_row, 24])  # opens up away from it
    assert float(ao[2:10].min()) > 0.99  # the wall far above the crease is open
    assert float(ao[-4:].min()) > 0.99  # so is the floor close to the camera


def test_projection_matrix_matches_pixel_convention() -> None:
    # OpenGL perspective, 60 degree vertical fov, square image
    t = math.tan(math.radians(30))
    near, far = 0.1, 100.0
    p = torch.tensor([[1 / t, 0, 0, 0], [0, 1 / t, 0, 0],
                      [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)],
                      [0, 0, -1, 0]], dtype=torch.float64)
    # a view-space point projected through P lands on pixel centre (j, i) of the contract
    pt = torch.tensor([0.3, -0.2, -2.0, 1.0], dtype=torch.float64)
    clip = p @ pt
    x_ndc, y_ndc = clip[0] / clip[3], clip[1] / clip[3]
    j, i = (x_ndc + 1) * N / 2 - 0.5, (1 - y_ndc) * N / 2 - 0.5
    fx, fy, cx, cy = projection_to_intrinsics(p, (N, N))[0]
    assert float(fx * pt[0] / 2.0 + cx) == pytest.approx(float(j))
    assert float(cy - fy * pt[1] / 2.0) == pytest.approx(float(i))
    floor_d, floor_n = _plane((0, 1, 0), (0, -1, 0))
    wall_d, wall_n = _plane((0, 0, 1), (0, 0, -4))
    sel = floor_d < wall_d
    d, n = torch.where(sel, floor_d, wall_d), torch.where(sel, floor_n, wall_n)
    torch.testing.assert_close(SSAO()(d, n, projection=p), SSAO()(d, n, intrinsics=K))


def test_empty_pixels_zero_normals_and_range() -> None:
    d = torch.rand(2, 1, 16, 16, dtype=torch.float64) * 5 + 0.5
    d[:, :, :4] = math.inf
    d[:, :, 4, :3] = 0.0
    n = torch.randn(2, 3, 16, 16, dtype=torch.float64)
    n[:, :, 5, 5] = 0.0
    ao = SSAO(samples=8, blur=False)(d, n, intrinsics=torch.tensor([20.0, 20.0, 7.5, 7.5]))
    assert bool(torch.isfinite(ao).all()) and float(ao.min()) >= 0 and float(ao.max()) <= 1
    assert float(ao[:, :, :4].min()) == 1.0


def test_disabled_and_bad_args() -> None:
    d, n = torch.ones(1, 1, 4, 4), torch.zeros(1, 3, 4, 4)
    assert torch.equal(SSAO(enabled=False)(d, n), torch.ones(1, 1, 4, 4))
    with pytest.raises(ValueError, match="projection, intrinsics"):
        SSAO()(d, n)
    with pytest.raises(ValueError, match="intrinsics"):
        SSAO()(d, n, intrinsics=torch.ones(3))
    with pytest.raises(ValueError, match="normals"):
        SSAO()(d, torch.zeros(1, 3, 4, 5), intrinsics=torch.ones(4))
    with pytest.raises(ValueError, match="samples"):
        SSAO(samples=0)


def test_row_bands_equal_the_whole_frame(monkeypatch) -> None:
    # ssao evaluates its samples over bands of rows of SSAO_BAND_ELEMENTS pixel-samples
    # (cache-sized; every sample still reads the whole depth image): bands of one row, a
    # batch of 2 with per-item intrinsics and empty pixels, give the whole frame's AO and
    # gradients (up to the last bit of vectorised against scalar loops)
    import sys

    mod = sys.modules["torchraster.post.ssao"]
    g = torch.Generator().manual_seed(4)
    depth = torch.rand(2, 1, 23, 19, generator=g, dtype=torch.float64) * 2 + 1
    depth[:, :, :3] = float("inf")
    k = torch.tensor([[40.0, 42.0, 9.0, 11.0], [35.0, 35.0, 9.5, 11.5]], dtype=torch.float64)
    outs = []
    for band in (mod.SSAO_BAND_ELEMENTS, 1):
        monkeypatch.setattr(mod, "SSAO_BAND_ELEMENTS", band)
        normals = torch.randn(2, 3, 23, 19, generator=torch.Generator().manual_seed(5),
                              dtype=torch.float64).requires_grad_()
        ao = SSAO(radius=0.3, samples=8)(depth, normals, intrinsics=k)
        outs.append((ao, *torch.autograd.grad((ao * ao).sum(), normals)))
    assert float(outs[0][0].detach().min()) < 0.9 and float(outs[0][1].abs().max()) > 0
    for a, b in zip(*outs, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)
