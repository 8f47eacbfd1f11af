"""Every field of the render-config schema does something, or is declared metadata.

The walker visits every field of every pydantic model reachable from ``RenderFile`` (light
entries per ``type``). Each field must be either

* in ``VARIATIONS``: a base config and a change of that field; rendering both (16x16) must
  give different outputs (pixels of any channel, the set of outputs, or the outcome: an
  error instead of an image counts), or the change must raise ``NotImplementedError``
  naming the field (``NOT_IMPLEMENTED``); or
* in ``METADATA`` with the reason it cannot change a pixel (a name, a file format).

A field in neither fails ``test_every_config_field_is_accounted_for`` with its key path, so
whoever adds a field sees what to add here.
"""

from __future__ import annotations

import copy
import typing
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
import yaml
from pydantic import BaseModel
from skimage import io as skio

import torchraster as tr
from torchraster.config import Channel, RenderFile, check_config
from torchraster.config.schema import FLOW_CHANNELS, DistConfig
from torchraster.hdr_io import write_hdr
from torchraster.pipeline import render_config

#: Every channel of one frame (the flow channels need two: DATASET_VARIATIONS request them).
CHANNELS = [c for c in typing.get_args(Channel) if c not in FLOW_CHANNELS]

#: Fields that cannot change a rendered pixel, with the reason.
METADATA: dict[str, str] = {
    "cameras.name": "the output sub-folder of the camera",
    "lights.ambient.name": "a label for the user; not used by rendering",
    "lights.directional.name": "a label for the user; not used by rendering",
    "lights.point.name": "a label for the user; not used by rendering",
    "lights.spot.name": "a label for the user; not used by rendering",
    "lights.area.name": "a label for the user; not used by rendering",
    "outputs.formats": "file encodings (png / npy / exr) of the same images "
                       "(tests/test_config_cli.py checks the files)",
    "scene.objects.name": "a label; the default material name of a primitive "
                          "(scene.objects.material.name shows names act through overrides)",
    "outputs.exports": "dataset files made from the rendered views after the run "
                       "(tests/test_dataset_labels.py checks them)",
    "outputs.previews": "extra PNGs of the same ids in colours (tests/test_dataset_labels.py)",
    "outputs.png_compression": "zlib level of the same lossless PNGs "
                               "(tests/test_config_cli.py reads them back at levels 0 and 9)",
    "outputs.track_points": "query points of the tracks export, made from the rendered files "
                            "(tests/test_dataset_randomize.py)",
    "scene.objects.keypoints": "projected into the manifest records, not drawn "
                               "(tests/test_dataset_labels.py)",
}

#: Fields that are accepted but cannot act in a render config: the change must raise
#: NotImplementedError naming the field.
NOT_IMPLEMENTED: set[str] = {"post.auto_exposure.rate"}

#: Fields that are refused with a ConfigError naming them where they cannot act: the
#: cascade fields of point and spot lights' shadows.
REFUSED: set[str] = {f"lights.{kind}.shadows.{key}" for kind in ("point", "spot", "area")
                     for key in ("cascades", "split_lambda", "cascade_blend",
                                 "max_distance")} | {"lights.area.shadows.light_size"}

#: Fields whose base config is expected to fail (the change makes it render).
BASE_FAILS: dict[str, type[BaseException]] = {"scene.allow_missing_textures": tr.ConfigError,
                                              "randomize.objects.max_tries": tr.ConfigError}

PBR = {"render": {"shading": "pbr"}}
SUN = {"type": "directional", "direction": [-0.3, -1.0, -0.2], "intensity": 3.0}
POINT = {"type": "point", "position": [0.8, 1.6, 0.6], "intensity": 4.0}
SPOT = {"type": "spot", "position": [0.0, 2.5, 0.0], "direction": [0.0, -1.0, 0.0],
        "intensity": 8.0, "inner_cone_angle": 0.2, "outer_cone_angle": 0.5}
AMBIENT = {"type": "ambient", "color": [0.3, 0.3, 0.3]}
AREA = {"type": "area", "position": [0.3, 1.5, 0.2], "direction": [-0.2, -1.0, 0.0],
        "size": [1.0, 0.5], "intensity": 4.0}
DISC = {"type": "area", "shape": "disc", "position": [0.3, 1.5, 0.2],
        "direction": [0.0, -1.0, 0.0], "radius": 0.3, "intensity": 4.0}
SH = [[0.2, 0.2, 0.2]] + [[0.0, 0.1, 0.05]] * 8


def _light(light: dict, **change: object) -> dict:
    return {**PBR, "lights": [{**light, **change}]}


def _post(section: str, base: dict, **change: object) -> tuple[dict, dict]:
    return ({"post": {section: base}}, {"post": {section: {**base, **change}}})


def _camera(base: dict, **change: object) -> tuple[dict, dict]:
    return {"cameras": [base]}, {"cameras": [{**base, **change}]}


# Circle of confusion of the ball ~3.7 px (100 mm f/1 focused at 1 m, 4 m away, 16 px wide),
# below max_coc; bloom's soft knee spans most of the image's radiance.
DOF = {"enabled": True, "focus_distance": 1.0, "focal_length_mm": 100.0, "f_number": 1.0,
       "max_coc": 8.0, "levels": 4}
BLOOM = {"enabled": True, "threshold": 0.5, "knee": 0.4, "intensity": 2.0, "radius": 1.0,
         "levels": 2, "karis": False}
AUTO = {"enabled": True, "metering": "percentile", "percentile_low": 0.1,
        "percentile_high": 0.9}
SSAO = {"enabled": True, "radius": 0.5, "samples": 8, "bias": 0.0, "softness": 1.0,
        "blur": False}
SSAO_BASE = {**PBR, "lights": [AMBIENT]}
# a glossy metal ground under the ball: its mirror rays hit the ball
SSR = {"enabled": True, "max_steps": 64, "thickness": 0.5, "max_roughness": 0.6,
       "edge_fade": 0.0, "refine_steps": 4, "blur": True}
SSR_BASE = {**PBR, "lights": [AMBIENT],
            "materials": [{"match": "ground", "metallic": 1.0, "roughness": 0.3}]}
ORBIT = {"orbit": {"azimuth_deg": 30.0, "elevation_deg": 20.0, "distance": 4.0}}
LOOK = {"look_at": {"eye": [0.5, 1.5, 3.5], "target": [0.0, 0.4, 0.0], "up": [0.0, 1.0, 0.0]}}
INTRINSICS = {"fx": 20, "fy": 20, "cx": 8, "cy": 8}
DECAL_VIEW = {"orbit": {"elevation_deg": 60.0, "distance": 4.0}, "near": 1e-4, "far": 1e5}
INSIDE = {"look_at": {"eye": [0.0, 0.5, 0.0], "target": [0.0, 0.5, -1.0]}}
MATERIAL = {"match": "*", "base_color": [1.0, 0.2, 0.1], "metallic": 0.0, "roughness": 0.5}


