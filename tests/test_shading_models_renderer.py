"""Renderer(shading=...) with every model of torchraster.shading.models, and YAML
``render.shading`` / ``render.toon``: each model in the renderer equals the model function
evaluated by hand in float64 on G-buffer pixels (lights' illuminance from the glTF
KHR_lights_punctual formulas, written out here), errors name the choices, the plan reports
the model, stress inputs stay finite."""

from __future__ import annotations

import math
import warnings

import pytest
import torch
import trimesh

import torchraster as tr
from torchraster import camera
from torchraster.shading import models

EYE = torch.tensor([0.4, 0.6, 3.5], dtype=torch.float64)
VIEW = camera.look_at(EYE, torch.zeros(3, dtype=torch.float64))
PROJ = camera.perspective(40.0, 1.0, 0.1).double()
LIT = {"pbr": "cook_torrance", "blinn_phong": "blinn_phong", "half_lambert": "half_lambert",
       "toon": "toon"}


def _sphere(roughness: float = 0.4, metallic: float = 0.3) -> tr.RenderScene:
    ico = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    mat = tr.Material(base_color_factor=torch.tensor([0.8, 0.5, 0.3, 1.0]),
                      metallic_factor=metallic, roughness_factor=roughness)
    return tr.RenderScene(torch.tensor(ico.vertices, dtype=torch.float64),
                          torch.tensor(ico.faces), materials=[mat])


def _lights() -> tr.Lights:
    d = torch.float64
    return tr.Lights(
        directional=tr.DirectionalLights(direction=torch.tensor([[[-0.3, -1.0, -0.5]]], dtype=d),
                                         color=torch.tensor([[[1.0, 0.9, 0.8]]], dtype=d),
                                         intensity=torch.tensor([[2.0]], dtype=d)),
        point=tr.PointLights(position=torch.tensor([[[1.5, 1.0, 2.0]]], dtype=d),
                             color=torch.tensor([[[0.6, 0.8, 1.0]]], dtype=d),
                             intensity=torch.tensor([[5.0]], dtype=d)),
        spot=tr.SpotLights(position=torch.tensor([[[-1.0, 2.0, 2.0]]], dtype=d),
                           direction=torch.tensor([[[0.4, -0.8, -0.8]]], dtype=d),
                           color=torch.tensor([[[1.0, 1.0, 1.0]]], dtype=d),
                           intensity=torch.tensor([[9.0]], dtype=d),
                           inner_cone_angle=torch.tensor([[0.2]], dtype=d),
                           outer_cone_angle=torch.tensor([[0.6]], dtype=d)))


def _by_hand(model, gb: dict, eye: torch.Tensor, lights: tr.Lights) -> torch.Tensor:
    """sum over lights of model(n, v, l, surface) * E, evaluated pixel by pixel (B=1)."""
    p, n = gb["position"][0], gb["normal"][0]  # (3, H, W)
    n = n / n.norm(dim=0, keepdim=True).clamp_min(1e-30)
    v = eye.view(3, 1, 1) - p
    v = v / v.norm(dim=0, keepdim=True)
    surface = models.Surface(albedo=gb["albedo"][0], metallic=gb["metallic"][0],
                             roughness=gb["roughness"][0])
    total = torch.zeros_like(p)
    dl = lights.directional
    l = -dl.direction[0, 0] / dl.direction[0, 0].norm()
    total += model(n, v, l.view(3, 1, 1).expand_as(n), surface) * (
        dl.color[0, 0] * dl.intensity[0, 0]).view(3, 1, 1)
    for part, spot in ((lights.point, False), (lights.spot, True)):
        to = part.position[0, 0].view(3, 1, 1) - p
        d2 = (to * to).sum(0, keepdim=True)
        l = to / d2.sqrt()
        e = part.intensity[0, 0] / d2  # candela / m^2 (no range)
        if spot:  # glTF: smooth falloff between the cone angles, squared
            axis = part.direction[0, 0] / part.direction[0, 0].norm()
            cd = -(axis.view(3, 1, 1) * l).sum(0, keepdim=True)
            co, ci = math.cos(part.outer_cone_angle[0, 0]), math.cos(part.inner_cone_angle[0, 0])
            e = e * ((cd - co) / (ci - co)).clamp(0, 1) ** 2
        total += model(n, v, l, surface) * part.color[0, 0].view(3, 1, 1) * e
    return total * gb["mask"][0]


