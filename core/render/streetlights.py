"""Street lights of a night scenario: placed from a spec, or detected in the reconstruction.

A street lamp is a spot light pointing straight down (world ``-z``) at the lamp head, with its
intensity in candela along the axis (the project's light unit, :mod:`core.pbr.lights`: the
irradiance at distance ``d`` on a surface facing the lamp is ``I / d^2`` in the units of the
environment map's radiance; with a map in cd/m^2 (nits) the unit is the candela).
:class:`StreetLightSettings` holds a realistic default: a 6 m post-top LED luminaire of about
6000 lm, ~2000 cd toward the road, a wide smooth cone (full intensity within 55 deg of the
nadir, none beyond 75 deg: street luminaires throw their light sideways along the road) and a
warm 3000 K colour.

Three sources:

* :func:`lamps_at` - explicit positions: ``[x, y]`` (the head is put ``mount_height_m`` above the
  ground found there) or ``[x, y, z]`` (the head itself);
* :func:`lamps_along_path` - a spacing along the road's sides: stations every ``spacing_m``
  along the capture's camera path (extended ahead of it, where the camera looks), a lamp at each
  lateral offset of ``side_offsets_m`` (left positive), staggered between the sides;
* :func:`detect_poles` - pole-like vertical clusters in 3D points (the capture's LiDAR hits, or
  the reconstruction's opaque background Gaussians): thin (a few decimetres across), tall (points
  from 1 m to beyond 3 m above the local ground) and free-standing (no points around them between
  the height of a car roof and the lamp: not a wall, not a tree). The lamp goes at the top of the
  pole, at the tip of its arm when one is seen.

Every function returns :class:`Lamp` values (world positions, metres); :func:`lamp_lights` turns
them into :class:`core.render.scenario.LightSpec` spots.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from core.errors import ConfigError, ShapeError
from core.numerics import require_finite_np
from core.render.scenario import LightSpec


@dataclass(frozen=True)
class StreetLightSettings:
    """A street lamp and how lamps are placed and detected."""

    intensity_cd: float = 2000.0
    """Luminous intensity toward the road, candela (a ~6000 lm LED street luminaire)."""
    color: tuple[float, float, float] = (1.0, 0.82, 0.62)
    """Linear RGB of a 3000 K lamp (max channel 1)."""
    mount_height_m: float = 6.0
    """Lamp head above the ground when a position gives no height."""
    cone_inner_deg: float = 55.0
    """Full intensity within this angle of the nadir, degrees."""
    cone_outer_deg: float = 75.0
    """No light beyond this angle of the nadir, degrees (smooth between)."""
    range_m: float = 40.0
    """Light range, metres (smooth window to 0; lets the PBR pass cull far pairs)."""
    spacing_m: float = 25.0
    """Distance between stations along the road (placement by spacing), metres."""
    side_offsets_m: tuple[float, ...] = (-4.0, 4.0)
    """Lateral offsets of the lamp rows from the camera path, metres (left of travel positive)."""
    ahead_m: float = 45.0
    """How far past the last camera the rows continue (the camera looks ahead), metres."""
    behind_m: float = 5.0
    """How far before the first camera the rows start, metres."""
    ground_radius_m: float = 4.0
    """Detection / placement: the ground under a point is a low percentile of the points within
    this horizontal radius, metres."""
    pole_link_m: float = 0.45
    """Detection: points closer than this (horizontally) belong to the same vertical cluster."""
    pole_max_width_m: float = 0.7
    """Detection: a pole's cluster is at most this wide, metres."""
    pole_min_top_m: float = 2.4
    """Detection: a pole's points reach at least this height above the ground, metres (a LiDAR
    mounted at 1.9 m with a narrow vertical field sees a pole close by only up to ~2.5 m)."""
    pole_min_points: int = 5
    """Detection: a cluster with fewer points is noise."""
    max_path_distance_m: float = 12.0
    """Detection: poles farther than this from the camera path (horizontally; the path extended
    100 m past both ends) are ignored: lamps stand by the road, and beyond the facades are walls
    seen edge-on."""
    pole_min_bins: int = 3
    """Detection: the cluster occupies at least this many 0.5 m height bins between 1 and 4.5 m."""
    isolation_band_m: tuple[float, float] = (1.8, 4.0)
    """Detection: heights (above ground) where a pole stands alone: above car roofs, below crowns."""
    isolation_radius_m: tuple[float, float] = (0.7, 2.0)
    """Detection: the ring around a pole that must be (nearly) empty in ``isolation_band_m``."""
    arm_max_m: float = 2.5
    """Detection: the lamp head is under the farthest point of the pole's top within this radius."""
    arm_m: float = 1.5
    """Detection: when the top of a pole was not seen, its lamp is put this far from the pole
    toward the camera path (over the road, as a pole's arm holds it), metres."""
    head_drop_m: float = 0.35
    """Detection: the lamp hangs this far under the top seen (clear of the arm's and pole's
    Gaussians, which would otherwise shadow it), metres."""

    def __post_init__(self) -> None:
        def num(name, v, lo, hi):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
                raise ConfigError(f"{name}: must be a finite number in [{lo}, {hi}], got {v!r}")

        num("intensity_cd", self.intensity_cd, 1e-6, 1e7)
        num("mount_height_m", self.mount_height_m, 0.5, 50.0)
        num("cone_inner_deg", self.cone_inner_deg, 0.0, 89.0)
        num("cone_outer_deg", self.cone_outer_deg, 0.5, 89.9)
        if self.cone_inner_deg > self.cone_outer_deg:
            raise ConfigError("cone_inner_deg: must not exceed cone_outer_deg")
        num("range_m", self.range_m, 0.5, 1e4)
        num("spacing_m", self.spacing_m, 1.0, 1e4)
        num("ahead_m", self.ahead_m, 0.0, 1e4)
        num("behind_m", self.behind_m, 0.0, 1e4)
        num("ground_radius_m", self.ground_radius_m, 0.1, 100.0)
        if len(self.color) != 3 or min(self.color) < 0 or max(self.color) <= 0:
            raise ConfigError(f"color: expected 3 numbers >= 0, not all 0, got {self.color!r}")
        if not self.side_offsets_m:
            raise ConfigError("side_offsets_m: at least one offset is needed")
        for v in self.side_offsets_m:
            num("side_offsets_m", v, -1e3, 1e3)


