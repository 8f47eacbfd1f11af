"""Dataset-scale rendering: mesh sets and random orbits, the manifest, resume after a kill,
2 ranks under torchrun (gloo, 127.0.0.1) writing the same files as 1, and RenderDataset
giving the same items whatever the number of DataLoader workers."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from skimage import io as skio
from torch.utils.data import DataLoader

import torchraster as tr
from torchraster import camera, manifest
from torchraster.cli import main
from torchraster.config import check_config, expand_cameras, mesh_set
from torchraster.data import RenderDataset
from torchraster.pipeline import plan_objects

#: Fields of a record that differ between runs (when, where, how long).
VOLATILE = {"timings", "finished_at", "rank", "host", "config_file"}

CONFIG = """\
scene:
  meshes_from: objects.txt
cameras:
  - random_orbits: {count: 2, seed: 7, elevation_deg: [0, 40]}
  - name: front
    orbit: {azimuth_deg: 20, elevation_deg: 10}
render:
  resolution: 16
outputs:
  channels: [color, depth, normal]
  formats: [png, npy]
"""


def _env(threads: int = 1) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    if sys.platform.startswith("linux"):
        env["GLOO_SOCKET_IFNAME"] = "lo"  # loopback only
    return env


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    """Three small objects (two share a stem, in different folders) listed in objects.txt,
    a config of 3 views each: 9 views of 16x16."""
    root = tmp_path_factory.mktemp("dataset")
    (root / "a").mkdir()
    (root / "b").mkdir()
    trimesh.creation.icosphere(1).export(root / "a" / "thing.obj")
    trimesh.creation.box().export(root / "b" / "thing.obj")
    trimesh.creation.capsule(count=[6, 6]).export(root / "pill.obj")
    (root / "objects.txt").write_text("# objects\na/thing.obj\n\nb/thing.obj\npill.obj\n")
    (root / "set.yaml").write_text(CONFIG)
    return root


def _files(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _records(out: Path) -> dict[str, dict]:
    return {r["key"]: {k: v for k, v in r.items() if k not in VOLATILE}
            for r in manifest.read_manifest(out)}


def _no_temp_files(out: Path) -> bool:
    return not [p for p in out.rglob("*") if ".trtmp-" in p.name]


@pytest.fixture(scope="module")
def one_rank(dataset, tmp_path_factory) -> Path:
    """The dataset rendered by one process (in this one)."""
    out = tmp_path_factory.mktemp("one") / "out"
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the torchrun workers (OMP_NUM_THREADS=1)
    try:
        assert main(["render", str(dataset / "set.yaml"), "--out", str(out)]) == 0
    finally:
        torch.set_num_threads(threads)
    return out


# ------------------------------------------------------------------------ config and plan
def test_mesh_set_names_views_and_seeds(dataset):
    cfg = tr.load_config(dataset / "set.yaml")
    names = [e.name for e in mesh_set(cfg)]
    assert names == ["a_thing.obj", "b_thing.obj", "pill"]  # clashing stems get their path
    plans = plan_objects(cfg)
    folders = [v.folder for p in plans for v in p.views]
    assert folders[:3] == ["a_thing.obj/view0_000", "a_thing.obj/view0_001",
                           "a_thing.obj/front"]
    assert len(set(folders)) == 9
    # each object its own random orbits, the same in every call; seeds differ per view
    first, again = expand_cameras(cfg, "pill"), expand_cameras(cfg, "pill")
    assert [c.camera.orbit for c in first] == [c.camera.orbit for c in again]
    assert first[0].camera.orbit != expand_cameras(cfg, "a_thing.obj")[0].camera.orbit
    assert all(0 <= c.camera.orbit.elevation_deg <= 40 for c in first[:2])
    assert len({c.seed for c in first}) == 3
    assert expand_cameras(cfg, "pill", seed=1)[0].camera.orbit != first[0].camera.orbit


def test_glob_and_list_errors_name_the_file_and_line(dataset, tmp_path):
    glob_cfg = tr.parse_config("scene:\n  mesh: '*/thing.obj'\n", "g.yaml", base_dir=dataset)
    assert [e.path.parent.name for e in mesh_set(glob_cfg)] == ["a", "b"]  # sorted
    none = tr.parse_config("scene:\n  mesh: 'nothing/*.glb'\n", "n.yaml", base_dir=dataset)
    with pytest.raises(tr.ConfigError, match=r"n.yaml:2: scene.mesh: no file matches"):
        check_config(none)
    (tmp_path / "list.txt").write_text(f"{dataset / 'pill.obj'}\nmissing.obj\n"
                                       f"{dataset / 'pill.obj'}\n")
    listed = tr.parse_config("scene:\n  meshes_from: list.txt\n", "l.yaml", base_dir=tmp_path)
    with pytest.raises(tr.ConfigError) as err:
        check_config(listed)
    assert "list.txt:2: file not found" in str(err.value)
    assert "list.txt:3: pill.obj is listed twice (first at line 1)" in str(err.value)
    with pytest.raises(tr.ConfigError, match="give either 'mesh' or 'meshes_from'"):
        tr.parse_config("scene:\n  mesh: a.obj\n  meshes_from: l.txt\n")
    with pytest.raises(tr.ConfigError, match=r"cameras.0.random_orbits.elevation_deg"):
        tr.parse_config("scene:\n  mesh: a.obj\ncameras:\n  - random_orbits: "
                        "{count: 2, elevation_deg: [40, 10]}\n")
    dup = "scene:\n  mesh: a.obj\ncameras:\n  - random_orbits: {count: 2}\n  - name: view0_001\n"
    with pytest.raises(tr.ConfigError, match=r"cameras.1.name: camera name 'view0_001'"):
        tr.parse_config(dup)


def test_opencv_and_opengl_matrices_project_to_the_same_pixel():
    h, w = 12, 20
    view = camera.look_at([1.0, 2.0, 3.0], [0.1, 0.0, -0.2])[0]
    for proj in (camera.perspective(50.0, w / h, 0.1)[0],
                 camera.from_intrinsics(18.0, 15.0, 9.0, 5.0, w, h, 0.1)[0]):
        mats = manifest.camera_matrices(view, proj, (h, w))
        points = torch.tensor([[0.1, 0.2, -0.1, 1.0], [0.3, -0.2, 0.2, 1.0]])
        clip = points @ (proj @ view).T
        ndc = clip[:, :2] / clip[:, 3:]
        u_gl, v_gl = (ndc[:, 0] + 1) * w / 2 - 0.5, (1 - ndc[:, 1]) * h / 2 - 0.5
        k = torch.tensor(mats["opencv"]["K"], dtype=torch.float64)
        w2c = torch.tensor(mats["opencv"]["world_to_camera"], dtype=torch.float64)
        cam = points.double() @ w2c.T
        uvw = cam[:, :3] @ k.T
        torch.testing.assert_close(uvw[:, 0] / uvw[:, 2], u_gl.double(), atol=1e-4, rtol=0)
        torch.testing.assert_close(uvw[:, 1] / uvw[:, 2], v_gl.double(), atol=1e-4, rtol=0)
    k = manifest.camera_matrices(view, camera.from_intrinsics(18.0, 15.0, 9.0, 5.0, w, h,
                                                              0.1)[0], (h, w))["opencv"]["K"]
    np.testing.assert_allclose(k, [[18, 0, 9], [0, 15, 5], [0, 0, 1]], atol=1e-5)
    ortho = manifest.camera_matrices(view, camera.orthographic(-1, 1, -1, 1, 0.1, 9)[0], (h, w))
    assert ortho["opencv"]["K"] is None


# ------------------------------------------------------------------------ CLI and resume
def test_manifest_resume_changes_and_force(dataset, one_rank, tmp_path, capsys):
    records = _records(one_rank)
    assert len(records) == 9 and len(manifest.read_manifest(one_rank)) == 9
    r = records["set/pill/front"]
    assert r["object"] == "pill" and r["camera"] == "front" and r["resolution"] == [16, 16]
    assert r["camera_config"]["orbit"]["azimuth_deg"] == 20.0
    assert set(r["files"]) == {f"{c}.{f}" for c in ("color", "depth", "normal")
                               for f in ("png", "npy")}
    assert all((one_rank / p).is_file() for p in r["files"].values())
    assert len(r["opencv"]["K"]) == 3 and len(r["opengl"]["projection"]) == 4
    assert not manifest.shard_files(one_rank) and _no_temp_files(one_rank)
    # a second run skips everything; a changed config re-renders; --force re-renders all
    out = tmp_path / "out"
    cfg = dataset / "set.yaml"
    assert main(["render", str(cfg), "--out", str(out)]) == 0
    stamp = {p: p.stat().st_mtime_ns for p in out.rglob("*.npy")}
    capsys.readouterr()
    assert main(["render", str(cfg), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "0 view(s) written" in err and "9 already done" in err
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*.npy")} == stamp
    assert main(["render", str(cfg), "--out", str(out), "--force"]) == 0
    assert "9 view(s) written" in capsys.readouterr().err
    changed = dataset / "changed"
    changed.mkdir(exist_ok=True)
    (changed / "set.yaml").write_text(CONFIG.replace("objects.txt", "../objects.txt")
                                      .replace("count: 2,", "count: 3,"))
    assert main(["render", str(changed / "set.yaml"), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "3 view(s) written" in err and "9 already done" in err  # only the new views
    assert len(_records(out)) == 12


def test_a_broken_object_fails_alone(dataset, tmp_path, capsys):
    (tmp_path / "broken.glb").write_bytes(b"glTF but not really")
    (tmp_path / "objects.txt").write_text(f"{dataset / 'pill.obj'}\nbroken.glb\n")
    (tmp_path / "set.yaml").write_text(CONFIG)
    assert main(["render", str(tmp_path / "set.yaml"), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert "[object broken]" in err and "3 view(s) written" in err and "3 failed" in err
    assert {r["object"] for r in manifest.read_manifest(tmp_path / "out")} == {"pill"}


KILLABLE = """\
import sys, time
import numpy as np
real = np.save
def slow(path, arr):  # half-written temporary file for a while: a kill lands mid-write
    with open(path, "wb") as f:
        f.write(b"partial")
    time.sleep(0.12)
    real(path, arr)
