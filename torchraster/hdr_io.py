"""Read and write high-dynamic-range images: Radiance ``.hdr`` (RGBE) and OpenEXR.

Radiance RGBE (Greg Ward, "Real Pixels", Graphics Gems II, 1991; the Radiance source
``color.c``): each pixel stores an 8-bit mantissa per channel and one shared 8-bit
exponent ``e``; the linear value is ``(m + 0.5) * 2**(e - 136)`` (``e == 0`` is black).
Scanlines are either flat (4 bytes a pixel) or "new-style" run-length encoded: a scanline
starts with the bytes ``2, 2, W >> 8, W & 255`` and then holds the four byte planes one
after another, each as runs (``count > 128``: repeat the next byte ``count - 128`` times)
and literals (``count <= 128``: copy the next ``count`` bytes).

The RLE stream is sequential by nature, so one Python loop walks the run headers (a few
tens of thousands a megapixel); the bytes themselves are gathered and decoded to float in
vectorised numpy ops. Old-style (pre-1991) RLE is not supported: a file without new-style
scanlines is read as flat pixels.

Values are returned as stored (``EXPOSURE=`` header lines are not divided out, as in most
loaders); the Radiance convention is that stored values are linear radiance in W/(sr m^2).
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np
import torch

from ._validate import check_frame_memory

log = logging.getLogger("torchraster")

__all__ = ["MAX_RADIANCE", "read_exr", "read_hdr", "sanitize_radiance", "write_hdr"]

#: Largest radiance a loaded HDR texel keeps (W/(sr m^2), ~ nits): about six times the
#: sun's disc (1.6e9). RGBE holds up to 1.7e38 and EXR float up to 3.4e38, values whose
#: products in the lighting passes (SH projection, prefiltering, intensity) overflow
#: float32 to Inf and NaN; larger texels are clamped to this with a logged warning.
MAX_RADIANCE: float = 1e10

_RES_RE = re.compile(rb"^([-+])Y\s+(\d+)\s+([-+])X\s+(\d+)\s*$")
_EXR_HINT = "reading .exr needs the optional OpenEXR package: pip install 'torchraster[exr]'"


def read_hdr(path: str | os.PathLike) -> torch.Tensor:
    """Read an HDR image as linear radiance.

    Args:
        path: a Radiance ``.hdr`` / ``.pic`` file (RGBE, flat or new-style RLE), or an
            ``.exr`` file (needs the optional ``OpenEXR`` package).

    Returns:
        ``(3, H, W)`` float32 tensor, row 0 = top of the image.

    Raises:
        ValueError: the file is not a valid RGBE file (bad header, truncated or corrupt
            pixel data); the message names the file.
    """
    path = Path(path)
    if path.suffix.lower() == ".exr":
        return read_exr(path)
    data = path.read_bytes()
    try:
        header_end, height, width, flip_y, flip_x = _parse_header(data)
        _check_size(data, header_end, height, width)
        check_frame_memory(f"read_hdr: {path}", height * width, _DECODE_BYTES_PER_PIXEL,
                           torch.device("cpu"))
        rgbe = _decode_pixels(data, header_end, height, width)
    except ValueError as err:
        raise ValueError(f"read_hdr: {path}: {err}") from None
    img = _rgbe_to_float(rgbe)  # (H, W, 3)
    if flip_y:
        img = img[::-1]
    if flip_x:
        img = img[:, ::-1]
    out = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))
    return sanitize_radiance(out, str(path))


#: Peak bytes per pixel while decoding RLE data (int64 gather indices for 4 bytes, the
#: RGBE bytes and the float32 result).
_DECODE_BYTES_PER_PIXEL = 4 * 8 * 3 + 4 + 12


def _check_size(data: bytes, start: int, height: int, width: int) -> None:
    """Refuse a resolution the file cannot hold: every scanline needs at least its 4-byte
    header plus, per byte plane, one 2-byte run per 127 pixels (so an "RLE bomb" that claims
    a huge image from a small file fails here, before anything is allocated)."""
    if 8 <= width < 32768:
        least = height * (4 + 4 * 2 * -(-width // 127))
    else:
        least = height * width * 4
    if len(data) - start < least:
        raise ValueError(f"{height}x{width} pixels cannot fit in {len(data) - start} bytes of "
                         f"pixel data (at least {least} needed): truncated or corrupt")


def _parse_header(data: bytes) -> tuple[int, int, int, bool, bool]:
    """Return (offset of pixel data, H, W, flip rows, flip columns)."""
    if not (data.startswith(b"#?RADIANCE") or data.startswith(b"#?RGBE")):
        raise ValueError("not a Radiance HDR file (missing '#?RADIANCE' / '#?RGBE' magic)")
    pos = 0
    fmt = None
    while True:
        end = data.find(b"\n", pos)
        if end < 0:
            raise ValueError("header has no blank line before the resolution string")
        line = data[pos:end].strip()
        pos = end + 1
        if line == b"":
            break
        if line.startswith(b"FORMAT="):
            fmt = line[len(b"FORMAT=") :]
    if fmt is not None and fmt != b"32-bit_rle_rgbe":
        got = fmt.decode(errors="replace")
        raise ValueError(f"unsupported FORMAT={got} (only 32-bit_rle_rgbe)")
    end = data.find(b"\n", pos)
    if end < 0:
        raise ValueError("missing resolution string after the header")
    m = _RES_RE.match(data[pos:end].strip())
    if m is None:
        raise ValueError(
            f"unsupported resolution string {data[pos:end][:40]!r} (expected e.g. '-Y 512 +X 1024')"
        )
    height, width = int(m.group(2)), int(m.group(4))
    if height <= 0 or width <= 0:
        raise ValueError(f"invalid image size {height}x{width}")
    return end + 1, height, width, m.group(1) == b"+", m.group(3) == b"-"


def _decode_pixels(data: bytes, start: int, height: int, width: int) -> np.ndarray:
    """Decode pixel bytes to a ``(H, W, 4)`` uint8 RGBE array."""
    buf = np.frombuffer(data, dtype=np.uint8)
    new_rle = (
        8 <= width < 32768
        and len(buf) >= start + 4
        and buf[start] == 2
        and buf[start + 1] == 2
        and (int(buf[start + 2]) << 8 | int(buf[start + 3])) == width
    )
    if not new_rle:
        n = height * width * 4
        if len(buf) - start < n:
            raise ValueError(f"truncated pixel data: {len(buf) - start} bytes for {n} expected")
        return buf[start : start + n].reshape(height, width, 4)

    # Walk run headers: record (source offset, length, is_literal) per run, in output order
    # (scanline-major, then channel plane, then x).
    src, lens, literal = [], [], []
    pos, size = start, len(buf)
    for y in range(height):
        if pos + 4 > size:
            raise ValueError(f"truncated pixel data at scanline {y} of {height}")
        if bytes(buf[pos : pos + 4]) != bytes([2, 2, width >> 8, width & 255]):
            raise ValueError(f"corrupt RLE scanline header at scanline {y} (byte {pos})")
        pos += 4
        for _ in range(4):
            filled = 0
            while filled < width:
                if pos >= size:
                    raise ValueError(f"truncated pixel data at scanline {y} of {height}")
                count = int(buf[pos])
                if count > 128:
                    count -= 128
                    src.append(pos + 1)
                    literal.append(False)
                    pos += 2
                else:
                    if count == 0:
                        raise ValueError(f"corrupt RLE data (zero-length run) at scanline {y}")
                    src.append(pos + 1)
                    literal.append(True)
                    pos += 1 + count
                if filled + count > width:
                    raise ValueError(f"corrupt RLE data (run overflows scanline {y})")
                lens.append(count)
                filled += count
    if pos > size:
        raise ValueError(f"truncated pixel data ({pos - size} bytes missing at the end)")
    lens_a = np.asarray(lens, dtype=np.int64)
    run_start_out = np.cumsum(lens_a) - lens_a
    offset_in_run = np.arange(int(lens_a.sum()), dtype=np.int64) - np.repeat(run_start_out, lens_a)
    idx = np.repeat(np.asarray(src, dtype=np.int64), lens_a) + offset_in_run * np.repeat(
        np.asarray(literal, dtype=np.int64), lens_a
    )
    planes = buf[idx].reshape(height, 4, width)
    return planes.transpose(0, 2, 1)


def _rgbe_to_float(rgbe: np.ndarray) -> np.ndarray:
    """``(..., 4)`` uint8 RGBE -> ``(..., 3)`` float32 linear, Radiance ``colr_color``."""
    e = rgbe[..., 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(np.float32(1.0), e - 136), 0.0).astype(np.float32)
    return (rgbe[..., :3].astype(np.float32) + 0.5) * scale[..., None]


def write_hdr(path: str | os.PathLike, image: torch.Tensor) -> None:
    """Write a ``(3, H, W)`` linear image as a Radiance ``.hdr`` file (new-style RLE).

    Negative values are clamped to 0 (RGBE has no sign); values must be finite.
    Encoding follows Radiance ``setcolr``: shared exponent of the largest channel.
    """
    from torchraster._validate import check_tensor

    check_tensor("image", image, (3, "H", "W"), floating=True, finite=True)
    img = image.detach().to("cpu", torch.float64).clamp_min(0).permute(1, 2, 0).numpy()
    height, width = img.shape[:2]
    peak = img.max(axis=-1)
    mant, exp = np.frexp(peak)  # peak = mant * 2**exp, mant in [0.5, 1)
    keep = peak > 1e-38
    scale = np.where(keep, mant * 256.0 / np.where(keep, peak, 1.0), 0.0)
    rgbe = np.zeros((height, width, 4), dtype=np.uint8)
    rgbe[..., :3] = np.clip(np.floor(img * scale[..., None]), 0, 255).astype(np.uint8)
    rgbe[..., 3] = np.where(keep, np.clip(exp + 128, 0, 255), 0).astype(np.uint8)
    out = bytearray(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n")
    out += f"-Y {height} +X {width}\n".encode()
    if not 8 <= width < 32768:
        out += rgbe.tobytes()
    else:
        for y in range(height):
            out += bytes([2, 2, width >> 8, width & 255])
            for c in range(4):
                out += _rle_plane(rgbe[y, :, c])
    Path(path).write_bytes(bytes(out))


def _rle_plane(row: np.ndarray) -> bytes:
    """New-style RLE of one byte plane: runs of >= 4 equal bytes, literals otherwise."""
    out = bytearray()
    n, i = len(row), 0
    vals = row.tolist()
    while i < n:
        j = i
        while j < n and j - i < 127 and vals[j] == vals[i]:
            j += 1
        if j - i >= 4:
            out += bytes([128 + j - i, vals[i]])
            i = j
            continue
        k = i  # literal until the next run of >= 4 (or 128 bytes)
        while k < n and k - i < 128:
            if k + 3 < n and vals[k] == vals[k + 1] == vals[k + 2] == vals[k + 3]:
                break
            k += 1
        k = max(k, i + 1)
        out += bytes([k - i]) + bytes(vals[i:k])
        i = k
    return bytes(out)


def read_exr(path: str | os.PathLike) -> torch.Tensor:
    """Read the R, G, B channels of an OpenEXR file as a ``(3, H, W)`` float32 tensor.

    Needs the optional ``OpenEXR`` package (``pip install OpenEXR``); raises ImportError
    with that hint otherwise. Non-finite and negative texels are sanitised (see
    :func:`sanitize_radiance`); a file that cannot be read raises ``ValueError`` naming it.
    """
    try:
        import OpenEXR  # type: ignore[import-not-found]
    except ImportError:
        raise ImportError(f"read_hdr: {path}: {_EXR_HINT}") from None
    path = Path(path)
    try:
        return sanitize_radiance(_read_exr(OpenEXR, path), str(path))
    except (OSError, RuntimeError, TypeError) as e:
        raise ValueError(f"read_hdr: {path}: cannot read as OpenEXR ({e})") from None


def sanitize_radiance(image: torch.Tensor, source: str) -> torch.Tensor:
    """Make the texels of a loaded HDR image usable as light, with one logged warning naming
    ``source`` and the counts: NaN -> 0, +Inf -> the largest finite value of the image (a
    saturated sun), negative and -Inf -> 0, values above :data:`MAX_RADIANCE` (+Inf too)
    -> :data:`MAX_RADIANCE`.

    Args:
        image: ``(3, H, W)`` float radiance.
        source: the file name, for the warning.

    Returns:
        ``(3, H, W)``, finite and non-negative.
    """
    finite = torch.isfinite(image)
    n_nan, n_inf = int(torch.isnan(image).sum()), int(torch.isposinf(image).sum())
    n_neg = int((image < 0).sum())
    n_big = int((finite & (image > MAX_RADIANCE)).sum())
    if n_nan == n_inf == n_neg == n_big == 0:
        return image
    top = image[finite].max() if bool(finite.any()) else image.new_zeros(())
    top = top.clamp(0, MAX_RADIANCE)
    out = torch.where(torch.isposinf(image), top, image)
    out = torch.nan_to_num(out, nan=0.0, neginf=0.0).clamp(0, MAX_RADIANCE)
    if n_nan or n_inf or n_neg:
        log.warning("%s: %d NaN texel value(s) set to 0, %d +Inf set to %g, %d negative set "
                    "to 0", source, n_nan, n_inf, float(top), n_neg)
    if n_big:
        log.warning("%s: %d texel value(s) above MAX_RADIANCE = %g clamped to it", source,
                    n_big, MAX_RADIANCE)
    return out


def _read_exr(OpenEXR, path: Path) -> torch.Tensor:  # noqa: N803 (the module)
    if hasattr(OpenEXR, "File"):  # OpenEXR >= 3.3 Python API
        with OpenEXR.File(str(path)) as f:
            chans = f.channels()
            if "RGB" in chans:
                rgb = np.asarray(chans["RGB"].pixels, dtype=np.float32)
            elif "RGBA" in chans:
                rgb = np.asarray(chans["RGBA"].pixels, dtype=np.float32)[..., :3]
            else:
                try:
                    rgb = np.stack([np.asarray(chans[c].pixels, np.float32) for c in "RGB"], -1)
                except KeyError:
                    raise ValueError(f"read_hdr: {path}: no R, G, B channels") from None
        return torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1)))
    import Imath  # type: ignore[import-not-found]  # legacy API (OpenEXR < 3.3)

    f = OpenEXR.InputFile(str(path))
    win = f.header()["dataWindow"]
    width, height = win.max.x - win.min.x + 1, win.max.y - win.min.y + 1
    pt = Imath.PixelType(Imath.PixelType.FLOAT)
    planes = [np.frombuffer(f.channel(c, pt), dtype=np.float32) for c in "RGB"]
    return torch.from_numpy(np.stack(planes).reshape(3, height, width).copy())
