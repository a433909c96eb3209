"""How much can any forward pass conditioned on a reconstruction gain over OIDN? (diagnostic; reads
ground truth)

Issue 18 asks the forward (generative) pass for >= +1 dB over OIDN on relit reconstructions, and
issue 14 asks the re-render under the recovered capture lighting to come within 2 dB of the novel
views. Both ask a pass that sees the reconstruction's G-buffers and its PBR render to remove error
that the reconstruction put there. This script measures how much of that error a learned
per-pixel corrector *can* remove when it is given every advantage a shipped model never has:

* it is fitted on the **same scene** (its own G-buffers, the same Gaussians, the same camera path)
  against that scene's **Mitsuba ground truth**;
* ``relight``: leave one held-back map out, fitted on the frames relit under the bundle's other
  held-back maps, scored on the left-out map's frames (a new light, the same street);
* ``relight_same_map``: fitted on every second relit frame of a map, scored on the others (the same
  light and street: a looser bound);
* ``rerender``: fitted on every second test frame under the recovered capture map against the
  capture, scored on the others;
* ``*_in_sample``: scored on the frames it was fitted on (the loosest bound: memorisation);
* ``cross_street`` (two or more runs): fitted on every other street's relit frames, scored on one
  street's relit frames and its re-render, each street left out in turn: what a model trained on
  other streets, as the product's is, reaches.

The corrector is a small dilated CNN (receptive field 61 px) over the OIDN frame (LDR), the
reconstruction's albedo, camera-frame normal, roughness, metallic, opacity and log depth; it
predicts a residual added to the OIDN frame. The same-street gains say how much of the error is a
function of these inputs at this capacity; the cross-street gains, how much of it carries over.
The rendered inputs can be cached (``--cache``, one npz per run directory, keyed by its path: delete
it after re-running a stage).

    python benchmarks/forward_ceiling.py RUN [RUN ...] [--cross-only] [--cache DIR] --out J

Not part of the product: it reads the bundle's ground truth (the Mitsuba relit frames, the
capture's test frames).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from core.bundle import open_bundle  # noqa: E402
from core.camera import Camera  # noqa: E402
from core.gen.scene_corrector import SceneCorrector  # noqa: E402
from core.io.envmap_file import read_envmap  # noqa: E402
from core.metrics import psnr, ssim  # noqa: E402
from core.numerics import OPACITY_EPS, safe_normalize  # noqa: E402
from core.raster import RasterSettings, rasterize_gaussians  # noqa: E402
from core.render.scenario import views_from_frames  # noqa: E402
from core.stages.chain import RunDir  # noqa: E402
from core.synth.evaluate import EvalSettings, relit_reference_ldr, render_pbr_frames  # noqa: E402

FEATURES = ("oidn_ldr[3]", "albedo[3]", "normal_cam[3]", "roughness", "metallic", "opacity", "log_depth")


def gbuffer_features(graph, bundle, frame, times) -> np.ndarray:
    """[H, W, 10] G-buffer features of ``frame``: albedo 3, camera-frame normal 3, roughness,
    metallic, opacity, log depth (metres, 0 where empty), layers divided by the opacity."""
    c = bundle.camera(frame)
    cam = Camera.from_bundle(c, frame)
    g = graph.compose(float(times[frame.time_index])).detach()
    with torch.no_grad():
        r = rasterize_gaussians(g, cam, settings=RasterSettings(threads=2))
    op = r.opacity.float()
    inv = 1.0 / op.clamp_min(OPACITY_EPS)
    world_to_cam = cam.cam_to_world[:3, :3].T.float()
    n_cam = safe_normalize(r.normal.float()) @ world_to_cam.T
    depth = (r.depth.float() * inv).clamp_min(0)
    feats = [(r.albedo.float() * inv).clamp(0, 1), n_cam, (r.roughness.float() * inv).clamp(0, 1),
             (r.metallic.float() * inv).clamp(0, 1), op, torch.log1p(depth)]
    return torch.cat(feats, -1).numpy().astype(np.float32)


def Corrector(channels: int, width: int = 32) -> SceneCorrector:
    """The product's corrector network (:class:`core.gen.scene_corrector.SceneCorrector`) over
    ``channels`` input features: [B, C, H, W] -> the OIDN frame plus a residual, [B, 3, H, W]."""
    return SceneCorrector(width, channels)


def fit(inputs: list[np.ndarray], targets: list[np.ndarray], steps: int, crop: int, seed: int,
        width: int = 32) -> SceneCorrector:
    """The corrector (``width`` channels) fitted by Adam on random crops of ``inputs`` ([H, W, C])
    against ``targets`` ([H, W, 3] LDR), L1 loss."""
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    xs = [torch.from_numpy(x).permute(2, 0, 1) for x in inputs]
    ys = [torch.from_numpy(np.ascontiguousarray(y, np.float32)).permute(2, 0, 1) for y in targets]
    net = Corrector(xs[0].shape[0], width)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    for _ in range(steps):
        bx, by = [], []
        for _b in range(4):
            i = int(rng.integers(len(xs)))
            h, w = xs[i].shape[1:]
            y0, x0 = int(rng.integers(h - crop + 1)), int(rng.integers(w - crop + 1))
            bx.append(xs[i][:, y0:y0 + crop, x0:x0 + crop])
            by.append(ys[i][:, y0:y0 + crop, x0:x0 + crop])
        loss = (net(torch.stack(bx)) - torch.stack(by)).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    return net


def apply(net: SceneCorrector, x: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        y = net(torch.from_numpy(x).permute(2, 0, 1)[None])[0].permute(1, 2, 0)
    return y.clamp(0, 1).numpy()


def score(preds: list[np.ndarray], refs: list[np.ndarray]) -> dict:
    p = [float(psnr(torch.from_numpy(np.asarray(a, np.float32)), torch.from_numpy(np.asarray(b, np.float32))))
         for a, b in zip(preds, refs)]
    s = [float(ssim(torch.from_numpy(np.asarray(a, np.float32)), torch.from_numpy(np.asarray(b, np.float32))))
         for a, b in zip(preds, refs)]
    return {"psnr": float(np.mean(p)), "ssim": float(np.mean(s))}


def gain(net, xs, refs) -> dict:
    base = score([x[..., :3] for x in xs], refs)
    corr = score([apply(net, x) for x in xs], refs)
    return {"oidn": base, "corrected": corr, "psnr_gain_db": corr["psnr"] - base["psnr"],
            "ssim_gain": corr["ssim"] - base["ssim"]}


def collect(run_path: str, cache: Path | None, log) -> dict:
    """The corrector's inputs and references of one run: ``{"scene", "graph_stage", "relit":
    {map: (xs, ys)}, "rerender": (xs, ys) or None}``; read from / written to ``cache`` (npz)."""
    run = RunDir(run_path)
    b = open_bundle(run.scene_path())
    key = hashlib.sha1(str(Path(run_path).resolve()).encode()).hexdigest()[:10]
    f_cache = cache / f"{b.name}_{key}.npz" if cache else None
    if f_cache is not None and f_cache.is_file():
        z = np.load(f_cache, allow_pickle=True)
        return z["data"].item()
    graph, _sky, graph_stage = run.load_scene()
    env_path, _ = run.latest_envmap()
    times = b.manifest.times
    views = {v.name: v for v in views_from_frames(b, "all")}
    s = EvalSettings()
    test = sorted(b.frames("test"), key=lambda f: (f.time_index, f.id))
    feats = {f.id: gbuffer_features(graph, b, f, times) for f in test}

    def inputs(frames, env) -> list[np.ndarray]:
        ldr = render_pbr_frames(graph, b, env, frames, s, views=views)
        return [np.concatenate([np.asarray(p, np.float32), feats[f.id]], -1) for p, f in zip(ldr, frames)]

    data: dict = {"scene": b.name, "graph_stage": graph_stage, "relit": {}, "rerender": None}
    for rl in b.manifest.ground_truth.relit:
        frames = [f for f in test if f.id in rl.frames]
        if frames:
            data["relit"][rl.name] = (inputs(frames, b.load_envmap(rl.name)),
                                      [relit_reference_ldr(b, rl.name, f.id) for f in frames])
            log(f"{b.name}: rendered {rl.name} ({len(frames)} frames)")
    if env_path is not None:
        data["rerender"] = (inputs(test, read_envmap(env_path)),
                            [np.asarray(b.load_image(f), np.float32) for f in test])
    if f_cache is not None:
        f_cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez(f_cache, data=np.array(data, dtype=object))
    return data


def _mean(rows: dict) -> dict:
    m = {}
    if rows:
        for k in ("psnr_gain_db", "ssim_gain"):
            m[k] = float(np.mean([r[k] for r in rows.values()]))
        m["oidn_psnr"] = float(np.mean([r["oidn"]["psnr"] for r in rows.values()]))
        m["corrected_psnr"] = float(np.mean([r["corrected"]["psnr"] for r in rows.values()]))
    return {"mean": m, "per_map": rows}


def within_street(data: dict, run_path: str, steps: int, crop: int, seed: int, log) -> dict:
    """Fits on one street's own frames (leave one map out, every second frame of a map, every
    second re-rendered frame) and their held-out gains."""
    per_map = data["relit"]
    name0 = data["scene"]
    out: dict = {"run": run_path, "scene": name0, "graph_stage": data["graph_stage"]}
    names = sorted(per_map)
    rows_lomo, rows_same, rows_in = {}, {}, {}
    for k, name in enumerate(names):
        tr_x = [x for n in names if n != name for x in per_map[n][0]]
        tr_y = [y for n in names if n != name for y in per_map[n][1]]
        if tr_x:
            net = fit(tr_x, tr_y, steps, crop, seed + k)
            rows_lomo[name] = gain(net, *per_map[name])
            rows_in[name] = gain(net, tr_x, tr_y)
        xs, ys = per_map[name]
        if len(xs) >= 2:
            net = fit(xs[0::2], ys[0::2], steps, crop, seed + 100 + k)
            rows_same[name] = gain(net, xs[1::2], ys[1::2])
        log(f"{name0}: {name}: leave-map-out {rows_lomo.get(name, {}).get('psnr_gain_db')}, "
            f"same map {rows_same.get(name, {}).get('psnr_gain_db')}")
    out["relight"] = _mean(rows_lomo)
    out["relight_in_sample"] = _mean(rows_in)
    out["relight_same_map"] = _mean(rows_same)
    if data["rerender"] is not None:
        xs, ys = data["rerender"]
        net = fit(xs[0::2], ys[0::2], steps, crop, seed + 200)
        out["rerender"] = gain(net, xs[1::2], ys[1::2])
        out["rerender_in_sample"] = gain(net, xs[0::2], ys[0::2])
        log(f"{name0}: re-render held-out gain {out['rerender']['psnr_gain_db']:.2f} dB, "
            f"in-sample {out['rerender_in_sample']['psnr_gain_db']:.2f} dB")
    return out


def cross_street(datas: list[dict], steps: int, crop: int, seed: int, log) -> dict:
    """Fits on every other street's relit frames (all maps), scored on one street's relit frames
    (per map) and its re-render: what a model trained on other streets reaches."""
    out = {}
    for k, d in enumerate(datas):
        tr_x = [x for o in datas if o is not d for xs, _ in o["relit"].values() for x in xs]
        tr_y = [y for o in datas if o is not d for _, ys in o["relit"].values() for y in ys]
        net = fit(tr_x, tr_y, steps, crop, seed + 300 + k)
        row = {"trained_on": [o["scene"] for o in datas if o is not d],
               "relight": _mean({n: gain(net, *v) for n, v in d["relit"].items()})}
        if d["rerender"] is not None:
            row["rerender"] = gain(net, *d["rerender"])
        out[d["scene"]] = row
        log(f"cross-street: {d['scene']}: relight {row['relight']['mean'].get('psnr_gain_db')}, "
            f"re-render {row.get('rerender', {}).get('psnr_gain_db')}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="reconstruction run directories (brdf reconstruct --out)")
    ap.add_argument("--steps", type=int, default=800, help="Adam steps per fit")
    ap.add_argument("--crop", type=int, default=64, help="training crop, pixels")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--role", default="dev", help="development or test scenes (recorded)")
    ap.add_argument("--out", required=True, help="JSON to write")
    ap.add_argument("--cache", default="", help="folder for the rendered inputs (npz), reused when present")
    ap.add_argument("--cross-only", action="store_true", help="only the cross-street fits (two or more runs)")
    a = ap.parse_args(argv)
    torch.set_num_threads(2)
    t0 = time.perf_counter()
    res = {"what": __doc__.split("\n\n")[0], "machine": {"cpu": platform.machine(), "cores": 2,
                                                          "python": platform.python_version()},
           "features": FEATURES, "corrector": "8 dilated 3x3 conv layers (dilations 1,2,4,8,8,4,2,1), width 32, "
           "GELU, zero-initialised 1x1 head, residual on the OIDN frame; Adam 1e-3 cosine, L1, 4 crops a step",
           "steps": a.steps, "crop": a.crop, "role": a.role, "eval_settings": EvalSettings().__dict__,
           "runs": [], "mean": {}}
    log = lambda m: print(m, flush=True)  # noqa: E731
    cache = Path(a.cache) if a.cache else None
    datas = [collect(r, cache, log) for r in a.runs]
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if len(datas) >= 2:
        res["cross_street"] = cross_street(datas, a.steps, a.crop, a.seed, log)
        cs = list(res["cross_street"].values())
        res["mean"]["cross_street_relight_psnr_gain_db"] = float(np.mean([c["relight"]["mean"]["psnr_gain_db"] for c in cs]))
        res["mean"]["cross_street_relight_ssim_gain"] = float(np.mean([c["relight"]["mean"]["ssim_gain"] for c in cs]))
        rr = [c["rerender"]["psnr_gain_db"] for c in cs if "rerender" in c]
        res["mean"]["cross_street_rerender_psnr_gain_db"] = float(np.mean(rr)) if rr else None
        out.write_text(json.dumps(res, indent=1))  # the cross-street figures, before the longer fits
    if not a.cross_only:
        res["runs"] = [within_street(d, r, a.steps, a.crop, a.seed, log) for d, r in zip(datas, a.runs)]
        for key in ("relight", "relight_same_map", "relight_in_sample"):
            vals = [r[key]["mean"]["psnr_gain_db"] for r in res["runs"] if r[key]["mean"]]
            res["mean"][f"{key}_psnr_gain_db"] = float(np.mean(vals)) if vals else None
        for key in ("rerender", "rerender_in_sample"):
            vals = [r[key]["psnr_gain_db"] for r in res["runs"] if key in r]
            res["mean"][f"{key}_psnr_gain_db"] = float(np.mean(vals)) if vals else None
    res["seconds"] = round(time.perf_counter() - t0, 1)
    out.write_text(json.dumps(res, indent=1))
    print(json.dumps(res["mean"], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
