"""Prototype, not in the product: rank the lighting prior's sun candidates by the PBR pass.

The prior's search (:func:`core.lighting.prior.estimate_lighting`, the pbr stage's settings) on a
run's volume2; its best coarse cells at least 20 deg apart, each refined; for each candidate the
PBR pass renders its sun alone (the prior's irradiance) and the prior's sky alone on 1024 pixels
of every training frame, and the L1-optimal gains of the two (grid) give its residual against
the capture. Reads the true sun only to print each candidate's error.

    python benchmarks/proto_sun_verify.py RUN [K]

Result (``benchmarks/results/sun_floor.json``, ``tried_not_kept``): on the default scene it
preferred a candidate 30.5 deg off (L1 0.0836) to the prior's 4.6 deg one (0.0865): not kept.
"""
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
import core.lighting.prior as P
from core.stages.chain import RunDir
from core.bundle import open_bundle
from core.camera import Camera
from core.pbr.envmap import EnvironmentMap, resample
from core.pbr.render import render_pbr
from core.stages.pbr import _frames, prior_inputs
from core.stages.pbr_settings import PBRStageConfig
from core.lighting.prior import (LightingSettings, brightest_direction, compose_envmap, estimate_lighting,
                                 numpy_visibility, sun_direction_error_deg)

run = RunDir(sys.argv[1]); K = int(sys.argv[2]) if len(sys.argv) > 2 else 6
b = open_bundle(run.scene_path()); graph, _sky, stage = run.load_scene(before="pbr"); print("graph", stage)
cfg = PBRStageConfig()
frames, tracer = _frames(graph, b, cfg)
x = prior_inputs(frames); m = b.manifest
true_sun = brightest_direction(resample(torch.from_numpy(np.asarray(b.load_envmap(), np.float64)), 512, 1024).numpy())
probe = {}
orig = P._search_sun
def search(score, st):
    probe["score"] = score
    out = orig(score, st); return out
P._search_sun = search
est = estimate_lighting(x["img"], Camera.stack([f.camera for f in frames]), x["sky"], x["depth"], x["normal"], albedo=x["albedo"],
                        exposure=m.ldr_exposure, gamma=m.ldr_gamma,
                        settings=LightingSettings(height=256, sun_model="lambert", max_points=16000, basin_quantile=0.05),
                        visibility=numpy_visibility(tracer))
P._search_sun = orig
score = probe["score"]
print("prior sun err", round(sun_direction_error_deg(est.sun_dir, true_sun), 1), "irr", est.sun_irradiance)
# candidates: best coarse cells >= 20 deg apart, refined locally
step = math.radians(8.0)
az = np.arange(-math.pi, math.pi, step); el = np.arange(math.radians(2), math.radians(88), step)
a_, e_ = np.meshgrid(az, el, indexing="ij"); grid = P._sph(a_.ravel(), e_.ravel())
res = score(grid)
cands = [np.asarray(est.sun_dir)]
for i in np.argsort(res):
    if len(cands) >= K: break
    if all(grid[i] @ c < math.cos(math.radians(20)) for c in cands):
        ca, ce, cr = a_.ravel()[i], e_.ravel()[i], res[i]
        for fine in (step / 4, step / 16):
            da = np.arange(-4, 5) * fine
            aa, ee = np.meshgrid(ca + da / max(math.cos(ce), 0.2), np.clip(ce + da, math.radians(2), math.radians(89)), indexing="ij")
            cd = P._sph(aa.ravel(), ee.ravel()); r2 = score(cd); j = int(np.argmin(r2))
            if r2[j] <= cr: ca, ce, cr = aa.ravel()[j], ee.ravel()[j], r2[j]
        cands.append(P._sph(ca, ce))
H = 256
sky_only = compose_envmap(est.sky_coeffs, est.sun_dir, np.zeros(3), est.ground_radiance, H)  # same sky (glow at the prior's sun)
ps = cfg.pbr_settings(rays_per_pixel=16, exposure=1.0, gamma=1.0, threads=2, seed=0)
gen = torch.Generator().manual_seed(0)
idxs = [f.nonsky[torch.randperm(f.nonsky.numel(), generator=gen)[:1024]] for f in frames]
def render(envarr):
    env = EnvironmentMap(torch.from_numpy(np.asarray(envarr, np.float64)))
    out = []
    for f, idx in zip(frames, idxs):
        r = render_pbr(f.gbuf, f.camera, env, settings=ps, tracers=f.tracers, pixels=idx, generator=torch.Generator().manual_seed(1))
        out.append(r.hdr.detach().double().numpy().reshape(-1, 3))
    return np.concatenate(out)
t0 = time.time()
tgt = np.concatenate([f.target[idx].double().numpy() for f, idx in zip(frames, idxs)])
hk = render(sky_only)
rows = []
for c in cands:
    sun_only = compose_envmap(est.sky_coeffs, c, est.sun_irradiance, est.ground_radiance, H) - compose_envmap(est.sky_coeffs, c, np.zeros(3), est.ground_radiance, H)
    hs = render(np.maximum(sun_only, 1e-6))
    best = (np.inf, 1, 1)
    for gs in np.arange(0.1, 2.001, 0.05):
        for gk in np.arange(0.3, 2.001, 0.05):
            p = np.clip((gs * hs + gk * hk) * m.ldr_exposure, 0, 1) ** (1 / m.ldr_gamma)
            l = float(np.abs(p - tgt).mean())
            if l < best[0]: best = (l, gs, gk)
    rows.append((round(sun_direction_error_deg(c, true_sun), 1), round(float(np.degrees(np.arcsin(c[2]))), 1), round(best[0], 5), round(best[1], 2), round(best[2], 2), round(float(score(np.asarray(c)[None])[0]), 4)))
    print("cand err %5.1f elev %5.1f  L1 %.5f  gsun %.2f gsky %.2f  lambert %.4f" % rows[-1], flush=True)
print("seconds", round(time.time() - t0, 1))
best = min(rows, key=lambda r: r[2]); print("PICK", best)
