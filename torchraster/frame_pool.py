"""Reuse of large CPU frame buffers across calls.

torch has a caching allocator on CUDA but none on CPU, and glibc's malloc returns blocks of
32 MB and more to the OS when they are freed. Every call would then write its frame-sized
outputs (resolve keys and face ids, pixel and row indices, barycentrics, interpolated
images) into fresh memory, and Linux charges the first touch of each 4 KB page: on our
machine a fresh 64 MB buffer took 22 ms to fill, against 3 ms to refill, and at 1024²,
batch 8 these page faults were about a fifth of rasterize + interpolate.

:func:`empty` hands out such buffers (CPU, at least :data:`MIN_BYTES`) as tensors over
numpy arrays that the pool keeps (``torch.from_numpy``). When the last tensor or view using
one is freed (the storage drops its array), the array returns to the pool, and the next
request of a similar size reuses its already mapped pages. A buffer is never handed out
while anything still references it, so results of earlier calls stay intact.

The pool keeps at most :data:`POOL_BYTES` of released buffers, the most recently released
ones (0 turns it off; :func:`clear` returns them to the OS). Pooled tensors behave like any
tensor made with ``torch.from_numpy``: everything works except growing them in place with
``resize_``.
"""

from __future__ import annotations

import threading
import weakref

import numpy as np
import torch

#: Most bytes of released buffers the pool keeps for reuse (0: no pooling).
POOL_BYTES: int = 2**30
#: Smallest buffer the pool serves: glibc's malloc already recycles smaller blocks itself
#: (its mmap threshold adapts up to 32 MB).
MIN_BYTES: int = 2**25
#: dtypes the pool serves (numpy has no bfloat16).
_NUMPY_DTYPES = {torch.float32: np.float32, torch.float64: np.float64,
                 torch.float16: np.float16, torch.int64: np.int64, torch.int32: np.int32,
                 torch.uint8: np.uint8, torch.bool: np.bool_}

_free: list[np.ndarray] = []  # released byte arrays, ready for reuse
_lock = threading.RLock()


def empty(shape: tuple[int, ...], dtype: torch.dtype, device: torch.device | str
          ) -> torch.Tensor:
    """An uninitialised tensor like ``torch.empty(shape, dtype=dtype, device=device)``,
    served from the pool's released buffers when it is a large CPU buffer (see the module
    docstring); a plain ``torch.empty`` otherwise.

    Args:
        shape: the tensor's shape.
        dtype: its dtype.
        device: its device.

    Returns:
        A contiguous tensor of ``shape``.
    """
    np_dtype = _NUMPY_DTYPES.get(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if (POOL_BYTES <= 0 or np_dtype is None or nbytes < MIN_BYTES
            or torch.device(device).type != "cpu"):
        return torch.empty(shape, dtype=dtype, device=device)
    base = None
    with _lock:  # best fit among the released buffers, at most twice the size
        fits = [k for k, b in enumerate(_free) if nbytes <= b.nbytes <= 2 * nbytes]
        if fits:
            base = _free.pop(min(fits, key=lambda k: _free[k].nbytes))
    if base is None:
        base = np.empty(nbytes, dtype=np.uint8)
    array = base[:nbytes].view(np_dtype).reshape(shape)
    # The tensor's storage holds `array`; `array` dies (and `base` returns) only when the
    # storage does.
    weakref.finalize(array, _release, base).atexit = False
    return torch.from_numpy(array)


def flatnonzero(mask: torch.Tensor) -> torch.Tensor:
    """``mask.view(-1).nonzero().squeeze(1)``: the (M,) int64 indices of the True entries
    of a contiguous bool ``mask`` (any shape), written into a pooled buffer when it may be
    a large one (the entries are counted first, so the buffer has its final size)."""
    flat = mask.view(-1)
    if flat.numel() * 8 < MIN_BYTES or POOL_BYTES <= 0:
        return flat.nonzero().squeeze(1)
    out = empty((int(flat.sum()), 1), torch.int64, flat.device)
    return torch.nonzero(flat, out=out).squeeze(1)


def _release(base: np.ndarray) -> None:
    """Return ``base`` to the pool; the oldest released buffers leave when it holds more
    than :data:`POOL_BYTES` (a workload whose sizes changed keeps its current ones)."""
    with _lock:
        _free.append(base)
        total = sum(b.nbytes for b in _free)
        while _free and total > POOL_BYTES:
            total -= _free.pop(0).nbytes


def pooled_bytes() -> int:
    """Bytes of released buffers the pool holds now."""
    with _lock:
        return sum(b.nbytes for b in _free)


def clear() -> None:
    """Return every released buffer the pool holds to the OS."""
    with _lock:
        _free.clear()


__all__ = ["MIN_BYTES", "POOL_BYTES", "clear", "empty", "flatnonzero", "pooled_bytes"]
