"""Argument checks that turn bad input into one clear error naming the argument.

Every public function validates its inputs here before any torch op runs, so a user never
sees a traceback from deep inside torch for a wrong shape, dtype or value.
"""

from __future__ import annotations

import math
import operator
import os
from collections.abc import Sequence

import torch

from . import frame_pool


def check_tensor(
    name: str,
    value: object,
    shape: Sequence[int | str | None],
    *,
    floating: bool = False,
    integer: bool = False,
    finite: bool = False,
) -> torch.Tensor:
    """Check that ``value`` is a tensor of the given rank and sizes.

    ``shape`` holds one entry per dimension: an int (that exact size), a str (a named size,
    only documented in the message) or None (any size). Returns the tensor unchanged.
    Raises ``TypeError`` / ``ValueError`` with a message that names ``name``.
    """
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(value).__name__}")
    if finite:  # reading the values: a meta tensor has none
        check_has_data(name, value)
    want = "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"
    if value.dim() != len(shape):
        raise ValueError(f"{name}: expected shape {want}, got {tuple(value.shape)}")
    for dim, (got, exp) in enumerate(zip(value.shape, shape, strict=False)):
        if isinstance(exp, int) and got != exp:
            raise ValueError(
                f"{name}: expected shape {want}, got {tuple(value.shape)} (dim {dim} must be {exp})"
            )
    if floating and not value.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got {value.dtype}")
    if floating and value.dtype not in FLOAT_DTYPES:
        raise TypeError(f"{name}: dtype {value.dtype} is not supported; expected one of "
                        "float32, float64, float16, bfloat16")
    if integer and (value.is_floating_point() or value.is_complex() or value.dtype == torch.bool):
        raise TypeError(f"{name}: expected an integer tensor, got {value.dtype}")
    if finite and value.is_floating_point() and value.numel() and not all_finite(value):
        bad = int((~torch.isfinite(value)).sum())
        raise ValueError(f"{name}: contains {bad} NaN/Inf value(s); all values must be finite")
    return value


def all_finite(value: torch.Tensor) -> bool:
    """Whether every value of a non-empty floating tensor is finite: its min and max are
    (NaN propagates through both); one reduction, ~18x faster than ``isfinite(value).all()``
    on a 512² RGB frame."""
    lo, hi = torch.aminmax(value.detach())
    return bool(torch.isfinite(lo) & torch.isfinite(hi))


#: Floating dtypes the engine computes in (float16 / bfloat16 are evaluated in float32).
FLOAT_DTYPES = (torch.float32, torch.float64, torch.float16, torch.bfloat16)


def check_has_data(name: str, value: torch.Tensor) -> torch.Tensor:
    """Refuse a ``'meta'`` tensor (shape only, no values) where values are read, with an
    error naming ``name`` instead of torch's "cannot be called on meta tensors"."""
    if value.device.type == "meta":
        raise ValueError(f"{name}: a 'meta' tensor holds no data; expected a tensor on a real "
                         "device (cpu, cuda, ...)")
    return value


def check_bool(name: str, value: object) -> bool:
    """``value`` if it is a bool (Python or numpy), else a TypeError naming ``name``.

    Truthiness is not accepted: ``"no"``, ``None``, ``0.5`` or a tensor are errors, not
    silently ``True`` / ``False``.
    """
    if isinstance(value, bool) or type(value).__name__ == "bool_":  # numpy.bool_
        return bool(value)
    raise TypeError(f"{name}: expected True or False, got {value!r}")


def check_int(name: str, value: object, lo: int, hi: int | None = None) -> int:
    """``value`` as an int in ``[lo, hi]`` (``hi`` None: no upper bound), else a ValueError
    naming ``name``. Bools are not counts and floats are not ints (``2.0`` is refused)."""
    try:
        n = None if isinstance(value, bool) else operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        n = None
    if n is None or n < lo or (hi is not None and n > hi):
        want = f"an int in [{lo}, {hi}]" if hi is not None else f"an int >= {lo}"
        raise ValueError(f"{name}: expected {want}, got {value!r}")
    return n


