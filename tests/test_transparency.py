"""glTF alpha modes: MASK cut-outs show the next layer, BLEND composites layers front to
back ("over"), checked against the compositing formula on stacked quads (unlit shading, so
each layer's colour is its base colour exactly)."""

import pytest
import torch

import torchraster as tr

VIEW = tr.camera.look_at([0.0, 0.0, 3.0], [0.0, 0.0, 0.0])
PROJ = tr.camera.perspective(40.0, 1.0, 0.1)


def _quads(*zs: float, size: float = 1.0):
    """Axis-aligned quads facing +z at depths ``zs`` (front first), one material each."""
    pos, faces = [], []
    for i, z in enumerate(zs):
        s = size * (1 + 0.1 * i)  # the farther the larger: every quad fills the centre
        pos += [[-s, -s, z], [s, -s, z], [s, s, z], [-s, s, z]]
        faces += [[4 * i, 4 * i + 1, 4 * i + 2], [4 * i, 4 * i + 2, 4 * i + 3]]
    fm = torch.arange(len(zs)).repeat_interleave(2)
    return torch.tensor(pos), torch.tensor(faces), fm


def _material(rgb, alpha=1.0, mode="OPAQUE", cutoff=0.5):
    return tr.Material(base_color_factor=torch.tensor([*rgb, alpha]), alpha_mode=mode,
                       alpha_cutoff=cutoff, double_sided=True)


def _render(materials, zs, layers=4, background=(0.0, 0.0, 0.0)):
    pos, faces, fm = _quads(*zs)
    scene = tr.RenderScene(pos, faces, face_material=fm, materials=materials)
    r = tr.Renderer(8,
                    shading="unlit",
                    background=background,
                    raster=tr.RasterSettings(alpha_layers=layers))
    return r(scene, VIEW, PROJ)


def test_mask_below_cutoff_shows_the_next_layer():
    red, green = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)
    cut = _render([_material(green, 0.2, "MASK", 0.3), _material(red)], (0.5, 0.0))
    kept = _render([_material(green, 0.4, "MASK", 0.3), _material(red)], (0.5, 0.0))
    centre = (slice(None), slice(None), 4, 4)
    torch.testing.assert_close(cut.image[centre][0], torch.tensor(red))
    torch.testing.assert_close(kept.image[centre][0], torch.tensor(green))
    assert float(cut.alpha[0, 0, 4, 4]) == 1.0
    assert "rasterize 8x8 4 layers" in cut.plan and "alpha mask (first opaque layer)" in cut.plan


def test_blend_is_front_to_back_over():
    white, red, blue = (1.0, 1.0, 1.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)
    bg = (0.0, 0.5, 0.0)
    out = _render([_material(white, 0.25, "BLEND"), _material(red, 0.5, "BLEND"),
                   _material(blue)], (0.6, 0.3, 0.0), background=bg)
    # T0 = 1: 0.25 white; T1 = 0.75: 0.375 red; T2 = 0.375: blue (opaque, alpha 1)
    expect = 0.25 * torch.tensor(white) + 0.375 * torch.tensor(red) + 0.375 * torch.tensor(blue)
    torch.testing.assert_close(out.image[0, :, 4, 4], expect)
    assert float(out.alpha[0, 0, 4, 4]) == pytest.approx(1.0)
    # without the opaque back quad the background shows through T = 0.75 * 0.5
    out = _render([_material(white, 0.25, "BLEND"), _material(red, 0.5, "BLEND")], (0.6, 0.3),
                  background=bg)
    expect = 0.25 * torch.tensor(white) + 0.375 * torch.tensor(red) + 0.375 * torch.tensor(bg)
    torch.testing.assert_close(out.image[0, :, 4, 4], expect)
    assert float(out.alpha[0, 0, 4, 4]) == pytest.approx(0.625)
    assert "blend 4 layers front to back" in out.plan


def test_blend_drops_what_lies_behind_the_layer_limit():
    glass = _material((1.0, 1.0, 1.0), 0.5, "BLEND")
    out = _render([glass, glass, _material((1.0, 0.0, 0.0))], (0.6, 0.3, 0.0), layers=2)
    # two glass layers seen; the red quad is the third layer: not composited
    torch.testing.assert_close(out.image[0, :, 4, 4], torch.full((3,), 0.75))
    assert float(out.alpha[0, 0, 4, 4]) == pytest.approx(0.75)


def test_blend_alpha_has_gradients():
    factor = torch.tensor([1.0, 1.0, 1.0, 0.3], requires_grad=True)
    front = tr.Material(base_color_factor=factor, alpha_mode="BLEND", double_sided=True)
    out = _render([front, _material((1.0, 0.0, 0.0))], (0.5, 0.0))
    out.image[0, 1, 4, 4].backward()  # green = alpha * 1 (white over red)
    assert factor.grad[3] == pytest.approx(1.0)


def test_opaque_scenes_rasterize_one_layer():
    out = _render([_material((1.0, 0.0, 0.0))], (0.0,))
    assert out.plan.layers == 1 and out.plan.alpha == "none"
    assert "layers" not in str(out.plan)


def test_alpha_layers_is_checked():
    with pytest.raises(ValueError, match="alpha_layers"):
        tr.Renderer(8, raster=tr.RasterSettings(alpha_layers=0))


def test_antialias_reads_the_surface_a_cutout_shows():
    red, green = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)
    pos, faces, fm = _quads(0.5, 0.0)
    scene = tr.RenderScene(pos, faces, face_material=fm,
                           materials=[_material(green, 0.2, "MASK", 0.3), _material(red)])
    r = tr.Renderer(16, shading="unlit", raster=tr.RasterSettings(antialias=True))
    out = r(scene, VIEW, PROJ)
    assert "antialias" in out.plan
    assert bool(torch.isfinite(out.image).all()) and float(out.alpha.max()) <= 1.0
    # the front quad is cut out everywhere: the image is the back quad's, antialiased
    plain = tr.Renderer(16, shading="unlit", raster=tr.RasterSettings(antialias=True))(
        tr.RenderScene(pos[4:], faces[2:] - 4, materials=[_material(red)]), VIEW, PROJ)
    torch.testing.assert_close(out.image, plain.image)
