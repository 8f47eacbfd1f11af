"""The command line and config layer under hostile input: every problem is one line that
names the file (and line and key), nothing is written outside --out, one bad view never
stops the others, and float outputs hold linear HDR."""

import errno
import os
import stat
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

import torchraster as tr
from torchraster import pipeline
from torchraster.cli import main

REPO = Path(__file__).resolve().parents[1]
SPOT = (REPO / "torchraster" / "assets" / "spot" / "spot_triangulated.obj").as_posix()
ENV = (REPO / "torchraster" / "assets" / "envmaps" / "venice_sunset_256.hdr").as_posix()
BASE = f"scene:\n  mesh: {SPOT}\nrender:\n  resolution: 16\n"


def _write(tmp_path, text, name="c.yaml"):
    p = tmp_path / name
    p.write_text(text) if isinstance(text, str) else p.write_bytes(text)
    return p


def _run(tmp_path, *configs, extra=()):
    return main(["render", *map(str, configs), "--out", str(tmp_path / "out"), *extra])


def test_radiance_is_linear_hdr_and_color_is_display(tmp_path):
    text = (BASE + "render:\n  resolution: 16\n  shading: unlit\n").replace(
        "render:\n  resolution: 16\n", "", 1)
    text += ("materials:\n  - emissive: [4.0, 2.0, 0.5]\noutputs:\n"
             "  channels: [color, radiance]\n  formats: [npy, png]\n")
    cfg = tr.parse_config(text)
    tr.render_to_files(cfg, tmp_path)
    radiance, color = np.load(tmp_path / "radiance.npy"), np.load(tmp_path / "color.npy")
    assert radiance.max() > 4.0 and color.max() <= 1.0  # HDR kept; display in [0, 1]
    scene = tr.config.build_scene(cfg)
    view, proj = tr.config.build_camera(cfg.cameras[0], scene.positions, (16, 16))
    ref = tr.Renderer(16, shading="unlit")(scene, view, proj).image[0].numpy()
    np.testing.assert_allclose(radiance, ref, rtol=1e-6, atol=1e-6)
    assert (tmp_path / "radiance.png").is_file()


def test_camera_names_cannot_escape_and_duplicates_are_refused(tmp_path, capsys):
    text = BASE + "cameras:\n  - name: ../../escape\n  - name: ok\n"
    assert _run(tmp_path, _write(tmp_path, text)) == 0
    files = [p for p in tmp_path.rglob("*.png")]
    assert files and all((tmp_path / "out") in p.parents for p in files)
    dup = BASE + "cameras:\n  - name: a\n  - name: b\n  - name: a\n"
    assert _run(tmp_path, _write(tmp_path, dup, "d.yaml")) == 2
    err = capsys.readouterr().err
    assert "d.yaml:8: cameras.2.name" in err and "unique" in err


def test_two_configs_with_one_stem_are_refused(tmp_path, capsys):
    (tmp_path / "x").mkdir()
    a, b = _write(tmp_path, BASE), _write(tmp_path / "x", BASE)
    assert _run(tmp_path, a, b) == 2
    assert "rename one of the configs" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_output_files_get_umask_permissions(tmp_path):
    old = os.umask(0o022)
    try:
        written = tr.render_to_files(tr.parse_config(BASE), tmp_path)
    finally:
        os.umask(old)
    assert written and all(stat.S_IMODE(p.stat().st_mode) == 0o644 for p in written)


def test_all_config_problems_found_before_rendering(tmp_path, capsys):
    text = (f"scene:\n  mesh: nope.obj\nenvironment:\n  path: {tmp_path}\ncameras:\n"
            "  - look_at: {eye: [1, 2, 3], target: [1, 2, 3]}\n"
            "  - look_at: {eye: [0, 0, 3], up: [0, 0, 1]}\n")
    assert _run(tmp_path, _write(tmp_path, text)) == 2
    err = capsys.readouterr().err
    assert "c.yaml:2: scene.mesh: file not found" in err
    assert "c.yaml:4: environment.path" in err and "is a folder" in err
    assert "c.yaml:6: cameras.0.look_at" in err and "same point" in err
    assert "cameras.1.look_at.up" in err and "parallel" in err
    assert "Traceback" not in err


