"""Where a reconstruction's re-render under its recovered lighting loses against the capture.

Diagnostics only: every row reads the bundle's ground truth (G-buffers, the true map, the true
meshes as "oracle" occluders), which the product never does.

    python benchmarks/diagnose_rerender.py regions RUN            # error per region, low / high frequency
    python benchmarks/diagnose_rerender.py gains RUN [--albedo gt] [--occluders oracle] [--bounces N]
    python benchmarks/diagnose_rerender.py visibility RUN [--occluders oracle]
    python benchmarks/diagnose_rerender.py lighting RUN           # sun and sky irradiance of the run's maps
    python benchmarks/diagnose_rerender.py albedo RUN [--stages volume2,joint]   # shading baked into the albedo
    python benchmarks/diagnose_rerender.py bounce RUN             # is the missing light interreflection?

``regions``: the evaluation's re-render (64 rays, OIDN, ``core.synth.evaluate``'s settings) and the
novel views against the test frames, split by the true G-buffers into sky, ground (n_z > 0.8),
glass walls (|n_z| < 0.3, roughness < 0.25), other walls and the rest, and by frequency (a
Gaussian of ``--sigma`` pixels: the low-pass error is shading, the rest detail); and by the true
G-buffers' edges (:func:`edge_classes`: silhouettes, creases, albedo edges, flat surfaces, sky),
with the novel views' PSNR minus the re-render's per class (``edge_class_gap_db``).

``gains``: the true map split into its sun (10 deg around the brightest direction) and the rest,
each rendered by the PBR stage's pass on the stage's training pixels (the run's ``--stage``
G-buffers, its occluders or the oracle's, ``--albedo gt`` for the true albedo); the grid-searched
L1-optimal gains of the two parts, and the ratio capture / render (linear) per quintile of the
capture's shading (radiance / true albedo) on the ground, on walls (true roughness >= 0.25) and on
glass (below). Gains of 1 and ratios of 1
mean the reconstruction's geometry, materials and shadows explain the capture under the true map.

``visibility``: the sun's visibility (the true sun direction) at the training frames' surface
pixels facing it, through the run's occluders against the oracle's: on ground and walls, the mean
visibility where the truth is lit and where it is in shadow.

``lighting``: the sun's irradiance (10 deg cap, at normal incidence) and the sky's irradiance on a
horizontal and on a vertical surface facing the sun's azimuth, for the true map and each map of
the run (the prior, the pbr stage's, the joint stage's).

``albedo``: the reconstruction's albedo over the true one (median, non-metallic unclipped pixels of
every 4th training frame) per quintile of the capture's shading (radiance / true albedo), on the
ground, on walls (true roughness >= 0.25) and on glass: a ratio that rises with the shading is lighting baked into the albedo.

``bounce``: the true albedo, the true map and the true meshes as occluders, the PBR pass with
direct light only, plus a bounce that takes the *capture's own radiance* where each of 24 cosine
rays per pixel meets the frame's rendered depth (screen space; a ray the true meshes block off
screen takes the frame's mean radiance): capture / render per shading quintile with and without
that bounce. If the missing light were interreflection this would bring the ratios to 1.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import scipy.ndimage as nd
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from core.bundle import open_bundle  # noqa: E402
from core.camera import Camera  # noqa: E402
from core.conventions import envmap_directions, envmap_solid_angles  # noqa: E402
from core.io.envmap_file import read_envmap  # noqa: E402
from core.lighting.prior import brightest_direction  # noqa: E402
from core.pbr.envmap import EnvironmentMap, resample  # noqa: E402
from core.pbr.render import render_pbr  # noqa: E402
from core.raster import RasterSettings, rasterize_gaussians  # noqa: E402
from core.scene_graph import SceneGraph  # noqa: E402
from core.stages.chain import RunDir, profile_settings  # noqa: E402

SUN_CAP_DEG = 10.0
#: Edge classes of the regions split: a 3x3 neighbourhood whose true log depth spans more than this
#: is a silhouette, whose normals (any component) span more than ``CREASE_SPAN`` a crease, whose
#: albedo (any channel) spans more than ``ALBEDO_SPAN`` an albedo edge; each class dilated by 1 px.
SILHOUETTE_LOG_DEPTH_SPAN = 0.2
CREASE_SPAN = 0.2
ALBEDO_SPAN = 0.15
#: The oracle occluders' lattice is this many times finer than lighting_harness's (``--oracle-finer``).
ORACLE_FINER = 1.0
MAP_H = 256


def _psnr(mse: float) -> float:
    return float(10.0 * np.log10(1.0 / max(mse, 1e-12)))


def _true_map(b) -> np.ndarray:
    return resample(torch.from_numpy(np.asarray(b.load_envmap(), np.float64)), MAP_H, 2 * MAP_H).numpy()


def _sun_mask(true_map: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    sd = brightest_direction(true_map)
    d = envmap_directions(MAP_H, 2 * MAP_H)
    return d @ sd > np.cos(np.radians(SUN_CAP_DEG)), sd


def _span(x: np.ndarray) -> np.ndarray:
    """[H, W] the largest per-channel range of ``x`` [H, W, C] over each 3x3 neighbourhood."""
    return (nd.maximum_filter(x, size=(3, 3, 1)) - nd.minimum_filter(x, size=(3, 3, 1))).max(-1)


def edge_classes(albedo: np.ndarray, depth: np.ndarray, normal: np.ndarray) -> dict[str, np.ndarray]:
    """Disjoint [H, W] bool masks of one frame's true G-buffers (``albedo`` [H, W, 3], ``depth``
    [H, W] camera z, metres, 0 on sky, ``normal`` [H, W, 3]): ``silhouette`` (depth jumps),
    ``crease`` (normal changes, not a silhouette), ``albedo_edge`` (albedo changes only),
    ``flat`` (none of them) and ``sky`` (depth 0, not next to an edge); they cover the frame."""
    sky = depth <= 0
    logd = np.log(np.where(sky, 1e3, np.maximum(depth, 1e-3)))[..., None]
    grow = lambda m: nd.binary_dilation(m, iterations=1)  # noqa: E731
    sil = grow(_span(logd) > SILHOUETTE_LOG_DEPTH_SPAN)
    crease = grow(_span(normal) > CREASE_SPAN) & ~sil
    alb = grow(_span(albedo) > ALBEDO_SPAN) & ~sil & ~crease
    edge = sil | crease | alb
    return {"silhouette": sil, "crease": crease, "albedo_edge": alb, "flat": ~edge & ~sky, "sky": ~edge & sky}


def regions(run_dir: str, sigma: float) -> dict:
    from core.render.scenario import Scenario, render_scenario, views_from_frames
    from core.synth.evaluate import EvalSettings

    run, s = RunDir(run_dir), EvalSettings()
    b = open_bundle(run.scene_path())
    graph, sky, _ = run.load_scene()
    env_path, _ = run.latest_envmap()
    test = sorted(b.frames("test"), key=lambda f: (f.time_index, f.id))
    views = {v.name: v for v in views_from_frames(b, "all")}
    sc = Scenario(views=tuple(views[f.id] for f in test), envmap=np.asarray(read_envmap(env_path), np.float32),
                  base_exposure=b.manifest.ldr_exposure, gamma=b.manifest.ldr_gamma, rays_per_pixel=s.rays_per_pixel,
                  denoiser=s.denoiser, denoiser_fallback=None, normal_offset_m=s.normal_offset_m,
                  shadow_t_min_m=s.shadow_t_min_m, indirect_bounces=s.indirect_bounces, diffuse=s.diffuse,
                  masking=s.masking, opaque_above=s.opaque_above, object_solids=s.object_solids, outputs=("png",))
    with tempfile.TemporaryDirectory() as tmp:
        rr = np.stack(render_scenario(graph, sc, tmp).result.frames).astype(np.float64)
    nvs = []
    with torch.no_grad():
        for f in test:
            g = graph.compose(float(b.manifest.times[f.time_index])).detach()
            cam = Camera.from_bundle(b.camera(f), f)
            r = rasterize_gaussians(g, cam, settings=RasterSettings(threads=2))
            dirs = torch.from_numpy(cam.ray_directions()).to(g.dtype)
            nvs.append((r.color + (1 - r.opacity) * sky(dirs).to(g.dtype)).float().numpy())
    nvs = np.clip(np.stack(nvs), 0, 1).astype(np.float64)
    ref = np.stack([b.load_image(f) for f in test]).astype(np.float64)
    gts = [b.load_ground_truth(f) for f in test]
    h, w = ref.shape[1:3]
    dep = np.stack([g["depth"].reshape(h, w) for g in gts])
    nrm = np.stack([g["normal"].reshape(h, w, 3) for g in gts])
    rough = np.stack([g["roughness"].reshape(h, w) for g in gts])
    sky_m = dep <= 0
    ground = ~sky_m & (nrm[..., 2] > 0.8)
    wall = ~sky_m & (np.abs(nrm[..., 2]) < 0.3)
    glass = wall & (rough < 0.25)
    masks = {"sky": sky_m, "ground": ground, "wall_glass": glass, "wall_other": wall & ~glass,
             "rest": ~sky_m & ~ground & ~wall}
    alb = np.stack([g["albedo"].reshape(h, w, 3) for g in gts])
    per = [edge_classes(alb[i], dep[i], nrm[i]) for i in range(len(gts))]
    edges = {k: np.stack([p[k] for p in per]) for k in per[0]}
    low = lambda x: nd.gaussian_filter(x, (0, sigma, sigma, 0))  # noqa: E731
    out = {"frames": len(test), "sigma_px": sigma}
    for name, img in (("rerender", rr), ("nvs", nvs)):
        e_all = ((img - ref) ** 2).mean(-1)
        e_low = ((low(img) - low(ref)) ** 2).mean(-1)
        row = {"psnr": _psnr(e_all.mean()), "psnr_low": _psnr(e_low.mean()),
               "high_mse": float((((img - low(img)) - (ref - low(ref))) ** 2).mean()), "regions": {}}
        for k, m in masks.items():
            row["regions"][k] = {"pixels": round(float(m.mean()), 4), "share_of_error": round(float(e_all[m].sum() / e_all.sum()), 4),
                                 "share_of_low_error": round(float(e_low[m].sum() / e_low.sum()), 4),
                                 "low_mse": float(e_low[m].mean()) if m.any() else None,
                                 "mean": np.round(img[m].mean(0), 4).tolist(), "mean_capture": np.round(ref[m].mean(0), 4).tolist()}
        row["edge_classes"] = {k: {"pixels": round(float(m.mean()), 4), "psnr": round(_psnr(float(e_all[m].mean())), 3),
                                   "share_of_error": round(float(e_all[m].sum() / e_all.sum()), 4)}
                               for k, m in edges.items() if m.any()}
        out[name] = row
    out["edge_class_gap_db"] = {k: round(out["nvs"]["edge_classes"][k]["psnr"] - out["rerender"]["edge_classes"][k]["psnr"], 3)
                                for k in out["rerender"]["edge_classes"]}
    return out


def _stage_frames(run_dir: str, stage: str, occluders: str, diffuse: str | None = None):
    from core.stages.pbr import _frames

    b = open_bundle(RunDir(run_dir).scene_path())
    g = SceneGraph.load(Path(run_dir) / stage / "checkpoint" / "scene_graph.pt")
    if occluders in ("oracle", "oracle_only"):
        from lighting_harness import ORACLE_EDGE_REFINE, ORACLE_GAUSSIANS, ORACLE_MAX_SPACING_M
        from core.synth.oracle import OracleSettings, street_scene_graph
        from core.synth.prepare import synth_config_of

        st = OracleSettings(max_spacing=ORACLE_MAX_SPACING_M / ORACLE_FINER, edge_refine=ORACLE_EDGE_REFINE,
                            thin_slivers=True)
        og, _, _ = street_scene_graph(synth_config_of(b), (0,), settings=st,
                                      budget=int(ORACLE_GAUSSIANS * ORACLE_FINER ** 2))
        g.occluders = og._static_part().detach().to(g.occluders.means.dtype)
        if occluders == "oracle_only":  # shadow rays meet the true meshes alone, not the reconstruction
            g.shadow_static = lambda: g.occluders
    cfg = profile_settings("quick", "pbr")
    if diffuse is not None:
        cfg = dataclasses.replace(cfg, diffuse=diffuse)
    frames, _ = _frames(g, b, cfg)
    train = sorted(b.frames("train"), key=lambda f: (f.time_index, f.id))
    pick = np.unique(np.linspace(0, len(train) - 1, min(cfg.max_frames, len(train))).round().astype(int))
    return b, g, cfg, frames, [train[int(i)] for i in pick]


def gains(run_dir: str, stage: str, occluders: str, albedo: str, bounces: int | None, every: int, pixels: int,
          diffuse: str | None = None, map_name: str = "true") -> dict:
    b, _g, cfg, frames, train = _stage_frames(run_dir, stage, occluders, diffuse)
    if bounces is not None:
        cfg = dataclasses.replace(cfg, indirect_bounces=bounces)
    if map_name == "true":
        true_map = _true_map(b)
    else:  # one of the run's own maps (e.g. pbr/envmap_prior.exr), split at its own brightest direction
        true_map = resample(torch.from_numpy(np.asarray(read_envmap(Path(run_dir) / map_name), np.float64)),
                            MAP_H, 2 * MAP_H).numpy()
    sun, _ = _sun_mask(true_map)
    parts = {"sun": np.where(sun[..., None], true_map, 1e-6), "sky": np.where(sun[..., None], 1e-6, true_map)}
    envs = {k: EnvironmentMap(torch.from_numpy(v)) for k, v in parts.items()}
    ps = cfg.pbr_settings(rays_per_pixel=64, exposure=1.0, gamma=1.0, threads=2, seed=0)
    m = b.manifest
    hdr = {k: [] for k in parts}
    tgt, nrm, alb, rgh = [], [], [], []
    gen = torch.Generator().manual_seed(0)
    for i in range(0, len(frames), every):
        f, fr = frames[i], train[i]
        gt = b.load_ground_truth(fr)
        if albedo in ("gt", "gt_materials"):
            o = f.gbuf["opacity"]
            f.gbuf["albedo"] = torch.from_numpy(gt["albedo"].reshape(*o.shape[:2], 3)).to(o.dtype) * o
            if albedo == "gt_materials":  # roughness and metallic too
                for k in ("roughness", "metallic"):
                    f.gbuf[k] = torch.from_numpy(gt[k].reshape(*o.shape[:2], 1)).to(o.dtype) * o
        idx = f.nonsky[torch.randperm(f.nonsky.numel(), generator=gen)[:pixels]]
        for k, env in envs.items():
            r = render_pbr(f.gbuf, f.camera, env, settings=ps, tracers=f.tracers, pixels=idx,
                           generator=torch.Generator().manual_seed(1))
            hdr[k].append(r.hdr.detach().double().numpy().reshape(-1, 3))
        tgt.append(f.target[idx].double().numpy())
        nrm.append(gt["normal"].reshape(-1, 3)[idx.numpy()])
        alb.append(gt["albedo"].reshape(-1, 3)[idx.numpy()])
        rgh.append(gt["roughness"].reshape(-1)[idx.numpy()])
    hs, hk, t = np.concatenate(hdr["sun"]), np.concatenate(hdr["sky"]), np.concatenate(tgt)
    nrm, alb, rgh = np.concatenate(nrm), np.concatenate(alb), np.concatenate(rgh)
    best = (np.inf, 1.0, 1.0)
    grid = np.exp(np.linspace(np.log(0.1), np.log(10.0), 61)) if map_name != "true" else None
    for gs in (grid if grid is not None else np.arange(0.2, 2.001, 0.05)):
        for gk in (grid if grid is not None else np.arange(0.4, 2.001, 0.05)):
            p = np.clip((gs * hs + gk * hk) * m.ldr_exposure, 0, 1) ** (1 / m.ldr_gamma)
            loss = float(np.abs(p - t).mean())
            if loss < best[0]:
                best = (loss, float(gs), float(gk))
    p1 = np.clip((hs + hk) * m.ldr_exposure, 0, 1) ** (1 / m.ldr_gamma)
    lin_t = np.clip(t, 0, 0.999) ** m.ldr_gamma / m.ldr_exposure
    lin_p = hs + hk
    shade = lin_t.mean(-1) / np.maximum(alb.mean(-1), 1e-3)
    out = {"map": map_name, "stage": stage, "occluders": occluders, "albedo": albedo, "indirect_bounces": cfg.indirect_bounces,
           "diffuse": cfg.diffuse,
           "samples": int(len(t)), "l1_at_true_map": float(np.abs(p1 - t).mean()), "l1_best": best[0],
           "gain_sun": round(best[1], 2), "gain_sky": round(best[2], 2), "capture_over_render_by_shading_quintile": {}}
    wall = np.abs(nrm[:, 2]) < 0.3
    for name, msk in (("ground", nrm[:, 2] > 0.8), ("wall", wall & (rgh >= 0.25)), ("glass", wall & (rgh < 0.25))):
        ok = msk & (t.max(-1) < 0.97) & (alb.mean(-1) > 0.01)
        if ok.sum() < 50:
            continue
        q = np.quantile(shade[ok], [0, 0.2, 0.4, 0.6, 0.8, 1.0])
        ratio = lin_t.mean(-1) / np.maximum(lin_p.mean(-1), 1e-6)
        out["capture_over_render_by_shading_quintile"][name] = [
            round(float(np.median(ratio[ok & (shade >= q[j]) & (shade <= q[j + 1])])), 3) for j in range(5)]
    return out


def visibility(run_dir: str, stage: str, occluders: str, every: int) -> dict:
    from lighting_harness import occluder_tracer

    b, _g, _cfg, frames, train = _stage_frames(run_dir, stage, occluders)
    oracle = occluder_tracer(b, "oracle")
    _, sd = _sun_mask(_true_map(b))
    acc = {"ground": [], "wall": []}
    for i in range(0, len(frames), every):
        f, fr = frames[i], train[i]
        gt = b.load_ground_truth(fr)
        o = f.gbuf["opacity"].reshape(-1).double()
        dep = (f.gbuf["depth"].reshape(-1).double() / o.clamp_min(1e-3)).numpy()
        n = f.gbuf["normal"].reshape(-1, 3).double().numpy()
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
        rays = f.camera.ray_directions().reshape(-1, 3)
        pose = f.camera.pose_numpy()
        pts = pose[:3, 3] + rays * (dep / (rays @ pose[:3, 2]))[:, None]
        gn = gt["normal"].reshape(-1, 3)
        ok = (o.numpy() > 0.95) & (gt["depth"].reshape(-1) > 0) & (gn @ sd > 0.2)
        for name, msk in (("ground", gn[:, 2] > 0.8), ("wall", np.abs(gn[:, 2]) < 0.3)):
            sel = np.flatnonzero(ok & msk)
            if not len(sel):
                continue
            org = pts[sel] + 0.1 * n[sel]
            d = np.broadcast_to(sd, (len(sel), 3)).copy()
            v = np.ones(len(sel))
            for tr in f.tracers:
                v *= tr(torch.from_numpy(org).float(), torch.from_numpy(d).float(), None).double().numpy()
            acc[name].append(np.stack([v, oracle(org, d)], 1))
    out = {"stage": stage, "occluders": occluders}
    for name, rows in acc.items():
        v = np.concatenate(rows)
        lit = v[:, 1] > 0.5
        out[name] = {"true_lit_fraction": round(float(lit.mean()), 4),
                     "visibility_where_true_lit": round(float(v[lit, 0].mean()), 4),
                     "visibility_where_true_shadow": round(float(v[~lit, 0].mean()), 4)}
    return out


def lighting(run_dir: str) -> dict:
    b = open_bundle(RunDir(run_dir).scene_path())
    true_map = _true_map(b)
    sun, sd = _sun_mask(true_map)
    d = envmap_directions(MAP_H, 2 * MAP_H)
    sa = np.broadcast_to(np.asarray(envmap_solid_angles(MAP_H, 2 * MAP_H)).reshape(MAP_H, -1), (MAP_H, 2 * MAP_H))
    sky = ~sun & (d[..., 2] > 0)
    up, facing = np.array([0.0, 0.0, 1.0]), np.array([sd[0], sd[1], 0.0]) / np.linalg.norm(sd[:2])

    def irr(e, n, m):
        return np.round((e * (sa * np.maximum(d @ n, 0.0))[..., None])[m].sum(0), 3).tolist()

    maps = {"true": true_map}
    for rel in ("pbr/envmap_prior.exr", "pbr/envmap.exr", "joint/envmap.exr"):
        p = Path(run_dir) / rel
        if p.is_file():
            maps[rel] = resample(torch.from_numpy(np.asarray(read_envmap(p), np.float64)), MAP_H, 2 * MAP_H).numpy()
    return {k: {"sun_normal_incidence": irr(e, sd, sun), "sky_on_horizontal": irr(e, up, sky),
                "sky_on_wall_facing_sun": irr(e, facing, sky)} for k, e in maps.items()}


def albedo_bake(run_dir: str, stages: list[str]) -> dict:
    from core.numerics import OPACITY_EPS

    b = open_bundle(RunDir(run_dir).scene_path())
    frames = sorted(b.frames("train"), key=lambda f: (f.time_index, f.id))[::4]
    m = b.manifest
    out = {}
    for st in stages:
        g = SceneGraph.load(Path(run_dir) / st / "checkpoint" / "scene_graph.pt")
        shade, ratio, kind = [], [], []
        with torch.no_grad():
            for f in frames:
                r = rasterize_gaussians(g.compose(float(m.times[f.time_index])).detach(), Camera.from_bundle(b.camera(f), f),
                                        settings=RasterSettings(threads=2))
                a = (r.albedo / r.opacity.clamp_min(OPACITY_EPS)).numpy()
                h, w = a.shape[:2]
                gt = b.load_ground_truth(f)
                ga, gn = gt["albedo"].reshape(h, w, 3), gt["normal"].reshape(h, w, 3)
                img = b.load_image(f).astype(np.float64) ** m.ldr_gamma / m.ldr_exposure
                ok = ((gt["depth"].reshape(h, w) > 0) & (ga.mean(-1) > 0.04) & (r.opacity[..., 0].numpy() > 0.95)
                      & (b.load_image(f).max(-1) < 0.97) & (gt["metallic"].reshape(h, w) < 0.1))
                shade.append(img.mean(-1)[ok] / ga.mean(-1)[ok])
                ratio.append(a.mean(-1)[ok] / ga.mean(-1)[ok])
                glass = gt["roughness"].reshape(h, w) < 0.25
                kind.append(np.where(gn[..., 2] > 0.8, 0, np.where(np.abs(gn[..., 2]) < 0.3, np.where(glass, 3, 1), 2))[ok])
        shade, ratio, kind = map(np.concatenate, (shade, ratio, kind))
        row = {}
        for name, k in (("ground", 0), ("wall", 1), ("glass", 3)):
            s_, r_ = shade[kind == k], ratio[kind == k]
            if len(s_) < 50:
                continue
            q = np.quantile(s_, [0, 0.2, 0.4, 0.6, 0.8, 1.0])
            row[name] = {"shading_quintile_edges": np.round(q, 3).tolist(),
                         "albedo_over_true": [round(float(np.median(r_[(s_ >= q[j]) & (s_ <= q[j + 1])])), 3)
                                              for j in range(5)]}
        out[st] = row
    return out


def bounce_check(run_dir: str, rays: int, every: int) -> dict:
    """The ``bounce`` check (module docstring)."""
    from lighting_harness import occluder_tracer

    K = rays
    out: dict = {"rays": K, "hits": []}
    b, g, cfg, frames, train = _stage_frames(run_dir, 'volume2', 'oracle')
    cfg = dataclasses.replace(cfg, indirect_bounces=0)
    env = EnvironmentMap(torch.from_numpy(_true_map(b)))
    ps = cfg.pbr_settings(rays_per_pixel=64, exposure=1.0, gamma=1.0, threads=2, seed=0)
    orc = occluder_tracer(b, 'oracle')
    m = b.manifest; rng = np.random.default_rng(0); gen = torch.Generator().manual_seed(0)
    T, D, I, N, A, R = [], [], [], [], [], []
    for i in range(0, len(frames), every):
        f, fr = frames[i], train[i]; gt = b.load_ground_truth(fr); H, W = f.camera.height, f.camera.width
        o = f.gbuf['opacity']; f.gbuf['albedo'] = torch.from_numpy(gt['albedo'].reshape(H, W, 3)).to(o.dtype) * o
        idx = f.nonsky[torch.randperm(f.nonsky.numel(), generator=gen)[:3000]]
        r = render_pbr(f.gbuf, f.camera, env, settings=ps, tracers=f.tracers, pixels=idx, generator=torch.Generator().manual_seed(1))
        direct = r.hdr.detach().double().numpy().reshape(-1, 3)
        cap = (b.load_image(fr).reshape(-1, 3).astype(np.float64) ** m.ldr_gamma) / m.ldr_exposure
        dep = (f.gbuf['depth'].reshape(-1).double() / o.reshape(-1).double().clamp_min(1e-3)).numpy()
        dep[o.reshape(-1).numpy() < 0.5] = np.inf
        n = f.gbuf['normal'].reshape(-1, 3).double().numpy(); n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
        rays = f.camera.ray_directions().reshape(-1, 3); pose = f.camera.pose_numpy(); R_, t_ = pose[:3, :3], pose[:3, 3]
        pts = t_ + rays * (np.where(np.isfinite(dep), dep, 0) / (rays @ pose[:3, 2]))[:, None]
        sel = idx.numpy(); P = pts[sel]; Nn = n[sel]
        # cosine directions
        u1, u2 = rng.random((len(sel), K)), rng.random((len(sel), K))
        rr, ph = np.sqrt(u1), 2 * np.pi * u2
        loc = np.stack([rr * np.cos(ph), rr * np.sin(ph), np.sqrt(1 - u1)], -1)
        tmp = np.where(np.abs(Nn[:, 2:3]) < 0.9, np.array([0, 0, 1.0]), np.array([1.0, 0, 0]))
        tx = np.cross(tmp, Nn); tx /= np.linalg.norm(tx, axis=-1, keepdims=True); ty = np.cross(Nn, tx)
        wi = loc[..., :1] * tx[:, None] + loc[..., 1:2] * ty[:, None] + loc[..., 2:3] * Nn[:, None]
        org = P[:, None] + 0.1 * Nn[:, None]
        Lhit = np.zeros((len(sel), K, 3)); status = np.zeros((len(sel), K), int)  # 0 open, 1 hit on screen, 2 undecided
        steps = np.concatenate([np.linspace(0.15, 2, 10), np.linspace(2.3, 25, 40)])
        done = np.zeros((len(sel), K), bool)
        for s in steps:
            q = org + wi * s
            pc = (q - t_) @ R_; z = pc[..., 2]
            ok = (z > 0.1) & ~done
            u = np.where(ok, f.camera.fx * pc[..., 0] / np.where(ok, z, 1) + f.camera.cx, -1)
            v = np.where(ok, f.camera.fy * pc[..., 1] / np.where(ok, z, 1) + f.camera.cy, -1)
            ins = ok & (u >= 0) & (u < W) & (v >= 0) & (v < H)
            pix = np.where(ins, v.astype(int).clip(0, H - 1) * W + u.astype(int).clip(0, W - 1), 0)
            zb = dep[pix]
            hit = ins & (z > zb + 0.05) & (z < zb + 1.5)
            Lhit[hit] = cap[pix[hit]]; status[hit] = 1; done |= hit
        # blocked but not found on screen: oracle says blocked -> frame mean of the capture (non-sky)
        blocked = orc(np.repeat(org, K, 0).reshape(-1, 3), wi.reshape(-1, 3)).reshape(len(sel), K) < 0.5
        fallback = blocked & ~done
        meanL = cap[np.isfinite(dep)].mean(0)
        Lhit[fallback] = meanL
        # a screen hit the oracle calls unblocked is sky: drop it (the direct term has the sky)
        Lhit[done & ~blocked] = 0
        alb = gt['albedo'].reshape(-1, 3)[sel]; met = gt['metallic'].reshape(-1)[sel]
        ind = (1 - met)[:, None] * alb * Lhit.mean(1)
        T.append(cap[sel]); D.append(direct); I.append(ind); N.append(gt['normal'].reshape(-1, 3)[sel]); A.append(alb); R.append(gt['roughness'].reshape(-1)[sel])
        out["hits"].append({"frame": i, "on_screen": round(float(done.mean()), 3), "off_screen_blocked": round(float(fallback.mean()), 3)})
    T, D, I, N, A, R = map(np.concatenate, (T, D, I, N, A, R))
    shade = T.mean(-1) / np.maximum(A.mean(-1), 1e-3)
    wall = np.abs(N[:, 2]) < 0.3
    for nm, msk in (('ground', N[:, 2] > 0.8), ('wall', wall & (R >= 0.25))):
        ok = msk & (T.max(-1) < 0.9) & (A.mean(-1) > 0.04)
        q = np.quantile(shade[ok], [0, .2, .4, .6, .8, 1])
        for lab, pred in (('direct only', D), ('direct + ssgi bounce', D + I)):
            rat = T.mean(-1) / np.maximum(pred.mean(-1), 1e-6)
            out.setdefault(nm, {})[lab] = [round(float(np.median(rat[ok & (shade >= q[j]) & (shade <= q[j + 1])])), 3) for j in range(5)]

    return out

def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("what", choices=["regions", "gains", "visibility", "lighting", "albedo", "bounce"])
    ap.add_argument("run")
    ap.add_argument("--stage", default="volume2", help="the graph whose G-buffers the PBR pass shades (gains, visibility)")
    ap.add_argument("--occluders", default="run", choices=["run", "oracle", "oracle_only"],
                    help="the run's completed facades, the true meshes in their place, or the true meshes alone "
                         "(without the reconstruction's Gaussians) as shadow casters")
    ap.add_argument("--oracle-finer", type=float, default=1.0,
                    help="oracle occluders: spacing divided by this, Gaussian budget times its square")
    ap.add_argument("--diffuse", default=None, choices=["lambert", "burley"], help="diffuse lobe (gains; default the stage's)")
    ap.add_argument("--albedo", default="run", choices=["run", "gt", "gt_materials"],
                    help="the reconstruction's albedo, the true albedo, or the true albedo, roughness and metallic (gains)")
    ap.add_argument("--bounces", type=int, default=None, help="indirect bounces (default: the pbr stage's)")
    ap.add_argument("--every", type=int, default=3, help="every this many of the stage's training frames")
    ap.add_argument("--pixels", type=int, default=3000, help="pixels per frame (gains)")
    ap.add_argument("--stages", default="volume2,joint", help="graphs compared (albedo)")
    ap.add_argument("--map", default="true", help="gains: the map split into sun and sky: 'true' (the bundle's) or a "
                    "map of the run, e.g. pbr/envmap_prior.exr (gains searched 0.1-10)")
    ap.add_argument("--sigma", type=float, default=3.0, help="low-pass of the regions split, pixels")
    a = ap.parse_args()
    global ORACLE_FINER
    ORACLE_FINER = a.oracle_finer
    if a.what == "regions":
        res = regions(a.run, a.sigma)
    elif a.what == "gains":
        res = gains(a.run, a.stage, a.occluders, a.albedo, a.bounces, a.every, a.pixels, a.diffuse, a.map)
    elif a.what == "visibility":
        res = visibility(a.run, a.stage, a.occluders, a.every)
    elif a.what == "bounce":
        res = bounce_check(a.run, 24, a.every)
    elif a.what == "albedo":
        res = albedo_bake(a.run, [x for x in a.stages.split(",") if x])
    else:
        res = lighting(a.run)
    print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
