"""YAML configs (errors name file, line and key path) and the render command end to end."""

from pathlib import Path

import numpy as np
import pytest
import torch
from skimage import io as skio

import torchraster as tr
from torchraster.cli import main

REPO = Path(__file__).resolve().parents[1]
QUICKSTART = REPO / "configs" / "quickstart.yaml"
SPOT = (REPO / "torchraster" / "assets" / "spot" / "spot_triangulated.obj").as_posix()


def _write(tmp_path, text, name="c.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_quickstart_config_parses_with_defaults():
    cfg = tr.load_config(QUICKSTART)
    assert cfg.render.size == (512, 512)
    assert cfg.resolve(cfg.scene.mesh).is_file()
    assert cfg.cameras[0].orbit is not None and cfg.cameras[0].far is None


@pytest.mark.parametrize("text, where", [
    ("scene:\n  mesh: m.obj\ncameras:\n  - fov_deg: 200\n", "c.yaml:4: cameras.0.fov_deg"),
    ("scene:\n  mesh: m.obj\nrender:\n  resolution: [0, 10]\n", "c.yaml:4: render.resolution"),
    ("scene:\n  mesh: m.obj\n  colour: red\n", "c.yaml:3: scene.colour"),
    ("scene:\n  mesh: m.obj\nlights:\n  - type: point\n    range: -1\n",
     "c.yaml:5: lights.0.point.range"),
    ("cameras: []\n", "scene"),
])
def test_errors_name_file_line_and_key_path(tmp_path, text, where):
    with pytest.raises(tr.ConfigError) as err:
        tr.load_config(_write(tmp_path, text))
    assert where in str(err.value)


def test_malformed_yaml_names_the_line(tmp_path):
    with pytest.raises(tr.ConfigError, match=r"c.yaml:3: malformed YAML"):
        tr.load_config(_write(tmp_path, "scene:\n  mesh: a.obj\n  bad: [1, 2\n"))


def test_missing_config_file(tmp_path):
    with pytest.raises(tr.ConfigError, match="cannot read"):
        tr.load_config(tmp_path / "nope.yaml")


def test_cli_renders_quickstart_atomically(tmp_path, capsys):
    text = QUICKSTART.read_text().replace("[512, 512]", "[64, 96]")
    text = text.replace("supersample: 2", "supersample: 1")
    text = text.replace("../torchraster", (REPO / "torchraster").as_posix())
    cfg = _write(tmp_path, text, "quick.yaml")
    assert main(["render", str(cfg), "--out", str(tmp_path / "out")]) == 0
    out = tmp_path / "out" / "quick"
    color = skio.imread(out / "color.png")
    depth = skio.imread(out / "depth.png")
    normal = skio.imread(out / "normal.png")
    assert color.shape == (64, 96, 3) and color.dtype == np.uint8
    assert depth.shape == (64, 96) and depth.dtype == np.uint16
    assert normal.shape == (64, 96, 3)
    # the cow covers the centre, the corner is background
    assert depth[32, 48] > 0 and depth[0, 0] == 0
    assert color[32, 48].sum() > color[0, 0].sum()
    assert sorted(p.name for p in out.iterdir()) == ["color.png", "depth.png", "normal.png"]


def test_cli_bad_config_exit_code_and_message(tmp_path, capsys):
    cfg = _write(tmp_path, f"scene:\n  mesh: {SPOT}\ncameras:\n  - fov_deg: -3\n")
    assert main(["render", str(cfg), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "cameras.0.fov_deg" in err and "c.yaml:4" in err
    assert not (tmp_path / "out").exists()


def test_cli_missing_mesh_names_the_file(tmp_path, capsys):
    cfg = _write(tmp_path, "scene:\n  mesh: missing.obj\n")
    assert main(["render", str(cfg), "--out", str(tmp_path / "out")]) == 2  # before rendering
    err = capsys.readouterr().err
    assert "c.yaml:2: scene.mesh: file not found" in err and "missing.obj" in err


def test_several_cameras_and_npy_outputs(tmp_path):
    text = (f"scene:\n  mesh: {SPOT}\ncameras:\n  - name: a\n  - name: b\n"
            f"    projection: orthographic\nrender:\n  resolution: 32\noutputs:\n"
            f"  channels: [color, depth, face_id]\n  formats: [png, npy]\n")
    written = tr.render_to_files(tr.parse_config(text), tmp_path)
    names = sorted(str(p.relative_to(tmp_path)) for p in written)
    assert "a/depth.npy" in names and "b/face_id.png" in names
    depth = np.load(tmp_path / "a" / "depth.npy")
    assert depth.shape == (1, 32, 32) and np.isfinite(depth).all() and depth.max() > 0


def test_png_compression_levels_write_the_same_pixels(tmp_path):
    """``outputs.png_compression`` trades bytes for time only: levels 0 and 9 decode to the
    same pixels (8-bit colour, 16-bit depth and face ids) as the npy values encode, and the
    schema's default is the writer's."""
    from torchraster.config.schema import OutputConfig
    from torchraster.pipeline import PNG_COMPRESSION

    assert OutputConfig().png_compression == PNG_COMPRESSION
    files = {}
    for level in (0, 9):
        text = (f"scene:\n  mesh: {SPOT}\nrender:\n  resolution: 40\noutputs:\n"
                f"  channels: [color, depth, face_id]\n  formats: [png, npy]\n"
                f"  png_compression: {level}\n")
        tr.render_to_files(tr.parse_config(text), tmp_path / str(level))
        files[level] = {n: skio.imread(next((tmp_path / str(level)).rglob(n + ".png")))
                        for n in ("color", "depth", "face_id")}
    for name in ("color", "depth", "face_id"):
        assert np.array_equal(files[0][name], files[9][name]), name
        size = [next((tmp_path / str(lv)).rglob(name + ".png")).stat().st_size for lv in (0, 9)]
        assert size[1] < size[0], name
    face_id = np.load(next((tmp_path / "9").rglob("face_id.npy")))[0]
    assert files[9]["face_id"].dtype == np.uint16
    assert np.array_equal(files[9]["face_id"], ((face_id + 1) % 65536).astype(np.uint16))
    with pytest.raises(tr.ConfigError, match="outputs.png_compression"):
        tr.parse_config(f"scene:\n  mesh: {SPOT}\noutputs:\n  png_compression: 10\n")


def test_material_overrides_and_transform_apply(tmp_path):
    from torchraster.config import build_scene

    text = (f"scene:\n  mesh: {SPOT}\n  transform:\n    translate: [1, 2, 3]\n    scale: 2\n"
            "materials:\n  - base_color: [0.2, 0.4, 0.6]\n    metallic: 0.7\n    roughness: 0.3\n")
    cfg = tr.parse_config(text)
    scene = build_scene(cfg)
    raw = tr.load_mesh(SPOT)
    expected = raw.positions * 2 + torch.tensor([1.0, 2.0, 3.0])
    assert torch.allclose(scene.positions, expected, atol=1e-5)
    (mat,) = scene.materials
    assert torch.allclose(mat.base_color_factor, torch.tensor([0.2, 0.4, 0.6, 1.0]))
    assert mat.metallic_factor == 0.7 and mat.roughness_factor == 0.3
