"""Exports of a rendered dataset folder into the files training code reads.

Each writer reads the folder's manifest records (:func:`torchraster.manifest.read_manifest`)
and the channel files they name, and writes under ``<out_dir>/exports/`` atomically:

* :func:`write_coco` -> ``exports/coco/instances.json`` (COCO instances, RLE masks);
* :func:`write_bop` -> ``exports/bop/<scene_id:06d>/...`` (BOP 6D pose format);
* :func:`write_nerf` -> ``exports/nerf/transforms.json`` (NeRF / instant-ngp / nerfstudio);
* :func:`write_webdataset` -> ``exports/webdataset/shard-%06d.tar`` (resumable);
* :func:`write_tracks` -> ``exports/tracks/<video>.npz`` (TAP-Vid style point tracks).

COCO needs pycocotools (``pip install 'torchraster[datasets]'``); the other writers need
no extra package (the shards are plain tar files WebDataset reads).
"""

from .bop import write_bop
from .coco import coco_dataset, write_coco
from .common import EXPORTS, ExportError
from .nerf import write_nerf
from .tracks import write_tracks
from .wds import sample_key, write_webdataset

__all__ = ["EXPORTS", "ExportError", "coco_dataset", "sample_key", "write_bop", "write_coco",
           "write_nerf", "write_tracks", "write_webdataset"]
