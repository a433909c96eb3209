"""core.stages.wall_heights: the unseen walls' heights chosen by the capture's shading, written by
the pbr stage and applied to the graph by RunDir.load_scene."""

from __future__ import annotations

import math
import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch

from core.errors import ConfigError, FormatError
from core.gaussians import Gaussians
from core.scene_graph import SceneGraph
from core.stages.occluders import OccluderSettings, complete_occluders
from core.stages.wall_heights import (HYPOTHESES, OCCLUDERS_FILE, choose, hypothesis_occluders,
                                      hypothesis_settings, load_occluders, save_occluders)

from test_occluders import UPWARD_ONLY, _view, _wall


def test_choose_takes_the_smallest_finite_residual_and_prefers_the_guess_on_a_tie():
    assert choose({"none": 0.32, "left": 0.33, "right": 0.314, "both": 0.3146}) == "right"
    assert choose({"none": 0.3, "left": 0.3, "right": math.inf}) == "none"
    assert choose({"none": math.inf, "both": 0.5, "left": None}) == "both"
    # with a margin: a lifted side must beat the guess (and one side both) by more than it
    res = {"none": 0.3197, "left": 0.31967, "right": 0.31439, "both": 0.31458}
    assert choose(res) == "right" and choose(res, 0.01) == "right" and choose(res, 0.02) == "none"
    assert choose({"none": 0.40, "left": 0.30, "both": 0.299}, 0.01) == "left"
    # the stage's default margin: a near-tie keeps the simpler hypothesis (dev4: "right" beat the
    # guess by less than 1e-5; the default scene: "sky+right" beat "right" by 0.2%)
    from core.stages.pbr_settings import PBRStageConfig

    g = PBRStageConfig().wall_min_gain
    assert choose({"none": 0.188912, "right": 0.188905}, g) == "none"
    assert choose({"none": 0.33156, "right": 0.31160, "sky": 0.31239, "sky+right": 0.31098}, g) == "right"
    assert choose({"none": 0.11654, "sky": 0.11588}, g) == "sky"  # dev3: 0.57% better
    with pytest.raises(ConfigError, match="min_gain"):
        choose(res, -0.1)
    with pytest.raises(ConfigError, match="finite"):
        choose({"none": math.inf, "left": math.nan})
    with pytest.raises(ConfigError, match="unknown hypotheses"):
        choose({"up": 0.1})


def test_occluders_round_trip_and_a_bad_file_is_named(tmp_path):
    occ = complete_occluders(_wall(), [], OccluderSettings(max_height_m=8.0, **UPWARD_ONLY))
    save_occluders(tmp_path / OCCLUDERS_FILE, occ, {"hypothesis": "left"})
    back = load_occluders(tmp_path / OCCLUDERS_FILE)
    assert back.num == occ.num and torch.equal(back.means, occ.means)
    (tmp_path / "bad.pt").write_bytes(b"not a torch file")
    with pytest.raises(FormatError, match="bad.pt"):
        load_occluders(tmp_path / "bad.pt")


def test_hypotheses_keep_the_graphs_own_occluders_and_lift_one_side():
    wall = _wall(x0=0.0, x1=30.0, z1=4.0)  # left of a path along +x
    path = [_view((x, 0.0, 1.5), (x + 10.0, 0.0, 1.5)) for x in (0.0, 1.0)]
    far_sky = _view((25.0, -30.0, 9.0), (25.0, 5.0, 9.0), fov_deg=20.0, sky=True)
    views = [path[0], far_sky, path[1]]
    s = OccluderSettings(max_height_m=12.0, extend_m=0.0, **UPWARD_ONLY)
    graph = SceneGraph(wall, [], torch.zeros(1, dtype=torch.float64))
    graph.occluders = complete_occluders(wall, views, s)
    occs = hypothesis_occluders(graph, views, s)
    assert tuple(occs) == HYPOTHESES
    assert torch.equal(occs["none"].means, graph.occluders.means)
    assert torch.equal(occs["right"].means, occs["none"].means)  # nothing stands right of the path
    assert occs["left"].num > occs["none"].num and occs["left"].means[:, 2].max() > 11.0
    assert torch.equal(occs["both"].means, occs["left"].means)
    # sky-only carving of the wall line: the same here, where no view saw through the wall
    assert torch.equal(occs["sky+left"].means, occs["left"].means)
    assert hypothesis_settings(s, "sky+right") == replace(s, tall_unseen="right", wall_line_sky_only=True)
    assert hypothesis_settings(s, "sky") == replace(s, wall_line_sky_only=True)
    with pytest.raises(ConfigError, match="hypothesis"):
        hypothesis_settings(s, "up")
    with pytest.raises(ConfigError, match="OccluderSettings"):
        hypothesis_occluders(graph, views, {"max_height_m": 12.0})


