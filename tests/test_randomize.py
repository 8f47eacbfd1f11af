"""Domain randomisation: reproducibility per (seed, parts) whatever the order of draws,
moments of 20k draws against the analytic ones, choice frequencies against binomial bounds,
placement checked geometrically on real vertices, and the error messages."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from torchraster import randomize as R

N = 20_000


def _draws(spec, seed=0, n=N):
    rng = R.rng_for(seed, "stats")
    spec = R.distribution(spec) if isinstance(spec, dict) else spec  # parse once
    return np.array([R.sample(spec, rng) for _ in range(n)], dtype=object)


# --------------------------------------------------------------------------- seeding


def test_same_seed_and_parts_give_identical_values_in_any_order():
    spec = {"type": "uniform", "low": [0.0, 0.0, 0.0], "high": [1.0, 1.0, 1.0]}

    def view(i):
        rng = R.rng_for(7, "config-a", "view", i)
        return [R.sample(spec, rng), R.sample({"type": "normal", "mean": 0, "std": 1}, rng)]

    forward = [view(i) for i in range(20)]
    backward = [view(i) for i in reversed(range(20))][::-1]
    assert forward == backward  # exact equality: same draws whatever the render order
    assert view(3) != view(4)
    assert R.sample(spec, R.rng_for(8, "config-a", "view", 3)) != forward[3][0]


def test_streams_are_stable_across_processes():
    """Python's hash() is salted per process; rng_for must not depend on it."""
    code = ("import importlib.util as u, sys; "  # load the file alone: no torch import (fast)
            f"s = u.spec_from_file_location('r', {R.__file__!r}); R = u.module_from_spec(s); "
            "sys.modules['r'] = R; s.loader.exec_module(R); "
            "print(R.rng_for(3, 'view', 5, 'x').uniform())")
    runs = set()
    for seed in (1, 2):
        res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             env={"PYTHONHASHSEED": str(seed), "PATH": ""})
        assert res.returncode == 0, res.stderr
        runs.add(res.stdout)
    assert len(runs) == 1 and float(runs.pop()) == R.rng_for(3, "view", 5, "x").uniform()


def test_parts_are_distinguished_by_type_and_value():
    first = {repr(p): R.rng_for(0, p).uniform() for p in (1, 1.0, "1", True, None, [1])}
    assert len(set(first.values())) == len(first)
    assert R.rng_for(0, np.int64(4)).uniform() == R.rng_for(0, 4).uniform()
    assert R.rng_for(0, "a", "b").uniform() != R.rng_for(0, "ab").uniform()


def test_different_parts_are_independent():
    # first draw of 4000 consecutive views: uniform, and neighbours uncorrelated
    x = np.array([R.rng_for(1, "view", i).uniform() for i in range(4000)])
    assert abs(x.mean() - 0.5) < 5 * math.sqrt(1 / 12 / x.size)
    assert abs(np.corrcoef(x[:-1], x[1:])[0, 1]) < 5 / math.sqrt(x.size)
    hist, _ = np.histogram(x, bins=10, range=(0, 1))
    assert (np.abs(hist - 400) < 5 * math.sqrt(400 * 0.9)).all()
    # two whole streams
    a = R.rng_for(1, "view", 0).uniform(size=N)
    b = R.rng_for(1, "view", 1).uniform(size=N)
    assert abs(np.corrcoef(a, b)[0, 1]) < 5 / math.sqrt(N)


def test_rng_for_errors():
    with pytest.raises(ValueError, match="seed: expected a non-negative int"):
        R.rng_for(-1)
    with pytest.raises(ValueError, match="seed"):
        R.rng_for(1.5)
    with pytest.raises(TypeError, match=r"parts\[1\]: expected str, int"):
        R.rng_for(0, "view", object())
    with pytest.raises(ValueError, match=r"parts\[0\]: expected a finite"):
        R.rng_for(0, float("nan"))


# --------------------------------------------------------------------------- distributions


