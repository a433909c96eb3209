"""Initialise Gaussians from a bundle's LiDAR sweeps (the paper's volume stage starts here).

Points inside a tracked object's box at their sweep time go to that object's node (in the object
frame, accumulated over sweeps); the rest form the background. Each point becomes one Gaussian:
isotropic scale from the mean distance to its nearest neighbours, normal from a local PCA oriented
toward the sensor, colour from the training frame of the same time index it projects into.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from core.bundle import SceneBundle
from core.camera import Camera
from core.errors import ConfigError
from core.gaussians import Gaussians


@dataclass(frozen=True)
class LidarInitConfig:
    """How LiDAR points become Gaussians."""

    max_background_points: int = 60_000
    """Background points kept after voxel downsampling (random subset beyond this)."""
    max_object_points: int = 4_000
    """Points kept per tracked object."""
    voxel_size_m: float = 0.08
    """Voxel grid for downsampling, metres (one point per occupied voxel)."""
    knn: int = 4
    """Neighbours for the scale (mean distance) and the PCA normal."""
    min_scale_m: float = 0.01
    """Smallest initial scale, metres."""
    max_scale_m: float = 0.5
    """Largest initial scale, metres."""
    init_opacity: float = 0.3
    """Initial opacity of every Gaussian."""
    init_roughness: float = 0.7
    """Initial roughness (alpha = roughness^2 in the BRDF)."""
    init_metallic: float = 0.05
    """Initial metallic."""
    box_margin_m: float = 0.1
    """Extra margin around object boxes when assigning points to objects, metres."""
    drop_unseen: bool = True
    """Drop background points that no training camera sees (LiDAR scans 360 degrees, cameras
    do not: those Gaussians would cost render time and never receive a gradient)."""
    seed: int = 0
    """Random seed of the subsampling."""


def _knn_stats(pts: np.ndarray, origins: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean neighbour distance [N] and PCA normals [N, 3] oriented toward the sensor."""
    from scipy.spatial import cKDTree

    n = len(pts)
    if n == 0:
        return np.zeros(0), np.zeros((0, 3))
    kk = min(k + 1, n)
    dist, idx = cKDTree(pts).query(pts, k=kk)
    dist = dist.reshape(n, kk)
    idx = idx.reshape(n, kk)
    mean_d = dist[:, 1:].mean(1) if kk > 1 else np.full(n, 0.1)
    nb = pts[idx]  # [N, k+1, 3]
    c = nb - nb.mean(1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", c, c)
    _, vecs = np.linalg.eigh(cov)
    normals = vecs[:, :, 0]  # smallest eigenvalue
    to_sensor = origins - pts
    flip = np.sum(normals * to_sensor, axis=1) < 0
    normals[flip] *= -1
    degenerate = ~np.isfinite(normals).all(1) | (kk < 3)
    if degenerate.any():
        v = to_sensor[degenerate]
        normals[degenerate] = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)
    return mean_d, normals