RANDOM = {"random_orbits": {"count": 2, "distance": 4.0}}


def _random(**change: object) -> tuple[dict, dict]:
    return {"cameras": [RANDOM]}, {"cameras": [{"random_orbits": {
        **RANDOM["random_orbits"], **change}}]}


def _material(**change: object) -> tuple[dict, dict]:
    return {**PBR, "lights": [SUN], "materials": [MATERIAL]}, {
        **PBR, "lights": [SUN], "materials": [{**MATERIAL, **change}]}


def _shadow(light: dict, kind: str, base: dict, **change: object) -> tuple[dict, dict]:
    return (_light({**light, "shadows": base}),
            _light({**light, "shadows": {**base, **change}}))


#: (light, kind) -> {shadow field: (base shadows block, change)}; cascade fields only act
#: on directional lights (point / spot lights refuse them: an error is a changed outcome).
_SHADOW_CHANGES: dict[str, tuple[dict, dict]] = {
    "enabled": ({}, {"enabled": False}),
    "map_size": ({"filter": "hard"}, {"map_size": 8}),
    "filter": ({"filter": "hard", "map_size": 32}, {"filter": "vsm"}),
    "pcf_radius": ({"filter": "pcf", "map_size": 32}, {"pcf_radius": 6.0}),
    "pcf_taps": ({"filter": "pcf", "pcf_radius": 4.0, "map_size": 32}, {"pcf_taps": 2}),
    "pcf_pattern": ({"filter": "pcf", "pcf_radius": 4.0, "pcf_taps": 9},
                    {"pcf_pattern": "grid"}),
    "bias": ({"filter": "hard"}, {"bias": 1000.0}),
    "slope_bias": ({"filter": "hard"}, {"slope_bias": 1000.0}),
    "normal_bias": ({"filter": "hard"}, {"normal_bias": 1000.0}),
    "intensity": ({}, {"intensity": 0.3}),
    "cascades": ({"filter": "hard", "max_distance": 3.0}, {"cascades": 3}),
    "split_lambda": ({"filter": "hard", "cascades": 3, "map_size": 32, "max_distance": 3.0},
                     {"split_lambda": 0.0}),
    # a short max_distance makes the cascades smaller than the scene (each its own map)
    "cascade_blend": ({"filter": "hard", "cascades": 2, "map_size": 12, "max_distance": 4.0,
                       "split_lambda": 0.0, "cascade_blend": 0.0}, {"cascade_blend": 0.5}),
    "max_distance": ({"filter": "hard"}, {"max_distance": 0.5}),
    # metres for point / spot lights, degrees for the sun: 20 is a wide penumbra for both
    "light_size": ({"filter": "pcss", "map_size": 64, "light_size": 0.01},
                   {"light_size": 20.0}),
    "max_penumbra": ({"filter": "pcss", "light_size": 5.0, "map_size": 256},
                     {"max_penumbra": 0.5}),
    "vsm_blur": ({"filter": "vsm"}, {"vsm_blur": 8.0}),
    # a 256² map: texels much smaller than the test's pixels, so the footprint widens PCF
    "pixel_radius": ({"filter": "pcf", "map_size": 256}, {"pixel_radius": 8.0}),
    "vsm_bleed": ({"filter": "vsm", "vsm_blur": 6.0, "vsm_bleed": 0.0}, {"vsm_bleed": 0.9}),
    "vsm_min_variance": ({"filter": "vsm"}, {"vsm_min_variance": 0.5}),
}
SLANTED_SPOT = {**SPOT, "position": [1.5, 2.0, 0.0], "direction": [-1.5, -2.0, 0.0]}
CASCADE_KEYS = ("cascades", "split_lambda", "cascade_blend", "max_distance")


def _shadow_variation(kind: str, light: dict, key: str) -> tuple[dict, dict]:
    base, change = _SHADOW_CHANGES[key]
    if kind != "directional" and key in CASCADE_KEYS or (kind, key) == ("area", "light_size"):
        base = {}  # refused on point / spot lights: the change alone must name the key
    if kind == "area":  # an area light's PCSS size is its own (light_size is refused)
        base = {k: v for k, v in base.items() if k != "light_size"}
    if (kind, key) == ("spot", "slope_bias"):
        light = SLANTED_SPOT  # a spot straight down meets the ground at slope 0
    return _shadow(light, kind, base, **change)


SHADOW_VARIATIONS = {
    f"lights.{kind}.shadows.{key}": _shadow_variation(kind, light, key)
    for kind, light in (("directional", SUN), ("point", POINT), ("spot", SPOT),
                        ("area", AREA))
    for key in _SHADOW_CHANGES}
# cascade boundaries show with the camera close to the ground (slices smaller than the
# scene, each cascade its own map) and more than 16 pixels
_NEAR_VIEW = {"cameras": [{"orbit": {"azimuth_deg": 30.0, "elevation_deg": 25.0,
                                     "distance": 1.6}}],
              "render": {"resolution": 48, "shading": "pbr"}}
for _key in ("cascade_blend", "split_lambda"):
    _b, _c = SHADOW_VARIATIONS[f"lights.directional.shadows.{_key}"]
    SHADOW_VARIATIONS[f"lights.directional.shadows.{_key}"] = ({**_b, **_NEAR_VIEW},
                                                               {**_c, **_NEAR_VIEW})
PRIMITIVE = {"name": "block", "primitive": "box", "size": 0.6,
             "transform": {"translate": [0.8, 0.3, 0.3]}}
OBJECT_BASE = {**PBR, "lights": [{**SUN, "cast_shadows": True}],
               "scene": {"objects": [PRIMITIVE]}}


def _object(**change: object) -> tuple[dict, dict]:
    return OBJECT_BASE, {**OBJECT_BASE, "scene": {"objects": [{**PRIMITIVE, **change}]}}


TWO_GLASS = {**OBJECT_BASE, "scene": {"objects": [
    {**PRIMITIVE, "material": {"base_color": [1, 0, 0, 0.5], "alpha_mode": "BLEND"}},
    {**PRIMITIVE, "transform": {"translate": [0.8, 0.3, -0.6]},
     "material": {"base_color": [0, 0, 1, 0.5], "alpha_mode": "BLEND"}}]}}

