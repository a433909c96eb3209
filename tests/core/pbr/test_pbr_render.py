"""The full PBR pass (Eq. 3) on rasterized G-buffers: unprojection, composition, native vs torch
(same expectation), the skips (sky, lights, static nodes) giving the same image, the training
pixel subset (differentiable), EXR/MP4 output, and the issue's stability list (finite,
non-negative values and gradients; white furnace)."""

from __future__ import annotations


import numpy as np
import pytest
import torch

from core.conventions import look_at
from core.errors import ConfigError
from core.gaussians import Gaussians
from core.pbr import EnvironmentMap, GaussianTracer
from core.pbr.lights import PointLight, SpotLight, lights_to_world
from core.synth.oracle import OracleSettings, oracle_gaussians
from core.camera import Camera
from core.pbr.render import (ClipRenderer, PBRSettings, render_pbr, sample_pixels, shading_inputs, tonemap,
                             write_clip_mp4, write_frame_exr)
from core.raster import RasterSettings, rasterize_gaussians
from core.synth import geometry as geo
from core.synth.street import Material, Part

W, H = 48, 32
CITY = "data/hdri/city.exr"


def _scene(material=("m", (0.6, 0.5, 0.4), 0.5, 0.0)):
    ground = Part("ground", *geo.quad([(-6, -6, 0), (6, -6, 0), (6, 6, 0), (-6, 6, 0)]), Material(*material))
    box = Part("box", *geo.box((1.0, 0.0, 0.5), (1.0, 1.0, 1.0)), Material("b", (0.2, 0.3, 0.8), 0.3, 1.0))
    cam = Camera.from_intrinsics(look_at(np.array([-4.0, -1.0, 2.5]), np.array([1.0, 0.0, 0.3])), 40.0, 40.0, W / 2,
                                 H / 2, W, H)
    g = oracle_gaussians([ground, box], cam.pose_numpy()[:3, 3][None], cam.fx,
                         OracleSettings(spacing_px=2.0, max_spacing=0.4))
    return g, cam


@pytest.fixture(scope="module")
def scene():
    g, cam = _scene()
    out = rasterize_gaussians(g, cam, settings=RasterSettings(threads=1))
    tr = GaussianTracer.from_gaussians(g, PBRSettings().trace)
    return g, cam, out, tr


@pytest.fixture(scope="module")
def city():
    return EnvironmentMap.from_file(CITY)


