"""The "oracle" Gaussian scene: thin flat Gaussians placed densely on the triangles of a synthetic
street (:mod:`core.synth.street`) with the ground-truth materials, so the PBR pass can be compared
with Mitsuba's render of the same mesh scene (agreement with an independent renderer, ``benchmarks/bench_pbr.py``).

Placement (world frame, metres)
    Every triangle is split at the midpoint of its longest edge until that edge is at most
    ``max_cells`` times the local spacing. The local spacing of a (sub-)triangle is
    ``clip(spacing_px * dist / fx, min_spacing, max_spacing)`` with ``dist`` the distance from
    its centroid to the nearest of ``camera_positions`` (so Gaussians are about ``spacing_px``
    pixels apart where the camera sees them, coarser far away: distant shadow casters need less
    detail). On each sub-triangle the lattice of cell centres ``v0 + ((i + 1/2) / n1) e1 +
    ((j + 1/2) / n2) e2`` inside the triangle (``n = ceil(|e| / spacing)``; half a cell inside
    the edges, so silhouettes grow by about one standard deviation, not a spacing) gets one
    Gaussian per point: in-plane standard deviation
    ``sigma_factor * spacing`` (isotropic), ``thickness`` along the face normal, opacity
    ``opacity``, normal = the outward face normal, albedo / roughness / metallic from the part's
    :class:`core.synth.street.Material` (a triangle smaller than half a lattice cell gets one
    Gaussian at its centroid; a ``"lambert"`` material gets roughness 1, metallic 0;
    render it with ``specular = 0``).

``budget``: when given, the pixel spacing and ``min_spacing`` are scaled by one factor (bisection on the predicted count) so
the scene has about that many Gaussians (used for the 50k-Gaussian speed benchmark).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch

from core.camera import Camera
from core.errors import ConfigError
from core.gaussians import Gaussians
from core.scene_graph import RigidNode, SceneGraph
from core.synth.generate import camera_pose, ego_positions, intrinsics
from core.synth.street import EGO_LANE_Y, Part, make_street


@dataclass(frozen=True)
class OracleSettings:
    """How densely and how thin the oracle Gaussians are. Lengths in metres."""

    spacing_px: float = 1.5
    """Target lattice spacing in pixels (of a camera with focal length ``fx``) at the distance of
    the nearest camera position."""
    min_spacing: float = 0.01
    """Smallest lattice spacing (metres)."""
    max_spacing: float = 0.5
    """Largest lattice spacing (metres), for surfaces far from every camera."""
    sigma_factor: float = 0.75
    """In-plane standard deviation as a multiple of the spacing (0.75: neighbours overlap enough
    that a surface composites to opacity > 0.99 between lattice points)."""
    thickness: float = 2e-3
    """Standard deviation along the face normal (metres)."""
    opacity: float = 0.99
    """Opacity of every Gaussian."""
    max_cells: int = 12
    """Sub-triangles are split until their longest edge is at most this many spacings."""
    edge_inset: float = 1.5
    """Gaussians closer than this many spacings to a boundary edge of their planar face (an edge
    not shared with another triangle of the same part and plane) are moved inward to this
    distance, so the composited silhouette (opacity 0.5) lies on the mesh edge instead of about
    two spacings outside it (0 disables)."""

    edge_refine: int = 1
    """> 1: a band ``3 x sigma_factor`` lattice spacings wide along every boundary edge of a planar
    face is filled with a lattice ``edge_refine`` times finer (rows parallel to the edge, the
    first ``edge_inset`` fine spacings inside it; the coarse lattice Gaussians in the band are
    dropped), so albedo, normal and silhouette edges are as sharp as the fine spacing while the
    face interior keeps the coarse one. 1 disables (the speed benchmarks; agreement uses 4)."""

    thin_slivers: bool = False
    """A triangle smaller than half a lattice cell (one Gaussian at its centroid) gets half its own
    extent along each of its axes instead of half its longest edge in both: a window's 6 cm deep
    side face then stays 6 cm deep instead of standing up to ~1.7 m out of the facade (at
    coarse spacing 4,600 of 50,000 Gaussians of a street narrow more than 2x). The lighting
    prior's occluders use True (the blurred slivers shadowed walls from a grazing sun); the PBR
    benchmarks and the forward model's training inputs were measured with False."""

    def __post_init__(self) -> None:
        for name in ("spacing_px", "min_spacing", "max_spacing", "sigma_factor", "thickness", "opacity"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ConfigError(f"{name}: must be a finite number > 0, got {v!r}")
        if self.opacity > 1:
            raise ConfigError(f"opacity: must be <= 1, got {self.opacity}")
        if self.min_spacing > self.max_spacing:
            raise ConfigError("min_spacing: exceeds max_spacing")
        if isinstance(self.edge_inset, bool) or not isinstance(self.edge_inset, (int, float)) \
                or not 0 <= self.edge_inset <= 10:
            raise ConfigError(f"edge_inset: must be a number in [0, 10], got {self.edge_inset!r}")
        if isinstance(self.edge_refine, bool) or not isinstance(self.edge_refine, int) or not 1 <= self.edge_refine <= 16:
            raise ConfigError(f"edge_refine: must be an int in [1, 16], got {self.edge_refine!r}")
        if isinstance(self.max_cells, bool) or not isinstance(self.max_cells, int) or not 1 <= self.max_cells <= 64:
            raise ConfigError(f"max_cells: must be an int in [1, 64], got {self.max_cells!r}")


def _tris_of_parts(parts):
    tris, mat = [], []
    for k, p in enumerate(parts):
        v = np.asarray(p.vertices, np.float64)
        f = np.asarray(p.faces, np.int64)
        tris.append(v[f])
        mat.append(np.full(len(f), k))
    return np.concatenate(tris, 0), np.concatenate(mat, 0)


def _cell_centres(a: int, b: int):
    """Barycentric (u, v) of the lattice cell centres ``((i + 1/2) / a, (j + 1/2) / b)`` inside
    the triangle (``u + v <= 1``), plus the mask of kept cells: Gaussians sit half a cell inside
    the edges, so silhouettes are not widened by a whole spacing."""
    i, j = np.meshgrid(np.arange(a), np.arange(b), indexing="ij")
    u = (i + 0.5) / a
    v = (j + 0.5) / b
    ok = (u + v) <= 1.0 + 1.0 / max(a, b)  # overlap the neighbour across the hypotenuse: no seam
    if not ok.any():
        ok = (i == 0) & (j == 0)
    return u[ok], v[ok], np.ones(int(ok.sum()), bool)


def _spacing(tris, cams, fx, s: OracleSettings, scale: float):
    c = tris.mean(1)
    d = np.full(len(c), np.inf)
    for p in cams:
        d = np.minimum(d, np.linalg.norm(c - p, axis=-1))
    lo = scale * s.min_spacing
    return np.clip(scale * s.spacing_px * d / fx, lo, max(s.max_spacing, lo))


def _subdivide(tris, mat, cams, fx, s: OracleSettings, scale: float):
    """Split triangles at the midpoint of their longest edge until short enough."""
    done_t, done_m = [], []
    for _ in range(64):
        if len(tris) == 0:
            break
        e = np.stack([tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 1], tris[:, 0] - tris[:, 2]], 1)
        el = np.linalg.norm(e, axis=-1)
        longest = el.argmax(1)
        sp = _spacing(tris, cams, fx, s, scale)
        split = el.max(1) > s.max_cells * sp
        done_t.append(tris[~split])
        done_m.append(mat[~split])
        t, m, k = tris[split], mat[split], longest[split]
        if len(t) == 0:
            tris = t
            break
        # rotate vertices so the longest edge is (a, b), then split it at its midpoint
        idx = np.stack([k, (k + 1) % 3, (k + 2) % 3], 1)
        t = np.take_along_axis(t, idx[:, :, None], 1)
        a, b, c = t[:, 0], t[:, 1], t[:, 2]
        mid = 0.5 * (a + b)
        tris = np.concatenate([np.stack([a, mid, c], 1), np.stack([mid, b, c], 1)], 0)
        mat = np.concatenate([m, m], 0)
    if len(tris):
        done_t.append(tris)
        done_m.append(mat)
    return np.concatenate(done_t, 0), np.concatenate(done_m, 0)