@pytest.mark.mitsuba
def test_the_pbr_stage_records_its_choice_and_later_stages_load_it(tiny_scene, tmp_path_factory):
    from core.stages.pbr_settings import PBRStageConfig
    from core.stages.chain import RunDir, run_pipeline

    out = tmp_path_factory.mktemp("walls") / "run"
    run_pipeline(tiny_scene, out, "tiny", progress=False)
    run = RunDir(out)
    walls = run.summary("pbr")["wall_heights"]
    assert walls["enabled"] and walls["chosen"] in HYPOTHESES and set(walls["hypotheses"]) == set(HYPOTHESES)
    own = run.load_scene(before="pbr")[0].occluders
    res = {h: v["residual"] for h, v in walls["hypotheses"].items()}
    assert walls["chosen"] == choose({h: (math.inf if r is None else r) for h, r in res.items()})
    from core.stages.pbr import wall_shadow_source

    assert walls["rendered_with"] == wall_shadow_source(res, walls["chosen"], PBRStageConfig())[0]
    assert (out / "pbr" / OCCLUDERS_FILE).is_file() == (walls["rendered_with"] != "none")
    # a choice in the pbr directory replaces the graph's occluders for the joint stage and after,
    # not for the stages before it; the joint stage's own graph is not replaced
    copy = tmp_path_factory.mktemp("walls") / "copy"
    shutil.copytree(out, copy)
    marker = Gaussians.cat([own, own]) if own.num else complete_occluders(_wall(), [], OccluderSettings())
    save_occluders(copy / "pbr" / OCCLUDERS_FILE, marker, {"hypothesis": "both"})
    r2 = RunDir(copy)
    assert r2.load_scene(before="joint")[0].occluders.num == marker.num
    assert r2.load_scene(before="pbr")[0].occluders.num == own.num
    assert r2.load_scene()[2] == "joint"
    assert r2.load_scene()[0].occluders.num == run.load_scene()[0].occluders.num
    assert np.isfinite(walls["seconds"])


@pytest.fixture(scope="module")
def volume_run(tiny_scene, tmp_path_factory):
    """A tiny-profile run of the volume stage alone (its graph carries the occluder guess)."""
    from core.stages.chain import run_pipeline

    out = tmp_path_factory.mktemp("walls_volume") / "run"
    run_pipeline(tiny_scene, out, "tiny", stages=("volume",), progress=False)
    return out


