from __future__ import annotations

import json
from dataclasses import replace

import pytest

from core.bundle import open_bundle
from core.train.nvs import NVS_PROFILES, train_nvs

pytestmark = pytest.mark.mitsuba


def test_tiny_training_improves_and_writes_outputs(tiny_scene, tmp_path):
    cfg = replace(NVS_PROFILES["tiny"], iterations=40, densify_until=30)
    s = train_nvs(open_bundle(tiny_scene), cfg, tmp_path, progress=False, log_every=10)
    hist = s["history"]
    assert hist[-1]["loss"] < hist[0]["loss"]
    assert 10 < s["test_psnr"] < 60 and 10 < s["train_psnr"] < 60
    assert (tmp_path / "checkpoint" / "scene_graph.pt").is_file()
    assert (tmp_path / "test_renders.mp4").is_file()
    assert json.loads((tmp_path / "summary.json").read_text())["gaussians"] == s["gaussians"]


def test_gaussian_cap_holds_across_scene_graph_nodes(tiny_scene):
    from core.train.density import DensityConfig

    b = open_bundle(tiny_scene)
    cap = 1500
    cfg = replace(NVS_PROFILES["tiny"], iterations=30, densify_from=5, densify_every=5, densify_until=30,
                  density=DensityConfig(max_gaussians=cap, grad_threshold=0.0))
    s = train_nvs(b, cfg, None, progress=False)
    assert s["gaussians"] <= cap
