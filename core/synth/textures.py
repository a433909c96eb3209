"""Procedural albedo textures of the randomised streets (numpy, deterministic from a seed).

An :class:`AlbedoTexture` is a small frozen description (pattern, base colour, noise, seed,
repeat size); :func:`texture_image` turns it into a linear-albedo bitmap [H, W, 3] that the
Mitsuba backend hands to a ``bitmap`` texture (``raw``: linear, bilinear, repeating). The same
Mitsuba texture object is evaluated for the ground-truth albedo G-buffer, so the rendered frames
and the ground truth agree texel for texel.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

#: Facade palettes: linear-albedo base colours (low, high per channel) and the patterns used.
PALETTES: dict[str, dict] = {
    "plaster": {"lo": (0.45, 0.42, 0.36), "hi": (0.78, 0.74, 0.66), "patterns": ("noise", "panels")},
    "brick": {"lo": (0.22, 0.08, 0.05), "hi": (0.48, 0.22, 0.13), "patterns": ("bricks",)},
    "concrete": {"lo": (0.22, 0.22, 0.21), "hi": (0.50, 0.49, 0.47), "patterns": ("panels", "noise")},
    "sandstone": {"lo": (0.45, 0.34, 0.20), "hi": (0.66, 0.52, 0.34), "patterns": ("blocks", "noise")},
    "pastel": {"lo": (0.35, 0.35, 0.35), "hi": (0.85, 0.80, 0.80), "patterns": ("noise", "panels"),
               "saturate": True},
    "dark": {"lo": (0.04, 0.04, 0.045), "hi": (0.14, 0.13, 0.13), "patterns": ("panels", "noise")},
}

PATTERNS = ("noise", "bricks", "blocks", "panels", "tiles", "asphalt")


@dataclass(frozen=True)
class AlbedoTexture:
    """A procedural albedo texture. ``albedo`` is the base colour (linear), ``noise`` the relative
    amplitude of the spatial noise, ``repeat_m`` the metres one repeat covers, ``seed`` fixes the
    pattern, ``size`` the bitmap's side in texels."""

    pattern: str
    albedo: tuple[float, float, float]
    noise: float
    repeat_m: float
    seed: int
    size: int = 64


def _fbm(rng: np.random.Generator, n: int, octaves: int = 4) -> np.ndarray:
    """Tileable fractal value noise [n, n] with zero mean and unit-ish amplitude."""
    out = np.zeros((n, n))
    amp, total = 1.0, 0.0
    for o in range(octaves):
        g = 2 ** (o + 2)
        grid = rng.standard_normal((g, g))
        # bilinear upsampling with wrap-around (tileable)
        x = np.arange(n) * g / n
        i0 = np.floor(x).astype(int)
        t = x - i0
        i1 = (i0 + 1) % g
        rows = grid[i0] * (1 - t)[:, None] + grid[i1] * t[:, None]
        up = rows[:, i0] * (1 - t)[None, :] + rows[:, i1] * t[None, :]
        out += amp * up
        total += amp
        amp *= 0.5
    return out / total


def _mortar(n: int, rows: int, cols: int, offset: bool, line: float) -> tuple[np.ndarray, np.ndarray]:
    """(mortar mask [n, n] bool, unit id [n, n]) of a running-bond grid."""
    y, x = np.mgrid[0:n, 0:n] / n
    r = np.floor(y * rows)
    xs = x * cols + (0.5 * (r % 2) if offset else 0.0)
    c = np.floor(xs) % cols
    fy, fx = (y * rows) % 1.0, xs % 1.0
    mortar = (fy < line * rows / 2) | (fy > 1 - line * rows / 2) | (fx < line * cols / 4) | (fx > 1 - line * cols / 4)
    return mortar, r * cols + c


@lru_cache(maxsize=256)
def _texture_image(tex: AlbedoTexture) -> np.ndarray:
    rng = np.random.default_rng(tex.seed)
    n = tex.size
    base = np.asarray(tex.albedo, np.float64)
    mod = 1.0 + tex.noise * _fbm(rng, n)
    img = base[None, None, :] * mod[..., None]
    if tex.pattern in ("bricks", "blocks", "tiles"):
        rows, cols = {"bricks": (16, 4), "blocks": (6, 3), "tiles": (4, 4)}[tex.pattern]
        mortar, unit = _mortar(n, rows, cols, tex.pattern != "tiles", 0.012)
        # each brick/block its own shade
        shade = 1.0 + 0.5 * tex.noise * rng.standard_normal(int(unit.max()) + 1)
        img = img * shade[unit.astype(int)][..., None]
        mortar_col = np.full(3, float(np.clip(base.mean() * 1.6 + 0.1, 0.2, 0.7)))
        img = np.where(mortar[..., None], mortar_col, img)
    elif tex.pattern == "panels":
        mortar, unit = _mortar(n, 2, 2, False, 0.02)
        shade = 1.0 + 0.3 * tex.noise * rng.standard_normal(int(unit.max()) + 1)
        img = img * shade[unit.astype(int)][..., None]
        img = np.where(mortar[..., None], img * 0.6, img)
    elif tex.pattern == "asphalt":
        speck = rng.uniform(size=(n, n)) < 0.04
        img = np.where(speck[..., None], img * 1.8, img)
    elif tex.pattern != "noise":
        raise ValueError(tex.pattern)
    return np.clip(img, 0.01, 0.95).astype(np.float32)


def texture_image(tex: AlbedoTexture) -> np.ndarray:
    """Linear albedo [size, size, 3] float32 in [0.01, 0.95] (tileable; a copy)."""
    return _texture_image(tex).copy()


def palette_colour(rng: np.random.Generator, palette: str) -> tuple[float, float, float]:
    """A base colour drawn from ``palette`` (pastel: a saturated hue at high value)."""
    p = PALETTES[palette]
    if p.get("saturate"):
        hue = rng.uniform()
        rgb = 0.5 + 0.5 * np.cos(2 * np.pi * (hue + np.array([0.0, 1 / 3, 2 / 3])))
        v = rng.uniform(0.55, 0.85)
        c = v * (0.55 + 0.45 * rgb)
    else:
        lo, hi = np.asarray(p["lo"]), np.asarray(p["hi"])
        t = rng.uniform()
        c = lo + t * (hi - lo) + rng.uniform(-0.02, 0.02, 3)
    return tuple(float(x) for x in np.clip(c, 0.02, 0.9).round(4))


def planar_uvs(vertices: np.ndarray, faces: np.ndarray, repeat_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unshare vertices and give each face a planar projection along its dominant axis, in
    repeats of ``repeat_m`` metres. Returns (vertices [3F, 3], faces [F, 3], uvs [3F, 2])."""
    v = np.asarray(vertices, np.float64)[np.asarray(faces).reshape(-1)].reshape(-1, 3, 3)
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    axis = np.argmax(np.abs(n), axis=1)
    pick = np.array([[1, 2], [0, 2], [0, 1]])[axis]  # x-facing: (y, z); y-facing: (x, z); z: (x, y)
    uv = np.take_along_axis(v, pick[:, None, :].repeat(3, 1), axis=2) / repeat_m
    F = len(v)
    return (v.reshape(-1, 3).astype(np.float32), np.arange(3 * F, dtype=np.uint32).reshape(F, 3),
            uv.reshape(-1, 2).astype(np.float32))