@dataclass(frozen=True)
class Lamp:
    """A street lamp: the head (world metres) and where it came from."""

    position: tuple[float, float, float]
    source: str
    """``spec``, ``spacing`` or ``detected``."""
    pole_base: tuple[float, float, float] | None = None
    """Detected lamps: the foot of the pole."""

    def as_dict(self) -> dict:
        d = {"position": [round(float(x), 3) for x in self.position], "source": self.source}
        if self.pole_base is not None:
            d["pole_base"] = [round(float(x), 3) for x in self.pole_base]
        return d


def _points3(points, what: str) -> np.ndarray:
    p = np.asarray(points, np.float64)
    if p.ndim != 2 or p.shape[1] not in (3, 6):
        raise ShapeError(f"{what}: expected [N, 3] points (or [N, 6] LiDAR origin + hit), got {p.shape}")
    p = p[:, 3:6] if p.shape[1] == 6 else p
    require_finite_np(p, what)
    return p


class Ground:
    """The local ground height under a horizontal position, from 3D points (a low percentile of
    the points within ``radius``); ``fallback`` where there are too few points."""

    def __init__(self, points: np.ndarray | None, radius: float, fallback: float, percentile: float = 2.0):
        from scipy.spatial import cKDTree

        self.points = None if points is None or len(points) == 0 else np.asarray(points, np.float64)
        self.tree = None if self.points is None else cKDTree(self.points[:, :2])
        self.radius, self.fallback, self.percentile = radius, float(fallback), percentile

    def at(self, xy) -> float:
        if self.tree is None:
            return self.fallback
        for r in (self.radius, 2 * self.radius, 4 * self.radius):
            idx = self.tree.query_ball_point(np.asarray(xy, np.float64)[:2], r)
            if len(idx) >= 20:
                return float(np.percentile(self.points[idx, 2], self.percentile))
        return self.fallback


def lamps_at(positions: Sequence[Sequence[float]], ground: Ground | None = None,
             settings: StreetLightSettings | None = None, what: str = "street_light_positions") -> list[Lamp]:
    """Lamps at explicit positions: ``[x, y]`` (head ``mount_height_m`` above the ground there;
    the ground is z = 0 without ``ground``) or ``[x, y, z]`` (the head)."""
    s = settings or StreetLightSettings()
    out = []
    for i, p in enumerate(positions):
        if not (isinstance(p, (list, tuple, np.ndarray)) and len(p) in (2, 3)
                and all(isinstance(x, (int, float, np.floating, np.integer)) and math.isfinite(x) for x in p)):
            raise ConfigError(f"{what}[{i}]: expected [x, y] or [x, y, z] finite metres, got {p!r}")
        if len(p) == 3:
            out.append(Lamp((float(p[0]), float(p[1]), float(p[2])), "spec"))
        else:
            gz = ground.at(p) if ground is not None else 0.0
            out.append(Lamp((float(p[0]), float(p[1]), gz + s.mount_height_m), "spec"))
    return out


