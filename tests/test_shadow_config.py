"""Shadows from YAML and in the renderer's plan: `shadows:` blocks, `cast_shadows: true`,
scene objects with cast / receive flags, and the example config (accuracy against a ray
tracer is in test_shadows.py)."""

from pathlib import Path

import pytest
import torch

import torchraster as tr
from torchraster import pipeline
from torchraster.shading.shadows import ShadowSettings

REPO = Path(__file__).resolve().parents[1]
SPOT = (REPO / "torchraster" / "assets" / "spot" / "spot_triangulated.obj").as_posix()

SCENE = f"""
scene:
  mesh: {SPOT}
  objects:
    - name: ground
      primitive: plane
      size: 5
      transform: {{translate: [0, -0.74, 0]}}
      cast_shadows: false
cameras:
  - look_at: {{eye: [0, 3, 3], target: [0, -0.5, 0]}}
render:
  resolution: 48
  shading: pbr
outputs:
  channels: [radiance]
"""


def _render(text):
    cfg = tr.parse_config(text)
    return pipeline.render_config(cfg)[0]


def _sun(extra=""):
    return SCENE + f"lights:\n  - type: directional\n    direction: [0.3, -1, 0.2]\n{extra}"


def test_cast_shadows_true_darkens_the_ground_and_is_planned():
    lit = _render(_sun())
    shadowed = _render(_sun("    cast_shadows: true\n"))
    assert not any("shadow" in step for step in lit.plan)
    assert any(step.startswith("shadow directional[0] 1 map 1024x1024 pcf")
               for step in shadowed.plan)
    darker = (shadowed.images["radiance"] < lit.images["radiance"] - 1e-3).any(0)
    assert int(darker.sum()) > 20  # the cow's shadow on the plane
    assert bool((shadowed.images["radiance"] <= lit.images["radiance"] + 1e-5).all())


def test_shadow_block_settings_reach_the_light():
    cfg = tr.parse_config(_sun("    shadows: {filter: vsm, map_size: 64, cascades: 3, "
                               "intensity: 0.5}\n"))
    lights = tr.lights_from_config(cfg.lights)
    assert bool(lights.directional.cast_shadows.all())
    s = lights.directional.shadow[0]
    assert (s.filter, s.map_size, s.cascades, s.intensity) == ("vsm", 64, 3, 0.5)
    out = _render(_sun("    shadows: {filter: vsm, map_size: 64, cascades: 3}\n"))
    assert any("64x64 vsm" in step and "cascades" in step for step in out.plan)


def test_shadow_intensity_zero_is_the_unshadowed_image():
    lit = _render(_sun())
    none = _render(_sun("    shadows: {intensity: 0.0}\n"))
    torch.testing.assert_close(none.images["radiance"], lit.images["radiance"])


def test_receive_false_keeps_the_ground_lit():
    text = _sun("    cast_shadows: true\n").replace("      cast_shadows: false\n",
                                                      "      receive_shadows: false\n")
    text = text.replace(f"  mesh: {SPOT}\n", f"  mesh: {SPOT}\n  receive_shadows: false\n")
    out = _render(text)
    assert not any("shadow" in step for step in out.plan)  # nobody receives: no pass


@pytest.mark.parametrize("extra, match", [
    ("    cast_shadows: true\n    shadows: {enabled: false}\n", "contradicts"),
    ("    shadows: {filter: soft}\n", "filter"),
    ("    shadows: {map_size: 4}\n", "map_size"),
    ("    shadows: {cascadez: 2}\n", "cascadez"),
])
def test_bad_shadow_blocks_name_the_key(extra, match):
    with pytest.raises(tr.ConfigError, match=match):
        tr.parse_config(_sun(extra))


