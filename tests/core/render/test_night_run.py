"""Night and edits on a real reconstruction (the tiny Mitsuba street, its volume stage), through
the library and the ``brdf`` command line."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from core.cli import main
from core.stages.chain import RunDir, run_pipeline

pytestmark = pytest.mark.mitsuba


@pytest.fixture(scope="module")
def tiny_run(tiny_scene, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("nightrun") / "run"
    run_pipeline(tiny_scene, out, "tiny", stages=("volume",), progress=False)
    return out


def test_night_at_the_defaults_is_neither_black_nor_clipped(tiny_run, tmp_path):
    from core.bundle import open_bundle
    from core.render.scenario import night_scenario, render_scenario, views_from_frames

    run = RunDir(tiny_run)
    b = open_bundle(run.scene_path())
    graph, _sky, _ = run.load_scene()
    sc, note = night_scenario(run, views=tuple(views_from_frames(b, "all")), rays_per_pixel=16, graph=graph)
    assert sc.exposure_ev is None and sc.headlights and sc.street_lights and "street lights:" in note
    res = render_scenario(graph, sc, tmp_path / "n")
    frames = np.round(res.result.frames * 255)
    for f in frames:
        px = f.max(-1)
        assert (px >= 255).mean() < 0.02 and (px <= 0).mean() < 0.20
    assert res.metrics["exposure"] == "auto" and res.metrics["street_lights"]


def test_cli_info_night_export_and_insert_with_a_camera_path(tiny_run, tmp_path, capsys):
    assert main(["info", str(tiny_run), "--json"]) == 0
    info = json.loads(capsys.readouterr().out.split("\n", 1)[1])  # after the reconstruction line
    ids = [o["id"] for o in info["objects"]]
    moving = [o["id"] for o in info["objects"] if o["moving"]]
    assert ids and moving and all(o["reconstructed"] for o in info["objects"])
    assert main(["info", str(tiny_run)]) == 0
    assert "parked" in capsys.readouterr().out

    out = tmp_path / "night"
    assert main(["night", str(tiny_run), "--out", str(out), "--rays", "4", "--denoiser", "none", "--split", "all",
                 "--street-lights", "spacing", "--street-light-spacing", "10", "--lights-off", ids[0],
                 "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "exposure: auto" in printed and (out / "preview.png").is_file()
    lamps = json.loads((out / "street_lights.json").read_text())["street_lights"]
    assert len(lamps) >= 4 and all(abs(p[2] - lamps[0][2]) < 1.0 for p in lamps)
    pos = tmp_path / "lamps.json"
    pos.write_text(json.dumps([[5.0, 5.0], [12.0, -5.0, 6.0]]))
    assert main(["night", str(tiny_run), "--out", str(tmp_path / "n2"), "--rays", "2", "--denoiser", "none",
                 "--street-light-positions", str(pos), "--exposure", "1.5", "--quiet"]) == 0
    assert "exposure: fixed EV +1.50" in capsys.readouterr().out
    lamps = json.loads((tmp_path / "n2" / "street_lights.json").read_text())["street_lights"]
    assert lamps[1] == [12.0, -5.0, 6.0] and len(lamps) == 2
    assert main(["night", str(tiny_run), "--out", str(tmp_path / "x"), "--lights-off", "nope", "--quiet"]) == 2
    assert "vehicle_lights_off" in capsys.readouterr().err

    asset = tmp_path / "car.pt"
    assert main(["export-object", str(tiny_run), moving[0], "--out", str(asset)]) == 0
    assert asset.is_file() and "insert it" in capsys.readouterr().out
    edits = tmp_path / "edits.json"
    edits.write_text(json.dumps([{"op": "insert", "object_id": "new_car", "asset": str(asset),
                                  "offset_m": [10.0, -1.75, 0.75]},
                                 {"op": "remove", "object_id": moving[0]},
                                 {"op": "move", "object_id": ids[0], "speed": 0.0, "lateral_offset_m": 0.5}]))
    rel = tmp_path / "rel"
    assert main(["relight", str(tiny_run), "--envmap", "city", "--out", str(rel), "--rays", "2", "--denoiser", "none",
                 "--edits", str(edits), "--lateral-shift", "3.5", "--path-fps", "20", "--split", "train",
                 "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "exposure: auto" in printed
    t = json.loads((Path(RunDir(tiny_run).scene_path()) / "bundle.json").read_text())["times"]
    assert len(list((rel / "frames").glob("*.exr"))) == int(round((t[-1] - t[0]) * 20)) + 1
    edits.write_text(json.dumps([{"op": "insert", "object_id": "x", "asset": str(asset), "color": 1}]))
    assert main(["relight", str(tiny_run), "--envmap", "city", "--out", str(rel), "--edits", str(edits),
                 "--quiet"]) == 2
    assert "unknown field" in capsys.readouterr().err


def test_relight_under_the_recovered_map_needs_one(tiny_run, tmp_path, capsys):
    """``--envmap recovered`` names the run's own map; a volume-only run has none, which is said
    (the corrector test relights a run that has one)."""
    assert main(["relight", str(tiny_run), "--envmap", "recovered", "--out", str(tmp_path / "rel"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--envmap recovered" in err and "no recovered environment map" in err
    assert not (tmp_path / "rel").exists()
