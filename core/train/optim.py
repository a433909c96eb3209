"""Adam over the fields of a :class:`Gaussians`, with moment surgery for densification.

torch.optim keeps its state keyed by tensor identity, which clone/split/prune break; this small
optimiser keeps the first and second moments next to each field so that adding and removing
Gaussians edits parameters and moments together.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from core.errors import ConfigError
from core.gaussians import Gaussians


@dataclass(frozen=True)
class GaussianLR:
    """Learning rates per Gaussian field (3DGS-like defaults, for a scene of ~100 m)."""

    means: float = 1.6e-4 * 10
    """Position, metres per step (3DGS: 1.6e-4 times the scene extent)."""
    quats: float = 1e-3
    """Rotation quaternion."""
    log_scales: float = 5e-3
    """Log-scale."""
    opacity_logits: float = 5e-2
    """Opacity logit."""
    normals: float = 1e-3
    """Normal vector."""
    color_logits: float = 1e-2
    """Colour logits."""
    albedo_logits: float = 1e-2
    """Albedo logits."""
    roughness_logits: float = 1e-2
    """Roughness logit."""
    metallic_logits: float = 1e-2
    """Metallic logit."""
    view_dep: float = 2.5e-3
    """View-dependent colour matrix (3DGS: the higher SH bands learn 20x slower than the base)."""


class GaussianAdam:
    """Adam (beta 0.9/0.999, eps 1e-15 as 3DGS) on every field of a Gaussians container."""

    def __init__(self, g: Gaussians, lr: GaussianLR = GaussianLR(), betas=(0.9, 0.999), eps: float = 1e-15):
        self.g = g
        self.lr = {k: getattr(lr, k) for k in g.tensors()}
        self.betas = betas
        self.eps = eps
        self.step_count = 0
        self.m = {k: torch.zeros_like(v) for k, v in g.tensors().items()}
        self.v = {k: torch.zeros_like(v) for k, v in g.tensors().items()}
        g.requires_grad_(True)

    def zero_grad(self) -> None:
        for t in self.g.tensors().values():
            t.grad = None

    @torch.no_grad()
    def step(self, lr_scale: dict[str, float] | None = None) -> None:
        self.step_count += 1
        b1, b2 = self.betas
        c1 = 1 - b1 ** self.step_count
        c2 = 1 - b2 ** self.step_count
        for k, p in self.g.tensors().items():
            if p.grad is None:
                continue
            grad = torch.nan_to_num(p.grad, nan=0.0, posinf=0.0, neginf=0.0)
            self.m[k].mul_(b1).add_(grad, alpha=1 - b1)
            self.v[k].mul_(b2).addcmul_(grad, grad, value=1 - b2)
            lr = self.lr[k] * (lr_scale or {}).get(k, 1.0)
            p.sub_(lr * (self.m[k] / c1) / ((self.v[k] / c2).sqrt() + self.eps))

    # -- surgery -------------------------------------------------------------------------------
    def replace(self, new: Gaussians, keep: torch.Tensor, n_added: int) -> None:
        """Swap in ``new`` = old[keep] followed by ``n_added`` fresh Gaussians; moments of kept
        rows move with them, new rows start at zero."""
        if new.num != int(keep.sum() if keep.dtype == torch.bool else len(keep)) + n_added:
            raise ConfigError("new: row count does not match keep + n_added")
        for k in self.m:
            z = torch.zeros(n_added, self.m[k].shape[1], dtype=self.m[k].dtype)
            self.m[k] = torch.cat([self.m[k][keep], z])
            self.v[k] = torch.cat([self.v[k][keep], z.clone()])
        self.g = new
        new.requires_grad_(True)

    def reset_moments(self, field: str, rows: torch.Tensor | None = None) -> None:
        """Zero the moments of one field (e.g. opacity after an opacity reset)."""
        if rows is None:
            self.m[field].zero_()
            self.v[field].zero_()
        else:
            self.m[field][rows] = 0
            self.v[field][rows] = 0
