"""Benchmark of the generative pass (paper Sec. 3.2, Eq. 5): speed of the forward denoiser, OIDN yardstick,
lighting prior, and (when trained models exist) held-out quality.

    python benchmarks/bench_generative.py --quick            # seconds; random weights, default scene
    python benchmarks/bench_generative.py --scenes scenes/h7 scenes/h8 --out benchmarks/results/generative.json
    python benchmarks/bench_generative.py --lighting-only --lighting-scenes scenes/h7 scenes/h8 scenes/h15 scenes/h16 scenes/h17

What it measures
    forward.s_per_frame    wall seconds per 320x213 frame of SDEdit (8 Euler steps, onnxruntime,
                           ``--threads`` threads) with the forward model: the committed
                           ``models/forward_denoiser.onnx`` when present, else a freshly exported
                           random-weight network of the default width (speed does not depend on
                           the weights; quality fields are then null).
    forward.psnr_* / flip_* / flicker_*   on held-out scenes (``--scenes``) with a trained model and
                           PBR inputs under ``<scene>/derived/pbr`` (or ``--degrade`` for the
                           synthetic Monte-Carlo degradation, reported as such).
    oidn                   PSNR of a Monte-Carlo-degraded frame of the default scene before/after OIDN.
    onnx_parity_max_abs    per committed model: max |onnxruntime - PyTorch| on 3 random inputs of
                           its contract, PyTorch rebuilt from the file's weights.
    inverse.*              held-out G-buffer metrics of the inverse model (one-step sampler,
                           :data:`core.gen.edm.GENERATE_SAMPLER`, mean of the product's ensemble
                           :class:`core.gen.gbuffer_ensemble.EnsembleSettings`), non-sky pixels.
    lighting               sun direction error (deg) and log-space error of the physically fitted
                           prior on each scene (ground-truth geometry/albedo stand in for the
                           reconstruction, glossy and metallic pixels left out; cast shadows traced
                           through the ground-truth meshes as thin Gaussians; without shadows and
                           with LiDAR-point occluders per scene) on the default scene and
                           ``--lighting-scenes`` (default ``--scenes``). ``sun_dir_err_deg`` /
                           ``_max``: mean / largest over the sunny scenes (the sun disc gives >= 0.1
                           of the horizontal irradiance); ``_all``: over every scene.
Every result records the machine (cpu count, load average) and the mode.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def forward_speed(threads: int, runs: int, model_path: Path | None) -> dict:
    import torch

    from core.gen.edm import OnnxDenoiser, SamplerSettings, sdedit
    from core.gen.nets import build_model, example_inputs, export_onnx
    from core.gen.runtime import load_model

    trained = model_path is not None and model_path.is_file()
    if not trained:
        tmp = Path(tempfile.mkdtemp()) / "forward_random.onnx"
        torch.manual_seed(0)
        m = build_model("forward_denoiser", frames=1)
        with torch.no_grad():
            for p in m.parameters():
                p.add_(torch.randn_like(p) * 0.02)
        model_path = export_onnx(m, tmp)
    sess = load_model(model_path, kind="forward_denoiser", threads=threads)
    ex = example_inputs("forward_denoiser", 1, 1, 213, 320)
    x = ex.pop("x_t")[0]
    ex.pop("sigma")
    cond = {k: v[0] for k, v in ex.items()}
    st = SamplerSettings(steps=8, solver="euler")
    sdedit(OnnxDenoiser(sess), x, cond, SamplerSettings(steps=1))  # warm-up
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        sdedit(OnnxDenoiser(sess), x, cond, st)
        times.append(time.perf_counter() - t)
    return {"s_per_frame": float(np.median(times)), "runs": times, "steps": 8, "solver": "euler",
            "resolution": [320, 213], "threads": threads, "weights": "trained" if trained else "random",
            "model": str(model_path)}


def onnx_parity(models: Path, threads: int, runs: int = 3) -> dict:
    """Max |onnxruntime - PyTorch| of each committed model on random inputs of its contract
    (64x96, seeds 0..runs-1), the PyTorch network rebuilt from the file's own weights
    (:func:`core.synth.gen_train.load_onnx_weights`) with the card's architecture."""
    import torch

    from core.gen.nets import UNetSettings, build_model, example_inputs
    from core.gen.runtime import load_model
    from core.synth.gen_train import load_onnx_weights

    out = {}
    for kind in ("forward_denoiser", "inverse_gbuffer"):
        path = models / f"{kind}.onnx"
        if not path.is_file():
            continue
        net = json.loads((models / f"{kind}.card.json").read_text())["network"]
        u = dict(net["unet"], channel_mult=tuple(net["unet"]["channel_mult"]))
        view = bool(net.get("view", False))  # the inverse model's optional camera input (contract 1.1)
        m = build_model(kind, UNetSettings(**u), net["sigma_data"], net["frames"], view=view).eval()
        load_onnx_weights(m, path)
        sess = load_model(path, kind=kind, threads=threads)
        worst = 0.0
        for seed in range(runs):
            x = example_inputs(kind, 1, 1, 64, 96, seed=seed)
            if not view:
                x.pop("view", None)
            with torch.no_grad():
                ref = m(**x).numpy()
            got = next(iter(sess.run(**{k: v.numpy() for k, v in x.items()}).values()))
            worst = max(worst, float(np.abs(got - ref).max()))
        out[kind] = worst
    return out