def _colors(bundle: SceneBundle, pts: np.ndarray, time_indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(RGB [N, 3] in [0, 1], seen [N] bool): colour from the training frame of each point's time
    index it projects into, else from any training frame; 0.5 grey for points no camera sees."""
    cols = np.full((len(pts), 3), 0.5)
    done = np.zeros(len(pts), bool)
    for f in bundle.frames("train"):
        sel = np.nonzero((time_indices == f.time_index) & ~done)[0]
        if len(sel) == 0:
            continue
        cam = Camera.from_bundle(bundle.camera(f), f)
        uv, z = cam.project(pts[sel])
        ok = (z > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        if not ok.any():
            continue
        img = bundle.load_image(f)
        u = uv[ok, 0].astype(int)
        v = uv[ok, 1].astype(int)
        cols[sel[ok]] = img[v, u]
        done[sel[ok]] = True
    # points not seen by a camera at their own time: try every train frame
    if not done.all():
        rest = np.nonzero(~done)[0]
        for f in bundle.frames("train"):
            if len(rest) == 0:
                break
            cam = Camera.from_bundle(bundle.camera(f), f)
            uv, z = cam.project(pts[rest])
            ok = (z > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
            if ok.any():
                img = bundle.load_image(f)
                cols[rest[ok]] = img[uv[ok, 1].astype(int), uv[ok, 0].astype(int)]
                done[rest[ok]] = True
                rest = rest[~ok]
    return cols, done


def _make(pts, origins, cols, cfg: LidarInitConfig, dtype, exposure: float = 1.0, gamma: float = 2.2) -> Gaussians:
    """Gaussians at the points; ``cols`` are the LDR colours seen by the cameras (the NVS colour),
    the albedo starts at their linearised value ``cols^gamma / exposure`` (albedo is linear
    reflectance: the gamma-encoded colour would be about twice too bright for the PBR pass)."""
    n = len(pts)
    if n == 0:
        return Gaussians.empty(dtype)
    mean_d, normals = _knn_stats(pts, origins, cfg.knn)
    s = np.clip(mean_d, cfg.min_scale_m, cfg.max_scale_m)
    t = lambda x: torch.as_tensor(np.asarray(x), dtype=dtype)  # noqa: E731
    # flat-ish disks: the axis along the normal gets a tenth of the scale
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(np.broadcast_to(z, normals.shape), normals)
    sin = np.linalg.norm(axis, axis=1)
    cos = normals @ z
    ang = np.arctan2(sin, cos)
    axis = np.where(sin[:, None] > 1e-9, axis / np.maximum(sin[:, None], 1e-9), np.array([1.0, 0.0, 0.0]))
    quats = np.concatenate([np.cos(ang / 2)[:, None], axis * np.sin(ang / 2)[:, None]], 1)
    scales = np.stack([s, s, s * 0.1], 1)
    return Gaussians.from_activated(
        means=t(pts), quats=t(quats), scales=t(scales),
        opacities=t(np.full(n, cfg.init_opacity)), colors=t(np.clip(cols, 0.02, 0.98)),
        normals=t(normals), albedo=t(np.clip(np.power(np.clip(cols, 0.0, 1.0), gamma) / exposure, 0.02, 0.98)),
        roughness=t(np.full(n, cfg.init_roughness)), metallic=t(np.full(n, cfg.init_metallic)),
    )


def gaussians_from_lidar(bundle: SceneBundle, cfg: LidarInitConfig = LidarInitConfig(),
                         dtype: torch.dtype = torch.float32, sweeps=None) -> tuple[Gaussians, dict[str, Gaussians]]:
    """(background Gaussians in world frame, {object id: Gaussians in the object frame}).

    ``sweeps``: optional list of ``(time_index, [N, 6] float array: origin xyz, hit xyz, world)``
    used instead of the bundle's LiDAR (e.g. points unprojected from a depth prior when the bundle
    has no LiDAR: :func:`sweeps_from_depth`)."""
    m = bundle.manifest
    tone = (float(m.ldr_exposure), float(m.ldr_gamma))
    if sweeps is None:
        if not m.lidar:
            raise ConfigError("bundle: has no LiDAR sweeps to initialise from")
        sweeps = [(s.time_index, None) for s in m.lidar]
    if not sweeps:
        raise ConfigError("sweeps: no points to initialise from")
    rng = np.random.default_rng(cfg.seed)
    bg_pts, bg_org, bg_t = [], [], []
    obj_pts: dict[str, list] = {o.id: [] for o in m.objects}
    obj_org: dict[str, list] = {o.id: [] for o in m.objects}
    obj_t: dict[str, list] = {o.id: [] for o in m.objects}
    for ti, arr in sweeps:
        arr = bundle.load_lidar(ti) if arr is None else arr
        arr = np.asarray(arr, np.float64)
        org, pts = arr[:, :3], arr[:, 3:]
        free = np.ones(len(pts), bool)
        for o in m.objects:
            pose = o.poses.get(ti)
            if pose is None:
                continue
            local = (pts - pose[:3, 3]) @ pose[:3, :3]
            inside = np.all(np.abs(local) <= np.asarray(o.size) / 2 + cfg.box_margin_m, axis=1)
            if inside.any():
                obj_pts[o.id].append(local[inside])
                obj_org[o.id].append((org[inside] - pose[:3, 3]) @ pose[:3, :3])
                obj_t[o.id].append(np.full(int(inside.sum()), ti))
                free &= ~inside
        bg_pts.append(pts[free])
        bg_org.append(org[free])
        bg_t.append(np.full(int(free.sum()), ti))
    pts, org = np.concatenate(bg_pts), np.concatenate(bg_org)
    tidx = np.concatenate(bg_t)
    keys = np.floor(pts / cfg.voxel_size_m).astype(np.int64)
    _, keep = np.unique(keys, axis=0, return_index=True)
    if cfg.drop_unseen:  # subsample among the points a camera sees
        keep = keep[_colors(bundle, pts[keep], tidx[keep])[1]]
    if len(keep) > cfg.max_background_points:
        keep = rng.choice(keep, cfg.max_background_points, replace=False)
    pts, org, tidx = pts[keep], org[keep], tidx[keep]
    cols, seen = _colors(bundle, pts, tidx)
    if cfg.drop_unseen:
        pts, org, cols = pts[seen], org[seen], cols[seen]
    background = _make(pts, org, cols, cfg, dtype, *tone)

    nodes: dict[str, Gaussians] = {}
    for o in m.objects:
        if not obj_pts[o.id]:
            continue
        lp = np.concatenate(obj_pts[o.id])
        lo = np.concatenate(obj_org[o.id])
        lt = np.concatenate(obj_t[o.id])
        keys = np.floor(lp / (cfg.voxel_size_m / 2)).astype(np.int64)
        _, keep = np.unique(keys, axis=0, return_index=True)
        if len(keep) > cfg.max_object_points:
            keep = rng.choice(keep, cfg.max_object_points, replace=False)
        lp, lo, lt = lp[keep], lo[keep], lt[keep]
        # colours: project the world positions at their sweep times
        world = np.empty_like(lp)
        for t in np.unique(lt):
            sel = lt == t
            pose = o.poses[int(t)]
            world[sel] = lp[sel] @ pose[:3, :3].T + pose[:3, 3]
        nodes[o.id] = _make(lp, lo, _colors(bundle, world, lt)[0], cfg, dtype, *tone)
    return background, nodes


def sweeps_from_depth(bundle: SceneBundle, depth_by_frame: dict[str, np.ndarray], stride: int = 2,
                      max_depth_m: float = 80.0) -> list[tuple[int, np.ndarray]]:
    """Pseudo-LiDAR sweeps ``[(time_index, [N, 6] origin + hit, world)]`` unprojected from
    per-frame camera z-depth maps ``[H, W(, 1)]`` (metres, 0 = no surface) of the training frames,
    every ``stride``-th pixel: the initialisation of a bundle without LiDAR."""
    out = []
    for f in bundle.frames("train"):
        d = depth_by_frame.get(f.id)
        if d is None:
            continue
        c = Camera.from_bundle(bundle.camera(f), f)
        d = np.asarray(d, np.float64).reshape(c.height, c.width)[::stride, ::stride]
        dirs = c.ray_directions()[::stride, ::stride]
        c2w = c.pose_numpy()
        fwd = c2w[:3, 2]
        ok = (d > 0.3) & (d < max_depth_m)
        cosf = np.clip(dirs[ok] @ fwd, 1e-3, None)
        hits = c2w[:3, 3] + dirs[ok] * (d[ok] / cosf)[:, None]
        org = np.broadcast_to(c2w[:3, 3], hits.shape)
        out.append((f.time_index, np.concatenate([org, hits], 1)))
    return out