@pytest.mark.parametrize("shading", ["blinn_phong", "half_lambert", "toon"])
def test_each_model_in_the_renderer_equals_the_model_by_hand(shading: str):
    renderer = tr.Renderer(24, shading=shading)
    lights = _lights()
    out = renderer(_sphere(), VIEW, PROJ, lights,
                   channels={"position", "normal", "albedo", "metallic", "roughness", "mask"})
    assert out.image.dtype == torch.float64
    assert out.plan.shading == shading
    eye = EYE
    want = _by_hand(models.MODELS[LIT[shading]], out.gbuffer, eye, lights)
    covered = out.gbuffer["mask"][0, 0] > 0
    assert int(covered.sum()) > 150
    got = out.image[0]
    torch.testing.assert_close(got[:, covered], want[:, covered], rtol=1e-9, atol=1e-12)
    assert float(want.amax()) > 0.1  # lit, not a vacuous comparison


def test_pbr_is_the_unchanged_lighting_pass():
    """pbr renders what ``shade`` (the Cook-Torrance pass, with its energy terms) gives."""
    lights = _lights()
    out = tr.Renderer(24, shading="pbr")(
        _sphere(), VIEW, PROJ, lights,
        channels={"position", "normal", "albedo", "metallic", "roughness", "mask"})
    eye = EYE[None]
    want = tr.shade(tr.GBuffer(**out.gbuffer), camera_position=eye, lights=lights)
    torch.testing.assert_close(out.image, want, rtol=1e-9, atol=1e-12)
    assert out.plan.shading == "pbr" and float(want.amax()) > 0.1


def test_toon_options_reach_the_model():
    lights = _lights()
    opts = {"bands": 2, "rim": 0.7, "rim_width": 0.5}
    out = tr.Renderer(24, shading=tr.ShadingSettings("toon", options=opts))(
        _sphere(), VIEW, PROJ, lights,
        channels={"position", "normal", "albedo", "metallic", "roughness", "mask"})
    eye = EYE
    plain = _by_hand(models.toon, out.gbuffer, eye, lights)
    want = _by_hand(lambda *a: models.toon(*a, **opts), out.gbuffer, eye, lights)
    covered = out.gbuffer["mask"][0, 0] > 0
    torch.testing.assert_close(out.image[0][:, covered], want[:, covered], rtol=1e-9,
                               atol=1e-12)
    assert float((want - plain).abs().amax()) > 0.05  # the options change the picture
    # the rim term alone: white, on the lit silhouette side only
    n = torch.tensor([1.0, 0.0, 0.0]).view(3, 1, 1).double()
    v = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).double()  # n.v = 0 < rim_width
    s = models.Surface(albedo=torch.zeros(3, 1, 1).double(), metallic=torch.zeros(1, 1, 1),
                       roughness=torch.full((1, 1, 1), 0.2))  # no highlight at 45 deg
    lit = models.toon(n, v, n, s, rim=0.7)
    torch.testing.assert_close(lit, torch.full_like(lit, 0.7 / math.pi))
    assert float(models.toon(n, v, -n, s, rim=0.7).abs().max()) == 0.0


def test_unknown_names_and_options_raise_naming_the_choices():
    with pytest.raises(ValueError,
                       match="^ShadingSettings.model: expected one of .*toon.*got 'cel'"):
        tr.Renderer(8, shading="cel")
    with pytest.raises(ValueError, match=r"shading options \['bandz'\].*bands"):
        tr.Renderer(8, shading=tr.ShadingSettings("toon", options={"bandz": 2}))
    with pytest.raises(ValueError, match="bands: expected an int >= 1"):
        tr.Renderer(8, shading=tr.ShadingSettings("toon", options={"bands": 0}))
    with pytest.raises(ValueError,
                       match="^ShadingSettings.options: shading 'unlit' takes no options"):
        tr.Renderer(8, shading=tr.ShadingSettings("unlit", options={"bands": 2}))
    with pytest.raises(ValueError, match="not parameters of model 'blinn_phong'"):
        tr.Renderer(8, shading=tr.ShadingSettings("blinn_phong", options={"rim": 1.0}))


