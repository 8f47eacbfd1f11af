"""Domain randomisation in YAML (``randomize:``): draws follow their distributions, are
reproducible per scene whatever the process (1 or 2 ranks give byte-identical datasets),
land in the manifest, and impossible draws fail before anything is written."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

import torchraster as tr
from torchraster import manifest
from torchraster.cli import main
from torchraster.config import scene_variants

CONFIG = """\
categories: [box, ball]
frames: {count: 2, fps: 4}
scene:
  objects:
    - {name: floor, primitive: plane, size: 6, cast_shadows: false}
randomize:
  seed: 5
  scenes: 3
  objects:
    count: {choice: [2, 3]}
    pool:
      - {primitive: box, size: 0.4, category: box}
      - {primitive: sphere, size: 0.5, category: ball}
    scale: {uniform: [0.6, 1.2]}
    bounds: [-1.5, -1.5, 1.5, 1.5]
    base_color: {uniform: [[0.1, 0.1, 0.1], [1, 1, 1]]}
    roughness: {normal: [0.5, 0.1]}
    metallic: {choice: [0.0, 1.0], weights: [3, 1]}
    velocity: {uniform: [[-0.3, 0, -0.3], [0.3, 0, 0.3]]}
    spin_deg_per_s: {uniform: [-60, 60]}
  lights: {count: 1, intensity: {loguniform: [1, 4]}}
  camera: {azimuth_deg: {uniform: [0, 360]}, elevation_deg: {uniform: [20, 50]}}
cameras:
  - name: cam
    orbit: {distance: 5, target: [0, 0, 0]}
render: {resolution: 24}
outputs:
  channels: [color, instance, semantic, flow_forward]
  formats: [png, npy]
