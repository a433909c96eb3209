"""core.gen.encoding: the data spaces of the model contracts (shapes, ranges, round trips, the
environment encoding, bad inputs)."""

from __future__ import annotations

import numpy as np
import pytest

from core.conventions import envmap_directions, look_at
from core.errors import NumericalError, ShapeError
from core.gen import contract as C
from core.gen.encoding import (area_downsample, camera_to_world_dirs, data_to_ldr, decode_depth, decode_gbuffer,
                               encode_depth, encode_env, encode_gbuffer, forward_conditioning, ldr_to_data,
                               world_to_camera_dirs)

H, W = 6, 8


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.fixture
def pose():
    """A tilted camera-to-world pose (OpenCV), away from the origin."""
    return look_at(np.array([1.0, -2.0, 1.5]), np.array([4.0, 3.0, 0.5]))


def _unit(rng, *shape):
    v = rng.normal(size=(*shape, 3))
    return (v / np.linalg.norm(v, axis=-1, keepdims=True)).astype(np.float32)


def _gbuffer(rng):
    """Channels-last layers: albedo, roughness, metallic, a unit camera-frame normal, depth with sky."""
    depth = (rng.random((H, W)) * 60).astype(np.float32)
    depth[0, :3] = 0.0  # sky
    return (rng.random((H, W, 3)).astype(np.float32), rng.random((H, W)).astype(np.float32),
            rng.random((H, W, 1)).astype(np.float32), _unit(rng, H, W), depth)


def _env(rng, scale=1.0):
    return (rng.random((2 * C.ENV_H, 2 * C.ENV_W, 3)) * scale).astype(np.float32)


# --- LDR and depth ----------------------------------------------------------------------------------

def test_ldr_round_trip_and_range(rng):
    ldr = rng.random((H, W, 3)).astype(np.float32)
    x = ldr_to_data(ldr)
    assert x.shape == ldr.shape and x.dtype == np.float32
    assert x.min() >= -1.0 and x.max() <= 1.0
    np.testing.assert_allclose(data_to_ldr(x), ldr, atol=1e-7)
    assert ldr_to_data([0.0, 0.5, 1.0]).tolist() == [-1.0, 0.0, 1.0]
    back = data_to_ldr(np.linspace(-3.0, 3.0, 13))
    assert back.min() == 0.0 and back.max() == 1.0 and back.dtype == np.float32  # clipped


def test_depth_round_trip_sky_and_range(rng):
    depth = (rng.random((H, W)) * 200 + 0.01).astype(np.float32)
    depth[0] = 0.0
    enc = encode_depth(depth)
    assert enc.dtype == np.float32 and enc.shape == depth.shape
    assert (enc[0] == 0.0).all() and (enc[1:] > 0).all() and enc.max() <= 1.0
    assert (np.diff(encode_depth(np.linspace(0.1, 100, 50))) < 0).all()  # nearer is larger
    assert encode_depth(np.array([C.DEPTH_SCALE_M]))[0] == pytest.approx(np.exp(-1.0))
    np.testing.assert_allclose(decode_depth(enc), depth, rtol=1e-4)
    assert encode_depth(np.array([-5.0]))[0] == 0.0  # no surface
    assert decode_depth(np.array([0.0, 1e-7]))[0] == 0.0 and decode_depth(np.array([1e-7]))[0] == 0.0


# --- frames ---------------------------------------------------------------------------------------