@pytest.mark.parametrize("device", ["gpu0", "cuda:7"])
def test_bad_devices_are_one_line(tmp_path, capsys, device):
    if device.startswith("cuda") and torch.cuda.device_count() > 7:
        pytest.skip("has 8 GPUs")
    assert _run(tmp_path, _write(tmp_path, BASE), extra=["--device", device]) == 2
    err = capsys.readouterr().err
    assert f"--device: {device!r}" in err and "Traceback" not in err


def test_a_failing_view_is_reported_and_the_others_render(tmp_path, capsys, monkeypatch):
    real = pipeline.build_camera

    def flaky(cam, *args):
        if cam.name == "bad":
            raise RuntimeError("boom inside torch")
        return real(cam, *args)

    monkeypatch.setattr(pipeline, "build_camera", flaky)
    text = BASE + "cameras:\n  - name: good\n  - name: bad\n  - name: also_good\n"
    assert _run(tmp_path, _write(tmp_path, text)) == 1
    err = capsys.readouterr().err
    assert "[camera bad]: RuntimeError: boom inside torch" in err
    assert "2 view(s) written" in err and "1 failed" in err and "Traceback" not in err
    assert (tmp_path / "out" / "c" / "also_good" / "color.png").is_file()


def test_empty_view_of_a_textured_mesh_renders(tmp_path):
    texture = f"{Path(SPOT).parent.as_posix()}/spot_texture.png"
    text = (f"scene:\n  mesh: {SPOT}\nmaterials:\n  - base_color_texture: {texture}\n"
            "cameras:\n  - look_at: {eye: [0, 0, 50], target: [0, 0, 100]}\n"
            "render:\n  resolution: 16\n")
    written = tr.render_to_files(tr.parse_config(text), tmp_path)
    assert written


BOMB = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [{', '.join(['*' + p] * 9)}]\n" for p, c in zip("abcdefgh", "bcdefghi",
                                                               strict=True))


@pytest.mark.parametrize("text, match", [
    (BOMB, "aliases expand to more than"),
    ("scene: &s\n  mesh: *s\n", "recursive YAML alias"),
    (b"scene:\n  mesh: caf\xe9.obj\n", "not UTF-8"),
])
def test_yaml_hostile_documents(tmp_path, text, match):
    path = _write(tmp_path, text)
    start = time.perf_counter()
    with pytest.raises(tr.ConfigError, match=match) as err:
        tr.load_config(path)
    assert "c.yaml" in str(err.value) and time.perf_counter() - start < 2.0


def test_output_folder_problems_are_one_line(tmp_path, capsys):
    cfg = _write(tmp_path, BASE)
    (tmp_path / "file").write_text("x")
    assert main(["render", str(cfg), "--out", str(tmp_path / "file")]) == 2
    assert "must be a folder" in capsys.readouterr().err
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        assert main(["render", str(cfg), "--out", str(ro)]) == 2
        assert "not writable" in capsys.readouterr().err


def test_disk_full_names_the_file(tmp_path, monkeypatch):
    def full(path, arr):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "save", full)
    text = BASE + "outputs:\n  formats: [npy]\n"
    with pytest.raises(pipeline.OutputError, match=r"color.npy: cannot write \(disk full\)"):
        tr.render_to_files(tr.parse_config(text), tmp_path)
    assert not list(tmp_path.glob(".*trtmp*"))  # the temporary file is gone


def test_corrupt_environment_and_image_bombs_are_one_line(tmp_path, capsys):
    bad_env = _write(tmp_path, b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 60000 +X 60000\n"
                     + bytes([2, 2, 60000 >> 8, 60000 & 255]) + b"\xff\x00" * 1000, "bomb.hdr")
    text = BASE.replace("resolution: 16", "resolution: 16\n  shading: pbr") + (
        f"environment:\n  path: {bad_env}\n")
    assert _run(tmp_path, _write(tmp_path, text)) == 1
    err = capsys.readouterr().err
    assert "bomb.hdr" in err and "cannot fit" in err and "Traceback" not in err
    # a PNG whose header claims 60000 x 60000 pixels
    png = bytearray(b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + b"IHDR"
                    + struct.pack(">IIBBBBB", 60000, 60000, 8, 2, 0, 0, 0) + b"\0\0\0\0")
    bomb = _write(tmp_path, bytes(png), "bomb.png")
    with pytest.raises(tr.MeshFileError, match="bomb.png"):
        tr.io.load_texture(bomb)


