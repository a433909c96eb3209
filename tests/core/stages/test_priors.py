"""core.stages.priors: the inverse model's G-buffer priors of a capture, with a model that takes
the capture's camera (contract inverse_gbuffer 1.1) and one that does not."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from core.bundle import open_bundle
from core.gen.edm import GENERATE_SAMPLER, OnnxDenoiser, generate
from core.gen.encoding import ldr_to_data, view_conditioning
from core.gen.gbuffer_ensemble import generate_gbuffer
from core.gen.nets import UNetSettings, build_model, export_onnx
from core.gen.runtime import load_model
from core.stages.priors import decode_to_priors, run_inverse_model

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _model(path, view: bool, seed: int):
    torch.manual_seed(seed)
    m = build_model("inverse_gbuffer", UNetSettings(base_channels=8, emb_dim=32), view=view)
    with torch.no_grad():  # no zero-initialised head: outputs depend on every input
        for p in m.parameters():
            p.add_(torch.randn(p.shape) * 0.05)
    return export_onnx(m.eval(), path)


@pytest.mark.parametrize("view", [False, True])
def test_priors_feed_the_camera_to_a_model_that_takes_it(tiny_scene, tmp_path, view):
    b = open_bundle(tiny_scene)
    path = _model(tmp_path / "inv.onnx", view, seed=1)
    pri = run_inverse_model(b, "train", model=path, threads=1)
    frames = sorted(b.frames("train"), key=lambda f: (f.time_index, f.id))
    assert set(pri.layers) == {f.id for f in frames}
    f0 = [f for f in frames if f.camera == frames[0].camera]
    cam = b.manifest.cameras[f0[0].camera]
    rgb = torch.from_numpy(np.stack([ldr_to_data(b.load_image(f)).transpose(2, 0, 1) for f in f0]))
    cond = {"rgb": rgb}
    if view:
        cond["view"] = torch.from_numpy(np.stack([view_conditioning(f.cam_to_world, cam.fx, cam.fy, cam.cx, cam.cy,
                                                                    cam.width, cam.height) for f in f0]))
    den = OnnxDenoiser(load_model(path, threads=1))
    y = generate_gbuffer(den, (len(f0), 9, rgb.shape[2], rgb.shape[3]), cond, GENERATE_SAMPLER).numpy()
    want = decode_to_priors(y[0], np.asarray(f0[0].cam_to_world, np.float64))
    got = pri.layers[f0[0].id]
    for k in ("albedo", "roughness", "metallic", "normal"):
        assert np.isfinite(got[k]).all() and np.allclose(got[k], want[k], atol=1e-5), k
    if view:  # the same network fed another camera (negated rays and up) gives other priors
        cond.pop("view")
        other = generate(den, (len(f0), 9, rgb.shape[2], rgb.shape[3]), {**cond, "view": -torch.from_numpy(
            np.stack([view_conditioning(f.cam_to_world, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)
                      for f in f0]))}, GENERATE_SAMPLER).numpy()
        assert np.abs(other[0] - y[0]).max() > 1e-4
