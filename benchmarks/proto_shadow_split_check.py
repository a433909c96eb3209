"""How well the capture's ground pixels split into sun and shade (the cue of
``benchmarks/proto_shadow_carving.py``), against the true sun visibility (the true meshes as
occluders, the true sun direction: ground truth, a diagnostic).

    python benchmarks/proto_shadow_split_check.py RUN

Ground pixels (reconstructed normal z > 0.9, unclipped) of every other pbr-stage training frame,
radiance / reconstructed albedo; 2-means per frame on log brightness, on log red/blue, or on both
(standardised); precision and recall of the lit cluster.
"""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1])); sys.path.insert(0, str(Path(__file__).resolve().parent))
from core.bundle import open_bundle
from core.stages.chain import RunDir, profile_settings
from core.scene_graph import SceneGraph
from core.stages.pbr import _frames, prior_inputs
from lighting_harness import occluder_tracer
import diagnose_rerender as dr
if len(sys.argv) < 2:
    raise SystemExit(__doc__)
run = sys.argv[1]
b = open_bundle(RunDir(run).scene_path()); g = SceneGraph.load(f'{run}/volume2/checkpoint/scene_graph.pt')
cfg = profile_settings('quick', 'pbr'); frames, _ = _frames(g, b, cfg); x = prior_inputs(frames)
orc = occluder_tracer(b, 'oracle'); _, sd = dr._sun_mask(dr._true_map(b)); m = b.manifest
res = {'bright': [], 'chroma': [], 'both': []}
for i, f in enumerate(frames[::2]):
    i *= 2
    img = x['img'][i].astype(np.float64) ** m.ldr_gamma / m.ldr_exposure
    alb = np.maximum(x['albedo'][i], 0.02); n = x['normal'][i]; dep = x['depth'][i]
    ground = (~x['sky'][i]) & (dep > 0) & (n[..., 2] > 0.9) & (img.max(-1) < 0.95 ** 2.2)
    if ground.sum() < 200: continue
    rays = f.camera.ray_directions(); pose = f.camera.pose_numpy()
    pts = pose[:3, 3] + rays * (dep / (rays @ pose[:3, 2]))[..., None]
    P = pts[ground] + np.array([0, 0, 0.1])
    truth = orc(P, np.broadcast_to(sd, P.shape).copy()) > 0.5
    sh = img / alb
    lb = np.log(sh.mean(-1)[ground])
    lc = np.log(sh[ground][:, 0] / np.maximum(sh[ground][:, 2], 1e-6))  # red / blue of the shading: the sun is warm
    for name, feat in (('bright', lb[:, None]), ('chroma', lc[:, None]), ('both', np.stack([lb, lc], 1))):
        z = (feat - feat.mean(0)) / np.maximum(feat.std(0), 1e-9)
        c = np.percentile(z, [20, 80], axis=0)
        for _ in range(30):
            lab = ((z - c[1]) ** 2).sum(1) < ((z - c[0]) ** 2).sum(1)
            if lab.all() or (~lab).all(): break
            c = np.stack([z[~lab].mean(0), z[lab].mean(0)])
        # the lit cluster: the brighter / redder one
        if z[lab].sum() < z[~lab].sum() * lab.sum() / max((~lab).sum(), 1): lab = ~lab
        res[name].append(((lab & truth).sum(), (lab & ~truth).sum(), (~lab & truth).sum(), (~lab & ~truth).sum()))
for k, v in res.items():
    tp, fp, fn, tn = np.sum(v, 0)
    print(k, 'precision of lit %.3f recall %.3f | true lit frac %.3f' % (tp / max(tp + fp, 1), tp / max(tp + fn, 1), (tp + fn) / (tp + fp + fn + tn)))
