"""The paper's tone map between linear HDR radiance and display LDR, and its inverse (numpy).

    ldr = clip(exposure * hdr, 0, 1) ** (1 / gamma)           (clip before the power)
    hdr = ldr ** gamma / exposure                              (inverse, exact for unclipped)

Values above 1 / exposure are clipped, so the inverse recovers only ``min(hdr, 1/exposure)``.
"""

from __future__ import annotations

import math

import numpy as np

from core.errors import ConfigError, NumericalError, ShapeError


def _check_positive(value: float, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ConfigError(f"{name}: must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v) or v <= 0.0:
        raise ConfigError(f"{name}: must be finite and > 0, got {value!r}")
    return v


def _float_array(x, name: str) -> np.ndarray:
    a = np.asarray(x)
    if a.dtype.kind not in "fiu":
        raise ShapeError(f"{name}: dtype {a.dtype} is not a real number type")
    if a.dtype != np.float64:
        a = a.astype(np.float32)
    finite = np.isfinite(a)
    if not finite.all():
        raise NumericalError(f"{name}: {int(finite.size - finite.sum())} non-finite value(s) "
                             "(NaN or Inf)")
    if (a < 0).any():
        raise NumericalError(f"{name}: {int((a < 0).sum())} negative value(s) (min "
                             f"{float(a.min()):.4g}); expected >= 0")
    return a


def hdr_to_ldr(hdr: np.ndarray, exposure: float = 1.0, gamma: float = 2.2) -> np.ndarray:
    """Tone-map linear radiance to display values: ``clip(exposure * hdr, 0, 1) ** (1/gamma)``.

    Args:
        hdr: any shape, linear radiance >= 0, finite.
        exposure: multiplier > 0 applied before clipping.
        gamma: display gamma > 0.

    Returns:
        Same shape, in [0, 1]; float64 if ``hdr`` is float64, else float32.

    Raises:
        NumericalError: ``hdr`` has NaN, Inf or negative values.
        ConfigError: ``exposure`` or ``gamma`` not finite and > 0.
    """
    e = _check_positive(exposure, "exposure")
    g = _check_positive(gamma, "gamma")
    a = _float_array(hdr, "hdr")
    return np.power(np.clip(a * a.dtype.type(e), 0.0, 1.0), a.dtype.type(1.0 / g))


def ldr_to_uint8(ldr: np.ndarray) -> np.ndarray:
    """Quantise display values in [0, 1] to uint8 as ``round(255 * ldr)``.

    Raises:
        NumericalError: NaN/Inf, or values outside [0, 1] (tone-map first).
    """
    a = _float_array(ldr, "ldr")
    if (a > 1.0).any():
        raise NumericalError(f"ldr: {int((a > 1).sum())} value(s) above 1 (max "
                             f"{float(a.max()):.4g}); expected [0, 1]")
    return np.round(a.astype(np.float64) * 255.0).astype(np.uint8)


def ldr_to_hdr(ldr: np.ndarray, exposure: float = 1.0, gamma: float = 2.2) -> np.ndarray:
    """Invert :func:`hdr_to_ldr`: ``ldr ** gamma / exposure``.

    Args:
        ldr: uint8 (read as value / 255) or float in [0, 1], any shape.

    Returns:
        Linear radiance, float64 if ``ldr`` is float64, else float32. Pixels that were clipped
        at 1 come back as ``1 / exposure``.

    Raises:
        NumericalError: NaN/Inf, negative, or float values above 1.
        ConfigError: ``exposure`` or ``gamma`` not finite and > 0.
    """
    e = _check_positive(exposure, "exposure")
    g = _check_positive(gamma, "gamma")
    raw = np.asarray(ldr)
    if raw.dtype == np.uint8:
        a = raw.astype(np.float32) / np.float32(255.0)
    else:
        a = _float_array(raw, "ldr")
        if (a > 1.0).any():
            raise NumericalError(f"ldr: {int((a > 1).sum())} value(s) above 1 (max "
                                 f"{float(a.max()):.4g}); expected [0, 1]")
    return np.power(a, a.dtype.type(g)) / a.dtype.type(e)
