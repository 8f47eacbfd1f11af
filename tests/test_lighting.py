"""Deferred lighting pass vs closed forms and an independent per-pixel reference."""

from __future__ import annotations

import math

import pytest
import torch

from torchraster.config import lights_from_config
from torchraster.gbuffer import GBuffer
from torchraster.shading import MODELS, Lights, shade
from torchraster.shading.brdf import cook_torrance
from torchraster.shading.lighting import dfg_lut, env_brdf
from torchraster.shading.lights import DirectionalLights
from torchraster.shading.models import Surface
from torchraster.testing.reference_brdf import directional_albedo, heitz_v, walter_ggx

F64 = torch.float64
CAM = (0.0, 0.0, 10.0)


def sphere(h: int = 32, w: int = 32, b: int = 1, dtype: torch.dtype = F64):
    """Unit sphere seen along -z: analytic world positions, normals (B, 3, H, W) and mask."""
    y, x = torch.meshgrid(
        torch.linspace(1, -1, h, dtype=dtype),
        torch.linspace(-1, 1, w, dtype=dtype),
        indexing="ij",
    )
    r2 = x * x + y * y
    mask = r2 < 1
    z = torch.sqrt((1 - r2).clamp_min(0))
    n = torch.where(mask, torch.stack([x, y, z]), torch.zeros(3, h, w, dtype=dtype))
    n = n[None].expand(b, 3, h, w).contiguous()
    return n.clone(), n, mask[None, None].expand(b, 1, h, w).contiguous()


def cam(b: int = 1, dtype: torch.dtype = F64) -> torch.Tensor:
    return torch.tensor([CAM] * b, dtype=dtype)


def lambert(n, v, l, surface):
    return surface.albedo / math.pi * (n * l).sum(-3, keepdim=True).clamp_min(0)


def test_lambert_sphere_matches_closed_form() -> None:
    pos, n, mask = sphere()
    albedo = torch.tensor([0.8, 0.5, 0.2], dtype=F64).view(1, 3, 1, 1).expand(1, 3, 32, 32)
    zero = torch.zeros(1, 1, 32, 32, dtype=F64)
    d = torch.tensor([-1.0, -2.0, -2.0], dtype=F64)
    lights = lights_from_config(
        [
            {
                "type": "directional",
                "direction": d.tolist(),
                "intensity": 3.0,
                "color": [1.0, 0.9, 0.8],
            }
        ],
        dtype=F64,
    )
    out = shade(
        GBuffer(
            position=pos, normal=n, albedo=albedo, metallic=zero, roughness=zero + 0.5, mask=mask
        ),
        camera_position=cam(),
        lights=lights,
        model=lambert,
    )
    l = (-d / d.norm()).view(1, 3, 1, 1)
    e = 3.0 * torch.tensor([1.0, 0.9, 0.8], dtype=F64).view(1, 3, 1, 1)
    ref = albedo / math.pi * e * (n * l).sum(1, keepdim=True).clamp_min(0) * mask
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-14)


def reference_pixel(p, nrm, albedo, metallic, rough, light):
    """Independent Cook-Torrance for one pixel and one light (Walter D, Heitz G2, Schlick)."""
    n = nrm / nrm.norm()
    v = torch.tensor(CAM, dtype=F64) - p
    v = v / v.norm()
    if light["type"] == "directional":
        l = -torch.tensor(light["direction"], dtype=F64)
        l = l / l.norm()
        e = light["intensity"]
    else:
        to = torch.tensor(light["position"], dtype=F64) - p
        d = to.norm()
        l = to / d
        e = light["intensity"] / d**2 * max(0.0, 1 - (d / light.get("range", math.inf)) ** 4) ** 2
        if light["type"] == "spot":
            axis = torch.tensor(light["direction"], dtype=F64)
            cos_a = -(axis / axis.norm()) @ l
            ci, co = math.cos(light["inner_cone_angle"]), math.cos(light["outer_cone_angle"])
            e = e * min(max((cos_a - co) / (ci - co), 0.0), 1.0) ** 2
    nl, nv = (n @ l).item(), (n @ v).item()
    if nl <= 0 or nv <= 0:
        return torch.zeros(3, dtype=F64) if nl <= 0 else None
    h = (v + l) / (v + l).norm()
    a = max(rough, 0.045) ** 2
    dd = walter_ggx(n @ h, a)
    vis = heitz_v(torch.tensor(nv, dtype=F64), torch.tensor(nl, dtype=F64), a)
    f0 = 0.04 * (1 - metallic) + albedo * metallic
    fres = f0 + (1 - f0) * (1 - (v @ h)) ** 5
    f = (1 - metallic) * albedo / math.pi + dd * vis * fres
    return f * nl * e * torch.tensor(light.get("color", [1.0, 1.0, 1.0]), dtype=F64)


