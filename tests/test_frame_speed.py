"""The full-frame fast paths (issue 10, items 3-5) agree with what they replace.

* :class:`~torchraster.mip_atlas.MipAtlas` (all levels of stacked same-size textures in one
  padded image, one ``grid_sample`` a lookup) equals ``sample_texture(filter="trilinear")``
  of each texture (float64), in values and gradients, for every address mode, odd sizes and
  levels of detail beyond both ends; the G-buffer pass samples materials through it.
* shadow maps are reused across calls by content (:class:`ShadowMapCache`): a second call
  renders nothing, equal views of a batch are rendered once, an in-place edit of the
  casters renders anew, and the image is bit for bit the uncached one;
* the padded PCF lookup equals the four-fetch one bit for bit (taps outside the map, empty
  texels);
* the chunked irradiance map never allocates more than its chunk (a 64-row map of a
  512-row source, which needed 17 GB in one product, runs in bounded memory).
"""

from __future__ import annotations

import pytest
import torch

import torchraster as tr
from torchraster.gbuffer import MipCache, geometry_pass
from torchraster.mesh import transform_points
from torchraster.mip_atlas import MipAtlas
from torchraster.raster import interpolate_with_derivatives, rasterize
from torchraster.shading import ibl
from torchraster.shading.shadows import ShadowSettings, _pcf, _pcf_padded
from torchraster.testing import raytrace as rt
from torchraster.texture import sample_texture

F64 = torch.float64


def _lookups(n: int, seed: int, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    uv = torch.rand(2, n, generator=g, dtype=dtype) * 3 - 1  # outside [0, 1]: addressing
    # derivatives spanning lod < 0 (clamped to level 0) to beyond the last level
    scale = 2.0 ** (torch.rand(1, n, generator=g, dtype=dtype) * 16 - 10)
    ddx = torch.randn(2, n, generator=g, dtype=dtype) * scale
    ddy = torch.randn(2, n, generator=g, dtype=dtype) * scale
    return uv, ddx, ddy


@pytest.mark.parametrize("address", ["wrap", "clamp", "mirror"])
@pytest.mark.parametrize("size", [(13, 7), (16, 16), (1, 5)])
def test_mip_atlas_equals_trilinear_sampling(address, size) -> None:
    g = torch.Generator().manual_seed(1)
    textures = [torch.rand(c, *size, generator=g, dtype=F64) for c in (3, 1, 2)]
    atlas = MipAtlas(textures, address=address)
    uv, ddx, ddy = _lookups(500, 2)
    got = atlas.sample(uv, ddx, ddy).split(atlas.channels)
    for tex, val in zip(textures, got, strict=True):
        ref = sample_texture(tex[None], uv[None, :, None], filter="trilinear", address=address,
                             duv_dx=ddx[None, :, None], duv_dy=ddy[None, :, None])[0, :, 0]
        torch.testing.assert_close(val, ref, rtol=0, atol=1e-12)


def test_mip_atlas_gradients() -> None:
    g = torch.Generator().manual_seed(3)
    tex = torch.rand(2, 6, 5, generator=g, dtype=F64, requires_grad=True)
    uv, ddx, ddy = _lookups(7, 4)
    uv = (uv * 0.3 + 0.4).requires_grad_()  # away from wrap seams (derivative jumps)
    ddx, ddy = (ddx * 0.1).requires_grad_(), (ddy * 0.1).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda t, u, dx, dy: MipAtlas([t]).sample(u, dx, dy), (tex, uv, ddx, ddy))


def test_geometry_pass_samples_materials_through_the_atlas() -> None:
    """Albedo / emissive / AO of a textured quad at a grazing angle (many levels) equal
    sample_texture of each map at the interpolated UVs and their derivatives."""
    g = torch.Generator().manual_seed(5)
    pos = torch.tensor([[-1.0, 0.0, -6.0], [1.0, 0.0, -6.0], [1.0, 0.0, 1.0], [-1.0, 0.0, 1.0]],
                       dtype=F64)
    faces = torch.tensor([[0, 2, 1], [0, 3, 2]])
    uvs = torch.tensor([[0.0, 0.0], [3.0, 0.0], [3.0, 9.0], [0.0, 9.0]], dtype=F64)
    maps = {"base_color": torch.rand(4, 32, 32, generator=g, dtype=F64),
            "emissive": torch.rand(3, 32, 32, generator=g, dtype=F64),
            "occlusion": torch.rand(1, 32, 32, generator=g, dtype=F64),
            "metallic_roughness": torch.rand(3, 16, 8, generator=g, dtype=F64)}  # other size
    mat = tr.Material(emissive_factor=(1.0, 1.0, 1.0),
                      **{k + "_texture": v for k, v in maps.items()})
    view = tr.camera.look_at([0.0, 0.6, 2.0], [0.0, 0.0, -2.0]).to(F64)
    proj = tr.camera.perspective(60.0, 1.0, 0.1).to(F64)
    clip = transform_points(pos, proj @ view)
    frags = rasterize(clip, faces, (24, 24), derivatives=True)
    cache = MipCache()
    gb = geometry_pass(frags, {"albedo", "alpha", "emissive", "ao", "roughness", "metallic",
                               "mask"}, positions=pos, view=view, uvs=uvs,
                       materials=[mat], mip_cache=cache)
    uv, ddx, ddy = interpolate_with_derivatives(uvs[None], frags, faces)
    mask = gb.mask > 0
    assert int(mask.sum()) > 100

    def ref(slot):
        return sample_texture(mat.texture(slot, dtype=F64)[None], uv, filter="trilinear",
                              duv_dx=ddx, duv_dy=ddy) * mask

    base, mr = ref("base_color"), ref("metallic_roughness")
    for got, want in ((gb.albedo, base[:, :3]), (gb.alpha, base[:, 3:]),
                      (gb.emissive, ref("emissive")), (gb.ao, ref("occlusion")),
                      (gb.roughness, mr[:, 1:2]), (gb.metallic, mr[:, 2:3])):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    assert len(cache) == 2  # one atlas per texture size, kept for the next frame


