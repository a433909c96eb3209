"""The lighting prior's ground-truth harness: :func:`core.lighting.prior.estimate_lighting` run on a
synthetic bundle's ground-truth G-buffers (depth, normals, albedo, roughness, metallic) standing in
for the reconstruction, optionally perturbed, with optional occluders (the capture's LiDAR, or the
street's true meshes as Gaussians). It reads ground truth and rebuilds the generator's street, so
it lives with the benchmarks, never on the product path (which runs the prior on the
reconstruction's own G-buffers: :mod:`core.stages.pbr`).

Used by ``benchmarks/eval_lighting.py`` and ``benchmarks/bench_generative.py``.
"""

from __future__ import annotations

import math

import numpy as np

from core.camera import Camera
from core.errors import ConfigError
from core.lighting.prior import LightingEstimate, LightingSettings, estimate_lighting, numpy_visibility
from core.numerics import safe_normalize_np

#: Gaussians of the "oracle" occluders (the street's true meshes as thin Gaussians), and the
#: largest spacing between them (metres).
ORACLE_GAUSSIANS = 60_000
ORACLE_MAX_SPACING_M = 1.0
#: ``edge_refine`` of the oracle occluders: a 4x finer lattice along face edges keeps building
#: corners and roof edges from blurring ~0.5 m out of the facade (at a grazing sun those blurred
#: edges shadowed most of the wall they belong to).
ORACLE_EDGE_REFINE = 4


def estimate_from_bundle(root, split: str = "train", settings: LightingSettings | None = None,
                         depth_noise_m: float = 0.0, normal_noise_deg: float = 0.0, albedo_noise: float = 0.0,
                         use_albedo: bool = True, seed: int = 0, occluders: str = "none",
                         use_materials: bool = True, oracle_gaussians: int = ORACLE_GAUSSIANS) -> LightingEstimate:
    """:func:`estimate_lighting` on a bundle's frames of ``split``, with the bundle's ground-truth
    depth, normals, albedo (and, with ``use_materials``, roughness and metallic) standing in for
    the reconstruction (optionally perturbed: Gaussian depth noise in metres, normal noise in
    degrees, multiplicative log-normal albedo noise of std ``albedo_noise`` per pixel, to measure
    robustness).

    ``occluders`` (the cast-shadow cue): ``"none"``; ``"lidar"``: Gaussians at the capture's
    LiDAR points (every sweep, seen by a camera or not, opacity 0.9), what any reconstruction
    starts from; ``"oracle"``: the synthetic street's ground-truth meshes as thin Gaussians
    (:func:`core.synth.oracle.street_scene_graph`, static parts at time 0), the stand-in for a
    converged reconstruction: a face lattice of ``oracle_gaussians`` Gaussians plus 4x finer
    bands along the face edges (:data:`ORACLE_EDGE_REFINE`; about 3x as many in all), thin
    slivers (:attr:`core.synth.oracle.OracleSettings.thin_slivers`).
    """
    from core.bundle import open_bundle

    b = open_bundle(root, validate=False)
    visibility = occluder_tracer(b, occluders, oracle_gaussians)
    frames = sorted(b.frames(split), key=lambda fr: fr.time_index)
    if not frames:
        raise ConfigError(f"{root}: no frames in split {split!r}")
    rng = np.random.default_rng(seed)
    imgs, cams, skies, deps, nrms, albs, rough, metal = [], [], [], [], [], [], [], []
    for fr in frames:
        gt = b.load_ground_truth(fr)
        imgs.append(b.load_image(fr))
        cams.append(Camera.from_bundle(b.camera(fr), fr))
        sk = b.load_sky_mask(fr)
        skies.append(sk if sk is not None else gt["depth"][..., 0] <= 0)
        d = gt["depth"][..., 0].copy()
        n = gt["normal"].copy()
        if depth_noise_m > 0:
            d = np.where(d > 0, np.maximum(d + rng.normal(0, depth_noise_m, d.shape), 0.05), 0)
        if normal_noise_deg > 0:
            n = n + rng.normal(0, math.radians(normal_noise_deg), n.shape)
            n = safe_normalize_np(n) * (np.linalg.norm(gt["normal"], axis=-1, keepdims=True) > 0.5)
        deps.append(d)
        nrms.append(n)
        al = gt["albedo"]
        if albedo_noise > 0:
            al = np.clip(al * np.exp(rng.normal(0, albedo_noise, al.shape[:2] + (1,))), 0, 1)
        albs.append(al)
        rough.append(gt["roughness"][..., 0])
        metal.append(gt["metallic"][..., 0])
    m = b.manifest
    return estimate_lighting(np.stack(imgs), Camera.stack(cams), np.stack(skies),
                             np.stack(deps), np.stack(nrms).astype(np.float32),
                             albedo=np.stack(albs) if use_albedo else None, exposure=m.ldr_exposure,
                             gamma=m.ldr_gamma, settings=settings, visibility=visibility,
                             roughness=np.stack(rough) if use_materials else None,
                             metallic=np.stack(metal) if use_materials else None)


def occluder_tracer(bundle, occluders: str, oracle_gaussians: int = ORACLE_GAUSSIANS):
    """A shadow-ray tracer (:class:`core.pbr.visibility.GaussianTracer`) of a bundle's occluders
    (see :func:`estimate_from_bundle`), or None for ``"none"``."""
    from dataclasses import replace

    from core.pbr.visibility import GaussianTracer, TraceSettings

    if occluders == "none":
        return None
    if occluders == "lidar":
        from core.train.init_lidar import LidarInitConfig, gaussians_from_lidar

        g, _ = gaussians_from_lidar(bundle, replace(LidarInitConfig(), drop_unseen=False, init_opacity=0.9,
                                                     max_background_points=150_000))
    elif occluders == "oracle":
        from core.synth.prepare import synth_config_of
        from core.synth.oracle import OracleSettings, street_scene_graph

        cfg = synth_config_of(bundle)
        st = OracleSettings(max_spacing=ORACLE_MAX_SPACING_M, edge_refine=ORACLE_EDGE_REFINE, thin_slivers=True)
        graph, _, _ = street_scene_graph(cfg, (0,), settings=st, budget=int(oracle_gaussians))
        g = graph.compose(0.0)
    else:
        raise ConfigError(f"occluders: must be 'none', 'lidar' or 'oracle', got {occluders!r}")
    return numpy_visibility(GaussianTracer.from_gaussians(g.detach(), TraceSettings(leaf_size=16)))