np.save = slow
from torchraster.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _kill_after(cmd: list[str], out: Path, records: int, env: dict) -> None:
    """Start ``cmd`` and SIGKILL its process group once ``records`` views are recorded."""
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            lines = sum(len(p.read_bytes().splitlines()) for p in manifest.shard_files(out))
            if lines >= records:
                break
            time.sleep(0.02)
        assert proc.poll() is None, f"finished before the kill: {proc.stderr.read()[-2000:]}"
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def _check_complete(out: Path, n_views: int) -> None:
    keys = [r["key"] for r in manifest.read_manifest(out)]
    assert len(keys) == n_views and len(set(keys)) == n_views  # every view, exactly once
    assert _no_temp_files(out) and not manifest.shard_files(out)
    for r in manifest.read_manifest(out):
        for rel in r["files"].values():
            path = out / rel
            data = np.load(path) if path.suffix == ".npy" else skio.imread(path)
            assert data.size > 0 and np.isfinite(data).all()


def test_sigkill_mid_run_then_resume(dataset, one_rank, tmp_path):
    out = tmp_path / "out"
    script = tmp_path / "killable.py"
    script.write_text(KILLABLE)
    _kill_after([sys.executable, str(script), "render", str(dataset / "set.yaml"), "--out",
                 str(out)], out, 2, _env())
    before = manifest.load_records(out)
    assert 2 <= len(before) < 9
    stamps = {p: (p.stat().st_ino, p.stat().st_mtime_ns) for r in before.values()
              for p in (out / f for f in r["files"].values())}
    assert main(["render", str(dataset / "set.yaml"), "--out", str(out)]) == 0
    _check_complete(out, 9)
    # views finished before the kill were not rendered again
    assert {p: (p.stat().st_ino, p.stat().st_mtime_ns) for p in stamps} == stamps
    assert _files(out / "set") == _files(one_rank / "set")
    assert _records(out) == _records(one_rank)