def test_hdr_exr_texels_are_sanitised(caplog):
    from torchraster.hdr_io import sanitize_radiance

    img = torch.ones(3, 2, 2)
    img[0, 0, 0], img[1, 0, 1], img[2, 1, 1] = float("nan"), float("inf"), -2.0
    out = sanitize_radiance(img, "sun.exr")
    assert torch.isfinite(out).all() and out.min() >= 0 and out[1, 0, 1] == 1.0
    assert "sun.exr" in caplog.text and "NaN" in caplog.text


@pytest.mark.parametrize("section, match", [
    ("render:\n  resolution: 16384\n  supersample: 8\n", "exceeds 16384"),
    ("post:\n  ssao: {samples: 100000000}\n", "post.ssao.samples"),
    ("post:\n  dof: {levels: 100000}\n", "post.dof.levels"),
    ("render:\n  shading: pbr\n", "needs light"),
    ("camras:\n  - {}\n", "did you mean 'cameras'"),
    ("render:\n  supersampel: 2\n", "did you mean 'supersample'"),
])
def test_schema_bounds_and_suggestions(section, match):
    with pytest.raises(tr.ConfigError, match=match):
        tr.parse_config(f"scene:\n  mesh: {SPOT}\n" + section)


def test_missing_textures_are_errors_unless_allowed(tmp_path, capsys):
    (tmp_path / "m.mtl").write_text("newmtl skin\nKd 1 1 1\nmap_Kd gone.png\n")
    obj = "mtllib m.mtl\nusemtl skin\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\n"
    (tmp_path / "m.obj").write_text(obj + "f 1/1 2/2 3/3\n")
    with pytest.raises(tr.MeshFileError, match="gone.png"):
        tr.load_scene(tmp_path / "m.obj")
    assert tr.load_scene(tmp_path / "m.obj", allow_missing_textures=True)
    cfg = _write(tmp_path, "scene:\n  mesh: m.obj\nrender:\n  resolution: 8\n")
    assert _run(tmp_path, cfg) == 2
    assert "c.yaml:2: scene.mesh" in capsys.readouterr().err
    assert _run(tmp_path, cfg, extra=["--allow-missing-textures"]) == 0


def test_non_utf8_obj_loads(tmp_path):
    obj = "# caf\xe9 \xa9 latin-1 comment\no caf\xe9\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
    (tmp_path / "l.obj").write_bytes(obj.encode("latin-1"))
    assert tr.load_mesh(tmp_path / "l.obj").num_faces == 1


def test_stale_temporary_files_are_swept(tmp_path):
    stale = tmp_path / ".color.trtmp-abc123.png"
    stale.write_bytes(b"half")
    tr.render_to_files(tr.parse_config(BASE), tmp_path)
    assert not stale.exists() and (tmp_path / "color.png").is_file()


def test_ctrl_c_exits_130_with_one_line(tmp_path, capsys, monkeypatch):
    def interrupted(cfg, device):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "view_renderer", interrupted)
    assert _run(tmp_path, _write(tmp_path, BASE)) == 130
    err = capsys.readouterr().err
    assert err.strip().endswith("interrupted") and "Traceback" not in err


def test_verbose_prints_the_plan_once(tmp_path, capsys):
    assert _run(tmp_path, _write(tmp_path, BASE), extra=["-v"]) == 0
    err = capsys.readouterr().err
    assert err.count("rasterize 16x16") == 1


def test_schema_version_and_module_entry_point(capsys):
    assert main(["schema"]) == 0
    text = capsys.readouterr().out
    assert "## RenderConfig" in text and "[H, W]" in text and "`supersample`" in text
    committed = (REPO / "docs" / "config.md").read_text()
    assert committed.strip() == text.strip(), "docs/config.md is stale: run " \
        "python scripts/make_config_docs.py"
    with pytest.raises(SystemExit):
        main(["--version"])
    assert tr.__version__ in capsys.readouterr().out
    out = subprocess.run([sys.executable, "-m", "torchraster", "--version"], capture_output=True,
                         text=True, check=True)
    assert out.stdout.strip() == f"torchraster {tr.__version__}"
