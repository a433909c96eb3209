"""GET /scenes/{id}/objects and the up-front check of relight / night requests against the scene:
a reference the scene cannot satisfy is a 422 naming the field and the valid choices, and nothing
is queued."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import redis
from sqlalchemy import func, select

from worker.db import Job


def _pose(x, y, yaw=0.0):
    c, s = np.cos(yaw), np.sin(yaw)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = [x, y, 0.75]
    return m


@pytest.fixture(scope="module")
def objects_zip(tmp_path_factory) -> Path:
    """Three frames, a parked car, a moving truck, and LiDAR seeing a 6 m pole at (12, 6)."""
    from core.bundle import BundleWriter, Camera, pack_bundle
    from core.conventions import look_at

    d = tmp_path_factory.mktemp("objscene")
    rng = np.random.default_rng(0)
    w = BundleWriter(d / "b", "objects", overwrite=True)
    w.set_times([0.0, 0.1, 0.2])
    w.add_camera(Camera("front", 32, 24, 32, 32, 16, 12))
    for t in range(3):
        w.add_frame(f"f{t:03d}", "front", t, look_at([t * 1.0, 0, 1.5], [t + 10.0, 0, 1.0]),
                    image=rng.integers(0, 255, (24, 32, 3), dtype=np.uint8), split="test" if t == 2 else "train")
        ground = np.c_[rng.uniform(-5, 40, 3000), rng.uniform(-8, 8, 3000), np.zeros(3000)]
        a = rng.uniform(0, 2 * np.pi, 60)
        pole = np.c_[12 + 0.08 * np.cos(a), 6 + 0.08 * np.sin(a), rng.uniform(0, 6, 60)]
        hits = np.concatenate([ground, pole])
        w.add_lidar(t, np.c_[np.tile([t * 1.0, 0.0, 1.9], (len(hits), 1)), hits])
    w.add_object("car0", "car", (4.4, 1.8, 1.5), {t: _pose(8, 4.3, np.pi) for t in range(3)})
    w.add_object("truck1", "truck", (8.0, 2.5, 3.0), {t: _pose(20 - 2 * t, 1.75, np.pi) for t in range(3)})
    return pack_bundle(w.finish(), d / "objects.zip")


@pytest.fixture
def obj_scene(client, objects_zip) -> str:
    r = client.post("/scenes", content=objects_zip.read_bytes(), headers={"Content-Type": "application/zip"})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def test_objects_are_listed_with_class_box_motion_poses_and_lamps(client, obj_scene, keys):
    r = client.get(f"/scenes/{obj_scene}/objects")
    assert r.status_code == 200, r.text
    d = r.json()
    objs = {o["id"]: o for o in d["objects"]}
    assert set(objs) == {"car0", "truck1"}
    assert objs["car0"]["class"] == "car" and objs["car0"]["size"] == [4.4, 1.8, 1.5] and not objs["car0"]["moving"]
    assert objs["truck1"]["moving"] and objs["truck1"]["vehicle"] and objs["truck1"]["path_length_m"] == 4.0
    poses = objs["truck1"]["poses"]
    assert [p["time_index"] for p in poses] == [0, 1, 2] and [p["time_s"] for p in poses] == [0.0, 0.1, 0.2]
    assert [p["obj_to_world"][0][3] for p in poses] == [20.0, 18.0, 16.0]
    assert d["cameras"] == ["front"] and d["frames"] == {"all": 3, "train": 2, "test": 1}
    (lamp,) = d["street_lights"]
    assert np.hypot(lamp["pole_base"][0] - 12, lamp["pole_base"][1] - 6) < 0.2 and lamp["source"] == "detected"
    # another tenant does not see the scene
    other = client.get(f"/scenes/{obj_scene}/objects", headers={"Authorization": f"Bearer {keys['acme']}"})
    assert other.status_code == 404
    assert client.get("/scenes/nope/objects").status_code == 404


@pytest.mark.parametrize("path,body,field,choice", [
    ("relight", {"envmap_name": "nowhere"}, "envmap_name", "city"),
    ("relight", {"envmap_name": "city", "object_edits": [{"op": "remove", "object_id": "car9"}]},
     "object_edits[0].object_id", "truck1"),
    ("relight", {"envmap_name": "city", "object_edits": [{"op": "insert", "object_id": "car2",
                                                          "source_object_id": "bus"}]},
     "object_edits[0].source_object_id", "car0"),
    ("relight", {"envmap_name": "city", "object_edits": [{"op": "insert", "object_id": "car0",
                                                          "source_object_id": "truck1"}]},
     "object_edits[0].object_id", "already exists"),
    ("relight", {"envmap_name": "city", "object_edits": [{"op": "remove", "object_id": "car0"}],
                 "lights": [{"kind": "point", "position": [0, 0, 1], "intensity": 5, "attach_to": "car0"}]},
     "lights[0].attach_to", "truck1"),  # removed by the edit before it
    ("relight", {"envmap_name": "city", "lights": [{"kind": "spot", "position": [2.4, 0.6, -0.1],
                                                    "direction": [1, 0, -0.08], "intensity": 3000,
                                                    "attach_to": "car5"}]},
     "lights[0].attach_to", "car0"),
    ("relight", {"envmap_name": "city", "camera_path": {"camera": "rear", "poses": [
        {"cam_to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}},
     "camera_path.camera", "front"),
    ("relight", {"envmap_name": "city", "frames": {"split": "test", "start": 5}}, "frames", "1 test frame"),
    ("night", {"captured_path": {"camera": "side"}}, "captured_path.camera", "front"),
    ("night", {"captured_path": {"start_s": 5.0}}, "captured_path.start_s", "[0, 0.1]"),
    ("night", {"vehicle_lights_off": ["car0", "van3"]}, "vehicle_lights_off[1]", "truck1"),
    ("night", {"object_edits": [{"op": "move", "object_id": "truck1", "poses": [
        {"time_index": 7, "obj_to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}]},
     "object_edits[0].poses[0].time_index", "[0, 2]"),
])
def test_requests_that_do_not_fit_the_scene_are_422_naming_field_and_choices(client, obj_scene, app, settings,
                                                                            path, body, field, choice):
    r = client.post(f"/scenes/{obj_scene}/{path}", json=body)
    assert r.status_code == 422, r.text
    d = r.json()
    assert d["detail"].count(field + ":") >= 1 and choice in d["detail"], d
    with app.state.db.session() as s:
        assert s.scalar(select(func.count()).select_from(Job)) == 0
    assert redis.Redis.from_url(settings.redis_url).llen("rq:queue:render") == 0


def test_requests_that_fit_get_past_the_check(client, obj_scene):
    """Edits referring to an inserted object, lights on it, lights off for a real one: valid; the
    scene has no reconstruction yet, so the answer is the 409 that says so."""
    body = {"object_edits": [{"op": "insert", "object_id": "car9", "source_object_id": "car0",
                              "offset_m": [0, -3, 0]},
                             {"op": "move", "object_id": "truck1", "speed": 0.5, "lateral_offset_m": 1.0}],
            "lights": [{"kind": "point", "position": [0, 0, 2], "intensity": 5, "attach_to": "car9"}],
            "vehicle_lights_off": ["car0"], "street_light_positions": [[5, 5], [10, -5, 6]],
            "captured_path": {"lateral_shift_m": 3.5, "fps": 20, "start_s": 0.0, "stop_s": 0.2}}
    r = client.post(f"/scenes/{obj_scene}/night", json=body)
    assert r.status_code == 409 and "no finished reconstruction" in r.json()["detail"], r.text
    r = client.post(f"/scenes/{obj_scene}/relight", json={"envmap_name": "sunset", "frames": {"split": "test"}})
    assert r.status_code == 409, r.text
    r = client.post(f"/scenes/{obj_scene}/night", json={"frames": {"split": "train"}, "captured_path": {}})
    assert r.status_code == 422 and "one of frames, camera_path or captured_path" in r.text
