"""Paths of a config are resolved once, when it is loaded: every path field is absolute
afterwards (remembering the text the file gave), builders never resolve again, and the
manifest's config hash does not depend on where the project lives."""

import pickle
import shutil
from pathlib import Path

import pytest

import torchraster as tr
from torchraster import manifest
from torchraster.config import ConfigPath, RenderFile, written
from torchraster.pipeline import plan_objects

ASSETS = Path(tr.__file__).parent / "assets"

CONFIG = """\
scene:
  mesh: meshes/spot.obj
  objects:
    - {mesh: meshes/spot.obj, transform: {translate: [2, 0, 0]}}
    - primitive: plane
      size: 4
      material: {base_color_texture: tex/spot.png}
environment:
  path: env/sky.hdr
materials:
  - {match: '*', base_color_texture: tex/spot.png}
render:
  resolution: 8
  background_image: {path: tex/spot.png}
outputs:
  channels: [color]
"""


def _project(root: Path) -> Path:
    """A project folder with the config and its files (meshes/, tex/, env/)."""
    (root / "meshes").mkdir(parents=True)
    (root / "tex").mkdir()
    (root / "env").mkdir()
    shutil.copy(ASSETS / "spot" / "spot_triangulated.obj", root / "meshes" / "spot.obj")
    shutil.copy(ASSETS / "spot" / "spot_texture.png", root / "tex" / "spot.png")
    shutil.copy(ASSETS / "envmaps" / "venice_sunset_256.hdr", root / "env" / "sky.hdr")
    (root / "c.yaml").write_text(CONFIG)
    return root / "c.yaml"


def _path_fields(cfg: RenderFile) -> dict[str, str]:
    sc = cfg.scene
    return {"scene.mesh": sc.mesh, "scene.objects.0.mesh": sc.objects[0].mesh,
            "scene.objects.1.material.base_color_texture":
                sc.objects[1].material.base_color_texture,
            "environment.path": cfg.environment.path,
            "materials.0.base_color_texture": cfg.materials[0].base_color_texture,
            "render.background_image.path": cfg.render.background_image.path}


def test_every_path_field_is_absolute_after_load(tmp_path):
    cfg = tr.load_config(_project(tmp_path / "p"))
    texts = {"scene.mesh": "meshes/spot.obj", "scene.objects.0.mesh": "meshes/spot.obj",
             "scene.objects.1.material.base_color_texture": "tex/spot.png",
             "environment.path": "env/sky.hdr", "materials.0.base_color_texture": "tex/spot.png",
             "render.background_image.path": "tex/spot.png"}
    for key, value in _path_fields(cfg).items():
        assert isinstance(value, ConfigPath), key
        assert Path(value).is_absolute() and Path(value).is_file(), key
        assert Path(value) == (tmp_path / "p" / texts[key]).resolve(), key
        assert written(value) == texts[key], key
    # dumps show the paths as written (records, hashes)
    dump = cfg.model_dump(mode="json")
    assert dump["environment"]["path"] == "env/sky.hdr"
    assert dump["scene"]["objects"][0]["mesh"] == "meshes/spot.obj"
    # a mesh-set pattern and a list file are made absolute too; the pattern text is kept
    glob_cfg = tr.parse_config("scene:\n  mesh: 'meshes/*.obj'\n", "g.yaml",
                               base_dir=tmp_path / "p")
    assert Path(glob_cfg.scene.mesh).is_absolute() and glob_cfg.scene.mesh.written == (
        "meshes/*.obj")
    assert [e.name for e in tr.config.mesh_set(glob_cfg)] == ["spot"]
    listed = tr.parse_config("scene:\n  meshes_from: l.txt\n", "l.yaml", base_dir=tmp_path)
    assert Path(listed.scene.meshes_from) == tmp_path.resolve() / "l.txt"


def test_builders_never_resolve_again(tmp_path, monkeypatch):
    """Loaded in one folder, rendered from another working folder with RenderFile.resolve
    disabled: every file (meshes, textures, environment, background image) is found."""
    cfg = tr.load_config(_project(tmp_path / "p"))

    def no_resolve(self, relative):
        raise AssertionError(f"RenderFile.resolve({relative!r}) called after load")

    monkeypatch.setattr(RenderFile, "resolve", no_resolve)
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    tr.config.check_config(cfg)
    (view,) = tr.render_config(cfg)
    assert view.images["color"].shape == (3, 8, 8)
    assert view.plan.background.startswith("image")


