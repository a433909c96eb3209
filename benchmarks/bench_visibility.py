"""The reconstruction's shadow rays against the true meshes: how much of each map's light reaches
the street, per held-back map, measured apart from materials and normals.

Relit PSNR mixes three errors: materials, normals and visibility (what the Gaussians let through
toward the light). This benchmark isolates the last one. At the ground-truth surface points and
normals of the bundle's relit test frames (its Mitsuba G-buffers: camera z-depth and normals),
for ``--dirs`` light directions drawn from each map in proportion to radiance x solid angle, it
traces

* the true scene: Mitsuba's ``ray_test`` against the generator's meshes at that time (street,
  parked and moving cars), from 1 cm off the surface;
* the reconstruction, as a relight request traces it: the scene graph composed at the frame's
  time plus its shadow-only occluders (:mod:`core.stages.occluders`), from
  ``Scenario.normal_offset_m`` off the surface, ignoring Gaussians nearer than
  ``Scenario.shadow_t_min_m``; and the same without the occluders.

Per pixel, the light-weighted visibility ``E = sum_k V_k cos_k / sum_k cos_k`` (the share of the
map's direct light, cosine-weighted, that reaches the point; the draws already carry radiance x
solid angle). Reported per map, over the non-sky pixels of every relit frame (every
``--stride``-th pixel): the mean of E true and reconstructed (with and without occluders), the
mean absolute difference, and the bias split into ground (true normal z > 0.9) and walls
(|normal z| < 0.3); a PNG per map (one frame: true | reconstructed | reconstructed - true, grey =
equal, white = the reconstruction lets more light through).

Also per map, on that frame: the share of the non-sky radiance of Mitsuba's frame that is
indirect (its ``max_depth`` of the bundle against ``max_depth = 2``, direct light only, same
sampler seed, ``--spp``). The project's PBR pass renders direct light only, so this share is what
it misses with exact visibility; a leaky visibility partly hides it.

    python benchmarks/bench_visibility.py RUN --out benchmarks/results/visibility.json

Reads ground truth: a benchmark, never the product path.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.eval_pipeline import machine  # noqa: E402


def sample_directions(env: np.ndarray, k: int, seed: int) -> np.ndarray:
    """[k, 3] world directions drawn from an equirect map in proportion to its mean radiance
    times each texel's solid angle."""
    from core.conventions import pixel_to_direction

    h, w = env.shape[:2]
    weight = np.asarray(env, np.float64).mean(-1) * np.sin((np.arange(h) + 0.5) / h * np.pi)[:, None]
    p = weight.ravel() / weight.sum()
    idx = np.random.default_rng(seed).choice(len(p), k, p=p)
    return np.stack([pixel_to_direction(*np.unravel_index(i, (h, w)), h, w) for i in idx])