def test_direction_frames_round_trip(rng, pose):
    d = _unit(rng, H, W)
    cam = world_to_camera_dirs(d, pose)
    assert cam.shape == d.shape and cam.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(cam, axis=-1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(camera_to_world_dirs(cam, pose), d, atol=1e-6)
    # the camera's optical axis (+z in OpenCV) is the pose's third column in the world
    axis = pose[:3, 2]
    np.testing.assert_allclose(world_to_camera_dirs(axis, pose), [0.0, 0.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(camera_to_world_dirs(np.array([0.0, 0.0, 1.0]), pose), axis, atol=1e-6)
    np.testing.assert_array_equal(world_to_camera_dirs(d, np.eye(4)), d)  # translation plays no part


# --- G-buffers ------------------------------------------------------------------------------------

def test_gbuffer_shape_range_and_round_trip(rng):
    albedo, rough, metal, normal, depth = _gbuffer(rng)
    x = encode_gbuffer(albedo, rough, metal, normal, depth)
    assert x.shape == (C.GBUFFER_CHANNELS, H, W) and x.dtype == np.float32 and x.flags.c_contiguous
    assert x.min() >= -1.0 and x.max() <= 1.0
    back = decode_gbuffer(x)
    assert set(back) == {"albedo", "roughness", "metallic", "normal", "depth"}
    np.testing.assert_allclose(back["albedo"], albedo, atol=1e-6)
    np.testing.assert_allclose(back["roughness"], rough[..., None], atol=1e-6)
    np.testing.assert_allclose(back["metallic"], metal, atol=1e-6)
    np.testing.assert_allclose(back["normal"], normal, atol=1e-6)
    np.testing.assert_allclose(back["depth"][..., 0], depth, rtol=1e-3, atol=1e-5)
    assert (back["depth"][0, :3] == 0.0).all()


def test_decode_gbuffer_clips_and_renormalises(rng):
    x = rng.normal(size=(C.GBUFFER_CHANNELS, H, W)).astype(np.float32) * 3
    x[C.GBUFFER_SLICES["normal"], 0, 0] = 0.05  # too short to carry a direction
    out = decode_gbuffer(x)
    for k in ("albedo", "roughness", "metallic"):
        assert out[k].min() >= 0.0 and out[k].max() <= 1.0
    n = np.linalg.norm(out["normal"], axis=-1)
    assert n[0, 0] == 0.0
    np.testing.assert_allclose(n.reshape(-1)[1:], 1.0, rtol=1e-5)
    assert np.isfinite(out["depth"]).all() and out["depth"].min() >= 0.0


def test_gbuffer_bad_inputs(rng):
    albedo, rough, metal, normal, depth = _gbuffer(rng)
    with pytest.raises(ShapeError, match="differ in size"):
        encode_gbuffer(albedo, rough, metal, normal, depth[:-1])
    with pytest.raises(ShapeError, match="albedo"):
        encode_gbuffer(albedo[..., :2], rough, metal, normal, depth)
    with pytest.raises(ShapeError, match="normal"):
        encode_gbuffer(albedo, rough, metal, normal[0], depth)
    bad = rough.copy()
    bad[1, 1] = np.nan
    with pytest.raises(NumericalError, match="roughness"):
        encode_gbuffer(albedo, bad, metal, normal, depth)
    with pytest.raises(ShapeError, match=r"\[9, H, W\]"):
        decode_gbuffer(np.zeros((8, H, W)))
    with pytest.raises(ShapeError):
        decode_gbuffer(np.zeros((C.GBUFFER_CHANNELS, H)))


# --- environment maps -----------------------------------------------------------------------------

def test_area_downsample_block_means(rng):
    env = _env(rng, scale=1e4)
    small = area_downsample(env, C.ENV_H, C.ENV_W)
    assert small.shape == (C.ENV_H, C.ENV_W, 3) and small.dtype == np.float32
    np.testing.assert_allclose(small.mean(axis=(0, 1), dtype=np.float64), env.mean(axis=(0, 1), dtype=np.float64), rtol=1e-6)
    np.testing.assert_allclose(small[3, 5], env[6:8, 10:12].mean(axis=(0, 1), dtype=np.float64), rtol=1e-6)
    const = np.full((16, 32, 3), 7.25, np.float32)
    np.testing.assert_array_equal(area_downsample(const, 4, 8), np.full((4, 8, 3), 7.25, np.float32))
    np.testing.assert_array_equal(area_downsample(const, 16, 32), const)  # factor 1: unchanged


@pytest.mark.parametrize("shape,size", [((10, 32, 3), (4, 8)), ((16, 30, 3), (4, 8)), ((16, 32), (4, 8))])
def test_area_downsample_rejects_non_multiples(shape, size):
    with pytest.raises(ShapeError, match="env"):
        area_downsample(np.ones(shape, np.float32), *size)


def test_encode_env_shapes_ranges_and_determinism(rng, pose):
    env = _env(rng, scale=5.0)
    env[0, 0] = C.ENV_LOG_MAX * 10  # a sun far above the log normaliser
    enc = encode_env(env, pose)
    assert set(enc) == {"env_ldr", "env_log", "env_dir"}
    for k, v in enc.items():
        assert v.shape == (3, C.ENV_H, C.ENV_W) and v.dtype == np.float32 and v.flags.c_contiguous, k
    assert enc["env_ldr"].min() >= 0.0 and enc["env_ldr"].max() < 1.0
    assert enc["env_log"].min() >= 0.0
    np.testing.assert_allclose(np.linalg.norm(enc["env_dir"], axis=0), 1.0, rtol=1e-5)
    again = encode_env(env.copy(), pose.copy())
    for k in enc:
        np.testing.assert_array_equal(enc[k], again[k])
    small = area_downsample(env, C.ENV_H, C.ENV_W).transpose(2, 0, 1)
    np.testing.assert_allclose(enc["env_ldr"], small / (1 + small), rtol=1e-6)
    np.testing.assert_allclose(enc["env_log"], np.log1p(small) / np.log1p(C.ENV_LOG_MAX), rtol=1e-5)
    one = encode_env(np.full((C.ENV_H, C.ENV_W, 3), C.ENV_LOG_MAX, np.float32), pose)["env_log"]
    np.testing.assert_allclose(one, 1.0, rtol=1e-6)


def test_encode_env_directions_follow_the_camera(rng, pose):
    env = _env(rng)
    world = envmap_directions(C.ENV_H, C.ENV_W).transpose(2, 0, 1)
    np.testing.assert_allclose(encode_env(env, np.eye(4))["env_dir"], world, atol=1e-6)
    cam = encode_env(env, pose)["env_dir"]
    np.testing.assert_allclose(camera_to_world_dirs(cam.transpose(1, 2, 0), pose).transpose(2, 0, 1), world,
                               atol=1e-5)
    # the radiance channels do not depend on the pose
    np.testing.assert_array_equal(encode_env(env, pose)["env_ldr"], encode_env(env, np.eye(4))["env_ldr"])


def test_encode_env_bad_inputs(rng, pose):
    env = _env(rng)
    neg = env.copy()
    neg[1, 2, 0] = -1.0
    with pytest.raises(ShapeError, match="negative"):
        encode_env(neg, pose)
    nan = env.copy()
    nan[0, 0, 0] = np.inf
    with pytest.raises(NumericalError, match="env"):
        encode_env(nan, pose)
    with pytest.raises(ShapeError, match="env"):
        encode_env(env[:-1], pose)
    with pytest.raises(ShapeError, match="env"):
        encode_env(env[..., :2], pose)


# --- forward conditioning -------------------------------------------------------------------------

def test_forward_conditioning(rng, pose):
    albedo, rough, metal, _, depth = _gbuffer(rng)
    normal_world = _unit(rng, H, W)
    normal_world[2, 2] = 0.0  # no surface: stays zero
    env = _env(rng)
    out = forward_conditioning(albedo * 1.5, rough, metal, normal_world, depth, pose, env_hdr=env)
    channels = {"normal": 3, "depth": 1, "albedo": 3, "roughness": 1, "metallic": 1,
                "env_ldr": 3, "env_log": 3, "env_dir": 3}
    assert {k: v.shape[0] for k, v in out.items()} == channels
    for k in ("normal", "depth", "albedo", "roughness", "metallic"):
        assert out[k].shape[1:] == (H, W) and out[k].dtype == np.float32, k
    assert out["albedo"].max() <= 1.0  # clipped
    np.testing.assert_allclose(out["depth"][0], encode_depth(depth))
    n = out["normal"].transpose(1, 2, 0)
    np.testing.assert_array_equal(n[2, 2], 0.0)
    np.testing.assert_allclose(np.delete(n.reshape(-1, 3), 2 * W + 2, axis=0),
                               np.delete(world_to_camera_dirs(normal_world, pose).reshape(-1, 3), 2 * W + 2, axis=0),
                               atol=1e-6)
    reused = forward_conditioning(albedo * 1.5, rough, metal, normal_world, depth, pose,
                                  env_encoded=encode_env(env, pose))
    for k in out:
        np.testing.assert_array_equal(out[k], reused[k])
    with pytest.raises(ShapeError, match="env_hdr or env_encoded"):
        forward_conditioning(albedo, rough, metal, normal_world, depth, pose)
    with pytest.raises(ShapeError, match="depth"):
        forward_conditioning(albedo, rough, metal, normal_world, depth[..., None].repeat(2, -1), pose, env_hdr=env)


def test_view_conditioning_rays_and_up():
    """view_conditioning: unit rays through the pixel centres (the principal point looks down +z)
    and the world up in the camera frame, for a level camera and one pitched down by 10 deg."""
    from core.gen.encoding import view_conditioning

    level = look_at(np.array([0.0, 0.0, 1.5]), np.array([0.0, 10.0, 1.5]))
    v = view_conditioning(level, 50.0, 50.0, 4.0, 3.0, W, H)
    assert v.shape == (6, H, W) and v.dtype == np.float32
    assert np.allclose(np.linalg.norm(v[:3], axis=0), 1, atol=1e-6)
    assert np.allclose(v[:3, 2, 3], np.array([-0.5, -0.5, 50.0]) / np.linalg.norm([-0.5, -0.5, 50.0]), atol=1e-6)
    assert v[0, 0, 0] < 0 and v[0, 0, -1] > 0 and v[1, 0, 0] < 0 and v[1, -1, 0] > 0  # x right, y down
    assert np.allclose(v[3:], np.array([0.0, -1.0, 0.0])[:, None, None], atol=1e-6)  # up = -y (OpenCV)
    t = np.radians(10.0)
    down = look_at(np.array([0.0, 0.0, 1.5]), np.array([0.0, 10.0, 1.5 - 10.0 * np.tan(t)]))
    up = view_conditioning(down, 50.0, 50.0, 4.0, 3.0, W, H)[3:, 0, 0]
    assert np.allclose(up, [0.0, -np.cos(t), -np.sin(t)], atol=1e-6)  # a camera pitched down sees up lean back
    with pytest.raises(ShapeError, match="cam_to_world"):
        view_conditioning(np.eye(3), 50.0, 50.0, 4.0, 3.0, W, H)
    with pytest.raises(ShapeError, match="intrinsics"):
        view_conditioning(level, 0.0, 50.0, 4.0, 3.0, W, H)
    bad = level.copy()
    bad[0, 0] = np.nan
    with pytest.raises(NumericalError, match="cam_to_world"):
        view_conditioning(bad, 50.0, 50.0, 4.0, 3.0, W, H)
