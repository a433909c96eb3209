"""Multi-layer OpenEXR files: write named layers, read them back grouped, check headers first.

Channel naming (write side), for a layer ``name`` holding an [H, W, C] array:

====  ==================================
C     channels
====  ==================================
1     ``name.Y`` (a 2-D [H, W] array is C = 1)
2     ``name.X``, ``name.Y``
3     ``name.R``, ``name.G``, ``name.B``
4     ``name.R``, ``name.G``, ``name.B``, ``name.A``
====  ==================================

A layer called ``"rgb"`` or ``"beauty"`` (C = 3 or 4) is written as the un-prefixed channels
``R, G, B(, A)`` so image viewers show it as the main picture; it is read back as ``"rgb"``.
``channel_names`` overrides the suffixes of any layer, e.g. ``{"normal": ("X", "Y", "Z")}``.

Reading never hands an untrusted size to the OpenEXR library: :func:`exr_header` parses the
header bytes itself (bounded: 1 MB of header, 1 MB per attribute, 1024 attributes) and
:func:`read_exr` refuses absurd images before any pixel memory is allocated.

Multi-part files: every part's header is checked, but only part 0 is returned.
"""

from __future__ import annotations

import dataclasses
import os
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from core.errors import ConfigError, FormatError, ShapeError
from core.numerics import require_finite_np

#: Largest finite float16 value; half layers are clamped to +-HALF_MAX before the cast.
HALF_MAX = 65504.0
#: The four magic bytes every EXR file starts with (20000630 little-endian).
EXR_MAGIC = b"\x76\x2f\x31\x01"
#: Bounds of the header parser: a real header is a few kB; these stop hostile files early.
MAX_HEADER_BYTES = 1 << 20
MAX_ATTRIBUTE_BYTES = 1 << 20
MAX_ATTRIBUTES = 1024
MAX_PARTS = 64

_PIXEL_TYPES = {0: "uint", 1: "half", 2: "float"}
_COMPRESSION_NAMES = (
    "none", "rle", "zips", "zip", "piz", "pxr24", "b44", "b44a", "dwaa", "dwab",
    "htj2k256", "htj2k32", "lj2k", "zstd",
)
_DEFAULT_SUFFIXES = {1: ("Y",), 2: ("X", "Y"), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}
_MAIN_IMAGE_LAYERS = ("rgb", "beauty")
#: Channel orders restored on read; any other set of suffixes comes back sorted.
_CANONICAL_ORDERS = (("R", "G", "B", "A"), ("X", "Y", "Z", "W"))

_FLAG_TILED = 0x200
_FLAG_LONG_NAMES = 0x400
_FLAG_NON_IMAGE = 0x800
_FLAG_MULTIPART = 0x1000
_KNOWN_FLAGS = _FLAG_TILED | _FLAG_LONG_NAMES | _FLAG_NON_IMAGE | _FLAG_MULTIPART


@dataclass(frozen=True)
class ExrHeader:
    """What :func:`exr_header` learns from the header of part 0 of an EXR file.

    ``width``/``height`` are the data-window size in pixels; ``channels`` and ``pixel_types``
    ("uint", "half" or "float") are parallel tuples in file order (alphabetical per the spec);
    ``data_window`` is (xmin, ymin, xmax, ymax), inclusive; ``num_parts`` counts parts.
    """

    width: int
    height: int
    channels: tuple[str, ...]
    pixel_types: tuple[str, ...]
    data_window: tuple[int, int, int, int]
    compression: str
    tiled: bool
    deep: bool
    num_parts: int
    #: (xSampling, ySampling) per channel, parallel to ``channels``.
    sampling: tuple[tuple[int, int], ...] = ()
    #: Byte offset of the chunk offset table (single-part files; -1 otherwise).
    table_offset: int = -1


# atomic_output lives in core.io.atomic; re-exported here for the writers that import it from exr
from core.io.atomic import atomic_output  # noqa: E402,F401


# ---------------------------------------------------------------------------------------------
# header parser (pure Python, bounded)
# ---------------------------------------------------------------------------------------------