def test_unprojection_composition_and_tone_map(scene, city):
    g, cam, out, tr = scene
    si = shading_inputs(out, cam)
    o = si.opacity[:, 0]
    surf = o > 0.99
    assert surf.any() and (o < 1 / 255).any()
    # composited (mean-depth) G-buffers put ground points near z = 0 (biased toward the camera
    # by a fraction of a Gaussian, as 3DGS depth is); normals face up
    ground = surf & (si.normals[:, 2] > 0.99) & (si.points[:, 2] < 0.6)
    assert ground.sum() > 100
    assert float(si.points[ground, 2].abs().median()) < 0.3
    # exact G-buffers unproject exactly: a plane z = 0 seen by the scene's camera
    from core.conventions import camera_ray_directions

    d = torch.from_numpy(camera_ray_directions(cam.cam_to_world, cam.fx, cam.fy, cam.cx, cam.cy, W, H)).float()
    c = torch.as_tensor(cam.cam_to_world, dtype=torch.float32)
    t = -c[2, 3] / d[..., 2]
    zc = t * (d @ c[:3, 2])
    hit = (t > 0)[..., None].float()
    gb = {"opacity": hit * 0.5, "depth": zc[..., None] * hit * 0.5, "normal": torch.tensor([0.0, 0, 0.5]).expand(H, W, 3) * hit,
          "albedo": hit.expand(H, W, 3) * 0.25, "roughness": hit * 0.25, "metallic": hit * 0.0}
    si2 = shading_inputs(gb, cam)
    m = hit.reshape(-1) > 0
    assert si2.points[m, 2].abs().max() < 1e-3
    np.testing.assert_allclose(si2.albedo[m].numpy(), 0.5, atol=1e-6)  # accumulated / O
    np.testing.assert_allclose(si2.normals[m].numpy(), np.tile([0, 0, 1.0], (int(m.sum()), 1)), atol=1e-6)
    res = render_pbr(out, cam, city, settings=PBRSettings(rays_per_pixel=16, threads=1), tracers=[tr])
    assert res.hdr.shape == (H, W, 3) and torch.isfinite(res.hdr).all() and (res.hdr >= 0).all()
    sky = (o < 1 / 255).reshape(H, W)
    np.testing.assert_allclose(res.hdr[sky].numpy(), ((1 - si.opacity) * city.lookup(si.view_dirs)).reshape(H, W, 3)[sky],
                               rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(res.ldr.numpy(), tonemap(res.hdr, 1.0, 2.2).numpy(), atol=1e-6)
    assert (res.samples[~sky] == 16).all() and (res.samples[sky] == 0).all()


def test_native_and_torch_passes_have_the_same_expectation(scene, city):
    g, cam, out, tr = scene
    surf = (out.opacity[..., 0] > 0.99)
    means = {}
    for backend in ("native", "torch"):
        imgs = []
        for seed in range(3):
            s = PBRSettings(rays_per_pixel=32, backend=backend, seed=seed, threads=1)
            res = render_pbr(out, cam, city, settings=s, tracers=[tr], generator=torch.Generator().manual_seed(seed))
            imgs.append(res.lr[surf].double().mean(0).numpy())
        means[backend] = np.array(imgs)
    a, b = means["native"], means["torch"]
    se = np.sqrt(a.var(0, ddof=1) / 3 + b.var(0, ddof=1) / 3) + 1e-3 * np.abs(a.mean(0))
    assert np.all(np.abs(a.mean(0) - b.mean(0)) < 5 * se), (a.mean(0), b.mean(0))


def test_skips_give_the_same_image(scene, city):
    g, cam, out, tr = scene
    lights = lights_to_world([PointLight((0.0, 0.0, 1.5), intensity=5.0, range=4.0),
                              SpotLight((2.5, 0.0, 2.0), direction=(-1, 0, -1), inner_deg=10, outer_deg=25,
                                        intensity=40.0)])
    base = PBRSettings(rays_per_pixel=8, threads=1)
    ref = render_pbr(out, cam, city, settings=base, tracers=[tr], lights=lights)
    no_sky = render_pbr(out, cam, city, settings=PBRSettings(rays_per_pixel=8, threads=1, skip_sky=False),
                        tracers=[tr], lights=lights)
    no_cull = render_pbr(out, cam, city, settings=PBRSettings(rays_per_pixel=8, threads=1, cull_lights=False),
                         tracers=[tr], lights=lights)
    np.testing.assert_allclose(no_cull.hdr.numpy(), ref.hdr.numpy(), rtol=1e-5, atol=1e-6)
    # without the sky skip the near-transparent pixels get O L_r with O < 1/255 on top
    diff = (no_sky.hdr - ref.hdr).abs()
    assert float(diff.max()) <= float(no_sky.lr.max()) / 255.0 + 1e-6
    assert no_cull.counters["light_evals"] > ref.counters["light_evals"]
    assert no_sky.counters["shaded_pixels"] > ref.counters["shaded_pixels"]


def test_pixel_subset_is_the_full_frame_at_those_pixels_and_differentiable(scene, city):
    g, cam, out, tr = scene
    idx = sample_pixels(out.opacity, 200, generator=torch.Generator().manual_seed(0))
    assert len(idx) == 200 and (out.opacity.reshape(-1)[idx] >= 1 / 255).all()
    s = PBRSettings(rays_per_pixel=8, threads=1)
    full = render_pbr(out, cam, city, settings=s, tracers=[tr])
    sub = render_pbr(out, cam, city, settings=s, tracers=[tr], pixels=idx)
    np.testing.assert_allclose(sub.hdr.numpy(), full.hdr.reshape(-1, 3)[idx].numpy(), rtol=1e-6, atol=1e-7)
    # the torch backend: gradients reach the environment map (log space, as the PBR stage)
    env = EnvironmentMap.from_file(CITY, log_space=True, requires_grad=True)
    r = render_pbr(out, cam, env, settings=PBRSettings(rays_per_pixel=8, backend="torch"), tracers=[tr],
                   pixels=idx, generator=torch.Generator().manual_seed(1))
    assert r.ldr.shape == (200, 3)
    r.ldr.mean().backward()
    grad = env.param.grad
    assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0


def test_white_furnace_through_the_whole_pass():
    """White Lambert (specular 0) Gaussians under a constant environment of 1: C = 1 within 1%."""
    ground = Part("g", *geo.quad([(-3, -3, 0), (3, -3, 0), (3, 3, 0), (-3, 3, 0)]),
                  Material("w", (1.0, 1.0, 1.0), 1.0, 0.0, "lambert"))
    cam = Camera.from_intrinsics(look_at(np.array([0.0, -0.5, 3.0]), np.array([0.0, 0.0, 0.0])), 30.0, 30.0, W / 2,
                                 H / 2, W, H)
    g = oracle_gaussians([ground], cam.pose_numpy()[:3, 3][None], cam.fx, OracleSettings(spacing_px=2.0))
    out = rasterize_gaussians(g, cam)
    env = EnvironmentMap.constant(1.0, 16, 32)
    for backend, sampling in (("native", "env"), ("native", "mis"), ("torch", "mis")):
        res = render_pbr(out, cam, env, settings=PBRSettings(rays_per_pixel=256, specular=0.0, sampling=sampling,
                                                             backend=backend, threads=1))
        inner = res.hdr[8:-8, 12:-12]
        assert abs(float(inner.mean()) - 1.0) < 0.01, (backend, sampling, float(inner.mean()))


def _gbuf(normal, wo_dir=(0.0, 0.0, -1.0), rough=0.5, metal=0.0, albedo=0.5, n=4):
    """A hand-made 1 x n G-buffer seen by a camera at the origin looking down -z... built so the
    camera ray of every pixel is ~``wo_dir``; normals as given (may be zero or face away)."""
    cam = Camera.from_intrinsics(look_at(np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.0, 0.0]), up=(0.0, 1.0, 0.0)),
                                 1e4, 1e4, n / 2, 0.5, n, 1)
    t = lambda x, c: torch.as_tensor(np.broadcast_to(np.asarray(x, np.float32), (1, n, c)).copy())  # noqa: E731
    gb = {"opacity": t(1.0, 1), "depth": t(2.0, 1), "normal": t(normal, 3), "albedo": t(albedo, 3),
          "roughness": t(rough, 1), "metallic": t(metal, 1)}
    return gb, cam