def test_uniform_moments_per_component():
    low, high = np.array([0.0, -2.0, 5.0]), np.array([1.0, 2.0, 5.0])
    x = np.array(list(_draws(R.Uniform(low.tolist(), high.tolist()))), dtype=float)
    assert x.shape == (N, 3)
    assert (x >= low).all() and (x <= high).all()
    var = (high - low) ** 2 / 12
    assert (np.abs(x.mean(0) - (low + high) / 2) <= 5 * np.sqrt(var / N) + 1e-12).all()
    np.testing.assert_allclose(x.var(0), var, rtol=0.05, atol=1e-12)


def test_scalar_and_broadcast_parameters():
    rng = R.rng_for(0)
    v = R.sample({"type": "uniform", "low": 0.2, "high": 1.0}, rng)
    assert isinstance(v, float) and 0.2 <= v <= 1.0
    w = R.sample({"type": "uniform", "low": 0.0, "high": [1.0, 2.0, 3.0]}, rng)
    assert isinstance(w, list) and len(w) == 3 and all(isinstance(c, float) for c in w)


def test_loguniform_log_is_uniform():
    x = np.array(list(_draws({"type": "loguniform", "low": 0.01, "high": 100.0})), float)
    assert (x >= 0.01).all() and (x <= 100.0).all()
    lx = np.log(x)
    a, b = math.log(0.01), math.log(100.0)
    assert abs(lx.mean() - (a + b) / 2) < 5 * math.sqrt((b - a) ** 2 / 12 / N)
    assert lx.var() == pytest.approx((b - a) ** 2 / 12, rel=0.05)
    hist, _ = np.histogram(lx, bins=8, range=(a, b))
    assert (np.abs(hist - N / 8) < 5 * math.sqrt(N / 8)).all()


def test_normal_moments():
    x = np.array(list(_draws(R.Normal([1.0, -3.0], [0.5, 2.0]))), float)
    assert (np.abs(x.mean(0) - [1.0, -3.0]) < 5 * np.array([0.5, 2.0]) / math.sqrt(N)).all()
    np.testing.assert_allclose(x.var(0), [0.25, 4.0], rtol=0.05)
    assert R.sample(R.Normal(2.0, 0.0), R.rng_for(0)) == 2.0


def test_choice_frequencies():
    opts = ["wood", "metal", "plastic"]
    x = list(_draws({"type": "choice", "options": opts, "weights": [1, 2, 5]}))
    p = np.array([1, 2, 5]) / 8
    counts = np.array([x.count(o) for o in opts])
    assert (np.abs(counts - N * p) < 5 * np.sqrt(N * p * (1 - p))).all()
    y = list(_draws(R.Choice([0, 1, 2, 3])))
    counts = np.array([y.count(o) for o in range(4)])
    assert (np.abs(counts - N / 4) < 5 * math.sqrt(N * 0.25 * 0.75)).all()
    z = list(_draws(R.Choice(["a", "b"], weights=[0, 1]), n=200))
    assert set(z) == {"b"}


def test_drawn_values_are_json_and_constants_pass_through(tmp_path):
    rng = R.rng_for(0)
    specs = [R.Uniform(0, 1), R.LogUniform([1, 1], [2, 3]), R.Normal(0, 1),
             R.Choice([{"a": 1}, [1, 2], "x", None]), R.Choice([tmp_path / "a.png"]),
             0.5, 3, [0.1, 0.2], "fixed", True, None]
    for s in specs:
        v = R.sample(s, rng)
        assert json.loads(json.dumps(v)) == v
    assert R.sample([1, 2, 3], rng) == [1.0, 2.0, 3.0]
    assert R.sample(R.Choice([tmp_path / "a.png"]), rng) == str(tmp_path / "a.png")
    opt = R.Choice([[1, 2]])
    R.sample(opt, rng).append(3)  # mutating a drawn value does not change the options
    assert R.sample(opt, rng) == [1, 2]


