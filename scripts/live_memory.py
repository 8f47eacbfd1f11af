"""Live tensor bytes of one Renderer call: the peak, the op and the Python stack there.

RSS (what scripts/bench_memory.py measures) includes malloc's retention and varies by
~10 % between runs; this counts only the storages of tensors alive, so a change's effect on
the peak is exact and the place of the peak is named. A ``TorchDispatchMode`` sees every
op's outputs, counts each storage once (views share it) and releases it when the last
tensor seen on it is collected (weak references).

    python scripts/live_memory.py [--res 512] [--batch 8] [--lights 1] [--backward]

Prints the peak in bytes per pixel above what existed before the call, the op and the
torchraster frames at the peak, and the largest storages alive there.
"""

from __future__ import annotations

import argparse
import dataclasses
import traceback
import weakref

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten


class LiveBytes(TorchDispatchMode):
    """Sum of the storages of live tensors made inside the mode; ``peak``, ``where`` (op,
    stack) and ``largest`` (storage sizes alive at the peak) of the maximum."""

    def __init__(self) -> None:
        super().__init__()
        self.refs: dict[int, int] = {}
        self.sizes: dict[int, int] = {}
        self.total = self.peak = 0
        self.where: tuple[str, list[str]] = ("", [])
        self.largest: list[int] = []
        self.origin: dict[int, str] = {}
        self.alive: list[tuple[int, str]] = []

    def _release(self, key: int) -> None:
        self.refs[key] -= 1
        if self.refs[key] == 0:
            self.total -= self.sizes.pop(key)
            del self.refs[key]
            self.origin.pop(key, None)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):  # noqa: ANN001, ANN204
        out = func(*args, **(kwargs or {}))
        for t in tree_flatten(out)[0]:
            if isinstance(t, torch.Tensor):
                storage = t.untyped_storage()
                key = storage.data_ptr()
                if key == 0:
                    continue
                if key not in self.refs:
                    frames = [f"{f.filename.split('torchraster/')[-1]}:{f.lineno}"
                              for f in traceback.extract_stack() if "torchraster/" in f.filename]
                    self.origin[key] = f"{func} " + " < ".join(frames[::-1][:3])
                    self.refs[key] = 0
                    self.sizes[key] = storage.nbytes()
                    self.total += storage.nbytes()
                self.refs[key] += 1
                weakref.finalize(t, self._release, key)
        if self.total > self.peak:
            self.peak = self.total
            stack = [f"{f.filename.split('torchraster/')[-1]}:{f.lineno} {f.name}"
                     for f in traceback.extract_stack() if "torchraster/" in f.filename]
            self.where = (str(func), stack[-10:])
            self.largest = sorted(self.sizes.values(), reverse=True)[:12]
            self.alive = sorted(((self.sizes[k], self.origin.get(k, "?")) for k in self.sizes),
                                reverse=True)
        return out


def main() -> None:
    import bench_memory

    import torchraster as tr

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--res", type=int, default=512)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--lights", type=int, default=1)
    ap.add_argument("--backward", action="store_true",
                    help="forward + backward to the vertex positions (as bench_memory's "
                    "fwd+bwd rows)")
    ap.add_argument("--detail", action="store_true",
                    help="list every storage alive at the peak with the op and the "
                    "torchraster lines that made it")
    args = ap.parse_args()
    _, scene, view, proj, lights = bench_memory._scene(args.res, args.batch, args.lights)
    renderer = tr.Renderer((args.res, args.res), shading="pbr")
    positions = scene.positions.clone().requires_grad_(args.backward)
    scene = dataclasses.replace(scene, positions=positions)
    with torch.set_grad_enabled(args.backward):
        renderer(scene, view[:1], proj, lights).image.sum()  # warm-up: pyramids, tables
        live = LiveBytes()
        with live:
            loss = renderer(scene, view, proj, lights).image.square().mean()
            forward = (live.peak, live.where)
            if args.backward:
                loss.backward()
    px = args.batch * args.res * args.res
    if args.backward:
        print(f"forward's live peak {forward[0] / px:.1f} B/px at {forward[1][0]}: "
              + " < ".join(forward[1][1][::-1][:3]))
    print(f"live peak {live.peak / px:.1f} B/px at {live.where[0]}")
    print("\n".join("  " + s for s in live.where[1]))
    print("largest storages alive there (B/px):", [round(s / px, 1) for s in live.largest])
    if args.detail:
        groups: dict[str, list[int]] = {}
        for size, origin in live.alive:
            groups.setdefault(origin, []).append(size)
        print("storages alive at the peak by the op and torchraster lines that made them "
              "(B/px, count):")
        for origin, sizes in sorted(groups.items(), key=lambda g: -sum(g[1])):
            if sum(sizes) / px >= 0.5:
                print(f"  {sum(sizes) / px:6.1f} {len(sizes):4d}  {origin}")


if __name__ == "__main__":
    main()
