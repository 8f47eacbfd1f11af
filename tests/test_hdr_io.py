"""Radiance RGBE reader: independent encoder in the test, real env maps, bad files."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest
import torch

from torchraster.hdr_io import read_hdr, write_hdr


def _encode_pixel(r: float, g: float, b: float) -> tuple[int, int, int, int]:
    """Ward's RGBE encoding, written out per pixel with math.frexp (independent of the module)."""
    v = max(r, g, b)
    if v < 1e-32:
        return 0, 0, 0, 0
    m, e = math.frexp(v)
    s = m * 256.0 / v
    return int(r * s), int(g * s), int(b * s), e + 128


def _rgbe_bytes(img: np.ndarray, rle: bool) -> bytes:
    """Encode an (H, W, 3) float image to RGBE file bytes, flat or new-style RLE.

    The RLE writer here uses only literal runs of up to 128 and repeat runs of exactly
    the longest equal stretch (<= 127), emitted per plane: a different policy from
    ``write_hdr``, so both code paths of the reader are exercised.
    """
    h, w, _ = img.shape
    px = np.array([[_encode_pixel(*map(float, img[y, x])) for x in range(w)] for y in range(h)],
                  dtype=np.uint8)
    head = b"#?RADIANCE\n# test\nFORMAT=32-bit_rle_rgbe\nEXPOSURE=1.0\n\n"
    head += f"-Y {h} +X {w}\n".encode()
    if not rle:
        return head + px.tobytes()
    body = bytearray()
    for y in range(h):
        body += bytes([2, 2, w >> 8, w & 255])
        for c in range(4):
            plane = px[y, :, c].tolist()
            i = 0
            while i < w:
                j = i
                while j < w and j - i < 127 and plane[j] == plane[i]:
                    j += 1
                if j - i >= 2:
                    body += bytes([128 + (j - i), plane[i]])
                else:
                    body += bytes([1, plane[i]])
                i = j
    return head + bytes(body)


def _test_image(h: int, w: int) -> np.ndarray:
    rng = np.random.default_rng(1)
    img = np.exp(rng.normal(0, 3, size=(h, w, 3)))  # spans ~1e-6 .. 1e6
    img[:, : w // 3] = [0.25, 0.5, 1.0]  # long constant runs for RLE
    img[0, 0] = 0.0
    return img


@pytest.mark.parametrize("rle", [True, False])
def test_decode_matches_independent_encoding(tmp_path: Path, rle: bool) -> None:
    img = _test_image(5, 37)
    path = tmp_path / "x.hdr"
    path.write_bytes(_rgbe_bytes(img, rle))
    out = read_hdr(path)
    assert out.shape == (3, 5, 37) and out.dtype == torch.float32
    ref = torch.from_numpy(img).permute(2, 0, 1)
    peak = ref.amax(0, keepdim=True)
    # 8-bit shared-exponent mantissa: error <= 1/256 of the largest channel of the pixel
    err = (out.double() - ref).abs() / peak.clamp_min(1e-30)
    assert float(err.max()) <= 1.0 / 256 + 1e-6
    assert out[:, 0, 0].abs().max() == 0


def test_write_read_roundtrip(tmp_path: Path) -> None:
    ref = torch.from_numpy(_test_image(9, 70)).permute(2, 0, 1).float()
    write_hdr(tmp_path / "y.hdr", ref)
    out = read_hdr(tmp_path / "y.hdr")
    rel = (out - ref).abs() / ref.amax(0, keepdim=True).clamp_min(1e-30)
    assert float(rel.max()) <= 1.0 / 256 + 1e-6


def test_plus_y_flips_rows(tmp_path: Path) -> None:
    img = _test_image(4, 3)
    data = _rgbe_bytes(img, rle=False).replace(b"-Y 4 +X 3", b"+Y 4 +X 3")
    (tmp_path / "f.hdr").write_bytes(data)
    a = read_hdr(tmp_path / "f.hdr")
    ref = torch.from_numpy(img[::-1].copy()).permute(2, 0, 1).float()
    rel = (a - ref).abs() / ref.amax(0, keepdim=True).clamp_min(1e-30)
    assert float(rel.max()) <= 1.0 / 256 + 1e-6


@pytest.mark.parametrize(
    "mutate, msg",
    [
        (lambda d: b"P6\n" + d, "magic"),
        (lambda d: d[:-10], "truncated"),
        (lambda d: d.replace(b"-Y 6 +X 40", b"-Y 6 X 40"), "resolution"),
        (lambda d: d.replace(b"FORMAT=32-bit_rle_rgbe", b"FORMAT=32-bit_rle_xyze"), "FORMAT"),
    ],
)
def test_bad_files_name_the_file(tmp_path: Path, mutate, msg: str) -> None:
    data = mutate(_rgbe_bytes(_test_image(6, 40), rle=True))
    path = tmp_path / "bad_file.hdr"
    path.write_bytes(data)
    with pytest.raises(ValueError, match=msg) as info:
        read_hdr(path)
    assert "bad_file.hdr" in str(info.value)


def test_corrupt_rle_run_overflow(tmp_path: Path) -> None:
    head = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 1 +X 8\n"
    body = bytes([2, 2, 0, 8]) + bytes([128 + 100, 7])  # run of 100 > width 8
    (tmp_path / "c.hdr").write_bytes(head + body)
    with pytest.raises(ValueError, match="c.hdr"):
        read_hdr(tmp_path / "c.hdr")


def test_exr_without_openexr_says_how_to_install(tmp_path: Path) -> None:
    pytest.importorskip("numpy")
    try:
        import OpenEXR  # noqa: F401

        pytest.skip("OpenEXR is installed")
    except ImportError:
        pass
    (tmp_path / "a.exr").write_bytes(struct.pack("<I", 20000630))
    with pytest.raises(ImportError, match="pip install"):
        read_hdr(tmp_path / "a.exr")


@pytest.mark.parametrize(
    "name, peak, mean", [("venice_sunset_1k", 2.1e3, 0.43), ("pedestrian_overpass_1k", 6.9e4, 0.51)]
)
def test_real_env_maps(shared_data: Path, name: str, peak: float, mean: float) -> None:
    img = read_hdr(shared_data / "envmaps" / f"{name}.hdr")
    assert img.shape == (3, 512, 1024)
    assert bool(torch.isfinite(img).all()) and float(img.min()) >= 0
    lum = 0.2126 * img[0] + 0.7152 * img[1] + 0.0722 * img[2]  # Rec. 709 luminance
    assert abs(float(lum.max()) / peak - 1) < 0.05
    assert abs(float(lum.mean()) - mean) < 0.01