@pytest.mark.parametrize("spec,err,match", [
    ({"type": "uniform", "low": 2, "high": 1}, ValueError, "uniform: low 2 > high 1"),
    ({"type": "uniform", "low": [0, 0], "high": [1, 1, 1]}, ValueError, "equal lengths"),
    ({"type": "uniform", "low": 0}, ValueError, r"uniform: missing field\(s\) \['high'\]"),
    ({"type": "uniform", "low": 0, "high": 1, "hgh": 2}, ValueError, "unknown field"),
    ({"type": "uniform", "low": "a", "high": 1}, TypeError, "uniform.low"),
    ({"type": "uniform", "low": 0, "high": float("inf")}, ValueError, "uniform.high"),
    ({"type": "loguniform", "low": 0, "high": 1}, ValueError, "loguniform: low 0 must be > 0"),
    ({"type": "normal", "mean": 0, "std": -1}, ValueError, "normal: std -1 must be >= 0"),
    ({"type": "choice", "options": []}, ValueError, "at least one option"),
    ({"type": "choice", "options": "abc"}, TypeError, "choice.options: expected a list"),
    ({"type": "choice", "options": [1, 2], "weights": [1]}, ValueError, "2 weights"),
    ({"type": "choice", "options": [1, 2], "weights": [1, -1]}, ValueError, "non-negative"),
    ({"type": "choice", "options": [1, 2], "weights": [0, 0]}, ValueError, "summing to > 0"),
    ({"type": "choice", "options": [object()]}, TypeError, r"options\[0\].*not a JSON"),
    ({"type": "gauss", "mean": 0}, ValueError, "distribution type: expected one of"),
    ({"low": 0, "high": 1}, ValueError, "with a 'type'"),
    (object(), TypeError, "spec: expected a distribution"),
    (float("nan"), ValueError, "spec: expected a finite"),
])
def test_distribution_errors(spec, err, match):
    with pytest.raises(err, match=match):
        R.sample(spec, R.rng_for(0))


def test_sample_needs_a_generator():
    with pytest.raises(TypeError, match="rng: expected a numpy.random.Generator"):
        R.sample(0.5, np.random.RandomState(0))


# --------------------------------------------------------------------------- placement


def _box(half):
    """Vertices of an axis-aligned box [-hx, hx] x [-hy, hy] x [-hz, hz] raised by 0.3."""
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    return corners * half + [0.0, 0.3, 0.0]


def test_place_on_floor_rests_without_overlap_inside_bounds():
    halves = [np.array(h) for h in ([0.2, 0.1, 0.3], [0.5, 0.4, 0.5], [0.1, 0.1, 0.1],
                                    [0.3, 0.2, 0.1], [0.25, 0.6, 0.25], [0.15, 0.3, 0.4])]
    boxes = [_box(h) for h in halves]
    foot = [R.floor_footprint(b) for b in boxes]
    radii, min_y = [f[0] for f in foot], [f[1] for f in foot]
    np.testing.assert_allclose(radii, [math.hypot(h[0], h[2]) for h in halves])
    bounds, floor_y = (-2.0, -1.0, 2.0, 1.5), -0.75
    pos, yaw = R.place_on_floor(radii, min_y, bounds, floor_y, R.rng_for(5, "place"))
    assert json.loads(json.dumps([pos, yaw])) == [pos, yaw]
    assert len(pos) == len(yaw) == 6 and all(0 <= a < 360 for a in yaw)
    world = []
    for b, p, a in zip(boxes, pos, yaw, strict=True):
        c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
        ry = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        world.append(b @ ry.T + p)
    for w in world:  # resting on the floor, inside the bounds
        assert w[:, 1].min() == pytest.approx(floor_y, abs=1e-12)
        assert (w[:, 0] >= bounds[0] - 1e-12).all() and (w[:, 0] <= bounds[2] + 1e-12).all()
        assert (w[:, 2] >= bounds[1] - 1e-12).all() and (w[:, 2] <= bounds[3] + 1e-12).all()
    for i in range(6):  # bounding circles apart
        for j in range(i):
            d = math.hypot(pos[i][0] - pos[j][0], pos[i][2] - pos[j][2])
            assert d >= radii[i] + radii[j]
    again = R.place_on_floor(radii, min_y, bounds, floor_y, R.rng_for(5, "place"))
    assert again == (pos, yaw)
    other = R.place_on_floor(radii, min_y, bounds, floor_y, R.rng_for(6, "place"))
    assert other != (pos, yaw)


