from __future__ import annotations

import json
from dataclasses import replace

import pytest

from core.bundle import open_bundle
from core.stages.chain import profile_settings
from core.stages.volume import run_volume

TINY = profile_settings("tiny", "volume")

pytestmark = pytest.mark.mitsuba


def test_tiny_training_improves_and_writes_outputs(tiny_scene, tmp_path):
    cfg = replace(TINY, iterations=40, densify_until=30)
    s = run_volume(open_bundle(tiny_scene), cfg, tmp_path, progress=False, log_every=10)
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
    cfg = replace(TINY, iterations=30, densify_from=5, densify_every=5, densify_until=30,
                  density=DensityConfig(max_gaussians=cap, grad_threshold=0.0))
    s = run_volume(b, cfg, None, progress=False)
    assert s["gaussians"] <= cap


def test_resume_from_checkpoint_matches_an_uninterrupted_run(tiny_scene, tmp_path):
    """A run stopped after its checkpoint at step 20 and resumed ends exactly where a run that
    was never interrupted ends (same Gaussians, same loss history)."""
    b = open_bundle(tiny_scene)
    cfg = replace(TINY, iterations=30, densify_from=5, densify_every=10, densify_until=25)

    class Stop(Exception):
        pass

    def stop_after_20(it, total, rec):
        if it == 20:
            raise Stop()

    with pytest.raises(Stop):
        run_volume(b, cfg, None, progress=False, log_every=10, checkpoint_dir=tmp_path / "ck",
                  checkpoint_every=10, on_progress=stop_after_20)
    resumed = run_volume(b, cfg, None, progress=False, log_every=10, checkpoint_dir=tmp_path / "ck",
                        checkpoint_every=10)
    straight = run_volume(b, cfg, None, progress=False, log_every=10)
    assert [h["it"] for h in resumed["history"]] == [10, 20, 30]
    assert resumed["gaussians"] == straight["gaussians"]
    for a, c in zip(resumed["history"], straight["history"]):
        assert a["loss"] == pytest.approx(c["loss"], rel=1e-5)
    assert resumed["test_psnr"] == pytest.approx(straight["test_psnr"], abs=1e-3)


def test_corrupt_checkpoint_is_an_error_not_a_silent_restart(tiny_scene, tmp_path):
    from core.errors import FormatError

    ck = tmp_path / "ck"
    ck.mkdir()
    (ck / "train_state.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(FormatError, match="train_state.pt"):
        run_volume(open_bundle(tiny_scene), TINY, None, progress=False, checkpoint_dir=ck)
