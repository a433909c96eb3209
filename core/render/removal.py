"""What a removed object leaves behind, cleared: remnants of it in the background, and the road
it hid in every frame.

A moving car's Gaussians are a node of the scene graph, but the volume stage explains part of
what the capture shows of it with background Gaussians: blobs of its paint on the road where its
silhouette blurred into the road, and on the road beyond it that no frame saw past the car. On
the default scene's quick reconstruction, removing the blue car5 left a cyan blob and blue
smears where it drove (a Gaussian of albedo 0.01 / 0.17 / 0.88 on the road at its last pose).

* :func:`object_remnants` - the background Gaussians in the strip a removed object drove along
  (its box's footprint extended ahead and behind, up to its roof) whose colour is not the
  ground's and is the object's own;
* :func:`ground_fill` - flat road Gaussians where the road was hidden in every frame, coloured
  like the road around it (else its pixels show sky after the removal);
* :func:`clear_removed` - both, as an object removal applies them
  (:func:`core.relight.apply_edits`).

Node frame: as :mod:`core.render.objects` (origin at the box's centre, x forward, y left, z up,
metres); poses are node to world 4x4.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch

from core.errors import ConfigError
from core.gaussians import Gaussians
from core.numerics import EPS_PDF

#: Ground fill under a removed object: grid step, how far the strip reaches past the box ahead
#: and behind (a camera behind a car never sees the road it hides, up to where a view ray over
#: its roof meets the ground), the strip's margin beside the box, metres.
GROUND_FILL_CELL_M = 0.25
GROUND_FILL_REACH_M = 30.0
GROUND_FILL_MARGIN_M = 0.3
#: ... and only where observed ground surrounds the cell within this distance (a hole in the road).
GROUND_FILL_MAX_GAP_M = 4.0
#: The fill's colour and materials skip observed ground this close (x-y, metres) to the object's
#: footprint at any of its poses: the road there carries the object's colour where its silhouette
#: blurred into the road behind it, and its contact shadow. On the default scene's quick
#: reconstruction the road beyond the blue car5 was filled blue-grey (median colour
#: 0.39 / 0.43 / 0.56 against the road's 0.41 / 0.43 / 0.48) from the road just behind it.
GROUND_FILL_BLEED_M = 1.0
#: ... and ground whose colour (in some channel) or chroma (max - min channel, of its colour or its
#: albedo) lies farther than this many robust deviations (1.4826 MAD, at least 0.01) from the
#: observed ground's median. On that reconstruction the road beyond car5, which no frame saw past
#: the car, held blue Gaussians (albedo 0.08 / 0.22 / 0.39) that the volume stage had left there
#: to explain the far car.
GROUND_FILL_OUTLIER_MAD = 3.0


def _box_and_poses(size: Sequence[float], poses) -> tuple[np.ndarray, np.ndarray]:
    """(``size`` as [3] float64, ``poses`` as [K, 4, 4] float64); ConfigError names a bad size."""
    sz = np.asarray([float(x) for x in size], np.float64)
    if sz.shape != (3,) or not np.isfinite(sz).all() or (sz <= 0).any():
        raise ConfigError(f"size: expected 3 finite lengths > 0, got {size!r}")
    P = np.asarray(poses.detach().cpu().numpy() if isinstance(poses, torch.Tensor) else poses, np.float64)
    return sz, P.reshape(-1, 4, 4)


def ground_fill(background, poses, size: Sequence[float], *, cell_m: float = GROUND_FILL_CELL_M,
                reach_m: float = GROUND_FILL_REACH_M, margin_m: float = GROUND_FILL_MARGIN_M,
                max_gap_m: float = GROUND_FILL_MAX_GAP_M, bleed_m: float = GROUND_FILL_BLEED_M, k: int = 16):
    """Flat road Gaussians for the ground a removed object hid in every frame.

    A car that drives ahead of the camera for the whole clip hides the road under it and, for
    tens of metres, the road beyond it: the reconstruction has no Gaussians there, so after a
    plain removal its pixels show sky. The strip considered is, at every keyframe pose
    ``[K, 4, 4]`` (node to world), the box's footprint (``size`` l, w, h; grown by
    ``margin_m`` at the sides) extended ``reach_m`` ahead and behind along the node's x axis, on
    the plane of the box's bottom (a tracked box stands on the road). Its cells (``cell_m``
    grid, world x-y) that no observed ground Gaussian of ``background`` covers (opacity > 0.3,
    within 0.3 m of that plane, its mean nearer than twice its largest scale, at least one cell)
    and that observed ground surrounds within ``max_gap_m`` (no angular gap of 150 deg or more in
    the directions to it: a hole in the road, not past its end) get one opaque disc Gaussian
    (opacity 0.95, 0.6 cell wide, 2 cm thick, normal up) with the per-channel median colour and
    materials of the ``k`` nearest observed ground Gaussians farther than ``bleed_m`` from the
    box's footprint at every pose and of a typical ground colour (:data:`GROUND_FILL_OUTLIER_MAD`;
    fewer than ``k`` such: far only, then typical only, then all): the surrounding road, where the
    road was observed nowhere, without the object's own colour. Where the background
    was observed it is left as it is. Empty when the background has no ground Gaussian near the
    strip."""
    from scipy.spatial import cKDTree

    for name, v, lo, hi in (("cell_m", cell_m, 0.02, 5.0), ("reach_m", reach_m, 0.0, 500.0),
                            ("margin_m", margin_m, 0.0, 10.0), ("max_gap_m", max_gap_m, 0.0, 100.0),
                            ("bleed_m", bleed_m, 0.0, 100.0)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and lo <= v <= hi):
            raise ConfigError(f"{name}: must be a finite number in [{lo}, {hi}], got {v!r}")
    sz, P = _box_and_poses(size, poses)
    g = background.detach()
    if g.num == 0 or len(P) == 0:
        return Gaussians.empty(g.dtype)
    xs = np.arange(-sz[0] / 2 - reach_m, sz[0] / 2 + reach_m + 1e-9, cell_m)
    ys = np.arange(-sz[1] / 2 - margin_m, sz[1] / 2 + margin_m + 1e-9, cell_m)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    local = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, -sz[2] / 2), np.ones(gx.size)], 1)
    pts = np.concatenate([(p @ local.T).T[:, :3] for p in P])
    key = np.floor(pts[:, :2] / cell_m).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    key, z = key[first], pts[first, 2]
    cells = np.concatenate([(key + 0.5) * cell_m, z[:, None]], 1)  # cell centres on the box-bottom plane

    means = g.means.to(torch.float64).numpy()
    opa = g.opacities().reshape(-1).numpy()
    cand = np.nonzero(opa > 0.3)[0]
    if len(cand) == 0:
        return Gaussians.empty(g.dtype)
    # ground Gaussians: near the plane of some strip cell (nearest cell in x-y)
    near_cell = cKDTree(cells[:, :2]).query(means[cand, :2], k=1, distance_upper_bound=5.0)
    has = np.isfinite(near_cell[0])
    cand = cand[has]
    cand = cand[np.abs(means[cand, 2] - cells[near_cell[1][has], 2]) < 0.3]
    if len(cand) == 0:
        return Gaussians.empty(g.dtype)
    gm = means[cand]
    rho = np.maximum(2.0 * g.scales().to(torch.float64).numpy()[cand, :2].max(1), cell_m)
    tree = cKDTree(gm[:, :2])
    kk = min(16, len(cand))
    d, nn = tree.query(cells[:, :2], k=kk)
    d, nn = d.reshape(len(cells), kk), nn.reshape(len(cells), kk)
    covered = ((d < rho[nn]) & (np.abs(gm[nn, 2] - cells[:, 2:3]) < 0.3)).any(1)
    holes = cells[~covered & (d[:, 0] <= max_gap_m)]
    if len(holes):
        # a hole is surrounded by observed ground: its directions to the observed ground within
        # max_gap_m (thinned to one point per half metre) leave no angular gap of 150 deg or more
        # (past the road's end, or at its very edge, they all lie on one side)
        _, first = np.unique(np.floor(gm[:, :2] / 0.5).astype(np.int64), axis=0, return_index=True)
        thin = gm[first, :2]
        kt = min(256, len(thin))
        dt, nt = cKDTree(thin).query(holes[:, :2], k=kt, distance_upper_bound=max_gap_m)
        dt, nt = dt.reshape(len(holes), kt), nt.reshape(len(holes), kt)
        ok = np.isfinite(dt)
        vec = thin[np.where(ok, nt, 0)] - holes[:, None, :2]
        ang = np.sort(np.where(ok, np.arctan2(vec[..., 1], vec[..., 0]), np.inf), axis=1)
        n_ok = ok.sum(1)
        last = np.take_along_axis(ang, np.maximum(n_ok - 1, 0)[:, None], 1)[:, 0]
        with np.errstate(invalid="ignore"):
            gaps = np.where(np.isfinite(ang[:, 1:]), np.diff(ang, axis=1), 0.0)
            wrap = np.where(n_ok > 0, 2 * np.pi - (last - ang[:, 0]), 2 * np.pi)
        widest = np.maximum(gaps.max(1, initial=0.0), wrap)
        holes = holes[(n_ok >= 3) & (widest < np.radians(150.0))]
    if len(holes) == 0:
        return Gaussians.empty(g.dtype)
    if int(k) != k or k < 1:
        raise ConfigError(f"k: need an integer >= 1, got {k!r}")
    # colour sources: observed ground away from the object's footprint at every pose
    far = np.ones(len(cand), bool)
    for p in P:
        loc = (gm - p[:3, 3]) @ p[:3, :3]
        out_x = np.maximum(np.abs(loc[:, 0]) - sz[0] / 2, 0.0)
        out_y = np.maximum(np.abs(loc[:, 1]) - sz[1] / 2, 0.0)
        far &= np.hypot(out_x, out_y) > bleed_m
    act = g.activated()
    # ... and typical of the ground: a colour within GROUND_FILL_OUTLIER_MAD robust deviations of
    # the ground's median in every channel (remnants of the object the volume stage left on the
    # road beyond it, saturated paint; also lane markings, which a fill should not smear)
    typical = _typical(act["colors"].detach().to(torch.float64).numpy()[cand],
                       act["albedo"].detach().to(torch.float64).numpy()[cand])
    pool = next((np.flatnonzero(sel) for sel in (far & typical, far, typical) if sel.sum() >= k),
                np.arange(len(cand)))
    kk = min(int(k), len(pool))
    _, src = cKDTree(gm[pool, :2]).query(holes[:, :2], k=kk)
    src = torch.as_tensor(cand[pool[np.asarray(src).reshape(len(holes), kk)]])

    def near(x):
        return x.detach()[src].median(dim=1).values

    n = len(holes)
    quats = torch.zeros(n, 4, dtype=g.dtype)
    quats[:, 0] = 1.0
    normals = torch.zeros(n, 3, dtype=g.dtype)
    normals[:, 2] = 1.0
    scales = torch.tensor([0.6 * cell_m, 0.6 * cell_m, 0.02], dtype=g.dtype).repeat(n, 1)
    return Gaussians.from_activated(torch.as_tensor(holes, dtype=g.dtype), quats, scales,
                                    torch.full((n, 1), 0.95, dtype=g.dtype), near(act["colors"]), normals,
                                    near(act["albedo"]), near(act["roughness"]), near(act["metallic"]))


def _chroma(x: np.ndarray) -> np.ndarray:
    return x.max(1) - x.min(1)


def _outlier_bound(x: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
    med = np.median(x, axis=0)
    return med, k * np.maximum(1.4826 * np.median(np.abs(x - med), axis=0), 0.01)


def _typical(colors: np.ndarray, albedo: np.ndarray, ref_colors: np.ndarray | None = None,
             ref_albedo: np.ndarray | None = None) -> np.ndarray:
    """[N] bool: colour ``[N, 3]`` and albedo ``[N, 3]`` of ground Gaussians typical of the ground
    (``ref_*``, default themselves): each colour channel, the colour's chroma and the albedo's
    chroma within :data:`GROUND_FILL_OUTLIER_MAD` robust deviations of the ground's median."""
    rc = colors if ref_colors is None else ref_colors
    ra = albedo if ref_albedo is None else ref_albedo
    k = GROUND_FILL_OUTLIER_MAD
    med, tol = _outlier_bound(rc, k)
    ok = (np.abs(colors - med) <= tol).all(1)
    for x, r in ((colors, rc), (albedo, ra)):
        med, tol = _outlier_bound(_chroma(r), k)
        ok &= _chroma(x) <= med + tol
    return ok