def _lattice_counts(tris, sp):
    """Lattice subdivisions (n1, n2) per triangle; (0, 0) = a single Gaussian at the centroid
    (triangles smaller than half a lattice cell)."""
    e1v = tris[:, 1] - tris[:, 0]
    e2v = tris[:, 2] - tris[:, 0]
    e1 = np.linalg.norm(e1v, axis=-1)
    e2 = np.linalg.norm(e2v, axis=-1)
    n1 = np.maximum(1, np.ceil(e1 / sp)).astype(np.int64)
    n2 = np.maximum(1, np.ceil(e2 / sp)).astype(np.int64)
    small = 0.5 * np.linalg.norm(np.cross(e1v, e2v), axis=-1) < 0.5 * sp * sp
    n1[small] = 0
    n2[small] = 0
    return n1, n2


def predicted_count(parts, camera_positions, fx: float, settings: OracleSettings | None = None,
                    scale: float = 1.0) -> int:
    """Number of Gaussians :func:`oracle_gaussians` would place (same subdivision)."""
    s = settings or OracleSettings()
    cams = np.asarray(camera_positions, np.float64).reshape(-1, 3)
    tris, mat = _tris_of_parts(parts)
    tris, mat = _subdivide(tris, mat, cams, fx, s, scale)
    n1, n2 = _lattice_counts(tris, _spacing(tris, cams, fx, s, scale))
    keys, counts = np.unique(n1 * 1000 + n2, return_counts=True)
    total = 0
    for k, c in zip(keys, counts):
        a, b = int(k // 1000), int(k % 1000)
        if a == 0:
            total += int(c)
            continue
        total += int(_cell_centres(a, b)[2].sum()) * int(c)
    return total


def budget_scale(parts, camera_positions, fx: float, budget: int, settings: OracleSettings | None = None) -> float:
    """The spacing scale at which :func:`oracle_gaussians` places about ``budget`` Gaussians."""
    s = settings or OracleSettings()
    cams = np.asarray(camera_positions, np.float64).reshape(-1, 3)
    if isinstance(budget, bool) or not isinstance(budget, int) or budget < 100:
        raise ConfigError(f"budget: must be an int >= 100, got {budget!r}")
    lo, hi = 0.05, 50.0
    for _ in range(30):
        mid = math.sqrt(lo * hi)
        if predicted_count(parts, cams, fx, s, mid) > budget:
            lo = mid
        else:
            hi = mid
        if hi / lo < 1.01:
            break
    return hi


def oracle_gaussians(parts, camera_positions, fx: float, settings: OracleSettings | None = None, *,
                     budget: int | None = None, scale: float | None = None,
                     dtype: torch.dtype = torch.float32) -> Gaussians:
    """Gaussians on the triangles of ``parts`` (:class:`core.synth.street.Part` list, world
    frame) as described in the module docstring. ``camera_positions``: ``[C, 3]`` world metres;
    ``fx``: focal length in pixels; ``budget`` (about that many Gaussians) or ``scale`` (of the
    spacing, see :func:`budget_scale`). Returns a :class:`core.gaussians.Gaussians`."""
    s = settings or OracleSettings()
    cams = np.asarray(camera_positions, np.float64).reshape(-1, 3)
    if not np.all(np.isfinite(cams)) or len(cams) == 0:
        raise ConfigError("camera_positions: expected [C, 3] finite positions, C >= 1")
    if not (isinstance(fx, (int, float)) and math.isfinite(fx) and fx > 0):
        raise ConfigError(f"fx: must be > 0, got {fx!r}")
    if scale is None:
        scale = 1.0 if budget is None else budget_scale(parts, cams, fx, budget, s)
    tris0, mat0 = _tris_of_parts(parts)
    tris, mat = _subdivide(tris0, mat0, cams, fx, s, scale)
    sp = _spacing(tris, cams, fx, s, scale)
    n1, n2 = _lattice_counts(tris, sp)
    pts, tri_of = [], []
    # group triangles by their lattice size so each group is one vectorised grid
    key = n1 * 1000 + n2
    for k in np.unique(key):
        sel = np.nonzero(key == k)[0]
        a, b = int(k // 1000), int(k % 1000)
        if a == 0:  # small triangle: one Gaussian at the centroid
            ok = np.ones(1, bool)
            u = np.full((1, 1, 1), 1.0 / 3.0)
            v = u
        else:
            u, v, ok = _cell_centres(a, b)
            u, v = u[None, :, None], v[None, :, None]
        t = tris[sel]
        p = t[:, None, 0] + u * (t[:, None, 1] - t[:, None, 0]) + v * (t[:, None, 2] - t[:, None, 0])
        pts.append(p.reshape(-1, 3))
        tri_of.append(np.repeat(sel, ok.sum()))
    pts = np.concatenate(pts, 0)
    tri_of = np.concatenate(tri_of, 0)
    e1 = tris[:, 1] - tris[:, 0]
    e2 = tris[:, 2] - tris[:, 0]
    nrm = np.cross(e1, e2)
    nl = np.linalg.norm(nrm, axis=-1, keepdims=True)
    good = nl[:, 0] > 1e-12
    nrm = nrm / np.where(nl > 0, nl, 1.0)
    t1 = e1 / np.maximum(np.linalg.norm(e1, axis=-1, keepdims=True), 1e-12)
    t2 = np.cross(nrm, t1)
    keep = good[tri_of]
    pts, tri_of = pts[keep], tri_of[keep]
    if s.edge_inset > 0:
        pts = _inset_boundaries(pts, tri_of, tris, mat, nrm, sp, n1, tris0, mat0, s.edge_inset)
    fine_w = np.zeros(len(pts))  # > 0: a band Gaussian with this isotropic lattice spacing
    if s.edge_refine > 1:
        keep, bpts, btri, bw = _edge_band(pts, tri_of, tris, mat, nrm, sp, n1, tris0, mat0, s, cams, fx, scale)
        pts = np.concatenate([pts[keep], bpts], 0)
        tri_of = np.concatenate([tri_of[keep], btri], 0)
        fine_w = np.concatenate([fine_w[keep], bw], 0)
    rot = np.stack([t1, t2, nrm], -1)[tri_of]  # columns = local axes
    quats = _rotmat_to_quat(rot)
    l1 = np.linalg.norm(e1, axis=-1)
    h2 = nl[:, 0] / np.maximum(l1, 1e-12)  # height of the triangle across e1
    # anisotropic: never wider than the lattice step across a thin triangle (poles, wheels); a
    # single-Gaussian triangle isotropic at half its longest edge, or (thin_slivers) at half its
    # own extent along each axis
    if s.thin_slivers:
        one1, one2 = np.minimum(sp, 0.5 * l1), np.minimum(sp, np.maximum(0.5 * h2, 1e-4))
    else:
        one1 = one2 = np.minimum(sp, 0.5 * np.maximum(l1, np.linalg.norm(e2, axis=-1)))
    s1 = np.where(n1 == 0, one1, np.minimum(sp, l1 / np.maximum(n1, 1)))
    s2 = np.where(n1 == 0, one2, np.minimum(sp, np.maximum(h2 / np.maximum(n2, 1), 1e-4)))
    band = fine_w > 0
    s1p = np.where(band, fine_w, s1[tri_of])
    s2p = np.where(band, fine_w, s2[tri_of])
    scales = np.stack([s.sigma_factor * s1p, s.sigma_factor * s2p, np.full(len(tri_of), s.thickness)], -1)
    mats = [p.material for p in parts]
    alb = np.array([m.albedo for m in mats], np.float64)
    rough = np.array([1.0 if m.model == "lambert" else m.roughness for m in mats], np.float64)
    metal = np.array([0.0 if m.model == "lambert" else m.metallic for m in mats], np.float64)
    mid = mat[tri_of]
    n = len(pts)

    def T(x):
        return torch.as_tensor(np.ascontiguousarray(x), dtype=dtype)

    return Gaussians.from_activated(
        T(pts), T(quats), T(scales), T(np.full(n, s.opacity)), T(alb[mid]), T(nrm[tri_of]), T(alb[mid]),
        T(rough[mid]), T(metal[mid]))


def _plane_keys(tris, mat):
    e1 = tris[:, 1] - tris[:, 0]
    e2 = tris[:, 2] - tris[:, 0]
    n = np.cross(e1, e2)
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-30)
    off = (n * tris[:, 0]).sum(-1)
    q = np.round(np.concatenate([n * 1e3, off[:, None] * 1e3], 1)).astype(np.int64)
    return [(int(m),) + tuple(row) for m, row in zip(mat, q)]


def _boundary_edges(tris0, mat0):
    """Per planar group (key of :func:`_plane_keys`): its boundary edges ``(a, b, third)`` (edges
    used by one triangle of the group; ``third``: that triangle's third vertex), and the largest
    inradius of its triangles."""
    keys0 = _plane_keys(tris0, mat0)
    groups: dict = {}
    for i, k in enumerate(keys0):
        groups.setdefault(k, []).append(i)
    bound: dict = {}
    for k, idx in groups.items():
        count: dict = {}
        for i in idx:
            for a, b, c in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
                pa, pb = tuple(np.round(tris0[i, a] * 1e5).astype(np.int64)), tuple(np.round(tris0[i, b] * 1e5).astype(np.int64))
                e = (pa, pb) if pa < pb else (pb, pa)
                n_, _third = count.get(e, (0, None))
                count[e] = (n_ + 1, tris0[i, c])
        bound[k] = [(np.array(e[0], np.float64) / 1e5, np.array(e[1], np.float64) / 1e5, third)
                    for e, (c, third) in count.items() if c == 1]
    e1 = tris0[:, 1] - tris0[:, 0]
    e2 = tris0[:, 2] - tris0[:, 0]
    e3 = tris0[:, 2] - tris0[:, 1]
    area2 = np.linalg.norm(np.cross(e1, e2), axis=-1)
    perim = np.linalg.norm(e1, axis=-1) + np.linalg.norm(e2, axis=-1) + np.linalg.norm(e3, axis=-1)
    inr = area2 / np.maximum(perim, 1e-12)
    group_inr = {k: float(max(inr[i] for i in idx)) for k, idx in groups.items()}
    return bound, group_inr


def _edge_frames(edges, nn):
    """(a, unit direction, length, unit inward normal in the plane) of each boundary edge."""
    out = []
    for a, b, third in edges:
        e = b - a
        L = float(np.linalg.norm(e))
        if L < 1e-9:
            continue
        e = e / L
        inward = np.cross(nn, e)
        if np.dot(third - a, inward) < 0:  # the side of the triangle that owns the edge
            inward = -inward
        out.append((a, e, L, inward))
    return out


def _edge_band(pts, tri_of, tris, mat, nrm, sp, n1, tris0, mat0, s: OracleSettings, cams, fx, scale):
    """The fine band of :attr:`OracleSettings.edge_refine`: returns (mask of the coarse points kept,
    band points ``[B, 3]``, their representative sub-triangle ``[B]``, their fine spacing ``[B]``).

    For every boundary edge of a planar group, band rows run parallel to the edge at inward
    distances ``(edge_inset + r) w`` up to the band width ``3 sigma_factor s`` (``s``: the coarse
    spacing at the edge's midpoint, ``w = s / edge_refine``), points ``w`` apart along it. A band
    point is kept unless another boundary edge whose span it projects into is nearer (thin faces,
    corners: each point belongs to its nearest edge). Coarse points that project into an edge's
    span closer than the band width are dropped (points in the wedge of a reflex corner stay)."""
    bound, group_inr = _boundary_edges(tris0, mat0)
    keys = _plane_keys(tris, mat)
    k_ref = int(s.edge_refine)
    band_cells = 3.0 * s.sigma_factor
    keep = np.ones(len(pts), bool)
    lattice = n1[tri_of] > 0
    by_key: dict = {}
    for j, t in enumerate(tri_of):
        by_key.setdefault(keys[t], []).append(j)
    rep: dict = {}
    for t, k in enumerate(keys):
        rep.setdefault(k, t)
    bp, bt, bw = [], [], []
    for k, edges in bound.items():
        t_rep = rep.get(k)
        if t_rep is None or not edges:
            continue
        nn = nrm[t_rep]
        fr = _edge_frames(edges, nn)
        if not fr:
            continue
        lo = scale * s.min_spacing

        def local_spacing(x):
            d_cam = np.min(np.linalg.norm(x[:, None, :] - cams[None, :, :], axis=-1), axis=1)
            return np.clip(scale * s.spacing_px * d_cam / fx, lo, max(s.max_spacing, lo))

        mids = np.stack([a + 0.5 * L * e for a, e, L, _ in fr])
        s_edge = local_spacing(mids)
        if group_inr.get(k, 0.0) < 0.5 * float(s_edge.min()):
            continue  # narrower than the coarse spacing (poles, wheel treads): left as is
        # band width per edge: the largest local spacing along it (the coarse points dropped
        # near it are those of its widest part)
        cand, cand_w, cand_e, cand_d = [], [], [], []
        edge_pieces: list = []
        for ei, (a, e, L, inward) in enumerate(fr):
            # pieces of the edge short enough that the spacing is about constant on each
            pieces = [(0.0, L)]
            out_pieces = []
            for _ in range(40):
                if not pieces:
                    break
                st = np.array([p_[0] for p_ in pieces])
                en = np.array([p_[1] for p_ in pieces])
                sp_mid = local_spacing(a + (0.5 * (st + en))[:, None] * e)
                long_ = (en - st) > s.max_cells * sp_mid
                out_pieces += [(float(x0), float(x1), float(q)) for x0, x1, q in zip(st[~long_], en[~long_], sp_mid[~long_])]
                pieces = [(float(x0), float(0.5 * (x0 + x1))) for x0, x1 in zip(st[long_], en[long_])] + \
                         [(float(0.5 * (x0 + x1)), float(x1)) for x0, x1 in zip(st[long_], en[long_])]
            out_pieces += [(x0, x1, float(local_spacing((a + 0.5 * (x0 + x1) * e)[None])[0])) for x0, x1 in pieces]
            s_edge[ei] = max(q for _, _, q in out_pieces)
            edge_pieces.append(out_pieces)
            for x0, x1, se in out_pieces:
                w = se / k_ref
                width = band_cells * se
                rows = np.arange(s.edge_inset, width / w + 1.0, 1.0) * w
                n_al = max(1, int(math.ceil((x1 - x0) / w)))
                al = x0 + (np.arange(n_al) + 0.5) * ((x1 - x0) / n_al)
                A, D = np.meshgrid(al, rows, indexing="ij")
                p = a + A.reshape(-1, 1) * e + D.reshape(-1, 1) * inward
                cand.append(p)
                cand_w.append(np.full(len(p), w))
                cand_e.append(np.full(len(p), ei))
                cand_d.append(D.reshape(-1))
        p = np.concatenate(cand)
        pw = np.concatenate(cand_w)
        pe = np.concatenate(cand_e)
        pd = np.concatenate(cand_d)
        ok = np.ones(len(p), bool)
        for ei, (a, e, L, inward) in enumerate(fr):
            rel = p - a
            along = rel @ e
            d = rel @ inward
            other = pe != ei
            in_span = (along >= 0) & (along <= L)
            # nearer to this edge (inside the face) or on its outer side: not this point's edge's
            ok &= ~(other & in_span & (d < pd - 1e-9) & (d > -band_cells * s_edge[ei]))
        bp.append(p[ok])
        bw.append(pw[ok])
        bt.append(np.full(int(ok.sum()), t_rep))
        # coarse points of this group inside some edge's band span
        idx = np.asarray(by_key.get(k, []), np.int64)
        if len(idx):
            q = pts[idx]
            drop = np.zeros(len(idx), bool)
            for ei, (a, e, L, inward) in enumerate(fr):
                rel = q - a
                along = rel @ e
                d = rel @ inward
                for x0, x1, se in edge_pieces[ei]:
                    drop |= (along >= x0) & (along <= x1) & (d > -1e-9) & (d < band_cells * se)
            keep[idx[drop & lattice[idx]]] = False
    if bp:
        return keep, np.concatenate(bp), np.concatenate(bt).astype(np.int64), np.concatenate(bw)
    return keep, np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0)


