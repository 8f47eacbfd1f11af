"""The pre-integrated GGX lobe table (``specular="table"``) against independent sums."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from torchraster.shading.ibl import Environment, shade_ibl
from torchraster.shading.ibl_table import (
    lookup_specular_table,
    specular_table,
    table_atlas,
    table_roughness,
    table_rows,
)
from torchraster.testing.reference_brdf import heitz_v, walter_ggx
from torchraster.texture import latlong_directions, latlong_solid_angles

D64 = torch.float64


def _smooth_env(h: int, w: int, seed: int = 0) -> torch.Tensor:
    """``(1, 3, h, w)`` positive map: a sky gradient plus two soft bright blobs."""
    d = latlong_directions(h, w, dtype=D64)[0]
    g = torch.Generator().manual_seed(seed)
    out = 0.2 + 0.5 * (d[1:2] + 1.0).expand(3, h, w)
    for _ in range(2):
        c = F.normalize(torch.randn(3, generator=g, dtype=D64), dim=0)
        col = 0.5 + torch.rand(3, 1, 1, generator=g, dtype=D64)
        out = out + 6.0 * col * torch.exp(8.0 * ((d * c.view(3, 1, 1)).sum(0) - 1.0))
    return out[None]


def _frame(r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """East and south tangents at unit ``r`` ``(3,)``, written independently of the module:
    e_phi = normalize(r x y), e_theta = r x e_phi."""
    e_phi = F.normalize(torch.linalg.cross(r, torch.tensor([0.0, 1.0, 0.0], dtype=D64)), dim=0)
    return torch.linalg.cross(r, e_phi), e_phi


def _lobe_mean(env: torch.Tensor, n: torch.Tensor, v: torch.Tensor, rough: float
               ) -> torch.Tensor:
    """Brute force over every texel of ``env`` ``(1, 3, h, w)``: sum L D V (n.l) dw / sum
    D V (n.l) dw with the reference GGX / Smith forms -> ``(3,)``."""
    h, w = env.shape[-2:]
    d = latlong_directions(h, w, dtype=D64).reshape(3, -1)
    dw = latlong_solid_angles(h, w, dtype=D64).expand(h, w).reshape(-1)
    a = max(rough, 0.045) ** 2
    nl = n @ d
    nh = (n @ F.normalize(d + v[:, None], dim=0)).clamp(1e-12, 1.0)
    wgt = walter_ggx(nh, a) * heitz_v((n @ v).clamp_min(1e-4), nl.clamp_min(1e-12), a)
    wgt = torch.where(nl > 0, wgt * nl * dw, 0.0)
    return env.reshape(3, -1) @ wgt / wgt.sum()


def _img(x: torch.Tensor) -> torch.Tensor:
    """``(K, C)`` -> ``(1, C, 1, K)``."""
    return x.T.reshape(1, x.shape[1], 1, x.shape[0])


def test_nodes_equal_the_brute_force_sum_of_the_level_grid() -> None:
    # at a node (texel centre, view node, azimuth node, level) a lookup is one entry of
    # the table: the exact sum over the level's grid; the mirrored azimuths (> az / 2) and
    # the normal-incidence node are derived, not computed, so they are checked too
    h = table_rows(table_roughness(2)[0])
    env = _smooth_env(h, 2 * h)  # level 0's own grid: no resampling
    views, az = 4, 6
    vol, blocks = table_atlas(specular_table(env, levels=2, views=views, azimuths=az))
    rough = table_roughness(2)[0]
    dirs = latlong_directions(h, 2 * h, dtype=D64)[0]
    cases = [(7, 11, 0, 0), (20, 3, 1, 1), (30, 90, 2, 4), (45, 50, 1, 5), (3, 0, 2, 3)]
    ns, vs, refs = [], [], []
    for i, m, k, a in cases:
        r = dirs[:, i, m]
        e_t, e_p = _frame(r)
        tv = k * (math.pi / 2) / (views - 1)
        psi = a * 2 * math.pi / az
        n = math.cos(tv) * r + math.sin(tv) * (math.cos(psi) * e_t + math.sin(psi) * e_p)
        v = 2 * math.cos(tv) * n - r
        ns.append(n)
        vs.append(v)
        refs.append(_lobe_mean(env, n, v, rough))
    got = lookup_specular_table(vol, blocks, _img(torch.stack(ns)), _img(torch.stack(vs)),
                                torch.full((1, 1, 1, len(cases)), rough, dtype=D64))
    torch.testing.assert_close(got[0, :, 0].T, torch.stack(refs), rtol=1e-9, atol=0.0)
    # the grazing node: n.v = 0, clamped to 1e-4 as shade_ibl's MIN_N_DOT_V (the lookup's
    # coordinate of n.v = 1e-4 lies 2e-4 of a step off the node)
    r = dirs[:, 25, 40]
    e_t, e_p = _frame(r)
    psi = 2 * 2 * math.pi / az
    n = 1e-4 * r + math.sqrt(1 - 1e-8) * (math.cos(psi) * e_t + math.sin(psi) * e_p)
    v = 2e-4 * n - r
    got = lookup_specular_table(vol, blocks, _img(n[None]), _img(v[None]),
                                torch.full((1, 1, 1, 1), rough, dtype=D64))[0, :, 0, 0]
    torch.testing.assert_close(got, _lobe_mean(env, n, v, rough), rtol=1e-3, atol=0.0)


@pytest.mark.parametrize("rough", [0.35, 0.6, 0.9])
def test_between_nodes_close_to_the_full_brute_force(rough: float) -> None:
    # a smooth map finer than the levels: interpolation and resampling errors together
    env = _smooth_env(96, 192, seed=1)
    g = torch.Generator().manual_seed(2)
    n = F.normalize(torch.randn(48, 3, generator=g, dtype=D64), dim=1)
    v = F.normalize(torch.randn(48, 3, generator=g, dtype=D64), dim=1)
    v = F.normalize(torch.where((n * v).sum(1, keepdim=True) < 0, -v, v) + 0.3 * n, dim=1)
    refs = torch.stack([_lobe_mean(env, a, b, rough) for a, b in zip(n, v, strict=True)])
    e = Environment(env, specular_size=32)
    got = e.specular_table_lookup(_img(n), _img(v), torch.full((1, 1, 1, 48), rough,
                                                                dtype=D64))[0, :, 0].T
    err = float(((got - refs).abs() / refs).mean())
    assert err < 0.01, err


def test_constant_map_is_exact_in_every_dtype() -> None:
    env = Environment(torch.full((1, 3, 8, 16), 2.5), table_levels=3, table_views=3,
                      table_azimuths=4)
    g = torch.Generator().manual_seed(0)
    n = F.normalize(torch.randn(1, 3, 4, 8, generator=g), dim=1)
    v = F.normalize(n + torch.randn(1, 3, 4, 8, generator=g), dim=1)
    rough = torch.rand(1, 1, 4, 8, generator=g)
    for dt in (torch.float32, torch.float16, torch.bfloat16):
        out = env.specular_table_lookup(n.to(dt), v.to(dt), rough.to(dt))
        assert out.dtype == dt
        torch.testing.assert_close(out.float(), torch.full_like(out.float(), 2.5),
                                   rtol=1e-2 if dt != torch.float32 else 1e-5, atol=0.0)


def test_gradcheck_normal_view_roughness() -> None:
    env = _smooth_env(32, 64)
    vol, blocks = table_atlas(specular_table(env, levels=3, views=4, azimuths=6))
    g = torch.Generator().manual_seed(3)
    n = F.normalize(torch.randn(1, 3, 1, 5, generator=g, dtype=D64), dim=1)
    v = F.normalize(n + 0.8 * torch.randn(1, 3, 1, 5, generator=g, dtype=D64), dim=1)
    rough = 0.35 + 0.6 * torch.rand(1, 1, 1, 5, generator=g, dtype=D64)
    args = tuple(t.clone().requires_grad_(True) for t in (n, v, rough))
    assert torch.autograd.gradcheck(lambda a, b, c: lookup_specular_table(vol, blocks, a, b, c),
                                    args, eps=1e-7, atol=1e-5, rtol=1e-3)


def test_gradient_wrt_radiance_is_the_table_of_the_perturbation() -> None:
    # the table is linear in the map: d/de lookup(env + e delta) = lookup(table(delta))
    env = _smooth_env(16, 32).requires_grad_(True)
    delta = torch.rand(1, 3, 16, 32, generator=torch.Generator().manual_seed(4), dtype=D64)
    g = torch.Generator().manual_seed(5)
    n = F.normalize(torch.randn(1, 3, 2, 3, generator=g, dtype=D64), dim=1)
    v = F.normalize(n + torch.randn(1, 3, 2, 3, generator=g, dtype=D64), dim=1)
    rough = torch.full((1, 1, 2, 3), 0.5, dtype=D64)
    knobs = {"levels": 2, "views": 3, "azimuths": 4}
    out = lookup_specular_table(*table_atlas(specular_table(env, **knobs)), n, v, rough)
    (grad,) = torch.autograd.grad(out.sum(), env)
    want = lookup_specular_table(*table_atlas(specular_table(delta, **knobs)), n, v, rough)
    torch.testing.assert_close((grad * delta).sum(), want.sum(), rtol=1e-9, atol=0.0)


def _surface(k: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    n = F.normalize(torch.randn(1, 3, 1, k, generator=g, dtype=D64), dim=1)
    v = F.normalize(n + torch.randn(1, 3, 1, k, generator=g, dtype=D64), dim=1)
    return n, v


def test_shade_ibl_table_is_continuous_across_the_blend_band() -> None:
    env = Environment(_smooth_env(32, 64), specular_size=16, specular_levels=6,
                      table_levels=3, table_views=4, table_azimuths=6)
    n, v = _surface(6, 6)
    one = torch.ones(1, 1, 1, 6, dtype=D64)

    def shade(r: float | torch.Tensor) -> torch.Tensor:
        return shade_ibl(n, v, one.expand(1, 3, 1, 6), one, r * one, None, env)

    for edge in (0.2, 0.3):
        torch.testing.assert_close(shade(edge - 1e-9), shade(edge + 1e-9), rtol=1e-6,
                                   atol=0.0)
    assert torch.equal(shade(0.1), shade_ibl(n, v, one.expand(1, 3, 1, 6), one, 0.1 * one,
                                             None, env, specular="split_sum"))
    rough = torch.tensor([0.1, 0.2, 0.25, 0.3, 0.6, 1.0], dtype=D64).view(1, 1, 1, 6)
    rough.requires_grad_(True)
    (grad,) = torch.autograd.grad(shade(rough).sum(), rough)
    assert torch.isfinite(grad).all() and grad[0, 0, 0, 2] != 0


def test_shade_ibl_table_mask_batch_and_rotation() -> None:
    rad = _smooth_env(32, 64).float()
    yaw = 0.7
    env_r = Environment(rad, yaw=yaw, table_levels=3, table_views=4, table_azimuths=6)
    env_0 = Environment(rad, table_levels=3, table_views=4, table_azimuths=6)
    g = torch.Generator().manual_seed(7)
    n = F.normalize(torch.randn(2, 3, 4, 5, generator=g), dim=1)
    v = F.normalize(n + torch.randn(2, 3, 4, 5, generator=g), dim=1)
    alb = torch.rand(2, 3, 4, 5, generator=g)
    met, rough = torch.rand(2, 1, 4, 5, generator=g), torch.rand(2, 1, 4, 5, generator=g)
    whole = shade_ibl(n, v, alb, met, rough, None, env_r)
    mask = torch.rand(2, 1, 4, 5, generator=g) > 0.4
    masked = shade_ibl(n, v, alb, met, rough, None, env_r, mask=mask.float())
    torch.testing.assert_close(masked, torch.where(mask, whole, 0.0), rtol=1e-5, atol=1e-6)
    c, s = math.cos(yaw), math.sin(yaw)
    rot = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])  # yaw_rotation(yaw)
    to_env = lambda d: torch.einsum("ji,bjhw->bihw", rot, d)  # noqa: E731
    ref = shade_ibl(to_env(n), to_env(v), alb, met, rough, None, env_0)
    torch.testing.assert_close(whole, ref, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("mode", ["split_sum", "fitted", "table"])
def test_pixel_chunks_give_the_same_values(mode: str, monkeypatch) -> None:
    # a masked shade_ibl shades its pixels in chunks of IBL_PIXEL_CHUNK (cache-sized; the
    # table mode nests a second packing below roughness 0.3): chunks of 7 pixels, a whole
    # covered frame included, give the values and gradients of one piece (up to the last
    # bit of vectorised against scalar transcendental functions: a chunk's tail runs the
    # scalar loop)
    from torchraster.shading import ibl

    env = Environment(_smooth_env(32, 64), specular=mode, table_levels=3,
                      table_views=4, table_azimuths=6, sun_threshold=3.0)
    g = torch.Generator().manual_seed(8)

    def rand(c: int, normal: bool = False) -> torch.Tensor:
        return (torch.randn if normal else torch.rand)(2, c, 6, 7, generator=g, dtype=D64)

    n = F.normalize(rand(3, True), dim=1)
    v = F.normalize(n + rand(3, True), dim=1)
    alb, met, ao, rough = rand(3), rand(1), rand(1), rand(1).requires_grad_(True)
    for mask in ((rand(1) > 0.3).to(D64), torch.ones(2, 1, 6, 7, dtype=D64)):
        outs = []
        for chunk in (ibl.IBL_PIXEL_CHUNK, 7):
            monkeypatch.setattr(ibl, "IBL_PIXEL_CHUNK", chunk)
            out = shade_ibl(n, v, alb, met, rough, ao, env, mask=mask)
            outs.append((out, *torch.autograd.grad(out.square().sum(), rough)))
        for a, b in zip(*outs, strict=True):
            torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-13)


def test_poles_and_normal_incidence_are_finite() -> None:
    env = Environment(_smooth_env(32, 64), table_levels=2, table_views=3, table_azimuths=4)
    up = torch.tensor([0.0, 1.0, 0.0], dtype=D64)
    tilt = F.normalize(torch.tensor([1e-9, 1.0, 0.0], dtype=D64), dim=0)
    n = torch.stack((up, up, tilt, -up)).T.reshape(1, 3, 1, 4).clone().requires_grad_(True)
    v = torch.stack((up, tilt, up, -up)).T.reshape(1, 3, 1, 4).clone().requires_grad_(True)
    rough = torch.full((1, 1, 1, 4), 0.5, dtype=D64, requires_grad=True)
    out = env.specular_table_lookup(n, v, rough)
    grads = torch.autograd.grad(out.sum(), (n, v, rough))
    assert torch.isfinite(out).all() and all(torch.isfinite(t).all() for t in grads)


@pytest.mark.parametrize("kw, match", [
    ({"table_azimuths": 3}, "table_azimuths"), ({"table_views": 1}, "table_views"),
    ({"table_levels": 1.5}, "table_levels"), ({"specular": "tables"}, "specular")])
def test_bad_knobs_name_the_argument(kw: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        Environment(torch.ones(3, 8, 16), **kw)


def test_float32_table_matches_float64_at_grazing_views() -> None:
    # at n.v -> 0 the half vector of l near R is (l + v) / |l + v| with l + v -> 0: the
    # build forms |l + v|^2 from l - R, not 2 + 2 v.l (whose float32 cancellation gave up
    # to 98 % errors at the grazing node)
    env = _smooth_env(32, 64)
    knobs = {"levels": 3, "views": 4, "azimuths": 4}
    single = specular_table(env.float(), **knobs)
    double = specular_table(env, **knobs)
    for a, b in zip(single, double, strict=True):
        assert float(((a.double() - b).abs() / b.abs()).max()) < 1e-3


def test_yaml_table_knobs_and_randomized_specular(tmp_path) -> None:
    import torchraster as tr
    from torchraster.config.build import build_environment
    from torchraster.config.variants import scene_variants
    from torchraster.hdr_io import write_hdr

    write_hdr(tmp_path / "sky.hdr", torch.rand(3, 8, 16) + 0.1)
    text = ("cameras: [{orbit: {distance: 3}}]\nrender: {resolution: [8, 8]}\n"
            "scene: {objects: [{primitive: sphere}]}\n%s\n")
    cfg = tr.parse_config(text % "environment: {path: sky.hdr, table_views: 3, "
                          "table_azimuths: 4}", "a.yaml", base_dir=tmp_path)
    env = build_environment(cfg)
    assert env.table_knobs == (8, 3, 4) and env.specular_mode == "table"
    with pytest.raises(tr.ConfigError, match=r"b.yaml:4: environment.table_azimuths: expec"):
        tr.parse_config(text % "environment: {path: sky.hdr, table_azimuths: 3}", "b.yaml",
                        base_dir=tmp_path)
    cfg = tr.parse_config(text % "randomize: {environment: {paths: [sky.hdr], specular: "
                          "split_sum, table_levels: 3}}", "c.yaml", base_dir=tmp_path)
    drawn = scene_variants(cfg)[0].config.environment
    assert drawn.specular == "split_sum" and drawn.table_levels == 3


@pytest.mark.parametrize("mode", ["table", "split_sum", "importance"])
def test_checkpointed_chunks_take_gradients_to_the_environment(mode: str) -> None:
    # Renderer(max_batch=1) checkpoints each chunk; the environment's lazy data (chain, table,
    # irradiance) are built before the chunks, else the recomputation records another graph
    import trimesh

    import torchraster as tr

    ico = trimesh.creation.icosphere(subdivisions=1)
    mesh = tr.Mesh(torch.tensor(ico.vertices, dtype=torch.float32), torch.tensor(ico.faces))
    view = tr.camera.look_at([0.0, 0.4, 3.0], [0.0, 0.0, 0.0]).expand(2, 4, 4)
    proj = tr.camera.perspective(40.0, 1.0, 0.1, 10.0)
    rad = (torch.rand(3, 8, 16, generator=torch.Generator().manual_seed(0)) + 0.1)
    grads = []
    for max_batch in (1, None):
        leaf = rad.clone().requires_grad_(True)
        env = tr.Environment(leaf, specular=mode, table_levels=2, table_views=2,
                             table_azimuths=2, importance_samples=2)
        r = tr.Renderer(16, shading="pbr", raster=tr.RasterSettings(max_batch=max_batch))
        grads.append(torch.autograd.grad(r(mesh, view, proj, None, env).image.sum(), leaf)[0])
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-4, atol=1e-6)