def _chromaticity(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(x.sum(1, keepdims=True), EPS_PDF)


def _strip(means: np.ndarray, poses: np.ndarray, size: np.ndarray, reach_m: float, margin_m: float,
           below_m: float, above_m: float) -> np.ndarray:
    """[N] bool: ``means`` inside the box's footprint extended ``reach_m`` ahead and behind and
    ``margin_m`` beside, from ``below_m`` under its bottom to ``above_m`` over its top, at some pose."""
    inside = np.zeros(len(means), bool)
    for p in poses:
        loc = (means - p[:3, 3]) @ p[:3, :3]
        inside |= ((np.abs(loc[:, 0]) <= size[0] / 2 + reach_m) & (np.abs(loc[:, 1]) <= size[1] / 2 + margin_m)
                   & (loc[:, 2] >= -size[2] / 2 - below_m) & (loc[:, 2] <= size[2] / 2 + above_m))
    return inside


#: An object whose Gaussians hold fewer than this many of a colour the ground does not have is
#: achromatic (grey, white, black paint): its remnants cannot be told from the road by colour, and
#: :func:`object_remnants` finds none.
REMNANT_MIN_COLOURED = 20


def object_remnants(background, object_gaussians, poses, size: Sequence[float], *,
                    reach_m: float = GROUND_FILL_REACH_M, margin_m: float = GROUND_FILL_MARGIN_M) -> torch.Tensor:
    """[N] bool over ``background``: its Gaussians the volume stage left to explain the object
    ``object_gaussians`` (node frame) that drove along ``poses`` ``[K, 4, 4]`` with box ``size``
    (l, w, h, metres). A remnant lies in the object's strip (the footprint extended ``reach_m``
    ahead and behind, ``margin_m`` beside, 0.3 m under its bottom to 0.3 m over its roof), has a
    colour the ground does not have (:func:`_typical` fails against the background's Gaussians
    near the strip's bottom plane), and its chromaticity lies nearer the object's coloured
    Gaussians' median chromaticity than the ground's. None for an achromatic object
    (:data:`REMNANT_MIN_COLOURED`)."""
    sz, P = _box_and_poses(size, poses)
    g = background.detach()
    none = torch.zeros(g.num, dtype=torch.bool)
    if g.num == 0 or len(P) == 0 or object_gaussians.num == 0:
        return none
    means = g.means.to(torch.float64).numpy()
    opa = g.opacities().reshape(-1).detach().numpy()
    col = g.colors().detach().to(torch.float64).numpy()
    alb = g.albedo().detach().to(torch.float64).numpy()
    # the ground: background Gaussians at the strip's bottom plane, wide around it
    ground = _strip(means, P, sz, reach_m + 10.0, margin_m + 10.0, 0.3, 0.3 - sz[2]) & (opa > 0.3)
    if ground.sum() < 50:
        return none
    gc, ga = col[ground], alb[ground]
    oc = object_gaussians.colors().detach().to(torch.float64).numpy()
    oa = object_gaussians.albedo().detach().to(torch.float64).numpy()
    coloured = ~_typical(oc, oa, gc, ga)
    if coloured.sum() < REMNANT_MIN_COLOURED:
        return none
    obj_chroma = np.median(_chromaticity(oc[coloured]), axis=0)
    ground_chroma = np.median(_chromaticity(gc), axis=0)
    cand = _strip(means, P, sz, reach_m, margin_m, 0.3, 0.3) & ~_typical(col, alb, gc, ga)
    ch = _chromaticity(col[cand])
    nearer = np.linalg.norm(ch - obj_chroma, axis=1) < np.linalg.norm(ch - ground_chroma, axis=1)
    out = np.zeros(g.num, bool)
    out[np.flatnonzero(cand)[nearer]] = True
    return torch.from_numpy(out)


def clear_removed(background, node):
    """``background`` (:class:`core.gaussians.Gaussians`) after the removal of ``node`` (a
    :class:`core.scene_graph.RigidNode`): without the node's remnants (:func:`object_remnants`),
    with the road it hid filled (:func:`ground_fill`); returns ``(background, remnants dropped,
    fill Gaussians added)``."""
    from core.render.objects import object_box

    size = object_box(node)
    rem = object_remnants(background, node.gaussians, node.poses, size)
    if bool(rem.any()):
        background = background.detach().index(torch.nonzero(~rem).reshape(-1))
    fill = ground_fill(background, node.poses, size)
    if fill.num:
        background = Gaussians.cat([background.detach(), fill.to(background.dtype)])
    return background, int(rem.sum()), int(fill.num)


__all__ = ["GROUND_FILL_CELL_M", "GROUND_FILL_REACH_M", "GROUND_FILL_MARGIN_M", "GROUND_FILL_MAX_GAP_M",
           "GROUND_FILL_BLEED_M", "GROUND_FILL_OUTLIER_MAD", "REMNANT_MIN_COLOURED", "ground_fill",
           "object_remnants", "clear_removed"]
