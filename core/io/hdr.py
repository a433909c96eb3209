"""Radiance RGBE ``.hdr`` files (a.k.a. ``.pic``): read flat / RLE scanlines, write RLE.

Format: a text header (``#?RADIANCE`` or ``#?RGBE``, ``KEY=value`` lines, a blank line), a
resolution line such as ``-Y 512 +X 1024`` (512 rows stored top to bottom, 1024 columns left to
right), then the pixels as 4-byte RGBE: value = (mantissa + 0.5) * 2**(E - 136) for E > 0, and
0 for E == 0 (the Radiance decoding convention). Each scanline is either

* flat: W * 4 bytes, possibly using old-style runs (pixel 1,1,1,n repeats the previous pixel);
* new-style RLE (8 <= W < 32768): bytes 2, 2, W >> 8, W & 255, then each of the four components
  run-length coded: a count byte c > 128 repeats the next byte c - 128 times, 0 < c <= 128 is
  followed by c literal bytes.

``EXPOSURE`` and ``COLORCORR`` header lines are ignored (as most readers do): values are
returned as stored. Only ``FORMAT=32-bit_rle_rgbe`` is supported (XYZE is refused).
Orientations ``+-Y H +-X W`` are supported (flipped to row 0 = top, column 0 = left);
transposed ones (``+-X W +-Y H``) are refused.
"""

from __future__ import annotations

import os

import numpy as np

from core.errors import ConfigError, FormatError, NumericalError, ShapeError
from core.io.atomic import atomic_output
from core.numerics import require_finite_np

#: Longest text header accepted (real headers are a few hundred bytes).
MAX_HDR_HEADER_BYTES = 64 * 1024
#: Runs shorter than this are written as literals (the value Radiance itself uses).
_MIN_RUN = 4


def _parse_header(data: bytes, path: str) -> tuple[int, int, bool, bool, int]:
    """Return (height, width, flip_rows, flip_cols, offset of the first pixel byte)."""
    if not (data.startswith(b"#?RADIANCE") or data.startswith(b"#?RGBE")):
        raise FormatError(f"{path}: not a Radiance HDR file (missing '#?RADIANCE' signature)")
    pos = 0
    fmt = None
    while True:
        end = data.find(b"\n", pos, MAX_HDR_HEADER_BYTES)
        if end < 0:
            if len(data) < MAX_HDR_HEADER_BYTES:
                raise FormatError(f"{path}: truncated HDR header (no blank line before the "
                                  "resolution line)")
            raise FormatError(f"{path}: HDR header longer than {MAX_HDR_HEADER_BYTES} bytes")
        line = data[pos:end].strip()
        pos = end + 1
        if line == b"":
            break
        if line.startswith(b"FORMAT="):
            fmt = line[len(b"FORMAT="):].decode("latin-1")
    if fmt is not None and fmt != "32-bit_rle_rgbe":
        raise FormatError(f"{path}: unsupported HDR pixel format {fmt!r} (only 32-bit_rle_rgbe)")
    end = data.find(b"\n", pos, pos + 256)
    if end < 0:
        raise FormatError(f"{path}: truncated or missing HDR resolution line")
    tokens = data[pos:end].decode("latin-1").split()
    if len(tokens) != 4 or tokens[0] not in ("-Y", "+Y") or tokens[2] not in ("-X", "+X"):
        raise FormatError(f"{path}: unsupported HDR resolution line {data[pos:end]!r} "
                          "(expected '-Y H +X W'; transposed layouts are not supported)")
    try:
        height, width = int(tokens[1]), int(tokens[3])
    except ValueError as exc:
        raise FormatError(f"{path}: bad HDR resolution line {data[pos:end]!r}") from exc
    if height < 1 or width < 1:
        raise FormatError(f"{path}: empty HDR image ({width} x {height})")
    return height, width, tokens[0] == "+Y", tokens[2] == "-X", end + 1