def oidn_gain(threads: int) -> dict:
    from core.bundle import open_bundle
    from core.synth.gen_data import degrade_mc
    from core.gen.denoise import DenoiseSettings, denoise
    from core.tonemap import hdr_to_ldr

    b = open_bundle(REPO / "data" / "scenes" / "default", validate=False)
    fr = b.frames("test")[0]
    gt = b.load_ground_truth(fr)
    noisy = degrade_mc(gt["rgb"], 4, np.random.default_rng(0))
    clean = hdr_to_ldr(gt["rgb"])
    psnr = lambda a: float(-10 * np.log10(np.mean((a.astype(np.float64) - clean) ** 2)))  # noqa: E731
    t = time.perf_counter()
    out = denoise(noisy, gt["albedo"], gt["normal"], backend="oidn", hdr=True, settings=DenoiseSettings(threads=threads))
    dt = time.perf_counter() - t
    return {"frame": fr.id, "noise": "degrade_mc spp=4", "psnr_noisy": psnr(hdr_to_ldr(noisy)),
            "psnr_oidn": psnr(hdr_to_ldr(out.frames[0])), "s_per_frame": dt}


#: A map counts as sunny when its sun disc gives at least this share of the irradiance on a
#: horizontal surface (:func:`core.lighting.prior.sky_statistics`).
SUNNY_DIRECT_FRACTION = 0.1