def test_the_plan_reports_the_model_and_skips_what_it_need_not():
    lights = _lights()
    scene = _sphere()
    for shading in ("blinn_phong", "half_lambert", "toon"):
        plan = tr.Renderer(8, shading=shading).plan(scene, lights)
        assert plan.shading == shading and f"shade {shading}" in plan
        assert "light directional x1" in plan and "light spot x1" in plan
    plan = tr.Renderer(8, shading="pbr").plan(scene, lights)
    assert not any(s.startswith("shade ") for s in plan)
    with pytest.warns(UserWarning, match="shading='toon'.*no lights"):
        plan = tr.Renderer(8, shading="toon").plan(scene)
    assert plan.shading == "unlit"


def test_stylised_models_take_shadows_and_ambient_like_pbr():
    ground = trimesh.creation.box(extents=[4.0, 0.1, 4.0])
    ground.apply_translation([0, -1.2, 0])
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.6)
    both = trimesh.util.concatenate([ball, ground])
    scene = tr.RenderScene(torch.tensor(both.vertices, dtype=torch.float32),
                           torch.tensor(both.faces))
    sun = tr.Lights(ambient=tr.sh_from_color(torch.tensor([[0.1, 0.1, 0.1]])),
                    directional=tr.DirectionalLights(
                        direction=torch.tensor([[[0.0, -1.0, 0.0]]]),
                        color=torch.ones(1, 1, 3), intensity=torch.tensor([[3.0]]),
                        cast_shadows=torch.tensor([[True]])))
    view = camera.look_at([0.0, 2.5, 4.0], [0.0, -0.8, 0.0])
    proj = camera.perspective(45.0, 1.0, 0.1)
    for shading in ("toon", "half_lambert"):
        lit = tr.Renderer(32, shading=shading)(scene, view, proj, sun)
        flat = tr.Renderer(32, shading=shading, shadows=False)(scene, view, proj, sun)
        assert any(s.startswith("shadow directional") for s in lit.plan)
        assert "light ambient" in lit.plan
        assert float((flat.image - lit.image).amax()) > 0.1  # the ball shadows the ground
        assert bool(torch.isfinite(lit.image).all())


