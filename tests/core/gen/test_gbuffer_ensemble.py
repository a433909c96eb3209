"""core.gen.gbuffer_ensemble: the mirrored member undoes its mirror exactly (normal x, ray x, up x
signs), the noise draws are averaged, and bad settings are refused."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from core.errors import ConfigError
from core.gen import contract as C
from core.gen.edm import GENERATE_SAMPLER, generate
from core.gen.gbuffer_ensemble import (SINGLE, EnsembleSettings, generate_gbuffer, mirror_gbuffer, mirror_inputs)

T, H, W = 2, 6, 10
SHAPE = (T, C.GBUFFER_CHANNELS, H, W)


def _cond(seed=0):
    g = torch.Generator().manual_seed(seed)
    return {"rgb": torch.rand((T, 3, H, W), generator=g) * 2 - 1, "view": torch.randn((T, 6, H, W), generator=g)}


def _equivariant(x, sigma, cond):
    """A per-pixel 'model' that commutes with mirroring: albedo from rgb, normal = the view ray
    (x component follows the ray's), other channels from rgb; ignores the noise."""
    rgb, view = cond["rgb"], cond["view"]
    n = view[:, :, 0:3]
    out = torch.cat([rgb, rgb[:, :, :1] * 0.5, rgb[:, :, 1:2] * 0.25, n, rgb[:, :, 2:3]], dim=2)
    assert out.shape == x.shape
    return out


def _noise_only(x, sigma, cond):
    """A 'model' whose output is its (scaled) noisy input: the ensemble must average the draws."""
    return x / sigma.reshape(-1, 1, 1, 1, 1)


def test_mirror_twice_is_identity_and_flips_the_x_channels():
    cond = _cond()
    back = mirror_inputs(mirror_inputs(cond))
    for k in cond:
        assert torch.equal(back[k], cond[k])
    m = mirror_inputs(cond)["view"]
    assert torch.equal(m[:, 0], -torch.flip(cond["view"][:, 0], dims=[-1]))
    assert torch.equal(m[:, 1], torch.flip(cond["view"][:, 1], dims=[-1]))
    assert torch.equal(m[:, 3], -torch.flip(cond["view"][:, 3], dims=[-1]))
    g = torch.randn(SHAPE)
    assert torch.equal(mirror_gbuffer(mirror_gbuffer(g)), g)


def test_an_equivariant_model_gives_the_same_mean_as_one_call():
    cond = _cond(1)
    one = generate(_equivariant, SHAPE, cond, GENERATE_SAMPLER)
    for e in (EnsembleSettings(seeds=1, mirror=True), EnsembleSettings(seeds=3, mirror=True)):
        assert torch.allclose(generate_gbuffer(_equivariant, SHAPE, cond, GENERATE_SAMPLER, e), one, atol=1e-4)  # float32 Euler step from sigma 80


def test_a_wrong_sign_would_show():
    """The same check fails when the mirrored output's normal x is not negated back."""
    cond = _cond(2)
    one = generate(_equivariant, SHAPE, cond, GENERATE_SAMPLER)
    raw = torch.flip(generate(_equivariant, SHAPE, mirror_inputs(cond), GENERATE_SAMPLER), dims=[-1])
    assert not torch.allclose((one + raw) / 2, one, atol=1e-3)


def test_draws_are_averaged():
    cond = _cond(3)
    plain = [generate(_noise_only, SHAPE, cond, replace(GENERATE_SAMPLER, seed=s)) for s in (0, 1)]
    got = generate_gbuffer(_noise_only, SHAPE, cond, GENERATE_SAMPLER, EnsembleSettings(seeds=2, mirror=False))
    assert torch.allclose(got, (plain[0] + plain[1]) / 2, atol=1e-6)
    assert torch.allclose(generate_gbuffer(_noise_only, SHAPE, cond, GENERATE_SAMPLER, SINGLE), plain[0], atol=1e-6)
    assert got.std() < plain[0].std() * 0.85  # two independent draws: variance halves


@pytest.mark.parametrize("seeds", [0, -1, 1.5])
def test_bad_seeds(seeds):
    with pytest.raises(ConfigError, match="seeds"):
        EnsembleSettings(seeds=seeds)


def test_bad_shape():
    with pytest.raises(ConfigError, match="shape"):
        generate_gbuffer(_equivariant, (T, 3, H, W), _cond())
