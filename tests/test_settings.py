"""The renderer's settings groups (torchraster/settings.py): one source for Python and YAML,
each field checked, the shortcuts equal to the groups they stand for."""

from __future__ import annotations

import dataclasses

import pytest
import torch

import torchraster as tr
from torchraster.config.build import RENDER_SETTINGS_KEYS, SETTINGS_OF_RENDER, build_renderer
from torchraster.config.schema import RenderConfig
from torchraster.settings import SETTINGS_BOUNDS

#: Fields a YAML config does not set (they never change the image, or are set elsewhere).
PYTHON_ONLY = {(tr.RasterSettings, "max_batch"), (tr.RasterSettings, "camera_relative"),
               (tr.TextureSettings, "cache_bytes"), (tr.ShadingSettings, "options"),
               (tr.BackgroundSettings, "environment"), (tr.BackgroundSettings, "image"),
               (tr.BackgroundSettings, "fit")}
VIEW = tr.camera.look_at(torch.tensor([[0.0, 0.4, 2.6]]), torch.zeros(1, 3),
                         torch.tensor([[0.0, 1.0, 0.0]]))
PROJ = tr.camera.perspective(40.0, 1.0, 0.1)


def test_every_field_is_a_yaml_key_or_named_python_only() -> None:
    yaml_fields = set(RENDER_SETTINGS_KEYS.values())
    for cls in SETTINGS_OF_RENDER.values():
        for f in dataclasses.fields(cls):
            assert ((cls, f.name) in yaml_fields) != ((cls, f.name) in PYTHON_ONLY), (cls, f.name)
    assert set(RENDER_SETTINGS_KEYS) <= set(RenderConfig.model_fields)


@pytest.mark.parametrize("key", sorted(RENDER_SETTINGS_KEYS))
def test_yaml_defaults_and_bounds_are_the_dataclasses(key: str) -> None:
    cls, name = RENDER_SETTINGS_KEYS[key]
    yaml_field = RenderConfig.model_fields[key]
    default = yaml_field.get_default(call_default_factory=True)
    if key == "shading":
        assert default is None  # chosen from the lights; ShadingSettings' default is pbr
        return
    want = cls().__getattribute__(name)
    assert (tuple(default) if isinstance(default, list) else default) == want
    if name in SETTINGS_BOUNDS:
        lo, hi = SETTINGS_BOUNDS[name]
        schema = RenderConfig.model_json_schema()["properties"][key]
        assert (schema["minimum"], schema["maximum"]) == (lo, hi)
        aniso = name == "max_anisotropy"  # used by the anisotropic filter only
        extra, yaml_extra = ({"filter": "anisotropic"}, "texture_filter: anisotropic, ") if (
            aniso) else ({}, "")
        cls(**{name: hi}, **extra)
        for bad in (lo - 1, hi + 1):
            with pytest.raises(ValueError, match=rf"^{cls.__name__}.{name}: expected an int"):
                cls(**{name: bad}, **extra)
            with pytest.raises(tr.ConfigError, match=f"render.{key}"):
                tr.parse_config(f"scene: {{mesh: spot}}\nrender: {{{yaml_extra}{key}: {bad}}}\n",
                                "x.yaml")


def test_yaml_builds_the_groups_python_builds(tmp_path) -> None:  # noqa: ANN001
    text = ("scene: {mesh: spot}\nlights: [{type: directional, direction: [0, -1, 0]}]\n"
            "render: {resolution: [12, 16], shading: toon, toon: {bands: 2}, supersample: 2,"
            " cull_backfaces: true, antialias: true, alpha_layers: 3, texture_filter: "
            "anisotropic, max_anisotropy: 4, background: [0.1, 0.2, 0.3]}\n")
    r = build_renderer(tr.parse_config(text, "a.yaml", base_dir=tmp_path), True)
    assert r.shading_settings.model == "toon"
    assert r.shading_settings.options["bands"] == 2 and r.shading_settings.multiscatter
    assert r.raster_settings == tr.RasterSettings(supersample=2, cull_backfaces=True,
                                                  antialias=True, alpha_layers=3)
    assert r.texture_settings == tr.TextureSettings(filter="anisotropic", max_anisotropy=4)
    assert r.background_settings.color == (0.1, 0.2, 0.3)
    assert r.background_settings.image is None and r.resolution == (12, 16)


def test_shortcuts_equal_the_groups() -> None:
    scene = tr.RenderScene.from_mesh(tr.load_spot())
    short = tr.Renderer(16, shading="headlight", background=(0.2, 0.3, 0.4))
    full = tr.Renderer(16, shading=tr.ShadingSettings("headlight"),
                       background=tr.BackgroundSettings(color=(0.2, 0.3, 0.4)))
    a, b = short(scene, VIEW, PROJ), full(scene, VIEW, PROJ)
    assert torch.equal(a.image, b.image) and a.plan == b.plan
    assert bool((a.image[..., 0, 0] == torch.tensor([0.2, 0.3, 0.4])).all())  # a corner


def test_groups_are_frozen_and_replaceable() -> None:
    raster = tr.RasterSettings(supersample=2)
    with pytest.raises(dataclasses.FrozenInstanceError):
        raster.supersample = 3  # type: ignore[misc]
    r = tr.Renderer(8, shading="unlit", raster=raster)
    r.raster_settings = dataclasses.replace(raster, supersample=3)
    assert r.plan(tr.load_spot()).resolution == (24, 24)
    r.shading_settings = tr.ShadingSettings("toon", {"bands": 2})
    assert r.shading == "toon" and r.model is not None
    with pytest.raises(ValueError, match=r"^RasterSettings.edge_supersample: not combined"):
        dataclasses.replace(raster, edge_supersample=2)


@pytest.mark.parametrize("group,kwargs,match", [
    (tr.ShadingSettings, {"model": "toon", "options": [1]}, "^ShadingSettings.options: expected"),
    (tr.ShadingSettings, {"model": "headlight", "multiscatter": False},
     "^ShadingSettings.multiscatter: the energy terms of pbr"),
    (tr.RasterSettings, {"antialias": True, "edge_supersample": 2},
     "^RasterSettings.edge_supersample: not combined with antialias"),
    (tr.RasterSettings, {"camera_relative": 1}, "^RasterSettings.camera_relative: expected"),
    (tr.TextureSettings, {"filter": "anisotropic", "max_anisotropy": 65},
     r"^TextureSettings.max_anisotropy: expected an int in \[1, 64\]"),
    (tr.BackgroundSettings, {"fit": "zoom"}, "^BackgroundSettings.fit: expected one of"),
    (tr.BackgroundSettings, {"image": torch.rand(2, 4, 4)}, "^BackgroundSettings.image"),
])
def test_each_group_names_the_bad_field(group: type, kwargs: dict, match: str) -> None:
    with pytest.raises((TypeError, ValueError), match=match):
        group(**kwargs)


def test_edge_supersample_refuses_the_effects_it_lacks() -> None:
    raster = tr.RasterSettings(edge_supersample=2)
    with pytest.raises(NotImplementedError, match="^RasterSettings.edge_supersample: .*fog="):
        tr.Renderer(8, raster=raster, fog=tr.Fog(density=0.1))
    with pytest.raises(NotImplementedError, match="^RasterSettings.edge_supersample: .*ssr="):
        tr.Renderer(8, raster=raster, ssr=tr.post.SSR())