def _inset_boundaries(pts, tri_of, tris, mat, nrm, sp, n1, tris0, mat0, inset):
    """Move lattice points within ``inset * spacing`` of a boundary edge of their planar face to
    that distance (see :attr:`OracleSettings.edge_inset`)."""
    bound, group_inr = _boundary_edges(tris0, mat0)
    keys = _plane_keys(tris, mat)
    out = pts.copy()
    lattice = n1[tri_of] > 0
    by_key: dict = {}
    for j, t in enumerate(tri_of):
        if lattice[j]:
            by_key.setdefault(keys[t], []).append(j)
    for k, idx in by_key.items():
        edges = bound.get(k)
        if not edges:
            continue
        idx = np.asarray(idx)
        p = out[idx]
        delta = inset * sp[tri_of[idx]]
        if group_inr.get(k, 0.0) < 2.0 * float(delta.max()):
            continue  # narrow faces (poles, wheels) are left alone
        for a, e, L, inward in _edge_frames(edges, nrm[tri_of[idx[0]]]):
            rel = p - a
            along = rel @ e
            d = rel @ inward
            near = (d > -0.25 * delta) & (d < delta) & (along > -delta) & (along < L + delta)
            p[near] += inward * (delta[near] - d[near])[:, None]
        out[idx] = p
    return out