def test_relative_paths_without_a_base_dir_resolve_against_the_working_folder(
        tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cfg = tr.parse_config("scene:\n  mesh: m.obj\n")
    assert Path(cfg.scene.mesh) == tmp_path.resolve() / "m.obj"
    built = RenderFile(scene={"mesh": "m.obj"})  # Python construction: same rule
    assert Path(built.scene.mesh) == tmp_path.resolve() / "m.obj"
    absolute = tr.parse_config(f"scene:\n  mesh: {tmp_path / 'x.obj'}\n")
    assert absolute.scene.mesh == str(tmp_path / "x.obj")


def test_resolved_paths_survive_pickling_and_copies(tmp_path):
    cfg = tr.load_config(_project(tmp_path / "p"))
    for copy in (pickle.loads(pickle.dumps(cfg)), cfg.model_copy(deep=True)):
        assert copy.scene.mesh == cfg.scene.mesh
        assert copy.scene.mesh.written == "meshes/spot.obj"
        assert copy.where("scene", "mesh") == cfg.where("scene", "mesh")


def test_unknown_home_is_a_config_error():
    with pytest.raises(tr.ConfigError, match=r"c.yaml:2: scene.mesh: .*~no_such_user_h5"):
        tr.parse_config("scene:\n  mesh: ~no_such_user_h5/m.obj\n", "c.yaml")


def _hashes(config_file: Path) -> list[str]:
    return [manifest.config_hash(o.config) for o in plan_objects(tr.load_config(config_file))]


def test_config_hash_does_not_depend_on_where_the_project_lives(tmp_path):
    first = _project(tmp_path / "a")
    shutil.copytree(tmp_path / "a", tmp_path / "deeper" / "b")  # keeps modification times
    moved = tmp_path / "deeper" / "b" / "c.yaml"
    assert _hashes(first) == _hashes(moved)
    # ... while what decides the pixels still changes it
    moved.write_text(CONFIG.replace("resolution: 8", "resolution: 9"))
    assert _hashes(first) != _hashes(moved)
    moved.write_text(CONFIG.replace("env/sky.hdr", "env/sky2.hdr"))
    assert _hashes(first) != _hashes(moved)


def test_messages_name_nan_and_carry_no_pydantic_prefix():
    with pytest.raises(tr.ConfigError) as err:
        tr.parse_config("scene:\n  mesh: a.obj\nrender:\n  fog: {color: [.nan, 0, 0]}\n",
                        "f.yaml")
    assert "f.yaml:4: render.fog.color.0: expected a number, got NaN" in str(err.value)
    assert "less than" not in str(err.value)
    with pytest.raises(tr.ConfigError) as err:
        tr.parse_config("scene:\n  mesh: a.obj\nlights:\n  - {type: spot, inner_cone_angle: "
                        "0.5, outer_cone_angle: 0.4}\n", "s.yaml")
    assert "s.yaml:4: lights.0.spot: inner_cone_angle (0.5) must be <" in str(err.value)
    assert "Value error" not in str(err.value)


def test_reference_says_what_leaving_out_post_means():
    text = tr.config.config_reference()
    section = text[text.index("## PostConfig"):]
    assert "Leaving ``post:`` out means no tone" in section and "``post: {}``" in section
    # ... and it is what the builders do
    no_post = tr.parse_config("scene:\n  mesh: a.obj\n")
    empty_post = tr.parse_config("scene:\n  mesh: a.obj\npost: {}\n")
    assert not tr.config.build_post(no_post).tonemap.enabled
    assert tr.config.build_post(empty_post).tonemap.enabled
    assert tr.config.build_post(empty_post).tonemap.curve == "aces"


def test_reference_states_every_bound():
    """Every constrained key's row in the reference states its bounds (the pydantic
    constraints of the field as well as of its annotation; the field's own were left out
    before), and a stated bound is what loading enforces."""
    from torchraster.config.reference import _bounds_text, _models_in

    text = tr.config.config_reference()
    seen: list = []
    rows = 0

    def visit(model) -> None:
        nonlocal rows
        if model in seen:
            return
        seen.append(model)
        section = text[text.index(f"## {model.__name__}\n"):]
        section = section[:section.find("\n## ") if "\n## " in section else None]
        for name, field in model.model_fields.items():
            bounds = _bounds_text(field.metadata)
            if bounds and not field.exclude:
                row = next(r for r in section.splitlines() if r.startswith(f"| `{name}` |"))
                assert bounds in row, (model.__name__, name, row)
                rows += 1
            for sub in _models_in(field.annotation):
                visit(sub)

    visit(tr.config.RenderFile)
    assert rows > 100
    with pytest.raises(tr.ConfigError, match="size"):  # 'float > 0' is what it says
        tr.parse_config("scene:\n  objects:\n    - {primitive: box, size: 0}\n")


@pytest.mark.parametrize("where", ["object", "override"])
def test_unreadable_texture_names_the_config_key(tmp_path, where):
    """A texture file that exists but is no image: the error names the file:line: key of
    the config and the image file (not a traceback from the image reader)."""
    from torchraster.config import build_objects

    (tmp_path / "notes.png").write_text("not an image")
    obj = "    - {name: ball, primitive: sphere, size: 1"
    if where == "object":
        text = f"scene:\n  objects:\n{obj}, material: {{base_color_texture: notes.png}}}}\n"
        key = "3: scene.objects.0.material.base_color_texture"
    else:
        text = (f"scene:\n  objects:\n{obj}}}\nmaterials:\n"
                "  - {match: '*', base_color_texture: notes.png}\n")
        key = "5: materials.0.base_color_texture"
    cfg = tr.parse_config(text, "t.yaml", base_dir=tmp_path)
    with pytest.raises(tr.ConfigError) as err:
        build_objects(cfg)
    msg = str(err.value)
    assert msg.startswith("t.yaml:") and key in msg and "notes.png" in msg, msg
    assert "cannot read as an image" in msg