LIGHTS = [
    {"type": "directional", "direction": [-1.0, -1.0, -1.0], "intensity": 2.0},
    {
        "type": "directional",
        "direction": [1.0, 0.0, -0.5],
        "intensity": 1.0,
        "color": [0.2, 0.4, 1.0],
    },
    {
        "type": "point",
        "position": [1.5, 1.0, 2.0],
        "intensity": 8.0,
        "range": 4.0,
        "color": [1.0, 0.5, 0.2],
    },
    {"type": "point", "position": [-1.0, 0.0, 1.5], "intensity": 3.0},
    {
        "type": "spot",
        "position": [0.0, 2.5, 1.5],
        "direction": [0.0, -1.0, -0.5],
        "intensity": 20.0,
        "inner_cone_angle": 0.2,
        "outer_cone_angle": 0.6,
    },
]


def test_cook_torrance_sphere_matches_reference() -> None:
    pos, n, mask = sphere(16, 16)
    g = torch.Generator().manual_seed(6)
    albedo = torch.rand(1, 3, 16, 16, generator=g, dtype=F64)
    metallic = torch.rand(1, 1, 16, 16, generator=g, dtype=F64)
    rough = torch.rand(1, 1, 16, 16, generator=g, dtype=F64) * 0.9 + 0.1
    lights = lights_from_config(LIGHTS, dtype=F64)
    out = shade(
        GBuffer(
            position=pos, normal=n, albedo=albedo, metallic=metallic, roughness=rough, mask=mask
        ),
        camera_position=cam(),
        lights=lights,
        multiscatter=False,  # the reference is the single-scattering BRDF (test_energy.py)
    )
    checked = 0
    for i in range(16):
        for j in range(16):
            if not mask[0, 0, i, j]:
                assert (out[0, :, i, j] == 0).all()
                continue
            total = torch.zeros(3, dtype=F64)
            ok = True
            for light in LIGHTS:
                c = reference_pixel(
                    pos[0, :, i, j],
                    n[0, :, i, j],
                    albedo[0, :, i, j],
                    metallic[0, 0, i, j].item(),
                    rough[0, 0, i, j].item(),
                    light,
                )
                if c is None:
                    ok = False  # n.v <= 0: our pass shades it as grazing; skip
                    break
                total += c
            if ok:
                torch.testing.assert_close(out[0, :, i, j], total, rtol=1e-9, atol=1e-12)
                checked += 1
    assert checked > 150


def test_ambient_matches_brute_force_directional_albedo() -> None:
    # Constant ambient radiance c: reflected radiance = c * integral of BRDF cos (exact),
    # here by the reference half-vector quadrature, vs the pass's SH + DFG table.
    c = 0.7
    lights = lights_from_config([{"type": "ambient", "color": [c, c, c]}], dtype=F64)
    thetas = [0.0, 0.6, 1.2]
    for rough, metal, alb in [(0.045, 1.0, 1.0), (0.3, 1.0, 0.9), (0.5, 0.0, 0.8), (1.0, 0.5, 0.5)]:
        n = torch.tensor([[math.sin(t), 0.0, math.cos(t)] for t in thetas], dtype=F64)
        n = n.T.reshape(1, 3, 1, len(thetas))
        pos = torch.zeros_like(n)
        one = torch.ones(1, 1, 1, len(thetas), dtype=F64)
        out = shade(
            GBuffer(
                position=pos,
                normal=n,
                albedo=alb * torch.ones_like(n),
                metallic=metal * one,
                roughness=rough * one,
            ),
            camera_position=cam(),
            lights=lights,
            multiscatter=False,  # single-scattering reference (compensated: test_energy.py)
        )
        for k, t in enumerate(thetas):
            ref = c * directional_albedo(
                lambda n, v, l, r=rough, m=metal, a=alb: cook_torrance(n, v, l, a, m, r),
                t, n_theta=300, n_phi=48)
            assert out[0, 0, 0, k].item() == pytest.approx(ref, rel=0.01), (rough, metal, t)