def _decode_rle_component(data: bytes, pos: int, width: int, out: np.ndarray, path: str,
                          row: int) -> int:
    """Decode one RLE component of one scanline into ``out`` [W] uint8; return new pos."""
    x = 0
    n = len(data)
    while x < width:
        if pos >= n:
            raise FormatError(f"{path}: truncated HDR data in scanline {row}")
        count = data[pos]
        pos += 1
        if count > 128:
            count -= 128
            if x + count > width:
                raise FormatError(f"{path}: HDR run overflows scanline {row}")
            if pos >= n:
                raise FormatError(f"{path}: truncated HDR data in scanline {row}")
            out[x:x + count] = data[pos]
            pos += 1
        else:
            if count == 0 or x + count > width:
                raise FormatError(f"{path}: bad HDR run length {count} in scanline {row}")
            if pos + count > n:
                raise FormatError(f"{path}: truncated HDR data in scanline {row}")
            out[x:x + count] = np.frombuffer(data, np.uint8, count, pos)
            pos += count
        x += count
    return pos


def _decode_flat_scanline(data: bytes, pos: int, width: int, out: np.ndarray, path: str,
                          row: int) -> int:
    """Flat (possibly old-RLE) scanline into ``out`` [W, 4]; return new pos."""
    n = len(data)
    if pos + 4 * width <= n:
        chunk = np.frombuffer(data, np.uint8, 4 * width, pos).reshape(width, 4)
        is_run = (chunk[:, 0] == 1) & (chunk[:, 1] == 1) & (chunk[:, 2] == 1)
        if not is_run.any():  # the common case: plain flat pixels
            out[:] = chunk
            return pos + 4 * width
    x, shift = 0, 0
    while x < width:
        if pos + 4 > n:
            raise FormatError(f"{path}: truncated HDR data in scanline {row}")
        px = data[pos:pos + 4]
        pos += 4
        if px[0] == 1 and px[1] == 1 and px[2] == 1:  # old-style run of the previous pixel
            if x == 0:
                raise FormatError(f"{path}: HDR run with no previous pixel in scanline {row}")
            count = px[3] << shift
            if x + count > width:
                raise FormatError(f"{path}: HDR run overflows scanline {row}")
            out[x:x + count] = out[x - 1]
            x += count
            shift += 8
        else:
            out[x] = np.frombuffer(px, np.uint8)
            x += 1
            shift = 0
    return pos


def rgbe_to_float(rgbe: np.ndarray) -> np.ndarray:
    """[..., 4] uint8 RGBE -> [..., 3] float32 linear RGB (Radiance's +0.5 convention)."""
    e = rgbe[..., 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(np.float32(1.0), e - 136), np.float32(0.0)).astype(np.float32)
    return ((rgbe[..., :3].astype(np.float32) + 0.5) * scale[..., None]).astype(np.float32)


def float_to_rgbe(rgb: np.ndarray) -> np.ndarray:
    """[..., 3] non-negative finite floats -> [..., 4] uint8 RGBE (truncating mantissas).

    Values below ~1e-38 (relative to the pixel's largest channel) become 0; values beyond the
    RGBE range (> 2**127) are clamped to the largest representable value.
    """
    rgb = np.asarray(rgb, dtype=np.float64)
    peak = rgb.max(axis=-1)
    mant, exp = np.frexp(peak)  # peak = mant * 2**exp, mant in [0.5, 1)
    out = np.zeros(rgb.shape[:-1] + (4,), dtype=np.uint8)
    ok = peak > 1e-38
    exp = np.clip(exp, -127, 127)  # biased exponent must fit 1..255
    scale = np.where(ok, np.ldexp(1.0, 8 - exp), 0.0)  # 256 / 2**exp
    m = np.floor(rgb * scale[..., None])
    out[..., :3] = np.clip(m, 0, 255).astype(np.uint8)
    out[..., 3] = np.where(ok, exp + 128, 0).astype(np.uint8)
    return out


