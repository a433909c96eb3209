"""Helpers shared by the capture-layout adapters (private to :mod:`core.adapters`)."""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TypeVar

import numpy as np
from tqdm.auto import tqdm

from core.conventions import is_rigid
from core.errors import BundleError, ConfigError

T = TypeVar("T")

#: Tolerance of the rigidity check on imported poses. Text files written with ``%.18e`` are exact;
#: this also accepts poses printed with ~6 significant digits. Accepted rotations are then projected
#: onto the nearest rotation so products of several poses stay rigid to float64 precision.
RIGID_TOL = 1e-3

#: Image formats a bundle may hold as they are (schema: ``images/<frame_id>.png|.jpg``).
COPYABLE_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def rigid_or_error(m, path: str | Path, field: str | None = None) -> np.ndarray:
    """Return ``m`` as a float64 4x4 rigid transform (rotation re-orthonormalised) or raise a
    :class:`BundleError` naming ``path`` (and ``field``). A 3x4 matrix gets the row 0 0 0 1."""
    try:
        a = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError):
        raise BundleError("expected a 4x4 matrix of numbers", str(path), field) from None
    if a.shape == (3, 4):
        a = np.vstack([a, [0.0, 0.0, 0.0, 1.0]])
    if a.shape != (4, 4):
        raise BundleError(f"expected a 4x4 matrix, got shape {list(a.shape)}", str(path), field)
    if not np.all(np.isfinite(a)):
        raise BundleError("matrix contains NaN or Inf", str(path), field)
    if not is_rigid(a, tol=RIGID_TOL):
        det = float(np.linalg.det(a[:3, :3]))
        raise BundleError(
            "not a rigid transform (rotation must be orthonormal with det +1 and the last row "
            f"0 0 0 1; det of the 3x3 part is {det:.6g}, last row {a[3].tolist()})", str(path), field)
    u, _, vt = np.linalg.svd(a[:3, :3])
    out = a.copy()
    out[:3, :3] = u @ vt
    out[3] = [0.0, 0.0, 0.0, 1.0]
    return out


def read_numbers(path: Path, count: int, what: str) -> np.ndarray:
    """Read exactly ``count`` whitespace/comma separated numbers from a text file (float64)."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise BundleError(f"missing {what} file", str(path)) from None
    except (OSError, UnicodeDecodeError) as e:
        raise BundleError(f"cannot read {what} file: {e}", str(path)) from None
    tokens = [t for t in re.split(r"[\s,]+", text.strip()) if t]
    try:
        vals = np.array([float(t) for t in tokens], dtype=np.float64)
    except ValueError as e:
        raise BundleError(f"unparsable {what}: {e}", str(path)) from None
    if vals.size != count:
        raise BundleError(f"expected {count} numbers for the {what}, found {vals.size}", str(path))
    if not np.all(np.isfinite(vals)):
        raise BundleError(f"{what} contains NaN or Inf", str(path))
    return vals


def check_test_every(test_every: int | None) -> None:
    if test_every is None:
        return
    if isinstance(test_every, bool) or not isinstance(test_every, int) or test_every < 2:
        raise ConfigError(f"test_every: expected None or an integer >= 2, got {test_every!r}")


def split_for(position: int, test_every: int | None) -> str:
    """Split of the ``position``-th (0-based) time step: with ``test_every=N`` positions
    N-1, 2N-1, ... are "test" (the first step is always "train"), everything else "train"."""
    if test_every is None:
        return "train"
    return "test" if position % test_every == test_every - 1 else "train"


def safe_id(s: str) -> str:
    """A frame-id-safe version of ``s`` (letters, digits, ``-``, ``_``, ``.``)."""
    out = re.sub(r"[^A-Za-z0-9_.-]+", "_", s).strip("._")
    return out or "frame"


def progress(it: Iterable[T], *, enabled: bool, total: int | None = None, desc: str = "") -> Iterator[T]:
    """Wrap ``it`` in a tqdm bar when ``enabled``."""
    if not enabled:
        return iter(it)
    return iter(tqdm(it, total=total, desc=desc, unit="frame", leave=False))
