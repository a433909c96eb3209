"""The inverse model's G-buffer from frames as an ensemble mean: several noise samples of
:func:`core.gen.edm.generate`, on the frames and on their mirror image, averaged.

The shipped sampler is one Euler step from sigma 80 (:data:`core.gen.edm.GENERATE_SAMPLER`), so
each sample is the network's estimate of the mean G-buffer given one noise draw; that estimate
still varies with the draw and with the image's handedness. Averaging the members lowers the
variance (what the paper metrics - albedo si-PSNR, normal MAE, roughness / metallic RMSE - punish),
at one model call per member.

Mirroring (x -> W - 1 - x) is exact for the contract's inputs and outputs when the x components of
the camera-frame vectors change sign: the G-buffer normal's x (``inverse_gbuffer`` data space) and,
for contract 1.1's ``view`` input, the ray's x and the up direction's x. The mirrored member's
output is mirrored back and its normal x negated before the mean; the mean normal is renormalised
by the decoder downstream (:func:`core.gen.encoding.decode_gbuffer`).

Chosen on validation streets only (``benchmarks/train_generative.py``'s randomised ``val`` split and
the first generator's ``v9``): two seeds and the mirror (4 calls) against one call, candidate model
on val: albedo si-PSNR 16.93 -> 17.30 dB, normal MAE 14.9 -> 13.9 deg, metallic RMSE 0.212 -> 0.205;
shipped model on v9: 20.64 -> 21.17 dB, 8.6 -> 7.7 deg, roughness 0.136 -> 0.128.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Mapping

import torch

from core.errors import ConfigError
from core.gen import contract as C
from core.gen.edm import GENERATE_SAMPLER, Denoiser, SamplerSettings, generate

#: Channel of the G-buffer data space holding the camera-frame normal's x component.
NORMAL_X = C.GBUFFER_SLICES["normal"].start
#: Channels of the ``view`` input holding x components (the ray's and the up direction's).
VIEW_X = (0, 3)


@dataclass(frozen=True)
class EnsembleSettings:
    """How many members the G-buffer mean averages (members = ``seeds`` x (2 if ``mirror``))."""

    seeds: int = 2
    """Noise draws (sampler seeds 0 .. seeds - 1); >= 1."""
    mirror: bool = True
    """Also run every draw on the mirrored frames (and mirror the result back)."""

    def __post_init__(self) -> None:
        if int(self.seeds) != self.seeds or self.seeds < 1:
            raise ConfigError(f"seeds: need an integer >= 1, got {self.seeds!r}")

    @property
    def members(self) -> int:
        return self.seeds * (2 if self.mirror else 1)


#: One call: the plain sampler (what the models' first cards were measured with).
SINGLE = EnsembleSettings(seeds=1, mirror=False)


def mirror_inputs(cond: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The conditioning of the mirrored frames: every [.., C, H, W] tensor flipped along W, with
    the x channels of ``view`` negated."""
    out = {}
    for k, v in cond.items():
        m = torch.flip(v, dims=[-1]).clone()
        if k == "view":
            m[..., VIEW_X, :, :] *= -1
        out[k] = m
    return out


def mirror_gbuffer(x: torch.Tensor) -> torch.Tensor:
    """A [.., 9, H, W] data-space G-buffer of mirrored frames, mirrored back (normal x negated)."""
    m = torch.flip(x, dims=[-1]).clone()
    m[..., NORMAL_X, :, :] *= -1
    return m


def generate_gbuffer(denoiser: Denoiser, shape: tuple[int, int, int, int], cond: Mapping[str, torch.Tensor],
                     sampler: SamplerSettings | None = None,
                     ensemble: EnsembleSettings | None = None) -> torch.Tensor:
    """The ensemble-mean G-buffer [T, 9, H, W] (data space) of a clip.

    Args:
        denoiser: the inverse model (:class:`core.gen.edm.OnnxDenoiser` or a torch one).
        shape: (T, 9, H, W) of the output.
        cond: ``rgb`` [T, 3, H, W] and optionally ``view`` [T, 6, H, W] (contract 1.1).
        sampler: default :data:`core.gen.edm.GENERATE_SAMPLER`; its ``seed`` is replaced per draw.
        ensemble: default :class:`EnsembleSettings` (two draws, mirrored: 4 calls).
    """
    s = sampler or GENERATE_SAMPLER
    e = ensemble or EnsembleSettings()
    if len(shape) != 4 or shape[1] != C.GBUFFER_CHANNELS:
        raise ConfigError(f"shape: need (T, {C.GBUFFER_CHANNELS}, H, W), got {tuple(shape)}")
    mirrored = mirror_inputs(cond) if e.mirror else None
    acc = torch.zeros(shape, dtype=torch.float32)
    for seed in range(e.seeds):
        sd = replace(s, seed=s.seed + seed)
        acc += generate(denoiser, shape, cond, sd)
        if mirrored is not None:
            acc += mirror_gbuffer(generate(denoiser, shape, mirrored, sd))
    return acc / e.members


__all__ = ["EnsembleSettings", "SINGLE", "generate_gbuffer", "mirror_inputs", "mirror_gbuffer", "NORMAL_X", "VIEW_X"]
