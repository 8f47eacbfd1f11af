"""Background images: exact fit geometry (cover / contain / stretch) against a float64
reference written out here and on checkers whose cell boundaries must land on known pixels;
compositing only where the scene lets light through; YAML end to end; errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from skimage import io as skio

import torchraster as tr
from torchraster import camera
from torchraster.background import fit_background, load_background
from torchraster.hdr_io import write_hdr

VIEW = camera.look_at([0.0, 0.0, 4.0], [0.0, 0.0, 0.0])
PROJ = camera.perspective(40.0, 1.0, 0.1)


def _cells(h: int, w: int, cell: int) -> torch.Tensor:
    """(3, h, w): channel 0 = column cell index, 1 = row cell index, 2 = checker parity."""
    col = (torch.arange(w) // cell).double().expand(h, w)
    row = (torch.arange(h) // cell).double()[:, None].expand(h, w)
    return torch.stack([col, row, (col + row) % 2])


def _reference(img: np.ndarray, frame: tuple[int, int], fit: str, fill: np.ndarray):
    """Pixel by pixel: centre -> source point, clamped bilinear, box coverage of bars."""
    _, h, w = img.shape
    hh, ww = frame
    if fit == "stretch":
        sy, sx = hh / h, ww / w
    else:
        pick = max if fit == "cover" else min
        sy = sx = pick(hh / h, ww / w)
    out = np.zeros((3, hh, ww))
    for i in range(hh):
        for j in range(ww):
            y = (i + 0.5 - hh / 2) / sy + h / 2 - 0.5  # in pixel-centre coordinates
            x = (j + 0.5 - ww / 2) / sx + w / 2 - 0.5
            y0, x0 = math.floor(y), math.floor(x)
            fy, fx = y - y0, x - x0
            val = np.zeros(3)
            for dy, wy in ((0, 1 - fy), (1, fy)):
                for dx, wx in ((0, 1 - fx), (1, fx)):
                    yy, xx = min(max(y0 + dy, 0), h - 1), min(max(x0 + dx, 0), w - 1)
                    val += wy * wx * img[:, yy, xx]
            if fit == "contain":
                top, left = hh / 2 - h * sy / 2, ww / 2 - w * sx / 2
                cy = min(max(min(i + 1, top + h * sy) - max(i, top), 0), 1)
                cx = min(max(min(j + 1, left + w * sx) - max(j, left), 0), 1)
                val = val * cy * cx + fill * (1 - cy * cx)
            out[:, i, j] = val
    return out


def test_cover_crops_and_cell_boundaries_land_on_known_pixels():
    # 40 x 80 image, 10 px cells, into 32 x 32: scale 0.8, 64 columns of which the middle
    # 32 show: frame column j shows cell 2 + j // 8, frame row i cell i // 8, exactly.
    out = fit_background(_cells(40, 80, 10), (32, 32), "cover")[0]
    j, i = torch.arange(32).double(), torch.arange(32).double()
    assert torch.equal(out[0], (2 + j // 8).expand(32, 32))
    assert torch.equal(out[1], (i // 8)[:, None].expand(32, 32))


def test_contain_letterboxes_with_the_fill_colour():
    # 8 x 16 image, 4 px cells, into 32 x 32: scale 2, rows 8..23 hold the image
    fill = (0.25, 0.5, 0.75)
    out = fit_background(_cells(8, 16, 4), (32, 32), "contain", fill)[0]
    bars = torch.cat([out[:, :8], out[:, 24:]], 1)
    assert torch.equal(bars, torch.tensor(fill).double().view(3, 1, 1).expand_as(bars))
    inside = out[:, 8:24]
    # bilinear across a cell boundary at frame column 8: weights 1/4, 3/4 either side
    assert torch.equal(inside[0, :, 6], torch.zeros(16, dtype=torch.float64))
    assert torch.equal(inside[0, :, 7], torch.full((16,), 0.25, dtype=torch.float64))
    assert torch.equal(inside[0, :, 8], torch.full((16,), 0.75, dtype=torch.float64))
    assert torch.equal(inside[0, :, 9], torch.ones(16, dtype=torch.float64))


@pytest.mark.parametrize("fit", ["cover", "contain", "stretch"])
@pytest.mark.parametrize("source, frame", [((7, 13), (20, 9)), ((14, 11), (12, 17)),
                                           ((5, 5), (6, 10))])  # no axis shrinks 2x
def test_fit_matches_the_reference(fit, source, frame):
    g = torch.Generator().manual_seed(1)
    img = torch.rand(3, *source, generator=g, dtype=torch.float64)
    fill = np.array([0.1, 0.7, 0.3])
    got = fit_background(img, frame, fit, tuple(fill))[0].numpy()
    want = _reference(img.numpy(), frame, fit, fill)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_shrinking_averages_instead_of_aliasing():
    fine = (torch.arange(64)[:, None] + torch.arange(64)).remainder(2).double()
    out = fit_background(fine.expand(3, 64, 64), (8, 8), "cover")
    torch.testing.assert_close(out, torch.full_like(out, 0.5), rtol=0, atol=1e-12)


def test_gradients_reach_the_image():
    img = torch.rand(1, 3, 6, 9, dtype=torch.float64, requires_grad=True)
    for fit in ("cover", "contain", "stretch"):
        assert torch.autograd.gradcheck(lambda x, f=fit: fit_background(x, (5, 4), f), (img,))


def _quad(alpha: float = 1.0, mode: str = "OPAQUE") -> tr.RenderScene:
    pos = torch.tensor([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=torch.float32)
    mat = tr.Material(base_color_factor=torch.tensor([1.0, 0.2, 0.1, alpha]), alpha_mode=mode,
                      double_sided=True)
    return tr.RenderScene(pos, torch.tensor([[0, 1, 2], [0, 2, 3]]), materials=[mat])


def test_composited_only_where_alpha_is_below_one():
    bg = torch.rand(3, 10, 30)
    renderer = tr.Renderer(24,
                           shading="unlit",
                           background=tr.BackgroundSettings(color=(0.0, 0.0, 1.0), image=bg,
                                                            fit="contain"))
    out = renderer(_quad(), VIEW, PROJ)
    assert out.plan.background == "image contain" and "background image contain" in out.plan
    fitted = fit_background(bg, 24, "contain", (0.0, 0.0, 1.0))
    covered = out.alpha == 1
    assert 0 < int(covered.sum()) < 24 * 24
    albedo = torch.tensor([1.0, 0.2, 0.1]).view(1, 3, 1, 1)
    torch.testing.assert_close(out.image, torch.where(covered, albedo, fitted))
    # a half-transparent quad: half the surface over half the background
    out = renderer(_quad(0.5, "BLEND"), VIEW, PROJ)
    want = torch.where(covered, 0.5 * albedo + 0.5 * fitted, fitted)
    torch.testing.assert_close(out.image, want)
    # no image: the plan says colour / none, and the colour shows
    plain = tr.Renderer(24, shading="unlit")(_quad(), VIEW, PROJ)
    assert plain.plan.background == "none"


def test_image_beats_environment_and_supersampling_fits_the_big_frame():
    bg = torch.rand(3, 9, 9)
    env = tr.Environment(torch.full((3, 8, 16), 3.0))
    out = tr.Renderer(12,
                      shading="unlit",
                      raster=tr.RasterSettings(supersample=2),
                      background=tr.BackgroundSettings(image=bg))(
        _quad(), VIEW, PROJ, environment=env)
    assert out.plan.background == "image cover"
    want = torch.nn.functional.avg_pool2d(fit_background(bg, 24, "cover"), 2)
    empty = out.alpha == 0
    torch.testing.assert_close(out.image[empty.expand_as(out.image)],
                               want[empty.expand_as(want)])


def test_errors_name_the_argument():
    with pytest.raises(ValueError, match=r"^BackgroundSettings.fit: expected one of"):
        tr.Renderer(8, background=tr.BackgroundSettings(image=torch.rand(3, 4, 4), fit="fill"))
    with pytest.raises(ValueError, match="BackgroundSettings.image"):
        tr.Renderer(8, background=tr.BackgroundSettings(image=torch.rand(4, 4, 4)))
    with pytest.raises(ValueError, match="BackgroundSettings.image"):
        tr.Renderer(8, background=tr.BackgroundSettings(image=torch.full((3, 4, 4), float("nan"))))
    with pytest.raises(ValueError, match="fit: expected one of"):
        fit_background(torch.rand(3, 4, 4), 8, "zoom")
    with pytest.raises(FileNotFoundError, match="nope.png"):
        load_background("nope.png")


def test_files_are_decoded_to_linear(tmp_path):
    skio.imsave(tmp_path / "grey.png", np.full((4, 6, 3), 128, np.uint8), check_contrast=False)
    img = load_background(tmp_path / "grey.png")
    srgb = 128 / 255
    linear = ((srgb + 0.055) / 1.055) ** 2.4  # IEC 61966-2-1
    assert img.shape == (3, 4, 6)
    torch.testing.assert_close(img, torch.full_like(img, linear), rtol=1e-5, atol=1e-6)
    hdr = torch.tensor([4.0, 0.5, 0.25]).view(3, 1, 1).expand(3, 2, 3).contiguous()
    write_hdr(tmp_path / "sky.hdr", hdr)
    # RGBE: 8-bit mantissas under the largest channel's exponent
    torch.testing.assert_close(load_background(tmp_path / "sky.hdr"), hdr, rtol=0, atol=4 / 128)


CONFIG = """
scene:
  objects:
    - primitive: box
      size: 0.3
      material: {base_color: [1.0, 1.0, 1.0]}
