"""Prototype (not in the product): carve a run's occluders with the capture's own shadows.

    python benchmarks/proto_shadow_carving.py SRC_RUN DST_RUN SUN_RUN [RADIUS_M]

Copies SRC_RUN's stages up to volume2 into DST_RUN and edits volume2's occluders (then run
``brdf reconstruct --out DST_RUN --resume --stages pbr,joint``). Inputs are the capture's own:
the sun direction is SUN_RUN's pbr-stage lighting prior (``sun_dir_prior``), the ground pixels
(reconstructed normal z > 0.9) of the pbr stage's training frames are split into sun and shade
by 2-means on (log brightness, log red/blue) of radiance / reconstructed albedo (shade is
bluer: lit by the sky alone), keeping only pixels a margin (env MARGIN, default 0.5 in
standardised units) nearer one centre; an occluder Gaussian within RADIUS_M (default 0.4) of the
sun rays of at least 2 lit samples and of more than twice as many lit as shadowed samples'
rays is removed. Measured on the default scene (``benchmarks/results/rerender_diagnosis.json``,
``shadow_carving_prototype``)."""
import json
import os
import shutil
import sys

import numpy as np
import torch
sys.path.insert(0, str(__import__('pathlib').Path(__file__).resolve().parents[1]))
from pathlib import Path
from core.bundle import open_bundle
from core.stages.chain import RunDir, profile_settings
from core.scene_graph import SceneGraph
from core.stages.pbr import _frames, prior_inputs

def split_sun_shade(shading, ground, margin):
    """Sun / shade masks [H, W] of the ``ground`` pixels from ``shading`` [H, W, 3] (radiance /
    albedo): 2-means on standardised (log brightness, log red/blue), each cluster kept where a
    pixel is ``margin`` nearer its centre; (None, None) without two clusters."""
    g = shading[ground]
    feat = np.stack([np.log(g.mean(-1)), np.log(g[:, 0] / np.maximum(g[:, 2], 1e-6))], 1)
    z = (feat - feat.mean(0)) / np.maximum(feat.std(0), 1e-9)
    c = np.percentile(z, [20, 80], axis=0)
    for _ in range(30):
        lab = ((z - c[1]) ** 2).sum(1) < ((z - c[0]) ** 2).sum(1)
        if lab.all() or (~lab).all():
            return None, None
        c = np.stack([z[~lab].mean(0), z[lab].mean(0)])
    if z[lab].mean() < z[~lab].mean():  # the lit cluster is the brighter, redder one
        lab, c = ~lab, c[::-1]
    marg = np.sqrt(((z - c[0]) ** 2).sum(1)) - np.sqrt(((z - c[1]) ** 2).sum(1))
    lit, shade = np.zeros_like(ground), np.zeros_like(ground)
    lit[ground], shade[ground] = lab & (marg > margin), ~lab & (marg < -margin)
    return lit, shade


def main():
    if len(sys.argv) < 4:
        raise SystemExit(__doc__)
    src, dst, sun_src = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3])
    radius = float(sys.argv[4]) if len(sys.argv) > 4 else 0.4
    sd = np.array(json.load(open(sun_src / 'pbr/summary.json'))['sun_dir_prior'])
    if dst.exists(): shutil.rmtree(dst)
    dst.mkdir(parents=True)
    for d in ('priors', 'volume', 'generative_refine', 'volume2'):
        shutil.copytree(src / d, dst / d)
    shutil.copy2(src / 'run.json', dst / 'run.json')
    b = open_bundle(RunDir(src).scene_path())
    p = dst / 'volume2/checkpoint/scene_graph.pt'
    g = SceneGraph.load(p)
    cfg = profile_settings('quick', 'pbr')
    frames, _ = _frames(g, b, cfg)
    x = prior_inputs(frames)
    m = b.manifest
    rays_all = []; shadow_all = []
    for i, f in enumerate(frames):
        H, W = f.camera.height, f.camera.width
        img = x['img'][i].astype(np.float64) ** m.ldr_gamma / m.ldr_exposure
        alb = np.maximum(x['albedo'][i], 0.02)
        n = x['normal'][i]; dep = x['depth'][i]
        ground = (~x['sky'][i]) & (dep > 0) & (n[..., 2] > 0.9) & (img.max(-1) < 0.95 ** 2.2)
        if ground.sum() < 200: continue
        lit, shadow = split_sun_shade(img / alb, ground, float(os.environ.get('MARGIN', '0.5')))
        if lit is None: continue
        rays = f.camera.ray_directions(); pose = f.camera.pose_numpy()
        pts = pose[:3, 3] + rays * (dep / (rays @ pose[:3, 2]))[..., None]
        Q = pts[shadow]
        if len(Q) > 400: Q = Q[np.random.default_rng(100 + i).choice(len(Q), 400, replace=False)]
        shadow_all.append(Q)
        P = pts[lit]
        if len(P) > 400: P = P[np.random.default_rng(i).choice(len(P), 400, replace=False)]
        rays_all.append(P)
    O = np.concatenate(rays_all) + np.array([0, 0, 0.1])
    occ = g.occluders
    M = occ.means.detach().double().numpy()
    def votes(OO):
        cnt = np.zeros(len(M))
        for k in range(0, len(OO), 100):
            o = OO[k:k + 100]
            v = M[None] - o[:, None]
            t = v @ sd
            d2 = (v ** 2).sum(-1) - t ** 2
            cnt += ((t > 0.5) & (d2 < radius ** 2)).sum(0)
        return cnt
    S = np.concatenate(shadow_all) + np.array([0, 0, 0.1])
    lit_v, sh_v = votes(O), votes(S)
    keep = ~((lit_v >= 2) & (lit_v > 2 * sh_v))
    print('shadow rays', len(S))
    print('lit rays', len(O), 'occluders', len(M), '->', int(keep.sum()))
    g.occluders = occ.index(torch.from_numpy(np.flatnonzero(keep)))
    g.save(p)


if __name__ == '__main__':
    main()