OBJECT_VARIATIONS = {
    "scene.objects.mesh": ({**OBJECT_BASE, "scene": {"objects": [
        {"primitive": "box", "size": 0.6, "transform": PRIMITIVE["transform"]}]}},
        {**OBJECT_BASE, "scene": {"objects": [{"mesh": "quad.obj",
                                               "transform": PRIMITIVE["transform"]}]}}),
    "scene.objects.primitive": _object(primitive="sphere"),
    "scene.objects.size": _object(size=1.2),
    "scene.objects.transform.translate": _object(transform={"translate": [-0.8, 0.3, 0.3]}),
    "scene.objects.transform.rotate_deg": _object(transform={**PRIMITIVE["transform"],
                                                             "rotate_deg": [0, 30, 20]}),
    "scene.objects.transform.scale": _object(transform={**PRIMITIVE["transform"],
                                                        "scale": [1.0, 2.0, 1.0]}),
    "scene.objects.material.base_color": _object(material={"base_color": [1.0, 0.1, 0.1]}),
    "scene.objects.material.metallic": _object(material={"metallic": 1.0}),
    "scene.objects.material.roughness": _object(material={"roughness": 0.1}),
    "scene.objects.material.emissive": _object(material={"emissive": [2.0, 0.0, 0.0]}),
    # the name only matters to `materials:` overrides that match it
    "scene.objects.material.name": (
        {**OBJECT_BASE, "materials": [{"match": "paint", "base_color": [0.1, 0.9, 0.1]}]},
        {**OBJECT_BASE, "materials": [{"match": "paint", "base_color": [0.1, 0.9, 0.1]}],
         "scene": {"objects": [{**PRIMITIVE, "material": {"name": "paint"}}]}}),
    "scene.objects.material.base_color_texture": _object(
        material={"base_color_texture": "override.png"}),
    "scene.objects.material.alpha_mode": _object(
        material={"base_color": [1.0, 1.0, 1.0, 0.3], "alpha_mode": "BLEND"}),
    "scene.objects.material.alpha_cutoff": (
        {**OBJECT_BASE, "scene": {"objects": [{**PRIMITIVE, "material": {
            "base_color": [1.0, 1.0, 1.0, 0.5], "alpha_mode": "MASK", "alpha_cutoff": 0.4}}]}},
        {**OBJECT_BASE, "scene": {"objects": [{**PRIMITIVE, "material": {
            "base_color": [1.0, 1.0, 1.0, 0.5], "alpha_mode": "MASK", "alpha_cutoff": 0.6}}]}}),
    # two blended boxes in a row: with one layer only the front one is seen
    "render.alpha_layers": ({**TWO_GLASS, "render": {"alpha_layers": 4, "shading": "pbr"}},
                            {**TWO_GLASS, "render": {"alpha_layers": 1, "shading": "pbr"}}),
    "render.antialias": ({}, {"render": {"antialias": True}}),
    # a rough metal under the sun: the compensated lobe is brighter
    "render.multiscatter": ({**PBR, "lights": [SUN], "materials": [{**MATERIAL, "metallic": 1.0,
                                                                     "roughness": 1.0}]},
                            {"render": {"shading": "pbr", "multiscatter": False},
                             "lights": [SUN], "materials": [{**MATERIAL, "metallic": 1.0,
                                                             "roughness": 1.0}]}),
    "scene.objects.cast_shadows": _object(cast_shadows=False),
    # a sun from the side: the ball's shadow falls on the box
    "scene.objects.receive_shadows": (
        {**OBJECT_BASE, "lights": [{**SUN, "direction": [1.0, -0.4, 0.0], "cast_shadows": True}]},
        {**OBJECT_BASE, "lights": [{**SUN, "direction": [1.0, -0.4, 0.0], "cast_shadows": True}],
         "scene": {"objects": [{**PRIMITIVE, "receive_shadows": False}]}}),
    "scene.cast_shadows": (OBJECT_BASE, {**OBJECT_BASE, "scene": {"cast_shadows": False}}),
    "scene.receive_shadows": (OBJECT_BASE, {**OBJECT_BASE,
                                            "scene": {"receive_shadows": False}}),
}


# volumetric fog: a point light (always marched) in fog with a little ambient glow
FOG = {"density": 0.3, "ambient": [0.2, 0.2, 0.2], "steps": 4, "blur": 0.0}


def _fog(base: dict | None = None, **change: object) -> tuple[dict, dict]:
    base = FOG if base is None else base
    return ({"render": {"shading": "pbr", "fog": base}, "lights": [POINT]},
            {"render": {"shading": "pbr", "fog": {**base, **change}}, "lights": [POINT]})


FOG_VARIATIONS = {
    "render.fog.enabled": _fog({**FOG, "enabled": False}, enabled=True),
    "render.fog.density": _fog(density=1.0),
    "render.fog.height_falloff": _fog(height_falloff=2.0),
    "render.fog.base_height": _fog({**FOG, "height_falloff": 1.0}, base_height=1.0),
    "render.fog.color": _fog(color=[1.0, 0.5, 0.2]),
    "render.fog.ambient": _fog(ambient=[0.5, 0.0, 0.0]),
    "render.fog.anisotropy": _fog(anisotropy=0.8),
    "render.fog.steps": _fog(steps=1),
    "render.fog.jitter": _fog(jitter=False),
    "render.fog.blur": _fog(blur=2.0),
    "render.fog.max_distance": _fog(max_distance=2.0),
    "render.fog.seed": _fog(seed=3),
    "render.fog.light_transmittance": _fog(light_transmittance=False),
}


# shading models, background image, dissolve (issue 12 item 3)
TOON = {"lights": [SUN], "render": {"shading": "toon"}}


def _toon(base: dict, **change: object) -> tuple[dict, dict]:
    return ({**TOON, "render": {"shading": "toon", "toon": base}},
            {**TOON, "render": {"shading": "toon", "toon": {**base, **change}}})


# a square image in a 16 x 12 frame: cover crops it, contain letterboxes it
BG_FRAME = {"resolution": [16, 12], "background": [0.0, 1.0, 0.0]}
DISSOLVE = {"threshold": 0.5}


def _dissolve(**change: object) -> tuple[dict, dict]:
    return ({"render": {"dissolve": DISSOLVE}},
            {"render": {"dissolve": {**DISSOLVE, **change}}})