def read_hdr(path: str | os.PathLike, *, max_pixels: int = 64_000_000) -> np.ndarray:
    """Read a Radiance ``.hdr`` file as [H, W, 3] float32 linear RGB, row 0 at the top.

    The resolution line is checked against ``max_pixels`` before pixel memory is allocated.

    Raises:
        FormatError: (naming ``path`` and the problem) not an HDR file, unsupported format or
            orientation, truncated or malformed scanlines, image larger than ``max_pixels``.
        ConfigError: ``max_pixels`` is not a positive int.
        FileNotFoundError: ``path`` does not exist.
    """
    if isinstance(max_pixels, bool) or not isinstance(max_pixels, int) or max_pixels < 1:
        raise ConfigError(f"max_pixels: must be a positive int, got {max_pixels!r}")
    p = os.fspath(path)
    with open(p, "rb") as fh:
        head = fh.read(MAX_HDR_HEADER_BYTES + 256)
        height, width, flip_rows, flip_cols, offset = _parse_header(head, p)
        if height * width > max_pixels:
            raise FormatError(f"{p}: image size {width} x {height} = {width * height} pixels "
                              f"exceeds max_pixels={max_pixels}")
        # Worst case per scanline: 4-byte marker + literal runs (1 count byte per 128 bytes).
        budget = height * (4 + 4 * width + 4 * (width // 128 + 1))
        fh.seek(offset)
        data = fh.read(budget)
    rgbe = np.empty((height, width, 4), dtype=np.uint8)
    pos = 0
    n = len(data)
    for row in range(height):
        if 8 <= width < 32768 and pos + 4 <= n and data[pos] == 2 and data[pos + 1] == 2 \
                and not data[pos + 2] & 0x80:
            line_w = (data[pos + 2] << 8) | data[pos + 3]
            if line_w != width:
                raise FormatError(f"{p}: HDR scanline {row} declares width {line_w}, "
                                  f"image width is {width}")
            pos += 4
            comp = np.empty(width, dtype=np.uint8)
            for c in range(4):
                pos = _decode_rle_component(data, pos, width, comp, p, row)
                rgbe[row, :, c] = comp
        else:
            pos = _decode_flat_scanline(data, pos, width, rgbe[row], p, row)
    img = rgbe_to_float(rgbe)
    if flip_rows:
        img = img[::-1]
    if flip_cols:
        img = img[:, ::-1]
    return np.ascontiguousarray(img)


def _encode_rle_component(values: np.ndarray) -> bytes:
    """RLE-encode one component of one scanline ([W] uint8), new-style Radiance runs."""
    w = values.shape[0]
    # boundaries of maximal runs of equal bytes
    change = np.flatnonzero(values[1:] != values[:-1]) + 1
    starts = np.concatenate(([0], change))
    lengths = np.diff(np.concatenate((starts, [w])))
    out = bytearray()
    raw = values.tobytes()
    lit_start = 0  # start of the pending literal stretch
    for s, ln in zip(starts.tolist() + [w], lengths.tolist() + [_MIN_RUN]):
        if ln < _MIN_RUN:
            continue
        for a in range(lit_start, s, 128):  # literals before this run (or the end)
            k = min(128, s - a)
            out.append(k)
            out += raw[a:a + k]
        if s == w:
            break
        for a in range(s, s + ln, 127):
            out.append(128 + min(127, s + ln - a))
            out.append(raw[s])
        lit_start = s + ln
    return bytes(out)


def write_hdr(path: str | os.PathLike, rgb: np.ndarray) -> None:
    """Write [H, W, 3] linear RGB (non-negative, finite) as a Radiance ``.hdr``, atomically.

    Uses ``-Y H +X W`` (row 0 at the top) and new-style RLE scanlines when 8 <= W < 32768,
    flat scanlines otherwise. RGBE keeps ~8 bits of mantissa per pixel relative to its
    brightest channel (relative error < 0.4 % for that channel).

    Raises:
        ShapeError: ``rgb`` is not [H, W, 3] of a real dtype.
        NumericalError: ``rgb`` holds NaN, Inf or negative values (RGBE cannot store them).
    """
    arr = np.asarray(rgb)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise ShapeError(f"rgb: expected [H, W, 3], got shape {arr.shape}")
    if arr.dtype.kind not in "fiu":
        raise ShapeError(f"rgb: dtype {arr.dtype} is not a real number type")
    require_finite_np(arr, "rgb")
    if arr.dtype.kind in "fi" and (arr < 0).any():
        raise NumericalError(f"rgb: {int((arr < 0).sum())} negative value(s); RGBE stores "
                             "only non-negative radiance")
    height, width = arr.shape[:2]
    rgbe = float_to_rgbe(arr)
    chunks = [b"#?RADIANCE\n# written by BRDFusion core.io.hdr\nFORMAT=32-bit_rle_rgbe\n\n",
              f"-Y {height} +X {width}\n".encode("ascii")]
    if 8 <= width < 32768:
        marker = bytes((2, 2, width >> 8, width & 255))
        for row in range(height):
            chunks.append(marker)
            for c in range(4):
                chunks.append(_encode_rle_component(rgbe[row, :, c]))
    else:
        chunks.append(rgbe.tobytes())
    with atomic_output(path, suffix=".hdr") as tmp:
        with open(tmp, "wb") as fh:
            fh.write(b"".join(chunks))
