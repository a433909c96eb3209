"""The cleanup pass on relit reconstructions: OIDN against the diffusion forward pass and
structure-keeping variants of it, scored against the bundle's Mitsuba relit frames.

    python benchmarks/bench_forward_relit.py RUN [RUN ...] [--role dev|test] [--out J]

For every run (a ``brdf reconstruct`` directory whose bundle has relit ground truth) and every
held-back map of its bundle, the PBR pass renders the relit test frames once (the evaluation's
settings: ``core.synth.evaluate.EvalSettings``, no denoiser), then each variant cleans the same
raw LDR clip:

* ``none``: the raw render;
* ``oidn``: OIDN with the albedo and normal guides (the product's default);
* ``diffusion``: the forward model's SDEdit of the raw render at sigma_tau 0.4, its output
  everywhere (the paper's forward pass; the product's backend before this benchmark);
  ``diffusion_product``: ``--denoiser diffusion`` as the product runs it now
  (``DenoiseSettings`` defaults);
* ``diffusion_on_oidn_tau{t}``: SDEdit of the OIDN result at start level ``t``, the model's
  output everywhere;
* ``lowpass_s{s}`` and ``lowpass_on_oidn_tau{t}_s{s}``: OIDN plus the Gaussian low-pass
  (sigma ``s`` pixels) of the diffusion result's difference to OIDN: the model's tone and colour
  corrections with OIDN's structure;
* ``..._keep_sky``: the same with the sky pixels (G-buffer depth 0: the map seen directly, which
  the PBR pass renders without noise) kept from OIDN, and the low-pass taken over the surface
  pixels only (normalised convolution).

Reads ground truth (the relit references): a benchmark, never the product. Prints the machine
and per-variant means; ``--out`` writes JSON.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from core.bundle import open_bundle  # noqa: E402
from core.gen.denoise import DenoiseSettings, denoise, surface_lowpass, surface_mask  # noqa: E402
from core.gen.edm import SamplerSettings  # noqa: E402
from core.io.exr import read_exr  # noqa: E402
from core.render.scenario import Scenario, render_scenario, views_from_frames  # noqa: E402
from core.stages.chain import RunDir  # noqa: E402
from core.synth.evaluate import EvalSettings, _img_metrics, relit_reference_ldr  # noqa: E402


def raw_relit(graph, bundle, views, env: np.ndarray, s: EvalSettings) -> dict:
    """The raw LDR clip and the G-buffers of ``views`` lit by ``env`` (no denoiser)."""
    m = bundle.manifest
    sc = Scenario(views=tuple(views), envmap=np.asarray(env, np.float32), base_exposure=m.ldr_exposure,
                  gamma=m.ldr_gamma, rays_per_pixel=s.rays_per_pixel, denoiser="none", denoiser_fallback=None,
                  normal_offset_m=s.normal_offset_m, shadow_t_min_m=s.shadow_t_min_m,
                  object_shadow_t_min_m=s.object_shadow_t_min_m, indirect_bounces=s.indirect_bounces,
                  diffuse=s.diffuse, masking=s.masking, opaque_above=s.opaque_above,
                  object_solids=s.object_solids, outputs=("exr", "png"))
    with tempfile.TemporaryDirectory(prefix="brdf-fwd-") as tmp:
        r = render_scenario(graph, sc, tmp)
        layers = [read_exr(p) for p in r.result.exr_files]
    g = {k: np.stack([lay[k] for lay in layers]) for k in ("albedo", "normal", "depth", "roughness", "metallic")}
    return {"ldr": np.clip(np.stack(r.result.frames), 0, 1).astype(np.float32), "gbuffer": g,
            "c2w": np.stack([v.camera.pose_numpy() for v in views])}


def variants(raw: dict, env: np.ndarray, taus, sigmas) -> dict[str, np.ndarray]:
    g = raw["gbuffer"]
    alb, nrm = np.clip(g["albedo"], 0, 1), g["normal"]
    surface = surface_mask(nrm)  # [T, H, W]; the sky (the map seen directly): zero normal
    everywhere = np.ones_like(surface)
    kw = dict(gbuffer={k: g[k] for k in ("depth", "roughness", "metallic")}, cam_to_world=raw["c2w"], env=env)
    out = {"none": raw["ldr"]}
    oidn = denoise(raw["ldr"], alb, nrm, backend="oidn").frames
    out["oidn"] = oidn

    def add(name: str, d: np.ndarray) -> None:
        out[name] = d
        out[f"{name}_keep_sky"] = np.where(surface[..., None], d, oidn)
        for s in sigmas:
            lp = name.replace("diffusion", "lowpass")
            out[f"{lp}_s{s:g}"] = np.clip(oidn + surface_lowpass(d - oidn, everywhere, s), 0, 1)
            out[f"{lp}_s{s:g}_keep_sky"] = np.clip(oidn + surface_lowpass(d - oidn, surface, s), 0, 1)

    def model_only(start: str, tau: float) -> DenoiseSettings:  # the model's own output everywhere
        return DenoiseSettings(sampler=SamplerSettings(sigma_tau=tau), diffusion_start=start,
                               correction_sigma_px=0.0, keep_sky=False)

    # the paper's forward pass: SDEdit of the raw render (the product's backend before forward_relit.json)
    add("diffusion", denoise(raw["ldr"], alb, nrm, backend="diffusion", settings=model_only("input", 0.4), **kw).frames)
    for t in taus:
        add(f"diffusion_on_oidn_tau{t:g}",
            denoise(raw["ldr"], alb, nrm, backend="diffusion", settings=model_only("oidn", t), **kw).frames)
    out["diffusion_product"] = denoise(raw["ldr"], alb, nrm, backend="diffusion", **kw).frames  # the defaults
    return out


def bench_run(run_path: Path, taus, sigmas, s: EvalSettings, max_frames: int) -> dict:
    run = RunDir(run_path)
    b = open_bundle(run.scene_path())
    gt = b.manifest.ground_truth
    if gt is None or not gt.relit:
        raise SystemExit(f"{run_path}: its bundle has no relit ground truth")
    graph, _sky, stage = run.load_scene()
    views = {v.name: v for v in views_from_frames(b, "all")}
    per_map = {}
    for rl in gt.relit:
        frames = [f for f in b.frames("test") if f.id in rl.frames]
        if max_frames and len(frames) > max_frames:
            frames = [frames[i] for i in np.unique(np.linspace(0, len(frames) - 1, max_frames).round().astype(int))]
        if not frames:
            continue
        env = np.asarray(b.load_envmap(rl.name), np.float32)
        t0 = time.perf_counter()
        raw = raw_relit(graph, b, [views[f.id] for f in frames], env, s)
        refs = [relit_reference_ldr(b, rl.name, f.id) for f in frames]
        rows = {}
        for name, clip in variants(raw, env, taus, sigmas).items():
            ms = [_img_metrics(p, r, True) for p, r in zip(clip, refs)]
            rows[name] = {k: float(np.mean([m[k] for m in ms])) for k in ms[0]}
        per_map[rl.name] = {"frames": len(frames), "seconds": round(time.perf_counter() - t0, 1), "variants": rows}
        print(f"{run_path.name} {rl.name}: " + ", ".join(f"{k} {v['psnr']:.2f}/{v['ssim']:.3f}"
                                                          for k, v in rows.items()), flush=True)
    names = next(iter(per_map.values()))["variants"].keys()
    mean = {n: {k: float(np.mean([pm["variants"][n][k] for pm in per_map.values()]))
                for k in ("psnr", "ssim", "flip")} for n in names}
    return {"scene": b.name, "graph_stage": stage, "per_map": per_map, "mean": mean}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--role", default="dev", choices=["dev", "test"], help="recorded with the figures")
    ap.add_argument("--taus", type=float, nargs="*", default=[0.2, 0.4], help="SDEdit start levels on OIDN")
    ap.add_argument("--sigmas", type=float, nargs="*", default=[2.0, 4.0, 8.0], help="low-pass sigmas, pixels")
    ap.add_argument("--rays", type=int, default=64)
    ap.add_argument("--max-frames", type=int, default=0, help="relit frames per map (0 = all)")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    torch.set_num_threads(2)
    s = EvalSettings(rays_per_pixel=a.rays)
    res = {"machine": {"cpu": platform.processor() or platform.machine(), "cores": torch.get_num_threads(),
                       "python": platform.python_version(), "platform": platform.platform()},
           "role": a.role, "rays_per_pixel": a.rays, "runs": {}}
    print(json.dumps(res["machine"]), flush=True)
    for r in a.runs:
        res["runs"][r.name] = bench_run(r, a.taus, a.sigmas, s, a.max_frames)
    names = next(iter(res["runs"].values()))["mean"].keys()
    res["mean"] = {n: {k: float(np.mean([rr["mean"][n][k] for rr in res["runs"].values()]))
                       for k in ("psnr", "ssim", "flip")} for n in names}
    base = res["mean"]["oidn"]
    print(f"{'variant':36s} {'PSNR':>7s} {'dPSNR':>7s} {'SSIM':>6s} {'dSSIM':>7s} {'FLIP':>6s}")
    for n, m in res["mean"].items():
        print(f"{n:36s} {m['psnr']:7.2f} {m['psnr'] - base['psnr']:+7.2f} {m['ssim']:6.3f} "
              f"{m['ssim'] - base['ssim']:+7.3f} {m['flip']:6.3f}")
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
