"""Adaptive density control as in 3DGS: clone small Gaussians and split large ones where the
screen-space positional gradient is large, prune transparent or oversized ones, reset opacity
periodically, and never exceed a cap on the count."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from core.camera import Camera, require_one_camera
from core.errors import ShapeError
from core.gaussians import Gaussians, _logit
from core.rotations import quat_to_rotmat
from core.train.optim import GaussianAdam


@dataclass(frozen=True)
class DensityConfig:
    """Adaptive density control settings."""

    grad_threshold: float = 2e-4
    """Mean screen-space positional gradient (NDC units, as 3DGS) above which a Gaussian is
    densified."""
    percent_dense: float = 0.01
    """Gaussians larger than this fraction of the scene extent are split, smaller ones cloned."""
    prune_opacity: float = 0.005
    """Gaussians below this opacity are pruned."""
    prune_scale_fraction: float = 0.2
    """Gaussians larger than this fraction of the scene extent are pruned (after the first reset)."""
    opacity_reset_value: float = 0.01
    """Opacity after a reset."""
    max_gaussians: int = 200_000
    """Never grow beyond this many Gaussians: the highest-gradient candidates win."""
    split_factor: float = 1.6
    """Scale divisor for the two children of a split."""


class DensityController:
    """Accumulates gradient statistics between densification steps."""

    def __init__(self, cfg: DensityConfig, scene_extent: float, num: int):
        self.cfg = cfg
        self.extent = float(scene_extent)
        self._reset_stats(num)

    def _reset_stats(self, num: int) -> None:
        self.grad_accum = torch.zeros(num, dtype=torch.float64)
        self.count = torch.zeros(num, dtype=torch.float64)

    @torch.no_grad()
    def accumulate(self, means_grad: torch.Tensor | None, means: torch.Tensor, camera: Camera) -> None:
        """Add the screen-space (NDC) gradient norm of each Gaussian in front of the camera.

        means_grad: [N, 3] dL/dmean (world frame, per metre) or None (nothing to add); means:
        [N, 3] Gaussian centres, world metres; camera: the one :class:`core.camera.Camera` the
        gradient was rendered through (pose, ``fx, fy`` in pixels, image size).

        The rasterizer returns dL/dmean in world space; its screen-space counterpart is the
        gradient projected on the image plane scaled by depth / focal, converted to NDC units
        (half the image = 1) like 3DGS's mean2D gradient. Raises :class:`ConfigError` /
        :class:`ShapeError` naming ``camera`` (not one Camera) or ``means_grad`` (not [N, 3] like
        ``means``)."""
        require_one_camera(camera)
        if means_grad is None or len(means) == 0:
            return
        if means_grad.shape != means.shape:
            raise ShapeError(f"means_grad: expected {list(means.shape)} like means, got {list(means_grad.shape)}")
        fx, fy, width, height = camera.fx, camera.fy, camera.width, camera.height
        w2c = torch.linalg.inv(camera.cam_to_world.double())
        r = w2c[:3, :3].to(means.dtype)
        t = w2c[:3, 3].to(means.dtype)
        pc = means @ r.T + t
        z = pc[:, 2]
        gc = means_grad @ r.T  # gradient in camera axes
        vis = z > 0.2
        gx = gc[:, 0] * z / fx * (width / 2)
        gy = gc[:, 1] * z / fy * (height / 2)
        g2d = torch.sqrt(gx * gx + gy * gy).double()
        touched = vis & (means_grad.abs().sum(1) > 0)
        self.grad_accum[touched] += g2d[touched]
        self.count[touched] += 1

    @torch.no_grad()
    def densify_and_prune(self, opt: GaussianAdam, prune_large: bool,
                          max_gaussians: int | None = None) -> dict[str, int]:
        """Clone / split / prune in place on ``opt.g``; returns counts. ``max_gaussians``
        overrides the configured cap (a trainer with several containers shares one cap)."""
        cfg = self.cfg
        cap = cfg.max_gaussians if max_gaussians is None else int(max_gaussians)
        g = opt.g
        n = g.num
        avg = torch.where(self.count > 0, self.grad_accum / self.count.clamp_min(1), torch.zeros_like(self.count))
        scales = g.scales()
        smax = scales.max(1).values
        big = smax > cfg.percent_dense * self.extent
        cand = avg >= cfg.grad_threshold
        room = max(0, cap - n)
        clone = cand & ~big
        split = cand & big
        # cap: a split adds one net Gaussian (2 children replace the parent), a clone adds one
        want = int(clone.sum() + split.sum())
        if want > room:
            order = torch.argsort(avg, descending=True)
            chosen = torch.zeros(n, dtype=torch.bool)
            chosen[order[:room]] = True
            clone &= chosen
            split &= chosen
        opac = g.opacities()[:, 0]
        prune = opac < cfg.prune_opacity
        if prune_large:
            prune |= smax > cfg.prune_scale_fraction * self.extent
        prune |= split  # the parent of a split is replaced by its two children
        keep = ~prune
        t = g.tensors()
        add = {k: [] for k in t}
        if clone.any():
            for k in t:
                add[k].append(t[k][clone])
        if split.any():
            s = scales[split]
            rot = quat_to_rotmat(g.quats[split])
            for _ in range(2):
                offs = (rot @ (torch.randn_like(s) * s)[..., None])[..., 0]
                for k in t:
                    if k == "means":
                        add[k].append(t[k][split] + offs)
                    elif k == "log_scales":
                        add[k].append(torch.log(s / cfg.split_factor))
                    else:
                        add[k].append(t[k][split])
        n_added = sum(len(x) for x in add["means"])
        new = Gaussians(**{k: torch.cat([t[k].detach()[keep]] + [a.detach() for a in add[k]]) for k in t})
        opt.replace(new, keep, n_added)
        self._reset_stats(new.num)
        return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": int((prune & ~split).sum()),
                "total": new.num}

    @torch.no_grad()
    def reset_opacity(self, opt: GaussianAdam) -> None:
        """Clamp every opacity to at most ``opacity_reset_value`` (3DGS's periodic reset)."""
        g = opt.g
        cap = torch.as_tensor(_logit(torch.tensor(self.cfg.opacity_reset_value, dtype=g.dtype)))
        g.opacity_logits.copy_(torch.minimum(g.opacity_logits, cap))
        opt.reset_moments("opacity_logits")


def scene_extent(cam_centres: torch.Tensor) -> float:
    """3DGS's scene extent: 1.1 x the largest distance of a camera centre from their mean."""
    c = cam_centres.double()
    d = (c - c.mean(0)).norm(dim=1).max()
    return float(max(1.1 * float(d), 1.0)) if math.isfinite(float(d)) else 1.0
