"""Stop a stage once its validation error stops improving (a skip: work a scene does not need).

One rule for every stage: a validation value is measured every N steps (the volume stages: PSNR
on held-out frames, higher is better; the PBR stage: the mean photometric L1 of the last N
steps, lower is better); the stage stops once ``patience`` measurements in a row have not
improved on the best before them by ``min_delta``. The rule reads only the list of
measurements, so a resumed stage (its history restored) decides as the uninterrupted one."""

from __future__ import annotations

from typing import Sequence

from core.errors import ConfigError


def stalled(values: Sequence[float], patience: int, min_delta: float, *, higher_is_better: bool,
            relative: bool = False) -> bool:
    """True when none of the last ``patience`` ``values`` improved on the best of the values
    before them by more than ``min_delta`` (absolute, or relative to that best with
    ``relative``). False while fewer than ``patience + 1`` values exist. Non-finite values never
    count as an improvement."""
    if patience < 1:
        raise ConfigError(f"patience: must be >= 1, got {patience}")
    if len(values) <= patience:
        return False
    before = [v for v in values[:-patience] if v == v and abs(v) != float("inf")]
    if not before:
        return False
    best = max(before) if higher_is_better else min(before)
    margin = abs(best) * min_delta if relative else min_delta
    for v in values[-patience:]:
        if v != v or abs(v) == float("inf"):
            continue
        if (v > best + margin) if higher_is_better else (v < best - margin):
            return False
    return True


__all__ = ["stalled"]
