"""Full-frame benchmark: our ``Renderer`` against pyrender on Mesa llvmpipe.

The same glTF model (``../shared/data/gltf/DamagedHelmet``, full-resolution textures), the
same cameras (orbiting the model's bounding sphere, fov 45 deg, infinite far plane), two
point lights and a directional light, PBR shading, at 256² and 512², batch 1 and 8. Rows:

* ours forward (``torch.no_grad``): ``Renderer(...)(scene, view, proj, lights).image``;
* ours forward + backward: the same with gradients to the vertex positions and the light
  intensities, ``image.mean().backward()``;
* pyrender: ``OffscreenRenderer.render(scene)`` (colour and depth read back to numpy), one
  call per view (pyrender has no batch), OpenGL on Mesa's llvmpipe through EGL;
* shadowed variants: ``sun``: the directional light casts shadows (our default
  ``ShadowSettings``; pyrender ``RenderFlags.SHADOWS_DIRECTIONAL``); ``all``: every light
  casts (ours: cube maps for the point lights; pyrender ``RenderFlags.SHADOWS_ALL``, which
  raises ``NotImplementedError`` for point lights, reported under the table).

Both sides run in this one process on the same cores: torch with ``--threads`` intra-op
threads and llvmpipe with ``LP_NUM_THREADS`` set to the same number. Each configuration is
timed in turns (ours, then pyrender, repeated), so load from other processes hits both
alike; medians of the repeats after a warm-up, and the median of the per-turn ratios.

pyrender 0.1.45 needs two runtime patches here, applied by :func:`load_pyrender` (the
installed package is not modified): numpy 2 removed ``np.infty`` (used by
``pyrender.Mesh.bounds``), restored as ``np.inf``; and ``PYOPENGL_PLATFORM=egl`` is set
before import (headless). pyrender is a benchmark-only dependency (``pip install -e
'.[bench]'``).

    python scripts/bench_frame.py             # the table, written to docs/benchmarks.md
    python scripts/bench_frame.py --quick     # 256², batch 1, few repeats; no doc update
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "data"
MODEL = DATA / "gltf" / "DamagedHelmet" / "DamagedHelmet.gltf"
FOV_DEG = 45.0
ELEVATION_DEG = 12.0
#: Two point lights (candela) and a directional light (lux), in units of the model's
#: bounding-sphere radius around its centre.
POINTS = [((1.5, 1.5, 2.0), 12.0, (1.0, 0.85, 0.7)), ((-2.0, 0.8, 1.5), 8.0, (0.7, 0.8, 1.0))]
SUN = ((-1.0, -1.0, -1.0), 2.0, (1.0, 1.0, 1.0))


def load_pyrender():
    """Import pyrender headless (EGL) with the numpy-2 patch; returns the module."""
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    import numpy as np

    if not hasattr(np, "infty"):  # numpy 2 removed the alias; pyrender.Mesh.bounds uses it
        np.infty = np.inf
    import pyrender

    return pyrender


def cameras(batch: int, center, radius: float):
    """World -> view ``(B, 4, 4)`` orbit cameras framing the bounding sphere, and the
    projection ``(1, 4, 4)``; the same numbers go to pyrender."""
    import torch

    import torchraster as tr

    fov = math.radians(FOV_DEG)
    distance = radius / math.sin(fov / 2) * 1.05
    az = torch.linspace(0.0, 360.0, batch + 1)[:batch] + 25.0
    view = tr.camera.orbit(az, torch.full((batch,), ELEVATION_DEG),
                           torch.full((batch,), distance), center.tolist())
    near = max(distance - 2 * radius, distance * 1e-3)
    proj = tr.camera.perspective(FOV_DEG, 1.0, near)
    return view, proj, near


def our_lights(center, radius: float, shadows: str):
    """The three lights; ``shadows``: "none", "sun" (the directional light casts) or "all"."""
    from torchraster.config import lights_from_config

    cfg = [{"type": "point", "position": [c + radius * p for c, p in zip(center.tolist(), pos,
                                                                          strict=True)],
            "intensity": inten * radius ** 2, "color": list(col),
            "cast_shadows": shadows == "all"}
           for pos, inten, col in POINTS]
    cfg.append({"type": "directional", "direction": list(SUN[0]), "intensity": SUN[1],
                "color": list(SUN[2]), "cast_shadows": shadows != "none"})
    return lights_from_config(cfg)


def pyrender_scene(pyrender, center, radius: float):
    """The model, the three lights and a camera node (pose set per view)."""
    import numpy as np
    import trimesh

    scene = pyrender.Scene.from_trimesh_scene(trimesh.load(MODEL), ambient_light=np.zeros(3),
                                              bg_color=np.zeros(4))
    for pos, inten, col in POINTS:
        pose = np.eye(4)
        pose[:3, 3] = center.numpy() + radius * np.array(pos)
        scene.add(pyrender.PointLight(color=np.array(col), intensity=inten * radius ** 2),
                  pose=pose)
    d = -np.array(SUN[0]) / np.linalg.norm(SUN[0])  # pyrender lights shine along -z
    up = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.99 else np.array([1.0, 0.0, 0.0])
    x = np.cross(up, d)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(d, x), d], axis=1)
    scene.add(pyrender.DirectionalLight(color=np.array(SUN[2]), intensity=SUN[1]), pose=pose)
    return scene


def timed_turns(fns: dict, repeats: int) -> dict:
    """Seconds of ``repeats`` calls of each function, the functions called in turns (load
    from other processes hits them alike), after one warm-up call each: ``{key: [s, ...]}``
    (also used by scripts/bench_shading.py)."""
    for fn in fns.values():
        fn()  # warm-up: allocator, caches, shader compilation
    times = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t)
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="256², batch 1, 3 repeats, no doc")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 1,
                    help="torch intra-op threads = LP_NUM_THREADS of llvmpipe")
    args = ap.parse_args()
    os.environ["LP_NUM_THREADS"] = str(args.threads)  # before any GL context exists
    import torch

    import torchraster as tr

    torch.set_num_threads(args.threads)
    if not MODEL.exists():
        print(f"{MODEL} not found: nothing to do")
        return
    scene = tr.load_scene(MODEL)
    mesh, face_material, materials = scene.flatten()
    lo, hi = mesh.positions.amin(0), mesh.positions.amax(0)
    center = (lo + hi) / 2
    radius = float((mesh.positions - center).norm(dim=-1).max())

    try:
        pyrender = load_pyrender()
        pr_error = None
    except Exception as err:  # noqa: BLE001 (reported in the table)
        pyrender, pr_error = None, f"{type(err).__name__}: {err}"

    sizes = [256] if args.quick else [256, 512]
    batches = [1] if args.quick else [1, 8]
    repeats = 3 if args.quick else args.repeats
    rows, notes, gl_name = [], [], "n/a"
    flag_of = {"none": "NONE", "sun": "SHADOWS_DIRECTIONAL", "all": "SHADOWS_ALL"}
    for shadows in ("none", "sun", "all"):
        lights = our_lights(center, radius, shadows)
        pr_scene = pyrender_scene(pyrender, center, radius) if pyrender else None
        for res in sizes:
            renderer = tr.Renderer((res, res), shading="pbr")
            offscreen = pyrender.OffscreenRenderer(res, res) if pyrender else None
            if offscreen is not None and gl_name == "n/a":
                from OpenGL import GL

                offscreen._platform.make_current()
                gl_name = GL.glGetString(GL.GL_RENDERER).decode()
            for batch in batches:
                view, proj, near = cameras(batch, center, radius)
                rscene = tr.RenderScene.from_mesh(mesh, face_material, materials)

                def ours(rscene=rscene, view=view, proj=proj, lights=lights,
                         renderer=renderer):
                    with torch.no_grad():
                        return renderer(rscene, view, proj, lights).image

                def ours_grad(view=view, proj=proj, lights=lights, renderer=renderer,
                              rscene=rscene):
                    pos = mesh.positions.clone().requires_grad_()
                    grad_scene = tr.RenderScene(pos, rscene.faces, rscene.normals, rscene.uvs,
                                                rscene.tangents, face_material, materials)
                    point = lights.point
                    inten = point.intensity.clone().requires_grad_()
                    lit = tr.Lights(point=tr.PointLights(point.position, point.color, inten,
                                                         point.range, point.cast_shadows),
                                    directional=lights.directional)
                    img = renderer(grad_scene, view, proj, lit).image
                    img.mean().backward()
                    return img

                fns = {"ours": ours, "ours_grad": ours_grad}
                poses = torch.linalg.inv(view.double()).numpy()
                if offscreen is not None:
                    cam_node = pr_scene.add(pyrender.PerspectiveCamera(
                        yfov=math.radians(FOV_DEG), znear=near, aspectRatio=1.0))
                    flags = getattr(pyrender.RenderFlags, flag_of[shadows])

                    def pyr(cam_node=cam_node, poses=poses, flags=flags, offscreen=offscreen,
                            pr_scene=pr_scene):
                        out = []
                        for pose in poses:
                            pr_scene.set_pose(cam_node, pose)
                            out.append(offscreen.render(pr_scene, flags=flags))
                        return out

                    try:
                        pyr()
                        fns["pyrender"] = pyr
                    except Exception as err:  # noqa: BLE001 (reported below the table)
                        notes.append(f"pyrender `RenderFlags.{flag_of[shadows]}` at {res}², "
                                     f"batch {batch}: `{type(err).__name__}: {err}`")
                times = timed_turns(fns, repeats)
                med = {k: statistics.median(v) * 1e3 for k, v in times.items()}
                ratio = (statistics.median(a / b for a, b in zip(times["ours"],
                                                                  times["pyrender"],
                                                                  strict=True))
                         if "pyrender" in times else math.nan)
                row = [shadows, f"{res}²", batch, med["ours"],
                       med["ours_grad"], med.get("pyrender", math.nan), ratio,
                       med["ours_grad"] / med["ours"]]
                rows.append(row)
                print(" | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in row),
                      flush=True)
                if offscreen is not None:
                    pr_scene.remove_node(cam_node)
            if offscreen is not None:
                offscreen.delete()
    for n in notes:
        print(n)
    if args.quick:
        return
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from benchmd import markdown_table, update_section

    table = markdown_table(["shadows", "resolution", "batch", "ours forward ms",
                            "ours forward+backward ms", "pyrender ms", "ours / pyrender",
                            "fwd+bwd / fwd"], rows)
    note = "\n".join(f"- {n}" for n in notes) if notes else "- none"
    if pr_error:
        note += f"\n- pyrender could not be imported: {pr_error}"
    body = (
        "## Full frame vs pyrender\n\n"
        f"DamagedHelmet (glTF, {mesh.faces.shape[0]} triangles, full-resolution textures), "
        f"orbit cameras framing its bounding sphere (fov {FOV_DEG:g}°, elevation "
        f"{ELEVATION_DEG:g}°), two point lights and a directional light, PBR; batch B = B "
        "views (pyrender renders them one by one). *ours forward*: `Renderer(...)` under "
        "`no_grad`; *forward+backward*: gradients to the vertex positions and the point-light "
        "intensities; *pyrender*: `OffscreenRenderer.render` (colour + depth read back), "
        f"{gl_name}, LP_NUM_THREADS={args.threads}, torch with {args.threads} threads, in the "
        "same process. Shadows: every light `cast_shadows` (default `ShadowSettings`: maps "
        "rendered by our rasterizer, PCF) vs pyrender `RenderFlags.SHADOWS_ALL`. Medians of "
        f"{repeats} turns after a warm-up; *ours / pyrender* is the median of the per-turn "
        f"ratios (< 1: we are faster).\n\n{table}\n\n"
        f"pyrender problems:\n{note}\n\n"
        "pyrender runtime patches (numpy 2): `np.infty = np.inf`; `PYOPENGL_PLATFORM=egl`.\n"
    )
    update_section("frame", body)


if __name__ == "__main__":
    main()
