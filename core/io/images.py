"""8-bit images (PNG, JPEG, anything pillow reads) and binary masks.

Every reader refuses images larger than ``max_pixels`` from the header alone, before decoding,
and turns pillow's many exception types into :class:`FormatError` naming the file.
"""

from __future__ import annotations

import os
import warnings

import numpy as np

from core.errors import ConfigError, FormatError, ShapeError
from core.io.atomic import atomic_output
from core.numerics import require_finite_np

DEFAULT_MAX_PIXELS = 64_000_000


def _check_max_pixels(max_pixels: int) -> None:
    if isinstance(max_pixels, bool) or not isinstance(max_pixels, int) or max_pixels < 1:
        raise ConfigError(f"max_pixels: must be a positive int, got {max_pixels!r}")


def _open(path: str, max_pixels: int):
    """Open lazily with pillow (header only) and check the size; caller must close."""
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im = Image.open(path)
    except FileNotFoundError:
        raise
    except Exception as exc:  # UnidentifiedImageError, OSError, SyntaxError, ...
        raise FormatError(f"{path}: not a readable image ({exc})") from exc
    w, h = im.size
    if w * h > max_pixels:
        im.close()
        raise FormatError(f"{path}: image size {w} x {h} = {w * h} pixels exceeds "
                          f"max_pixels={max_pixels}")
    return im


def _load_array(path: str, max_pixels: int) -> tuple[np.ndarray, str]:
    """Decode to a numpy array; returns (array, pillow mode after normalisation)."""
    from PIL import Image

    im = _open(path, max_pixels)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im.load()
        mode = im.mode
        if mode == "P" or mode == "PA":
            im = im.convert("RGBA")
            mode = "RGBA"
        elif mode in ("CMYK", "YCbCr", "LAB", "HSV", "RGBX", "RGBa"):
            im = im.convert("RGB")
            mode = "RGB"
        elif mode == "La":
            im = im.convert("LA")
            mode = "LA"
        arr = np.asarray(im)
    except FormatError:
        raise
    except Exception as exc:  # truncated / corrupt data is raised only at load time
        raise FormatError(f"{path}: corrupt or truncated image ({exc})") from exc
    finally:
        im.close()
    return arr, mode


def _to_uint8(arr: np.ndarray, mode: str, path: str) -> np.ndarray:
    """Map a decoded array of any supported mode to uint8 with the same layout."""
    if arr.dtype == np.uint8:
        return arr
    if arr.dtype == bool:
        return arr.astype(np.uint8) * 255
    if mode.startswith("I;16") or mode == "I":
        # 16-bit data (pillow may hand 16-bit PNGs over as mode "I"): keep the top 8 bits
        return (np.clip(arr.astype(np.int64), 0, 65535) >> 8).astype(np.uint8)
    raise FormatError(f"{path}: unsupported image mode {mode!r} (dtype {arr.dtype})")


def read_image(path: str | os.PathLike, *, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Read an image file as [H, W, 3] uint8 RGB.

    Grayscale is repeated into three channels, alpha is dropped, palettes are expanded,
    16-bit data keeps its top 8 bits.

    Raises:
        FormatError: (naming the file) not an image, corrupt/truncated, unsupported mode, or
            larger than ``max_pixels`` (checked from the header, before decoding).
        FileNotFoundError: ``path`` does not exist.
    """
    _check_max_pixels(max_pixels)
    p = os.fspath(path)
    arr, mode = _load_array(p, max_pixels)
    arr = _to_uint8(arr, mode, p)
    if arr.ndim == 2:
        arr = np.repeat(arr[:, :, None], 3, axis=2)
    elif arr.ndim == 3 and arr.shape[2] == 2:  # LA
        arr = np.repeat(arr[:, :, :1], 3, axis=2)
    elif arr.ndim == 3 and arr.shape[2] >= 3:
        arr = arr[:, :, :3]
    else:
        raise FormatError(f"{p}: unexpected decoded shape {arr.shape} (mode {mode!r})")
    return np.ascontiguousarray(arr)


def read_mask(path: str | os.PathLike, *, max_pixels: int = DEFAULT_MAX_PIXELS) -> np.ndarray:
    """Read a mask image as [H, W] bool: True where the pixel is non-zero.

    Single-channel images (1-bit, 8-bit, 16-bit) use their value; gray+alpha uses the gray
    value; colour images are True where any of R, G, B is non-zero (alpha is ignored).

    Raises:
        FormatError: as :func:`read_image`.
    """
    _check_max_pixels(max_pixels)
    p = os.fspath(path)
    arr, mode = _load_array(p, max_pixels)
    if arr.ndim == 2:
        return np.ascontiguousarray(arr != 0)
    if arr.ndim == 3 and arr.shape[2] == 2:
        return np.ascontiguousarray(arr[:, :, 0] != 0)
    if arr.ndim == 3 and arr.shape[2] >= 3:
        return np.ascontiguousarray((arr[:, :, :3] != 0).any(axis=2))
    raise FormatError(f"{p}: unexpected decoded shape {arr.shape} (mode {mode!r})")


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of an image file, from its header only (no pixel decoding).

    Raises:
        FormatError: (naming the file) not an image pillow can identify.
    """
    p = os.fspath(path)
    im = _open(p, max_pixels=1 << 62)
    try:
        return int(im.size[0]), int(im.size[1])
    finally:
        im.close()


def write_png(path: str | os.PathLike, arr: np.ndarray) -> None:
    """Write an image as PNG, atomically.

    Args:
        arr: [H, W] (gray), [H, W, 1], [H, W, 3] (RGB) or [H, W, 4] (RGBA) as uint8, as bool
            (False -> 0, True -> 255), or as float in [0, 1], which is quantised to
            round(255 * x).

    Raises:
        ShapeError: bad shape or dtype (other integer types are refused, not rescaled).
        ConfigError: float values outside [0, 1].
        NumericalError: float values NaN or Inf.
    """
    from PIL import Image

    a = np.asarray(arr)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (3, 4))):
        raise ShapeError(f"arr: expected [H, W], [H, W, 1], [H, W, 3] or [H, W, 4], got "
                         f"shape {np.shape(arr)}")
    if a.shape[0] < 1 or a.shape[1] < 1:
        raise ShapeError(f"arr: empty image of shape {a.shape}")
    if a.dtype == bool:
        a = a.astype(np.uint8) * 255
    elif a.dtype.kind == "f":
        require_finite_np(a, "arr")
        lo, hi = float(a.min()), float(a.max())
        if lo < 0.0 or hi > 1.0:
            raise ConfigError(f"arr: float images must lie in [0, 1], got [{lo:.4g}, {hi:.4g}]")
        a = np.round(a.astype(np.float64) * 255.0).astype(np.uint8)
    elif a.dtype != np.uint8:
        raise ShapeError(f"arr: dtype {a.dtype} not supported (use uint8, bool or float in "
                         "[0, 1])")
    mode = {2: "L"}.get(a.ndim) or {3: "RGB", 4: "RGBA"}[a.shape[2]]
    img = Image.fromarray(np.ascontiguousarray(a))
    assert img.mode == mode, (img.mode, mode)
    with atomic_output(path, suffix=".png") as tmp:
        img.save(tmp, format="PNG")
