"""Blotches and floaters of a reconstruction, measured before and after their fixes.

For each reconstruction run (``brdf reconstruct --out RUN``) on a bundle with ground truth:

* sky floaters: the fraction of sky-mask pixels that the reconstruction covers with opacity
  > 0.1 (train and test views), and the novel-view PSNR;
* normals that flip or tilt: the fraction of Gaussians (opacity > 0.5) whose normal faces away
  from every training camera that sees the Gaussian's centre, and the mean ``1 - |a . n|`` of the
  shortest axis ``a`` against the normal (0: flat disks lying in their surface);
* self-shadowing: the relit frames (the bundle's held-back maps, OIDN) with the shadow-ray
  settings before (``normal_offset`` 0.02 m, ``t_min`` 0.01 m: the PBR pass's defaults, made for
  thin oracle Gaussians) and after (the relight defaults of ``core.render.scenario.Scenario``), and
  without shadows; PSNR / SSIM against Mitsuba, and a side-by-side PNG of one frame.

    python benchmarks/bench_artifacts.py RUN [RUN ...] --label before=RUN_A --out benchmarks/results/artifacts.json

Reads ground truth: a benchmark, never the product path.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def sky_floaters(run, b) -> dict:
    from core.camera import Camera
    from core.raster import RasterSettings, rasterize_gaussians

    graph, _sky, stage = run.load_scene()
    out = {"graph_stage": stage}
    for split in ("train", "test"):
        fr = []
        for f in b.frames(split):
            c = b.camera(f)
            g = graph.compose(float(b.manifest.times[f.time_index])).detach()
            r = rasterize_gaussians(g, Camera.from_bundle(c, f), settings=RasterSettings())
            sky = b.load_ground_truth(f)["depth"].reshape(c.height, c.width) <= 0
            if sky.any():
                fr.append(float((r.opacity[..., 0].numpy()[sky] > 0.1).mean()))
        out[f"sky_pixels_covered_{split}"] = round(float(np.mean(fr)), 4) if fr else None
    return out


def normals(run, b) -> dict:
    from core.rotations import quat_to_rotmat

    graph, _sky, _stage = run.load_scene()
    g = graph.background.detach()
    keep = g.opacities().reshape(-1) > 0.5
    means, n = g.means[keep].double(), torch.nn.functional.normalize(g.normals[keep].double(), dim=-1)
    facing = torch.zeros(len(means), dtype=torch.bool)
    seen = torch.zeros(len(means), dtype=torch.bool)
    for f in b.frames("train"):
        c2w = torch.as_tensor(np.asarray(f.cam_to_world), dtype=torch.float64)
        to_cam = c2w[:3, 3] - means
        w2c = torch.linalg.inv(c2w)
        pc = means @ w2c[:3, :3].T + w2c[:3, 3]
        c = b.camera(f)
        z = pc[:, 2].clamp_min(1e-6)
        u, v = c.fx * pc[:, 0] / z + c.cx, c.fy * pc[:, 1] / z + c.cy
        vis = (pc[:, 2] > 0.3) & (u >= 0) & (u < c.width) & (v >= 0) & (v < c.height)
        seen |= vis
        facing |= vis & ((n * to_cam).sum(-1) > 0)
    rot = quat_to_rotmat(g.quats[keep].double())
    ax = g.log_scales[keep].argmin(1)
    a = rot.gather(2, ax.view(-1, 1, 1).expand(-1, 3, 1))[..., 0]
    return {"gaussians": int(keep.sum()), "flipped_fraction": round(float((seen & ~facing).sum() / max(int(seen.sum()), 1)), 4),
            "tilt_1_minus_abs_dot": round(float((1 - (a * n).sum(-1).abs()).mean()), 4)}


def relit(run, b, variants: dict, png: Path | None) -> dict:
    import tempfile

    from core.io.exr import read_exr
    from core.io.images import write_png
    from core.metrics import psnr, ssim
    from core.render.scenario import Scenario, render_scenario, views_from_frames
    from core.tonemap import hdr_to_ldr

    graph, _sky, _stage = run.load_scene()
    m = b.manifest
    views = {v.name: v for v in views_from_frames(b, "all")}
    res: dict = {}
    strips = []
    for name, kw in variants.items():
        ps, ss = [], []
        for k, rl in enumerate(m.ground_truth.relit):
            frames = [f for f in b.frames("test") if f.id in rl.frames]
            sc = Scenario(views=tuple(views[f.id] for f in frames), envmap=b.load_envmap(rl.name),
                          base_exposure=m.ldr_exposure, gamma=m.ldr_gamma, outputs=("png",), **kw)
            with tempfile.TemporaryDirectory() as tmp:
                clip = render_scenario(graph, sc, tmp).result.frames
            for i, (p, f) in enumerate(zip(clip, frames)):
                ref = read_exr(b.path(rl.frames[f.id]))
                ref = hdr_to_ldr(np.asarray(ref["rgb"] if isinstance(ref, dict) else ref, np.float32)[..., :3],
                                 m.ldr_exposure, m.ldr_gamma)
                pt, rt = torch.from_numpy(np.clip(p, 0, 1)), torch.from_numpy(ref)
                ps.append(float(psnr(pt, rt)))
                ss.append(float(ssim(pt, rt)))
                if k == 0 and i == len(frames) // 2:
                    strips.append((name, p, ref))
        res[name] = {"relit_psnr": round(float(np.mean(ps)), 3), "relit_ssim": round(float(np.mean(ss)), 4),
                     "settings": kw}
    if png is not None and strips:
        row = np.concatenate([x[1] for x in strips] + [strips[0][2]], 1)
        write_png(png, np.clip(row, 0, 1))
        res["png"] = str(png.relative_to(REPO)) if png.is_relative_to(REPO) else str(png)
        res["png_columns"] = [x[0] for x in strips] + ["Mitsuba ground truth"]
    return res


VARIANTS = {
    "before (PBR-pass defaults: offset 0.02 m, t_min 0.01 m)": {"normal_offset_m": 0.02, "shadow_t_min_m": 0.01},
    "after (relight defaults)": {},
    "no shadows": {"shadows": False},
}


def main() -> int:
    from core.bundle import open_bundle
    from core.stages.chain import RunDir

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="NAME=RUN_DIR reconstruction runs")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "artifacts.json"))
    ap.add_argument("--no-relit", action="store_true", help="skip the (slower) relit comparison")
    a = ap.parse_args()
    out = {"what": __doc__.split("\n\n")[1].replace("\n", " "), "runs": {}}
    for item in a.runs:
        name, _, path = item.partition("=")
        run = RunDir(path)
        b = open_bundle(run.scene_path())
        row = {"scene": b.name, "profile": run.profile, **sky_floaters(run, b), **normals(run, b)}
        ev = run.root / "evaluation.json"
        if ev.is_file():
            row["nvs_psnr"] = json.loads(ev.read_text())["summary"]["nvs_psnr"]
        if not a.no_relit:
            row["relit"] = relit(run, b, VARIANTS, Path(a.out).with_name(f"artifacts_{name}.png"))
        out["runs"][name] = row
        print(name, json.dumps(row, indent=1), flush=True)
    Path(a.out).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
