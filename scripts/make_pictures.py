"""Reference pictures for docs/images from the optional asset folder ($TORCHRASTER_DATA,
``torchraster.testing.assets``; skips when absent).

    python scripts/make_pictures.py [--size 320]

Writes: pbr_<asset>_env.png (image-based lighting, environment as background),
pbr_<asset>_lights.png (point + spot + a dim ambient), gbuffer_<asset>.png (albedo,
normal, roughness, metallic, AO, depth) for DamagedHelmet and MaterialsVariantsShoe, and
pbr_overview.png (the four lit images side by side), and pbr_sphere_grid.png (metallic x
roughness spheres under the environment, one rasterize call with 25 materials).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import kornia
import numpy as np
import torch
import trimesh
from skimage import io as skio

import torchraster as tr
from torchraster.config import CameraConfig, OrbitConfig, lights_from_config
from torchraster.hdr_io import read_hdr
from torchraster.pipeline import build_camera
from torchraster.post.tonemap import tone_curve
from torchraster.shading.ibl import Environment
from torchraster.testing.assets import data_dir

ROOT = Path(__file__).resolve().parents[1]
DATA = data_dir()
OUT = ROOT / "docs" / "images"
ASSETS = {
    "helmet": ("gltf/DamagedHelmet/DamagedHelmet.gltf", 25.0),
    "shoe": ("gltf/MaterialsVariantsShoe/MaterialsVariantsShoe.gltf", 35.0),
}


def _display(img: torch.Tensor) -> np.ndarray:
    """Linear HDR (3, H, W) -> ACES tone mapped sRGB uint8 (H, W, 3)."""
    srgb = kornia.color.linear_rgb_to_rgb(tone_curve(img[None], "aces").clamp(0, 1))[0]
    return (srgb.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)


def _channel(img: torch.Tensor, name: str, mask: torch.Tensor) -> np.ndarray:
    if name == "normal":
        img = (img * 0.5 + 0.5) * mask
    elif name == "depth":
        valid = mask[0] > 0
        lo, hi = float(img[0][valid].min()), float(img[0][valid].max())
        img = ((hi - img) / (hi - lo)).clamp(0, 1) * mask
    elif name == "albedo":
        img = kornia.color.linear_rgb_to_rgb(img[None].clamp(0, 1))[0]
    img = img.clamp(0, 1).expand(3, -1, -1)
    return (img.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)


def sphere_grid(env: Environment, size: int) -> None:
    """5 x 5 spheres, metallic 0 -> 1 (rows) x roughness 0 -> 1 (columns): one mesh, one
    material per sphere (face_material), one rasterize call, IBL from the environment."""
    ico = trimesh.creation.icosphere(subdivisions=4)
    verts = torch.tensor(ico.vertices, dtype=torch.float32) * 0.42
    faces = torch.tensor(ico.faces, dtype=torch.int64)
    positions, all_faces, face_material, materials = [], [], [], []
    for i, metallic in enumerate(torch.linspace(0, 1, 5).tolist()):
        for j, roughness in enumerate(torch.linspace(0, 1, 5).tolist()):
            k = len(materials)
            positions.append(verts + torch.tensor([j - 2.0, 2.0 - i, 0.0]))
            all_faces.append(faces + k * verts.shape[0])
            face_material.append(torch.full((faces.shape[0],), k))
            materials.append(tr.Material(base_color_factor=torch.tensor([0.9, 0.6, 0.3, 1.0]),
                                         metallic_factor=metallic, roughness_factor=roughness))
    pos = torch.cat(positions)
    scene = tr.RenderScene(pos, torch.cat(all_faces), tr.vertex_normals(pos, torch.cat(
        all_faces)), face_material=torch.cat(face_material), materials=materials)
    view = tr.camera.look_at([0.0, 0.0, 9.0], [0.0, 0.0, 0.0])
    proj = tr.camera.perspective(32.0, 1.0, 0.1)
    with torch.no_grad():
        out = tr.Renderer((size, size),
                          shading="pbr",
                          background=(0.02, 0.02, 0.03),
                          raster=tr.RasterSettings(supersample=2))(scene, view, proj, None, env)
    image = out.image[0] * out.alpha[0] + (1 - out.alpha[0]) * 0.02
    skio.imsave(OUT / "pbr_sphere_grid.png", _display(image), check_contrast=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    args = ap.parse_args()
    if not DATA.is_dir():
        print(f"{DATA} not found: nothing to do")
        return
    res = (args.size, args.size)
    env = Environment(read_hdr(DATA / "envmaps" / "venice_sunset_1k.hdr"), yaw=math.radians(90))
    lights = lights_from_config([
        {"type": "point", "position": [1.5, 1.5, 2.0], "intensity": 12.0, "color": [1, 0.85, 0.7]},
        {"type": "spot", "position": [-2.0, 2.5, 1.0], "direction": [1.0, -1.2, -0.4],
         "intensity": 40.0, "outer_cone_angle": 0.5, "inner_cone_angle": 0.3,
         "color": [0.6, 0.8, 1.0]},
        {"type": "ambient", "intensity": 0.03},
    ])
    sphere_grid(env, 2 * args.size)
    for name, (path, azimuth) in ASSETS.items():
        t = time.time()
        scene = tr.load_scene(DATA / path, max_texture_size=1024)
        mesh, face_material, materials = scene.flatten()
        rscene = tr.RenderScene.from_mesh(mesh, face_material, materials)
        cam = CameraConfig(orbit=OrbitConfig(azimuth_deg=azimuth, elevation_deg=12))
        view, proj = build_camera(cam, mesh.positions, res)
        renderer = tr.Renderer(res, shading="pbr", raster=tr.RasterSettings(supersample=2))
        with torch.no_grad():
            lit = renderer(rscene, view, proj, None, env,
                           {"albedo", "normal", "roughness", "metallic", "ao", "depth", "mask"})
            skio.imsave(OUT / f"pbr_{name}_env.png", _display(lit.image[0]), check_contrast=False)
            # move the lights with the camera framing: scale by the scene's size
            spot = tr.Renderer(res,
                               shading="pbr",
                               background=(0.02, 0.02, 0.03),
                               raster=tr.RasterSettings(supersample=2))
            lit2 = spot(rscene, view, proj, lights)
            skio.imsave(OUT / f"pbr_{name}_lights.png", _display(lit2.image[0]),
                        check_contrast=False)
        mask = lit.gbuffer["mask"][0]
        tiles = [_channel(lit.gbuffer[c][0], c, mask)
                 for c in ("albedo", "normal", "roughness", "metallic", "ao", "depth")]
        strip = np.concatenate(tiles, axis=1)[::2, ::2]
        skio.imsave(OUT / f"gbuffer_{name}.png", strip, check_contrast=False)
        print(f"{name}: {time.time() - t:.1f} s; plan: {'; '.join(lit.plan)}")
    strip = [skio.imread(OUT / f"pbr_{name}_{kind}.png") for name in ASSETS
             for kind in ("env", "lights")]
    skio.imsave(OUT / "pbr_overview.png", np.concatenate(strip, axis=1), check_contrast=False)


if __name__ == "__main__":
    main()