"""


def _cfg(text: str = CONFIG, tmp_path=None) -> tr.config.RenderFile:
    return tr.parse_config(text, "r.yaml", base_dir=tmp_path)


def test_variants_are_reproducible_and_independent():
    cfg = _cfg()
    a, b = scene_variants(cfg), scene_variants(cfg)
    assert [v.drawn for v in a] == [v.drawn for v in b]
    assert len({json.dumps(v.drawn["objects"]) for v in a}) == 3  # scenes differ
    # adding scenes changes none of the existing ones; another dataset seed changes all
    more = scene_variants(_cfg(CONFIG.replace("scenes: 3", "scenes: 5")))
    assert [v.drawn for v in more[:3]] == [v.drawn for v in a]
    other = scene_variants(cfg, seed=1)
    assert all(x.drawn != y.drawn for x, y in zip(a, other, strict=True))
    json.dumps([v.drawn for v in a], allow_nan=False)


def test_draws_follow_their_distributions():
    """Each kind of random value: the drawn values of many scenes lie in the distribution's
    support and match its moments (uniform, loguniform, normal, weighted choice)."""
    cfg = _cfg(CONFIG.replace("scenes: 3", "scenes: 300"))
    variants = scene_variants(cfg)
    objs = [o for v in variants for o in v.drawn["objects"]]
    scale = np.array([o["scale"] for o in objs])
    assert scale.min() >= 0.6 and scale.max() <= 1.2
    assert abs(scale.mean() - 0.9) < 5 * 0.6 / math.sqrt(12 * len(scale))
    rough = np.array([o["roughness"] for o in objs])  # normal(0.5, 0.1), clipped to [0, 1]
    assert abs(rough.mean() - 0.5) < 5 * 0.1 / math.sqrt(len(rough))
    assert abs(rough.std() - 0.1) < 0.02
    metal = np.array([o["metallic"] for o in objs])
    assert set(np.unique(metal)) <= {0.0, 1.0}
    p = metal.mean()  # weights 3 : 1
    assert abs(p - 0.25) < 5 * math.sqrt(0.25 * 0.75 / len(metal))
    counts = [len(v.drawn["objects"]) for v in variants]
    assert set(counts) == {2, 3}
    inten = np.log([v.drawn["lights"][0]["intensity"] for v in variants])  # loguniform
    assert inten.min() >= 0 and inten.max() <= math.log(4)
    assert abs(inten.mean() - math.log(4) / 2) < 5 * math.log(4) / math.sqrt(12 * len(inten))
    for v in variants:  # placements: inside the bounds, apart, resting on the floor
        o = v.drawn["objects"]
        for i, a in enumerate(o):
            assert -1.5 <= a["position"][0] <= 1.5 and -1.5 <= a["position"][2] <= 1.5
            for b in o[i + 1:]:
                d = math.dist([a["position"][0], a["position"][2]],
                              [b["position"][0], b["position"][2]])
                assert d > 0.2 * min(a["scale"], b["scale"])


def test_drawn_objects_become_config_objects():
    """The draws are ordinary config fields: positions, yaw, scale, material and a keyframed
    motion that moves by velocity x time."""
    v = scene_variants(_cfg())[0]
    placed = [o for o in v.config.scene.objects if o.name and o.name.startswith("random")]
    assert len(placed) == len(v.drawn["objects"])
    for obj, rec in zip(placed, v.drawn["objects"], strict=True):
        assert obj.transform.translate == pytest.approx(rec["position"])
        assert obj.transform.scale == pytest.approx(rec["scale"])
        keys = obj.animation.keys
        t = keys[-1].time
        end = [p + u * t for p, u in zip(rec["position"], rec["velocity"], strict=True)]
        assert keys[-1].translate == pytest.approx(end)
        assert keys[-1].rotate_deg[1] == pytest.approx(rec["yaw_deg"] + rec["spin_deg_per_s"] * t)
        assert obj.material.base_color == pytest.approx(rec["base_color"])
    assert v.config.randomize is None and len(v.config.lights) == 1


def test_records_hold_the_draws(tmp_path):
    (tmp_path / "r.yaml").write_text(CONFIG.replace("scenes: 3", "scenes: 2"))
    assert main(["render", str(tmp_path / "r.yaml"), "--out", str(tmp_path / "out")]) == 0
    records = manifest.read_manifest(tmp_path / "out")
    assert len(records) == 2 * 2  # scenes x frames
    keys = sorted(r["key"] for r in records)
    assert keys == ["r/scene_0000/cam/00000", "r/scene_0000/cam/00001",
                    "r/scene_0001/cam/00000", "r/scene_0001/cam/00001"]
    drawn = {r["key"]: r["randomized"] for r in records}
    expect = {v.name: v.drawn for v in scene_variants(_cfg(CONFIG.replace("scenes: 3",
                                                                          "scenes: 2")))}
    for key, d in drawn.items():
        assert d == json.loads(json.dumps(expect[key.split("/")[1]]))
    for r in records:  # the categories of the drawn objects are in the per-object records
        names = {o["name"]: o["category"] for o in r["objects"]}
        for i, o in enumerate(r["randomized"]["objects"]):
            assert names[f"random{i}"] == ["box", "ball"][o["pool"]]


@pytest.mark.parametrize("change, message", [
    ("bounds: [-1.5, -1.5, 1.5, 1.5]", "bounds: [-0.3, -0.3, 0.3, 0.3]"),
])
def test_impossible_placement_is_a_config_error_before_any_file(tmp_path, capsys, change,
                                                                 message):
    (tmp_path / "r.yaml").write_text(CONFIG.replace(change, message))
    assert main(["render", str(tmp_path / "r.yaml"), "--out", str(tmp_path / "out")]) != 0
    err = capsys.readouterr().err
    assert "r.yaml:" in err and "randomize.objects" in err and "place_on_floor" in err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").rglob("*.png"))


def test_bad_random_values_name_the_key():
    for bad, where in (("scale: {uniform: [0.6, 1.2]}", "scale: {uniform: [0.6]}"),
                       ("scale: {uniform: [0.6, 1.2]}", "scale: {uniform: [1, 2], normal: [0, 1]}"),
                       ("metallic: {choice: [0.0, 1.0], weights: [3, 1]}",
                        "metallic: {choice: [0.0, 1.0], weights: [3]}")):
        with pytest.raises(tr.ConfigError, match=r"r\.yaml:\d+: randomize\.objects\.scale|"
                           r"r\.yaml:\d+: randomize\.objects\.metallic"):
            _cfg(CONFIG.replace(bad, where))


@pytest.mark.slow
def test_one_and_two_ranks_write_identical_datasets(tmp_path):
    """The same seed gives byte-identical files on 1 and 2 ranks (torchrun, gloo, loopback)."""
    import os

    (tmp_path / "r.yaml").write_text(CONFIG)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "GLOO_SOCKET_IFNAME": "lo"}
    base = [sys.executable, "-m", "torch.distributed.run", "--rdzv-backend", "c10d",
            "--rdzv-endpoint", "127.0.0.1:0"]
    for n in (1, 2):
        res = subprocess.run(base[:3] + ["--nproc-per-node", str(n)] + base[3:] + [
            "-m", "torchraster", "render", str(tmp_path / "r.yaml"), "--out",
            str(tmp_path / f"out{n}")], env=env, capture_output=True, text=True, timeout=600)
        assert res.returncode == 0, res.stderr[-3000:]

    def files(out):
        return {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*"))
                if p.is_file() and p.suffix in (".png", ".npy")}

    one, two = files(tmp_path / "out1"), files(tmp_path / "out2")
    assert one.keys() == two.keys() and len(one) > 0
    assert all(one[k] == two[k] for k in one)


def test_render_dataset_items_equal_the_command_line_files(tmp_path):
    """RenderDataset renders the same (scene, camera, frame) views as torchraster render:
    the same instance ids and flow, item by item."""
    from torchraster.data import RenderDataset

    text = CONFIG.replace("scenes: 3", "scenes: 1")
    (tmp_path / "r.yaml").write_text(text)
    assert main(["render", str(tmp_path / "r.yaml"), "--out", str(tmp_path / "out")]) == 0
    ds = RenderDataset(tmp_path / "r.yaml", channels=["instance", "flow_forward"])
    assert ds.num_views == 2
    for i in range(ds.num_views):
        item = ds[i]
        folder = tmp_path / "out" / "r" / "scene_0000" / "cam" / f"{item['frame']:05d}"
        assert item["frame"] == i and item["time"] == pytest.approx(i / 4)
        assert np.array_equal(item["instance"].numpy().astype(np.int32),
                              np.load(folder / "instance.npy"))
        assert np.array_equal(item["flow_forward"].numpy(), np.load(folder / "flow_forward.npy"))


def test_a_folder_with_a_non_image_is_an_error_naming_it(tmp_path):
    from skimage import io as skio

    (tmp_path / "tex").mkdir()
    skio.imsave(tmp_path / "tex" / "a.png", np.zeros((4, 4, 3), np.uint8), check_contrast=False)
    (tmp_path / "tex" / "notes.txt").write_text("not an image")
    text = CONFIG.replace("    spin_deg_per_s:", "    textures: tex\n    spin_deg_per_s:")
    cfg = _cfg(text, tmp_path)
    with pytest.raises(tr.ConfigError, match=r"r\.yaml:\d+: randomize\.objects\.textures: .*"
                       r"notes\.txt"):
        tr.config.check_config(cfg)


def test_a_camera_that_sees_nothing_warns_naming_the_view(tmp_path, caplog):
    import logging

    text = """\
