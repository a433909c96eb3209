"""Night and lights on a reconstruction, measured (issue "night, lights and edits").

For a reconstruction run (``brdf reconstruct --out RUN``) of a synthetic bundle:

* exposure: the night clip at the request defaults (automatic exposure, detected street lamps,
  vehicle lights), per frame the share of pixels at 255 and at 0; the same with the old defaults
  (EV +2, no street lights) beside it;
* street lamps: the poles detected in the bundle's LiDAR against the generator's pole geometry
  (rebuilt from the bundle's recorded config), and how much brighter the road is under each lamp
  than 8-12 m away from it (lamps alone, no sky);
* headlights: every headlight of every moving vehicle rendered alone on every frame of the clip
  (train and test views). Its footprint is computed from the light itself: the ground points
  (the plane of its car's box bottom, up to 25 m ahead) that receive more than 5% of the
  footprint's peak irradiance (cone, cos / d^2). A frame counts when the footprint is in view:
  at least 10% of those points (and 5) project into the image in front of the camera and are
  not hidden by the rendered depth (0.5 m tolerance), covering at least 10 pixels. A car driving
  away from the camera hides
  the road its lamps light (car5 on the default scene: 0-14 of 142 points visible); that is
  not a defect of the light, so such frames are listed apart, not counted. In every counted
  frame the lit road (road pixels, not on any car box, radiance > 5% of the maximum over the
  road pixels; the frame's maximum is often another car's side a few metres into the beam)
  must show (>= 5 pixels) and the share of it in front of its car is reported, with the share of
  the visible footprint's pixels above 1% of that maximum;
* removal: every moving car removed; in every frame where it showed, the share of its former
  pixels looking down at the street's ground (view ray below -2 deg: the ground lies within
  ~50 m there, never sky) that now show background (opacity > 0.5) rather than sky, and the
  pixels still inside its box; the same share over the pixels whose ground point (the ray's hit
  with the plane of the car's box bottom) some training frame saw (in its image, no object box
  of that frame in between), which is what the issue asks of a removal;
* the README's spot-light example: pixels of the relit clip that change by more than 2/255 with
  the light on.

    python benchmarks/bench_night.py RUN --out benchmarks/results/night.json [--rays 16]

Reads the generator's geometry for the poles (a benchmark, never the product path).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def clip_stats(frames) -> dict:
    u8 = np.round(np.asarray(frames) * 255).max(-1)
    at255 = [float((f >= 255).mean()) for f in u8]
    at0 = [float((f <= 0).mean()) for f in u8]
    return {"max_share_at_255": round(max(at255), 4), "max_share_at_0": round(max(at0), 4),
            "mean_ldr": round(float(np.asarray(frames).mean() * 255), 1)}


def world_points(view, depth):
    from core.conventions import camera_ray_directions

    cam = view.camera
    d = camera_ray_directions(cam.cam_to_world, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height).reshape(-1, 3)
    c2w = np.asarray(cam.cam_to_world)
    z = depth.reshape(-1)
    return c2w[:3, 3] + d * (z / (d @ c2w[:3, 2]))[:, None], z > 0


#: A headlight's footprint counts as in view when it covers at least this many pixels, twice the
#: 5 of the lit region asked for: a footprint seen in a handful of pixels (car5 driving away on
#: the default scene: 6 pixels of 17 visible points, all lit) cannot show 5 pixels above 5% of
#: the road's brightest.
MIN_FOOTPRINT_PIXELS = 10


def headlight_footprint(light, size, reach_m: float = 25.0, step_m: float = 0.25) -> np.ndarray:
    """Node-frame ground points (the box bottom's plane) lit by the spot ``light`` with more than
    5% of the footprint's peak irradiance: the cone (full inside ``inner_deg``, linear in cos to
    ``outer_deg``) times the cosine of incidence over the squared distance."""
    lp = np.asarray(light.position, np.float64)
    d = np.asarray(light.direction, np.float64)
    d = d / np.linalg.norm(d)
    gx, gy = np.meshgrid(np.arange(size[0] / 2, size[0] / 2 + reach_m, step_m), np.arange(-8.0, 8.0, step_m))
    g = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, -size[2] / 2)], 1)
    to = g - lp
    dist = np.linalg.norm(to, axis=1)
    c = (to @ d) / dist
    ci, co = np.cos(np.radians(light.inner_deg)), np.cos(np.radians(light.outer_deg))
    cone = np.clip((c - co) / max(ci - co, 1e-9), 0.0, 1.0)
    irr = cone * np.clip(-to[:, 2] / dist, 0.0, 1.0) / dist ** 2
    return g[irr > 0.05 * irr.max()]


def footprint_visible(view, depth, pts_world, tol_m: float = 0.5) -> int:
    """How many world points project into the image, in front of the camera, not hidden by the
    rendered ``depth`` (camera z, 0 = nothing) by more than ``tol_m``."""
    return len(footprint_pixels(view, depth, pts_world, tol_m)[1])


def footprint_pixels(view, depth, pts_world, tol_m: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(distinct flat pixel indices, per visible point its flat pixel index) of the world points
    that project into the image, in front of the camera, not hidden by the rendered ``depth``
    (camera z, 0 = nothing) by more than ``tol_m``."""
    cam = view.camera
    c2w = np.asarray(cam.cam_to_world)
    pc = (pts_world - c2w[:3, 3]) @ c2w[:3, :3]
    z = pc[:, 2]
    front = z > 0.1
    u = cam.fx * pc[:, 0] / np.maximum(z, 1e-6) + cam.cx
    v = cam.fy * pc[:, 1] / np.maximum(z, 1e-6) + cam.cy
    ok = front & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    if not ok.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ui, vi = u[ok].astype(int), v[ok].astype(int)
    dz = depth.reshape(cam.height, cam.width)[vi, ui]
    seen = (dz <= 0) | (dz > z[ok] - tol_m)
    flat = (vi * cam.width + ui)[seen]
    return np.unique(flat), flat


