"""Full-frame benchmark: our ``Renderer`` against pyrender on Mesa llvmpipe.

The same glTF model (``gltf/DamagedHelmet`` of the asset folder ``$TORCHRASTER_DATA``,
full-resolution textures), the same cameras (orbiting the model's bounding sphere, fov 45
deg, infinite far plane), two point lights and a directional light, PBR shading, at 256²
and 512², batch 1 and 8. Rows:

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
    python scripts/bench_frame.py --profile   # top ops + stages of 512², batch 1, no shadows
    python scripts/bench_frame.py --picture   # docs/images/frame_vs_pyrender.png

``--profile`` writes section ``frame-profile``: torch.profiler's top operators by self CPU
time and the CPU time of each stage of ``Renderer.forward`` (one call after warm-ups), as
the "after" table; the "before" table is kept from the section as it was, or replaced with
``--label before`` (run against an older checkout, e.g. ``PYTHONPATH=<old checkout>``).
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

# the asset folder as torchraster.testing.assets.data_dir() names it (not imported: this
# script also times older checkouts, which lack that module)
DATA = Path(os.environ.get("TORCHRASTER_DATA")
            or Path(__file__).resolve().parents[2] / "shared" / "data")
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


#: Stages of ``Renderer.forward`` timed by ``--profile``: (module, attribute, label).
STAGES = [("torchraster.renderer", "transform_points", "transform"),
          ("torchraster.renderer", "rasterize", "rasterize"),
          ("torchraster.renderer", "geometry_pass", "G-buffer (total)"),
          ("torchraster.gbuffer", "interpolate_packed", "  interpolate"),
          ("torchraster.gbuffer", "_sample_atlases", "  texture sampling"),
          ("torchraster.gbuffer", "_material_values", "  material values"),
          ("torchraster.gbuffer", "_apply_normal_maps", "  normal mapping"),
          ("torchraster.gbuffer", "to_image", "  scatter to images"),
          ("torchraster.renderer", "shade", "lighting (shade)"),
          ("torchraster.renderer", "view_rays", "background rays")]


def load_model():
    """DamagedHelmet flattened: (mesh, face_material, materials, bounding-sphere centre
    (3,), radius)."""
    import torchraster as tr

    mesh, face_material, materials = tr.load_scene(MODEL).flatten()
    lo, hi = mesh.positions.amin(0), mesh.positions.amax(0)
    center = (lo + hi) / 2
    return mesh, face_material, materials, center, float(
        (mesh.positions - center).norm(dim=-1).max())


def profile_frame(label: str, source: str, threads: int, rows: int = 12) -> None:
    """Profile one 512², batch 1, no-shadow ``Renderer`` forward; print and write the
    ``frame-profile`` section (see the module docstring)."""
    import importlib
    import re
    import shlex

    import torch
    from torch.profiler import ProfilerActivity, profile, record_function

    import torchraster as tr

    torch.set_num_threads(threads)
    mesh, face_material, materials, center, radius = load_model()
    lights = our_lights(center, radius, "none")
    renderer = tr.Renderer((512, 512), shading="pbr")
    view, proj, _ = cameras(1, center, radius)
    rscene = tr.RenderScene.from_mesh(mesh, face_material, materials)
    for mod_name, attr, name in STAGES:  # label the stages in the profile
        mod = importlib.import_module(mod_name)
        fn = getattr(mod, attr, None)
        if fn is None:
            continue

        def labelled(*a, _fn=fn, _name=name, **k):
            with record_function("stage: " + _name.strip()):
                return _fn(*a, **k)

        setattr(mod, attr, labelled)

    def frame():
        with torch.no_grad():
            return renderer(rscene, view, proj, lights).image

    for _ in range(3):
        frame()
    wall = statistics.median(timed_turns({"ours": frame}, 5)["ours"]) * 1e3
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        frame()
    events = prof.key_averages()
    total = sum(e.self_cpu_time_total for e in events) / 1e3
    stage = {e.key[len("stage: "):]: e.cpu_time_total / 1e3 for e in events
             if e.key.startswith("stage: ")}
    ops = sorted((e for e in events if not e.key.startswith("stage: ")),
                 key=lambda e: -e.self_cpu_time_total)[:rows]
    from benchmd import markdown_table, update_section

    run = "python " + shlex.join([os.path.relpath(sys.argv[0])] + sys.argv[1:])
    stage_rows = [[name, stage[name.strip()]] for _, _, name in STAGES if name.strip() in stage]
    op_rows = [[e.key, e.self_cpu_time_total / 1e3, 100 * e.self_cpu_time_total / 1e3 / total,
                e.count] for e in ops]
    block = (f"### {label}\n\n"
             f"Code: {source}; forward {wall:.1f} ms (median of 5, no profiler); profiled call: "
             f"{total:.1f} ms self CPU in total. Run: `{run}`.\n\n"
             + markdown_table(["stage (CPU total, ms)", "ms"], stage_rows) + "\n\n"
             + markdown_table(["top op by self CPU", "self ms", "% of total", "calls"], op_rows)
             + "\n")
    print(block)
    doc = Path(__file__).resolve().parent.parent / "docs" / "benchmarks.md"
    old = doc.read_text() if doc.exists() else ""
    match = re.search(r"<!-- begin frame-profile -->(.*?)<!-- end frame-profile -->", old, re.S)
    blocks = {}
    if match:
        for m in re.finditer(r"(### (before|after).*?)(?=### (?:before|after)|\nCommand:|$)",
                             match.group(1), re.S):
            blocks[m.group(2)] = m.group(1).rstrip() + "\n"
    blocks[label] = block
    body = ("## Full-frame profile (512², batch 1, no shadows)\n\n"
            "DamagedHelmet as in *Full frame vs pyrender*, `Renderer(...)` forward under "
            f"`no_grad`, torch with {threads} threads; torch.profiler (CPU), stages labelled "
            "with `record_function` around the functions `Renderer.forward` calls (stage rows "
            "include their children). Before: the commit named there; after: this tree.\n\n"
            + "\n".join(blocks[k] for k in ("before", "after") if k in blocks))
    update_section("frame-profile", body, command=run)


def picture(threads: int, res: int = 256) -> None:
    """docs/images/frame_vs_pyrender.png: the no-shadow frame by pyrender and by us (linear
    radiance clamped to [0, 1], sRGB-encoded, as pyrender writes its colour buffer)."""
    import numpy as np
    import torch
    from PIL import Image

    import torchraster as tr

    torch.set_num_threads(threads)
    mesh, face_material, materials, center, radius = load_model()
    view, proj, near = cameras(1, center, radius)
    with torch.no_grad():
        img = tr.Renderer((res, res), shading="pbr")(
            tr.RenderScene.from_mesh(mesh, face_material, materials), view, proj,
            our_lights(center, radius, "none")).image[0]
    x = img.clamp(0, 1)
    x = torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-12) ** (1 / 2.4) - 0.055)
    ours = (x.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)
    pyrender = load_pyrender()
    pr_scene = pyrender_scene(pyrender, center, radius)
    pr_scene.add(pyrender.PerspectiveCamera(yfov=math.radians(FOV_DEG), znear=near,
                                            aspectRatio=1.0),
                 pose=torch.linalg.inv(view.double())[0].numpy())
    offscreen = pyrender.OffscreenRenderer(res, res)
    theirs = offscreen.render(pr_scene)[0][..., :3]
    offscreen.delete()
    out = Path(__file__).resolve().parent.parent / "docs" / "images" / "frame_vs_pyrender.png"
    Image.fromarray(np.concatenate([theirs, ours], 1)).save(out, optimize=True)
    print(f"wrote {out} ({out.stat().st_size // 1024} KB)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--picture", action="store_true",
                    help="write docs/images/frame_vs_pyrender.png (pyrender | ours, 256²)")
    ap.add_argument("--quick", action="store_true", help="256², batch 1, 3 repeats, no doc")
    ap.add_argument("--profile", action="store_true",
                    help="profile 512², batch 1, no shadows; write section frame-profile")
    ap.add_argument("--label", choices=("before", "after"), default="after",
                    help="which table of the profile section --profile writes")
    ap.add_argument("--source", default="this tree",
                    help="what code was profiled (printed above the --profile table)")
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
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    if args.profile:
        profile_frame(args.label, args.source, args.threads)
        return
    if args.picture:
        picture(args.threads)
        return
    mesh, face_material, materials, center, radius = load_model()

    try:
        pyrender = load_pyrender()
        pr_error = None
    except Exception as err:  # noqa: BLE001 (reported in the table)
        pyrender, pr_error = None, f"{type(err).__name__}: {err}"

    sizes = [256] if args.quick else [256, 512]
    batches = [1] if args.quick else [1, 8]
    repeats = 3 if args.quick else args.repeats
    rows, notes, gl_name = [], [], "n/a"
    flag_of = {"none": "NONE", "sun": "SHADOWS_DIRECTIONAL",
               "sun, uncached": "SHADOWS_DIRECTIONAL", "all": "SHADOWS_ALL"}
    for shadows in ("none", "sun", "sun, uncached", "all"):
        lights = our_lights(center, radius, shadows.split(",")[0])
        pr_scene = pyrender_scene(pyrender, center, radius) if pyrender else None
        for res in sizes:
            renderer = tr.Renderer((res, res), shading="pbr")
            if shadows.endswith("uncached"):
                renderer.shadow_cache = None  # every call renders its shadow maps
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
        "same process. Shadows (default `ShadowSettings`: maps rendered by our rasterizer, "
        "4-tap PCF): *sun*: the directional light casts (pyrender "
        "`RenderFlags.SHADOWS_DIRECTIONAL`); our shadow maps are cached by content across "
        "calls (`Renderer.shadow_cache`: casters and lights do not move here, so after the "
        "warm-up no map is rendered, and the batch's 8 cameras share the sun's map); *sun, "
        "uncached*: the same with `renderer.shadow_cache = None` (every call renders its "
        "map, as pyrender does); *all*: every light casts (cube maps for the point lights) vs "
        "`RenderFlags.SHADOWS_ALL`. Medians of "
        f"{repeats} turns after a warm-up; *ours / pyrender* is the median of the per-turn "
        f"ratios (< 1: we are faster).\n\n{table}\n\n"
        f"pyrender problems:\n{note}\n\n"
        "pyrender runtime patches (numpy 2): `np.infty = np.inf`; `PYOPENGL_PLATFORM=egl`.\n\n"
        "Load average at the end of the run (1/5/15 min): "
        + " / ".join(f"{x:.1f}" for x in os.getloadavg())
        + f" on {os.cpu_count()} cores (the machine is shared: other processes slow both "
        "sides; compare the per-turn ratios).\n"
    )
    update_section("frame", body)


if __name__ == "__main__":
    main()
