"""PBR training inputs of the forward model: perturbed oracle scenes of synthetic bundles."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from core.bundle import open_bundle
from core.errors import ConfigError, FormatError
from core.synth.gen_data import DataSettings, load_clips
from core.synth.prepare import PerturbSettings, perturb_gaussians, render_pbr_inputs
from core.gaussians import Gaussians
from core.io.exr import read_exr

pytestmark = pytest.mark.mitsuba


def test_pbr_inputs_are_written_where_the_data_loader_reads_them(tiny_scene, tmp_path):
    root = tmp_path / "b"
    shutil.copytree(tiny_scene, root)
    seen = []
    meta = render_pbr_inputs(root, PerturbSettings(budget=3000, rays_per_pixel=4),
                             on_frame=lambda k, n: seen.append((k, n)))
    b = open_bundle(root)
    assert meta["frames"] == len(b.frames()) == len(seen) and seen[-1] == (len(seen), len(seen))
    assert json.loads((root / "derived" / "pbr" / "meta.json").read_text())["frames"] == meta["frames"]
    fr = b.frames("test")[0]
    layers = read_exr(root / "derived" / "pbr" / f"{fr.id}.exr")
    assert {"rgb", "albedo", "normal", "depth", "roughness", "metallic"} <= set(layers)
    rgb, gt = layers["rgb"], b.load_ground_truth(fr)["rgb"]
    assert np.isfinite(rgb).all() and rgb.min() >= 0 and rgb.shape == gt.shape
    # an imperfect render of the same street under the same sky: the same brightness, roughly
    sky = gt.mean() > 0 and b.load_sky_mask(fr)
    ratio = rgb[~sky].mean() / gt[~sky].mean()
    assert 0.5 < ratio < 2.0, ratio
    clips = load_clips(root, DataSettings(forward_source="pbr"), kinds=("forward",))
    assert clips and clips[0][0]["input_ldr"].shape == clips[0][0]["target_ldr"].shape


def test_perturbation_changes_what_it_should():
    torch.manual_seed(0)
    n = 2000
    g = Gaussians.from_activated(means=torch.randn(n, 3), quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
                                 scales=torch.full((n, 3), 0.05), opacities=torch.full((n,), 0.9),
                                 colors=torch.full((n, 3), 0.5), normals=torch.tensor([[0, 0, 1.0]]).repeat(n, 1),
                                 albedo=torch.full((n, 3), 0.4), roughness=torch.full((n,), 0.5),
                                 metallic=torch.zeros(n))
    s = PerturbSettings(drop_fraction=0.1)
    p = perturb_gaussians(g, s, np.random.default_rng(0), np.ones(3))
    assert 0.85 * n < p.num < 0.95 * n
    ang = torch.rad2deg(torch.acos(p.unit_normals()[:, 2].clamp(-1, 1)))
    assert 3 < float(ang.mean()) < 15  # about normal_sigma_deg * sqrt(pi/2)
    assert float(p.roughness().std()) == pytest.approx(s.roughness_sigma, rel=0.2)
    assert float(p.metallic().min()) >= 0 and float(p.albedo().max()) <= 1
    assert torch.isfinite(p.means).all() and (p.scales() >= g.scales()[: p.num] * 0.999).all()


def test_bad_settings_and_non_synthetic_bundles(small_bundle):
    with pytest.raises(ConfigError, match="drop_fraction"):
        PerturbSettings(drop_fraction=0.7)
    with pytest.raises(ConfigError, match="normal_sigma_deg"):
        PerturbSettings(normal_sigma_deg=float("nan"))
    with pytest.raises(FormatError, match="not a core.synth bundle"):
        render_pbr_inputs(small_bundle)
