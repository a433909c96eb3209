"""The scene corrector (core.gen.scene_corrector): identity at the start, learns a residual that
is a function of its inputs, resumes exactly, and rejects bad input by name."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from core.errors import ModelLoadError, NumericalError, ShapeError
from core.gen.scene_corrector import (FEATURES, CorrectorSettings, SceneCorrector, apply_corrector, fit_corrector,
                                      frame_features, light_fingerprint, load_corrector,
                                      save_corrector)


def _gbuffers(rng, h=24, w=32):
    n = rng.normal(size=(h, w, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return {"albedo": rng.uniform(0, 1, (h, w, 3)).astype(np.float32), "normal": n,
            "roughness": rng.uniform(0, 1, (h, w, 1)).astype(np.float32),
            "metallic": rng.uniform(0, 1, (h, w, 1)).astype(np.float32),
            "opacity": np.ones((h, w, 1), np.float32), "depth": rng.uniform(1, 30, (h, w, 1)).astype(np.float32)}


def _frames(seed, count, h=24, w=32):
    """Features of smooth random frames and targets that darken the frame where albedo red is high:
    a residual that only the G-buffers predict."""
    rng = np.random.default_rng(seed)
    xs, ys = [], []
    for _ in range(count):
        gb = _gbuffers(rng, h, w)
        ldr = rng.uniform(0.2, 0.8, (h, w, 3)).astype(np.float32)
        xs.append(frame_features(ldr, gb, np.eye(3)))
        ys.append(np.clip(ldr * (1.0 - 0.5 * gb["albedo"][..., :1]), 0, 1).astype(np.float32))
    return xs, ys


def test_features_layout_and_camera_frame():
    rng = np.random.default_rng(0)
    gb = _gbuffers(rng)
    ldr = rng.uniform(0, 1, (24, 32, 3)).astype(np.float32)
    rot = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], np.float32)  # world -> camera: 90 deg about z
    f = frame_features(ldr, gb, rot)
    assert f.shape == (24, 32, len(FEATURES)) and f.dtype == np.float32
    np.testing.assert_allclose(f[..., :3], ldr)
    np.testing.assert_allclose(f[..., 6:9], gb["normal"] @ rot.T, atol=1e-5)
    np.testing.assert_allclose(f[..., 12:13], np.log1p(gb["depth"]), rtol=1e-6)


def test_features_name_a_missing_or_misshapen_layer():
    rng = np.random.default_rng(0)
    gb = _gbuffers(rng)
    ldr = np.zeros((24, 32, 3), np.float32)
    with pytest.raises(ShapeError, match="metallic"):
        frame_features(ldr, {k: v for k, v in gb.items() if k != "metallic"}, np.eye(3))
    with pytest.raises(ShapeError, match="depth"):
        frame_features(ldr, {**gb, "depth": gb["depth"][:10]}, np.eye(3))
    with pytest.raises(ShapeError, match="world_to_cam"):
        frame_features(ldr, gb, np.eye(4))
    bad = {**gb, "depth": np.full_like(gb["depth"], np.inf)}
    with pytest.raises(NumericalError):
        frame_features(ldr, bad, np.eye(3))


def test_starts_as_the_identity():
    xs, _ = _frames(0, 1)
    out = apply_corrector(SceneCorrector(8), xs[0])
    np.testing.assert_allclose(out, np.clip(xs[0][..., :3], 0, 1), atol=1e-7)


def test_learns_a_residual_of_its_inputs_on_held_out_frames():
    xs, ys = _frames(1, 6)
    tx, ty = _frames(2, 2)
    net, _ = fit_corrector(xs, ys, CorrectorSettings(width=16, steps=300, crop=16, lr=3e-3))
    before = np.mean([np.abs(x[..., :3] - y).mean() for x, y in zip(tx, ty)])
    after = np.mean([np.abs(apply_corrector(net, x) - y).mean() for x, y in zip(tx, ty)])
    assert after < 0.7 * before, (before, after)  # the identity scores 1.0 x before


def test_a_resumed_fit_ends_where_an_uninterrupted_one_does():
    xs, ys = _frames(3, 3)
    s = CorrectorSettings(width=8, steps=20, crop=16)
    straight, _ = fit_corrector(xs, ys, s)
    torch.manual_seed(s.seed)
    half = SceneCorrector(s.width)
    opt = torch.optim.Adam(half.parameters(), lr=s.lr)
    stop = {}

    class Stop(Exception):
        pass

    def at(step, _loss):
        if step == 9:
            stop["net"] = {k: v.clone() for k, v in half.state_dict().items()}
            stop["opt"] = opt.state_dict()
            raise Stop

    with pytest.raises(Stop):
        fit_corrector(xs, ys, s, net=half, optimizer=opt, on_step=at)
    net2 = SceneCorrector(s.width)
    net2.load_state_dict(stop["net"])
    opt2 = torch.optim.Adam(net2.parameters(), lr=s.lr)
    opt2.load_state_dict(stop["opt"])
    resumed, _ = fit_corrector(xs, ys, s, net=net2, optimizer=opt2, start_step=9)
    for (k, a), b in zip(straight.state_dict().items(), resumed.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=k)


def test_a_non_finite_target_stops_the_fit_naming_the_step():
    xs, ys = _frames(4, 2)
    ys = [np.full_like(y, np.nan) for y in ys]
    with pytest.raises(NumericalError, match="step 1"):
        fit_corrector(xs, ys, CorrectorSettings(width=8, steps=5, crop=16))


def test_mismatched_inputs_are_named():
    xs, ys = _frames(5, 2)
    with pytest.raises(Exception, match="features / targets"):
        fit_corrector(xs, ys[:1], CorrectorSettings(steps=1))
    with pytest.raises(ShapeError, match=r"targets\[0\]"):
        fit_corrector(xs[:1], [ys[0][:5]], CorrectorSettings(steps=1))


def test_save_load_round_trip_and_bad_files(tmp_path):
    xs, ys = _frames(6, 2)
    s = CorrectorSettings(width=8, steps=10, crop=16)
    net, _ = fit_corrector(xs, ys, s)
    p = tmp_path / "c.pt"
    save_corrector(p, net, s, {"graph_stage": "joint"})
    back = load_corrector(p)
    np.testing.assert_allclose(apply_corrector(back, xs[0]), apply_corrector(net, xs[0]), atol=1e-7)
    assert back.fitted_light is None  # a file without the light it was fitted under
    env = np.random.default_rng(3).uniform(0, 5, (8, 16, 3)).astype(np.float32)
    save_corrector(p, net, s, {"graph_stage": "joint", "fitted_light": light_fingerprint(env)})
    assert load_corrector(p).fitted_light == light_fingerprint(env.astype(np.float64))  # float32 either way
    with pytest.raises(ModelLoadError, match="no scene corrector"):
        load_corrector(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ModelLoadError, match="unreadable"):
        load_corrector(tmp_path / "junk.pt")
    torch.save({"format": "other"}, tmp_path / "other.pt")
    with pytest.raises(ModelLoadError, match="not a scene corrector"):
        load_corrector(tmp_path / "other.pt")


def test_the_light_fingerprint_tells_maps_apart():
    env = np.random.default_rng(4).uniform(0, 5, (8, 16, 3)).astype(np.float32)
    fp = light_fingerprint(env)
    assert light_fingerprint(env.copy()) == fp
    nudged = env.copy()
    nudged[3, 5, 1] = np.nextafter(nudged[3, 5, 1], np.float32(10))
    assert light_fingerprint(nudged) != fp  # one ulp of one texel
    assert light_fingerprint(np.roll(env, 1, axis=1)) != fp  # a rotation
    assert light_fingerprint(env.reshape(16, 8, 3)) != fp  # the same values in another shape
    with pytest.raises(ShapeError, match="envmap"):
        light_fingerprint(env[..., :2])