GRAZING = [(0.0, 0.0, 1.0), (1.0, 0.0, 1e-7), (1.0, 0.0, -1e-7), (1.0, 0.0, 1e-3), (1.0, 0.0, -1e-3),
           (0.0, 0.0, 0.0), (0.0, 0.0, -1.0)]


@pytest.mark.parametrize("backend", ["native", "torch"])
@pytest.mark.parametrize("sun", ["city", 1e6, "zero"])
def test_stability_list_finite_non_negative_with_finite_gradients(backend, sun, tmp_path):
    """Roughness 0/1, metallic 0/1, grazing normals from both sides, zero and back-facing normals,
    the city sun (3.5e4) / a 1e6 sun / an all-zero map, a light inside a Gaussian and a light at
    the shading point: outputs finite and >= 0, gradients (torch) finite; the EXR never holds Inf."""
    if sun == "city":
        rgb = EnvironmentMap.from_file(CITY).radiance_map().detach().numpy()
    else:
        rgb = np.full((32, 64, 3), 0.2 if sun != "zero" else 0.0, np.float32)
        if sun != "zero":
            rgb[3, 10] = sun
    lights = lights_to_world([PointLight((0.0, 0.0, 0.0), intensity=1e6),          # at the shading points
                              PointLight((0.05, 0.0, 0.01), intensity=100.0),      # inside the Gaussian below
                              SpotLight((0.0, 0.0, 0.5), direction=(0, 0, -1), inner_deg=0, outer_deg=0,
                                        intensity=10.0)])
    blob = Gaussians.from_activated(torch.tensor([[0.05, 0.0, 0.0]]), torch.tensor([[1.0, 0, 0, 0]]),
                                    torch.tensor([[0.1, 0.1, 0.02]]), torch.tensor([0.9]), torch.ones(1, 3),
                                    torch.tensor([[0.0, 0, 1]]), torch.ones(1, 3), torch.ones(1), torch.zeros(1))
    tr = GaussianTracer.from_gaussians(blob, PBRSettings().trace)
    env = EnvironmentMap(rgb, log_space=backend == "torch", requires_grad=backend == "torch")
    for normal in GRAZING:
        for rough in (0.0, 1.0):
            for metal in (0.0, 1.0):
                env.param.grad = None
                gb, cam = _gbuf(normal, rough=rough, metal=metal)
                albedo = gb["albedo"].clone().requires_grad_(backend == "torch")
                gb["albedo"] = albedo
                res = render_pbr(gb, cam, env, settings=PBRSettings(rays_per_pixel=8, backend=backend, threads=1),
                                 tracers=[tr], lights=lights, generator=torch.Generator().manual_seed(0))
                assert torch.isfinite(res.hdr).all() and (res.hdr >= 0).all(), (normal, rough, metal)
                assert torch.isfinite(res.ldr).all()
                if backend == "torch":
                    res.ldr.sum().backward()
                    assert torch.isfinite(env.param.grad).all() and torch.isfinite(albedo.grad).all()
    if backend == "native":
        full = EnvironmentMap(np.full((8, 16, 3), 1e6, np.float32))
        gb, cam = _gbuf((0.0, 0.0, 1.0))
        gb["opacity"] = torch.zeros_like(gb["opacity"])  # all sky: beauty = 1e6
        res = render_pbr(gb, cam, full, settings=PBRSettings(rays_per_pixel=4, threads=1))
        write_frame_exr(tmp_path / "f.exr", res)
        from core.io import read_exr

        layers = read_exr(tmp_path / "f.exr")
        rgb_back = layers["rgb"] if "rgb" in layers else layers["beauty"]
        assert np.all(np.isfinite(rgb_back)) and rgb_back.max() == pytest.approx(1e6, rel=1e-6)
        assert all(np.all(np.isfinite(v)) for v in layers.values())