class _Reader:
    """Cursor over the header bytes; running off the end is a FormatError naming the file."""

    def __init__(self, buf: bytes, path: str, file_size: int):
        self.buf, self.pos, self.path, self.file_size = buf, 0, path, file_size

    def fail(self, what: str) -> FormatError:
        return FormatError(f"{self.path}: malformed EXR header: {what}")

    def take(self, n: int, what: str) -> bytes:
        if self.pos + n > len(self.buf):
            if len(self.buf) >= MAX_HEADER_BYTES:
                raise FormatError(f"{self.path}: EXR header larger than {MAX_HEADER_BYTES} bytes")
            raise self.fail(f"file truncated while reading {what} ({self.file_size} bytes)")
        out = self.buf[self.pos:self.pos + n]
        self.pos += n
        return out

    def cstring(self, max_len: int, what: str) -> str:
        end = self.buf.find(b"\0", self.pos, self.pos + max_len + 1)
        if end < 0:
            if len(self.buf) - self.pos <= max_len:
                self.take(max_len + 1, what)  # raises the right truncation / size error
            raise self.fail(f"{what} longer than {max_len} bytes")
        raw = self.buf[self.pos:end]
        self.pos = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise self.fail(f"{what} is not UTF-8") from exc


def _parse_chlist(data: bytes, rd: _Reader) -> tuple[list[str], list[str], list[tuple[int, int]]]:
    names, types, sampling = [], [], []
    pos = 0
    while True:
        end = data.find(b"\0", pos)
        if end < 0:
            raise rd.fail("unterminated channel list")
        if end == pos:  # empty name terminates the list
            break
        name = data[pos:end].decode("utf-8", errors="replace")
        if end + 17 > len(data):
            raise rd.fail(f"channel list entry {name!r} is cut short")
        ptype, _plinear, xs, ys = struct.unpack_from("<iB3xii", data, end + 1)
        if ptype not in _PIXEL_TYPES:
            raise rd.fail(f"channel {name!r} has unknown pixel type {ptype}")
        if xs < 1 or ys < 1:
            raise rd.fail(f"channel {name!r} has sampling ({xs}, {ys})")
        names.append(name)
        types.append(_PIXEL_TYPES[ptype])
        sampling.append((xs, ys))
        pos = end + 17
    return names, types, sampling


def _parse_one_header(rd: _Reader, long_names: bool) -> dict[str, tuple[str, bytes]]:
    attrs: dict[str, tuple[str, bytes]] = {}
    max_name = 255 if long_names else 31
    while True:
        name = rd.cstring(max_name, "attribute name")
        if name == "":
            return attrs
        if len(attrs) >= MAX_ATTRIBUTES:
            raise rd.fail(f"more than {MAX_ATTRIBUTES} attributes")
        type_name = rd.cstring(max_name, f"type of attribute {name!r}")
        (size,) = struct.unpack("<i", rd.take(4, f"size of attribute {name!r}"))
        if size < 0 or size > MAX_ATTRIBUTE_BYTES:
            raise rd.fail(f"attribute {name!r} has size {size} (limit {MAX_ATTRIBUTE_BYTES})")
        attrs[name] = (type_name, rd.take(size, f"value of attribute {name!r}"))


def _header_from_attrs(attrs: dict[str, tuple[str, bytes]], rd: _Reader, flags: int,
                       num_parts: int) -> ExrHeader:
    if "channels" not in attrs or attrs["channels"][0] != "chlist":
        raise rd.fail("missing 'channels' (chlist) attribute")
    if "dataWindow" not in attrs or attrs["dataWindow"][0] != "box2i" \
            or len(attrs["dataWindow"][1]) != 16:
        raise rd.fail("missing or malformed 'dataWindow' (box2i) attribute")
    names, types, sampling = _parse_chlist(attrs["channels"][1], rd)
    xmin, ymin, xmax, ymax = struct.unpack("<4i", attrs["dataWindow"][1])
    width, height = xmax - xmin + 1, ymax - ymin + 1  # Python ints: no overflow
    if width <= 0 or height <= 0:
        raise rd.fail(f"empty or negative data window ({xmin}, {ymin})-({xmax}, {ymax})")
    compression = "none"
    if "compression" in attrs and len(attrs["compression"][1]) >= 1:
        code = attrs["compression"][1][0]
        compression = _COMPRESSION_NAMES[code] if code < len(_COMPRESSION_NAMES) else f"#{code}"
    part_type = ""
    if "type" in attrs and attrs["type"][0] == "string":
        part_type = attrs["type"][1].decode("utf-8", errors="replace")
    return ExrHeader(
        width=width, height=height, channels=tuple(names), pixel_types=tuple(types),
        data_window=(xmin, ymin, xmax, ymax), compression=compression,
        tiled=bool(flags & _FLAG_TILED) or "tile" in part_type,
        deep=bool(flags & _FLAG_NON_IMAGE) or part_type.startswith("deep"),
        num_parts=num_parts, sampling=tuple(sampling),
    )