STYLE_VARIATIONS = {
    "render.toon.bands": _toon({"bands": 3}, bands=1),
    "render.toon.rim": _toon({"rim_width": 0.9}, rim=2.0),
    "render.toon.rim_width": _toon({"rim": 2.0, "rim_width": 0.1}, rim_width=0.9),
    "render.background_image.path": (
        {"render": {**BG_FRAME, "background_image": {"path": "tex.png"}}},
        {"render": {**BG_FRAME, "background_image": {"path": "override.png"}}}),
    "render.background_image.fit": (
        {"render": {**BG_FRAME, "background_image": {"path": "tex.png"}}},
        {"render": {**BG_FRAME, "background_image": {"path": "tex.png", "fit": "contain"}}}),
    "render.dissolve.threshold": _dissolve(threshold=0.3),
    "render.dissolve.edge_width": _dissolve(edge_width=0.3),
    "render.dissolve.edge_color": _dissolve(edge_color=[0.0, 1.0, 0.0]),
    "render.dissolve.edge_intensity": _dissolve(edge_intensity=10.0),
    "render.dissolve.scale": _dissolve(scale=1.0),
    "render.dissolve.octaves": _dissolve(octaves=1),
    "render.dissolve.seed": _dissolve(seed=5),
}


#: Two frames half a second apart, with the flow channels: the dataset fields act over time.
TWO_FRAMES = {"frames": {"count": 2, "fps": 2.0},
              "outputs": {"channels": CHANNELS + sorted(FLOW_CHANNELS), "formats": ["npy"]}}
KEYS = [{"time": 0.0}, {"time": 1.0, "translate": [0.3, 0.0, 0.0], "rotate_deg": [0, 40, 0],
                        "scale": 1.2}]


def _animated(where: str, **change: object) -> tuple[dict, dict]:
    """The main mesh (``scene``) or an object (``object``) animated; ``change`` edits the
    animation (``keys`` entries: {index: {field: value}})."""
    key_change = change.pop("keys", {})
    keys = [{**k, **key_change.get(i, {})} for i, k in enumerate(KEYS)]
    base_anim, anim = {"keys": KEYS}, {**change, "keys": keys}
    if where == "scene":
        return ({**TWO_FRAMES, "scene": {"animation": base_anim}},
                {**TWO_FRAMES, "scene": {"animation": anim}})
    obj = {**PRIMITIVE}
    return ({**OBJECT_BASE, **TWO_FRAMES, "scene": {"objects": [{**obj, "animation": base_anim}]}},
            {**OBJECT_BASE, **TWO_FRAMES, "scene": {"objects": [{**obj, "animation": anim}]}})


TRAJECTORY = {"trajectory": {"keys": [
    {"time": 0.0, "eye": [0.5, 1.5, 3.5], "target": [0.0, 0.4, 0.0]},
    {"time": 1.0, "eye": [2.5, 1.0, 2.5], "target": [0.0, 0.4, 0.0]}]}}


def _trajectory(**key1: object) -> tuple[dict, dict]:
    keys = TRAJECTORY["trajectory"]["keys"]
    return ({**TWO_FRAMES, "cameras": [TRAJECTORY]},
            {**TWO_FRAMES, "cameras": [{"trajectory": {"keys": [keys[0], {**keys[1], **key1}]}}]})


def _merge(base: dict, patch: dict) -> dict:
    out = copy.deepcopy(base)
    for key, value in patch.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


#: Fields holding a model whose every field is varied elsewhere: one variation each here.
#: (A random value, DistConfig, is a leaf too: test_random_values_follow_their_distribution.)
SHARED_MODELS = {"randomize.lights.shadows": "lights.directional.shadows"}

#: A randomised scene: boxes drawn onto the stage's ground, lit by a sun.
RZ = {"seed": 1, "objects": {"count": 3, "pool": [{"primitive": "box", "size": 0.4}],
                             "bounds": [-1.5, -1.5, 1.5, 1.5]}}


def _rz(base: dict | None = None, **change: object) -> tuple[dict, dict]:
    """(base, changed) randomised configs: ``change`` replaces keys of the randomize block
    (``objects``: of its objects block)."""
    rz = _merge(RZ, base or {})
    objects = change.pop("objects", None)
    changed = _merge(rz, change)
    if objects is not None:
        changed["objects"] = _merge(changed["objects"], objects)
    extra = {**PBR, "lights": [SUN]}
    if "velocity" in (objects or {}) or "spin_deg_per_s" in (objects or {}):
        extra.update(TWO_FRAMES)
    return {**extra, "randomize": rz}, {**extra, "randomize": changed}


RANDOM_VARIATIONS = {
    "randomize.seed": _rz(seed=2),
    "randomize.scenes": _rz(scenes=2),
    "randomize.objects.count": _rz(objects={"count": 2}),
    "randomize.objects.pool.mesh": _rz(objects={"pool": [{"mesh": "pebble.obj"}]}),
    "randomize.objects.pool.primitive": _rz(objects={"pool": [{"primitive": "sphere",
                                                               "size": 0.4}]}),
    "randomize.objects.pool.size": _rz(objects={"pool": [{"primitive": "box", "size": 0.3}]}),
    "randomize.objects.pool.category": _rz(objects={"pool": [{"primitive": "box", "size": 0.4,
                                                              "category": "rock"}]}),
    "randomize.objects.pool.weight": _rz(
        {"objects": {"pool": [{"primitive": "box", "size": 0.4}, {"primitive": "sphere"}]}},
        objects={"pool": [{"primitive": "box", "size": 0.4}, {"primitive": "sphere",
                                                              "weight": 0.0}]}),
    "randomize.objects.scale": _rz(objects={"scale": {"uniform": [0.5, 0.8]}}),
    "randomize.objects.bounds": _rz(objects={"bounds": [-1.0, -1.0, 1.0, 1.0]}),
    "randomize.objects.floor_y": _rz(objects={"floor_y": 0.3}),
    "randomize.objects.gap": _rz({"objects": {"count": 6}}, objects={"gap": 0.3}),
    "randomize.objects.max_tries": _rz(
        {"objects": {"count": 3, "bounds": [-0.7, -0.7, 0.7, 0.7], "max_tries": 1}},
        objects={"max_tries": 1000}),
    "randomize.objects.base_color": _rz(objects={"base_color": [1.0, 0.1, 0.1]}),
    "randomize.objects.roughness": _rz(objects={"roughness": 0.1}),
    "randomize.objects.metallic": _rz(objects={"metallic": 1.0}),
    "randomize.objects.textures": _rz(objects={"textures": "textures"}),
    "randomize.objects.velocity": _rz(objects={"velocity": [0.6, 0.0, 0.0]}),
    "randomize.objects.spin_deg_per_s": _rz(objects={"spin_deg_per_s": 90.0}),
    "randomize.lights.count": _rz({"lights": {"count": 1}}, lights={"count": 2}),
    **{f"randomize.lights.{key}": _rz({"lights": {}}, lights={key: value})
       for key, value in (("azimuth_deg", 90.0), ("elevation_deg", 80.0), ("intensity", 1.0),
                          ("color", [1.0, 0.2, 0.2]), ("shadows", {"map_size": 64}))},
    "randomize.environment.paths": _rz({"environment": {"paths": ["sky.hdr"]}},
                                       environment={"paths": ["dusk.hdr"]}),
    **{f"randomize.environment.{key}": _rz({"environment": {"paths": ["sky.hdr"]}},
                                           environment={"paths": ["sky.hdr"], key: value})
       for key, value in (("rotation_deg", 90.0), ("intensity", 0.5), ("background", False),
                          ("specular", "split_sum"), ("sun_threshold", 1.5), ("table_levels", 3),
                          ("table_views", 3), ("table_azimuths", 4))},
    "randomize.environment.importance_samples": _rz(
        {"environment": {"paths": ["sky.hdr"], "specular": "importance"}},
        environment={"paths": ["sky.hdr"], "specular": "importance", "importance_samples": 2}),
    **{f"randomize.camera.{key}": _rz({"camera": {}}, camera={key: value})
       for key, value in (("azimuth_deg", 60.0), ("elevation_deg", 40.0), ("distance", 5.0),
                          ("target", [0.2, 0.3, 0.0]), ("fov_deg", 30.0))},
    "randomize.background_images": _rz(background_images="textures"),
}