def lighting(scenes: list[Path]) -> dict:
    from core.bundle import open_bundle
    from dataclasses import replace

    from benchmarks.lighting_harness import estimate_from_bundle
    from core.lighting.prior import (LightingSettings, brightest_direction, envmap_log_error, sky_statistics,
                                     sun_direction_error_deg)

    out = {}
    for sc in scenes:
        b = open_bundle(sc, validate=False)
        gt = b.load_envmap()
        sun_gt = brightest_direction(gt)
        rec = {"envmap": b.manifest.ground_truth.envmap_name,
               "rotation_deg": b.manifest.ground_truth.envmap_rotation_deg, "ground_truth_sky": sky_statistics(gt)}
        # the headline uses the ground-truth geometry as occluders (it already stands in for the
        # reconstruction's depth and normals); the other two show what each cue is worth
        for occ, model in (("oracle", None), ("oracle", "lambert"), ("none", None), ("lidar", None)):
            t = time.perf_counter()
            st = None if model is None else replace(LightingSettings(), sun_model=model)
            est = estimate_from_bundle(sc, "train", occluders=occ, settings=st)
            r = {"sun_dir_err_deg": sun_direction_error_deg(est.sun_dir, sun_gt), "sun_source": est.sun_source,
                 **envmap_log_error(est.envmap, gt), "seconds": time.perf_counter() - t}
            if model is not None:
                rec[f"sun_model_{model}"] = r
            elif occ == "oracle":
                rec.update(r)
            else:
                rec[f"occluders_{occ}"] = r
        out[str(sc)] = rec
    errs = [v["sun_dir_err_deg"] for v in out.values()]
    sunny = [v["sun_dir_err_deg"] for v in out.values() if v["ground_truth_sky"]["direct_fraction"] >= SUNNY_DIRECT_FRACTION]
    return {"occluders": "oracle (ground-truth meshes as thin Gaussians; 'none' and 'lidar' per scene)",
            "sun_model": LightingSettings().sun_model, "per_scene": out,
            "sunny": f"scenes whose map's sun disc gives >= {SUNNY_DIRECT_FRACTION} of the horizontal irradiance "
                     "(ground_truth_sky.direct_fraction: city 0.27, sunrise 0.35; sunset 0.005, forest 0.05, "
                     "courtyard 0.002 are not sunny)",
            "sun_dir_err_deg": float(np.mean(sunny)) if sunny else None,
            "sun_dir_err_deg_max": float(np.max(sunny)) if sunny else None,
            "sunny_scenes": len(sunny),
            "sun_dir_err_deg_all": float(np.mean(errs)), "sun_dir_err_deg_all_max": float(np.max(errs)),
            "log_err": float(np.mean([v["log_l1"] for v in out.values()]))}