def _read_headers(path: str | os.PathLike) -> list[ExrHeader]:
    """Parse the header of every part (at most MAX_PARTS) without touching pixel data."""
    p = os.fspath(path)
    with open(p, "rb") as fh:
        file_size = os.fstat(fh.fileno()).st_size
        buf = fh.read(MAX_HEADER_BYTES)
    rd = _Reader(buf, p, file_size)
    if len(buf) < 8 or buf[:4] != EXR_MAGIC:
        raise FormatError(f"{p}: not an OpenEXR file (bad magic number)")
    rd.pos = 4
    (version_field,) = struct.unpack("<I", rd.take(4, "version"))
    version, flags = version_field & 0xFF, version_field & ~0xFF
    if version != 2:
        raise FormatError(f"{p}: unsupported EXR version {version}")
    if flags & ~_KNOWN_FLAGS:
        raise FormatError(f"{p}: unknown EXR version flags 0x{flags & ~_KNOWN_FLAGS:x}")
    long_names = bool(flags & _FLAG_LONG_NAMES)
    if not flags & _FLAG_MULTIPART:
        attrs = _parse_one_header(rd, long_names)
        return [dataclasses.replace(_header_from_attrs(attrs, rd, flags, 1), table_offset=rd.pos)]
    parts: list[dict[str, tuple[str, bytes]]] = []
    while True:  # multi-part: headers back to back, the list ends with an empty header
        if rd.pos < len(rd.buf) and rd.buf[rd.pos] == 0:
            rd.pos += 1
            break
        if len(parts) >= MAX_PARTS:
            raise FormatError(f"{p}: more than {MAX_PARTS} parts")
        parts.append(_parse_one_header(rd, long_names))
    if not parts:
        raise FormatError(f"{p}: multi-part EXR with no parts")
    return [_header_from_attrs(a, rd, flags, len(parts)) for a in parts]


#: Scanlines per chunk of each compression (the OpenEXR spec); others are not checked here.
_LINES_PER_CHUNK = {"none": 1, "rle": 1, "zips": 1, "zip": 16, "pxr24": 16, "piz": 32, "b44": 32, "b44a": 32,
                    "dwaa": 32, "dwab": 256, "htj2k32": 32, "htj2k256": 256}