DATASET_VARIATIONS = {
    "frames.count": ({}, {"frames": {"count": 2}}),
    "frames.fps": (_animated("scene")[0], {**_animated("scene")[0],
                                           "frames": {"count": 2, "fps": 4.0}}),
    "categories": ({"categories": ["ball", "box"], "scene": {"category": "ball"}},
                   {"categories": ["box", "ball"], "scene": {"category": "ball"}}),
    "scene.category": ({}, {"scene": {"category": "ball"}}),
    "scene.objects.category": ({**OBJECT_BASE}, {**OBJECT_BASE, "scene": {"objects": [
        {**PRIMITIVE, "category": "box"}]}}),
    **{f"{prefix}.animation.interpolation": _animated(where, interpolation="step")
       for prefix, where in (("scene", "scene"), ("scene.objects", "object"))},
    **{f"{prefix}.animation.euler_order": _animated(where, euler_order="XYZ", keys={
        1: {"rotate_deg": [30, 40, 0]}}) for prefix, where in (("scene", "scene"),
                                                              ("scene.objects", "object"))},
    **{f"{prefix}.animation.keys.{field}": _animated(where, keys={1: {field: value}})
       for prefix, where in (("scene", "scene"), ("scene.objects", "object"))
       for field, value in (("time", 2.0), ("translate", [0.0, 0.3, 0.0]),
                            ("rotate_deg", [0, 80, 0]), ("scale", 0.7))},
    **{f"{prefix}.animation.keys.rotation": _animated(where, keys={
        1: {"rotate_deg": None, "rotation": [0.9, 0.0, 0.44, 0.0]}})
       for prefix, where in (("scene", "scene"), ("scene.objects", "object"))},
    "cameras.orbit.degrees_per_second": (
        {**TWO_FRAMES, "cameras": [ORBIT]},
        {**TWO_FRAMES, "cameras": [{"orbit": {**ORBIT["orbit"], "degrees_per_second": 30}}]}),
    "cameras.trajectory.interpolation": (
        {**TWO_FRAMES, "cameras": [TRAJECTORY]},
        {**TWO_FRAMES, "cameras": [{"trajectory": {**TRAJECTORY["trajectory"],
                                                   "interpolation": "step"}}]}),
    "cameras.trajectory.keys.time": _trajectory(time=2.0),
    "cameras.trajectory.keys.eye": _trajectory(eye=[-2.5, 1.0, 2.5]),
    "cameras.trajectory.keys.target": _trajectory(target=[0.3, 0.2, 0.0]),
    "cameras.trajectory.keys.up": _trajectory(up=[0.3, 1.0, 0.0]),
}

