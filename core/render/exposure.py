"""Automatic exposure of a rendered clip: one exposure for the whole clip, from its HDR frames.

A relight under a new sky or a night scene with lamps has no capture exposure that fits it: the
capture's exposure was set for the capture's own light. The automatic exposure measures the
rendered HDR frames (linear radiance, before the LDR transform
``ldr = clip(exposure * hdr, 0, 1)^(1/gamma)``) and picks

    exposure = min(key / log_average(Y),  white / max_f percentile_f(max(R, G, B)))

* ``key / log_average(Y)``: the photographic key (Reinhard et al. 2002): the log-average
  luminance ``Y = 0.2126 R + 0.7152 G + 0.0722 B`` of all pixels of all frames maps to ``key``
  (0.18, mid grey). This sets a daylight frame.
* ``white / percentile``: the highlight limit: in every frame, the ``highlight_percentile`` of
  the brightest channel maps to ``white``, so at most ``100 - highlight_percentile`` % of a
  frame's pixels clip. At night (a dark frame with a few lamps) this is the one that decides:
  the log-average of a night frame is tiny, and the key alone would blow the lamps out.

One value for the clip (not one per frame), so nothing flickers as a car drives through a lamp's
cone. The result is clamped to ``[min_ev, max_ev]`` stops around 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from core.errors import ConfigError, ShapeError
from core.numerics import require_finite_np

#: Rec. 709 luminance weights of linear RGB.
LUMA = np.array([0.2126, 0.7152, 0.0722], np.float64)
#: Radiance floor of the log-average (a black pixel would send log to -inf).
LOG_AVERAGE_FLOOR = 1e-6


@dataclass(frozen=True)
class AutoExposure:
    """Settings of :func:`auto_exposure`."""

    key: float = 0.18
    """Linear LDR value (before gamma) the clip's log-average luminance maps to (mid grey)."""
    highlight_percentile: float = 99.0
    """Percentile (per frame) of the brightest channel that maps to ``white``: at most
    ``100 - highlight_percentile`` % of a frame's pixels clip."""
    white: float = 0.9
    """Linear value the highlight percentile maps to (below 1: a margin against rounding to 255
    and against the denoiser brightening a pixel)."""
    min_ev: float = -12.0
    """Lowest exposure, stops (exposure >= 2^min_ev)."""
    max_ev: float = 16.0
    """Highest exposure, stops (a black clip does not get an infinite exposure)."""

    def __post_init__(self) -> None:
        for name, v, lo, hi in (("key", self.key, 1e-4, 1.0), ("highlight_percentile", self.highlight_percentile,
                                                                 50.0, 100.0),
                                ("white", self.white, 1e-3, 1.0), ("min_ev", self.min_ev, -30.0, 30.0),
                                ("max_ev", self.max_ev, -30.0, 30.0)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
                raise ConfigError(f"{name}: must be a finite number in [{lo}, {hi}], got {v!r}")
        if self.min_ev > self.max_ev:
            raise ConfigError(f"min_ev: {self.min_ev} exceeds max_ev {self.max_ev}")


@dataclass(frozen=True)
class ExposureChoice:
    """What :func:`auto_exposure` chose and why."""

    exposure: float
    """The multiplier on the HDR frames."""
    ev: float
    """``log2(exposure)``."""
    limited_by: str
    """``key``, ``highlights`` or ``clamp``."""


def auto_exposure(frames: Sequence[np.ndarray], settings: AutoExposure | None = None) -> ExposureChoice:
    """One exposure for the HDR clip ``frames`` (each ``[H, W, 3]``, linear, >= 0), module
    docstring. Raises ShapeError / NumericalError naming ``frames[i]``."""
    s = settings or AutoExposure()
    if len(frames) == 0:
        raise ConfigError("frames: at least one frame is needed")
    log_sum, count, highs = 0.0, 0, []
    for i, f in enumerate(frames):
        a = np.asarray(f)
        if a.ndim != 3 or a.shape[2] != 3:
            raise ShapeError(f"frames[{i}]: expected [H, W, 3], got {a.shape}")
        require_finite_np(a, f"frames[{i}]")
        a = np.maximum(a.astype(np.float64), 0.0)
        y = a @ LUMA
        log_sum += float(np.log(y + LOG_AVERAGE_FLOOR).sum())
        count += y.size
        highs.append(float(np.percentile(a.max(axis=2), s.highlight_percentile)))
    log_avg = math.exp(log_sum / max(count, 1))
    high = max(highs)
    by_key = s.key / max(log_avg, LOG_AVERAGE_FLOOR)
    by_high = s.white / high if high > 0 else math.inf
    exposure, limited = (by_key, "key") if by_key <= by_high else (by_high, "highlights")
    lo, hi = 2.0 ** s.min_ev, 2.0 ** s.max_ev
    if not lo <= exposure <= hi:
        exposure, limited = min(max(exposure, lo), hi), "clamp"
    return ExposureChoice(float(exposure), float(math.log2(exposure)), limited)


__all__ = ["AutoExposure", "ExposureChoice", "auto_exposure", "LUMA"]