def _check_chunks(p: str, head: ExrHeader) -> None:
    """Check a single-part scanline file's chunk offset table and chunk leaders against the file,
    so a truncated or garbled file is refused with what is wrong and where (the OpenEXR binding
    only says "file has 0 parts"). Raises :class:`FormatError`."""
    lpc = _LINES_PER_CHUNK.get(head.compression)
    if head.table_offset < 0 or head.tiled or head.deep or lpc is None:
        return
    n = -(-head.height // lpc)
    with open(p, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        end = head.table_offset + 8 * n
        if end > size:
            raise FormatError(f"{p}: truncated EXR: the table of {n} chunk offsets ends at byte {end}, "
                              f"the file has {size} bytes")
        fh.seek(head.table_offset)
        offsets = struct.unpack(f"<{n}Q", fh.read(8 * n))
        for i, off in enumerate(offsets):
            what = f"scanline chunk {i} of {n} (lines {head.data_window[1] + i * lpc}...)"
            if off < end or off + 8 > size:
                raise FormatError(f"{p}: truncated or corrupt EXR: {what} starts at byte {off}, outside the pixel "
                                  f"data (bytes {end}-{size})")
            fh.seek(off)
            y, packed = struct.unpack("<ii", fh.read(8))
            if y != head.data_window[1] + i * lpc:
                raise FormatError(f"{p}: corrupt EXR: {what} at byte {off} is labelled line {y}")
            if packed < 0 or off + 8 + packed > size:
                raise FormatError(f"{p}: truncated EXR: {what} at byte {off} holds {packed} bytes and ends past "
                                  f"the end of the file ({size} bytes)")


def exr_header(path: str | os.PathLike) -> ExrHeader:
    """Read only the header of part 0 of the EXR file at ``path`` (no pixel data is read).

    Raises :class:`FormatError` naming the file if it is not an EXR, the header is cut short,
    larger than 1 MB, has an attribute over 1 MB or more than 1024 attributes, or lacks a valid
    ``channels``/``dataWindow``. A missing file raises :class:`FileNotFoundError`.
    """
    return _read_headers(path)[0]


# ---------------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------------

def _compression_code(compression: str):
    import OpenEXR

    if not isinstance(compression, str) or compression.lower() not in _COMPRESSION_NAMES:
        raise ConfigError(f"compression: {compression!r} is not one of {_COMPRESSION_NAMES}")
    return OpenEXR.Compression(_COMPRESSION_NAMES.index(compression.lower()))


def _layer_precision(precision: str | Mapping[str, str], layers: Mapping) -> dict[str, str]:
    if isinstance(precision, str):
        per = {name: precision for name in layers}
    elif isinstance(precision, Mapping):
        unknown = set(precision) - set(layers)
        if unknown:
            raise ConfigError(f"precision: names layers that are not written: {sorted(unknown)}")
        per = {name: precision.get(name, "half") for name in layers}
    else:
        raise ConfigError("precision: must be 'half', 'float' or a mapping layer -> precision")
    bad = {name: prec for name, prec in per.items() if prec not in ("half", "float")}
    if bad:
        raise ConfigError(f"precision: {bad} (each must be 'half' or 'float')")
    return per


def write_exr(
    path: str | os.PathLike,
    layers: Mapping[str, np.ndarray],
    *,
    precision: str | Mapping[str, str] = "half",
    compression: str = "zip",
    channel_names: Mapping[str, Sequence[str]] | None = None,
) -> None:
    """Write named layers to a single-part scanline EXR at ``path``, atomically.

    Args:
        path: output file; written to a temporary file in the same directory, then renamed, so
            a failure never leaves a half-written file.
        layers: name -> [H, W] or [H, W, C] array (C in 1..4, any real dtype; all layers share
            H, W). See the module docstring for channel naming; ``"rgb"``/``"beauty"`` become
            the top-level ``R, G, B(, A)`` channels (only one of the two may be given).
        precision: "half" (float16) or "float" (float32), or a mapping layer -> precision
            (layers not in the mapping are "half"). Half layers are clamped to the largest
            finite half, 65504 (and -65504), before the cast, so they never hold Inf.
        compression: one of "none", "rle", "zips", "zip", "piz", "pxr24", "b44", "b44a",
            "dwaa", "dwab", "htj2k256", "htj2k32", "lj2k", "zstd" (lossy ones lose precision).
        channel_names: layer -> explicit channel suffixes, one per channel (no dots).

    Raises:
        ShapeError: a layer is not [H, W] / [H, W, C<=4], sizes differ, or dtype is not real.
        ConfigError: bad precision/compression/channel names, or two layers give the same
            channel name.
        NumericalError: a layer holds NaN or Inf (the message names the layer).
        FormatError: the OpenEXR library fails to write the file.
    """
    import OpenEXR

    if not isinstance(layers, Mapping) or len(layers) == 0:
        raise ConfigError("layers: must be a non-empty mapping name -> array")
    channel_names = dict(channel_names or {})
    unknown = set(channel_names) - set(layers)
    if unknown:
        raise ConfigError(f"channel_names: names layers that are not written: {sorted(unknown)}")
    if all(n in layers for n in _MAIN_IMAGE_LAYERS):
        raise ConfigError("layers: give either 'rgb' or 'beauty', not both (both are R, G, B)")
    per_precision = _layer_precision(precision, layers)
    comp = _compression_code(compression)

    channels: dict[str, np.ndarray] = {}
    size: tuple[int, int] | None = None
    for name, value in layers.items():
        if not isinstance(name, str) or not name or name.endswith("."):
            raise ConfigError(f"layers: layer name {name!r} must be a non-empty string "
                              "not ending in '.'")
        arr = np.asarray(value)
        if arr.dtype.kind not in "fiu":
            raise ShapeError(f"layers[{name!r}]: dtype {arr.dtype} is not a real number type")
        if arr.ndim == 2:
            arr = arr[:, :, None]
        if arr.ndim != 3 or not 1 <= arr.shape[2] <= 4:
            raise ShapeError(f"layers[{name!r}]: shape {np.shape(value)} is not [H, W] or "
                             "[H, W, C] with C in 1..4")
        if arr.shape[0] < 1 or arr.shape[1] < 1:
            raise ShapeError(f"layers[{name!r}]: empty image of shape {arr.shape}")
        if size is None:
            size = arr.shape[:2]
        elif arr.shape[:2] != size:
            raise ShapeError(f"layers[{name!r}]: size {arr.shape[:2]} differs from the "
                             f"other layers' {size} (all layers must share H, W)")
        require_finite_np(arr, f"layers[{name!r}]")
        nch = arr.shape[2]
        main = name in _MAIN_IMAGE_LAYERS
        if name in channel_names:
            suffixes = tuple(channel_names[name])
            if len(suffixes) != nch:
                raise ConfigError(f"channel_names[{name!r}]: {len(suffixes)} names for a "
                                  f"layer with {nch} channels")
            if any(not isinstance(s, str) or not s or "." in s for s in suffixes) \
                    or len(set(suffixes)) != nch:
                raise ConfigError(f"channel_names[{name!r}]: {suffixes} must be distinct "
                                  "non-empty strings without '.'")
        else:
            if main and nch not in (3, 4):
                raise ShapeError(f"layers[{name!r}]: the main image needs 3 or 4 channels, "
                                 f"got shape {arr.shape}")
            suffixes = _DEFAULT_SUFFIXES[nch]
        if per_precision[name] == "half":
            data = np.clip(arr.astype(np.float32), -HALF_MAX, HALF_MAX).astype(np.float16)
        else:
            data = arr.astype(np.float32)
        for c, suffix in enumerate(suffixes):
            full = suffix if main else f"{name}.{suffix}"
            if full in channels:
                raise ConfigError(f"layers[{name!r}]: channel {full!r} is written twice")
            # The library silently mis-writes non-contiguous views: always pass a copy.
            channels[full] = np.ascontiguousarray(data[:, :, c])

    header = {"compression": comp, "type": OpenEXR.scanlineimage}
    target = os.fspath(path)
    with atomic_output(target, suffix=".exr") as tmp:
        try:
            OpenEXR.File(header, channels).write(tmp)
        except Exception as exc:  # the binding raises bare RuntimeError/ValueError
            raise FormatError(f"{target}: OpenEXR failed to write the file: {exc}") from exc


# ---------------------------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------------------------

def _check_limits(path: str, headers: list[ExrHeader], max_pixels: int, max_channels: int):
    for i, h in enumerate(headers):
        where = f"{path}" + (f" (part {i})" if len(headers) > 1 else "")
        if h.deep:
            raise FormatError(f"{where}: deep EXR data is not supported")
        if h.width * h.height > max_pixels:
            raise FormatError(f"{where}: image size {h.width} x {h.height} = "
                              f"{h.width * h.height} pixels exceeds max_pixels={max_pixels}")
        if len(h.channels) > max_channels:
            raise FormatError(f"{where}: {len(h.channels)} channels exceed "
                              f"max_channels={max_channels}")
        if len(h.channels) == 0:
            raise FormatError(f"{where}: no channels")
    sub = [c for c, s in zip(headers[0].channels, headers[0].sampling) if s != (1, 1)]
    if sub:
        raise FormatError(f"{path}: sub-sampled channels are not supported: {sub}")


def _order_suffixes(suffixes: list[str]) -> list[str]:
    for order in _CANONICAL_ORDERS:
        if all(s in order for s in suffixes):
            return sorted(suffixes, key=order.index)
    return sorted(suffixes)


def _group_channels(names: Sequence[str]) -> dict[str, list[str]]:
    """Map output layer key -> full channel names in output order."""
    prefixed: dict[str, list[str]] = {}
    top: list[str] = []
    for full in names:
        layer, _, suffix = full.rpartition(".")
        if layer and suffix:
            prefixed.setdefault(layer, []).append(full)
        else:
            top.append(full)
    groups: dict[str, list[str]] = {}
    if {"R", "G", "B"} <= set(top):
        main = ["R", "G", "B"] + (["A"] if "A" in top else [])
        groups["rgb"] = main
        top = [t for t in top if t not in main]
    for t in sorted(top):
        groups[t] = [t]
    for layer in sorted(prefixed):
        fulls = prefixed[layer]
        by_suffix = {f.rpartition(".")[2]: f for f in fulls}
        ordered = [by_suffix[s] for s in _order_suffixes(list(by_suffix))]
        if layer in groups:
            raise FormatError(f"layer {layer!r} is both a top-level channel group and a prefix")
        groups[layer] = ordered
    return groups


def read_exr(
    path: str | os.PathLike,
    *,
    max_pixels: int = 64_000_000,
    max_channels: int = 64,
) -> dict[str, np.ndarray]:
    """Read part 0 of an EXR file as a dict layer name -> [H, W, C] array.

    Grouping: top-level ``R, G, B(, A)`` -> ``"rgb"``; ``name.S`` channels -> ``"name"`` (the
    layer is everything before the last dot), ordered R, G, B, A or X, Y, Z, W when the
    suffixes are drawn from one of those sets, otherwise sorted; any other top-level channel
    ``C`` -> its own layer ``"C"``. Single-channel layers are [H, W, 1]. Half and float data
    come back float32; a layer whose channels are all UINT comes back uint32.

    The header is parsed first (:func:`exr_header`) and the file is refused *before* pixel
    memory is allocated when width * height > ``max_pixels``, it has more than
    ``max_channels`` channels, an empty/negative data window, deep data or sub-sampled
    channels. Multi-part files: every part is checked, part 0 is returned.

    Raises:
        ConfigError: ``max_pixels``/``max_channels`` are not positive ints.
        FormatError: (naming ``path``) not an EXR, truncated, corrupt, too large, unsupported.
        FileNotFoundError: ``path`` does not exist.
    """
    import OpenEXR

    for arg, val in (("max_pixels", max_pixels), ("max_channels", max_channels)):
        if isinstance(val, bool) or not isinstance(val, int) or val < 1:
            raise ConfigError(f"{arg}: must be a positive int, got {val!r}")
    p = os.fspath(path)
    headers = _read_headers(p)
    _check_limits(p, headers, max_pixels, max_channels)
    head = headers[0]
    _check_chunks(p, head)
    try:
        exr = OpenEXR.File(p, separate_channels=True)
        chans = {name: ch.pixels for name, ch in exr.channels(0).items()}
    except Exception as exc:  # the binding raises bare RuntimeError/ValueError
        # its message for undecodable pixel data is "file has 0 parts": say what it means
        raise FormatError(f"{p}: corrupt EXR pixel data: the OpenEXR library could not decode part 0 "
                          f"({head.width}x{head.height}, {head.compression} compression); the file is damaged "
                          f"or was not completely written") from exc
    if set(chans) != set(head.channels):
        raise FormatError(f"{p}: channels {sorted(chans)} differ from the header's "
                          f"{sorted(head.channels)}")
    try:
        groups = _group_channels(list(chans))
    except FormatError as exc:
        raise FormatError(f"{p}: {exc}") from exc
    out: dict[str, np.ndarray] = {}
    for key, fulls in groups.items():
        planes = [np.asarray(chans[f]) for f in fulls]
        for f, plane in zip(fulls, planes):
            if plane.shape != (head.height, head.width):
                raise FormatError(f"{p}: channel {f!r} has shape {plane.shape}, header says "
                                  f"({head.height}, {head.width})")
        dtype = np.uint32 if all(pl.dtype == np.uint32 for pl in planes) else np.float32
        out[key] = np.stack([pl.astype(dtype, copy=False) for pl in planes], axis=-1)
    return out