def _rotmat_to_quat(r: np.ndarray) -> np.ndarray:
    """wxyz quaternions of rotation matrices ``[N, 3, 3]`` (Shepperd's method)."""
    m = r
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    q = np.zeros((len(m), 4))
    c0 = tr > 0
    s = np.sqrt(np.maximum(tr + 1.0, 1e-12)) * 2
    q[c0] = np.stack([0.25 * s, (m[:, 2, 1] - m[:, 1, 2]) / s, (m[:, 0, 2] - m[:, 2, 0]) / s,
                      (m[:, 1, 0] - m[:, 0, 1]) / s], -1)[c0]
    for axis in range(3):
        i, j, k = axis, (axis + 1) % 3, (axis + 2) % 3
        c = (~c0) & (m[:, i, i] >= m[:, j, j]) & (m[:, i, i] >= m[:, k, k])
        if axis > 0:
            c &= ~done
        s = np.sqrt(np.maximum(1.0 + m[:, i, i] - m[:, j, j] - m[:, k, k], 1e-12)) * 2
        qq = np.zeros((len(m), 4))
        qq[:, 0] = (m[:, k, j] - m[:, j, k]) / s
        qq[:, 1 + i] = 0.25 * s
        qq[:, 1 + j] = (m[:, j, i] + m[:, i, j]) / s
        qq[:, 1 + k] = (m[:, k, i] + m[:, i, k]) / s
        q[c] = qq[c]
        done = c if axis == 0 else (done | c)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def street_oracle(cfg, frames=(0,), *, settings: OracleSettings | None = None, budget: int | None = None,
                  lambert: bool = False, time_index: int = 0, dtype: torch.dtype = torch.float32):
    """The oracle scene of a synthetic street: ``(gaussians, cameras, parts)``.

    ``cfg``: a :class:`core.synth.config.SynthConfig`; ``frames``: time indices of the train
    trajectory whose cameras are returned (and used for the spacing); ``lambert``: replace every
    material by a pure Lambertian of the same albedo (validation of geometry, visibility and
    lighting against Mitsuba's ``diffuse`` BSDF, rendered with ``specular = 0``). ``cameras``
    are :class:`core.camera.Camera`. Parts are taken at ``time_index``.
    """
    ego = ego_positions(cfg)
    street = make_street(cfg, ego)
    parts = street.parts_at(time_index)
    if lambert:
        parts = [replace(p, material=replace(p.material, model="lambert")) for p in parts]
    ci = intrinsics(cfg)
    cams = [Camera.from_intrinsics(camera_pose(cfg, float(ego[t]), EGO_LANE_Y), ci.fx, ci.fy, ci.cx, ci.cy, cfg.width,
                                   cfg.height) for t in frames]
    pos = np.stack([c.pose_numpy()[:3, 3] for c in cams])
    g = oracle_gaussians(parts, pos, ci.fx, settings, budget=budget, dtype=dtype)
    return g, cams, parts


