"""The bundled HDRI library (``data/hdri/``: six real CC0 outdoor maps, 512x1024) and rotation.

``load_hdri("city", rotation_deg=45)`` reads a bundled map by name (or any .exr/.hdr path) and
rotates it about +z by whole columns (exact): a feature at azimuth phi moves to phi + degrees.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from core.errors import ConfigError
from core.io.envmap_file import read_envmap

#: Where the bundled real HDRIs live (CC0, see data/hdri/README.md).
HDRI_DIR = Path(__file__).resolve().parents[2] / "data" / "hdri"


def hdri_names() -> list[str]:
    """Names of the bundled HDRIs."""
    return sorted(q.stem for q in HDRI_DIR.glob("*.exr"))


def resolve_hdri(name_or_path: str) -> Path:
    """A bundled HDRI name (``city``) or a path to an .exr/.hdr file; ConfigError naming the
    bundled names when neither."""
    p = Path(str(name_or_path))
    if p.suffix.lower() in (".exr", ".hdr"):
        if not p.is_file():
            raise ConfigError(f"envmap: file not found: {p}")
        return p
    cand = HDRI_DIR / f"{name_or_path}.exr"
    if not cand.is_file():
        raise ConfigError(f"envmap: unknown environment map {name_or_path!r} (bundled: {hdri_names()})")
    return cand


def column_shift(env: np.ndarray, degrees: float) -> int:
    """Whole columns a rotation by ``degrees`` moves the map."""
    return int(round(degrees / 360.0 * env.shape[1])) % env.shape[1]


def rotate_equirect(env: np.ndarray, degrees: float) -> np.ndarray:
    """Rotate an equirect map about +z by ``degrees`` (counter-clockwise seen from above), rounded
    to whole columns so the result is exact."""
    return np.roll(env, -column_shift(env, degrees), axis=1)


def load_hdri(name_or_path: str, rotation_deg: float = 0.0) -> np.ndarray:
    """[H, W, 3] float32 linear radiance of a bundled HDRI or file, rotated."""
    return rotate_equirect(read_envmap(resolve_hdri(name_or_path)), rotation_deg)


__all__ = ["HDRI_DIR", "hdri_names", "resolve_hdri", "rotate_equirect", "column_shift", "load_hdri"]
