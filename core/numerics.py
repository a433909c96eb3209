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
#: Floor of an accumulated opacity when a G-buffer layer is divided by it (the per-surface value
#: of an expected-value layer): below 1e-3 a pixel is sky and its quotient would be noise.
OPACITY_EPS = 1e-3
#: Clamp for acos/asin inputs: keep away from +-1 so the derivative stays finite.
ACOS_CLAMP = 1.0 - 1e-7


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


# ---------------------------------------------------------------------------------------------
# guards of the physically based rendering pass (core.pbr)
# ---------------------------------------------------------------------------------------------

#: Smallest GGX ``alpha = roughness^2`` used anywhere (i.e. roughness >= ~0.0316). GGX is a delta
#: at alpha = 0; at 1e-3 its peak D = 1 / (pi alpha^2) ~ 3.2e5 per sr and its square stays far
#: inside float32, while the lobe is narrower than one pixel of a 512x1024 environment map.
GGX_ALPHA_MIN = 1e-3
#: Smallest squared distance (m^2) between a shading point and a point light used in the 1/d^2
#: falloff: a light closer than 1 cm is treated as 1 cm away, so a light exactly at the shading
#: point gives a large but finite irradiance.
LIGHT_DIST_SQ_MIN = 1e-4
#: Largest ``intensity * max(color)`` of a local light (W/sr-like units): with LIGHT_DIST_SQ_MIN
#: and the GGX peak above, the contribution stays below ~1e25, inside float32.
LIGHT_INTENSITY_MAX = 1e15
#: Largest radiance an environment map may hold (a clear sun is ~1e5-1e9 in linear HDR units).
#: float32 ends at 3.4e38: a bilinear lookup of a texel near it rounds to Inf, and so does
#: exp(log(x)) of the log-space parameterisation; at 1e15, times the GGX peak (~3.2e5) and the
#: samples of a frame (~1e7), sums stay below 1e28, far inside float32.
ENV_RADIANCE_MAX = 1e15
#: Floor of an environment map's radiance in its log-space parameterisation: log(0) is -inf,
#: so zero pixels are stored as log(1e-8) (1e-8 is far below any visible radiance).
LOG_RADIANCE_FLOOR = 1e-8


def safe_div(a, b, eps: float = EPS_PDF):
    """torch: ``a / b`` where ``|b| > eps``, else 0; both branches guarded (finite gradients)."""
    import torch

    ok = b.abs() > eps
    return torch.where(ok, a / torch.where(ok, b, torch.ones_like(b)), torch.zeros_like(a * b))


def smoothstep(edge0, edge1, x):
    """torch: Hermite ``3t^2 - 2t^3`` of ``t = clamp((x - edge0) / (edge1 - edge0), 0, 1)``.

    ``edge1 <= edge0`` (an empty interval) is a hard step ``x >= edge0``, never a division by 0.
    Edges may be tensors broadcasting with ``x``."""
    import torch

    e0 = torch.as_tensor(edge0, dtype=x.dtype, device=x.device)
    e1 = torch.as_tensor(edge1, dtype=x.dtype, device=x.device)
    width = e1 - e0
    ok = width > EPS_PDF
    t = torch.where(ok, (x - e0) / torch.where(ok, width, torch.ones_like(width)), (x >= e0).to(x.dtype))
    t = t.clamp(0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)