#: field key path -> (base patch, changed patch); patches are merged into BASE (mappings
#: recursively, lists replaced).
VARIATIONS: dict[str, tuple[dict, dict]] = {
    # scene
    "scene.mesh": ({}, {"scene": {"mesh": "quad.obj"}}),
    "scene.transform.translate": ({}, {"scene": {"transform": {"translate": [0.3, 0, 0]}}}),
    "scene.transform.rotate_deg": ({}, {"scene": {"transform": {"rotate_deg": [0, 40, 0]}}}),
    "scene.transform.scale": ({}, {"scene": {"transform": {"scale": 2.0}}}),
    "scene.normals": ({}, {"scene": {"normals": "flat"}}),
    "scene.max_texture_size": ({}, {"scene": {"max_texture_size": 1}}),
    "scene.allow_missing_textures": ({"scene": {"mesh": "missing.obj"}}, {
        "scene": {"mesh": "missing.obj", "allow_missing_textures": True}}),
    # a mesh set: the listed objects are rendered (and named) instead of stage.obj
    "scene.meshes_from": ({}, {"scene": {"mesh": None, "meshes_from": "meshes.txt"}}),
    # cameras
    "cameras.projection": _camera(ORBIT, projection="orthographic"),
    "cameras.fov_deg": _camera(ORBIT, fov_deg=30.0),
    **{f"cameras.intrinsics.{key}": _camera({**ORBIT, "intrinsics": INTRINSICS},
                                            intrinsics={**INTRINSICS, key: value})
       for key, value in (("fx", 30), ("fy", 30), ("cx", 5), ("cy", 5))},
    "cameras.ortho_height": _camera({**ORBIT, "projection": "orthographic"}, ortho_height=1.0),
    "cameras.near": _camera(ORBIT, near=3.7),
    "cameras.far": _camera(ORBIT, far=3.8),
    # a decal 0.2 mm above the ground, 4 m away: standard float32 depth with near 1e-4 cannot
    # separate them (ties go to the ground, listed first), reverse-Z can
    "cameras.reverse_z": ({"scene": {"mesh": "decal.obj"}, "cameras": [DECAL_VIEW]}, {
        "scene": {"mesh": "decal.obj"}, "cameras": [{**DECAL_VIEW, "reverse_z": True}]}),
    "cameras.orbit.azimuth_deg": _camera(ORBIT, orbit={**ORBIT["orbit"], "azimuth_deg": 80}),
    "cameras.orbit.elevation_deg": _camera(ORBIT, orbit={**ORBIT["orbit"],
                                                         "elevation_deg": 50}),
    "cameras.orbit.distance": _camera(ORBIT, orbit={**ORBIT["orbit"], "distance": 6.0}),
    "cameras.orbit.target": _camera(ORBIT, orbit={**ORBIT["orbit"], "target": [0.5, 0, 0]}),
    "cameras.look_at.eye": _camera(LOOK, look_at={**LOOK["look_at"], "eye": [2.0, 1.0, 3.0]}),
    "cameras.look_at.target": _camera(LOOK, look_at={**LOOK["look_at"],
                                                     "target": [0.4, 0.4, 0.0]}),
    "cameras.look_at.up": _camera(LOOK, look_at={**LOOK["look_at"], "up": [1.0, 1.0, 0.0]}),
    "cameras.random_orbits.count": _random(count=3),
    "cameras.random_orbits.seed": _random(seed=1),
    "cameras.random_orbits.azimuth_deg": _random(azimuth_deg=[90.0, 100.0]),
    "cameras.random_orbits.elevation_deg": _random(elevation_deg=[50.0, 60.0]),
    "cameras.random_orbits.distance": _random(distance=[6.0, 8.0]),
    "cameras.random_orbits.target": _random(target=[0.5, 0.0, 0.0]),
    # render
    "render.resolution": ({}, {"render": {"resolution": [16, 12]}}),
    "render.shading": ({}, {"render": {"shading": "unlit"}}),
    "render.background": ({}, {"render": {"background": [0.5, 0.2, 0.1]}}),
    "render.supersample": ({}, {"render": {"supersample": 2}}),
    "render.edge_supersample": ({}, {"render": {"edge_supersample": 2}}),
    "render.cull_backfaces": ({"cameras": [INSIDE]}, {"cameras": [INSIDE],
                                                      "render": {"cull_backfaces": True}}),
    "render.texture_filter": ({}, {"render": {"texture_filter": "nearest"}}),
    "render.max_anisotropy": ({"render": {"texture_filter": "anisotropic"}}, {
        "render": {"texture_filter": "anisotropic", "max_anisotropy": 2}}),
    # lights
    "lights.ambient.type": (_light(AMBIENT), _light({**AMBIENT, "type": "directional"})),
    "lights.ambient.color": (_light(AMBIENT), _light(AMBIENT, color=[0.1, 0.3, 0.2])),
    "lights.ambient.intensity": (_light(AMBIENT), _light(AMBIENT, intensity=2.0)),
    "lights.ambient.sh": (_light(AMBIENT), _light(AMBIENT, sh=SH)),
    "lights.directional.type": (_light(SUN), _light({**SUN, "type": "spot"})),
    "lights.directional.color": (_light(SUN), _light(SUN, color=[1.0, 0.5, 0.2])),
    "lights.directional.intensity": (_light(SUN), _light(SUN, intensity=1.0)),
    "lights.directional.direction": (_light(SUN), _light(SUN, direction=[0.5, -1.0, 0.0])),
    "lights.directional.cast_shadows": (_light(SUN), _light(SUN, cast_shadows=True)),
    "lights.point.type": (_light(POINT), _light({**POINT, "type": "spot"})),
    "lights.point.color": (_light(POINT), _light(POINT, color=[1.0, 0.5, 0.2])),
    "lights.point.intensity": (_light(POINT), _light(POINT, intensity=1.0)),
    "lights.point.position": (_light(POINT), _light(POINT, position=[-0.8, 1.6, 0.6])),
    "lights.point.range": (_light(POINT), _light(POINT, range=1.5)),
    "lights.point.cast_shadows": (_light(POINT), _light(POINT, cast_shadows=True)),
    "lights.spot.type": (_light(SPOT), _light({"type": "point", "position": SPOT["position"],
                                                "intensity": SPOT["intensity"]})),
    "lights.spot.color": (_light(SPOT), _light(SPOT, color=[1.0, 0.5, 0.2])),
    "lights.spot.intensity": (_light(SPOT), _light(SPOT, intensity=2.0)),
    "lights.spot.position": (_light(SPOT), _light(SPOT, position=[0.5, 2.5, 0.0])),
    "lights.spot.direction": (_light(SPOT), _light(SPOT, direction=[0.3, -1.0, 0.0])),
    "lights.spot.range": (_light(SPOT), _light(SPOT, range=2.3)),
    "lights.spot.inner_cone_angle": (_light(SPOT), _light(SPOT, inner_cone_angle=0.0)),
    "lights.spot.outer_cone_angle": (_light(SPOT), _light(SPOT, outer_cone_angle=0.3)),
    "lights.spot.cast_shadows": (_light(SPOT), _light(SPOT, cast_shadows=True)),
    "lights.area.type": (_light(DISC), _light({"type": "spot", "position": DISC["position"],
                                                "direction": DISC["direction"]})),
    "lights.area.color": (_light(AREA), _light(AREA, color=[1.0, 0.5, 0.2])),
    "lights.area.intensity": (_light(AREA), _light(AREA, intensity=1.0)),
    "lights.area.position": (_light(AREA), _light(AREA, position=[-0.5, 1.2, 0.4])),
    "lights.area.direction": (_light(AREA), _light(AREA, direction=[0.6, -1.0, 0.3])),
    "lights.area.size": (_light(AREA), _light(AREA, size=[2.0, 0.2])),
    "lights.area.up": (_light(AREA, size=[3.0, 0.2]), _light(AREA, size=[3.0, 0.2],
                                                              up=[1.0, 0.0, 0.0])),
    "lights.area.shape": (_light({**DISC, "shape": "rect", "radius": None}), _light(DISC)),
    "lights.area.radius": (_light(DISC), _light(DISC, radius=0.8)),
    # facing up, away from the ground and the ball: only its back side lights them
    "lights.area.two_sided": (_light(AREA, direction=[0.0, 1.0, 0.0]),
                              _light(AREA, direction=[0.0, 1.0, 0.0], two_sided=True)),
    "lights.area.cast_shadows": (_light(AREA), _light(AREA, cast_shadows=True)),
    # environment
    "environment.path": ({"environment": {"path": "sky.hdr"}},
                         {"environment": {"path": "dusk.hdr"}}),
    "environment.intensity": ({"environment": {"path": "sky.hdr"}},
                              {"environment": {"path": "sky.hdr", "intensity": 0.3}}),
    "environment.rotation_deg": ({"environment": {"path": "sky.hdr"}},
                                 {"environment": {"path": "sky.hdr", "rotation_deg": 90}}),
    "environment.background": ({"environment": {"path": "sky.hdr"}},
                               {"environment": {"path": "sky.hdr", "background": False}}),
    "environment.specular": ({**PBR, "environment": {"path": "sky.hdr"}},
                             {**PBR, "environment": {"path": "sky.hdr",
                                                     "specular": "importance"}}),
    "environment.importance_samples": (
        {**PBR, "environment": {"path": "sky.hdr", "specular": "importance"}},
        {**PBR, "environment": {"path": "sky.hdr", "specular": "importance",
                                "importance_samples": 2}}),
    "environment.sun_threshold": ({**PBR, "environment": {"path": "sky.hdr"}},
                                  {**PBR, "environment": {"path": "sky.hdr",
                                                          "sun_threshold": 1.5}}),
    **{f"environment.{key}": ({**PBR, "environment": {"path": "sky.hdr"}},
                              {**PBR, "environment": {"path": "sky.hdr", key: value}})
       for key, value in (("table_levels", 3), ("table_views", 3), ("table_azimuths", 4))},
    # materials
    "materials.match": _material(match="no such material"),
    "materials.base_color": _material(base_color=[0.1, 0.2, 1.0]),
    "materials.metallic": _material(metallic=1.0),
    "materials.roughness": _material(roughness=0.1),
    "materials.emissive": _material(emissive=[0.5, 0.0, 0.0]),
    "materials.base_color_texture": _material(base_color_texture="override.png"),
    # post
    "post.dof.enabled": _post("dof", {**DOF, "enabled": False}, enabled=True),
    **{f"post.dof.{key}": _post("dof", DOF, **{key: value}) for key, value in (
        ("focus_distance", 4.0), ("focal_length_mm", 35.0), ("f_number", 8.0),
        ("sensor_width_mm", 8.0), ("max_coc", 2.0), ("levels", 2))},
    "post.bloom.enabled": _post("bloom", {**BLOOM, "enabled": False}, enabled=True),
    **{f"post.bloom.{key}": _post("bloom", BLOOM, **{key: value}) for key, value in (
        ("threshold", 0.1), ("knee", 0.0), ("intensity", 0.5), ("radius", 3.0), ("levels", 1),
        ("karis", True))},
    "post.exposure.enabled": _post("exposure", {"ev": 1.0}, enabled=False),
    "post.exposure.ev": _post("exposure", {"ev": 0.0}, ev=1.0),
    "post.auto_exposure.enabled": _post("auto_exposure", {}, enabled=True),
    "post.auto_exposure.key": _post("auto_exposure", AUTO, key=0.5),
    "post.auto_exposure.min_ev": _post("auto_exposure", AUTO, min_ev=12.0),
    "post.auto_exposure.max_ev": _post("auto_exposure", AUTO, max_ev=-3.0),
    "post.auto_exposure.metering": _post("auto_exposure", AUTO, metering="average"),
    "post.auto_exposure.percentile_low": _post("auto_exposure", AUTO, percentile_low=0.6),
    "post.auto_exposure.percentile_high": _post("auto_exposure", AUTO, percentile_high=0.3),
    "post.auto_exposure.rate": _post("auto_exposure", AUTO, rate=5.0),
    "post.tonemap.enabled": _post("tonemap", {}, enabled=False),
    "post.tonemap.curve": _post("tonemap", {}, curve="hable"),
    "post.tonemap.white": _post("tonemap", {"curve": "reinhard_extended", "white": 4.0},
                                white=1.5),
    "post.encode.enabled": _post("encode", {}, enabled=False),
    "post.ssao.enabled": ({**SSAO_BASE, "post": {"ssao": {**SSAO, "enabled": False}}},
                          {**SSAO_BASE, "post": {"ssao": SSAO}}),
    **{f"post.ssao.{key}": ({**SSAO_BASE, "post": {"ssao": SSAO}},
                            {**SSAO_BASE, "post": {"ssao": {**SSAO, key: value}}})
       for key, value in (("radius", 2.0), ("samples", 2), ("bias", 0.5), ("softness", 0.1),
                          ("blur", True))},
    "post.ssr.enabled": ({**SSR_BASE, "post": {"ssr": {**SSR, "enabled": False}}},
                         {**SSR_BASE, "post": {"ssr": SSR}}),
    **{f"post.ssr.{key}": ({**SSR_BASE, "post": {"ssr": SSR}},
                           {**SSR_BASE, "post": {"ssr": {**SSR, key: value}}})
       for key, value in (("max_steps", 1), ("thickness", 0.001), ("max_roughness", 0.2),
                          ("edge_fade", 0.5), ("refine_steps", 0), ("max_distance", 0.05),
                          ("blur", False))},
    # outputs
    "outputs.channels": ({}, {"outputs": {"channels": ["color", "depth"]}}),
    **SHADOW_VARIATIONS,
    **OBJECT_VARIATIONS,
    **STYLE_VARIATIONS,
    **FOG_VARIATIONS,
    **DATASET_VARIATIONS,
    **RANDOM_VARIATIONS,
}

