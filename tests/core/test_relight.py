"""core.relight: object edits on a scene graph and the relit clip with its outputs."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from core.camera import Camera
from core.errors import ConfigError
from core.pbr.envmap import EnvironmentMap
from core.pbr.lights import PointLight
from core.synth.oracle import OracleSettings, oracle_gaussians
from core.pbr.render import PBRSettings
from core.relight import ObjectEdit, View, apply_edits, render_clip
from core.scene_graph import RigidNode, SceneGraph
from core.synth import geometry as geo
from core.synth.street import Material, Part
from core.conventions import look_at


@pytest.fixture(scope="module")
def scene():
    ground = Part("ground", *geo.quad([(-6, -6, 0), (6, -6, 0), (6, 6, 0), (-6, 6, 0)]), Material("g", (0.5, 0.5, 0.5), 0.8, 0.0))
    box = Part("box", *geo.box((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)), Material("b", (0.7, 0.2, 0.1), 0.4, 0.0))
    cam_pos = np.array([[-6.0, 0.0, 3.0]])
    bg = oracle_gaussians([ground], cam_pos, 40.0, OracleSettings(spacing_px=2.0))
    car = oracle_gaussians([box], cam_pos, 40.0, OracleSettings(spacing_px=2.0))
    poses = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    poses[:, 2, 3] = 0.5
    poses[1, 0, 3] = 1.0  # moves 1 m along +x between the two times
    graph = SceneGraph(bg, [RigidNode("car0", "car", car, torch.arange(2), poses)], torch.tensor([0.0, 0.1]))
    c2w = look_at(np.array([-6.0, 0.0, 3.0]), np.array([0.0, 0.0, 0.5]))
    views = [View(Camera.from_intrinsics(c2w, 40.0, 40.0, 24.0, 16.0, 48, 32), t, f"f{i}")
             for i, t in enumerate((0.0, 0.1))]
    return graph, views


def test_edits_move_remove_insert_and_errors(scene):
    graph, _ = scene
    moved = apply_edits(graph, [ObjectEdit("move", "car0", offset_m=(0.0, 2.0, 0.0), yaw_deg=90.0)])
    p0, p1 = graph.node("car0").poses, moved.node("car0").poses
    np.testing.assert_allclose((p1[:, :3, 3] - p0[:, :3, 3]).numpy(), [[0, 2, 0], [0, 2, 0]], atol=1e-12)
    np.testing.assert_allclose(p1[0, :3, 0].numpy(), [0, 1, 0], atol=1e-12)  # x axis yawed to +y
    assert torch.equal(graph.node("car0").poses, p0)  # the input is untouched
    ins = apply_edits(graph, [ObjectEdit("insert", "car9", "car0", (0.0, -3.0, 0.0), solid=False)])
    assert [n.name for n in ins.nodes] == ["car0", "car9"]
    assert ins.compose(0.0).num == graph.compose(0.0).num + graph.node("car0").gaussians.num
    gone = apply_edits(graph, [ObjectEdit("remove", "car0")])
    # the ground was observed everywhere (not past its edges): no ground fill
    assert gone.nodes == [] and gone.compose(0.0).num == graph.background.num
    for edit, field in ((ObjectEdit("remove", "nope"), "object_edits[0].object_id"),
                        (ObjectEdit("insert", "car0", "car0"), "object_edits[0].object_id"),
                        (ObjectEdit("insert", "new", "nope"), "object_edits[0].source_object_id"),
                        (ObjectEdit("spin", "car0"), "object_edits[0].op")):
        with pytest.raises(ConfigError, match=field.replace("[", r"\[").replace("]", r"\]")):
            apply_edits(graph, [edit], what="object_edits")


def test_render_clip_writes_frames_video_preview_and_lights_light(scene, tmp_path):
    from core.io import read_exr
    from core.io.images import read_image

    graph, views = scene
    env = EnvironmentMap.constant(0.2, 16, 32)
    s = PBRSettings(rays_per_pixel=8, threads=1)
    dark = render_clip(graph, env, views, tmp_path / "a", settings=s, outputs=["exr"])
    lit = render_clip(graph, env, views, tmp_path / "b", settings=s, outputs=["exr", "mp4", "png"],
                      lights=[PointLight((0.0, 0.0, 2.0), intensity=50.0, node="car0")], denoiser="oidn")
    assert [p.name for p in lit.exr_files] == ["f0.exr", "f1.exr"] and lit.video.is_file() and lit.preview.is_file()
    assert dark.video is None and dark.preview is None
    a, b = read_exr(dark.exr_files[0]), read_exr(lit.exr_files[0])
    assert {"rgb", "Lr", "albedo", "normal", "depth", "opacity"} <= set(b)
    assert np.isfinite(b["rgb"]).all() and (b["rgb"] >= 0).all()
    assert float(b["rgb"].mean()) > 1.2 * float(a["rgb"].mean())  # the light adds radiance
    assert read_image(lit.preview).shape == (32, 48, 3) and lit.denoiser == "oidn"
    with pytest.raises(ConfigError, match="outputs"):
        render_clip(graph, env, views, tmp_path / "c", settings=s, outputs=["gif"])
    with pytest.raises(ConfigError, match="views"):
        render_clip(graph, env, [], tmp_path / "c", settings=s)


def test_shadows_off_renders_exactly_as_without_any_tracer(scene):
    """``PBRSettings.shadows = False`` builds no BVH and gives the no-visibility estimate."""
    from core.pbr.render import ClipRenderer, render_pbr
    from core.raster import rasterize_gaussians

    graph, views = scene
    env = EnvironmentMap.constant(0.5, 16, 32)
    v = views[0]
    off = PBRSettings(rays_per_pixel=8, threads=1, shadows=False, reuse_visibility=True)
    r = ClipRenderer(graph, env, off)
    assert r.context.static_tracer is None and r.context.cache is None
    a = r.render(v.camera, time_s=v.time_s)
    g = graph.compose(v.time_s)
    gb = rasterize_gaussians(g, v.camera)
    b = render_pbr(gb, v.camera, env, settings=PBRSettings(rays_per_pixel=8, threads=1))
    np.testing.assert_allclose(a.hdr.numpy(), b.hdr.numpy(), rtol=1e-5, atol=1e-6)
    shadowed = ClipRenderer(graph, env, PBRSettings(rays_per_pixel=8, threads=1)).render(v.camera, time_s=v.time_s)
    assert float(shadowed.hdr.mean()) < float(a.hdr.mean())  # the box shadows the ground