def test_place_on_floor_many_small_objects_and_gap():
    rng = R.rng_for(0)
    r = np.full(30, 0.1)
    pos, yaw = R.place_on_floor(r, np.zeros(30), (0, 0, 3, 3), 0.0, rng, gap=0.05,
                                random_yaw=False)
    c = np.array(pos)[:, [0, 2]]
    d = np.hypot(*(c[:, None] - c[None]).transpose(2, 0, 1)) + np.eye(30) * 9
    assert d.min() >= 0.25 and yaw == [0.0] * 30
    assert (c >= 0.1).all() and (c <= 2.9).all()
    assert R.place_on_floor([], [], (0, 0, 1, 1), 0.0, rng) == ([], [])


def test_place_on_floor_impossible_raises_clearly():
    with pytest.raises(ValueError, match=r"20 circles .* cannot all fit"):
        R.place_on_floor([1.0] * 20, [0.0] * 20, (0, 0, 2, 2), 0.0, R.rng_for(0))
    with pytest.raises(ValueError, match=r"object 1 \(radius 1.5\) does not fit"):
        R.place_on_floor([0.1, 1.5], [0.0, 0.0], (0, 0, 2, 4), 0.0, R.rng_for(0))
    # five circles of radius 0.45 pass the area test (3.2 < 4) but cannot fit in 2 x 2
    msg = r"placed [0-4] of 5 objects.*max_tries = 200.*radii \[0.45"
    with pytest.raises(ValueError, match=msg):
        R.place_on_floor([0.45] * 5, [0.0] * 5, (0, 0, 2, 2), 0.0, R.rng_for(0), max_tries=200)


@pytest.mark.parametrize("kwargs,match", [
    ({"radii": [1.0, -1.0]}, "radii: expected values >= 0"),
    ({"min_y": [0.0]}, "min_y: expected 2 values"),
    ({"bounds": (1, 0, 0, 1)}, "bounds: expected"),
    ({"bounds": (0, 0, 1)}, "bounds: expected"),
    ({"floor_y": float("nan")}, "floor_y"),
    ({"max_tries": 0}, "max_tries"),
    ({"gap": -0.1}, "gap"),
])
def test_place_on_floor_argument_errors(kwargs, match):
    args = {"radii": [0.1, 0.1], "min_y": [0.0, 0.0], "bounds": (0, 0, 1, 1), "floor_y": 0.0,
            "rng": R.rng_for(0)} | kwargs
    with pytest.raises(ValueError, match=match):
        R.place_on_floor(**args)


# --------------------------------------------------------------------------- files


def test_files_in(tmp_path):
    for name in ("b.PNG", "a.jpg", "c.hdr", ".hidden.png", "notes.txt"):
        (tmp_path / name).write_bytes(b"x")
    (tmp_path / "sub.png").mkdir()
    assert [p.name for p in R.files_in(tmp_path)] == ["a.jpg", "b.PNG", "c.hdr"]
    assert [p.name for p in R.files_in(tmp_path, ["hdr"])] == ["c.hdr"]
    with pytest.raises(ValueError, match=r"'notes.txt' is not one of the accepted"):
        R.files_in(tmp_path, strict=True)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match=r"folder '.*empty' holds no file"):
        R.files_in(empty)
    with pytest.raises(FileNotFoundError, match="missing"):
        R.files_in(tmp_path / "missing")
    with pytest.raises(NotADirectoryError, match="a.jpg"):
        R.files_in(tmp_path / "a.jpg")