def test_cascades_are_for_directional_lights_only():
    text = SCENE + ("lights:\n  - type: point\n    position: [0, 2, 0]\n"
                    "    shadows: {cascades: 2}\n")
    with pytest.raises(tr.ConfigError, match="directional"):
        tr.parse_config(text)
    with pytest.raises(ValueError, match="cascades"):
        pts = tr.PointLights(position=torch.tensor([[[0.0, 2, 0]]]), color=torch.ones(1, 1, 3),
                             intensity=torch.ones(1, 1), cast_shadows=torch.ones(1, 1,
                                                                                dtype=torch.bool),
                             shadow=ShadowSettings(cascades=2))
        tr.Renderer(16)(tr.load_spot(), tr.camera.look_at([0.0, 0, 3], [0.0, 0, 0]),
                        tr.camera.perspective(45.0, 1.0, 0.1), tr.Lights(point=pts))


def test_objects_need_exactly_one_source():
    with pytest.raises(tr.ConfigError, match="exactly one"):
        tr.parse_config("scene:\n  objects:\n    - {primitive: box, mesh: x.obj}\n"
                        "render: {shading: unlit}\n")
    with pytest.raises(tr.ConfigError, match="objects"):
        tr.parse_config("scene: {}\nrender: {shading: unlit}\n")


def test_scene_of_primitives_only_renders_with_flags():
    text = ("scene:\n  objects:\n    - {primitive: sphere, size: 1, transform: {translate: "
            "[0, 0.5, 0]}}\n    - {primitive: box, size: 0.5, transform: {translate: [1, 0.25, "
            "0]}}\n    - {primitive: plane, size: 4, cast_shadows: false, material: "
            "{base_color: [0.2, 0.4, 0.8]}}\n"
            "lights:\n  - {type: point, position: [0, 3, 0], intensity: 10, cast_shadows: true}\n"
            "render: {resolution: 32}\noutputs: {channels: [radiance]}\n")
    cfg = tr.parse_config(text)
    scene = tr.config.build_scene(cfg)
    assert scene.cast_shadows is not None and int((~scene.cast_shadows).sum()) == 2
    assert scene.receive_shadows is None
    names = [m.name for m in scene.materials]
    assert names == ["object:sphere0", "object:box1", "object:plane2"]
    assert scene.materials[2].double_sided and not scene.materials[0].double_sided
    out = pipeline.render_config(cfg)[0]
    assert any("cube 6 faces" in step for step in out.plan)
    assert bool(torch.isfinite(out.images["radiance"]).all())


def test_gltf_node_extras_set_instance_flags(tmp_path):
    import json

    import trimesh

    box = trimesh.creation.box()
    scene = trimesh.Scene()
    scene.add_geometry(box, node_name="caster", geom_name="a")
    scene.add_geometry(box, node_name="ground", geom_name="b",
                       transform=trimesh.transformations.translation_matrix([0, -2, 0]))
    path = tmp_path / "s.gltf"
    files = scene.export(file_type="gltf")
    doc = json.loads(files["model.gltf"])
    for node in doc["nodes"]:
        if node.get("name") == "ground":
            node["extras"] = {"cast_shadows": False}
    files["model.gltf"] = json.dumps(doc).encode()
    for name, data in files.items():
        (tmp_path / (path.name if name == "model.gltf" else name)).write_bytes(data)
    loaded = tr.load_scene(path)
    flags = dict(zip(loaded.node_names, loaded.cast_shadows, strict=True))
    assert flags == {"caster": True, "ground": False}
    from torchraster.scene import as_render_scene

    rs = as_render_scene(loaded)
    assert rs.cast_shadows is not None and int(rs.cast_shadows.sum()) == 12
    assert rs.receive_shadows is None


def test_example_config_renders_with_shadows(tmp_path):
    cfg = tr.load_config(REPO / "configs" / "shadows.yaml")
    cfg.render.resolution = [48, 48]
    cfg.render.supersample = 1
    out = pipeline.render_config(cfg)[0]
    steps = list(out.plan)
    assert any(s.startswith("shadow directional[0] 2") for s in steps)
    assert any(s.startswith("shadow spot[0] 1 map 512x512 pcss") for s in steps)