def test_exr_layers_and_mp4(scene, city, tmp_path):
    g, cam, out, tr = scene
    res = render_pbr(out, cam, city, settings=PBRSettings(rays_per_pixel=4, threads=1), tracers=[tr])
    write_frame_exr(tmp_path / "a.exr", res)
    from core.io import exr_header, read_exr, read_mp4_frames

    layers = read_exr(tmp_path / "a.exr")
    for k in ("Lr", "opacity", "depth", "normal", "albedo", "roughness", "metallic", "samples"):
        assert k in layers, sorted(layers)
    hdr_back = layers["rgb"] if "rgb" in layers else layers["beauty"]
    np.testing.assert_allclose(hdr_back, res.hdr.numpy(), rtol=1e-6)  # float32, exact
    hdr_ = exr_header(tmp_path / "a.exr")
    types = dict(zip(hdr_.channels, hdr_.pixel_types))
    assert types["R"] == "float" and types["Lr.R"] == "float" and types["albedo.R"] == "half"
    write_clip_mp4(tmp_path / "c.mp4", [res, res.ldr, res.ldr.numpy()], fps=5)
    assert read_mp4_frames(tmp_path / "c.mp4").shape[0] == 3


def test_clip_renderer_static_reuse_and_moving_node_lights():
    from core.scene_graph import RigidNode, SceneGraph

    g, cam = _scene()
    car = oracle_gaussians([Part("c", *geo.box((0.0, 0.0, 0.0), (0.8, 0.6, 0.5)), Material("c", (0.8, 0.1, 0.1), 0.3,
                                                                                          0.0))],
                           cam.pose_numpy()[:3, 3][None], cam.fx, OracleSettings(spacing_px=3.0))
    poses = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
    poses[:, 0, 3] = torch.tensor([-1.0, -0.5, 0.0])
    poses[:, 2, 3] = 0.25
    graph = SceneGraph(g, [RigidNode("car", "car", car, torch.arange(3), poses)], torch.tensor([0.0, 0.1, 0.2]))
    env = EnvironmentMap.from_file(CITY)
    head = SpotLight((0.4, 0.0, 0.0), direction=(1, 0, 0), inner_deg=20, outer_deg=35, intensity=30.0, node="car")
    s = PBRSettings(rays_per_pixel=8, threads=1)
    with_reuse = ClipRenderer(graph, env, s, lights=[head], static_reuse=True)
    without = ClipRenderer(graph, env, s, lights=[head], static_reuse=False)
    imgs = []
    for t, r in ((0, with_reuse), (0, without), (2, with_reuse)):
        imgs.append(r.render(cam, time_s=0.1 * t, frame_index=t))
    assert with_reuse.context.static_tracer is not None and without.context.static_tracer is None
    d = (imgs[0].hdr - imgs[1].hdr).abs()
    assert float(d.mean()) < 1e-3 * float(imgs[0].hdr.mean()) + 1e-6  # same image up to float32 rounding
    assert not torch.equal(imgs[0].hdr, imgs[2].hdr)  # the car and its headlight moved


