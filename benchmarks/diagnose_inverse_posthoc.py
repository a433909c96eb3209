"""Can a post-hoc step lower the inverse model's roughness / metallic error? (diagnostic; reads
ground truth)

Two post-processing families of the product's ensemble-mean G-buffer (as ``generative.json``'s
``ood`` key scores it), neither in the product:

- **calibration**: a monotone map per channel (isotonic regression on 64 bins of the prediction,
  pool-adjacent-violators), fitted on the randomised training streets (``--fit-train`` of them) or
  on the validation split, applied to every split;
- **guided filter**: the colour guided filter (He et al. 2010) of roughness and metallic with the
  frame as guide (radius ``r`` px, regulariser ``eps``), which snaps blurred material edges to the
  frame's colour edges.

Figures per split as the ``ood`` key computes them (per clip RMSE over non-sky pixels, mean over
the clips of a street, then over the split's streets; the OOD mean over the four
``test_ood_<axis>`` splits). The choice is printed from the validation split only.

    python benchmarks/diagnose_inverse_posthoc.py ROOT --out J [--fit-train 8]

``ROOT``: ``benchmarks/make_randomised.py`` output (``ROOT/<split>/<split>_<i>``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

#: Bins of the calibration's monotone map over [0, 1].
BINS = 64
#: Guided-filter settings tried: (radius px, eps).
GUIDED = ((1, 1e-3), (1, 1e-2), (2, 1e-3), (2, 1e-2), (4, 1e-3))
CHANNELS = ("roughness", "metallic")


def box(x: torch.Tensor, r: int) -> torch.Tensor:
    """Mean of ``x`` [N, C, H, W] over a (2r+1)^2 window, normalised by the pixels inside the frame."""
    k = 2 * r + 1
    s = F.avg_pool2d(F.pad(x, (r, r, r, r)), k, stride=1)
    n = F.avg_pool2d(F.pad(torch.ones_like(x[:, :1]), (r, r, r, r)), k, stride=1)
    return s / n


def guided_filter(guide: torch.Tensor, p: torch.Tensor, r: int, eps: float) -> torch.Tensor:
    """Colour guided filter: ``guide`` [N, 3, H, W] in [0, 1], ``p`` [N, 1, H, W]."""
    m_i, m_p = box(guide, r), box(p, r)
    cov_ip = box(guide * p, r) - m_i * m_p
    n, _, h, w = guide.shape
    sigma = torch.empty(n, h, w, 3, 3, dtype=guide.dtype)
    for i in range(3):
        for j in range(3):
            sigma[..., i, j] = box(guide[:, i:i + 1] * guide[:, j:j + 1], r)[:, 0] - m_i[:, i] * m_i[:, j]
    sigma = sigma + eps * torch.eye(3, dtype=guide.dtype)
    a = torch.linalg.solve(sigma, cov_ip.permute(0, 2, 3, 1)[..., None])[..., 0].permute(0, 3, 1, 2)
    b = m_p - (a * m_i).sum(1, keepdim=True)
    return (box(a, r) * guide).sum(1, keepdim=True) + box(b, r)


def pava(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted isotonic (non-decreasing) least-squares fit of ``y`` (pool adjacent violators)."""
    blocks: list[list[float]] = []
    for v, wt in zip(y.tolist(), w.tolist()):
        blocks.append([v, wt, 1])
        while len(blocks) > 1 and blocks[-2][0] > blocks[-1][0]:
            a, b = blocks.pop(), blocks.pop()
            ww = a[1] + b[1]
            blocks.append([(a[0] * a[1] + b[0] * b[1]) / ww, ww, a[2] + b[2]])
    return np.concatenate([np.full(n, v) for v, _, n in blocks])


