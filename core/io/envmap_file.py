"""Equirectangular environment maps on disk (``.exr`` or ``.hdr``), validated on the way in.

An environment map is [H, W, 3] float32 linear radiance with W == 2 H (the layout of
:mod:`core.conventions`: row 0 = zenith). Values are finite and non-negative.
"""

from __future__ import annotations

import os

import numpy as np

from core.errors import ConfigError, FormatError, NumericalError, ShapeError
from core.io.exr import read_exr, write_exr
from core.io.hdr import read_hdr, write_hdr

_EXR_EXTS = (".exr",)
_HDR_EXTS = (".hdr", ".pic", ".rgbe")
#: Lossy EXR codecs (DWAA/DWAB, used by 5 of the 6 HDRIs in data/hdri) leave slightly negative
#: values next to bright pixels: down to -0.0022 in forest.exr. Values in [-tolerance, 0) are
#: treated as that noise and set to 0; anything more negative is a broken file.
NEGATIVE_TOLERANCE = 1e-2


def _kind(path: str, arg: str) -> str:
    ext = os.path.splitext(path)[1].lower()
    if ext in _EXR_EXTS:
        return "exr"
    if ext in _HDR_EXTS:
        return "hdr"
    raise ConfigError(f"{arg}: {path!r} has extension {ext!r}; environment maps must be "
                      f"one of {_EXR_EXTS + _HDR_EXTS}")


def _pick_exr_rgb(layers: dict[str, np.ndarray], path: str) -> np.ndarray:
    if "rgb" in layers:
        return layers["rgb"][..., :3]
    three = [k for k, v in layers.items() if v.shape[-1] == 3]
    if len(three) == 1:
        return layers[three[0]]
    raise FormatError(f"{path}: no 'rgb' layer and {len(three)} three-channel layers "
                      f"(layers: {sorted(layers)}); cannot tell which is the environment map")


def read_envmap(
    path: str | os.PathLike,
    *,
    max_pixels: int = 64_000_000,
    negative_tolerance: float = NEGATIVE_TOLERANCE,
) -> np.ndarray:
    """Read an equirectangular environment map as [H, W, 3] float32 linear radiance.

    ``.exr``: the top-level R, G, B channels (layer ``"rgb"``), else the only 3-channel layer.
    ``.hdr`` / ``.pic``: Radiance RGBE. The file must satisfy W == 2 H.

    Raises:
        ConfigError: the extension is not .exr/.hdr/.pic/.rgbe.
        FormatError: (naming the file) unreadable, no usable RGB layer, W != 2 H, or values
            below -negative_tolerance.
        NumericalError: (naming the file) the map holds NaN or Inf.
    """
    if isinstance(negative_tolerance, bool) \
            or not isinstance(negative_tolerance, (int, float, np.floating)) \
            or not np.isfinite(negative_tolerance) or negative_tolerance < 0:
        raise ConfigError(f"negative_tolerance: must be finite and >= 0, got "
                          f"{negative_tolerance!r}")
    tol = float(negative_tolerance)
    p = os.fspath(path)
    kind = _kind(p, "path")
    if kind == "exr":
        rgb = _pick_exr_rgb(read_exr(p, max_pixels=max_pixels), p)
    else:
        rgb = read_hdr(p, max_pixels=max_pixels)
    rgb = np.ascontiguousarray(rgb, dtype=np.float32)
    h, w = rgb.shape[:2]
    if w != 2 * h:
        raise FormatError(f"{p}: environment map is {w} x {h} (W x H); an equirectangular map "
                          "needs W == 2 H")
    finite = np.isfinite(rgb)
    if not finite.all():
        raise NumericalError(f"{p}: environment map has {int(finite.size - finite.sum())} "
                             "non-finite value(s) (NaN or Inf)")
    bad = rgb < -tol
    if bad.any():
        raise FormatError(f"{p}: environment map has {int(bad.sum())} negative value(s) below "
                          f"-{tol:g} (min {float(rgb.min()):.4g}); radiance must be >= 0")
    return np.maximum(rgb, 0.0, out=rgb)


def write_envmap(path: str | os.PathLike, rgb: np.ndarray) -> None:
    """Write [H, W, 3] (W == 2 H) non-negative finite radiance, atomically.

    ``.exr``: top-level R, G, B. Half (PIZ-compressed) when every value is exactly representable
    as a half float (as for maps read from half EXRs, like the bundled HDRIs): lossless and ~5x
    smaller; float32 (ZIP) otherwise (envmaps routinely exceed the half range, e.g. a sun at 1e5).
    ``.hdr``: Radiance RGBE (about 1 % precision).

    Raises:
        ConfigError: unsupported extension.
        ShapeError: ``rgb`` is not [H, W, 3] with W == 2 H.
        NumericalError: NaN, Inf or negative values.
    """
    p = os.fspath(path)
    kind = _kind(p, "path")
    arr = np.asarray(rgb)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] < 1:
        raise ShapeError(f"rgb: expected [H, W, 3], got shape {arr.shape}")
    if arr.shape[1] != 2 * arr.shape[0]:
        raise ShapeError(f"rgb: shape {arr.shape} is not equirectangular (needs W == 2 H)")
    if arr.dtype.kind not in "fiu":
        raise ShapeError(f"rgb: dtype {arr.dtype} is not a real number type")
    finite = np.isfinite(arr)
    if not finite.all():
        raise NumericalError(f"rgb: {int(finite.size - finite.sum())} non-finite value(s)")
    if (arr < 0).any():
        raise NumericalError(f"rgb: {int((arr < 0).sum())} negative value(s); radiance >= 0")
    if kind == "exr":
        a32 = arr.astype(np.float32)
        with np.errstate(over="ignore"):
            lossless_half = bool(np.all(a32.astype(np.float16).astype(np.float32) == a32))
        if lossless_half:
            write_exr(p, {"rgb": a32}, precision="half", compression="piz")
        else:
            write_exr(p, {"rgb": a32}, precision="float", compression="zip")
    else:
        write_hdr(p, arr)