def test_a_failed_search_leaves_the_graphs_occluders_as_they_came(tiny_scene, volume_run, tmp_path_factory,
                                                                  monkeypatch):
    """The hypotheses' loop puts each hypothesis's occluders on the graph in turn; an error in a
    search (here the third) must not leave the graph with another hypothesis's occluders."""
    import core.stages.pbr as pbr
    from core.bundle import open_bundle
    from core.stages.chain import RunDir, profile_settings

    graph = RunDir(volume_run).load_scene()[0]
    own = graph.occluders
    assert own is not None
    calls = {"n": 0}
    real = pbr._prior

    def failing(*a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("search failed")
        return real(*a, **k)

    monkeypatch.setattr(pbr, "_prior", failing)
    cfg = profile_settings("tiny", "pbr")
    b = open_bundle(tiny_scene)
    frames, static_tracer = pbr._frames(graph, b, cfg)
    with pytest.raises(RuntimeError, match="search failed"):
        pbr._choose_walls(graph, b, frames, static_tracer, OccluderSettings(), cfg,
                          tmp_path_factory.mktemp("walls_fail") / "pbr_try")
    assert graph.occluders is own and calls["n"] == 3


@pytest.mark.mitsuba
@pytest.mark.parametrize("wall_shadows", ["chosen", "guess"])
def test_wall_shadows_guess_keeps_the_graphs_occluders_for_rendering(tiny_scene, volume_run, tmp_path_factory,
                                                                     monkeypatch, wall_shadows):
    """With ``PBRStageConfig.wall_shadows`` "guess" the chosen hypothesis gives the prior only:
    the graph keeps its own occluders, no occluders file is written and the summary says so; with
    "chosen" the chosen hypothesis's occluders replace them and are saved."""
    import core.stages.pbr as pbr
    from core.bundle import open_bundle
    from core.stages.chain import RunDir, profile_settings

    graph = RunDir(volume_run).load_scene()[0]
    own = graph.occluders
    monkeypatch.setattr(pbr, "choose", lambda residuals, min_gain: "both")
    cfg = replace(profile_settings("tiny", "pbr"), wall_shadows=wall_shadows)
    b = open_bundle(tiny_scene)
    frames, static_tracer = pbr._frames(graph, b, cfg)
    dest = tmp_path_factory.mktemp(f"walls_{wall_shadows}")
    est, tracer, walls = pbr._choose_walls(graph, b, frames, static_tracer, OccluderSettings(), cfg, dest)
    assert walls["chosen"] == "both" and np.isfinite(est.sun_dir).all()
    if wall_shadows == "guess":
        assert walls["rendered_with"] == "none" and tracer is static_tracer
        assert graph.occluders.num == own.num and torch.equal(graph.occluders.means, own.means)
        assert not (dest / OCCLUDERS_FILE).exists()
    else:
        assert walls["rendered_with"] == "both" and graph.occluders is not own
        assert graph.occluders.num > own.num and (dest / OCCLUDERS_FILE).is_file()
    with pytest.raises(ConfigError, match="wall_shadows"):
        replace(cfg, wall_shadows="tallest")


def test_wall_shadow_source_auto_trusts_the_chosen_walls_only_on_a_clear_gain():
    from core.stages.pbr import wall_shadow_source
    from core.stages.pbr_settings import PBRStageConfig

    res = {"none": 0.31863, "sky": 0.31137, "sky+right": 0.3058, "right": 0.11021}
    auto = PBRStageConfig(wall_shadows="auto", wall_shadows_min_gain=0.02)
    src, gain = wall_shadow_source(res, "sky+right", auto)  # the default scene: 4.2% below the guess
    assert src == "sky+right" and math.isclose(gain, 0.31863 / 0.3058 - 1)
    assert wall_shadow_source({"none": 0.11063, "right": 0.11021}, "right", auto)[0] == "none"  # dev3: 0.4%
    assert wall_shadow_source(res, "none", auto) == ("none", 0.0)
    assert wall_shadow_source({"none": None, "sky": 0.3}, "sky", auto) == ("none", None)  # no gain known
    assert wall_shadow_source({"none": math.inf, "sky": 0.3}, "sky", auto) == ("none", None)
    assert wall_shadow_source(res, "sky", replace(auto, wall_shadows="chosen"))[0] == "sky"
    assert wall_shadow_source(res, "sky+right", replace(auto, wall_shadows="guess"))[0] == "none"
    assert wall_shadow_source(res, "sky+right", replace(auto, wall_shadows_min_gain=0.05))[0] == "none"
    for bad in (dict(wall_shadows="tallest"), dict(wall_shadows_min_gain=-0.1),
                dict(wall_shadows_min_gain=math.nan)):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            PBRStageConfig(**bad)
