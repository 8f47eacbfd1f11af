"""Material model: defaults, texture decoding and conversion from trimesh materials."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image
from trimesh.visual.material import PBRMaterial, SimpleMaterial, empty_material

from torchraster.material import (
    Material,
    material_from_trimesh,
    roughness_from_phong_exponent,
)


def srgb_to_linear_reference(c: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decode, written out independently of kornia."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def test_defaults_follow_gltf() -> None:
    m = Material()
    assert m.base_color_factor.tolist() == [1, 1, 1, 1]
    assert m.metallic_factor == 1.0 and m.roughness_factor == 1.0
    assert m.emissive_factor.tolist() == [0, 0, 0]
    assert m.normal_scale == 1.0 and m.occlusion_strength == 1.0
    assert m.alpha_mode == "OPAQUE" and m.alpha_cutoff == 0.5 and m.double_sided is False
    assert all(m.texture(s) is None for s in ("base_color", "normal", "emissive"))


def test_validation_errors() -> None:
    with pytest.raises(ValueError, match="base_color_factor"):
        Material(base_color_factor=[1, 1, 2, 1])
    with pytest.raises(ValueError, match="base_color_factor"):
        Material(base_color_factor=[1, 1, 1])
    with pytest.raises(ValueError, match="emissive_factor"):
        Material(emissive_factor=[-1, 0, 0])
    with pytest.raises(ValueError, match="metallic_factor"):
        Material(metallic_factor=1.5)
    with pytest.raises(ValueError, match="roughness_factor"):
        Material(roughness_factor=float("nan"))
    with pytest.raises(TypeError, match="roughness_factor"):
        Material(roughness_factor="rough")
    with pytest.raises(ValueError, match="alpha_mode"):
        Material(alpha_mode="CLIP")
    with pytest.raises(ValueError, match="normal_texture"):
        Material(normal_texture=torch.zeros(2, 4, 4, dtype=torch.uint8))
    with pytest.raises(ValueError, match="base_color_texture"):
        Material(base_color_texture=torch.zeros(8, 8, 3, dtype=torch.uint8))  # HWC
    with pytest.raises(TypeError, match="emissive_texture"):
        Material(emissive_texture=torch.zeros(3, 4, 4, dtype=torch.int64))
    with pytest.raises(ValueError, match="slot"):
        Material().texture("albedo")
    assert Material(alpha_mode="mask").alpha_mode == "MASK"
    assert Material(emissive_factor=[5.0, 0, 0]).emissive_factor[0] == 5.0  # emissive strength


def test_texture_decoding() -> None:
    codes = torch.arange(256, dtype=torch.uint8)
    tex = torch.stack([codes, codes.flip(0), codes, codes.flip(0)]).view(4, 16, 16)
    m = Material(base_color_texture=tex, emissive_texture=tex[:3],
                 metallic_roughness_texture=tex[:3], occlusion_texture=tex[:1])
    ref = srgb_to_linear_reference(tex.numpy() / 255.0)
    bc = m.texture("base_color", dtype=torch.float64)
    assert bc.shape == (4, 16, 16) and bc.dtype == torch.float64
    np.testing.assert_allclose(bc[:3].numpy(), ref[:3], atol=1e-12)
    np.testing.assert_allclose(bc[3].numpy(), tex[3].numpy() / 255.0)  # alpha stays linear
    np.testing.assert_allclose(m.texture("emissive_texture").numpy(), ref[:3], atol=1e-6)
    np.testing.assert_allclose(m.texture("metallic_roughness").numpy(),
                               tex[:3].numpy() / 255.0, atol=1e-7)
    assert m.texture("occlusion").shape == (1, 16, 16)
    # float textures are linear already and keep their gradient
    f = torch.rand(3, 2, 2, requires_grad=True)
    out = Material(base_color_texture=f).texture("base_color")
    assert out is f or torch.equal(out, f)
    out.sum().backward()
    assert torch.equal(f.grad, torch.ones_like(f))


def test_to_keeps_uint8_and_shared_storage() -> None:
    packed = torch.randint(0, 256, (3, 8, 8), dtype=torch.uint8)
    m = Material(metallic_roughness_texture=packed, occlusion_texture=packed[0:1])
    assert m.texture_nbytes == packed.numel()
    m2 = m.to("cpu")
    assert m2.metallic_roughness_texture.dtype == torch.uint8
    assert torch.equal(m2.occlusion_texture, packed[0:1])
    assert m2.texture_nbytes == packed.numel()


def _img(arr: np.ndarray) -> Image.Image:
    return Image.fromarray(np.asarray(arr, dtype=np.uint8))


def test_from_trimesh_pbr() -> None:
    rng = np.random.default_rng(0)
    mr = _img(rng.integers(0, 256, (8, 6, 3)))
    base = _img(rng.integers(0, 256, (8, 6, 4)))
    pbr = PBRMaterial(
        name="m", baseColorFactor=[0.5, 0.25, 1.0, 0.75], metallicFactor=0.2,
        emissiveFactor=[0.1, 0.2, 0.3], baseColorTexture=base, metallicRoughnessTexture=mr,
        occlusionTexture=mr, normalTexture=_img(rng.integers(0, 256, (4, 4, 3))),
        alphaMode="MASK", alphaCutoff=0.3, doubleSided=True,
    )
    assert pbr.baseColorFactor.dtype == np.uint8  # the trap the converter must handle
    m = material_from_trimesh(pbr)
    np.testing.assert_allclose(m.base_color_factor.numpy(), [0.5, 0.25, 1.0, 0.75], atol=1 / 255)
    assert m.metallic_factor == pytest.approx(0.2)
    assert m.roughness_factor == 1.0  # glTF default when missing
    np.testing.assert_allclose(m.emissive_factor.numpy(), [0.1, 0.2, 0.3], atol=1e-7)
    assert m.alpha_mode == "MASK" and m.alpha_cutoff == pytest.approx(0.3) and m.double_sided
    assert m.base_color_texture.shape == (4, 8, 6)
    assert torch.equal(m.base_color_texture.permute(1, 2, 0), torch.from_numpy(np.array(base)))
    # occlusion packed into the metallic-roughness image: R channel, sharing memory
    assert m.occlusion_texture.shape == (1, 8, 6)
    assert torch.equal(m.occlusion_texture[0], torch.from_numpy(np.array(mr)[:, :, 0]))
    assert (m.occlusion_texture.untyped_storage().data_ptr()
            == m.metallic_roughness_texture.untyped_storage().data_ptr())
    assert m.emissive_texture is None


def test_from_trimesh_palette_and_gray_images() -> None:
    pal = _img(np.arange(48).reshape(4, 4, 3) * 5).convert("P")
    m = material_from_trimesh(PBRMaterial(baseColorTexture=pal,
                                          occlusionTexture=_img(np.full((4, 4), 77))))
    assert m.base_color_texture.shape == (3, 4, 4)  # palette without transparency -> RGB
    assert m.occlusion_texture.shape == (1, 4, 4) and int(m.occlusion_texture.max()) == 77


def test_max_texture_size_downscales_by_area_average() -> None:
    arr = np.random.default_rng(1).integers(0, 256, (64, 32, 3))
    m = material_from_trimesh(PBRMaterial(baseColorTexture=_img(arr)), max_texture_size=16)
    assert m.base_color_texture.shape == (3, 16, 8)
    ref = arr.reshape(16, 4, 8, 4, 3).mean(axis=(1, 3))
    got = m.base_color_texture.permute(1, 2, 0).numpy().astype(np.float64)
    assert np.abs(got - ref).max() <= 1.0  # rounding to uint8
    with pytest.raises(ValueError, match="max_texture_size"):
        material_from_trimesh(PBRMaterial(), max_texture_size=0)


def test_from_trimesh_simple_material() -> None:
    img = _img(np.zeros((4, 4, 3)))
    sm = SimpleMaterial(image=img, diffuse=[0.8, 0.4, 0.2], glossiness=98.0, name="mtl",
                        kd=[0.8, 0.4, 0.2], d=["0.5"])
    m = material_from_trimesh(sm)
    np.testing.assert_allclose(m.base_color_factor.numpy(), [0.8, 0.4, 0.2, 0.5], atol=1e-7)
    assert m.metallic_factor == 0.0
    assert m.roughness_factor == pytest.approx((2 / 100) ** 0.25)
    assert m.alpha_mode == "BLEND"
    assert m.base_color_texture.shape == (3, 4, 4)
    # PBR extension of MTL wins over Ns
    m = material_from_trimesh(SimpleMaterial(name="p", glossiness=10.0, pr=["0.3"], pm=["1"]))
    assert m.roughness_factor == pytest.approx(0.3) and m.metallic_factor == 1.0
    # trimesh's placeholder for an OBJ without MTL means "no material"
    assert material_from_trimesh(empty_material()) is None
    assert material_from_trimesh(None) is None
    with pytest.raises(TypeError, match="visual_material"):
        material_from_trimesh("red")


def test_phong_exponent_mapping() -> None:
    """roughness**2 (GGX alpha) = sqrt(2 / (Ns + 2)) (Walter et al. 2007, eq. 8)."""
    for ns in (0.0, 1.0, 10.0, 96.0, 1000.0):
        r = roughness_from_phong_exponent(ns)
        assert r**2 == pytest.approx(np.sqrt(2 / (ns + 2)))
    assert roughness_from_phong_exponent(0.0) == 1.0
    assert roughness_from_phong_exponent(-5.0) == 1.0