def test_ao_emissive_mask_and_empty_lights() -> None:
    pos, n, mask = sphere(8, 8)
    albedo = torch.full_like(n, 0.5)
    m = torch.zeros(1, 1, 8, 8, dtype=F64)
    r = m + 0.4
    emissive = torch.full_like(n, 0.25)
    direct = lights_from_config(LIGHTS[:1], dtype=F64)
    both = lights_from_config(LIGHTS[:1] + [{"type": "ambient", "color": [1, 1, 1]}], dtype=F64)
    ao0, ao1 = torch.zeros_like(m), torch.ones_like(m)
    d_only = shade(
        GBuffer(position=pos, normal=n, albedo=albedo, metallic=m, roughness=r, mask=mask),
        camera_position=cam(),
        lights=direct,
    )
    torch.testing.assert_close(
        shade(
            GBuffer(
                position=pos, normal=n, albedo=albedo, metallic=m, roughness=r, ao=ao0, mask=mask
            ),
            camera_position=cam(),
            lights=direct,
        ),
        d_only,
    )
    torch.testing.assert_close(
        shade(
            GBuffer(
                position=pos, normal=n, albedo=albedo, metallic=m, roughness=r, ao=ao0, mask=mask
            ),
            camera_position=cam(),
            lights=both,
        ),
        d_only,
    )
    full = shade(
        GBuffer(position=pos, normal=n, albedo=albedo, metallic=m, roughness=r, ao=ao1, mask=mask),
        camera_position=cam(),
        lights=both,
    )
    half = shade(
        GBuffer(
            position=pos, normal=n, albedo=albedo, metallic=m, roughness=r, ao=ao1 * 0.5, mask=mask
        ),
        camera_position=cam(),
        lights=both,
    )
    torch.testing.assert_close(half - d_only, 0.5 * (full - d_only))
    assert ((full - d_only)[mask.expand_as(full)] > 0).all()
    with_e = shade(
        GBuffer(
            position=pos,
            normal=n,
            albedo=albedo,
            metallic=m,
            roughness=r,
            emissive=emissive,
            mask=mask,
        ),
        camera_position=cam(),
        lights=direct,
    )
    torch.testing.assert_close(with_e, d_only + emissive * mask)
    # no lights at all: only emission; masked pixels stay 0 even if the G-buffer is NaN there
    bad = pos.clone()
    bad[~mask.expand_as(bad)] = math.nan
    out = shade(
        GBuffer(
            position=bad,
            normal=n,
            albedo=albedo,
            metallic=m,
            roughness=r,
            emissive=emissive,
            mask=mask,
        ),
        camera_position=cam(),
        lights=Lights(),
    )
    torch.testing.assert_close(out, emissive * mask)
    empty = DirectionalLights(
        torch.zeros(1, 0, 3, dtype=F64),
        torch.zeros(1, 0, 3, dtype=F64),
        torch.zeros(1, 0, dtype=F64),
    )
    out = shade(
        GBuffer(position=pos, normal=n, albedo=albedo, metallic=m, roughness=r, mask=mask),
        camera_position=cam(),
        lights=Lights(directional=empty),
    )
    assert (out == 0).all()