def forward_quality(scenes: list[Path], model: Path, threads: int, sigma_tau: float | None = None) -> dict:
    """The forward pass on held-out clips (PBR renders under ``<scene>/derived/pbr``): PSNR, FLIP
    and flicker of the raw PBR frames, the diffusion pass (SDEdit, 8 Euler steps, shared noise)
    and OIDN (albedo and normal guides from the PBR render's own G-buffers) against the tone-mapped
    Mitsuba ground truth."""
    import torch

    from bench_pbr import flip
    from core.bundle import open_bundle
    from core.synth.gen_data import DataSettings, load_clips
    from core.gen.denoise import DenoiseSettings, denoise
    from core.gen.edm import OnnxDenoiser, SamplerSettings, flicker, sdedit
    from core.gen.runtime import load_model
    from core.io.exr import read_exr
    from core.tonemap import hdr_to_ldr

    sess = load_model(model, kind="forward_denoiser", threads=threads)
    den = OnnxDenoiser(sess)
    sampler = SamplerSettings() if sigma_tau is None else SamplerSettings(sigma_tau=sigma_tau)
    rows = {k: [] for k in ("psnr_pbr", "psnr_diffusion", "psnr_oidn", "flip_pbr", "flip_diffusion", "flip_oidn")}
    flick = {"flicker_pbr": [], "flicker_diffusion": [], "flicker_oidn": [], "flicker_target": []}
    per_scene = {}
    for sc in scenes:
        b = open_bundle(sc, validate=False)
        m = b.manifest
        clips = load_clips(sc, DataSettings(forward_source="pbr"), ("forward",))
        for split, clip in zip(("train", "test"), clips):
            frames = sorted(b.frames(split), key=lambda f: f.time_index)
            x_in = torch.from_numpy(np.stack([f["input_ldr"] for f in clip]))
            tgt = np.stack([(f["target_ldr"].transpose(1, 2, 0) + 1) / 2 for f in clip])
            cond = {k: torch.from_numpy(np.stack([f[k] for f in clip])) for k in
                    ("normal", "depth", "albedo", "roughness", "metallic", "env_ldr", "env_log", "env_dir")}
            y = ((sdedit(den, x_in, cond, sampler).clamp(-1, 1) + 1) / 2).permute(0, 2, 3, 1).numpy()
            pbr = ((x_in.clamp(-1, 1) + 1) / 2).permute(0, 2, 3, 1).numpy()
            layers = [read_exr(Path(sc) / "derived" / "pbr" / f"{fr.id}.exr") for fr in frames]
            hdr = np.stack([np.maximum(l_["rgb"], 0) for l_ in layers]).astype(np.float32)
            od = denoise(hdr, np.stack([l_["albedo"] for l_ in layers]), np.stack([l_["normal"] for l_ in layers]),
                         backend="oidn", hdr=True, settings=DenoiseSettings(threads=threads))
            oidn = np.clip(hdr_to_ldr(od.frames, m.ldr_exposure, m.ldr_gamma), 0, 1)
            rec = {}
            for name, img in (("pbr", pbr), ("diffusion", y), ("oidn", oidn)):
                p = [float(-10 * np.log10(max(np.mean((img[t] - tgt[t]) ** 2), 1e-12))) for t in range(len(tgt))]
                fl = [flip(tgt[t], img[t]) for t in range(len(tgt))]
                rows[f"psnr_{name}"] += p
                rows[f"flip_{name}"] += fl
                flick[f"flicker_{name}"].append(flicker(img))
                rec[name] = {"psnr": float(np.mean(p)), "flip": float(np.mean(fl))}
            flick["flicker_target"].append(flicker(tgt))
            per_scene[f"{Path(sc).name}/{split}"] = rec
    out = {k: float(np.mean(v)) for k, v in rows.items()}
    out.update({k: float(np.mean(v)) for k, v in flick.items()})
    out.update({"per_clip": per_scene, "sigma_tau": sampler.sigma_tau, "steps": sampler.steps,
                "frames": len(rows["psnr_pbr"]), "input": "PBR renders of perturbed oracle scenes, 16 rays/pixel",
                "flicker_note": "clips follow the moving camera of each trajectory (no static-camera clip in the "
                                "held-out bundles); flicker_target is the ground truth's own"})
    return out


