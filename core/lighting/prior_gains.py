"""The sun / sky split of the lighting prior, refitted to the capture through the PBR pass.

The lighting prior (:mod:`core.lighting.prior`) extrapolates the sky dome from the band of sky the
frames saw: a forward camera in a street sees sky near the horizon between the facades, never the
zenith that lights the street most. On a development street under the city map the prior's dome
came out 3-9x darker than the true one above 20 deg elevation and its sun twice as strong; the
pbr and joint stages' per-texel fits did not move it (75-300 noisy Adam steps), so walls facing
away from the sun re-rendered 17% too dark (LDR) and held 81% of the re-render's error.

The PBR pass is linear in the map's radiance (direct light, the bounce's ``L_b`` and the map seen
through partial coverage all are), so the render of ``g_sun E_sun + g_sky E_sky + E_held`` is
``g_sun R_sun + g_sky R_sky + R_held`` with the three parts rendered once each. The two gains are
then found by a grid search of the L1 between the tone-mapped sum and the training frames, at no
further rendering cost: a global move that gradient steps on single texels do not make.

Parts of the map (``[H, 2H, 3]``, linear radiance, project equirect convention):

* ``held``: texels the sky evidence fixes (weight >= 0.5: the sky the frames saw);
* ``sun``: the other texels within ``sun_cap_deg`` of the prior's sun direction;
* ``sky``: every other texel (the unseen dome, and the ground below the horizon).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.conventions import envmap_directions
from core.errors import ConfigError, ShapeError
from core.numerics import require_finite_np


@dataclass(frozen=True)
class PriorGainSettings:
    """How the prior's sun and sky gains are searched."""

    enabled: bool = True
    """Refit the prior's sun / sky split (False: the prior as :mod:`core.lighting.prior` made it)."""
    pixels: int = 4096
    """Random non-sky pixels per training frame rendered for the search (as the stage's
    ``eval_pixels``: the value measured; on the default scene's quick reconstruction the three
    parts took 163 s of a machine running two stages at once). Two unknowns: fewer would likely
    do, not measured yet."""
    sun_cap_deg: float = 10.0
    """Angular radius of the sun part around the prior's sun direction, degrees (the disc is
    1.5 deg; its glow belongs to it)."""
    gain_min: float = 0.1
    """Smallest gain searched (each part)."""
    gain_max: float = 10.0
    """Largest gain searched (each part)."""
    steps: int = 61
    """Gains per part, log-spaced over [gain_min, gain_max] (61: 8% apart)."""
    min_improvement: float = 0.01
    """The gains replace (1, 1) only when they lower the L1 by at least this share (0.01 = 1%):
    a flat optimum keeps the prior."""

    def __post_init__(self) -> None:
        bad = [n for n, ok in (("enabled", isinstance(self.enabled, bool)),
                               ("pixels", isinstance(self.pixels, int) and self.pixels >= 1),
                               ("sun_cap_deg", 0 < self.sun_cap_deg < 90),
                               ("gain_min", 0 < self.gain_min <= 1), ("gain_max", 1 <= self.gain_max <= 1e3),
                               ("steps", isinstance(self.steps, int) and 3 <= self.steps <= 1001),
                               ("min_improvement", 0 <= self.min_improvement < 1)) if not ok]
        if bad:
            raise ConfigError(f"PriorGainSettings: out of range: {', '.join(bad)} ({self})")


def split_map(env: np.ndarray, sun_dir: np.ndarray, held_weight: np.ndarray | None,
              sun_cap_deg: float) -> dict[str, np.ndarray]:
    """The map ``env`` ``[H, 2H, 3]`` as ``{"sun", "sky", "held"}`` parts that sum to it.

    Args:
        sun_dir: ``[3]`` world unit direction of the prior's sun.
        held_weight: ``[H, 2H]`` sky-evidence weight in [0, 1] at the map's resolution, or None.
    """
    env = np.asarray(env, np.float64)
    if env.ndim != 3 or env.shape[2] != 3 or env.shape[1] != 2 * env.shape[0]:
        raise ShapeError(f"env: expected [H, 2H, 3], got {env.shape}")
    sd = np.asarray(sun_dir, np.float64).reshape(3)
    if not np.isfinite(sd).all() or np.linalg.norm(sd) < 0.5:
        raise ConfigError(f"sun_dir: expected a finite unit direction, got {sun_dir!r}")
    h = env.shape[0]
    held = np.zeros((h, 2 * h), bool) if held_weight is None else np.asarray(held_weight) >= 0.5
    if held.shape != (h, 2 * h):
        raise ShapeError(f"held_weight: expected {(h, 2 * h)}, got {held.shape}")
    d = envmap_directions(h, 2 * h)
    sun = (d @ (sd / np.linalg.norm(sd)) > math.cos(math.radians(sun_cap_deg))) & ~held
    sky = ~sun & ~held
    z = np.zeros_like(env)
    return {"sun": np.where(sun[..., None], env, z), "sky": np.where(sky[..., None], env, z),
            "held": np.where(held[..., None], env, z)}


def search_gains(renders: dict[str, np.ndarray], target_ldr: np.ndarray, exposure: float, gamma: float,
                 settings: PriorGainSettings) -> dict:
    """Grid search of ``(g_sun, g_sky)`` minimising ``mean |clip(exposure (g_sun R_sun + g_sky R_sky
    + R_held), 0, 1)^(1/gamma) - target|``.

    Args:
        renders: ``{"sun", "sky", "held"}`` HDR renders ``[P, 3]`` of the parts (linear).
        target_ldr: ``[P, 3]`` the capture's LDR values in [0, 1].
    Returns ``{"gain_sun", "gain_sky", "l1_prior", "l1_best", "applied"}`` (``applied`` False
    when the best gains do not lower the L1 by ``min_improvement``: the gains are then 1).
    """
    t = np.asarray(target_ldr, np.float64)
    parts = {}
    for k in ("sun", "sky", "held"):
        if k not in renders:
            raise ConfigError(f"renders: missing part {k!r}")
        r = np.asarray(renders[k], np.float64)
        if r.shape != t.shape or r.ndim != 2 or r.shape[1] != 3:
            raise ShapeError(f"renders[{k!r}]: expected {t.shape} like target_ldr [P, 3], got {r.shape}")
        parts[k] = require_finite_np(r, f"renders[{k!r}]")
    if not (exposure > 0 and gamma > 0):
        raise ConfigError(f"exposure, gamma: expected > 0, got {exposure!r}, {gamma!r}")
    s = settings

    def l1(gs: float, gk: float) -> float:
        p = np.clip(exposure * (gs * parts["sun"] + gk * parts["sky"] + parts["held"]), 0.0, 1.0) ** (1.0 / gamma)
        return float(np.abs(p - t).mean())

    grid = np.exp(np.linspace(math.log(s.gain_min), math.log(s.gain_max), s.steps))
    l1_prior = l1(1.0, 1.0)
    best = (l1_prior, 1.0, 1.0)
    for gs in grid:
        for gk in grid:
            v = l1(float(gs), float(gk))
            if v < best[0]:
                best = (v, float(gs), float(gk))
    applied = best[0] < (1.0 - s.min_improvement) * l1_prior
    return {"gain_sun": best[1] if applied else 1.0, "gain_sky": best[2] if applied else 1.0,
            "l1_prior": l1_prior, "l1_best": best[0], "best_gain_sun": best[1], "best_gain_sky": best[2],
            "applied": bool(applied)}


__all__ = ["PriorGainSettings", "search_gains", "split_map"]
