"""Where the material error of a reconstruction comes from, stage by stage (a diagnostic: it reads
the bundle's ground truth, which the product never does).

For each finished stage with a scene graph (volume, volume2, joint) of a run, the intrinsics of
``brdf evaluate`` on the bundle's test frames (albedo si-PSNR, roughness and metallic RMSE, normal
MAE on non-sky pixels), plus the metallic error split into true-metal pixels (ground-truth
metallic > 0.5) and the rest, and the share of it on pixels within 2 px of a metal / non-metal
boundary (soft splat edges, thin poles) against the rest, and the share on pixels within 2 px of
thin metal parts (poles and their arms). With ``--priors``, the same split for the inverse model's
priors on the training frames against the training frames' ground truth. With ``--oracle-floor``,
each stage's metallic RMSE with every visible Gaussian's metallic taken from the truth (what the
splat footprints cost on their own) and with the metallic rounded to 0 / 1.

    python benchmarks/diagnose_materials.py RUN [RUN ...] [--priors] [--oracle-floor] [--out J]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import scipy.ndimage as nd
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from core.bundle import open_bundle  # noqa: E402
from core.camera import Camera  # noqa: E402
from core.numerics import OPACITY_EPS  # noqa: E402
from core.raster import RasterSettings, rasterize_gaussians  # noqa: E402
from core.stages.chain import GRAPH_STAGES, STAGES, RunDir  # noqa: E402
from core.synth.evaluate import frame_intrinsics  # noqa: E402

METAL_THRESHOLD = 0.5
#: Half-width of the metal / non-metal boundary band, pixels (materials_by_stage.json's boundary_finding).
BOUNDARY_PX = 2


def boundary_mask(true_metallic: np.ndarray, px: int = BOUNDARY_PX) -> np.ndarray:
    """``[H, W]`` bool: pixels within ``px`` pixels of a boundary between true metal and the rest
    (``true_metallic`` ``[H, W]``)."""
    metal = true_metallic > METAL_THRESHOLD
    return nd.binary_dilation(metal, iterations=px) & ~nd.binary_erosion(metal, iterations=px, border_value=1)


def thin_metal_mask(true_metallic: np.ndarray, px: int = BOUNDARY_PX) -> np.ndarray:
    """``[H, W]`` bool: pixels within ``px`` of a *thin* true-metal part (poles, arms: a connected
    metal region that an erosion by ``px`` pixels leaves less than a fifth of)."""
    metal = true_metallic > METAL_THRESHOLD
    lab, n = nd.label(metal)
    if n == 0:
        return np.zeros_like(metal)
    size = nd.sum(np.ones_like(lab), lab, index=np.arange(1, n + 1))
    core = nd.sum(nd.binary_erosion(metal, iterations=px), lab, index=np.arange(1, n + 1))
    thin_ids = np.flatnonzero(core < 0.2 * size) + 1
    return nd.binary_dilation(np.isin(lab, thin_ids), iterations=px)


def _split(pred: torch.Tensor, true: torch.Tensor, boundary: torch.Tensor, thin: torch.Tensor | None = None) -> dict:
    """Squared-error sums of ``pred`` vs ``true`` (flat, masked already), all / metal / rest, on
    ``boundary`` pixels (flat bool, same mask) and on ``thin`` ones (near thin metal; default none)."""
    metal = true > METAL_THRESHOLD
    e2 = (pred - true) ** 2
    thin = torch.zeros_like(boundary) if thin is None else thin
    return {"n_thin": int(thin.sum()), "se_thin": float(e2[thin].sum()),
            "pred_thin_metal_sum": float(pred[thin & metal].sum()), "n_thin_metal": int((thin & metal).sum()),
            "n": int(e2.numel()), "se": float(e2.sum()), "n_metal": int(metal.sum()), "se_metal": float(e2[metal].sum()),
            "pred_metal_sum": float(pred[metal].sum()), "pred_rest_sum": float(pred[~metal].sum()),
            "n_boundary": int(boundary.sum()), "se_boundary": float(e2[boundary].sum()),
            "n_metal_interior": int((metal & ~boundary).sum()),
            "pred_metal_interior_sum": float(pred[metal & ~boundary].sum())}


def _finish(acc: dict) -> dict:
    n, nm = max(acc["n"], 1), max(acc["n_metal"], 1)
    rest = max(acc["n"] - acc["n_metal"], 1)
    return {"metallic_rmse": float(np.sqrt(acc["se"] / n)),
            "metal_share_of_pixels": acc["n_metal"] / n,
            "metal_share_of_error": acc["se_metal"] / max(acc["se"], 1e-12),
            "metallic_rmse_metal": float(np.sqrt(acc["se_metal"] / nm)),
            "metallic_rmse_rest": float(np.sqrt((acc["se"] - acc["se_metal"]) / rest)),
            "mean_pred_on_metal": acc["pred_metal_sum"] / nm, "mean_pred_on_rest": acc["pred_rest_sum"] / rest,
            "boundary_share_of_pixels": acc["n_boundary"] / n,
            "boundary_share_of_error": acc["se_boundary"] / max(acc["se"], 1e-12),
            "metallic_rmse_off_boundary": float(np.sqrt((acc["se"] - acc["se_boundary"]) / max(n - acc["n_boundary"], 1))),
            "mean_pred_on_metal_interior": acc["pred_metal_interior_sum"] / max(acc["n_metal_interior"], 1),
            "thin_share_of_pixels": acc["n_thin"] / n,
            "thin_share_of_error": acc["se_thin"] / max(acc["se"], 1e-12),
            "mean_pred_on_thin_metal": acc["pred_thin_metal_sum"] / max(acc["n_thin_metal"], 1)}


def _frame_split(pred_metallic: torch.Tensor, true_metallic: np.ndarray, mask: torch.Tensor) -> dict:
    """:func:`_split` of one frame: ``pred_metallic`` and ``true_metallic`` ``[H, W]``, ``mask``
    ``[H, W]`` bool (non-sky); the boundary band from the full frame's truth."""
    tm = np.asarray(true_metallic, np.float32).reshape(mask.shape)
    return _split(pred_metallic[mask], torch.from_numpy(tm)[mask], torch.from_numpy(boundary_mask(tm))[mask],
                  torch.from_numpy(thin_metal_mask(tm))[mask])