#: What every variation starts from: a textured ball on a ground plane, all channels.
BASE: dict = {"scene": {"mesh": "stage.obj"},
              "cameras": [ORBIT],
              "render": {"resolution": 16, "shading": "headlight"},
              "outputs": {"channels": CHANNELS, "formats": ["npy"]}}


# ------------------------------------------------------------------------------- walker
def _models(annotation: object) -> list[type[BaseModel]]:
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for arg in typing.get_args(annotation) for m in _models(arg)]


def _light_type(model: type[BaseModel]) -> str | None:
    field = model.model_fields.get("type")
    args = typing.get_args(field.annotation) if field is not None else ()
    return args[0] if len(args) == 1 and isinstance(args[0], str) else None


def config_fields(model: type[BaseModel] = RenderFile, prefix: str = "") -> set[str]:
    """Key paths of every leaf field (a field holding a model is walked into instead;
    union members with a literal ``type`` get ``<type>`` in the path)."""
    out: set[str] = set()
    for name, field in model.model_fields.items():
        if field.exclude:
            continue
        path = f"{prefix}{name}"
        subs = [m for m in _models(field.annotation) if m is not DistConfig]
        if not subs or path in SHARED_MODELS:
            out.add(path)
            continue
        for sub in subs:
            kind = _light_type(sub)
            out |= config_fields(sub, f"{path}.{kind}." if kind and len(subs) > 1
                                 else f"{path}.")
    return out


def test_every_config_field_is_accounted_for():
    fields = config_fields()
    known = set(VARIATIONS) | set(METADATA)
    missing = sorted(fields - known)
    assert not missing, (
        f"config field(s) {missing} are neither shown to change the render (add a "
        "(base, change) entry to VARIATIONS in tests/test_config_fields.py) nor listed in "
        "METADATA with a reason; a field that is accepted but cannot act must raise "
        "NotImplementedError naming it (then add it to NOT_IMPLEMENTED too)")
    stale = sorted(known - fields)
    assert not stale, f"tests/test_config_fields.py names field(s) {stale} the schema lacks"
    assert NOT_IMPLEMENTED <= set(VARIATIONS)


