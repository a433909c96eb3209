"""Denoiser backends: OIDN improves a Monte-Carlo-noisy frame; diffusion fallback policy."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from core.errors import ConfigError, ModelLoadError, NumericalError, ShapeError
from core.synth.gen_data import degrade_mc
from core.gen.denoise import DenoiseSettings, denoise, surface_lowpass
from core.gen.edm import SamplerSettings
from core.tonemap import hdr_to_ldr

REPO = Path(__file__).resolve().parents[3]
SCENE = REPO / "data" / "scenes" / "default"


@pytest.fixture(scope="module")
def frame():
    from core.bundle import open_bundle

    b = open_bundle(SCENE, validate=False)
    fr = b.frames("test")[0]
    return b.load_ground_truth(fr), fr.cam_to_world, b.load_envmap()


def _psnr(a, b):
    return float(-10 * np.log10(np.mean((np.asarray(a, np.float64) - b) ** 2)))


@pytest.mark.parametrize("hdr", [False, True])
def test_oidn_improves_psnr_on_mc_noise(frame, hdr):
    gt, _, _ = frame
    noisy = degrade_mc(gt["rgb"], 4, np.random.default_rng(0))
    clean_ldr = hdr_to_ldr(gt["rgb"])
    inp = noisy if hdr else hdr_to_ldr(noisy)
    res = denoise(inp, gt["albedo"], gt["normal"], backend="oidn", hdr=hdr, settings=DenoiseSettings(threads=1))
    out = hdr_to_ldr(res.frames[0]) if hdr else res.frames[0]
    before, after = _psnr(hdr_to_ldr(noisy), clean_ldr), _psnr(out, clean_ldr)
    assert res.backend == "oidn" and res.fallback_reason is None
    assert after > before + 4.0, (before, after)  # measured: 15.1 -> 22.4 (HDR), 22.9 (LDR) dB


def test_none_backend_and_bad_input(frame):
    gt, _, _ = frame
    ldr = hdr_to_ldr(gt["rgb"])
    res = denoise(ldr, gt["albedo"], gt["normal"])
    assert res.backend == "none" and np.array_equal(res.frames[0], ldr)
    with pytest.raises(ConfigError, match="backend"):
        denoise(ldr, gt["albedo"], gt["normal"], backend="magic")
    bad = ldr.copy()
    bad[3, 4, 0] = np.nan
    with pytest.raises(NumericalError, match="frames"):
        denoise(bad, gt["albedo"], gt["normal"], backend="oidn", fallback="none")
    with pytest.raises(ShapeError, match="albedo"):
        denoise(ldr, gt["albedo"][:10], gt["normal"], backend="oidn")
    with pytest.raises(NumericalError, match="LDR values"):
        denoise(gt["rgb"] * 10, gt["albedo"], gt["normal"])


def test_diffusion_missing_model_raises_or_falls_back(frame, tmp_path):
    gt, c2w, env = frame
    ldr = hdr_to_ldr(gt["rgb"])
    kw = dict(gbuffer={k: gt[k] for k in ("depth", "roughness", "metallic")}, cam_to_world=c2w, env=env,
              settings=DenoiseSettings(threads=1, model_path=str(tmp_path / "missing_fwd.onnx")))
    with pytest.raises(ModelLoadError, match="missing_fwd.onnx"):
        denoise(ldr, gt["albedo"], gt["normal"], backend="diffusion", **kw)
    res = denoise(ldr, gt["albedo"], gt["normal"], backend="diffusion", fallback="oidn", **kw)
    assert res.backend == "oidn" and res.requested == "diffusion" and "missing_fwd.onnx" in res.fallback_reason
    corrupt = tmp_path / "corrupt_fwd.onnx"
    corrupt.write_bytes(b"garbage" * 100)
    kw["settings"] = DenoiseSettings(threads=1, model_path=str(corrupt))
    res = denoise(ldr, gt["albedo"], gt["normal"], backend="diffusion", fallback="none", **kw)
    assert res.backend == "none" and "corrupt_fwd.onnx" in res.fallback_reason


def test_diffusion_backend_runs_a_model(frame, small_models):
    gt, c2w, env = frame
    ldr = hdr_to_ldr(gt["rgb"])[:40, :64]
    sub = lambda a: np.asarray(a)[:40, :64]  # noqa: E731
    frames = np.stack([ldr, ldr])
    res = denoise(frames, np.stack([sub(gt["albedo"])] * 2), np.stack([sub(gt["normal"])] * 2), backend="diffusion",
                  gbuffer={k: np.stack([sub(gt[k])] * 2) for k in ("depth", "roughness", "metallic")},
                  cam_to_world=np.stack([c2w, c2w]), env=env,
                  settings=DenoiseSettings(threads=1, model_path=str(small_models["fwd_a"][1]),
                                           sampler=SamplerSettings(steps=2)))
    assert res.backend == "diffusion" and res.frames.shape == (2, 40, 64, 3)
    assert res.frames.min() >= 0 and res.frames.max() <= 1
    assert np.abs(res.frames[0] - res.frames[1]).max() < 1e-5  # same input, shared noise: same output


def _diffusion(frame, small_models, **settings):
    """The diffusion backend on the top-left 40 x 64 crop of a test frame (sky and surface)."""
    gt, c2w, env = frame
    ldr = hdr_to_ldr(gt["rgb"])[:40, :64]
    sub = lambda a: np.asarray(a)[:40, :64]  # noqa: E731
    out = denoise(ldr[None], sub(gt["albedo"])[None], sub(gt["normal"])[None], backend="diffusion",
                  gbuffer={k: sub(gt[k])[None] for k in ("depth", "roughness", "metallic")},
                  cam_to_world=c2w[None], env=env,
                  settings=DenoiseSettings(threads=1, model_path=str(small_models["fwd_a"][1]),
                                           sampler=SamplerSettings(steps=2), **settings)).frames[0]
    sky = np.linalg.norm(sub(gt["normal"]), axis=-1) < 0.5
    assert 0 < sky.mean() < 1  # the crop holds sky and surface
    return out, ldr.astype(np.float32), sky


def test_diffusion_keeps_the_sky_and_only_the_sky(frame, small_models):
    """Sky pixels (zero normal: the map itself, noise-free) keep the start frame; the surface
    pixels are the model's, the same with and without ``keep_sky``."""
    kw = dict(diffusion_start="input", correction_sigma_px=0.0)
    kept, ldr, sky = _diffusion(frame, small_models, keep_sky=True, **kw)
    model, _, _ = _diffusion(frame, small_models, keep_sky=False, **kw)
    assert np.array_equal(kept[sky], ldr[sky])
    assert np.abs(model[sky] - ldr[sky]).max() > 1e-3  # the model alone changes the sky
    assert np.allclose(kept[~sky], model[~sky], atol=1e-6)