def quality(scenes: list[Path], models: Path, threads: int, degrade: bool) -> dict:
    from core.synth.gen_data import DataSettings
    from core.synth.gen_train import evaluate_model

    data = DataSettings(forward_source="degrade" if degrade else "pbr")
    res = {}
    fwd, inv = models / "forward_denoiser.onnx", models / "inverse_gbuffer.onnx"
    if fwd.is_file() and degrade:  # PBR inputs: forward_quality() (with OIDN and FLIP)
        res["forward"] = evaluate_model("forward_denoiser", fwd, scenes, data, threads=threads)
        res["forward"]["input"] = data.forward_source
    if inv.is_file():
        res["inverse"] = evaluate_model("inverse_gbuffer", inv, scenes, data, threads=threads)
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1 speed run, default scene only")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--scenes", nargs="*", type=Path, default=[])
    ap.add_argument("--models", type=Path, default=REPO / "models")
    ap.add_argument("--degrade", action="store_true", help="forward inputs: synthetic MC degradation")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--sigma-tau", type=float, default=None, help="SDEdit start level (default: the sampler's)")
    ap.add_argument("--lighting-scenes", nargs="*", type=Path, default=None,
                    help="held-out scenes of the lighting prior (default: --scenes); the default scene is always added")
    ap.add_argument("--skip-lighting", action="store_true")
    ap.add_argument("--inverse-only", action="store_true",
                    help="measure only the inverse model (ONNX parity, and its figures on --scenes) and replace "
                         "the 'inverse' and 'onnx_parity_max_abs' entries of --out, keeping the rest of the file")
    ap.add_argument("--lighting-only", action="store_true",
                    help="measure only the lighting prior and replace the 'lighting' entry of --out (default "
                         "benchmarks/results/generative.json), keeping the rest of the file")
    a = ap.parse_args(argv)
    light_scenes = [REPO / "data" / "scenes" / "default"] + list(a.scenes if a.lighting_scenes is None
                                                                  else a.lighting_scenes)
    if a.inverse_only:
        out = a.out or REPO / "benchmarks" / "results" / "generative.json"
        result = json.loads(out.read_text()) if out.is_file() else {}
        parity = onnx_parity(a.models, a.threads)
        result["onnx_parity_max_abs"] = {**(result.get("onnx_parity_max_abs") or {}),
                                         "inverse_gbuffer": parity.get("inverse_gbuffer")}
        if a.scenes:
            result["inverse"] = quality(list(a.scenes), a.models, a.threads, a.degrade)["inverse"]
            result["inverse"]["scenes"] = [p.name for p in a.scenes]
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=2))
        print(json.dumps({"onnx_parity_max_abs": result["onnx_parity_max_abs"], "inverse": result.get("inverse"),
                          "out": str(out)}, indent=1))
        return 0
    if a.lighting_only:
        scenes = light_scenes
        out = a.out or REPO / "benchmarks" / "results" / "generative.json"
        result = json.loads(out.read_text()) if out.is_file() else {}
        result["lighting"] = lighting(scenes)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=2))
        print(json.dumps({"lighting_sun_err_deg_sunny": result["lighting"]["sun_dir_err_deg"],
                          "lighting_sun_err_deg_sunny_max": result["lighting"]["sun_dir_err_deg_max"],
                          "per_scene": {k: v["sun_dir_err_deg"] for k, v in result["lighting"]["per_scene"].items()},
                          "out": str(out)}, indent=1))
        return 0
    runs = 1 if a.quick else a.runs
    scenes = [REPO / "data" / "scenes" / "default"] + list(a.scenes)
    result = {"mode": "quick" if a.quick else "full", "machine": {"cpus": os.cpu_count(),
              "loadavg": list(os.getloadavg())}}
    fs = forward_speed(a.threads, runs, a.models / "forward_denoiser.onnx")
    result["forward"] = {"s_per_frame": fs["s_per_frame"], "speed": fs, "psnr_pbr": None, "psnr_diffusion": None,
                         "psnr_oidn": None, "flip_pbr": None, "flip_diffusion": None, "flip_oidn": None,
                         "flicker_pbr": None, "flicker_diffusion": None}
    result["oidn"] = oidn_gain(a.threads)
    result["onnx_parity_max_abs"] = onnx_parity(a.models, a.threads)
    result["lighting"] = lighting(light_scenes) if not a.skip_lighting else None
    if not a.quick and a.scenes:
        fwd = a.models / "forward_denoiser.onnx"
        if fwd.is_file() and not a.degrade:
            result["forward"].update(forward_quality(list(a.scenes), fwd, a.threads, a.sigma_tau))
        q = quality(list(a.scenes), a.models, a.threads, a.degrade)
        if "forward" in q and a.degrade:
            f = q["forward"]
            result["forward"].update({"psnr_pbr": f.get("psnr_input"), "psnr_diffusion": f.get("psnr_model"),
                                      "flicker_pbr": f.get("flicker_input"), "flicker_diffusion": f.get("flicker_model"),
                                      "input": f["input"]})
        if "inverse" in q:
            result["inverse"] = q["inverse"]
    out = a.out or (Path(tempfile.gettempdir()) / "generative_quick.json" if a.quick
                    else REPO / "benchmarks" / "results" / "generative.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2))
    print(json.dumps({"forward_s_per_frame": result["forward"]["s_per_frame"],
                      "oidn_psnr": [result["oidn"]["psnr_noisy"], result["oidn"]["psnr_oidn"]],
                      "lighting_sun_err_deg": (result["lighting"] or {}).get("sun_dir_err_deg"), "out": str(out)},
                     indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