def street_scene_graph(cfg, frames=(0,), *, settings: OracleSettings | None = None, budget: int | None = None):
    """The oracle street as a :class:`core.scene_graph.SceneGraph`: the static parts and parked
    cars in the background, every moving car a rigid node (its Gaussians in the car frame, its
    poses from the street's track), times ``t * cfg.frame_dt``. Returns ``(graph, cameras,
    street)``; ``graph.compose(t * cfg.frame_dt)`` holds the Gaussians of ``street.parts_at(t)``.
    ``budget`` spreads about that many Gaussians over the whole street at time 0."""
    s = settings or OracleSettings()
    ego = ego_positions(cfg)
    street = make_street(cfg, ego)
    ci = intrinsics(cfg)
    cams = [Camera.from_intrinsics(camera_pose(cfg, float(ego[t]), EGO_LANE_Y), ci.fx, ci.fy, ci.cx, ci.cy, cfg.width,
                                   cfg.height) for t in frames]
    pos = np.stack([c.pose_numpy()[:3, 3] for c in cams])
    scale = 1.0 if budget is None else budget_scale(street.parts_at(0), pos, ci.fx, budget, s)
    static_parts = list(street.static_parts)
    movers = []
    for car in street.cars:
        if car.moving:
            movers.append(car)
        else:
            pose = car.poses[0]
            for p in car.parts:
                v = (np.asarray(p.vertices, np.float64) @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32)
                static_parts.append(Part(f"{car.id}/{p.name}", v, p.faces, p.material))
    background = oracle_gaussians(static_parts, pos, ci.fx, s, scale=scale)
    nodes = []
    T = cfg.num_frames
    for car in movers:
        pose0 = car.poses[0]
        local_cams = (pos - pose0[:3, 3]) @ pose0[:3, :3]  # camera positions in the car frame at t = 0
        g = oracle_gaussians(car.parts, local_cams, ci.fx, s, scale=scale)
        poses = torch.tensor(np.stack([car.poses[t] for t in range(T)]), dtype=torch.float64)
        nodes.append(RigidNode(car.id, "car", g, torch.arange(T), poses))
    graph = SceneGraph(background, nodes, torch.arange(T, dtype=torch.float64) * cfg.frame_dt)
    return graph, cams, street
