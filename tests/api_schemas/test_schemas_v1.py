"""api_schemas v1: examples validate, ranges and finiteness are enforced, unknown fields are
refused, and the package depends on pydantic only."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import BaseModel, ValidationError

import api_schemas as S

MODELS = [getattr(S, n) for n in S.__all__ if isinstance(getattr(S, n), type) and issubclass(getattr(S, n), BaseModel)]


def test_every_example_in_the_openapi_schemas_validates():
    checked = 0
    for m in MODELS:
        for ex in m.model_json_schema().get("examples", []):
            m.model_validate(ex)
            checked += 1
    assert checked >= 8, f"only {checked} models carry examples"


def test_version_is_exported():
    assert S.API_VERSION == "1" and S.SCHEMA_VERSION == 1


def test_unknown_fields_are_refused_not_ignored():
    with pytest.raises(ValidationError, match="fps_typo"):
        S.RenderRequest.model_validate({"fps_typo": 3})


LIGHT = {"kind": "spot", "position": [0, 0, 1], "direction": [1, 0, 0], "intensity": 100.0}


@pytest.mark.parametrize("field,value,needle", [
    ("intensity", 0.0, "greater than 0"), ("intensity", 1e7, "less than or equal"),
    ("intensity", math.nan, "finite"), ("intensity", math.inf, "finite"),
    ("cone_outer_deg", 91.0, "less than or equal"), ("cone_inner_deg", -1.0, "greater than or equal"),
    ("color", [1.5, 0, 0], "less than or equal"), ("color", [0, 0, 0], "at least one channel"),
    ("position", [0, 0], "at least 3"), ("position", [0, 0, 1e9], "less than or equal"),
    ("direction", [0, 0, 0], "zero vector"), ("direction", None, "required for a spot"),
    ("kind", "area", "point"),
])
def test_out_of_range_light_parameters_are_named(field, value, needle):
    with pytest.raises(ValidationError) as e:
        S.LocalLight.model_validate({**LIGHT, field: value})
    assert needle in str(e.value), str(e.value)


def test_spot_cone_order():
    with pytest.raises(ValidationError, match="must not exceed"):
        S.LocalLight.model_validate({**LIGHT, "cone_inner_deg": 40, "cone_outer_deg": 30})


@settings(max_examples=60, deadline=None)
@given(st.floats(allow_nan=True, allow_infinity=True))
def test_light_intensity_accepted_exactly_in_its_range(x):
    ok = math.isfinite(x) and 0 < x <= 1e6
    try:
        S.LocalLight.model_validate({**LIGHT, "intensity": x})
        accepted = True
    except ValidationError:
        accepted = False
    assert accepted == ok


@settings(max_examples=60, deadline=None)
@given(st.floats(allow_nan=True, allow_infinity=True), st.floats(-30, 30))
def test_relight_rotation_and_exposure_ranges(rot, ev):
    body = {"envmap_name": "city", "rotation_deg": rot, "exposure_ev": ev}
    ok = math.isfinite(rot) and -360 <= rot <= 360 and -20 <= ev <= 20
    try:
        S.RelightRequest.model_validate(body)
        accepted = True
    except ValidationError:
        accepted = False
    assert accepted == ok


def test_relight_needs_exactly_one_envmap():
    with pytest.raises(ValidationError, match="exactly one"):
        S.RelightRequest.model_validate({})
    with pytest.raises(ValidationError, match="exactly one"):
        S.RelightRequest.model_validate({"envmap_id": "abc", "envmap_name": "city"})
    assert S.RelightRequest.model_validate({"envmap_id": "abc"}).quality.rays_per_pixel == 64


def test_camera_path_poses_must_be_rigid():
    eye = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    S.CameraPose.model_validate({"cam_to_world": eye})
    scaled = [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    with pytest.raises(ValidationError, match="orthonormal"):
        S.CameraPose.model_validate({"cam_to_world": scaled})
    mirror = [[-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    with pytest.raises(ValidationError, match="reflection"):
        S.CameraPose.model_validate({"cam_to_world": mirror})
    with pytest.raises(ValidationError, match="last row"):
        S.CameraPose.model_validate({"cam_to_world": [*eye[:3], [0, 0, 1, 1]]})


def test_frames_and_camera_path_are_exclusive_and_outputs_unique():
    with pytest.raises(ValidationError, match="one of frames, camera_path or captured_path"):
        S.NightRequest.model_validate({"frames": {}, "camera_path": {
            "camera": "front", "poses": [{"cam_to_world": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]}})
    with pytest.raises(ValidationError, match="one of frames, camera_path or captured_path"):
        S.RelightRequest.model_validate({"envmap_name": "city", "frames": {}, "captured_path": {}})
    with pytest.raises(ValidationError, match="must not be before start_s"):
        S.CapturedPath.model_validate({"start_s": 2.0, "stop_s": 1.0})
    with pytest.raises(ValidationError, match="lateral_shift_m"):
        S.CapturedPath.model_validate({"lateral_shift_m": 1e9})
    with pytest.raises(ValidationError, match="at most once"):
        S.RenderRequest.model_validate({"outputs": ["exr", "exr"]})
    with pytest.raises(ValidationError, match="greater than start"):
        S.FrameRange.model_validate({"start": 5, "stop": 5})


def test_night_and_exposure_defaults_and_trajectory_edit_rules():
    n = S.NightRequest()
    assert n.exposure_ev is None and S.RelightRequest(envmap_name="city").exposure_ev is None  # automatic
    assert n.street_lights and n.street_light_placement == "detect" and n.street_light_intensity == 2000.0
    with pytest.raises(ValidationError, match="street_light_positions"):
        S.NightRequest.model_validate({"street_light_positions": [[1.0]]})
    with pytest.raises(ValidationError, match="not allowed for remove"):
        S.ObjectEdit.model_validate({"op": "remove", "object_id": "car0", "speed": 2.0})
    eye = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    with pytest.raises(ValidationError, match="appears twice"):
        S.ObjectEdit.model_validate({"op": "move", "object_id": "car0", "poses": [
            {"time_index": 1, "obj_to_world": eye}, {"time_index": 1, "obj_to_world": eye}]})
    with pytest.raises(ValidationError, match="obj_to_world"):
        S.ObjectEdit.model_validate({"op": "move", "object_id": "car0", "poses": [
            {"time_index": 1, "obj_to_world": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}]})


def test_object_edit_rules():
    assert S.ObjectEdit.model_validate({"op": "remove", "object_id": "car0"}).offset_m == [0.0, 0.0, 0.0]
    with pytest.raises(ValidationError, match="required for insert"):
        S.ObjectEdit.model_validate({"op": "insert", "object_id": "car9"})
    with pytest.raises(ValidationError, match="only allowed for insert"):
        S.ObjectEdit.model_validate({"op": "move", "object_id": "car0", "source_object_id": "car1"})


def test_job_state_final():
    assert [s.value for s in S.JobState if s.final] == ["done", "failed", "canceled"]


def test_api_schemas_imports_pydantic_only():
    code = ("import sys, api_schemas; bad = [m for m in ('fastapi', 'sqlalchemy', 'redis', 'rq', 'core', "
            "'worker', 'services', 'torch') if m in sys.modules]; print(bad); sys.exit(1 if bad else 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
