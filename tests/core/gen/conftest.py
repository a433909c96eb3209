"""Fixtures of the generative-model tests: one torch thread (torch's OpenMP threads spin and
steal cores from other processes), small random-weight models exported once per session."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True)
def _one_torch_thread(one_torch_thread):
    yield


def randomize(model, scale: float = 0.05, seed: int = 0):
    """Perturb every parameter (the zero-initialised layers would make the net trivial)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(torch.randn(p.shape, generator=g) * scale)
    return model.eval()


@pytest.fixture(scope="session")
def small_models(tmp_path_factory):
    """Two forward models of different widths and one inverse model, random weights, exported."""
    torch.set_num_threads(1)
    from core.gen.nets import UNetSettings, build_model, export_onnx

    d = tmp_path_factory.mktemp("gen_models")
    out = {}
    torch.manual_seed(0)
    fa = randomize(build_model("forward_denoiser", UNetSettings(base_channels=8, emb_dim=32, env_channels=8), frames=2))
    fb = randomize(build_model("forward_denoiser", UNetSettings(base_channels=12, channel_mult=(1, 1, 2), blocks=2,
                                                                emb_dim=16, env_channels=4, temporal_mix=False), frames=3), seed=1)
    inv = randomize(build_model("inverse_gbuffer", UNetSettings(base_channels=8, emb_dim=32), frames=2), seed=2)
    out["fwd_a"] = (fa, export_onnx(fa, d / "fwd_a.onnx"))
    out["fwd_b"] = (fb, export_onnx(fb, d / "fwd_b.onnx"))
    out["inv"] = (inv, export_onnx(inv, d / "inv.onnx"))
    return out
