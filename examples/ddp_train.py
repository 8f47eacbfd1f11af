"""Fit a material colour with DistributedDataParallel, each rank rendering its own batch.

The data is a :class:`torchraster.data.RenderDataset` over a render config (Spot under a
headlight from 16 random orbits, base colour ``--true-color``), sharded by rank: each rank's
``DataLoader`` renders the targets of its own views. The model is an ``nn.Module`` that
renders the same scene with a learnable base colour (``sigmoid(logits)``) from the batch's
cameras; DDP averages the gradients over the ranks (gloo, CPU), so every rank takes the same
step. The loss is the mean squared error of linear radiance; the table (rank 0) shows the
loss averaged over the ranks and the colour error.

    python examples/ddp_train.py                        # spawns 2 processes (gloo, CPU)
    torchrun --nproc-per-node 2 examples/ddp_train.py   # the same, launched by torchrun
    python examples/ddp_train.py --steps 10 --resolution 16   # a quick run
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader

import torchraster as tr
from torchraster.data import RenderDataset
from torchraster.pipeline import build_scene

SPOT = Path(tr.__file__).resolve().parent / "assets" / "spot" / "spot_triangulated.obj"


def config_text(resolution: int, color: list[float]) -> str:
    """The render config of the targets (YAML)."""
    return (f"scene:\n  mesh: {SPOT.as_posix()}\n  max_texture_size: 64\n"
            "cameras:\n  - random_orbits: {count: 16, seed: 0, elevation_deg: [-10, 40]}\n"
            f"render:\n  resolution: {resolution}\n  shading: headlight\n"
            f"materials:\n  - base_color: {color}\n"
            "outputs:\n  channels: [color, radiance]\n")


class ColorModel(torch.nn.Module):
    """Renders the config's scene with a learnable base colour.

    Args:
        cfg: the render config (its scene, resolution and shading).
    """

    def __init__(self, cfg: tr.config.RenderFile) -> None:
        super().__init__()
        self.scene = build_scene(cfg)
        self.renderer = tr.Renderer(cfg.render.size, shading=cfg.render.shading)
        self.logits = torch.nn.Parameter(torch.zeros(3))

    @property
    def color(self) -> torch.Tensor:
        """``(3,)`` the current base colour in (0, 1)."""
        return torch.sigmoid(self.logits)

    def forward(self, view: torch.Tensor, proj: torch.Tensor) -> torch.Tensor:
        """Linear radiance ``(B, 3, H, W)`` seen by cameras ``view``, ``proj`` ``(B, 4, 4)``."""
        factor = torch.cat([self.color, self.color.new_ones(1)])
        materials = [dataclasses.replace(m, base_color_factor=factor) if m is not None
                     else tr.Material(base_color_factor=factor) for m in self.scene.materials]
        scene = dataclasses.replace(self.scene, materials=materials)
        return self.renderer(scene, view, proj).image


def train(rank: int, world: int, init_method: str, args: argparse.Namespace) -> None:
    """One rank of the training run."""
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=init_method, rank=rank, world_size=world)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "ddp_train.yaml"
            path.write_text(config_text(args.resolution, args.true_color))
            cfg = tr.load_config(path)
            data = RenderDataset(cfg, shuffle=True)  # shards by rank (torch.distributed)
            loader = DataLoader(data, batch_size=args.batch, num_workers=args.workers)
            model = DistributedDataParallel(ColorModel(cfg))
            opt = torch.optim.Adam(model.parameters(), lr=args.lr)
            truth = torch.tensor(args.true_color)
            if rank == 0:
                print(f"{world} ranks, {len(data)} views per rank per epoch, batch "
                      f"{args.batch}, {args.resolution}px")
                print(f"{'step':>5} {'loss':>10} {'colour error':>13} {'ms/step':>8}  colour")
            step, epoch = 0, 0
            while step < args.steps:
                data.set_epoch(epoch)
                for batch in loader:
                    t = time.perf_counter()
                    pred = model(batch["view"], batch["proj"])
                    loss = torch.nn.functional.mse_loss(pred, batch["radiance"])
                    opt.zero_grad()
                    loss.backward()  # DDP all-reduces (averages) the gradient here
                    opt.step()
                    mean = loss.detach().clone()
                    dist.all_reduce(mean)
                    step += 1
                    if rank == 0 and (step % args.log_every == 0 or step == args.steps):
                        color = model.module.color.detach()
                        err = float((color - truth).abs().max())
                        print(f"{step:>5} {float(mean) / world:>10.3e} {err:>13.4f} "
                              f"{(time.perf_counter() - t) * 1e3:>8.0f}  "
                              f"{[round(c, 3) for c in color.tolist()]}")
                    if step >= args.steps:
                        break
                epoch += 1
    finally:
        dist.destroy_process_group()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--nproc", type=int, default=2, help="processes when not under torchrun")
    p.add_argument("--steps", type=int, default=40, help="optimisation steps (default 40)")
    p.add_argument("--batch", type=int, default=4, help="views per rank per step (default 4)")
    p.add_argument("--resolution", type=int, default=32, help="image side (default 32)")
    p.add_argument("--lr", type=float, default=0.1, help="Adam learning rate (default 0.1)")
    p.add_argument("--workers", type=int, default=0, help="DataLoader workers per rank")
    p.add_argument("--log-every", type=int, default=5, help="print every N steps")
    p.add_argument("--true-color", type=float, nargs=3, default=[0.9, 0.35, 0.1],
                   help="base colour of the targets (default 0.9 0.35 0.1)")
    args = p.parse_args(argv)
    if "RANK" in os.environ:  # launched by torchrun: one process of WORLD_SIZE
        train(int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"]), "env://", args)
        return 0
    with tempfile.TemporaryDirectory() as tmp:  # rendezvous through a file: no network
        torch.multiprocessing.spawn(train, args=(args.nproc, f"file://{tmp}/rendezvous", args),
                                    nprocs=args.nproc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
