"""Where does the sun of a reconstruction go wrong? The lighting prior's sun search
(:func:`core.lighting.prior.estimate_lighting`) on a run's frames and G-buffers, in variants:

* ``product``: what the pbr stage runs at its defaults (cast shadows traced through the
  reconstruction's static Gaussians and completed facades, ``SceneGraph.shadow_static``;
  ``PBRStageConfig.prior_points`` and ``prior_basin_quantile``);
* ``no_shadows``: the stage's search before them (no cast shadows, 4000 samples, no basin);
* ``lambert_shadows`` / ``transport_shadows``: the two sun models with cast shadows;
* ``gt_*`` rows (diagnostics, **ground-truth inputs**, never the product): the bundle's true
  normals + depth, albedo, or everything, put in place of the reconstruction's, to see which
  G-buffer the search fails on.

Each row: the sun direction error against the true map's brightest direction, the sun source
and the search's residual contrast.

    python benchmarks/bench_sun.py RUN [RUN ...] [--variants product,lambert_shadows] --out J

``--compare ROLE:NAME:BEFORE:AFTER ...`` instead tabulates two evaluated runs per scene (their
``evaluation.json``, ``brdf evaluate``): the pipeline's figures before and after a change of the
pbr stage, per scene and the mean per role.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import core.lighting.prior as prior_mod  # noqa: E402
from core.camera import Camera  # noqa: E402
from core.lighting.prior import (LightingSettings, brightest_direction, estimate_lighting,  # noqa: E402
                                 numpy_visibility, sun_direction_error_deg)
from core.stages.chain import RunDir  # noqa: E402
from core.stages.pbr import _frames, prior_inputs  # noqa: E402
from core.stages.pbr_settings import PBRStageConfig  # noqa: E402
from eval_pipeline import machine  # noqa: E402

_STAGE = PBRStageConfig()

#: Named variants; any "+"-joined set of the tokens lambert | transport | hybrid (sun_model
#: "lambert+transport"), shadows, mats (leave out
#: glossy and metallic samples), nooccl (shadows through the Gaussians alone, no completed facades),
#: noalb (luminance instead of radiance / albedo), FIELD=JSON (a LightingSettings field), gtgeo, gtalb, gtmat (ground-truth G-buffers: diagnostics) is one too.
VARIANT_TOKENS = {"product": f"lambert+shadows+max_points={_STAGE.prior_points}+basin_quantile={_STAGE.prior_basin_quantile}",
                  "no_shadows": "lambert", "lambert_shadows": "lambert+shadows", "transport_shadows": "transport+shadows",
                  "gt_all": "lambert+gtgeo+gtalb+gtmat", "gt_all_shadows": "lambert+shadows+gtgeo+gtalb+gtmat"}
TOKENS = {"lambert", "transport", "hybrid", "shadows", "nooccl", "noalb", "mats", "gtgeo", "gtalb", "gtmat"}
VARIANTS = tuple(VARIANT_TOKENS)


def _gt(bundle, cfg):
    frames = sorted(bundle.frames("train"), key=lambda f: (f.time_index, f.id))
    pick = np.unique(np.linspace(0, len(frames) - 1, min(cfg.max_frames, len(frames))).round().astype(int))
    out = {"dep": [], "nrm": [], "alb": [], "rough": [], "metal": [], "sky": []}
    for i in pick:
        fr = frames[int(i)]
        c = bundle.camera(fr)
        g = bundle.load_ground_truth(fr)
        hw = (c.height, c.width)
        d = np.asarray(g["depth"], np.float64).reshape(hw)
        out["dep"].append(d)
        out["sky"].append(d <= 0)
        out["nrm"].append(np.asarray(g["normal"], np.float32).reshape(*hw, 3))
        out["alb"].append(np.asarray(g["albedo"], np.float64).reshape(*hw, 3))
        out["rough"].append(np.asarray(g["roughness"], np.float64).reshape(hw))
        out["metal"].append(np.asarray(g["metallic"], np.float64).reshape(hw))
    return {k: np.stack(v) for k, v in out.items()}


def _f(x) -> str:
    return "-" if x is None else f"{x:.4g}"


def run_one(run_path: str, variants) -> dict:
    run = RunDir(run_path)
    from core.bundle import open_bundle

    bundle = open_bundle(run.scene_path())
    graph, _sky, stage = run.load_scene(before="pbr")
    cfg = _STAGE
    t0 = time.perf_counter()
    frames, tracer = _frames(graph, bundle, cfg)
    pin = prior_inputs(frames)
    x = {k: pin[v] for k, v in (("img", "img"), ("sky", "sky"), ("dep", "depth"), ("nrm", "normal"), ("alb", "albedo"),
                                ("rough", "roughness"), ("metal", "metallic"))}
    cams = Camera.stack([f.camera for f in frames])
    m = bundle.manifest
    true_sun = brightest_direction(np.asarray(bundle.load_envmap(), np.float64))
    vis = numpy_visibility(tracer) if tracer is not None else None
    vis_bare = None
    if any("nooccl" in VARIANT_TOKENS.get(v, v) for v in variants):  # the Gaussians alone, no completed facades
        from core.pbr.visibility import GaussianTracer
        vis_bare = numpy_visibility(GaussianTracer.from_gaussians(graph._static_part().detach(), cfg.trace_settings()))
    gt = _gt(bundle, cfg) if any("gt" in VARIANT_TOKENS.get(v, v) for v in variants) else None
    rows = {"graph_stage": stage, "frames": len(frames), "setup_s": round(time.perf_counter() - t0, 1)}
    for v in variants:
        t1 = time.perf_counter()
        d = dict(x)
        toks = set(VARIANT_TOKENS.get(v, v).split("+"))
        model = ("lambert+transport" if "hybrid" in toks else "transport" if "transport" in toks else "lambert")
        use_vis, mats = "shadows" in toks, "mats" in toks or model == "transport"
        if "gtgeo" in toks:
            d.update(dep=np.where(gt["sky"], 0, gt["dep"]), nrm=gt["nrm"])
        if "gtalb" in toks:
            d.update(alb=gt["alb"])
        if "gtmat" in toks:
            d.update(rough=gt["rough"], metal=gt["metal"])
        kw = dict(roughness=d["rough"], metallic=d["metal"]) if mats else {}
        extra = {k: json.loads(val) for k, val in (t.split("=", 1) for t in toks if "=" in t)}
        probe = {}

        orig = prior_mod._search_sun

        def search(score, st, _probe=probe):
            def keep(c, _score=score):
                r = _score(c)
                _probe.setdefault("grid", (np.asarray(c), np.asarray(r)))  # the coarse grid
                return r
            out = orig(keep, st)
            _probe["true"] = float(score(true_sun[None])[0])  # the residual the true sun gets
            return out
        prior_mod._search_sun = search
        try:
            est = estimate_lighting(d["img"], cams, d["sky"], d["dep"], d["nrm"],
                                    albedo=None if "noalb" in toks else d["alb"], exposure=m.ldr_exposure,
                                    gamma=m.ldr_gamma, settings=LightingSettings(height=64, sun_model=model, **extra),
                                    visibility=(vis_bare if "nooccl" in toks else vis) if use_vis else None, **kw)
        finally:
            prior_mod._search_sun = orig
        err = float(sun_direction_error_deg(est.sun_dir, true_sun))
        if "grid" in probe:  # how the low region of the coarse grid lies around the true sun
            g, r = probe["grid"]
            ok = np.isfinite(r)
            g, r = g[ok], r[ok]
            soft = {}
            for q in (0.02, 0.05, 0.1):
                sel = r <= np.quantile(r, q)
                c = g[sel].mean(0)
                soft[f"centroid_best_{q:g}"] = round(float(sun_direction_error_deg(c / np.linalg.norm(c), true_sun)), 1)
            soft["rank_of_true_sun"] = round(float((r < probe["true"]).mean()), 3)
            probe["soft"] = soft
            print("   low region of the coarse grid:", soft, flush=True)
        dg = est.diagnostics
        rows[v] = {"sun_error_deg": round(err, 1), "sun_source": est.sun_source,
                   "sun_dir": [round(float(a), 3) for a in est.sun_dir],
                   "elevation_deg": round(math.degrees(math.asin(float(np.clip(est.sun_dir[2], -1, 1)))), 1),
                   "contrast": round(float(dg.get("shading_contrast", float("nan"))), 3),
                   "residual_best": dg.get("shading_residual"), "residual_median": dg.get("shading_residual_median"),
                   "residual_true_sun": probe.get("true"), "coarse_grid": probe.get("soft"),
                   "seconds": round(time.perf_counter() - t1, 1)}
        print(f"{Path(run_path).name:>16} {v:>20}: sun {err:6.1f} deg ({est.sun_source}, elev "
              f"{rows[v]['elevation_deg']}, contrast {rows[v]['contrast']}; residual best / true sun / median "
              f"{_f(dg.get('shading_residual'))} / {_f(probe.get('true'))} / {_f(dg.get('shading_residual_median'))})",
              flush=True)
    rows["true_sun"] = [round(float(a), 3) for a in true_sun]
    rows["true_elevation_deg"] = round(math.degrees(math.asin(float(true_sun[2]))), 1)
    return rows


COMPARE_KEYS = ("sun_error_deg", "rerender_psnr", "relight_psnr", "relight_ssim", "relight_flip", "nvs_psnr",
                "albedo_si_psnr")


def wall_hypotheses(run: str | Path) -> dict | None:
    """The pbr stage's wall-height hypotheses of ``run`` (``core.stages.wall_heights``), each
    with its residual and its sun's error against the bundle's true map (a diagnostic: reads
    ground truth), and the chosen one; None when the stage did not run them."""
    s = json.loads((Path(run) / "pbr" / "summary.json").read_text())
    w = s.get("wall_heights") or {}
    if not w.get("enabled"):
        return None
    from core.bundle import open_bundle

    true_sun = brightest_direction(np.asarray(open_bundle(RunDir(run).scene_path()).load_envmap(), np.float64))
    return {"chosen": w["chosen"], "seconds": w.get("seconds"),
            "hypotheses": {h: {"residual": v["residual"],
                               "sun_error_deg": round(sun_direction_error_deg(np.array(v["sun_dir"]), true_sun), 1)}
                           for h, v in w["hypotheses"].items()}}


def compare(specs) -> dict:
    """``ROLE:NAME:BEFORE:AFTER`` run pairs -> per scene and per role mean of COMPARE_KEYS."""
    out: dict = {"scenes": {}, "means": {}}
    for spec in specs:
        role, name, before, after = spec.split(":")
        row = {"role": role, "runs": {"before": before, "after": after}}
        for k, run in (("before", before), ("after", after)):
            ev = json.loads((Path(run) / "evaluation.json").read_text())["summary"]
            row[k] = {key: ev.get(key) for key in COMPARE_KEYS}
            walls = wall_hypotheses(run)
            if walls is not None:
                row[k]["wall_heights"] = walls
        out["scenes"][name] = row
    for role in sorted({r["role"] for r in out["scenes"].values()}):
        rows = [r for r in out["scenes"].values() if r["role"] == role]
        out["means"][role] = {k: {key: round(float(np.mean([r[k][key] for r in rows])), 3) for key in COMPARE_KEYS}
                              for k in ("before", "after")}
        out["means"][role]["scenes"] = [n for n, r in out["scenes"].items() if r["role"] == role]
    for name, r in out["scenes"].items():
        print(f"{name:>10} ({r['role']}): " + ", ".join(f"{k} {r['before'][k]:.2f} -> {r['after'][k]:.2f}"
                                                  for k in COMPARE_KEYS[:4]))
        w = r["after"].get("wall_heights")
        if w:
            print(f"{'':>10} walls: chosen {w['chosen']}; " + ", ".join(
                f"{h} {v['residual']} ({v['sun_error_deg']} deg)" for h, v in w["hypotheses"].items()))
    return out


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="*")
    ap.add_argument("--compare", nargs="+", default=None, metavar="ROLE:NAME:BEFORE:AFTER")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--out", default="")
    a = ap.parse_args()
    if a.compare:
        res = {"machine": machine(), "what": "the pipeline's figures (brdf evaluate) before and after", **compare(a.compare)}
        if a.out:
            Path(a.out).write_text(json.dumps(res, indent=1))
        return 0
    if not a.runs:
        ap.error("give runs, or --compare")
    variants = [v for v in a.variants.split(",") if v]
    bad = [v for v in variants if v not in VARIANTS
           and not all(t in TOKENS or "=" in t for t in v.split("+"))]
    if bad:
        ap.error(f"--variants: unknown {bad}; choose from {list(VARIANTS)}")
    res = {r: run_one(r, variants) for r in a.runs}
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