def test_diffusion_from_oidn_keeps_oidns_detail(frame, small_models):
    """The default recipe: SDEdit of OIDN's result, the model's change low-passed. What it adds
    to OIDN's frame is smooth (its own change is not), and the sky is OIDN's."""
    gt = frame[0]
    sub = lambda a: np.asarray(a)[:40, :64]  # noqa: E731
    out, ldr, sky = _diffusion(frame, small_models)
    oidn = denoise(ldr[None], sub(gt["albedo"])[None], sub(gt["normal"])[None], backend="oidn",
                   settings=DenoiseSettings(threads=1)).frames[0]
    raw, _, _ = _diffusion(frame, small_models, correction_sigma_px=0.0)

    def detail(x):  # mean |x - its 3x3 box mean| over the surface's interior
        from scipy.ndimage import uniform_filter

        return float(np.abs(x - uniform_filter(x, (3, 3, 1)))[1:-1, 1:-1][~sky[1:-1, 1:-1]].mean())

    assert np.array_equal(out[sky], oidn[sky])
    assert detail(raw - oidn) > 1e-3  # the untrained model adds grain ...
    assert detail(out - oidn) < 0.2 * detail(raw - oidn)  # ... which the low-pass removes


def test_surface_lowpass_keeps_constants_and_ignores_the_sky():
    x = np.full((1, 24, 24, 3), 0.2, np.float32)
    x[:, :8] = 5.0  # the sky's value, far off
    surface = np.ones((1, 24, 24), bool)
    surface[:, :8] = False
    y = surface_lowpass(x, surface, 4.0)
    assert np.allclose(y[:, 8:], 0.2, atol=1e-5)  # no sky bleeding in
    assert np.all(y[:, :8] == 0.0)
    rng = np.random.default_rng(0)
    noise = rng.normal(0.0, 0.1, (1, 64, 64, 3)).astype(np.float32)
    assert surface_lowpass(noise, np.ones((1, 64, 64), bool), 4.0).std() < 0.2 * noise.std()
    with pytest.raises(ShapeError, match="surface"):
        surface_lowpass(x, surface[0], 4.0)


@pytest.mark.parametrize("bad", [dict(keep_sky="yes"), dict(diffusion_start="raw"),
                                 dict(correction_sigma_px=-1.0), dict(correction_sigma_px=float("nan"))])
def test_diffusion_settings_are_validated(bad):
    with pytest.raises(ConfigError, match=next(iter(bad))):
        DenoiseSettings(**bad)