def _shadow_scene(batch: int):
    sphere = rt.icosphere(0.5, (0.0, 0.5, 0.0))
    ground = torch.tensor([[-2.0, 0.0, -2.0], [2.0, 0.0, -2.0], [2.0, 0.0, 2.0],
                           [-2.0, 0.0, 2.0]])
    pos = torch.cat([sphere[0].float(), ground])
    faces = torch.cat([sphere[1], torch.tensor([[0, 2, 1], [0, 3, 2]]) + sphere[0].shape[0]])
    scene = tr.RenderScene(pos, faces, materials=[tr.Material(roughness_factor=0.7)])
    lights = rt.make_lights("directional", ShadowSettings(map_size=64))
    eyes = [[0.0, 2.5, 4.0], [3.0, 2.0, 1.0], [-2.0, 3.0, 2.0], [0.5, 1.5, -3.0]][:batch]
    view = torch.cat([tr.camera.look_at(e, [0.0, 0.3, 0.0]) for e in eyes])
    return scene, lights, view, tr.camera.perspective(45.0, 1.0, 0.1)


def test_shadow_maps_are_cached_by_content() -> None:
    scene, lights, view, proj = _shadow_scene(4)
    plain = tr.Renderer(32)
    plain.shadow_cache = None
    cached = tr.Renderer(32)
    with torch.no_grad():
        want = plain(scene, view, proj, lights).image
        first = cached(scene, view, proj, lights).image
        # the sun's map is fitted to the casters: one render for the 4 cameras
        assert cached.shadow_cache.renders == 1
        second = cached(scene, view[:2], proj, lights).image
        assert cached.shadow_cache.renders == 1  # nothing new: another camera
    assert torch.equal(first, want) and torch.equal(second, want[:2])
    assert float((want[0] - plain.__class__(32, shadows=False)(scene, view[:1], proj,
                                                               lights).image[0]).abs().max()) > 0
    scene.positions[-4:, 1] -= 0.2  # the ground moves (in place): new maps
    with torch.no_grad():
        moved = cached(scene, view, proj, lights).image
        assert cached.shadow_cache.renders == 2
        torch.testing.assert_close(moved, plain(scene, view, proj, lights).image, rtol=0,
                                   atol=0)


def test_padded_pcf_equals_four_fetches() -> None:
    g = torch.Generator().manual_seed(7)
    size, n = 16, 400
    maps = torch.rand(3, size * size, generator=g, dtype=F64)
    maps[:, ::5] = float("inf")  # texels where nothing was drawn
    sel = torch.randint(0, 3, (n, 2), generator=g)
    tx = torch.rand(n, 2, 4, generator=g, dtype=F64) * (size + 8) - 4  # some outside
    ty = torch.rand(n, 2, 4, generator=g, dtype=F64) * (size + 8) - 4
    tx[:5] = 1e9
    ty[5:10] = -1e9
    z = torch.rand(n, 2, 4, generator=g, dtype=F64)
    assert torch.equal(_pcf_padded(maps, sel, tx, ty, z, size), _pcf(maps, sel, tx, ty, z, size))


def test_irradiance_map_memory_is_bounded(monkeypatch) -> None:
    """The largest single allocation of the chunked quadrature stays at the chunk's size
    (one product of an 8 x 16 map from a 32 x 64 source would be 128 x 2048 weights)."""
    monkeypatch.setattr(ibl, "QUADRATURE_CHUNK", 2**14)
    env = torch.rand(1, 3, 32, 64)
    with torch.profiler.profile(profile_memory=True) as prof:
        out = ibl.irradiance_map(env, height=8, source_height=None)
    biggest = max(e.cpu_memory_usage for e in prof.events())
    assert biggest <= 2**14 * 4 + 32 * 64 * 4 * 4, biggest  # chunk + a few source-sized
    torch.testing.assert_close(out, ibl.irradiance_map(env.double(), height=8,
                                                       source_height=None).float(),
                               rtol=1e-4, atol=1e-4)