scene:
  objects: [{primitive: box}]
cameras:
  - name: away
    look_at: {eye: [0, 0, 5], target: [0, 0, 10]}
render: {resolution: 8}
outputs: {channels: [color]}
"""
    (tmp_path / "a.yaml").write_text(text)
    with caplog.at_level(logging.WARNING, logger="torchraster"):
        assert main(["render", str(tmp_path / "a.yaml"), "--out", str(tmp_path / "out")]) == 0
    assert any("sees nothing" in r.getMessage() and "away" in r.getMessage()
               for r in caplog.records)


@pytest.mark.parametrize("outputs, key", [
    ("{channels: [color, instance], track_points: 8}", "outputs.track_points"),
    ("{channels: [color], previews: true}", "outputs.previews"),
])
def test_options_that_would_do_nothing_are_errors(outputs, key):
    text = f"scene:\n  objects: [{{primitive: box}}]\noutputs: {outputs}\n"
    with pytest.raises(tr.ConfigError, match=rf"r\.yaml:\d+: {key}: "):
        _cfg(text)


def test_previews_are_written_whatever_the_formats(tmp_path):
    text = ("scene:\n  objects: [{primitive: box, category: a}]\nrender: {resolution: 8}\n"
            "outputs: {channels: [color, semantic], formats: [npy], previews: true}\n")
    (tmp_path / "p.yaml").write_text(text)
    assert main(["render", str(tmp_path / "p.yaml"), "--out", str(tmp_path / "out")]) == 0
    assert (tmp_path / "out" / "p" / "semantic_preview.png").is_file()
    assert not (tmp_path / "out" / "p" / "semantic.png").exists()