def light_weighted(vis: np.ndarray, cos: np.ndarray) -> np.ndarray:
    """[P] share of the sampled light reaching each point: sum V cos / sum cos (0 where no sample
    is above the point's horizon)."""
    den = cos.sum(1)
    return np.where(den > 0, (vis * cos).sum(1) / np.maximum(den, 1e-12), 0.0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="a reconstruction run directory (brdf reconstruct --out)")
    ap.add_argument("--dirs", type=int, default=64, help="light directions drawn per map")
    ap.add_argument("--stride", type=int, default=2, help="every this many pixels in x and y")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--spp", type=int, default=64, help="Mitsuba samples per pixel of the indirect-share frames")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "visibility.json"))
    a = ap.parse_args()
    if a.dirs < 1 or a.stride < 1:
        ap.error("--dirs and --stride: must be >= 1")

    import torch

    from core.bundle import open_bundle
    from core.camera import Camera
    from core.gaussians import Gaussians
    from core.io.images import write_png
    from core.pbr.visibility import GaussianTracer, TraceSettings
    from core.render.scenario import Scenario
    from core.stages.chain import RunDir
    from core.synth import profile
    from core.synth.generate import ego_positions
    from core.synth.mitsuba_backend import _scene, mitsuba, render_beauty
    from core.synth.street import make_street

    torch.set_num_threads(a.threads)
    t0 = time.perf_counter()
    run = RunDir(a.run)
    b = open_bundle(run.scene_path(), validate=False)
    m = b.manifest
    if m.ground_truth is None or not m.ground_truth.relit:
        raise SystemExit(f"{b.name}: the bundle has no relit ground truth")
    cfg_src = m.source.get("config")
    if cfg_src is None:
        raise SystemExit(f"{b.name}: not a generated bundle (no generator config to rebuild its meshes from)")
    cfg = profile("quick", **{k: tuple(v) if isinstance(v, list) else v for k, v in cfg_src.items()})
    street = make_street(cfg, ego_positions(cfg))
    mi = mitsuba()
    graph, _sky, stage = run.load_scene()
    defaults = {f.name: f.default for f in dataclasses.fields(Scenario)}
    n_off, t_min = defaults["normal_offset_m"], defaults["shadow_t_min_m"]
    trace = TraceSettings(t_min=t_min, threads=a.threads)
    relit_ids = sorted({fid for rl in m.ground_truth.relit for fid in rl.frames})
    frames = [f for f in b.frames("test") if f.id in relit_ids]
    maps = [("capture", b.load_envmap())] + [(rl.name, b.load_envmap(rl.name)) for rl in m.ground_truth.relit]

    # per frame: true points, normals, the three tracers (built once per frame, shared by the maps)
    per_frame = []
    for f in frames:
        cam = Camera.from_bundle(b.camera(f), f)
        gt = b.load_ground_truth(f)
        h, w = cam.height, cam.width
        depth = gt["depth"].reshape(h, w).astype(np.float64)
        normal = gt["normal"].reshape(h, w, 3).astype(np.float64)
        dirs = cam.ray_directions()
        c2w = cam.pose_numpy()
        pts = c2w[:3, 3] + dirs / (dirs @ c2w[:3, 2])[..., None] * depth[..., None]
        sel = np.zeros((h, w), bool)
        sel[::a.stride, ::a.stride] = True
        sel &= depth > 0
        g = graph.compose(float(m.times[f.time_index])).detach()
        with_occ = Gaussians.cat([g, graph.occluders.detach().to(g.dtype)]) if graph.occluders is not None else g
        per_frame.append({
            "frame": f.id, "sel": sel, "p": pts[sel], "n": normal[sel],
            "scene": _scene(street.parts_at(f.time_index), {"type": "direct"}, None, None),
            "rec": GaussianTracer.from_gaussians(with_occ, trace),
            "rec_no_occ": GaussianTracer.from_gaussians(g, trace),
        })

    rows, pngs = {}, {}
    out = Path(a.out)
    for name, env in maps:
        dirs = sample_directions(env, a.dirs, a.seed)
        acc = {"true": [], "rec": [], "rec_no_occ": [], "nz": []}
        for i, fr in enumerate(per_frame):
            p, n = fr["p"], fr["n"]
            cos = np.clip(n @ dirs.T, 0.0, None)  # [P, K]
            v_true = np.zeros_like(cos)
            for k, d in enumerate(dirs):
                dv = mi.Vector3f(*d)
                for j in np.nonzero(cos[:, k] > 0)[0]:
                    o = p[j] + 0.01 * n[j]
                    v_true[j, k] = 0.0 if fr["scene"].ray_test(mi.Ray3f(mi.Point3f(*o), dv)) else 1.0
            o_t = torch.from_numpy(p + n_off * n)
            e = {"true": light_weighted(v_true, cos)}
            for key in ("rec", "rec_no_occ"):
                v = np.zeros_like(cos)
                for k, d in enumerate(dirs):
                    v[:, k] = fr[key](o_t, torch.from_numpy(np.broadcast_to(d, p.shape).copy())).numpy()
                e[key] = light_weighted(v, cos)
            for key in e:
                acc[key].append(e[key])
            acc["nz"].append(n[:, 2])
            if i == len(per_frame) // 2:  # the picture: the middle relit frame
                h, w = fr["sel"].shape
                imgs = []
                for arr in (e["true"], e["rec"], 0.5 + 0.5 * (e["rec"] - e["true"])):
                    im = np.zeros((h, w))
                    im[fr["sel"]] = arr
                    imgs.append(im[::a.stride, ::a.stride])
                pngs[name] = (fr["frame"], np.concatenate(imgs, 1))
        cat = {k: np.concatenate(v) for k, v in acc.items()}
        ground, wall = cat["nz"] > 0.9, np.abs(cat["nz"]) < 0.3
        diff = cat["rec"] - cat["true"]
        rows[name] = {
            "true_mean": round(float(cat["true"].mean()), 4),
            "reconstruction_mean": round(float(cat["rec"].mean()), 4),
            "reconstruction_without_occluders_mean": round(float(cat["rec_no_occ"].mean()), 4),
            "abs_diff_mean": round(float(np.abs(diff).mean()), 4),
            "abs_diff_mean_without_occluders": round(float(np.abs(cat["rec_no_occ"] - cat["true"]).mean()), 4),
            "bias_ground": round(float(diff[ground].mean()), 4) if ground.any() else None,
            "bias_walls": round(float(diff[wall].mean()), 4) if wall.any() else None,
            "points": int(len(diff)),
        }
        print(f"{name:10s} true {rows[name]['true_mean']:.3f}  recon {rows[name]['reconstruction_mean']:.3f} "
              f"(no occluders {rows[name]['reconstruction_without_occluders_mean']:.3f})  |diff| "
              f"{rows[name]['abs_diff_mean']:.3f}  bias ground {rows[name]['bias_ground']}  walls {rows[name]['bias_walls']}",
              flush=True)
        fid, img = pngs[name]
        write_png(out.with_name(f"{out.stem}_{name}.png"), np.repeat(np.clip(img, 0, 1)[..., None], 3, -1))
        rows[name]["png_frame"] = fid
        f = next(fr for fr in frames if fr.id == fid)
        cam = Camera.from_bundle(b.camera(f), f)
        parts = street.parts_at(f.time_index)
        env32 = np.asarray(env, np.float32)
        direct = render_beauty(parts, env32, cam, spp=a.spp, max_depth=2, seed=a.seed + 1)
        full = render_beauty(parts, env32, cam, spp=a.spp, max_depth=cfg.max_depth, seed=a.seed + 1)
        gt = b.load_ground_truth(f)
        nonsky = gt["depth"].reshape(cam.height, cam.width) > 0
        ground = nonsky & (gt["normal"].reshape(cam.height, cam.width, 3)[..., 2] > 0.9)
        rows[name]["indirect_share"] = round(float(1 - direct[nonsky].mean() / full[nonsky].mean()), 4)
        rows[name]["indirect_share_ground"] = round(float(1 - direct[ground].mean() / full[ground].mean()), 4)
        print(f"{'':10s} indirect share of Mitsuba's radiance ({fid}, max_depth {cfg.max_depth} vs 2): "
              f"{rows[name]['indirect_share']:.3f} (ground {rows[name]['indirect_share_ground']:.3f})", flush=True)

    res = {"machine": machine(), "run": str(run.root), "scene": b.name, "graph_stage": stage,
           "frames": [fr["frame"] for fr in per_frame], "dirs_per_map": a.dirs, "stride": a.stride, "seed": a.seed,
           "indirect_spp": a.spp, "mitsuba_max_depth": cfg.max_depth,
           "reconstruction_traced_as": {"normal_offset_m": n_off, "shadow_t_min_m": t_min},
           "maps": rows, "seconds": round(time.perf_counter() - t0, 1)}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print("written", out, f"({res['seconds']} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