# -------------------------------------------------------------------------------- assets
def _obj(path: Path, meshes: list[tuple[trimesh.Trimesh, str]], mtl: str) -> None:
    """Write meshes (with planar UVs) into one OBJ with one material each."""
    lines = [f"mtllib {mtl}"]
    offset = 0
    for mesh, material in meshes:
        v = np.asarray(mesh.vertices)
        uv = (v[:, [0, 2]] - v[:, [0, 2]].min(0)) / np.ptp(v[:, [0, 2]], 0).clip(1e-9)
        lines += [f"v {a:.6f} {b:.6f} {c:.6f}" for a, b, c in v]
        lines += [f"vt {a:.6f} {b:.6f}" for a, b in uv]
        lines.append(f"usemtl {material}")
        lines += ["f " + " ".join(f"{i + 1 + offset}/{i + 1 + offset}" for i in f)
                  for f in np.asarray(mesh.faces)]
        offset += len(v)
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def assets(tmp_path_factory) -> Path:
    """A textured ball on a ground plane, a quad, a mesh whose texture is missing, an image
    and two environment maps."""
    root = tmp_path_factory.mktemp("fields")
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    ball.apply_translation([0.0, 0.5, 0.0])
    ground = trimesh.Trimesh([[-1.5, 0, -1.5], [-1.5, 0, 1.5], [1.5, 0, 1.5], [1.5, 0, -1.5]],
                             [[0, 1, 2], [0, 2, 3]], process=False)
    g = np.random.default_rng(0)
    skio.imsave(root / "tex.png", g.integers(0, 256, (8, 8, 3), dtype=np.uint8),
                check_contrast=False)
    skio.imsave(root / "override.png", g.integers(0, 256, (4, 4, 3), dtype=np.uint8),
                check_contrast=False)
    (root / "stage.mtl").write_text("newmtl ball\nKd 1 1 1\nmap_Kd tex.png\n"
                                    "newmtl ground\nKd 0.7 0.7 0.7\n")
    _obj(root / "stage.obj", [(ball, "ball"), (ground, "ground")], "stage.mtl")
    _obj(root / "quad.obj", [(ground, "ground")], "stage.mtl")
    (root / "meshes.txt").write_text("# a mesh set\nquad.obj\n")
    decal = ground.copy()
    decal.apply_transform(np.diag([0.5, 1.0, 0.5, 1.0]))
    decal.apply_translation([0.0, 0.0002, 0.0])
    _obj(root / "decal.obj", [(ground, "ground"), (decal, "ball")], "stage.mtl")
    (root / "missing.mtl").write_text("newmtl ball\nKd 1 1 1\nmap_Kd no_such_file.png\n")
    _obj(root / "missing.obj", [(ball, "ball")], "missing.mtl")
    rows = torch.linspace(2.0, 0.1, 8)[None, :, None].expand(3, 8, 16).clone()
    rows[0, :, :8] *= 3.0  # a warm half, so a rotation shows
    write_hdr(root / "sky.hdr", rows)
    write_hdr(root / "dusk.hdr", torch.full((3, 8, 16), 0.4))
    pebble = trimesh.creation.icosphere(subdivisions=1, radius=0.2)
    _obj(root / "pebble.obj", [(pebble, "ground")], "stage.mtl")
    (root / "textures").mkdir()
    for name in ("a.png", "b.png"):
        skio.imsave(root / "textures" / name, g.integers(0, 256, (4, 4, 3), dtype=np.uint8),
                    check_contrast=False)
    return root


def _outcome(data: dict, root: Path, cache: dict) -> object:
    """The images of every view, or the exception a config ends in."""
    text = yaml.safe_dump(data, sort_keys=True)
    if text not in cache:
        try:
            cfg = tr.parse_config(text, "fields.yaml", base_dir=root)
            check_config(cfg)
            cache[text] = {(r.name, ch): img for r in render_config(cfg)
                           for ch, img in r.images.items()}
        except Exception as e:  # noqa: BLE001 - the outcome is what is compared
            cache[text] = e
    return cache[text]


def _same(a: object, b: object) -> bool:
    if isinstance(a, BaseException) or isinstance(b, BaseException):
        return type(a) is type(b) and str(a) == str(b)
    return a.keys() == b.keys() and all(  # type: ignore[union-attr]
        a[k].shape == b[k].shape and torch.equal(a[k], b[k]) for k in a)  # type: ignore[index]


@pytest.fixture(scope="module")
def outcomes() -> dict:
    return {}


@pytest.mark.parametrize("path", sorted(VARIATIONS))
def test_changing_a_config_field_changes_the_render(path: str, assets: Path, outcomes: dict):
    base_patch, change_patch = VARIATIONS[path]
    base = _outcome(_merge(BASE, base_patch), assets, outcomes)
    changed = _outcome(_merge(BASE, change_patch), assets, outcomes)
    if path in NOT_IMPLEMENTED:
        assert isinstance(changed, NotImplementedError), changed
        assert path in str(changed)
        assert not isinstance(base, BaseException), base
        return
    if isinstance(changed, NotImplementedError):
        assert path in str(changed), f"{path}: NotImplementedError not naming it: {changed}"
        return
    if path in REFUSED:  # the field cannot act there, so setting it is an error naming it
        assert isinstance(changed, tr.ConfigError), changed
        assert path.rsplit(".", 2)[-2] + "." + path.rsplit(".", 1)[-1] in str(changed), changed
        assert not isinstance(base, BaseException), base
        return
    assert not isinstance(changed, BaseException), f"{path}: the changed config fails: {changed!r}"
    if path in BASE_FAILS:  # the field turns an error into a render
        assert isinstance(base, BASE_FAILS[path]), base
        return
    assert not isinstance(base, BaseException), f"{path}: the base config fails: {base!r}"
    assert not _same(base, changed), f"{path}: changing it changed nothing in the render"


def test_the_comparison_is_deterministic(assets: Path):
    """Rendering one config twice gives bit-identical outputs (else a 'change' could be
    noise), including the stochastic-looking passes (SSAO, bloom, DOF)."""
    data = _merge(BASE, {**SSAO_BASE, "post": {"ssao": SSAO, "bloom": BLOOM, "dof": DOF}})
    first, second = _outcome(data, assets, {}), _outcome(data, assets, {})
    assert not isinstance(first, BaseException), first
    assert _same(first, second)


def test_base_dir_is_not_a_config_key(assets: Path):
    """base_dir was a schema field silently overwritten by the loader; now an unknown key."""
    text = yaml.safe_dump(_merge(BASE, {"base_dir": "/elsewhere"}))
    with pytest.raises(tr.ConfigError, match="base_dir: unknown key"):
        tr.parse_config(text, "fields.yaml", base_dir=assets)