def lamps_along_path(path_xyz: np.ndarray, ground: Ground | None = None,
                     settings: StreetLightSettings | None = None) -> list[Lamp]:
    """Lamps every ``spacing_m`` along the camera path ``path_xyz`` ``[T, 3]`` (in time order),
    at each of ``side_offsets_m`` (left of the direction of travel positive), staggered by half
    a spacing between rows, from ``behind_m`` before the first camera to ``ahead_m`` past the
    last. ``ground`` gives the ground height (default: 1.6 m under the cameras)."""
    s = settings or StreetLightSettings()
    p = np.asarray(path_xyz, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ShapeError(f"path_xyz: expected [T, 3] camera positions, got {p.shape}")
    require_finite_np(p, "path_xyz")
    # keep distinct stations (a static camera has one)
    keep = [0] + [i for i in range(1, len(p)) if np.linalg.norm(p[i, :2] - p[i - 1, :2]) > 1e-3]
    p = p[keep]
    if len(p) == 1:
        d = np.array([1.0, 0.0])  # a static camera: rows along its x (no direction of travel)
        seg = [(p[0, :2] - s.behind_m * d, d, s.behind_m + s.ahead_m)]
    else:
        dirs = np.diff(p[:, :2], axis=0)
        lens = np.linalg.norm(dirs, axis=1)
        dirs = dirs / lens[:, None]
        seg = [(p[0, :2] - s.behind_m * dirs[0], dirs[0], s.behind_m)]
        seg += [(p[i, :2], dirs[i], float(lens[i])) for i in range(len(dirs))]
        seg.append((p[-1, :2], dirs[-1], s.ahead_m))
    total = sum(L for _, _, L in seg)
    gz_default = float(np.median(p[:, 2])) - 1.6
    if ground is None:
        ground = Ground(None, s.ground_radius_m, gz_default)
    out = []
    for row, off in enumerate(s.side_offsets_m):
        a = (row % 2) * 0.5 * s.spacing_m
        while a <= total + 1e-9:
            acc = 0.0
            for o, d, L in seg:
                if a <= acc + L + 1e-9:
                    xy = o + d * (a - acc) + off * np.array([-d[1], d[0]])
                    break
                acc += L
            out.append(Lamp((float(xy[0]), float(xy[1]), ground.at(xy) + s.mount_height_m), "spacing"))
            a += s.spacing_m
    return out


def detect_poles(points, settings: StreetLightSettings | None = None, what: str = "points",
                 path_xyz: np.ndarray | None = None) -> list[Lamp]:
    """Street lamps on pole-like vertical clusters of ``points`` ([N, 3] world, or LiDAR [N, 6]
    whose hits are the last three columns); module docstring. With ``path_xyz`` (the camera
    positions [T, 3]) only poles within ``max_path_distance_m`` of it count. The lamp head is at
    the top seen, or ``mount_height_m`` above the ground when the points stop lower (the sensor
    did not see the top). Sorted by x then y."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    s = settings or StreetLightSettings()
    p = _points3(points, what)
    if len(p) < 10:
        return []
    ground = Ground(p, s.ground_radius_m, float(np.percentile(p[:, 2], 2)))
    path_xy = None
    if path_xyz is not None:
        path_xy = np.asarray(path_xyz, np.float64).reshape(-1, 3)[:, :2]
        require_finite_np(path_xy, "path_xyz")
        if len(path_xy) > 1 and np.linalg.norm(path_xy[-1] - path_xy[0]) > 1e-3:
            # the road goes on beyond the capture: extend the path along its end directions
            d0 = path_xy[1] - path_xy[0]
            d1 = path_xy[-1] - path_xy[-2]
            ext = 100.0
            path_xy = np.concatenate([path_xy[:1] - ext * d0 / max(np.linalg.norm(d0), 1e-9), path_xy,
                                      path_xy[-1:] + ext * d1 / max(np.linalg.norm(d1), 1e-9)])
    tree = cKDTree(p[:, :2])
    # coarse local ground per point (a 2 m grid, each cell's ground once)
    cells = np.floor(p[:, :2] / 2.0).astype(np.int64)
    keys, inv = np.unique(cells, axis=0, return_inverse=True)
    gz_cell = np.array([ground.at((k + 0.5) * 2.0) for k in keys])
    h = p[:, 2] - gz_cell[inv.ravel()]
    cand = np.nonzero((h > 1.0) & (h < 4.5))[0]
    if len(cand) == 0:
        return []
    ct = cKDTree(p[cand, :2])
    pairs = ct.query_pairs(s.pole_link_m, output_type="ndarray")
    n = len(cand)
    adj = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)) if len(pairs) else \
        coo_matrix((n, n))
    ncomp, label = connected_components(adj, directed=False)
    lo_b, hi_b = s.isolation_band_m
    r_in, r_out = s.isolation_radius_m
    out = []
    for c in range(ncomp):
        members = cand[label == c]
        if len(members) < s.pole_min_points:
            continue
        xy = p[members, :2]
        centre = np.median(xy, axis=0)
        if float(np.max(np.linalg.norm(xy - centre, axis=1))) * 2.0 > s.pole_max_width_m:
            continue
        bins = np.unique(np.floor(h[members] / 0.5))
        if len(bins) < s.pole_min_bins:
            continue
        if path_xy is not None and float(np.min(_seg_dist(path_xy, centre))) > s.max_path_distance_m:
            continue
        gz = ground.at(centre)
        column = tree.query_ball_point(centre, s.pole_link_m)
        top = float(np.max(p[column, 2])) - gz
        if top < s.pole_min_top_m:
            continue
        ring = np.asarray(tree.query_ball_point(centre, r_out), np.int64)
        dist = np.linalg.norm(p[ring, :2] - centre, axis=1)
        hr = p[ring, 2] - gz
        crowd = int(np.count_nonzero((dist > r_in) & (hr > lo_b) & (hr < hi_b)))
        if crowd > max(2, 0.25 * len(members)):
            continue
        # the head: the farthest point of the top (an arm over the road) within arm_max_m
        near = np.asarray(tree.query_ball_point(centre, s.arm_max_m), np.int64)
        top_z = gz + top
        head_z = gz + max(top - s.head_drop_m, s.mount_height_m - s.head_drop_m)
        head_pts = near[p[near, 2] > top_z - 0.6] if top >= s.mount_height_m - 0.5 else near[:0]
        far_xy = None
        if len(head_pts):
            far = head_pts[np.argmax(np.linalg.norm(p[head_pts, :2] - centre, axis=1))]
            if np.linalg.norm(p[far, :2] - centre) > 0.3:
                far_xy = p[far, :2]
        if far_xy is None and path_xy is not None:  # the arm was not seen: toward the road
            q = _closest_on_path(path_xy, centre)
            d = q - centre
            far_xy = centre + s.arm_m * d / max(float(np.linalg.norm(d)), 1e-9)
        if far_xy is None:
            far_xy = centre
        head = (float(far_xy[0]), float(far_xy[1]), float(head_z))
        out.append(Lamp(head, "detected", (float(centre[0]), float(centre[1]), float(gz))))
    # one lamp per pole: merge detections whose feet are closer than a metre
    merged: list[Lamp] = []
    for lamp in sorted(out, key=lambda x: (x.pole_base[0], x.pole_base[1])):
        if any(math.dist(lamp.pole_base[:2], m.pole_base[:2]) < 1.0 for m in merged):
            continue
        merged.append(lamp)
    return merged


def _closest_on_path(path_xy: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The point of the polyline ``path_xy`` closest to ``q``."""
    if len(path_xy) == 1:
        return path_xy[0]
    a, b = path_xy[:-1], path_xy[1:]
    ab = b - a
    t = np.clip(((q - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-12), 0.0, 1.0)
    c = a + t[:, None] * ab
    return c[int(np.argmin(np.linalg.norm(c - q, axis=1)))]


def _seg_dist(path_xy: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Horizontal distance of ``q`` to each segment of the polyline ``path_xy`` (to the point
    when the path is one point)."""
    if len(path_xy) == 1:
        return np.linalg.norm(path_xy - q, axis=1)
    a, b = path_xy[:-1], path_xy[1:]
    ab = b - a
    t = np.clip(((q - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(a + t[:, None] * ab - q, axis=1)


def lamp_lights(lamps: Sequence[Lamp], settings: StreetLightSettings | None = None,
                intensity_cd: float | None = None) -> list:
    """:class:`core.render.scenario.LightSpec` spots pointing down at each lamp head
    (``intensity_cd`` overrides the settings' intensity)."""
    s = settings or StreetLightSettings()
    cd = s.intensity_cd if intensity_cd is None else float(intensity_cd)
    if not (math.isfinite(cd) and cd > 0):
        raise ConfigError(f"intensity_cd: must be a finite number > 0 (candela), got {intensity_cd!r}")
    return [LightSpec("spot", tuple(l.position), cd, (0.0, 0.0, -1.0), tuple(s.color), s.cone_inner_deg,
                      s.cone_outer_deg, None, s.range_m) for l in lamps]


__all__ = ["StreetLightSettings", "Lamp", "Ground", "lamps_at", "lamps_along_path", "detect_poles", "lamp_lights"]