@pytest.mark.parametrize("shading", ["blinn_phong", "half_lambert", "toon"])
def test_hostile_inputs_stay_finite_with_finite_gradients(shading: str):
    """Roughness 0, a grazing light, a black and a blinding light, an empty frame."""
    scene = _sphere(roughness=0.0, metallic=1.0)
    lights = _lights()
    grazing = tr.Lights(directional=tr.DirectionalLights(
        direction=torch.tensor([[[1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]], dtype=torch.float64),
        color=torch.tensor([[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]], dtype=torch.float64),
        intensity=torch.tensor([[1e30, 1e6]], dtype=torch.float64)))
    albedo = torch.tensor([0.5, 0.5, 0.5, 1.0], dtype=torch.float64, requires_grad=True)
    scene.materials[0] = tr.Material(base_color_factor=albedo, metallic_factor=1.0,
                                     roughness_factor=0.0)
    for li in (lights, grazing):
        out = tr.Renderer(16, shading=shading)(scene, VIEW, PROJ, li)
        assert bool(torch.isfinite(out.image).all())
        (g,) = torch.autograd.grad(out.image.sum(), albedo)
        assert bool(torch.isfinite(g).all())
    away = camera.look_at([0.0, 0.0, -4.0], [0.0, 0.0, -8.0]).double()
    out = tr.Renderer(8, shading=shading)(scene, away, PROJ, lights)  # nothing in view
    assert float(out.image.detach().abs().sum()) == 0.0


def test_gradcheck_through_a_stylised_render():
    scene = _sphere()
    lights = _lights()
    renderer = tr.Renderer(6, shading="blinn_phong")

    def f(color: torch.Tensor) -> torch.Tensor:
        scene.materials[0] = tr.Material(base_color_factor=torch.cat([color, color[:1] * 0 + 1]),
                                         metallic_factor=0.3, roughness_factor=0.4)
        return renderer(scene, VIEW, PROJ, lights).image

    color = torch.tensor([0.8, 0.5, 0.3], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(f, (color,), eps=1e-6, atol=1e-7)


TOON_YAML = """
scene:
  objects:
    - primitive: sphere
      material: {base_color: [0.9, 0.4, 0.2], roughness: 0.4}
cameras:
  - orbit: {azimuth_deg: 20, elevation_deg: 15, distance: 3.0}
render:
  resolution: 24
  shading: toon
  toon: {bands: 2, rim: 0.6}
lights:
  - {type: directional, direction: [-0.5, -1.0, -0.6], intensity: 3.0}
outputs: {channels: [radiance]}
"""


def test_yaml_toon_end_to_end(tmp_path):
    cfg = tr.parse_config(TOON_YAML, "toon.yaml", base_dir=tmp_path)
    (view,) = tr.render_config(cfg)
    assert view.plan.shading == "toon" and "shade toon" in view.plan
    img = view.images["radiance"]
    assert bool(torch.isfinite(img).all())
    # the sphere's directional diffuse takes 2 + 1 levels (+ highlight, rim): few distinct
    # values, compared with the default 3 bands
    three = tr.parse_config(TOON_YAML.replace("bands: 2, ", ""), "toon.yaml", base_dir=tmp_path)
    (other,) = tr.render_config(three)
    assert not torch.equal(other.images["radiance"], img)
    with pytest.raises(tr.ConfigError, match="render.*toon: options of shading: toon"):
        tr.parse_config(TOON_YAML.replace("shading: toon", "shading: blinn_phong"), "t.yaml")
    with pytest.raises(tr.ConfigError, match="bands"):
        tr.parse_config(TOON_YAML.replace("bands: 2", "bands: 0"), "t.yaml")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for shading in ("blinn_phong", "half_lambert"):
            text = TOON_YAML.replace("shading: toon", f"shading: {shading}").replace(
                "  toon: {bands: 2, rim: 0.6}\n", "")
            (v,) = tr.render_config(tr.parse_config(text, "m.yaml", base_dir=tmp_path))
            assert v.plan.shading == shading


def test_the_shipped_config_renders_from_a_fresh_clone():
    """configs/shading_models.yaml (small): every file it names is in the repository."""
    from pathlib import Path

    cfg = tr.load_config(Path(__file__).resolve().parents[1] / "configs" /
                         "shading_models.yaml")
    tr.config.check_config(cfg)
    cfg.render.resolution, cfg.render.supersample = 24, 1
    (view,) = tr.render_config(cfg)
    assert view.plan.shading == "toon" and bool(torch.isfinite(view.images["color"]).all())


def test_options_a_model_does_not_read_are_refused(tmp_path):
    """multiscatter switches pbr's energy terms; the stylised models have none: setting it
    there would be a silent no-op, so it is refused (Renderer and YAML), as is a
    max_anisotropy without the anisotropic filter."""
    with pytest.raises(ValueError, match="multiscatter"):
        tr.Renderer(8, shading=tr.ShadingSettings("toon", multiscatter=False))
    tr.Renderer(8, shading=tr.ShadingSettings("pbr", multiscatter=False))
    with pytest.raises(ValueError, match="max_anisotropy"):
        tr.Renderer(8, textures=tr.TextureSettings(filter="trilinear", max_anisotropy=4))
    tr.Renderer(8, textures=tr.TextureSettings(filter="anisotropic", max_anisotropy=4))
    text = TOON_YAML.replace("render:", "render:\n  multiscatter: false", 1)
    assert text != TOON_YAML
    with pytest.raises(tr.ConfigError, match="multiscatter"):
        tr.parse_config(text, "t.yaml", base_dir=tmp_path)