def test_ibl_hook() -> None:
    pos, n, mask = sphere(8, 8)
    albedo, m = torch.full_like(n, 0.5), torch.zeros(1, 1, 8, 8, dtype=F64)
    seen = {}

    def ibl(s):
        seen["unit"] = bool(
            ((s.n.norm(dim=1) - 1).abs()[mask[:, 0]] < 1e-12).all()
            and ((s.v.norm(dim=1) - 1).abs() < 1e-12).all()
        )
        seen["by name"] = torch.equal(s.roughness, (m + 0.5) * mask) and torch.equal(
            s.metallic, m) and torch.equal(s.f0, torch.full_like(n, 0.04))
        torch.testing.assert_close(s.n_dot_v, (s.n * s.v).sum(1, keepdim=True))
        return s.albedo * 2.0

    ao = torch.full_like(m, 0.25)
    out = shade(
        GBuffer(
            position=pos, normal=n, albedo=albedo, metallic=m, roughness=m + 0.5, ao=ao, mask=mask
        ),
        camera_position=cam(),
        lights=Lights(),
        ibl=ibl,
    )
    assert seen["unit"] and seen["by name"]
    torch.testing.assert_close(out, albedo * 2.0 * 0.25 * mask)
    with pytest.raises(ValueError, match="ibl"):
        shade(
            GBuffer(position=pos, normal=n, albedo=albedo, metallic=m, roughness=m, mask=mask),
            camera_position=cam(),
            lights=Lights(),
            ibl=lambda *a: torch.zeros(1, 3, 4, 4, dtype=F64),
        )