def segment_hits_box(origin, pts, pose, size, margin_m: float = 0.1) -> np.ndarray:
    """[P] bool: the segments from ``origin`` [3] to ``pts`` [P, 3] (world) pass through the box of
    ``size`` (+ ``margin_m``) at ``pose`` (4x4 node -> world), by the slab test in the box frame."""
    o = (np.asarray(origin) - pose[:3, 3]) @ pose[:3, :3]
    d = (pts - pose[:3, 3]) @ pose[:3, :3] - o
    half = np.asarray(size) / 2 + margin_m
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - o) / d, (half - o) / d
    lo = np.nanmax(np.where(np.isfinite(np.minimum(t1, t2)), np.minimum(t1, t2), -np.inf), axis=1)
    hi = np.nanmin(np.where(np.isfinite(np.maximum(t1, t2)), np.maximum(t1, t2), np.inf), axis=1)
    inside_slab = (np.abs(o) <= half) | (d != 0)  # a ray parallel to a slab outside it never enters
    return (lo <= hi) & (hi >= 0.0) & (lo <= 1.0) & inside_slab.all(1)


def observed_in(pts, views, graph) -> np.ndarray:
    """[P] bool: the world points ``pts`` were seen by at least one of ``views`` (the capture's
    training frames): they project into its image in front of its camera, and no object box of
    that frame's scene graph (every node, with its tracked size) stands between the camera and
    them. Buildings are not tested: the points are on the road beside the removed car."""
    seen = np.zeros(len(pts), bool)
    for v in views:
        cam = v.camera
        c2w = np.asarray(cam.cam_to_world)
        pc = (pts - c2w[:3, 3]) @ c2w[:3, :3]
        z = pc[:, 2]
        u = cam.fx * pc[:, 0] / np.maximum(z, 1e-6) + cam.cx
        vv = cam.fy * pc[:, 1] / np.maximum(z, 1e-6) + cam.cy
        ok = (z > 0.1) & (u >= 0) & (u < cam.width) & (vv >= 0) & (vv < cam.height) & ~seen
        for name, pose in graph.node_poses(v.time_s).items():
            size = graph.node(name).size
            if size is not None and ok.any():
                ok[ok] &= ~segment_hits_box(c2w[:3, 3], pts[ok], pose.numpy(), size)
        seen |= ok
    return seen


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "night.json"))
    ap.add_argument("--rays", type=int, default=16)
    a = ap.parse_args()

    from core.bundle import open_bundle
    from core.io.hdri import load_hdri
    from core.pbr.envmap import EnvironmentMap
    from core.pbr.render import ClipRenderer, PBRSettings
    from core.render.objects import attach_sizes, describe_objects, vehicle_lights
    from core.render.scenario import (LightSpec, Scenario, night_scenario, render_scenario, street_lights_for,
                                      to_lights, views_from_frames)
    from core.stages.chain import RunDir

    run = RunDir(a.run)
    b = open_bundle(run.scene_path(), validate=False)
    graph, _sky, stage = run.load_scene()
    attach_sizes(graph, b.manifest)
    m = b.manifest
    views = tuple(views_from_frames(b, "test"))
    common = dict(views=views, base_exposure=m.ldr_exposure, gamma=m.ldr_gamma, rays_per_pixel=a.rays)
    res: dict = {"run": str(a.run), "graph_stage": stage, "frames": len(views), "rays_per_pixel": a.rays}
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        sc, note = night_scenario(run, graph=graph, bundle=b, **common)
        r = render_scenario(graph, sc, Path(tmp) / "n")
        res["night_defaults"] = {**clip_stats(r.result.frames), "exposure_ev": r.metrics["exposure_ev"],
                                 "limited_by": r.metrics["exposure_limited_by"], "lights": r.metrics["lights"],
                                 "street_lights": len(sc.street_lights), "note": note}
        old, _ = night_scenario(run, graph=graph, bundle=b, exposure_ev=2.0, street_lights=False, **common)
        r = render_scenario(graph, old, Path(tmp) / "o")
        res["night_old_defaults_ev2_no_lamps"] = clip_stats(r.result.frames)

    # street lamps: detection against the generator's poles
    specs, lamps, note = street_lights_for(b, graph)
    src = m.source.get("config") if isinstance(m.source, dict) else None
    if src:
        from core.synth import profile
        from core.synth.generate import ego_positions
        from core.synth.street import make_street

        cfg = profile("quick", **{k: tuple(v) if isinstance(v, list) else v for k, v in src.items()})
        poles = [np.asarray(p.vertices) for p in make_street(cfg, ego_positions(cfg)).static_parts
                 if p.name.startswith("pole")]
        truth = np.array([[(v[:, 0].min() + v[:, 0].max()) / 2, np.sign(v[:, 1].mean()) * 6.2] for v in poles])
        found = np.array([lp.pole_base[:2] for lp in lamps if lp.pole_base is not None]).reshape(-1, 2)
        d = np.linalg.norm(found[:, None] - truth[None], axis=2) if len(found) else np.zeros((0, len(truth)))
        res["pole_detection"] = {"poles": len(truth), "detected": len(found),
                                 "matched_within_0.3m": int((d.min(0) < 0.3).sum()) if len(found) else 0,
                                 "false_positives": int((d.min(1) >= 0.3).sum()) if len(found) else 0,
                                 "max_error_m": round(float(d.min(1).max()), 3) if len(found) else None}
    # the road under the lamps vs 8-12 m away (lamps alone)
    dark = EnvironmentMap.constant(0.0, 16, 32)
    settings = PBRSettings(rays_per_pixel=2, threads=2)
    lights = to_lights(specs, graph, what="street_lights")
    rend = ClipRenderer(graph, dark, settings, lights=lights)
    ratios = []
    for i, v in enumerate(views):
        out = rend.render(v.camera, time_s=v.time_s, frame_index=i)
        pts, ok = world_points(v, out.gbuffers["depth"].numpy())
        rad = out.hdr.numpy().reshape(-1, 3).sum(1)
        road = ok & (np.abs(pts[:, 1]) < 5.3) & (pts[:, 2] < 0.3)
        dists = [np.hypot(pts[:, 0] - lp.position[0], pts[:, 1] - lp.position[1]) for lp in lamps]
        for k, dist in enumerate(dists):
            others = np.min([d for j, d in enumerate(dists) if j != k], axis=0) if len(dists) > 1 else np.inf
            under = road & (dist < 2.0)
            away = road & (dist > 8.0) & (dist < 12.0) & (others > 8.0)  # not under another lamp
            if under.sum() >= 5 and away.sum() >= 5:
                ratios.append(float(rad[under].mean() / max(rad[away].mean(), 1e-9)))
    res["street_lamps"] = {"placement": note, "under_vs_8_12m_away_radiance_ratio": {
        "n": len(ratios), "min": round(min(ratios), 2) if ratios else None,
        "median": round(float(np.median(ratios)), 2) if ratios else None}}

    # headlights of the moving vehicles, every frame of the clip
    moving = [o["id"] for o in describe_objects(m) if o["moving"] and o["vehicle"]]
    all_views = tuple(views_from_frames(b, "all"))
    head = []
    for lt in vehicle_lights(graph, tail_lights=False):
        if lt.node not in moving:
            continue
        rend = ClipRenderer(graph, dark, settings, lights=[lt])
        size = np.asarray(graph.node(lt.node).size)
        foot = headlight_footprint(lt, size)
        ahead, in_view, lit_frames, hidden, foot_lit = [], 0, 0, [], []
        for i, v in enumerate(all_views):
            poses = graph.node_poses(v.time_s)
            if lt.node not in poses:
                continue
            out = rend.render(v.camera, time_s=v.time_s, frame_index=i)
            depth = out.gbuffers["depth"].numpy()
            pose = poses[lt.node].numpy()
            fpix, fpts = footprint_pixels(v, depth, foot @ pose[:3, :3].T + pose[:3, 3])
            vis = len(fpts)
            if vis < max(5, 0.1 * len(foot)) or len(fpix) < MIN_FOOTPRINT_PIXELS:
                hidden.append({"frame": v.name, "footprint_points_visible": int(vis), "of": len(foot),
                               "footprint_pixels_visible": int(len(fpix))})
                continue
            in_view += 1
            pts, ok = world_points(v, depth)
            rad = out.hdr.numpy().reshape(-1, 3).sum(1)
            local = (pts - pose[:3, 3]) @ pose[:3, :3]
            road = ok & (pts[:, 2] < 0.4)
            for name, p in poses.items():  # not on any car (it lights the cars in its beam too)
                p = p.numpy()
                sz = np.asarray(graph.node(name).size if graph.node(name).size is not None else size)
                road &= ~(np.abs((pts - p[:3, 3]) @ p[:3, :3]) <= sz / 2 + 0.3).all(1)
            if not road.any():
                continue
            lit = road & (rad > 0.05 * max(float(rad[road].max()), 1e-12))
            # the visible footprint's pixels lit by the light at all (well above the road's median)
            foot_lit.append(float((rad[fpix] > 0.01 * max(float(rad[road].max()), 1e-12)).mean()))
            if lit.sum() < 5:
                continue
            lit_frames += 1
            ahead.append(float((local[lit, 0] > size[0] / 2).mean()))
        head.append({"light": lt.name, "frames": len(all_views), "frames_footprint_in_view": in_view,
                     "frames_with_lit_road_of_those": lit_frames,
                     "min_share_ahead": round(min(ahead), 3) if ahead else None,
                     "min_share_of_footprint_pixels_lit": round(min(foot_lit), 3) if foot_lit else None,
                     "frames_footprint_hidden": hidden})
    res["headlights_of_moving_vehicles"] = head

    # removal of each moving car: in every frame, where the car was, background (opaque) or sky
    from core.relight import ObjectEdit, apply_edits

    rem = {}
    train_views = tuple(views_from_frames(b, "train"))
    for oid in moving:
        gone = apply_edits(graph, [ObjectEdit("remove", oid)])
        r_before = ClipRenderer(graph, dark, PBRSettings(rays_per_pixel=1, threads=2))
        r_after = ClipRenderer(gone, dark, PBRSettings(rays_per_pixel=1, threads=2))
        shares, frames_seen, left = [], 0, 0
        shares_obs, observed_px, unobserved_px = [], 0, 0
        for i, v in enumerate(all_views):
            if oid not in graph.node_poses(v.time_s):
                continue
            gb = r_before.render(v.camera, time_s=v.time_s, frame_index=i).gbuffers
            ga = r_after.render(v.camera, time_s=v.time_s, frame_index=i).gbuffers
            pts, ok = world_points(v, gb["depth"].numpy())
            pose = graph.node_poses(v.time_s)[oid].numpy()
            local = (pts - pose[:3, 3]) @ pose[:3, :3]
            on_car = ok & (np.abs(local) <= np.asarray(graph.node(oid).size) / 2 + 0.1).all(1)
            # only where the view ray points down enough to meet the street's ground (< ~50 m):
            # above that, sky behind the car is right
            c2w = np.asarray(v.camera.cam_to_world)
            dirs = (pts - c2w[:3, 3]) / np.maximum(np.linalg.norm(pts - c2w[:3, 3], axis=1, keepdims=True), 1e-9)
            on_car &= dirs[:, 2] < -0.035
            if on_car.sum() < 10:
                continue
            frames_seen += 1
            opaque = ga["opacity"].numpy().reshape(-1) > 0.5
            shares.append(float(opaque[on_car].mean()))
            # the ground behind the car along each of its pixels' rays (the box bottom's plane)
            ground_z = pose[2, 3] - graph.node(oid).size[2] / 2
            idx = np.flatnonzero(on_car)
            t_hit = (ground_z - c2w[2, 3]) / dirs[idx, 2]
            ground = c2w[:3, 3] + dirs[idx] * t_hit[:, None]
            seen = observed_in(ground, train_views, graph)
            observed_px += int(seen.sum())
            unobserved_px += int((~seen).sum())
            if seen.sum() >= 10:
                shares_obs.append(float(opaque[idx[seen]].mean()))
            pts_a, ok_a = world_points(v, ga["depth"].numpy())
            la = (pts_a - pose[:3, 3]) @ pose[:3, :3]
            left += int((ok_a & (np.abs(la) <= np.asarray(graph.node(oid).size) / 2 - 0.2).all(1)).sum())
        rem[oid] = {"frames_with_the_car": frames_seen, "min_share_background_not_sky": round(min(shares), 3)
                    if shares else None, "mean_share_background_not_sky": round(float(np.mean(shares)), 3)
                    if shares else None, "pixels_still_inside_its_box": left,
                    "pixels_whose_ground_the_training_frames_saw": observed_px,
                    "pixels_whose_ground_no_training_frame_saw": unobserved_px,
                    "frames_with_10_observed_pixels": len(shares_obs),
                    "min_share_background_where_observed": round(min(shares_obs), 3) if shares_obs else None,
                    "mean_share_background_where_observed": round(float(np.mean(shares_obs)), 3)
                    if shares_obs else None}
    res["removal_of_moving_cars"] = rem

    # the README's spot-light example: changed pixels of the relit clip
    spot = LightSpec("spot", (2.6, 0.6, -0.1), 20000.0, (1.0, 0.0, -0.15), (1.0, 0.95, 0.85), 15.0, 35.0, "car4")
    with tempfile.TemporaryDirectory() as tmp:
        base = Scenario(envmap=load_hdri("sunset"), rotation_deg=30.0, exposure_ev=0.0, denoiser="none",
                        outputs=("png",), **common)
        off = render_scenario(graph, base, Path(tmp) / "a").result.frames
        from dataclasses import replace

        on = render_scenario(graph, replace(base, lights=(spot,)), Path(tmp) / "b").result.frames
        diff = np.abs(np.round(on * 255) - np.round(off * 255)).max(-1)
        res["readme_spot_example"] = {"attach_to": "car4", "changed_pixels_gt_2_per_frame_min": int(
            min((f > 2).sum() for f in diff)), "changed_pixels_gt_2_per_frame_max": int(max((f > 2).sum() for f in diff)),
            "pixels_per_frame": int(diff[0].size)}
    res["seconds"] = round(time.perf_counter() - t0, 1)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1))
    print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
