"""The Blender side of the dataset benchmark: a MOVi-like scene rendered by Blender's own
Python module (``bpy``), for ``scripts/bench_dataset.py --blender PYTHON``.

Run with a Python that has ``bpy`` installed (e.g. a virtualenv with ``pip install
bpy==5.0.1``; not a dependency of torchraster). The scene follows configs/dataset_movi.yaml:
8 objects (the shipped Spot mesh, boxes of 0.7 and spheres of 0.8 on a 14 m floor, random
colours, roughness and metal), a sun and the shipped venice_sunset_256.hdr, an orbiting
camera (fov 50°), objects moving over 24 frames, 256 x 256, passes Combined, Depth,
Normal, IndexOB, Vector and Cryptomatte (objects), written as multilayer EXR per frame.
Prints one JSON line: seconds per frame (median over the timed frames, after one warm-up
frame) for each setting.

    PYTHON scripts/blender_movi.py [--frames 6] [--settings cycles1,cycles16,...]
"""

from __future__ import annotations

import argparse
import json
import math
import random
import statistics
import tempfile
import time
from pathlib import Path

import bpy

ROOT = Path(__file__).resolve().parent.parent
SPOT = ROOT / "torchraster" / "assets" / "spot" / "spot_triangulated.obj"
HDR = ROOT / "torchraster" / "assets" / "envmaps" / "venice_sunset_256.hdr"
SETTINGS = {  # name -> (engine, samples, persistent data)
    "cycles1": ("CYCLES", 1, False),
    "cycles1_persistent": ("CYCLES", 1, True),
    "cycles16": ("CYCLES", 16, False),
    "cycles64": ("CYCLES", 64, False),
    "workbench": ("BLENDER_WORKBENCH", 0, False),
}


def material(rng: random.Random) -> bpy.types.Material:
    mat = bpy.data.materials.new("m")
    mat.use_nodes = True
    bsdf = mat.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (rng.random(), rng.random(), rng.random(), 1)
    bsdf.inputs["Roughness"].default_value = rng.uniform(0.15, 0.9)
    bsdf.inputs["Metallic"].default_value = 1.0 if rng.random() < 0.25 else 0.0
    return mat


def build_scene(frames: int) -> bpy.types.Scene:
    """The scene (objects, sun, environment, camera, motion, passes)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    rng = random.Random(0)
    bpy.ops.mesh.primitive_plane_add(size=14)
    floor = bpy.context.object
    floor.data.materials.append(material(rng))
    floor.pass_index = 1
    for i in range(8):
        kind = ["cow", "cube", "cube", "ball", "ball"][rng.randrange(5)]
        x, z = rng.uniform(-3.2, 3.2), rng.uniform(-3.2, 3.2)
        if kind == "cow":
            bpy.ops.wm.obj_import(filepath=str(SPOT), forward_axis="NEGATIVE_Z", up_axis="Y")
            obj = bpy.context.selected_objects[0]
        elif kind == "cube":
            bpy.ops.mesh.primitive_cube_add(size=0.7)
            obj = bpy.context.object
        else:
            bpy.ops.mesh.primitive_uv_sphere_add(radius=0.4, segments=32, ring_count=16)
            obj = bpy.context.object
        obj.data.materials.clear()
        obj.data.materials.append(material(rng))
        obj.pass_index = i + 2
        obj.location = (x, z, 0.4)
        obj.keyframe_insert("location", frame=1)
        obj.location = (x + rng.uniform(-0.6, 0.6) * 2, z + rng.uniform(-0.6, 0.6) * 2, 0.4)
        obj.keyframe_insert("location", frame=frames)
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", type="SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (math.radians(40), 0, math.radians(30))
    scene.collection.objects.link(sun)
    world = bpy.data.worlds.new("w")
    world.use_nodes = True
    env = world.node_tree.nodes.new("ShaderNodeTexEnvironment")
    env.image = bpy.data.images.load(str(HDR))
    world.node_tree.links.new(env.outputs["Color"],
                              world.node_tree.nodes["Background"].inputs["Color"])
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.5
    scene.world = world
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    cam.data.angle = math.radians(50)
    scene.collection.objects.link(cam)
    scene.camera = cam
    target = bpy.data.objects.new("target", None)
    target.location = (0, 0, 0.2)
    scene.collection.objects.link(target)
    track = cam.constraints.new("TRACK_TO")
    track.target = target
    for f, az in ((1, 0.0), (frames, 12.0)):  # 6 degrees a second at 12 fps
        a, el = math.radians(az), math.radians(30)
        cam.location = (10 * math.cos(el) * math.sin(a), -10 * math.cos(el) * math.cos(a),
                        10 * math.sin(el))
        cam.keyframe_insert("location", frame=f)
    scene.frame_start, scene.frame_end = 1, frames
    scene.render.resolution_x = scene.render.resolution_y = 256
    scene.render.resolution_percentage = 100
    scene.render.threads_mode = "FIXED"
    scene.render.threads = 2
    layer = scene.view_layers[0]
    layer.use_pass_z = layer.use_pass_normal = layer.use_pass_object_index = True
    layer.use_pass_vector = layer.use_pass_cryptomatte_object = True
    settings = scene.render.image_settings
    if hasattr(settings, "media_type"):  # Blender 5: multilayer images are a media type
        settings.media_type = "MULTI_LAYER_IMAGE"
    settings.file_format = "OPEN_EXR_MULTILAYER"
    return scene


def time_setting(scene: bpy.types.Scene, name: str, frames: int, out: Path) -> float:
    """Median seconds per frame of ``frames`` frames after a warm-up frame."""
    engine, samples, persistent = SETTINGS[name]
    scene.render.engine = engine
    scene.render.use_persistent_data = persistent
    if engine == "CYCLES":
        scene.cycles.device = "CPU"
        scene.cycles.samples = samples
        scene.cycles.use_denoising = False
        scene.cycles.use_adaptive_sampling = False
    times = []
    for f in range(1, frames + 2):
        scene.frame_set(f)
        scene.render.filepath = str(out / f"{name}_{f:03d}")
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        if f > 1:
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--settings", default=",".join(SETTINGS))
    args, _ = ap.parse_known_args()
    scene = build_scene(24)
    result = {"bpy": bpy.app.version_string}
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.settings.split(","):
            result[name] = time_setting(scene, name, args.frames, Path(tmp))
    print(json.dumps(result))


if __name__ == "__main__":
    main()
