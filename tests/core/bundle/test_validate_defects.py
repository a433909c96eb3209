"""Each malformed bundle gets a clear message naming the file, the field and the problem."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from core.bundle import open_bundle, validate_bundle
from core.cli import main as cli_main
from core.errors import BundleError


def _edit_manifest(root: Path, fn) -> None:
    p = root / "bundle.json"
    d = json.loads(p.read_text())
    fn(d)
    p.write_text(json.dumps(d))


def _set(path, value):
    def fn(d):
        obj = d
        for k in path[:-1]:
            obj = obj[k]
        obj[path[-1]] = value
    return fn


def _write_exr_without(root: Path, layer: str):
    from core.io.exr import write_exr

    layers = {"rgb": np.ones((24, 32, 3), np.float32), "albedo": np.ones((24, 32, 3), np.float32),
              "roughness": np.ones((24, 32, 1), np.float32), "metallic": np.ones((24, 32, 1), np.float32),
              "normal": np.ones((24, 32, 3), np.float32), "depth": np.ones((24, 32, 1), np.float32)}
    del layers[layer]
    write_exr(root / "ground_truth/frames/f000.exr", layers)


def _scaled_pose(d):
    d["frames"][1]["cam_to_world"][0][1] += 0.5


# name -> (mutation, substring of the file, substring of the field or None, substring of the message)
DEFECTS = {
    "missing manifest": (lambda r: (r / "bundle.json").unlink(), "bundle.json", None, "missing manifest"),
    "invalid json": (lambda r: (r / "bundle.json").write_text("{\"format\": "), "bundle.json", None, "invalid JSON"),
    "unknown version": (lambda r: _edit_manifest(r, _set(["version"], 99)), "bundle.json", "version", "unknown version 99"),
    "unknown format": (lambda r: _edit_manifest(r, _set(["format"], "other")), "bundle.json", "format", "unknown format"),
    "missing frames": (lambda r: _edit_manifest(r, lambda d: d.pop("frames")), "bundle.json", "frames", "missing required field 'frames'"),
    "missing frame image": (lambda r: (r / "images/f001.png").unlink(), "images/f001.png", "frames[1]", "file is missing"),
    "pose not 4x4": (lambda r: _edit_manifest(r, _set(["frames", 0, "cam_to_world"], [[1, 0, 0], [0, 1, 0], [0, 0, 1]])),
                     "bundle.json", "frames[0] (id f000).cam_to_world", "4x4"),
    "pose not rigid": (lambda r: _edit_manifest(r, _scaled_pose), "bundle.json", "frames[1] (id f001).cam_to_world", "not a rigid transform"),
    "NaN in pose": (lambda r: _edit_manifest(r, _set(["frames", 2, "cam_to_world", 1, 3], float("nan"))),
                    "bundle.json", "frames[2] (id f002).cam_to_world", "NaN or Inf"),
    "image size vs intrinsics": (lambda r: _edit_manifest(r, _set(["cameras", "front", "width"], 40)),
                                 "images/f000.png", "frames[0]", "image is 32x24 but camera 'front' intrinsics say 40x24"),
    "unknown camera": (lambda r: _edit_manifest(r, _set(["frames", 1, "camera"], "rear")), "bundle.json", "frames[1] (id f001).camera", "unknown camera 'rear'"),
    "duplicate frame id": (lambda r: _edit_manifest(r, _set(["frames", 1, "id"], "f000")), "bundle.json", "frames[1] (id f000).id", "duplicate frame id"),
    "time index out of range": (lambda r: _edit_manifest(r, _set(["frames", 0, "time_index"], 7)), "bundle.json", "time_index", "outside 0..2"),
    "lidar wrong shape": (lambda r: np.save(r / "lidar/0001.npy", np.zeros((5, 3), np.float32)), "lidar/0001.npy", "lidar[1].file", "expected shape [N, 6]"),
    "lidar NaN": (lambda r: np.save(r / "lidar/0000.npy", np.full((5, 6), np.nan, np.float32)), "lidar/0000.npy", "lidar[0].file", "NaN or Inf"),
    "ground truth layer missing": (lambda r: _write_exr_without(r, "metallic"), "ground_truth/frames/f000.exr", "frames[0]", "layer 'metallic'"),
    "path leaves bundle": (lambda r: _edit_manifest(r, _set(["frames", 0, "image"], "../outside.png")), "bundle.json", "frames[0] (id f000).image", "stay inside the bundle"),
    "corrupt image": (lambda r: (r / "images/f002.png").write_bytes(b"not a png at all"), "images/f002.png", "frames[2]", "unreadable image"),
    "non-positive box size": (lambda r: _edit_manifest(r, _set(["objects", 0, "size", 1], 0)), "bundle.json", "objects[0].size[1]", "must be > 0"),
    "principal point outside": (lambda r: _edit_manifest(r, _set(["cameras", "front", "cx"], 500)), "bundle.json", "cameras.front.cx", "outside the image"),
    "envmap not equirect": (lambda r: __import__("core.io.exr", fromlist=["write_exr"]).write_exr(
        r / "ground_truth/envmaps/const.exr", {"rgb": np.ones((16, 16, 3), np.float32)}, precision="float"),
        "ground_truth/envmaps/const.exr", "ground_truth.envmap", "equirect"),
    "timestamps not increasing": (lambda r: _edit_manifest(r, _set(["times"], [0.0, 0.2, 0.1])), "bundle.json", "times", "strictly increasing"),
}


@pytest.mark.parametrize("name", sorted(DEFECTS))
def test_defect_is_reported_clearly(small_bundle, name, capsys):
    mutate, file_part, field_part, msg_part = DEFECTS[name]
    assert validate_bundle(small_bundle) == []
    mutate(small_bundle)
    issues = validate_bundle(small_bundle)
    assert issues, f"defect {name!r} was not detected"
    text = "\n".join(str(i) for i in issues)
    assert any(file_part in i.path for i in issues), text
    if field_part is not None:
        assert any(i.field and field_part in i.field for i in issues), text
    assert msg_part in text, text
    # open_bundle raises one BundleError carrying the same message
    with pytest.raises(BundleError) as ei:
        open_bundle(small_bundle)
    assert msg_part in str(ei.value)
    # the CLI prints it on stderr with exit status 1 and no traceback
    assert cli_main(["validate", str(small_bundle)]) == 1
    err = capsys.readouterr().err
    assert msg_part in err and "Traceback" not in err


def test_at_least_ten_distinct_defects():
    assert len(DEFECTS) >= 10