def _torchrun(nproc: int, *args: str) -> list[str]:
    return [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", str(nproc),
            "--rdzv-backend", "c10d", "--rdzv-endpoint", "127.0.0.1:0", "-m", "torchraster",
            *args]


def test_two_ranks_write_the_same_files_as_one(dataset, one_rank, tmp_path):
    out = tmp_path / "out"
    res = subprocess.run(_torchrun(2, "render", str(dataset / "set.yaml"), "--out", str(out)),
                         env=_env(), capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "9 view(s) written" in res.stderr and res.stderr.count("view(s) written") == 1
    assert _files(out / "set") == _files(one_rank / "set")  # bit-identical PNG and NPY
    assert _records(out) == _records(one_rank)
    assert {r["rank"] for r in manifest.read_manifest(out)} == {0, 1}  # both worked
    assert _no_temp_files(out) and not manifest.shard_files(out)


@pytest.mark.slow
def test_two_ranks_killed_then_resumed(dataset, one_rank, tmp_path):
    out = tmp_path / "out"
    script = tmp_path / "killable.py"
    script.write_text(KILLABLE)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", "2",
           "--rdzv-backend", "c10d", "--rdzv-endpoint", "127.0.0.1:0", str(script), "render",
           str(dataset / "set.yaml"), "--out", str(out)]
    _kill_after(cmd, out, 3, _env())
    res = subprocess.run(_torchrun(2, "render", str(dataset / "set.yaml"), "--out", str(out)),
                         env=_env(), capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    _check_complete(out, 9)
    assert _files(out / "set") == _files(one_rank / "set")


# ------------------------------------------------------------------------------ Dataset
def _same_items(a: list[dict], b: list[dict]) -> bool:
    return len(a) == len(b) and all(
        x.keys() == y.keys() and all(
            torch.equal(x[k], y[k]) if isinstance(x[k], torch.Tensor) else x[k] == y[k]
            for k in x) for x, y in zip(a, b, strict=True))


def test_dataset_items_do_not_depend_on_workers(dataset, one_rank):
    ds = RenderDataset(dataset / "set.yaml", channels=["radiance"])
    assert len(ds) == ds.num_views == 9
    serial = list(DataLoader(ds, batch_size=1, num_workers=0))
    workers = list(DataLoader(ds, batch_size=1, num_workers=2))
    assert [int(b["index"]) for b in workers] == list(range(9))
    assert _same_items(serial, workers)
    item = serial[4]
    assert item["image"].shape == (1, 3, 16, 16) and item["radiance"].shape == (1, 3, 16, 16)
    assert item["alpha"].shape == item["depth"].shape == (1, 1, 16, 16)
    assert item["K"].shape == (1, 3, 3) and item["view"].shape == (1, 4, 4)
    # the same pixels and seeds as the command line's files and manifest
    records = _records(one_rank)
    for b in serial:
        key = f"set/{b['object'][0]}/{b['camera'][0]}"
        color = np.load(one_rank / records[key]["files"]["color.npy"])
        assert np.array_equal(color, b["image"][0].numpy()) and int(b["seed"]) == \
            records[key]["seed"]
    other = RenderDataset(dataset / "set.yaml", seed=5)
    assert not torch.equal(other[0]["view"], ds[0]["view"])  # other random orbits
    assert torch.equal(other[2]["view"], ds[2]["view"])  # the fixed camera stays
    assert other[0]["seed"] != ds[0]["seed"]


def test_dataset_shards_by_rank_and_shuffles_alike(dataset):
    shards = [RenderDataset(dataset / "set.yaml", rank=r, world_size=2, shuffle=True)
              for r in range(2)]
    for s in shards:
        s.set_epoch(3)
    a, b = (s.indices() for s in shards)
    assert len(a) == len(b) == len(shards[0]) == 5  # padded so DDP ranks step together
    assert sorted(set(a) | set(b)) == list(range(9)) and len(set(a) & set(b)) == 1
    shards[0].set_epoch(4)
    assert shards[0].indices() != a


def test_ranks_that_see_different_views_stop(dataset, tmp_path):
    from torchraster.distributed import DatasetConfig, RankMismatchError, World, render_dataset

    class Other(World):  # a second rank that lists one view fewer
        def all_gather(self, obj):
            return [obj, (obj[0] - 1, obj[1])]

    cfg = tr.load_config(dataset / "set.yaml")
    with pytest.raises(RankMismatchError, match="the ranks see different views"):
        render_dataset([DatasetConfig(dataset / "set.yaml", "set", cfg)], tmp_path / "out",
                       world=Other(0, 2))
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_a_config_error_under_two_ranks_is_one_line(tmp_path):
    (tmp_path / "c.yaml").write_text("scene:\n  mesh: missing.obj\n")
    res = subprocess.run(_torchrun(2, "render", str(tmp_path / "c.yaml"), "--out",
                                   str(tmp_path / "out")),
                         env=_env(), capture_output=True, text=True, timeout=300)
    assert res.returncode != 0
    assert res.stderr.count("c.yaml:2: scene.mesh: file not found") == 1


@pytest.mark.slow
def test_ddp_example_fits_the_colour():
    script = Path(__file__).resolve().parents[1] / "examples" / "ddp_train.py"
    res = subprocess.run([sys.executable, str(script), "--steps", "20", "--resolution", "16",
                          "--log-every", "20"], env=_env(), capture_output=True, text=True,
                         timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    last = res.stdout.strip().splitlines()[-1].split()
    assert int(last[0]) == 20 and float(last[2]) < 0.1  # colour error, from 0.55


API_SCRIPT = """
import sys
from pathlib import Path
import torch
import torchraster as tr
from torchraster.distributed import DatasetConfig, render_dataset
cfg = tr.load_config(sys.argv[1])
s = render_dataset([DatasetConfig(Path(sys.argv[1]), "set", cfg)], sys.argv[2], progress=False)
# one write (atomic on a pipe): two unbuffered ranks' print() pieces can interleave
sys.stdout.write(f"left {torch.distributed.is_initialized()} {s.written}\\n")
"""


@pytest.mark.slow
def test_python_api_under_torchrun_leaves_its_process_group(dataset, tmp_path):
    """``render_dataset`` called from Python under ``torchrun`` (no world given) makes the
    process group and leaves it before returning: a process that exits with gloo's threads
    running may abort after its work ('terminate called without an active exception')."""
    script = tmp_path / "api.py"
    script.write_text(API_SCRIPT)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node", "2",
           "--rdzv-backend", "c10d", "--rdzv-endpoint", "127.0.0.1:0", str(script),
           str(dataset / "set.yaml"), str(tmp_path / "out")]
    res = subprocess.run(cmd, env=_env(), capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    lines = [x for x in res.stdout.splitlines() if x.startswith("left")]
    assert lines == ["left False 9"] * 2, res.stdout


def test_writer_core_leaves_one_core_to_the_writer(monkeypatch):
    """Beside the writer thread, torch's threads drop by one when they would use every
    core, and come back after the run; never below 1, never when OMP_NUM_THREADS fixes
    them."""
    from torchraster.distributed import writer_core

    before = torch.get_num_threads()
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    try:
        torch.set_num_threads(2)
        with writer_core() as n:
            assert n == torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3}, raising=False)
        with writer_core() as n:  # threads below the cores: the writer has its own
            assert n == 2
        monkeypatch.setenv("OMP_NUM_THREADS", "2")
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
        with writer_core() as n:  # the user's choice
            assert n == 2
        torch.set_num_threads(1)
        monkeypatch.delenv("OMP_NUM_THREADS")
        with writer_core() as n:
            assert n == 1
    finally:
        torch.set_num_threads(before)
