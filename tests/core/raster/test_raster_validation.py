"""Invalid inputs raise the project's errors, naming the argument."""

from __future__ import annotations

import math

import pytest
import torch
from raster_scenes import NAMES, camera, random_scene

from core.camera import Camera
from core.errors import ConfigError, NumericalError, ShapeError
from core.raster import RasterSettings, rasterize


def _call(scene=None, cam=None, **kw):
    scene = scene if scene is not None else random_scene(5, 0)
    cam = list(cam if cam is not None else camera(8, 8))
    return rasterize(*scene, Camera.from_intrinsics(*cam), **kw)


@pytest.mark.parametrize("i,bad_shape", [(0, (5, 2)), (1, (5, 3)), (2, (5,)), (3, (5, 2)), (4, (5, 4)),
                                         (5, (4, 3)), (6, (5, 3, 1)), (7, (5, 3)), (8, (6,))])
def test_wrong_shapes_name_the_argument(i, bad_shape):
    scene = random_scene(5, 0)
    scene[i] = torch.zeros(bad_shape, dtype=torch.float64)
    with pytest.raises(ShapeError, match=NAMES[i]):
        _call(scene)


@pytest.mark.parametrize("i", range(9))
def test_wrong_dtype_names_the_argument(i):
    scene = random_scene(5, 0)
    scene[i] = scene[i].float() if i else scene[i].to(torch.float16)
    with pytest.raises(ShapeError, match=NAMES[i]):
        _call(scene)


def test_integer_tensor_rejected():
    scene = random_scene(5, 0)
    scene[4] = torch.zeros(5, 3, dtype=torch.int64)
    with pytest.raises(ShapeError, match="colors"):
        _call(scene)


@pytest.mark.parametrize("i", range(9))
def test_non_finite_gaussians_name_the_argument(i):
    scene = random_scene(5, 0)
    scene[i] = scene[i].clone()
    scene[i].view(-1)[0] = math.nan
    with pytest.raises(NumericalError, match=NAMES[i]):
        _call(scene)


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_non_finite_pose(value):
    cam = list(camera(8, 8))
    cam[0] = cam[0].clone()
    cam[0][1, 3] = value
    with pytest.raises(NumericalError, match="cam_to_world"):
        _call(cam=cam)


def test_pose_shape_and_rigidity():
    cam = list(camera(8, 8))
    with pytest.raises(ShapeError, match="cam_to_world"):
        _call(cam=[cam[0][:3]] + cam[1:])
    scaled = cam[0].clone()
    scaled[:3, :3] *= 2.0
    with pytest.raises(ConfigError, match="cam_to_world"):
        _call(cam=[scaled] + cam[1:])
    mirrored = cam[0].clone()
    mirrored[:3, 0] *= -1.0
    with pytest.raises(ConfigError, match="cam_to_world"):
        _call(cam=[mirrored] + cam[1:])


@pytest.mark.parametrize("k,name,value,err", [(1, "fx", 0.0, ConfigError), (2, "fy", -3.0, ConfigError),
                                              (3, "cx", math.nan, NumericalError), (4, "cy", math.inf, NumericalError),
                                              (1, "fx", "a", ConfigError), (5, "width", 0, ConfigError),
                                              (6, "height", 2.5, ConfigError), (5, "width", True, ConfigError)])
def test_bad_intrinsics(k, name, value, err):
    cam = list(camera(8, 8))
    cam[k] = value
    with pytest.raises(err, match=name):
        _call(cam=cam)


def test_bad_background_and_settings():
    with pytest.raises(ShapeError, match="background"):
        _call(background=torch.zeros(4, dtype=torch.float64))
    with pytest.raises(NumericalError, match="background"):
        _call(background=torch.tensor([0.0, math.nan, 0.0], dtype=torch.float64))
    with pytest.raises(ConfigError, match="settings"):
        _call(settings={"tile_size": 16})


@pytest.mark.parametrize("kw", [{"tile_size": 8}, {"alpha_min": 0.0}, {"alpha_max": 1.0}, {"transmittance_min": -1.0},
                                {"low_pass": 0.0}, {"near": 0.0}, {"guard_band": 0.5}, {"max_scale": math.inf},
                                {"threads": 0}])
def test_settings_validation(kw):
    name = next(iter(kw))
    with pytest.raises(ConfigError, match=name):
        RasterSettings(**kw)


def test_settings_frozen():
    s = RasterSettings()
    with pytest.raises(Exception):
        s.near = 1.0  # type: ignore[misc]