def test_chunking_and_checkpoint_agree() -> None:
    pos, n, mask = sphere(12, 12)
    g = torch.Generator().manual_seed(7)
    lights = lights_from_config(LIGHTS * 3, dtype=F64)
    albedo = torch.rand(1, 3, 12, 12, generator=g, dtype=F64)
    grads, outs = [], []
    for chunk, ckpt in [(None, None), (1, False), (2, True), (4, None)]:
        rough = (
            torch.rand(1, 1, 12, 12, generator=torch.Generator().manual_seed(8), dtype=F64)
        ).requires_grad_()
        out = shade(
            GBuffer(
                position=pos,
                normal=n,
                albedo=albedo,
                metallic=rough * 0.5,
                roughness=rough,
                mask=mask,
            ),
            camera_position=cam(),
            lights=lights,
            light_chunk=chunk,
            checkpoint_chunks=ckpt,
        )
        out.square().sum().backward()
        outs.append(out.detach())
        grads.append(rough.grad)
    for o, gr in zip(outs[1:], grads[1:], strict=True):
        torch.testing.assert_close(o, outs[0], rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(gr, grads[0], rtol=1e-10, atol=1e-13)


@pytest.mark.parametrize("model", ["blinn_phong", "half_lambert", "toon", "lambert"])
def test_other_models_in_row_bands_equal_whole_frames(model: str, monkeypatch) -> None:
    """The models other than the fused Cook-Torrance run over bands of image rows of about
    MODEL_BAND_ELEMENTS pixel-lights (cache-sized); bands of one row, with shadows (a
    visibility hook), an area light and a batch of 2, give the whole frame's values and
    gradients."""
    from torchraster.shading import lighting

    pos, n, mask = sphere(9, 7, b=2)
    g = torch.Generator().manual_seed(5)
    lights = lights_from_config(LIGHTS + [{"type": "area", "position": [0.5, 1.5, 2.0],
                                           "direction": [0.0, -0.6, -1.0], "size": [1.0, 0.5],
                                           "intensity": 3.0}], dtype=F64)
    shadow = {kind: torch.rand(2, 4, 1, 9, 7, generator=g, dtype=F64)
              for kind in ("directional", "point", "spot", "area")}
    rough = torch.rand(2, 1, 9, 7, generator=g, dtype=F64)
    outs = []
    for band in (lighting.MODEL_BAND_ELEMENTS, 1):
        monkeypatch.setattr(lighting, "MODEL_BAND_ELEMENTS", band)
        albedo = torch.rand(2, 3, 9, 7, generator=torch.Generator().manual_seed(8),
                            dtype=F64).requires_grad_()
        out = shade(GBuffer(position=pos, normal=n, albedo=albedo, metallic=rough * 0.5,
                            roughness=rough, mask=mask),
                    camera_position=cam(2), lights=lights,
                    model=lambert if model == "lambert" else model,
                    visibility=lambda kind, sl: shadow[kind][:, sl])
        outs.append((out, *torch.autograd.grad(out.square().sum(), albedo)))
    assert float(outs[0][1].abs().max()) > 0
    for a, b in zip(*outs, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("model", sorted(MODELS))
def test_models_by_name_finite(model: str) -> None:
    pos, n, mask = sphere(16, 16, dtype=torch.float32)
    albedo = torch.full_like(n, 0.6)
    m = torch.zeros(1, 1, 16, 16)
    lights = lights_from_config(LIGHTS)
    out = shade(
        GBuffer(position=pos, normal=n, albedo=albedo, metallic=m, roughness=m + 0.3, mask=mask),
        camera_position=cam(dtype=torch.float32),
        lights=lights,
        model=model,
    )
    assert torch.isfinite(out).all() and out.max() > 0
    # by name == by callable
    same = shade(
        GBuffer(position=pos, normal=n, albedo=albedo, metallic=m, roughness=m + 0.3, mask=mask),
        camera_position=cam(dtype=torch.float32),
        lights=lights,
        model=MODELS[model],
    )
    torch.testing.assert_close(out, same)


def small_gbuffer(g: torch.Generator, h: int = 3, w: int = 3):
    pos = torch.randn(1, 3, h, w, generator=g, dtype=F64) * 0.3
    nrm = torch.randn(1, 3, h, w, generator=g, dtype=F64) * 0.2
    nrm[:, 2] = 1.0
    albedo = torch.rand(1, 3, h, w, generator=g, dtype=F64) * 0.8 + 0.1
    metal = torch.rand(1, 1, h, w, generator=g, dtype=F64) * 0.8 + 0.1
    rough = torch.rand(1, 1, h, w, generator=g, dtype=F64) * 0.8 + 0.15
    return pos, nrm, albedo, metal, rough


def test_gradcheck_pass() -> None:
    g = torch.Generator().manual_seed(9)
    pos, nrm, albedo, metal, rough = small_gbuffer(g)
    lights = lights_from_config(
        LIGHTS[:1]
        + LIGHTS[2:3]
        + [
            {
                "type": "spot",
                "position": [0, 0, 2],
                "direction": [0, 0, -1],
                "intensity": 5.0,
                "inner_cone_angle": 0.1,
                "outer_cone_angle": 1.2,
            },
            {"type": "ambient", "color": [0.3, 0.3, 0.3]},
        ],
        dtype=F64,
    )
    ao = torch.full((1, 1, 3, 3), 0.7, dtype=F64)

    def fn(albedo, metal, rough, nrm):
        return shade(
            GBuffer(
                position=pos, normal=nrm, albedo=albedo, metallic=metal, roughness=rough, ao=ao
            ),
            camera_position=cam(),
            lights=lights,
        )

    args = tuple(t.clone().requires_grad_() for t in (albedo, metal, rough, nrm))
    assert torch.autograd.gradcheck(fn, args)


def test_hostile_gbuffer_finite() -> None:
    # zero normals, back-facing normals, exactly grazing normals, roughness 0 and 1,
    # black and 1e6 cd lights, a light at the surface point
    pos = torch.zeros(1, 3, 2, 4)
    nrm = torch.tensor([[0, 0, 0], [0, 0, -1], [1, 0, 0], [0, 0, 1.0]]).T.reshape(1, 3, 1, 4)
    nrm = nrm.repeat(1, 1, 2, 1)
    rough = torch.tensor([0.0, 1.0]).view(1, 1, 2, 1).repeat(1, 1, 1, 4)
    lights = lights_from_config(
        [
            {"type": "point", "position": [0, 0, 0], "intensity": 1e6},
            {"type": "point", "position": [0, 0, 1], "intensity": 0.0, "color": [0, 0, 0]},
            {"type": "spot", "position": [0, 0, 1], "direction": [0, 0, -1], "intensity": 1e6},
            {"type": "directional", "direction": [0, 0, -1], "intensity": 1e6},
            {"type": "ambient", "color": [1, 1, 1]},
        ]
    )
    args = [
        t.clone().requires_grad_()
        for t in (pos, nrm, torch.full_like(pos, 0.5), torch.full_like(rough, 0.5), rough)
    ]
    gb = GBuffer(
        **dict(zip(["position", "normal", "albedo", "metallic", "roughness"], args, strict=True))
    )
    out = shade(gb, camera_position=torch.tensor([[0.0, 0, 5]]), lights=lights)
    assert torch.isfinite(out).all()
    out.sum().backward()
    for t in args:
        assert torch.isfinite(t.grad).all()


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_low_precision_pass(dtype: torch.dtype) -> None:
    pos, n, mask = sphere(24, 24, dtype=torch.float32)
    albedo = torch.full_like(n, 0.7)
    m = torch.linspace(0, 1, 24).view(1, 1, 1, 24).expand(1, 1, 24, 24).contiguous()
    r = torch.linspace(0, 1, 24).view(1, 1, 24, 1).expand(1, 1, 24, 24).contiguous()
    lights = lights_from_config(LIGHTS + [{"type": "ambient", "color": [0.2, 0.2, 0.2]}])
    ref = shade(
        GBuffer(position=pos, normal=n, albedo=albedo, metallic=m, roughness=r, mask=mask),
        camera_position=cam(dtype=torch.float32),
        lights=lights,
    )
    low16 = [t.to(dtype) for t in (pos, n, albedo, m, r)]
    low = shade(
        GBuffer(
            position=low16[0],
            normal=low16[1],
            albedo=low16[2],
            metallic=low16[3],
            roughness=low16[4],
            mask=mask,
        ),
        camera_position=cam(dtype=dtype),
        lights=lights,
    )
    assert low.dtype == dtype and torch.isfinite(low).all()
    err = (low.float() - ref).abs() / ref.abs().clamp_min(0.05)
    assert err.median().item() < 0.02  # inputs rounded to 8 (bf16) / 11 (fp16) bits


def test_bad_inputs() -> None:
    pos, n, mask = sphere(4, 4)
    a, m = torch.full_like(n, 0.5), torch.zeros(1, 1, 4, 4, dtype=F64)
    gb = GBuffer(position=pos, normal=n, albedo=a, metallic=m, roughness=m, mask=mask)
    with pytest.raises(ValueError, match="albedo"):
        GBuffer(position=pos, normal=n, albedo=a[:, :2], metallic=m, roughness=m)
    with pytest.raises(ValueError, match="roughness"):
        GBuffer(position=pos, normal=n, albedo=a, metallic=m, roughness=m[..., :3])
    with pytest.raises(ValueError, match="metallic"):  # needs every channel it reads
        shade(GBuffer(position=pos, normal=n, albedo=a, roughness=m), camera_position=cam())
    with pytest.raises(TypeError, match="gbuffer"):
        shade({"position": pos}, camera_position=cam())
    with pytest.raises(ValueError, match="camera_position"):
        shade(gb, camera_position=torch.zeros(1, 4, dtype=F64), lights=Lights())
    with pytest.raises(TypeError, match="lights"):
        shade(gb, camera_position=cam(), lights=[{"type": "ambient"}])
    with pytest.raises(ValueError, match="batch size"):
        shade(gb, camera_position=cam(), lights=lights_from_config(LIGHTS[:1], batch=3, dtype=F64))
    with pytest.raises(ValueError, match="model"):
        shade(gb, camera_position=cam(), model="phong")
    with pytest.raises(ValueError, match="model"):
        shade(
            gb,
            camera_position=cam(),
            lights=lights_from_config(LIGHTS[:1], dtype=F64),
            model=lambda n, v, l, s: torch.zeros(1, 3, 4, 4),
        )
    with pytest.raises(TypeError, match="metallic"):
        GBuffer(position=pos, normal=n, albedo=a, metallic=m.long(), roughness=m)
    with pytest.raises(TypeError):  # keyword-only after the G-buffer
        shade(gb, cam(), Lights())


def test_lights_of_batch_one_broadcast() -> None:
    pos, n, mask = sphere(8, 8, b=2)
    a, m = torch.full_like(n, 0.5), torch.zeros(2, 1, 8, 8, dtype=F64)
    gb = GBuffer(position=pos, normal=n, albedo=a, metallic=m, roughness=m + 0.5, mask=mask)
    eye = cam().expand(2, 3)
    shared = shade(gb, camera_position=eye, lights=lights_from_config(LIGHTS, dtype=F64))
    full = shade(gb, camera_position=eye, lights=lights_from_config(LIGHTS, batch=2, dtype=F64))
    torch.testing.assert_close(shared, full, rtol=0, atol=0)


def test_env_brdf_table_limits() -> None:
    lut = dfg_lut(dtype=F64)
    assert lut.shape[0] == 2 and torch.isfinite(lut).all() and lut.min() >= 0
    assert (lut.sum(0) <= 1.0 + 1e-3).all()  # f0 = 1: the white-furnace directional albedo
    one = torch.ones(1, 1, 1, 1, dtype=F64)
    s = Surface(one, one, one)  # noqa: F841  (the dataclass is importable / constructible)
    assert env_brdf(one.expand(1, 3, 1, 1), one * 0.045, one)[0, 0].item() > 0.99


def test_artistic_models_closed_forms() -> None:
    from torchraster.shading.models import TOON_BANDS, blinn_phong, half_lambert, toon

    z = torch.tensor([0.0, 0.0, 1.0], dtype=F64).view(1, 3, 1, 1)
    albedo = torch.tensor([0.2, 0.5, 0.8], dtype=F64).view(1, 3, 1, 1)
    zero = torch.zeros(1, 1, 1, 1, dtype=F64)
    s = Surface(albedo, zero, zero + 0.5)
    for cos, want in ((1.0, 1.0), (0.0, 0.25), (-1.0, 0.0)):
        l = torch.tensor([math.sqrt(1 - cos * cos), 0.0, cos], dtype=F64).view(1, 3, 1, 1)
        torch.testing.assert_close(half_lambert(z, z, l, s), albedo / math.pi * want)
    # Blinn-Phong at the mirror direction: kd / pi + f0 (s + 8) / (8 pi), s = 2 / a^2 - 2
    sh = 2 / 0.5**4 - 2
    torch.testing.assert_close(
        blinn_phong(z, z, z, s), albedo / math.pi + 0.04 * (sh + 8) / (8 * math.pi)
    )
    # toon: diffuse takes TOON_BANDS + 1 levels only
    ang = torch.linspace(0, math.pi, 50, dtype=F64)
    l = torch.stack([ang.sin(), torch.zeros_like(ang), ang.cos()]).view(1, 3, 1, 50)
    v = torch.tensor([1.0, 0.0, 0.0], dtype=F64).view(1, 3, 1, 1)  # no highlight
    levels = toon(z, v, l, Surface(albedo, zero, zero + 0.1))[0, 0, 0] * math.pi / 0.2
    assert set(torch.round(levels * TOON_BANDS).tolist()) == set(range(TOON_BANDS + 1))


def test_visibility_hook_scales_each_light() -> None:
    pos, n, mask = sphere(8, 8)
    gb = GBuffer(position=pos, normal=n, albedo=torch.full_like(n, 0.5),
                 metallic=torch.zeros(1, 1, 8, 8, dtype=F64),
                 roughness=torch.full((1, 1, 8, 8), 0.5, dtype=F64), mask=mask)
    two = [{"type": "point", "position": [1, 1, 3], "intensity": 4.0},
           {"type": "point", "position": [-1, 0, 3], "intensity": 2.0}]
    full = shade(gb, camera_position=cam(), lights=lights_from_config(two, dtype=F64))
    first = shade(gb, camera_position=cam(), lights=lights_from_config(two[:1], dtype=F64))
    calls = []

    def second_in_shadow(kind: str, sl: slice) -> torch.Tensor:
        calls.append((kind, sl))
        vis = torch.ones(1, 2, 1, 8, 8, dtype=F64)[:, sl]
        vis[:, -1] = 0.0 if sl.stop == 2 else 1.0
        return vis

    for chunk in (None, 1):
        out = shade(gb, camera_position=cam(), lights=lights_from_config(two, dtype=F64),
                    visibility=second_in_shadow, light_chunk=chunk)
        torch.testing.assert_close(out, first)
    assert ("point", slice(0, 1)) in calls and ("point", slice(1, 2)) in calls
    half = shade(gb, camera_position=cam(), lights=lights_from_config(two, dtype=F64),
                 visibility=lambda kind, sl: torch.full((1, sl.stop - sl.start, 1, 8, 8), 0.5,
                                                        dtype=F64))
    torch.testing.assert_close(half, full * 0.5)
    with pytest.raises(ValueError, match="visibility"):
        shade(gb, camera_position=cam(), lights=lights_from_config(two, dtype=F64),
              visibility=lambda kind, sl: torch.ones(1, 3, 1, 8, 8, dtype=F64))
