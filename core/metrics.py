"""Image metrics (torch): PSNR, SSIM, scale-invariant PSNR, angular error.

Images are [H, W, C] or [B, H, W, C] float tensors; values in [0, 1] unless stated.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from core.errors import ShapeError
from core.numerics import clamped_acos, safe_normalize

#: MSE floor of the PSNR: 1e-10 caps PSNR at 100 dB instead of +inf for identical images.
MSE_FLOOR = 1e-10


def _bhwc(x: torch.Tensor, name: str) -> torch.Tensor:
    if not isinstance(x, torch.Tensor) or x.dim() not in (3, 4):
        raise ShapeError(f"{name}: expected [H, W, C] or [B, H, W, C], got {getattr(x, 'shape', type(x))}")
    return x[None] if x.dim() == 3 else x


def psnr(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """PSNR in dB for a peak of 1. ``mask``: [H, W] or [B, H, W] bool, pixels to include."""
    p, t = _bhwc(pred, "pred"), _bhwc(target, "target")
    if p.shape != t.shape:
        raise ShapeError(f"pred {tuple(p.shape)} and target {tuple(t.shape)} differ")
    se = (p - t) ** 2
    if mask is not None:
        m = mask.reshape(se.shape[:-1]).to(se.dtype)[..., None].expand_as(se)
        mse = (se * m).sum() / m.sum().clamp_min(1)
    else:
        mse = se.mean()
    return -10.0 * torch.log10(mse.clamp_min(MSE_FLOOR))


def _gauss_window(size: int, sigma: float, channels: int, dtype, device) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    g = g / g.sum()
    w = (g[:, None] * g[None, :])[None, None]
    return w.expand(channels, 1, size, size).contiguous()


def ssim_map(pred: torch.Tensor, target: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Per-pixel SSIM [B, H, W] (Gaussian window 11, sigma 1.5, C1 = 0.01^2, C2 = 0.03^2; 'same'
    padding by reflection so the map covers every pixel). Differentiable."""
    p, t = _bhwc(pred, "pred"), _bhwc(target, "target")
    if p.shape != t.shape:
        raise ShapeError(f"pred {tuple(p.shape)} and target {tuple(t.shape)} differ")
    c = p.shape[-1]
    x = p.permute(0, 3, 1, 2)
    y = t.permute(0, 3, 1, 2)
    w = _gauss_window(window, sigma, c, p.dtype, p.device)
    pad = window // 2
    if min(x.shape[-2:]) <= pad:  # tiny images: no reflection possible
        mode = "replicate"
    else:
        mode = "reflect"

    def blur(z):
        return F.conv2d(F.pad(z, (pad, pad, pad, pad), mode=mode), w, groups=c)

    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return s.mean(1)


def ssim(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean SSIM (over ``mask`` pixels when given)."""
    s = ssim_map(pred, target)
    if mask is None:
        return s.mean()
    m = mask.reshape(s.shape).to(s.dtype)
    return (s * m).sum() / m.sum().clamp_min(1)


def si_psnr(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Scale-invariant PSNR (albedo metric): per channel, the least-squares scale of ``pred`` to
    ``target`` over the mask is applied before the PSNR."""
    p, t = _bhwc(pred, "pred"), _bhwc(target, "target")
    m = torch.ones(p.shape[:-1], dtype=torch.bool) if mask is None else mask.reshape(p.shape[:-1])
    mf = m.to(p.dtype)[..., None]
    num = (p * t * mf).sum(dim=(0, 1, 2))
    den = (p * p * mf).sum(dim=(0, 1, 2)).clamp_min(1e-12)
    return psnr((p * (num / den)).clamp(0, 1), t, m)


def angular_error_deg(n_pred: torch.Tensor, n_true: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean angle (degrees) between normal maps [..., 3] over ``mask``."""
    a = safe_normalize(n_pred)
    b = safe_normalize(n_true)
    ang = clamped_acos((a * b).sum(-1)) * (180.0 / math.pi)
    if mask is None:
        return ang.mean()
    m = mask.reshape(ang.shape).to(ang.dtype)
    return (ang * m).sum() / m.sum().clamp_min(1)
