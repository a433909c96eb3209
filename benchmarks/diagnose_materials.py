"""Where the material error of a reconstruction comes from, stage by stage (a diagnostic: it reads
the bundle's ground truth, which the product never does).

For each finished stage with a scene graph (volume, volume2, joint) of a run, the intrinsics of
``brdf evaluate`` on the bundle's test frames (albedo si-PSNR, roughness and metallic RMSE, normal
MAE on non-sky pixels), plus the metallic error split into true-metal pixels (ground-truth
metallic > 0.5) and the rest, and the share of it on pixels within 2 px of a metal / non-metal
boundary (soft splat edges, thin poles) against the rest. With ``--priors``, the same split for
the inverse model's priors on the training frames against the training frames' ground truth.

    python benchmarks/diagnose_materials.py RUN [RUN ...] [--out J]
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


def _split(pred: torch.Tensor, true: torch.Tensor, boundary: torch.Tensor) -> dict:
    """Squared-error sums of ``pred`` vs ``true`` (flat, masked already), all / metal / rest, and
    on ``boundary`` pixels (flat bool, same mask)."""
    metal = true > METAL_THRESHOLD
    e2 = (pred - true) ** 2
    return {"n": int(e2.numel()), "se": float(e2.sum()), "n_metal": int(metal.sum()), "se_metal": float(e2[metal].sum()),
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
            "mean_pred_on_metal_interior": acc["pred_metal_interior_sum"] / max(acc["n_metal_interior"], 1)}


def _frame_split(pred_metallic: torch.Tensor, true_metallic: np.ndarray, mask: torch.Tensor) -> dict:
    """:func:`_split` of one frame: ``pred_metallic`` and ``true_metallic`` ``[H, W]``, ``mask``
    ``[H, W]`` bool (non-sky); the boundary band from the full frame's truth."""
    tm = np.asarray(true_metallic, np.float32).reshape(mask.shape)
    return _split(pred_metallic[mask], torch.from_numpy(tm)[mask], torch.from_numpy(boundary_mask(tm))[mask])


def _add(acc: dict | None, d: dict) -> dict:
    if acc is None:
        return dict(d)
    return {k: acc[k] + d[k] for k in acc}


def stage_materials(run: RunDir, bundle, stage: str, threads: int = 2) -> dict:
    """Intrinsics of ``stage``'s scene graph on the bundle's test frames."""
    before = STAGES[STAGES.index(stage) + 1] if STAGES.index(stage) + 1 < len(STAGES) else None
    graph, _sky, st = run.load_scene(before)
    assert st == stage, (st, stage)
    rs = RasterSettings(threads=threads)
    times = bundle.manifest.times
    acc, rows = None, []
    with torch.no_grad():
        for f in sorted(bundle.frames("test"), key=lambda f: (f.time_index, f.id)):
            c = bundle.camera(f)
            g = graph.compose(float(times[f.time_index])).detach()
            r = rasterize_gaussians(g, Camera.from_bundle(c, f), settings=rs)
            gtl = bundle.load_ground_truth(f)
            mask = torch.from_numpy(gtl["depth"].reshape(c.height, c.width) > 0)
            row = frame_intrinsics(r, gtl, c.height, c.width)
            del row["metallic_rmse"]  # pooled over the frames below, with its metal / rest split
            met = (r.metallic * (1.0 / r.opacity.clamp_min(OPACITY_EPS))).clamp(0, 1)[..., 0].float()
            acc = _add(acc, _frame_split(met, gtl["metallic"], mask))
            rows.append(row)
    out = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
    out.update(_finish(acc))
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
                per[st] = stage_materials(run, b, st)
                print(r, st, json.dumps({k: round(v, 4) for k, v in per[st].items()}), flush=True)
        res[r] = per
    if a.out:
        Path(a.out).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