def _add(acc: dict | None, d: dict) -> dict:
    if acc is None:
        return dict(d)
    return {k: acc[k] + d[k] for k in acc}


def _metallic_map(r) -> torch.Tensor:
    """[H, W] the metallic a raster output ``r`` shows per pixel (its layer over its opacity)."""
    return (r.metallic * (1.0 / r.opacity.clamp_min(OPACITY_EPS))).clamp(0, 1)[..., 0].float()


def _oracle_metallic(g, cam: Camera, true_metallic: np.ndarray, true_depth: np.ndarray) -> torch.Tensor:
    """[N] the metallic of the Gaussians ``g`` with every one whose centre ``cam`` sees (its depth
    within 5% of the true depth at its pixel) set to the true metallic of that pixel."""
    h, w = true_depth.shape
    uv, z = cam.project(g.means.double().numpy())
    ok = np.isfinite(uv).all(1) & (z > 0)
    u = np.floor(np.nan_to_num(uv[:, 0], nan=-1.0)).astype(int)
    v = np.floor(np.nan_to_num(uv[:, 1], nan=-1.0)).astype(int)
    ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
    ok[ok] = np.abs(true_depth[v[ok], u[ok]] - z[ok]) < 0.05 * z[ok]
    m = g.metallic()[:, 0].clone()
    m[torch.from_numpy(ok)] = torch.from_numpy(true_metallic[v[ok], u[ok]]).to(m.dtype)
    return m


