"""Checks of a validated config that validation cannot make: files that must exist (meshes,
their textures, environment, images) and degenerate cameras, all found in one pass."""

from __future__ import annotations

from pathlib import Path

import torch

from .schema import FLOW_CHANNELS, MAX_INSTANCES, ConfigError, RenderFile
from .views import is_mesh_set, mesh_set_problems


def check_config(cfg: RenderFile) -> None:
    """Find, in one pass before rendering, every problem validation cannot see: missing or
    unreadable files (mesh, environment, textures) and degenerate cameras.

    Raises:
        ConfigError: listing each problem as ``file:line: key.path: message``.
    """
    problems = []

    def need_file(loc: tuple, path: str) -> None:
        p = Path(path)
        if p.is_dir():
            problems.append(f"{cfg.where(*loc)}: {p} is a folder, expected a file")
        elif not p.is_file():
            problems.append(f"{cfg.where(*loc)}: file not found: {p}")

    mesh_set_config = is_mesh_set(cfg)
    if mesh_set_config:  # files checked to exist; textures when each object loads
        problems += mesh_set_problems(cfg)
    meshes = [(("scene", "mesh"), cfg.scene.mesh)] if (
        cfg.scene.mesh is not None and not mesh_set_config) else []
    meshes += [(("scene", "objects", i, "mesh"), o.mesh)
               for i, o in enumerate(cfg.scene.objects) if o.mesh is not None]
    for loc, path in meshes:
        need_file(loc, path)
        mesh = Path(path)
        if mesh.is_file() and not cfg.scene.allow_missing_textures:
            from ..io import missing_textures

            missing = missing_textures(mesh)
            if missing:
                problems.append(f"{cfg.where(*loc)}: {mesh.name} refers to missing texture "
                                f"file(s) {', '.join(missing)} (set "
                                "scene.allow_missing_textures: true to render without them)")
    if cfg.environment is not None:
        need_file(("environment", "path"), cfg.environment.path)
    if cfg.render.background_image is not None:
        need_file(("render", "background_image", "path"), cfg.render.background_image.path)
    for i, m in enumerate(cfg.materials):
        if m.base_color_texture is not None:
            need_file(("materials", i, "base_color_texture"), m.base_color_texture)
    for i, cam in enumerate(cfg.cameras):
        if cam.look_at is None:
            continue
        eye, target, up = (torch.tensor(v, dtype=torch.float64) for v in (
            cam.look_at.eye, cam.look_at.target, cam.look_at.up))
        forward = target - eye
        if float(forward.norm()) <= 1e-12 * max(1.0, float(eye.norm())):
            problems.append(f"{cfg.where('cameras', i, 'look_at', 'eye')}: eye and target "
                            "are the same point; the camera has no direction")
        elif float(torch.linalg.cross(forward, up).norm()) <= 1e-9 * float(
                forward.norm() * up.norm()):
            problems.append(f"{cfg.where('cameras', i, 'look_at', 'up')}: up is parallel to "
                            "the view direction (or zero); pick another up vector")
    if cfg.randomize is not None and not problems:  # the draws must be usable too
        from .variants import scene_variants

        try:
            scene_variants(cfg)
        except ConfigError as e:
            problems.append(str(e))
    if problems:
        raise ConfigError("invalid render config\n  " + "\n  ".join(problems))


#: Channels each export reads.
EXPORT_NEEDS = {"coco": {"instance"}, "bop": {"instance", "amodal", "depth"},
                "tracks": {"instance", "object_coords", "depth"}}
#: Exports that read float channels from npy files.
EXPORT_NEEDS_NPY = {"bop", "tracks"}


def dataset_problems(cfg: RenderFile) -> list[str]:
    """Problems of the dataset sections that need the whole config (``file:line: key:
    message``): flow channels without a second frame, exports without the channels they
    read, unknown or repeated categories, more instances than 16-bit ids hold."""
    problems = []
    channels = set(cfg.outputs.channels)
    flow = sorted(FLOW_CHANNELS & channels)
    if flow and cfg.frames.count < 2:
        problems.append(f"{cfg.where('outputs', 'channels')}: {', '.join(flow)} "
                        f"{'needs' if len(flow) == 1 else 'need'} another frame; set "
                        "frames: {count: 2 or more, fps: ...}")
    if "track_points" in cfg.outputs.model_fields_set and "tracks" not in cfg.outputs.exports:
        problems.append(f"{cfg.where('outputs', 'track_points')}: used by the tracks export "
                        "only; add tracks to outputs.exports or remove it")
    if cfg.outputs.previews and not {"instance", "semantic"} & channels:
        problems.append(f"{cfg.where('outputs', 'previews')}: previews colour the instance / "
                        "semantic channels; add one to outputs.channels")
    for i, export in enumerate(cfg.outputs.exports):
        missing = EXPORT_NEEDS.get(export, set()) - channels
        if missing:
            problems.append(f"{cfg.where('outputs', 'exports', i)}: {export} needs the "
                            f"channel(s) {', '.join(sorted(missing))} in outputs.channels")
        if export in EXPORT_NEEDS_NPY and "npy" not in cfg.outputs.formats:
            problems.append(f"{cfg.where('outputs', 'exports', i)}: {export} reads npy files: "
                            "add npy to outputs.formats")
    keyed = [(("scene", "animation"), cfg.scene.animation)] + [
        (("scene", "objects", i, "animation"), o.animation)
        for i, o in enumerate(cfg.scene.objects)] + [
        (("cameras", i, "trajectory"), c.trajectory) for i, c in enumerate(cfg.cameras)]
    for loc, block in keyed:
        if block is None:
            continue
        for i in range(1, len(block.keys)):
            now, before = block.keys[i].time, block.keys[i - 1].time
            if now <= before:
                what = "duplicates" if now == before else "comes before"
                problems.append(f"{cfg.where(*loc, 'keys', i, 'time')}: {now} {what} "
                                f"keys[{i - 1}].time ({before}): keyframes must be in "
                                "increasing time order")
    named = [(("scene", "category"), cfg.scene.category)] + [
        (("scene", "objects", i, "category"), o.category)
        for i, o in enumerate(cfg.scene.objects)]
    if cfg.categories is not None:
        seen: set[str] = set()
        for i, c in enumerate(cfg.categories):
            if c in seen:
                problems.append(f"{cfg.where('categories', i)}: {c!r} is listed twice")
            seen.add(c)
        for loc, c in named:
            if c is not None and c not in seen:
                problems.append(f"{cfg.where(*loc)}: unknown category {c!r}; expected one of "
                                f"categories: {cfg.categories}")
    if "bop" in cfg.outputs.exports:  # BOP's obj_id is the category id
        pool = cfg.randomize.objects.pool if (cfg.randomize is not None
                                              and cfg.randomize.objects is not None) else []
        unnamed = ([("scene", "mesh")] if cfg.scene.mesh is not None and
                   cfg.scene.category is None else []) + [
            ("scene", "objects", i) for i, o in enumerate(cfg.scene.objects)
            if o.category is None] + [
            ("randomize", "objects", "pool", i) for i, o in enumerate(pool) if o.category is None]
        for loc in unnamed:
            problems.append(f"{cfg.where(*loc)}: the bop export numbers objects by category "
                            "(obj_id): give this object a category")
    if len(cfg.scene.objects) + 1 > MAX_INSTANCES:
        problems.append(f"{cfg.where('scene', 'objects')}: {len(cfg.scene.objects)} objects; "
                        f"instance ids are 16-bit (at most {MAX_INSTANCES} instances)")
    return problems