def check_float(name: str, value: object, lo: float = -math.inf, hi: float = math.inf, *,
                lo_open: bool = False, hi_open: bool = False,
                finite: bool = True) -> float:
    """``value`` as a float in the interval from ``lo`` to ``hi`` (each end closed unless
    ``lo_open`` / ``hi_open``), else a ValueError naming ``name``.

    NaN is always refused; +-inf only when ``finite`` is False (and the interval holds it).
    Bools and strings are refused; 0-d tensors and numpy scalars are not numbers here either.
    """
    ok = isinstance(value, int | float) and not isinstance(value, bool)
    v = float(value) if ok else math.nan  # type: ignore[arg-type]
    ok = ok and not math.isnan(v) and (not finite or math.isfinite(v))
    ok = ok and (lo < v if lo_open else lo <= v) and (v < hi if hi_open else v <= hi)
    if not ok:
        kind = "a finite number" if finite else "a number"
        if math.isinf(hi) and math.isinf(lo):
            where = ""
        elif math.isinf(hi):
            where = f" {'>' if lo_open else '>='} {lo:g}"
        elif math.isinf(lo):
            where = f" {'<' if hi_open else '<='} {hi:g}"
        else:
            where = f" in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
        raise ValueError(f"{name}: expected {kind}{where}, got {value!r}")
    return v


def check_radiance(name: str, value: torch.Tensor) -> torch.Tensor:
    """Check that a floating tensor of light (radiance, colours, intensities) is finite and
    non-negative; the error names ``name`` and counts the bad values. Returns ``value``."""
    if value.numel():
        v = value.detach()
        bad = int((~torch.isfinite(v)).sum())
        if bad:
            raise ValueError(f"{name}: contains {bad} NaN/Inf value(s); light must be finite "
                             "(files with Inf texels are sanitised by torchraster.read_hdr)")
        neg = int((v < 0).sum())
        if neg:
            raise ValueError(f"{name}: contains {neg} negative value(s); expected >= 0")
    return value


def check_resolution(resolution: object, name: str = "resolution") -> tuple[int, int]:
    """Check an ``(H, W)`` pair of positive ints and return it as a tuple."""
    if isinstance(resolution, int):
        resolution = (resolution, resolution)
    try:
        h, w = (int(v) for v in resolution)  # type: ignore[union-attr]
        ok = all(float(v) == int(v) for v in resolution)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected (H, W) positive integers, got {resolution!r}") from None
    if not ok or h <= 0 or w <= 0:
        raise ValueError(f"{name}: expected (H, W) positive integers, got {resolution!r}")
    if max(h, w) > MAX_RESOLUTION:
        raise ValueError(f"{name}: {h}x{w} exceeds the largest supported side "
                         f"{MAX_RESOLUTION}")
    return h, w


#: Largest image side accepted (pixel indices stay far inside the exact float64 range).
MAX_RESOLUTION: int = 2**16


def available_memory(device: torch.device) -> int | None:
    """Bytes that can still be allocated on ``device`` (None when unknown)."""
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    if device.type != "cpu":
        return None
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def check_frame_memory(name: str, pixels: int, bytes_per_pixel: int,
                       device: torch.device) -> None:
    """Refuse a frame whose buffers cannot fit in the memory available on ``device``.

    Raises a ``MemoryError`` saying how much the frame needs and how much is available,
    before anything large is allocated. Buffers held by :mod:`torchraster.frame_pool` count
    as available: they are returned to the OS before refusing.
    """
    need = pixels * bytes_per_pixel
    have = available_memory(device)
    if have is not None and need > have and frame_pool.pooled_bytes():
        frame_pool.clear()
        have = available_memory(device)
    if have is not None and need > have:
        raise MemoryError(
            f"{name}: a frame of {pixels:,} pixels needs about {need / 2**30:.1f} GiB "
            f"({bytes_per_pixel} B per covered pixel) but {have / 2**30:.1f} GiB is available "
            f"on {device}; lower the resolution, batch size or supersampling")


def check_same_batch(**tensors: torch.Tensor) -> int:
    """Check that all given tensors share the leading batch size; return it."""
    sizes = {name: t.shape[0] for name, t in tensors.items()}
    distinct = set(sizes.values())
    if len(distinct) > 1:
        raise ValueError(f"batch sizes differ: {sizes}")
    return distinct.pop()