def stage_materials(run: RunDir, bundle, stage: str, threads: int = 2, oracle_floor: bool = False) -> dict:
    """Intrinsics of ``stage``'s scene graph on the bundle's test frames. With ``oracle_floor``
    also ``metallic_rmse_oracle_per_gaussian``: the pooled metallic RMSE when, frame by frame,
    every Gaussian whose centre the frame sees takes the true metallic of its pixel, the rest
    keeping theirs (what the splats' footprints alone cost with per-Gaussian metallic right;
    ground truth input), and ``metallic_rmse_rounded`` with each Gaussian's metallic rounded to
    0 or 1 (``metallic_rmse_as_is`` beside them is the pooled ``metallic_rmse``)."""
    import dataclasses

    before = STAGES[STAGES.index(stage) + 1] if STAGES.index(stage) + 1 < len(STAGES) else None
    graph, _sky, st = run.load_scene(before)
    assert st == stage, (st, stage)
    rs = RasterSettings(threads=threads)
    times = bundle.manifest.times
    acc, rows = None, []
    se = {"oracle_per_gaussian": 0.0, "rounded": 0.0}
    n = 0
    with torch.no_grad():
        for f in sorted(bundle.frames("test"), key=lambda f: (f.time_index, f.id)):
            c = bundle.camera(f)
            cam = Camera.from_bundle(c, f)
            g = graph.compose(float(times[f.time_index])).detach()
            r = rasterize_gaussians(g, cam, settings=rs)
            gtl = bundle.load_ground_truth(f)
            mask = torch.from_numpy(gtl["depth"].reshape(c.height, c.width) > 0)
            row = frame_intrinsics(r, gtl, c.height, c.width)
            del row["metallic_rmse"]  # pooled over the frames below, with its metal / rest split
            acc = _add(acc, _frame_split(_metallic_map(r), gtl["metallic"], mask))
            rows.append(row)
            if oracle_floor:
                tm = gtl["metallic"].reshape(c.height, c.width)
                variants = {"oracle_per_gaussian": _oracle_metallic(g, cam, tm, gtl["depth"].reshape(c.height, c.width)),
                            "rounded": (g.metallic()[:, 0] > 0.5).to(g.metallic_logits.dtype)}
                for k, m in variants.items():
                    logits = torch.logit(m.clamp(1e-4, 1 - 1e-4))[:, None].to(g.metallic_logits.dtype)
                    pred = _metallic_map(rasterize_gaussians(dataclasses.replace(g, metallic_logits=logits), cam, settings=rs))
                    se[k] += float(((pred - torch.from_numpy(tm)) ** 2)[mask].sum())
                n += int(mask.sum())
    out = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
    out.update(_finish(acc))
    if oracle_floor:
        out["metallic_rmse_as_is"] = out["metallic_rmse"]
        out.update({f"metallic_rmse_{k}": float(np.sqrt(v / max(n, 1))) for k, v in se.items()})
    return out


def prior_materials(path: Path, bundle) -> dict:
    """A priors file's metallic layer on the training frames against their truth."""
    from core.stages.priors import GBufferPriors

    if not path.is_file():
        return {}
    pri, _ = GBufferPriors.load(path)
    acc = None
    for fr in bundle.frames("train"):
        layers = pri.frame(fr.id)
        if layers is None or "metallic" not in layers:
            continue
        gtl = bundle.load_ground_truth(fr)
        c = bundle.camera(fr)
        mask = torch.from_numpy(gtl["depth"].reshape(c.height, c.width) > 0)
        met = torch.as_tensor(np.asarray(layers["metallic"], np.float32)).reshape(mask.shape)
        acc = _add(acc, _frame_split(met, gtl["metallic"], mask))
    return _finish(acc) if acc else {}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--priors", action="store_true", help="also the inverse model's priors on the training frames")
    ap.add_argument("--oracle-floor", action="store_true",
                    help="also each stage's metallic RMSE with per-Gaussian metallic from the truth (stage_materials)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    res = {}
    for r in a.runs:
        run = RunDir(r)
        b = open_bundle(run.scene_path())
        per = {}
        if a.priors:
            per["priors_train_frames"] = prior_materials(run.root / "priors" / "priors.npz", b)
            per["refined_priors_train_frames"] = prior_materials(run.stage_dir("generative_refine") / "priors.npz", b)
            for k in ("priors_train_frames", "refined_priors_train_frames"):
                print(r, k, json.dumps({k2: round(v, 4) for k2, v in per[k].items()}), flush=True)
        for st in GRAPH_STAGES:
            if run.is_done(st):
                per[st] = stage_materials(run, b, st, oracle_floor=a.oracle_floor)
                print(r, st, json.dumps({k: round(v, 4) for k, v in per[st].items()}), flush=True)
        res[r] = per
    if a.out:
        Path(a.out).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
