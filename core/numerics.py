"""Numerical guards used everywhere in ``core``: one place for eps constants and safe ops.

Each eps says why it has its value. Functions accept numpy arrays or torch tensors where noted;
the torch versions guard both branches of ``torch.where`` so no NaN leaks into gradients.
"""

from __future__ import annotations

import math

import numpy as np

from core.errors import NumericalError

#: Smallest squared length treated as non-zero when normalising a vector: float32 has ~7
#: significant digits, so below 1e-12 the direction of a vector is noise.
EPS_NORM_SQ = 1e-12
#: Divisor guard for pdfs and cosines: a pdf below this is treated as zero (sample rejected).
EPS_PDF = 1e-8
#: Guard for sqrt of quantities that are >= 0 in exact arithmetic but may round slightly below.
EPS_SQRT = 1e-12
#: Clamp for acos/asin inputs: keep away from +-1 so the derivative stays finite.
ACOS_CLAMP = 1.0 - 1e-7


def safe_sqrt_np(x: np.ndarray) -> np.ndarray:
    """sqrt(max(x, 0)): for quantities that are non-negative up to rounding."""
    return np.sqrt(np.maximum(x, 0.0))


def safe_normalize_np(v: np.ndarray, axis: int = -1, fallback: np.ndarray | None = None) -> np.ndarray:
    """Normalise ``v`` along ``axis``; vectors shorter than sqrt(EPS_NORM_SQ) become ``fallback``
    (default: +z unit vector when the axis has length 3, else zeros)."""
    v = np.asarray(v, dtype=np.float64 if np.asarray(v).dtype == np.float64 else np.float32)
    n2 = np.sum(v * v, axis=axis, keepdims=True)
    ok = n2 > EPS_NORM_SQ
    out = v / np.sqrt(np.where(ok, n2, 1.0))
    if fallback is None:
        fallback = np.zeros(v.shape[axis], dtype=v.dtype)
        if v.shape[axis] == 3:
            fallback[2] = 1.0
    shape = [1] * v.ndim
    shape[axis] = v.shape[axis]
    return np.where(ok, out, np.asarray(fallback, dtype=v.dtype).reshape(shape))


def clamped_acos_np(x: np.ndarray) -> np.ndarray:
    """acos with the input clamped to [-1, 1] (exactly: used for angles, not gradients)."""
    return np.arccos(np.clip(x, -1.0, 1.0))


def require_finite_np(x: np.ndarray, name: str) -> np.ndarray:
    """Raise :class:`NumericalError` naming ``name`` if ``x`` holds NaN or Inf; return ``x``."""
    arr = np.asarray(x)
    if arr.dtype.kind in "fc" and not np.all(np.isfinite(arr)):
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise NumericalError(f"{name}: {bad} non-finite value(s) (NaN or Inf)")
    return arr


# ---------------------------------------------------------------------------------------------
# torch versions (imported lazily so numpy-only users do not pay for torch)
# ---------------------------------------------------------------------------------------------

def safe_sqrt(x):
    """torch: sqrt(max(x, EPS_SQRT)) where x > EPS_SQRT else 0, with a finite gradient at 0."""
    import torch

    ok = x > EPS_SQRT
    return torch.where(ok, torch.sqrt(torch.where(ok, x, torch.ones_like(x))), torch.zeros_like(x))


def safe_normalize(v, dim: int = -1):
    """torch: v / |v| along ``dim``; zero-length vectors map to zero with zero gradient."""
    import torch

    n2 = (v * v).sum(dim=dim, keepdim=True)
    ok = n2 > EPS_NORM_SQ
    inv = torch.where(ok, torch.rsqrt(torch.where(ok, n2, torch.ones_like(n2))), torch.zeros_like(n2))
    return v * inv


def clamped_acos(x):
    """torch: acos(clamp(x, -ACOS_CLAMP, ACOS_CLAMP)) so the derivative stays finite."""
    import torch

    return torch.acos(torch.clamp(x, -ACOS_CLAMP, ACOS_CLAMP))


def require_finite(x, name: str):
    """torch or numpy: raise :class:`NumericalError` naming ``name`` if ``x`` has NaN/Inf."""
    try:
        import torch

        if isinstance(x, torch.Tensor):
            if x.is_floating_point() and not bool(torch.isfinite(x).all()):
                bad = int((~torch.isfinite(x)).sum())
                raise NumericalError(f"{name}: {bad} non-finite value(s) (NaN or Inf)")
            return x
    except ImportError:  # pragma: no cover - torch is a hard dependency of the project
        pass
    return require_finite_np(x, name)


PI = math.pi