def test_settings_validation_names_the_field():
    for kw, name in ((dict(rays_per_pixel=0), "rays_per_pixel"), (dict(sampling="bsdf"), "sampling"),
                     (dict(backend="cuda"), "backend"), (dict(exposure=0.0), "exposure"),
                     (dict(specular=2.0), "specular"), (dict(adaptive="yes"), "adaptive"),
                     (dict(cache_cell_px=0.0), "cache_cell_px")):
        with pytest.raises(ConfigError, match=name):
            PBRSettings(**kw)
    assert PBRSettings(rays_per_pixel=7, sampling="mis").split == (4, 3)
    assert PBRSettings(rays_per_pixel=7, sampling="env").split == (7, 0)


@pytest.mark.parametrize("backend", ["native", "torch"])
def test_opaque_above_shades_partly_opaque_surfaces_without_the_map_showing_through(backend):
    """A floor 0.95 opaque seen from above under a map whose lower hemisphere is bright: the
    paper's blend (opaque_above 1.0) adds 5% of the floor of the map seen through the surface;
    at 0.5 the pixel is the surface alone, as if fully opaque; a half-covered pixel (0.4) keeps
    the blend either way."""
    gb, cam = _gbuf((0.0, 0.0, 1.0), n=3)
    gb = {k: v.clone() for k, v in gb.items()}
    cover = torch.tensor([1.0, 0.95, 0.4]).reshape(1, 3, 1)
    for k in ("opacity", "depth", "normal", "albedo", "roughness", "metallic"):
        gb[k] = gb[k] * cover  # accumulated sums, as the rasterizer composites them
    h, w = 16, 32
    tex = torch.full((h, w, 3), 0.2)
    tex[h // 2:] = 50.0  # the map's lower hemisphere: a sunlit floor
    env = EnvironmentMap(tex)
    ref = {}
    for opaque in (1.0, 0.5):
        s = PBRSettings(rays_per_pixel=8192, backend=backend, threads=1, shadows=False, opaque_above=opaque)
        ref[opaque] = render_pbr(gb, cam, env, settings=s, generator=torch.Generator().manual_seed(0)).hdr[0]
    lr_full = ref[0.5][0]  # the fully opaque pixel: L_r alone under both settings
    np.testing.assert_allclose(ref[1.0][0].numpy(), lr_full.numpy(), rtol=1e-6)
    # 0.95 opaque: the surface alone at 0.5 (the same expectation as the opaque pixel) ...
    np.testing.assert_allclose(ref[0.5][1].numpy(), lr_full.numpy(), rtol=0.1)
    # ... the paper's blend shows 5% of the map's floor (radiance 50) through it
    assert float(ref[1.0][1].mean()) > float(ref[0.5][1].mean()) + 0.05 * 50 * 0.8
    # below the threshold both blend the same way
    np.testing.assert_allclose(ref[1.0][2].numpy(), ref[0.5][2].numpy(), rtol=1e-6)
    with pytest.raises(ConfigError, match="opaque_above"):
        PBRSettings(opaque_above=0.0)
