"""Antialias benchmark: run time of ``antialias`` relative to ``rasterize``.

For an icosphere (5,120 faces) and Spot (5,856 faces) seen by cameras orbiting them, at
256^2 and 512^2, batch 1 and 4, in one process: the median time of

* ``rasterize`` (forward, no grad) and ``antialias`` (forward, no grad, on an RGB + alpha
  image from ``interpolate``, edge adjacency included), and their ratio;
* forward + backward of ``rasterize -> interpolate -> sum`` against
  ``rasterize -> interpolate -> antialias -> sum``, gradients to clip positions and vertex
  colours (the time antialiasing adds to a training step);

with the number of pixel pairs whose face ids differ and of those that blend. The
measurements of one row are interleaved (round-robin), so load changes on the machine hit
them alike.

    python scripts/bench_antialias.py            # the table, written to docs/benchmarks.md
    python scripts/bench_antialias.py --repeats 3 --no-write
    python scripts/bench_antialias.py --picture  # docs/images/antialias.png only
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parent))

import torchraster as tr  # noqa: E402
from torchraster.raster import antialias_topology  # noqa: E402


def scene(name: str, batch: int):
    """Clip positions (B, V, 4), faces (F, 3) and vertex colours (V, 4) (RGB + alpha)."""
    if name == "icosphere":
        ico = trimesh.creation.icosphere(subdivisions=4)
        verts = torch.tensor(ico.vertices, dtype=torch.float32)
        faces = torch.tensor(ico.faces, dtype=torch.int64)
        distance = 3.0
    else:
        mesh = tr.load_spot()
        verts, faces, distance = mesh.positions, mesh.faces, 2.4
    view = tr.camera.orbit(torch.linspace(20, 290, batch), torch.full((batch,), 20.0),
                           torch.full((batch,), distance))
    clip = tr.camera.transform_points(verts, tr.camera.perspective(45.0, 1.0, 0.1) @ view)
    colors = torch.cat([verts * 0.5 + 0.5, torch.ones_like(verts[:, :1])], 1)
    return clip.reshape(batch, -1, 4).contiguous(), faces, colors


def measure(name: str, res: int, batch: int, repeats: int) -> dict:
    clip, faces, colors = scene(name, batch)
    size = (res, res)

    def raster():
        with torch.no_grad():
            return tr.rasterize(clip, faces, size)

    frags = raster()
    image = tr.interpolate(colors, frags, faces)

    def aa():
        with torch.no_grad():
            return tr.antialias(image, frags, clip, faces)

    def step(with_aa: bool):
        def run():
            c = clip.clone().requires_grad_(True)
            col = colors.clone().requires_grad_(True)
            fr = tr.rasterize(c, faces, size)
            img = tr.interpolate(col, fr, faces)
            if with_aa:
                img = tr.antialias(img, fr, c, faces)
            img.sum().backward()
        return run

    fns = {"raster": raster, "aa": aa, "train": step(False), "train_aa": step(True),
           "topology": lambda: antialias_topology(faces)}
    for fn in fns.values():  # warm-up
        fn()
    times: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for key, fn in fns.items():
            t = time.perf_counter()
            fn()
            times[key].append(time.perf_counter() - t)
    out = {k: statistics.median(v) * 1e3 for k, v in times.items()}
    ids = frags.face_id
    out["pairs"] = int((ids[:, :, 1:] != ids[:, :, :-1]).sum() + (ids[:, 1:] != ids[:, :-1]).sum())
    blended = aa()
    out["changed"] = int(((blended - image).abs().sum(1) > 0).sum())
    return out


ROOT = Path(__file__).resolve().parents[1]


def _rgb(img: torch.Tensor, zoom: int) -> np.ndarray:
    """(3, h, w) in [0, 1] -> uint8 (h * zoom, w * zoom, 3), nearest-neighbour zoom."""
    img = img.clamp(0, 1).repeat_interleave(zoom, 1).repeat_interleave(zoom, 2)
    return (img.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)


def _signed(d: torch.Tensor, scale: float) -> torch.Tensor:
    """(h, w) signed values -> (3, h, w): blue negative, white 0, red positive."""
    v = (d / scale).clamp(-1, 1)
    pos, neg = v.clamp_min(0), (-v).clamp_min(0)
    return torch.stack([1 - neg, 1 - pos - neg, 1 - pos])


def picture(path: Path) -> None:
    """Spot at 96^2, zoomed 4x: no antialiasing, antialias, a 16x16 supersampled
    reference, the antialiased alpha's per-pixel derivative with respect to a screen-space
    shift to the right (autograd, double backward) and that of the supersampled reference
    (central differences)."""
    from PIL import Image, ImageDraw

    res, zoom, ss = 96, 4, 16
    crop = (slice(0, 96), slice(0, 96))
    mesh = tr.load_spot()
    verts, faces = mesh.positions.double(), mesh.faces
    view = tr.camera.look_at([2.3, 0.7, 1.9], [0.0, 0.0, 0.0]).double()
    clip0 = tr.camera.transform_points(
        verts, tr.camera.perspective(40.0, 1.0, 0.1).double() @ view).reshape(1, -1, 4)
    light = torch.tensor([0.4, 0.8, 0.6], dtype=torch.float64)
    light = light / light.norm()
    normals = tr.vertex_normals(verts, faces)
    shade = (0.25 + 0.75 * (normals.reshape(-1, 3) @ light).clamp_min(0))[:, None]
    colors = torch.cat([shade * torch.tensor([0.95, 0.75, 0.45], dtype=torch.float64),
                        torch.ones_like(shade)], 1)
    background = torch.tensor([0.16, 0.2, 0.28], dtype=torch.float64)[:, None, None]

    def shifted(dx: torch.Tensor) -> torch.Tensor:  # dx pixels to the right
        return torch.cat([clip0[..., :1] + dx * (2.0 / res) * clip0[..., 3:], clip0[..., 1:]],
                         -1)

    def render(dx: torch.Tensor, antialiased: bool) -> torch.Tensor:
        clip = shifted(dx)
        frags = tr.rasterize(clip, faces, (res, res))
        rgba = tr.interpolate(colors, frags, faces)
        if antialiased:
            rgba = tr.antialias(rgba, frags, clip, faces)
        return rgba[0]

    def reference(dx: float) -> torch.Tensor:
        clip = shifted(torch.tensor(dx, dtype=torch.float64))
        frags = tr.rasterize(clip, faces, (res * ss, res * ss))
        rgba = tr.interpolate(colors, frags, faces)[0]
        return rgba.reshape(4, res, ss, res, ss).mean((2, 4))

    def composite(rgba: torch.Tensor) -> torch.Tensor:
        return rgba[:3] + (1 - rgba[3:]) * background

    zero = torch.zeros((), dtype=torch.float64)
    plain, smooth, ref = render(zero, False), render(zero, True), reference(0.0)
    dx = torch.zeros((), dtype=torch.float64, requires_grad=True)
    alpha = render(dx, True)[3]
    u = torch.ones_like(alpha, requires_grad=True)
    (g,) = torch.autograd.grad((alpha * u).sum(), dx, create_graph=True)
    (d_alpha,) = torch.autograd.grad(g, u)
    step = 0.25
    d_ref = (reference(step)[3] - reference(-step)[3]) / (2 * step)
    err_plain = float((plain[3] - ref[3]).abs().mean())
    err_aa = float((smooth[3] - ref[3]).abs().mean())
    panels = [
        (composite(plain), f"rasterize (alpha err {err_plain:.4f})"),
        (composite(smooth), f"+ antialias (alpha err {err_aa:.4f})"),
        (composite(ref), f"{ss}x{ss} supersampled"),
        (_signed(d_alpha.detach(), 1.0), "d alpha / d shift: antialias"),
        (_signed(d_ref, 1.0), "reference (central diff.)"),
    ]
    tiles = []
    for img, text in panels:
        im = Image.fromarray(_rgb(img[:, crop[0], crop[1]], zoom))
        draw = ImageDraw.Draw(im)
        draw.rectangle((0, 0, 6 * len(text) + 8, 14), fill=(0, 0, 0))
        draw.text((4, 1), text, fill=(255, 255, 255))
        tiles.append(np.asarray(im))
    gap = np.full((tiles[0].shape[0], 4, 3), 255, dtype=np.uint8)
    row = np.concatenate([x for t in tiles for x in (t, gap)][:-1], 1)
    Image.fromarray(row).save(path, optimize=True)
    x = torch.arange(res, dtype=torch.float64)
    print(f"wrote {path.relative_to(ROOT)}: mean |alpha - reference| {err_plain:.4f} "
          f"without, {err_aa:.4f} with antialias; d/dshift sum(alpha x) "
          f"{float((d_alpha * x).sum()):.1f} (antialias), {float((d_ref * x).sum()):.1f} "
          f"(reference), area {float(ref[3].sum()):.1f} px")


def quality(name: str, res: int, ss: int = 8) -> list:
    """Accuracy at ``res``^2 against an ss x ss supersampled reference (rasterize at
    ss * res, box filter): mean |alpha - reference| without and with antialias, and the
    error of d/dx sum(alpha x) for a screen-space shift (should be the area)."""
    clip, faces, colors = scene(name, 1)
    clip = clip.double()
    alpha_attr = colors[:, 3:].double()
    with torch.no_grad():
        frags = tr.rasterize(clip, faces, (res * ss, res * ss))
        ref = tr.interpolate(alpha_attr, frags, faces)[0, 0].reshape(res, ss, res, ss).mean((1, 3))
    shift = torch.zeros((), dtype=torch.float64, requires_grad=True)
    moved = torch.cat([clip[..., :1] + shift * (2.0 / res) * clip[..., 3:], clip[..., 1:]], -1)
    frags = tr.rasterize(moved, faces, (res, res))
    plain = frags.mask[0, 0].double()
    alpha = tr.antialias(frags.mask.double(), frags, moved, faces)[0, 0]
    x = torch.arange(res, dtype=torch.float64)
    (moment,) = torch.autograd.grad((alpha * x).sum(), shift)
    area = float(ref.sum())
    return [name, f"{res}²", float((plain - ref).abs().mean()),
            float((alpha.detach() - ref).abs().mean()), area,
            100 * (float(moment) / area - 1)]


def renderer_rows(repeats: int) -> list:
    """Full Renderer frame (Spot, PBR, one point light, batch 4) with antialias off / on:
    forward and forward + backward to vertex positions, interleaved medians."""
    import statistics

    mesh = tr.load_spot()
    view = tr.camera.orbit(torch.tensor([0.0, 60, 120, 200]), 15.0, 2.6)
    proj = tr.camera.perspective(45.0, 1.0, 0.1)
    lights = tr.Lights(point=tr.PointLights(position=torch.tensor([[[2.0, 2.0, 3.0]]]),
                                            color=torch.ones(1, 1, 3),
                                            intensity=torch.tensor([[20.0]])))
    rows = []
    for res in (256, 512):
        # one renderer each, kept across calls as in a training loop (its caches warm)
        renderers = {aa: tr.Renderer(res, raster=tr.RasterSettings(antialias=aa))
                     for aa in (False, True)}
        for grad in (False, True):
            times: dict[bool, list[float]] = {False: [], True: []}
            for rep in range(repeats + 1):
                for aa in (False, True):
                    renderer = renderers[aa]
                    pos = mesh.positions.clone().requires_grad_(grad)
                    scene = tr.RenderScene(pos, mesh.faces, mesh.normals, mesh.uvs,
                                           materials=[mesh.material])
                    t = time.perf_counter()
                    with torch.set_grad_enabled(grad):
                        out = renderer(scene, view, proj, lights)
                        if grad:
                            (out.image.mean() + out.alpha.mean()).backward()
                    if rep:  # the first round warms up
                        times[aa].append(time.perf_counter() - t)
            off, on = statistics.median(times[False]), statistics.median(times[True])
            rows.append([f"{res}²", "forward + backward" if grad else "forward", off * 1e3,
                         on * 1e3, on / off])
            print(rows[-1], flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    ap.add_argument("--no-write", action="store_true", help="print only")
    ap.add_argument("--picture", action="store_true",
                    help="only write docs/images/antialias.png")
    ap.add_argument("--renderer", action="store_true",
                    help="only the full-frame cost of Renderer(antialias=True)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.picture:
        picture(ROOT / "docs" / "images" / "antialias.png")
        return
    from benchmd import markdown_table, update_section

    if args.renderer:
        rows = renderer_rows(args.repeats)
        body = ("## Antialiasing in the renderer: `Renderer(antialias=True)`\n\n"
                "The whole frame (Spot, 5,856 faces, PBR, one point light, batch 4: "
                "rasterize, G-buffer, lighting, one antialias call on colour + alpha) with "
                "antialias off and on; forward, and forward + backward of image and alpha "
                f"means to the vertex positions. One renderer per setting, kept across "
                f"calls; medians of {args.repeats} interleaved repeats after a warm-up "
                "round, one process (compare the ratios). Antialias stays off by default: "
                f"it adds {(min(r[4] for r in rows) - 1) * 100:.0f}-"
                f"{(max(r[4] for r in rows) - 1) * 100:.0f} % to a frame; turn it on to "
                "optimise geometry or cameras against silhouettes or edges, or as the "
                "cheapest edge antialiasing of images (docs/benchmarks.md, edge-aa).\n\n"
                + markdown_table(["resolution", "pass", "off ms", "on ms", "on / off"], rows))
        if not args.no_write:
            update_section("antialias-renderer", body)
        return
    rows = []
    header = ["mesh", "resolution", "batch", "pairs", "changed px", "rasterize ms",
              "antialias ms", "antialias / rasterize", "train step ms", "+ antialias ms",
              "step ratio", "topology ms"]
    print(" | ".join(header))
    for name in ("icosphere", "spot"):
        for res in (256, 512):
            for batch in (1, 4):
                r = measure(name, res, batch, args.repeats)
                row = [name, f"{res}²", batch, r["pairs"], r["changed"], r["raster"], r["aa"],
                       r["aa"] / r["raster"], r["train"], r["train_aa"],
                       r["train_aa"] / r["train"], r["topology"]]
                rows.append(row)
                print(" | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in row),
                      flush=True)
    quality_header = ["mesh", "resolution", "mean abs alpha error, rasterize",
                      "+ antialias", "area px", "d/dx sum(alpha x) - area (%)"]
    quality_rows = [quality(name, res) for name in ("icosphere", "spot")
                    for res in (64, 128)]
    for row in quality_rows:
        print(" | ".join(f"{v:.4g}" if isinstance(v, float) else str(v) for v in row))
    body = (
        "## Antialiasing: `antialias` against `rasterize`\n\n"
        "Analytic antialiasing (`tr.antialias`, gradients at silhouettes and occlusion "
        "edges) of an RGB + alpha image from `interpolate`; icosphere (5,120 faces) and "
        "Spot (5,856 faces), cameras orbiting at distance 3.0 / 2.4 (fov 45°). *pairs*: "
        "4-neighbour pixel pairs whose face ids differ (the work of the walk), *changed "
        "px*: pixels the blend changed. *rasterize ms* / *antialias ms*: forward, no grad "
        "(antialias including its edge-adjacency sort, *topology ms*, which "
        "`antialias(..., topology=antialias_topology(faces))` saves across calls). "
        "*train step*: rasterize -> interpolate -> sum, forward + backward to clip "
        "positions and colours; *+ antialias*: the same with antialias before the sum. "
        f"Medians of {args.repeats} interleaved repeats after a warm-up, one process "
        "(on a machine shared with other jobs: compare the ratios).\n\n"
        + markdown_table(header, rows)
        + "\n\nAccuracy against an 8x8 supersampled alpha (rasterize at 8x the resolution, "
        "box filter), batch 1: the mean absolute alpha error, and the gradient check of "
        "tests/test_antialias.py: d/dx of sum(alpha * x) for a screen-space shift by x "
        "pixels is the shape's area (the reference's alpha sum). Spot's horn tips and "
        "legs put two silhouettes between pixel centres, which antialias cannot see.\n\n"
        + markdown_table(quality_header, quality_rows)
    )
    if not args.no_write:
        update_section("antialias", body)
        print("wrote docs/benchmarks.md section 'antialias'")


if __name__ == "__main__":
    main()