def fit_monotone(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """[BINS] table of E[true | pred bin], made non-decreasing; empty bins keep their centre."""
    idx = np.clip((pred * BINS).astype(int), 0, BINS - 1)
    w = np.bincount(idx, minlength=BINS).astype(float)
    s = np.bincount(idx, weights=true, minlength=BINS)
    centres = (np.arange(BINS) + 0.5) / BINS
    y = np.where(w > 0, s / np.maximum(w, 1.0), centres)
    return pava(y, np.maximum(w, 1e-3))


def apply_monotone(table: np.ndarray, x: torch.Tensor) -> torch.Tensor:
    centres = (np.arange(BINS) + 0.5) / BINS
    return torch.from_numpy(np.interp(x.numpy(), centres, table))


def predict_street(sess, den, street: Path) -> list[dict]:
    """Per clip: prediction and truth of roughness / metallic [T, 1, H, W] in [0, 1], frames, mask."""
    from core.gen import contract as C
    from core.synth.gen_data import DataSettings, load_clips
    from core.synth.gen_train import predict_inverse_clip

    sl = C.GBUFFER_SLICES
    out = []
    for clip in load_clips(street, DataSettings(forward_source="degrade"), ("inverse",)):
        y, g, rgb, mask = predict_inverse_clip(sess, den, clip)
        y = y.double()
        to01 = lambda a: (a.double().clamp(-1, 1) + 1) / 2  # noqa: E731
        rec = {"guide": to01(rgb), "mask": mask}
        for k in CHANNELS:
            rec[f"pred_{k}"], rec[f"true_{k}"] = to01(y[:, sl[k]]), to01(g[:, sl[k]])
        out.append(rec)
    return out


def street_rmse(clips: list[dict], post) -> dict:
    """Roughness / metallic RMSE of one street: per clip over its non-sky pixels, after
    ``post(channel, clip)`` (clamped to [0, 1]), then the mean over its clips."""
    res = {}
    for k in CHANNELS:
        v = []
        for c in clips:
            q = post(k, c).clamp(0, 1)
            v.append(float(torch.sqrt(((q - c[f"true_{k}"])[:, 0][c["mask"]] ** 2).mean())))
        res[f"{k}_rmse"] = float(np.mean(v))
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("root", type=Path)
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--model", default=str(REPO / "models" / "inverse_gbuffer.onnx"))
    ap.add_argument("--fit-train", type=int, default=8, help="training streets the calibration is fitted on")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)

    from core.gen.edm import OnnxDenoiser
    from core.gen.runtime import load_model

    torch.set_num_threads(a.threads)
    sess = load_model(a.model, kind="inverse_gbuffer", threads=a.threads)
    den = OnnxDenoiser(sess)
    t0 = time.perf_counter()
    streets: dict[str, dict[str, list]] = {}
    splits = ["train", "val", "test_id"] + sorted(p.name for p in a.root.glob("test_ood_*"))
    for sp in splits:
        dirs = sorted(d for d in (a.root / sp).glob(f"{sp}_*") if (d / "bundle.json").is_file())
        if sp == "train":
            dirs = dirs[:a.fit_train]
        if not dirs:
            raise SystemExit(f"{a.root / sp}: no streets")
        streets[sp] = {d.name: predict_street(sess, den, d) for d in dirs}
        print(f"{sp}: {len(dirs)} streets", flush=True)

    def pooled(sp):
        """{(pred|true, channel): [pixels]} over every non-sky pixel of the split's streets."""
        return {(w, k): np.concatenate([c[f"{w}_{k}"][:, 0][c["mask"]].numpy() for cl in streets[sp].values() for c in cl])
                for k in CHANNELS for w in ("pred", "true")}

    variants = {"raw": lambda k, c: c[f"pred_{k}"]}
    tables = {}
    for fit_on in ("train", "val"):
        px = pooled(fit_on)
        tables[fit_on] = {k: fit_monotone(px[("pred", k)], px[("true", k)]) for k in CHANNELS}
        variants[f"calibrated_on_{fit_on}"] = (lambda t: lambda k, c: apply_monotone(t[k], c[f"pred_{k}"]))(tables[fit_on])
    for r, eps in GUIDED:
        variants[f"guided_r{r}_eps{eps:g}"] = (lambda r, eps: lambda k, c: guided_filter(c["guide"], c[f"pred_{k}"], r, eps))(r, eps)

    rows: dict[str, dict] = {}
    for name, post in variants.items():
        per = {}
        for sp, ss in streets.items():
            vals = [street_rmse(cl, post) for cl in ss.values()]
            per[sp] = {m: round(float(np.mean([v[m] for v in vals])), 4) for m in vals[0]}
        ood = [per[sp] for sp in per if sp.startswith("test_ood_")]
        per["ood_mean"] = {m: round(float(np.mean([o[m] for o in ood])), 4) for m in ood[0]}
        rows[name] = per
        print(f"{name:26s} " + "  ".join(f"{sp}={v['roughness_rmse']:.4f}/{v['metallic_rmse']:.4f}" for sp, v in per.items()),
              flush=True)
    score = {n: r["val"]["roughness_rmse"] + r["val"]["metallic_rmse"] for n, r in rows.items() if n != "calibrated_on_val"}
    chosen = min(score, key=score.get)
    res = {"what": __doc__.split("\n")[0] + " " + __doc__.split("\n")[1].strip(),
           "how": "python benchmarks/diagnose_inverse_posthoc.py ROOT --out J --fit-train %d" % a.fit_train,
           "machine": {"cores": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()},
           "model": a.model, "streets": {sp: sorted(ss) for sp, ss in streets.items()},
           "calibration_tables": {f: {k: np.round(t, 4).tolist() for k, t in tt.items()} for f, tt in tables.items()},
           "rows": rows,
           "chosen_on_val": {"rule": "lowest val roughness + metallic RMSE among the variants not fitted on val",
                             "variant": chosen, "val_score": round(score[chosen], 4),
                             "raw_val_score": round(score["raw"], 4)},
           "seconds": round(time.perf_counter() - t0, 1)}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(res, indent=1))
    print(f"chosen on val: {chosen} (val {score[chosen]:.4f} against raw {score['raw']:.4f}); wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
