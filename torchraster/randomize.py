"""Domain randomisation: seeded distributions, placement on a floor, files from a folder.

The key property is *reproducibility independent of scheduling*: every view draws from its
own generator ``rng_for(seed, *parts)`` (e.g. ``rng_for(seed, "view", i)``), derived from a
stable hash of the seed and the parts, never from a shared stream. View i of a config then
draws the same values whatever the number of ranks or workers and whatever order the views
are rendered in.

Every drawn value is a plain float, list of floats or one of the given options, so it can be
written to the manifest as JSON.

Distributions (dataclasses, or dicts ``{"type": "uniform", "low": ..., "high": ...}``):

* ``Uniform(low, high)``, ``LogUniform(low, high)`` (low > 0; log of the value uniform),
  ``Normal(mean, std)``: scalar parameters give a float, per-component lists (e.g. an RGB
  colour's low / high) give a list; scalars broadcast against lists.
* ``Choice(options, weights=None)``: one of the options (path options are stored as str).

Constants (a number, a list of numbers, a string, a bool, None) are valid specs too and
are returned unchanged, so a config field may hold either a value or a distribution.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import MISSING, dataclass
from pathlib import Path

import numpy as np

Number = float | int
Param = Number | Sequence[Number]


def _param(owner: str, name: str, value: object) -> np.ndarray:
    """A finite float64 scalar or vector parameter."""
    if isinstance(value, bool | str) or (isinstance(value, Sequence) and any(
            isinstance(v, bool | str) for v in value)):
        raise TypeError(f"{owner}.{name}: expected a number or a list of numbers, got {value!r}")
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{owner}.{name}: expected a number or a list of numbers, "
                        f"got {value!r}") from None
    if arr.ndim > 1 or arr.size == 0:
        raise ValueError(f"{owner}.{name}: expected a number or a non-empty flat list, "
                         f"got {value!r}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{owner}.{name}: expected finite values, got {value!r}")
    return arr


def _pair(owner: str, a_name: str, a: object, b_name: str, b: object
          ) -> tuple[np.ndarray, np.ndarray]:
    x, y = _param(owner, a_name, a), _param(owner, b_name, b)
    if x.ndim and y.ndim and x.shape != y.shape:
        raise ValueError(f"{owner}: {a_name} and {b_name} have {x.size} and {y.size} "
                         "components; expected equal lengths (or a scalar)")
    return np.broadcast_arrays(x, y)


def _out(x: np.ndarray) -> float | list[float]:
    return float(x) if x.ndim == 0 else [float(v) for v in x]


@dataclass(frozen=True)
class Uniform:
    """Uniform on [low, high] per component (low <= high; low == high is a constant)."""

    low: Param
    high: Param

    def __post_init__(self) -> None:
        low, high = _pair("uniform", "low", self.low, "high", self.high)
        if (low > high).any():
            raise ValueError(f"uniform: low {self.low!r} > high {self.high!r}; expected "
                             "low <= high")
        object.__setattr__(self, "_args", (low, high))  # parsed once (frozen dataclass)

    def draw(self, rng: np.random.Generator) -> float | list[float]:
        low, high = self._args
        return _out(rng.uniform(low, high, size=low.shape))


@dataclass(frozen=True)
class LogUniform:
    """log(value) uniform on [log low, log high] (0 < low <= high): scales, intensities."""

    low: Param
    high: Param

    def __post_init__(self) -> None:
        low, high = _pair("loguniform", "low", self.low, "high", self.high)
        if (low <= 0).any():
            raise ValueError(f"loguniform: low {self.low!r} must be > 0")
        if (low > high).any():
            raise ValueError(f"loguniform: low {self.low!r} > high {self.high!r}; expected "
                             "low <= high")
        object.__setattr__(self, "_args", (np.log(low), np.log(high)))

    def draw(self, rng: np.random.Generator) -> float | list[float]:
        log_low, log_high = self._args
        return _out(np.exp(rng.uniform(log_low, log_high, size=log_low.shape)))


@dataclass(frozen=True)
class Normal:
    """Gaussian with ``mean`` and standard deviation ``std >= 0`` per component."""

    mean: Param
    std: Param

    def __post_init__(self) -> None:
        mean, std = _pair("normal", "mean", self.mean, "std", self.std)
        if (std < 0).any():
            raise ValueError(f"normal: std {self.std!r} must be >= 0")
        object.__setattr__(self, "_args", (mean, std))

    def draw(self, rng: np.random.Generator) -> float | list[float]:
        mean, std = self._args
        return _out(rng.normal(mean, std, size=mean.shape))


@dataclass(frozen=True)
class Choice:
    """One of ``options`` (JSON values; paths become str), with optional ``weights``
    (non-negative, summing to > 0; normalised)."""

    options: Sequence[object]
    weights: Sequence[Number] | None = None

    def __post_init__(self) -> None:
        if isinstance(self.options, str | bytes | Mapping) or not isinstance(
                self.options, Sequence):
            raise TypeError(f"choice.options: expected a list, got {self.options!r}")
        if len(self.options) == 0:
            raise ValueError("choice.options: expected at least one option, got an empty list")
        options = tuple(os.fspath(o) if isinstance(o, os.PathLike) else o
                        for o in self.options)
        for i, o in enumerate(options):
            try:
                json.dumps(o, allow_nan=False)
            except (TypeError, ValueError):
                raise TypeError(f"choice.options[{i}]: {o!r} is not a JSON value (number, "
                                "string, bool, None, list, dict); drawn values must be "
                                "recordable in the manifest") from None
        object.__setattr__(self, "options", options)
        if self.weights is not None:
            w = _param("choice", "weights", self.weights)
            if w.ndim != 1 or w.size != len(options):
                raise ValueError(f"choice.weights: expected {len(options)} weights (one per "
                                 f"option), got {self.weights!r}")
            if (w < 0).any():
                raise ValueError(f"choice.weights: expected non-negative weights, "
                                 f"got {self.weights!r}")
            if not w.sum() > 0:
                raise ValueError(f"choice.weights: expected weights summing to > 0, "
                                 f"got {self.weights!r}")
            object.__setattr__(self, "_cdf", np.cumsum(w) / w.sum())

    def draw(self, rng: np.random.Generator) -> object:
        if self.weights is None:
            i = int(rng.integers(len(self.options)))
        else:
            # inverse CDF; side="right" never picks a zero-weight option
            i = min(int(np.searchsorted(self._cdf, rng.random(), side="right")),
                    len(self.options) - 1)
        o = self.options[i]
        return copy.deepcopy(o) if isinstance(o, list | dict) else o  # caller may mutate it


Distribution = Uniform | LogUniform | Normal | Choice

#: ``{"type": name, ...}`` -> the dataclass holding the other keys.
DISTRIBUTIONS: dict[str, type] = {
    "uniform": Uniform, "loguniform": LogUniform, "normal": Normal, "choice": Choice}


def distribution(spec: Mapping[str, object]) -> Distribution:
    """The distribution of a dict ``{"type": "uniform" | "loguniform" | "normal" | "choice",
    ...parameters}`` (the shape of a YAML block). Errors name the type and the field."""
    if not isinstance(spec, Mapping) or "type" not in spec:
        raise ValueError(f"distribution: expected a mapping with a 'type' in "
                         f"{sorted(DISTRIBUTIONS)}, got {spec!r}")
    kind = spec["type"]
    if kind not in DISTRIBUTIONS:
        raise ValueError(f"distribution type: expected one of {sorted(DISTRIBUTIONS)}, "
                         f"got {kind!r}")
    cls = DISTRIBUTIONS[kind]
    fields = set(cls.__dataclass_fields__)
    params = {k: v for k, v in spec.items() if k != "type"}
    unknown = set(params) - fields
    if unknown:
        raise ValueError(f"{kind}: unknown field(s) {sorted(unknown)}; expected "
                         f"{sorted(fields)}")
    required = {n for n, f in cls.__dataclass_fields__.items() if f.default is MISSING}
    missing = required - set(params)
    if missing:
        raise ValueError(f"{kind}: missing field(s) {sorted(missing)}")
    return cls(**params)


def sample(spec: object, rng: np.random.Generator) -> object:
    """Draw one value of ``spec`` with ``rng``: a distribution (dataclass or ``{"type": ...}``
    dict) gives a float / list of floats / an option; a constant (number, list of numbers,
    str, bool, None) is returned unchanged (a copy). The result is JSON-serialisable.

    Example:
        >>> spec = {"type": "uniform", "low": 1.0, "high": 2.0}
        >>> x = sample(spec, rng_for(0, "light", 3))
        >>> 1.0 <= x <= 2.0, x == sample(spec, rng_for(0, "light", 3))  # reproducible
        (True, True)
        >>> rng = rng_for(0)
        >>> sample(Choice(["wood", "metal"], weights=[1, 0]), rng), sample(3.0, rng)
        ('wood', 3.0)
    """
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng: expected a numpy.random.Generator (see rng_for), "
                        f"got {type(rng).__name__}")
    if isinstance(spec, Mapping):
        spec = distribution(spec)
    if isinstance(spec, Uniform | LogUniform | Normal | Choice):
        return spec.draw(rng)
    if spec is None or isinstance(spec, bool | str):
        return spec
    if isinstance(spec, int | float):
        if not math.isfinite(spec):
            raise ValueError(f"spec: expected a finite constant, got {spec!r}")
        return spec
    if isinstance(spec, Sequence):
        return [float(v) for v in _param("constant", "value", spec)]
    raise TypeError(f"spec: expected a distribution ({sorted(DISTRIBUTIONS)}) or a constant, "
                    f"got {type(spec).__name__}")


# --------------------------------------------------------------------------- seeding


def _plain(value: object, where: str) -> object:
    """The JSON form of a seed part; numpy scalars become Python numbers."""
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, bool | int | str):
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"{where}: expected a finite number, got {value}")
        return value
    if isinstance(value, list | tuple):
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
    raise TypeError(f"{where}: expected str, int, float, bool, None or a list of them, got "
                    f"{type(value).__name__} (its hash would not be stable across processes)")


def rng_for(seed: int, *parts: object) -> np.random.Generator:
    """An independent generator for ``(seed, *parts)``, e.g. ``rng_for(seed, "view", i)``.

    The generator is seeded by the SHA-256 of the canonical JSON of ``[seed, *parts]`` (not
    Python's ``hash``, which is salted per process), through numpy's ``SeedSequence`` and
    PCG64: equal arguments give identical streams in any process, different ones
    statistically independent streams. Parts are str / int / float / bool / None or lists
    of them; ``1``, ``1.0``, ``"1"`` and ``True`` are different parts.
    """
    if isinstance(seed, np.integer):
        seed = int(seed)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed: expected a non-negative int, got {seed!r}")
    key = json.dumps([seed] + [_plain(p, f"parts[{i}]") for i, p in enumerate(parts)],
                     separators=(",", ":"), ensure_ascii=True, allow_nan=False)
    digest = hashlib.sha256(key.encode()).digest()
    words = np.frombuffer(digest, dtype="<u4").tolist()
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(words)))


# --------------------------------------------------------------------------- placement


def floor_footprint(vertices: object) -> tuple[float, float]:
    """``(radius, min_y)`` of model-space vertices ``(V, 3)`` for :func:`place_on_floor`:
    the radius of the circle about the model's y axis that holds every vertex in the floor
    plane (invariant under yaw), and the lowest y. Apply the object's scale first."""
    v = np.asarray(vertices.detach().cpu() if hasattr(vertices, "detach") else vertices,
                   dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise ValueError(f"vertices: expected shape (V, 3) with V >= 1, got {v.shape}")
    if not np.isfinite(v).all():
        raise ValueError("vertices: expected finite values")
    return float(np.hypot(v[:, 0], v[:, 2]).max()), float(v[:, 1].min())


def _vector(name: str, value: object) -> np.ndarray:
    v = np.asarray(value.detach().cpu() if hasattr(value, "detach") else value,
                   dtype=np.float64).reshape(-1)
    if not np.isfinite(v).all():
        raise ValueError(f"{name}: expected finite values, got {v.tolist()}")
    return v


def place_on_floor(
    radii: object,
    min_y: object,
    bounds: Sequence[float],
    floor_y: float,
    rng: np.random.Generator,
    max_tries: int = 1000,
    random_yaw: bool = True,
    gap: float = 0.0,
) -> tuple[list[list[float]], list[float]]:
    """Random non-overlapping resting positions of N objects on the floor ``y = floor_y``.

    Args:
        radii: ``(N,)`` bounding-circle radius of each object in the floor plane (x, z)
            about its model origin (:func:`floor_footprint`), >= 0.
        min_y: ``(N,)`` each object's lowest model-space y (after scaling).
        bounds: ``(x0, z0, x1, z1)``: every circle lies inside this rectangle.
        floor_y: height of the floor.
        rng: the generator (``rng_for(seed, ...)``).
        max_tries: position draws per object before giving up.
        random_yaw: draw a yaw angle uniform in [0, 360) degrees (else 0).
        gap: extra clearance between circles (>= 0).

    Returns:
        positions ``(N, 3)`` (object origins: y = floor_y - min_y, so the lowest point
        rests on the floor; a yaw about +y keeps it there) and yaw angles ``(N,)`` in
        degrees, as plain lists. Circles satisfy ``|c_i - c_j| >= r_i + r_j + gap``.
        Objects are placed largest first (random sequential placement), each uniformly
        among the centres keeping its circle in bounds.

    Raises:
        ValueError: when an object cannot fit or ``max_tries`` draws all overlap, saying
            how many objects were placed, the bounds and the radii.
    """
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng: expected a numpy.random.Generator, got {type(rng).__name__}")
    r = _vector("radii", radii)
    lowest = _vector("min_y", min_y)
    if lowest.shape != r.shape:
        raise ValueError(f"min_y: expected {r.size} values (one per radius), got {lowest.size}")
    if (r < 0).any():
        raise ValueError(f"radii: expected values >= 0, got {r.tolist()}")
    b = _vector("bounds", bounds)
    if b.size != 4 or not (b[0] < b[2] and b[1] < b[3]):
        raise ValueError(f"bounds: expected (x0, z0, x1, z1) with x0 < x1 and z0 < z1, "
                         f"got {list(bounds)}")
    if not (isinstance(floor_y, int | float) and math.isfinite(floor_y)):
        raise ValueError(f"floor_y: expected a finite number, got {floor_y!r}")
    if isinstance(max_tries, bool) or not isinstance(max_tries, int) or max_tries < 1:
        raise ValueError(f"max_tries: expected an int >= 1, got {max_tries!r}")
    if not (isinstance(gap, int | float) and math.isfinite(gap) and gap >= 0):
        raise ValueError(f"gap: expected a finite number >= 0, got {gap!r}")
    x0, z0, x1, z1 = (float(v) for v in b)
    box = f"bounds (x0, z0, x1, z1) = {(x0, z0, x1, z1)}"
    width, depth = x1 - x0, z1 - z0
    too_big = np.nonzero(2 * r > min(width, depth))[0]
    if too_big.size:
        i = int(too_big[0])
        raise ValueError(f"place_on_floor: object {i} (radius {r[i]}) does not fit in {box} "
                         f"({width} x {depth})")
    if np.pi * (r ** 2).sum() > width * depth:
        raise ValueError(f"place_on_floor: the {r.size} circles (radii {r.tolist()}) cover "
                         f"{np.pi * (r ** 2).sum():.4g}, more than the area {width * depth:.4g} "
                         f"of {box}: they cannot all fit")
    order = sorted(range(r.size), key=lambda i: (-r[i], i))
    centres = np.zeros((r.size, 2))
    placed: list[int] = []
    for count, i in enumerate(order):
        lo = np.array([x0 + r[i], z0 + r[i]])
        hi = np.array([x1 - r[i], z1 - r[i]])
        for _ in range(max_tries):
            c = rng.uniform(lo, hi)
            if not placed or (np.hypot(*(centres[placed] - c).T)
                              >= r[placed] + r[i] + gap).all():
                break
        else:
            raise ValueError(
                f"place_on_floor: placed {count} of {r.size} objects; object {i} "
                f"(radius {r[i]}) still overlapped after max_tries = {max_tries} draws in {box} "
                f"with radii {r.tolist()} (gap {gap}); enlarge the bounds, use fewer or "
                "smaller objects, or raise max_tries")
        centres[i] = c
        placed.append(i)
    yaw = rng.uniform(0.0, 360.0, size=r.size) if random_yaw else np.zeros(r.size)
    positions = [[float(centres[i, 0]), float(floor_y - lowest[i]), float(centres[i, 1])]
                 for i in range(r.size)]
    return positions, [float(a) for a in yaw]


# --------------------------------------------------------------------------- files

#: Image and HDR file suffixes accepted by :func:`files_in` (lower case).
IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp",
                                   ".hdr", ".exr")


def files_in(folder: str | os.PathLike, suffixes: Sequence[str] = IMAGE_SUFFIXES,
             strict: bool = False) -> list[Path]:
    """The files of ``folder`` (not recursive) whose suffix is in ``suffixes`` (any case),
    sorted by name, for "textures / backgrounds from a folder".

    Hidden files (``.name``) and subfolders are skipped. With ``strict=True`` any other file
    raises, naming it. Raises ``FileNotFoundError`` / ``NotADirectoryError`` naming the
    folder, and ``ValueError`` when no file matches.
    """
    path = Path(folder)
    if not path.exists():
        raise FileNotFoundError(f"folder: {str(path)!r} does not exist")
    if not path.is_dir():
        raise NotADirectoryError(f"folder: {str(path)!r} is not a directory")
    if isinstance(suffixes, str) or not suffixes:
        raise ValueError(f"suffixes: expected a non-empty list such as ['.png', '.jpg'], "
                         f"got {suffixes!r}")
    wanted = {("" if s.startswith(".") else ".") + s.lower() for s in suffixes}
    found = []
    for f in sorted(path.iterdir(), key=lambda p: p.name):
        if f.name.startswith(".") or not f.is_file():
            continue
        if f.suffix.lower() in wanted:
            found.append(f)
        elif strict:
            raise ValueError(f"folder {str(path)!r}: {f.name!r} is not one of the accepted "
                             f"file types {sorted(wanted)} (strict=True)")
    if not found:
        raise ValueError(f"folder {str(path)!r} holds no file of the types {sorted(wanted)}")
    return found