cameras:
  - look_at: {eye: [0, 0, 4], target: [0, 0, 0]}
render:
  resolution: [16, 16]
  shading: unlit
  background: [0.0, 1.0, 0.0]
  background_image: {path: bg.png, fit: contain}
outputs: {channels: [radiance, alpha]}
"""


def test_yaml_background_image_end_to_end(tmp_path):
    skio.imsave(tmp_path / "bg.png", np.full((8, 16, 3), 128, np.uint8), check_contrast=False)
    cfg = tr.parse_config(CONFIG, "bg.yaml", base_dir=tmp_path)
    (view,) = tr.render_config(cfg)
    rad, alpha = view.images["radiance"], view.images["alpha"]
    grey = ((128 / 255 + 0.055) / 1.055) ** 2.4
    want = fit_background(torch.full((3, 8, 16), grey), 16, "contain", (0.0, 1.0, 0.0))[0]
    empty = (alpha == 0).expand_as(rad)
    torch.testing.assert_close(rad[empty], want[empty], rtol=1e-5, atol=1e-6)
    assert bool((rad[1, 0] == 1.0).all())  # the top bar has the background colour
    assert view.plan.background == "image contain"
    missing = tr.parse_config(CONFIG.replace("bg.png", "gone.png"), "bg.yaml",
                              base_dir=tmp_path)
    with pytest.raises(tr.ConfigError, match=r"render.background_image.path.*gone.png"):
        tr.config.check_config(missing)
    with pytest.raises(tr.ConfigError, match=r"render.background_image.path.*gone.png"):
        tr.render_config(missing)
    with pytest.raises(tr.ConfigError, match="fit"):
        tr.parse_config(CONFIG.replace("fit: contain", "fit: zoom"), "bg.yaml")
