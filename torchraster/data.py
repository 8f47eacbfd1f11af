"""Render a config's views on the fly, inside ``DataLoader`` workers.

    from torch.utils.data import DataLoader
    from torchraster.data import RenderDataset

    ds = RenderDataset("dataset.yaml", seed=0)       # every (object, camera) view
    for batch in DataLoader(ds, batch_size=8, num_workers=4):
        batch["image"]   # (8, 3, H, W) display colour in [0, 1]
        batch["depth"]   # (8, 1, H, W) linear view depth, 0 where empty
        batch["K"]       # (8, 3, 3) OpenCV intrinsics; batch["view"] (8, 4, 4) OpenGL

The views are those ``torchraster render`` writes for the same config (same order, same
names, same pixels: seed 0 is the command line's); another ``seed`` draws other random
orbits. Each item is rendered with torch's generator seeded with the item's own seed, so an
item is the same whichever process renders it. Iteration is sharded by distributed rank
(``torch.distributed``, if initialised) and by ``DataLoader`` worker: rank r of R gets
items r, r + R, ... (padded by wrapping around so every rank gets as many, as DDP needs) and
worker w of W every W-th of those; with ``batch_size=1`` (or per-item collation) a
``DataLoader`` returns them in the same order whatever ``num_workers``.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from torch.utils.data import IterableDataset, get_worker_info

from .config import RenderFile, check_config, load_config, stable_seed
from .distributed import current_rank_and_size, seeded_call
from .manifest import camera_matrices
from .pipeline import plan_objects, view_renderer

#: Channels every item holds (``color`` is returned as ``image``).
ITEM_CHANNELS = ("color", "alpha", "depth", "normal")


class RenderDataset(IterableDataset):
    """The views of a render config, rendered when asked for.

    Args:
        config: a config file or a loaded :class:`~torchraster.config.RenderFile` (checked
            with ``check_config``).
        seed: mixed into every view's seed (0: the views of ``torchraster render``).
        channels: more channels to return (names of ``outputs.channels``, e.g.
            ``"radiance"``, ``"albedo"``) besides image, alpha, depth and normal.
        device: where to render.
        shuffle: iterate in a random order, drawn from ``seed`` and the epoch
            (:meth:`set_epoch`), the same in every process.
        rank, world_size: the shard to iterate (default: from ``torch.distributed`` if it
            is initialised, else the whole dataset).

    Items (``dataset[i]`` for ``i`` in ``range(dataset.num_views)``, or by iterating):
        ``image`` ``(3, H, W)`` display colour in [0, 1] (post chain applied); ``alpha``
        ``(1, H, W)``; ``depth`` ``(1, H, W)`` linear view depth (0 where empty);
        ``normal`` ``(3, H, W)`` world-space unit normals; any extra ``channels``
        ``(C, H, W)``; ``view`` ``(4, 4)`` world -> view and ``proj`` ``(4, 4)`` (OpenGL,
        the renderer's); ``K`` ``(3, 3)`` OpenCV intrinsics (NaN for orthographic) and
        ``world_to_camera`` ``(4, 4)`` OpenCV extrinsics; ``seed``, ``index``, ``frame``
        (ints), ``time`` (seconds); label channels (``instance``, ``flow_forward``, ...) as
        ``channels`` (``amodal`` has one plane per object: batch it with
        ``batch_size=1`` or a custom collate when scenes differ in object count);
        ``object``, ``camera`` (names). Tensors are float32 on ``device`` (ids int64).
    """

    def __init__(self, config: str | Path | RenderFile, *, seed: int = 0,
                 channels: tuple[str, ...] | list[str] = (), device: str | torch.device = "cpu",
                 shuffle: bool = False, rank: int | None = None,
                 world_size: int | None = None) -> None:
        super().__init__()
        cfg = config if isinstance(config, RenderFile) else load_config(config)
        check_config(cfg)
        wanted = list(dict.fromkeys([*ITEM_CHANNELS, *channels, *cfg.outputs.channels]))
        cfg = cfg.model_copy(update={"outputs": cfg.outputs.model_copy(
            update={"channels": wanted})})
        self.seed, self.device, self.shuffle = seed, torch.device(device), shuffle
        self.rank, self.world_size = rank, world_size
        self.epoch = 0
        self.plans = plan_objects(cfg, seed)
        self._index = [(oi, vi) for oi, obj in enumerate(self.plans)
                       for vi in range(len(obj.views))]
        self._cache: tuple[int, object] | None = None

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_cache"] = None  # scenes are loaded again in each worker
        return state

    @property
    def num_views(self) -> int:
        """Views of the config (all objects, all cameras)."""
        return len(self._index)

    def __len__(self) -> int:
        """Items one rank iterates (the views divided over the ranks, rounded up)."""
        _, world = self._shard()
        return math.ceil(self.num_views / world)

    def set_epoch(self, epoch: int) -> None:
        """The epoch whose order ``shuffle`` draws (call it in every process, as with
        ``DistributedSampler``)."""
        self.epoch = epoch

    def _shard(self) -> tuple[int, int]:
        rank, world = current_rank_and_size()
        return (self.rank if self.rank is not None else rank,
                self.world_size if self.world_size is not None else world)

    def indices(self) -> list[int]:
        """The view indices this process iterates (its rank's and its worker's share)."""
        n = self.num_views
        order = list(range(n))
        if self.shuffle:
            g = torch.Generator().manual_seed(stable_seed(self.seed, "epoch", self.epoch))
            order = torch.randperm(n, generator=g).tolist()
        rank, world = self._shard()
        total = math.ceil(n / world) * world
        padded = (order * math.ceil(total / max(n, 1)))[:total]
        mine = padded[rank::world]
        info = get_worker_info()
        return mine[info.id::info.num_workers] if info is not None else mine

    def __iter__(self):
        for i in self.indices():
            yield self[i]

    def __getitem__(self, index: int) -> dict:
        if not 0 <= index < self.num_views:
            raise IndexError(f"index {index} out of range for {self.num_views} views")
        if get_worker_info() is not None and torch.get_num_threads() != 1:
            torch.set_num_threads(1)  # workers share the cores (README, "Threads")
        oi, vi = self._index[index]
        obj = self.plans[oi]
        if self._cache is None or self._cache[0] != oi:
            self._cache = (oi, view_renderer(obj.config, self.device))
        render = self._cache[1]
        spec = obj.views[vi]
        result = seeded_call(spec.seed, lambda: render(spec.camera_config, spec.camera,
                                                        spec.frame))
        item = {("image" if k == "color" else k): v for k, v in result.images.items()}
        mats = camera_matrices(result.view, result.proj, obj.config.render.size)
        k = mats["opencv"]["K"]
        item.update(
            view=result.view.float(), proj=result.proj.float(),
            K=torch.tensor(k) if k is not None else torch.full((3, 3), math.nan),
            world_to_camera=torch.tensor(mats["opencv"]["world_to_camera"]),
            seed=spec.seed, index=index, object=spec.object, camera=spec.camera,
            frame=spec.frame, time=result.time)
        return item


__all__ = ["ITEM_CHANNELS", "RenderDataset"]
