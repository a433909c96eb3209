"""The objects of a scene for simulator clients: what they are, their lights, their Gaussians as
assets, their trajectories.

* :func:`describe_objects` - each tracked object of a bundle (and of a reconstruction): id,
  class, box size, parked or moving, pose per frame (the service's ``GET /scenes/{id}/objects``
  and ``brdf info``);
* :func:`object_box` / :func:`crop_to_box` - a node's box (the tracked size, else a robust
  estimate from its Gaussians) and its Gaussians cropped to it, so no floater travels with an
  inserted or moved car;
* :func:`solid_filler` (from :mod:`core.object_solids`) - opaque Gaussians filling a node's
  inside, so that it casts a solid shadow, not the faint one of its shell;
* :func:`vehicle_lights` - two headlights (spots forward) and two tail lights (red points back)
  on every vehicle node, in the node frame (they follow its pose), switchable per object;
* :func:`export_asset` / :func:`load_asset` - a node as a file (Gaussians with their materials,
  box, class) to insert into another scene;
* :func:`retime_poses` - trajectory edits: speed, lateral offset.

Node frame (the bundles' convention): origin at the centre of the box, x forward, y left, z up,
metres.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from core.errors import ConfigError, FormatError
from core.gaussians import Gaussians
from core.io.atomic import atomic_output
from core.io.torchfile import read_torch_file
from core.object_solids import solid_filler
from core.pbr.lights import PointLight, SpotLight
from core.rotations import quat_slerp, quat_to_rotmat, rotmat_to_quat

#: Classes whose nodes carry vehicle lights (lower case; drivestudio's Waymo classes included).
VEHICLE_CLASSES = frozenset({"car", "vehicle", "truck", "bus", "van", "suv", "pickup", "motorcycle", "trailer",
                             "construction_vehicle", "emergency_vehicle"})
#: A node counts as moving when its box centre travels more than this over the clip, metres.
MOVING_MIN_M = 0.05
#: Headlight: candela of the on-axis beam (the REST default), cone half-angles, aim (slightly down).
HEADLIGHT_CONE_DEG = (12.0, 30.0)
HEADLIGHT_DIRECTION = (1.0, 0.0, -0.08)
HEADLIGHT_COLOR = (1.0, 0.95, 0.85)
#: Vehicle lamps sit this far out from the box's front / rear face, metres (clear of the body's
#: Gaussians, whose shadow rays would otherwise hide the lamp).
LAMP_CLEARANCE_M = 0.2
#: Tail light: a red point light just behind the rear face (candela; a lit tail lamp is 4-20 cd).
TAIL_LIGHT_CD = 10.0
TAIL_LIGHT_COLOR = (1.0, 0.03, 0.02)
ASSET_FORMAT = "brdfusion.object_asset"
ASSET_VERSION = 1


def is_vehicle(cls: str) -> bool:
    return str(cls).strip().lower().replace(" ", "_") in VEHICLE_CLASSES


def describe_objects(manifest, nodes: Sequence[str] | None = None) -> list[dict]:
    """One dict per tracked object of the bundle ``manifest``: ``id``, ``class``, ``size``
    ``[l, w, h]`` metres, ``moving`` (its box centre travels more than :data:`MOVING_MIN_M`),
    ``vehicle`` (it carries vehicle lights), ``time_indices``, ``poses``
    ``[{time_index, time_s, obj_to_world}]`` (4x4 row-major) and, with ``nodes`` (the node names
    of a reconstruction), ``reconstructed``: whether the reconstruction has Gaussians for it."""
    times = list(manifest.times)
    out = []
    for o in manifest.objects:
        ti = sorted(o.poses)
        centres = np.array([np.asarray(o.poses[t])[:3, 3] for t in ti], np.float64)
        travel = float(np.linalg.norm(centres[1:] - centres[:-1], axis=1).sum()) if len(ti) > 1 else 0.0
        d = {"id": o.id, "class": o.cls, "size": [float(x) for x in o.size], "moving": travel > MOVING_MIN_M,
             "vehicle": is_vehicle(o.cls), "path_length_m": round(travel, 3), "time_indices": ti,
             "poses": [{"time_index": int(t), "time_s": float(times[t]) if t < len(times) else None,
                        "obj_to_world": [[float(x) for x in row] for row in np.asarray(o.poses[t])]} for t in ti]}
        if nodes is not None:
            d["reconstructed"] = o.id in set(nodes)
        out.append(d)
    return out


def attach_sizes(graph, manifest):
    """Give every node of ``graph`` without a box the tracked size of the same id in the bundle
    ``manifest`` (reconstructions saved before node sizes were stored). In place; returns graph."""
    sizes = {o.id: tuple(float(x) for x in o.size) for o in manifest.objects}
    for n in graph.nodes:
        if n.size is None and n.name in sizes:
            n.size = sizes[n.name]
    return graph


def object_box(node) -> tuple[float, float, float]:
    """The node's box ``(l, w, h)`` metres: the tracked size when known, else twice the largest
    |coordinate| of the central 96% of its (opacity > 0.1) Gaussian means along each axis."""
    if getattr(node, "size", None) is not None:
        return tuple(node.size)
    g = node.gaussians
    m = g.means.detach().to(torch.float64)
    keep = g.opacities().detach().reshape(-1) > 0.1
    if int(keep.sum()) >= 8:
        m = m[keep]
    if m.shape[0] == 0:
        raise ConfigError(f"node {node.name!r}: no Gaussians, no box")
    lo = torch.quantile(m, 0.02, dim=0)
    hi = torch.quantile(m, 0.98, dim=0)
    half = torch.maximum(lo.abs(), hi.abs()).clamp_min(0.05)
    return tuple(float(2 * x) for x in half)


#: A tracked object's node also learns the road it stands on: flat, upward-facing Gaussians at
#: its box's bottom face, with its contact shadow in their colour and albedo. Gaussians of the
#: node below this height over the bottom face that face up (normal z above
#: CROP_GROUND_NORMAL_Z), and all below the bottom face, stay behind when the object is cropped.
#: On the default scene's quick reconstruction car1 had 313 such Gaussians (of 3272; colour 0.22
#: against the road's 0.3-0.45): inserted elsewhere they drew a dark strip beside the car that
#: the insertion benchmark counted as shadow where Mitsuba had none.
CROP_GROUND_M = 0.06
CROP_GROUND_NORMAL_Z = 0.7


def crop_to_box(gaussians, size: Sequence[float], margin_m: float = 0.1, ground_m: float = CROP_GROUND_M):
    """The Gaussians whose means lie inside the box ``size`` (l, w, h, centred at the origin of
    the node frame, z up) grown by ``margin_m`` at the sides and the top: what a tracked object
    really is, without the floaters optimisation attached to it, and without the road under it:
    means below the box's bottom face, and upward-facing ones (normal z > CROP_GROUND_NORMAL_Z)
    less than ``ground_m`` above it, are left out (0 = keep the road patch)."""
    for name, v in (("margin_m", margin_m), ("ground_m", ground_m)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and 0 <= v <= 10):
            raise ConfigError(f"{name}: must be in [0, 10] metres, got {v!r}")
    sz = torch.as_tensor([float(x) for x in size], dtype=torch.float64)
    if sz.shape != (3,) or not bool(torch.isfinite(sz).all()) or bool((sz <= 0).any()):
        raise ConfigError(f"size: expected 3 finite lengths > 0, got {size!r}")
    half = sz / 2 + margin_m
    m = gaussians.means.detach().to(torch.float64)
    inside = (m.abs() <= half).all(dim=1)
    if ground_m > 0:
        above_bottom = m[:, 2] + sz[2] / 2  # metres over the bottom face
        up = gaussians.unit_normals().detach()[:, 2].to(torch.float64) > CROP_GROUND_NORMAL_Z
        inside &= (above_bottom >= 0) & ~(up & (above_bottom < ground_m))
    return gaussians.index(torch.nonzero(inside).reshape(-1))


def prepare_edited(gaussians, size: Sequence[float], *, crop: bool = True, solid: bool = True):
    """An edited (moved or inserted) object's Gaussians: cropped to its box (:func:`crop_to_box`)
    and filled (:func:`solid_filler`), as asked."""
    g = crop_to_box(gaussians, size) if crop else gaussians.detach()
    if solid:
        f = solid_filler(g, size)
        if f.num:
            g = Gaussians.cat([g.detach(), f.to(g.dtype)])
    return g


def vehicle_lights(graph, *, headlight_cd: float = 3000.0, tail_light_cd: float = TAIL_LIGHT_CD,
                   headlights: bool = True, tail_lights: bool = True, off: Sequence[str] = ()) -> list:
    """Headlights (two spots forward, :data:`HEADLIGHT_CONE_DEG`, aimed 4.6 deg down) and tail
    lights (two red points) on every vehicle node of ``graph`` except those named in ``off``;
    placed from the node's box (:func:`object_box`): 0.25 m in from the sides, 0.65 m (head) and
    0.85 m (tail) above the box's bottom, :data:`LAMP_CLEARANCE_M` out from the front / rear
    face (a reconstructed body's Gaussians are centimetres wide: a lamp inside them would be
    shadowed by them). In the node frame: they follow the node's pose. ConfigError names an ``off`` id that
    is not a node."""
    names = [n.name for n in graph.nodes]
    bad = [x for x in off if x not in names]
    if bad:
        raise ConfigError(f"vehicle_lights_off: no object {bad[0]!r} in the scene (objects: {names})")
    out = []
    for n in graph.nodes:
        if n.name in off or not is_vehicle(n.cls):
            continue
        l, w, h = object_box(n)
        y = max(w / 2 - 0.25, 0.1)
        for k, side in enumerate((1.0, -1.0)):
            if headlights:
                out.append(SpotLight((l / 2 + LAMP_CLEARANCE_M, side * y, -h / 2 + 0.65), color=HEADLIGHT_COLOR,
                                     intensity=headlight_cd, range=80.0, node=n.name,
                                     name=f"{n.name}/headlight{k}", direction=HEADLIGHT_DIRECTION,
                                     inner_deg=HEADLIGHT_CONE_DEG[0], outer_deg=HEADLIGHT_CONE_DEG[1]))
            if tail_lights:
                out.append(PointLight((-l / 2 - LAMP_CLEARANCE_M, side * y, -h / 2 + 0.85), color=TAIL_LIGHT_COLOR,
                                      intensity=tail_light_cd, range=10.0, node=n.name, name=f"{n.name}/tail{k}"))
    return out


# -- assets -----------------------------------------------------------------------------------

def export_asset(graph, object_id: str, path: str | Path, *, crop: bool = True, margin_m: float = 0.1) -> Path:
    """Write node ``object_id`` of ``graph`` as an asset file: its Gaussians (geometry and
    materials, node frame; cropped to its box unless ``crop`` is False), box, class. ``torch.save``
    of ``{"format", "version", "id", "cls", "size": [l, w, h], "gaussians": <dict>}``."""
    names = [n.name for n in graph.nodes]
    if object_id not in names:
        raise ConfigError(f"object_id: no object {object_id!r} in the scene (objects: {names})")
    node = graph.node(object_id)
    size = object_box(node)
    g = crop_to_box(node.gaussians, size, margin_m) if crop else node.gaussians
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {"format": ASSET_FORMAT, "version": ASSET_VERSION, "id": node.name, "cls": node.cls,
               "size": list(size), "gaussians": {k: v.detach().cpu().contiguous() for k, v in g.tensors().items()}}

    with atomic_output(path) as tmp:
        torch.save(payload, tmp)
    return path


def load_asset(path: str | Path, what: str = "asset"):
    """``(cls, size, Gaussians)`` of an asset file (:func:`export_asset`); FormatError naming the
    file and field."""
    p = Path(path)
    d = read_torch_file(p, ASSET_FORMAT, (ASSET_VERSION,), "object asset", label=f"{what} {p}")
    try:
        return str(d["cls"]), tuple(float(x) for x in d["size"]), Gaussians(**d["gaussians"])
    except (KeyError, TypeError, ValueError) as exc:
        raise FormatError(f"{what} {p}: missing or malformed field ({exc})") from exc


# -- trajectories -----------------------------------------------------------------------------

def retime_poses(poses: torch.Tensor, time_indices: torch.Tensor, times: torch.Tensor, *, speed: float = 1.0,
                 lateral_offset_m: float = 0.0) -> torch.Tensor:
    """Keyframe poses ``[K, 4, 4]`` of an edited trajectory at the same time indices:

    * ``speed``: the object covers its path ``speed`` times as fast: the pose at time ``t`` is
      the original pose at ``t0 + speed (t - t0)`` (``t0`` its first keyframe time; translation
      interpolated linearly, extrapolated past the last keyframe with the last velocity; rotation
      of the nearest keyframe past the ends, slerp between);
    * ``lateral_offset_m``: every pose moved along its own left axis (node +y), metres: a lane
      offset that follows the road's curves.
    """
    if not (isinstance(speed, (int, float)) and math.isfinite(speed) and 0 <= speed <= 100):
        raise ConfigError(f"speed: must be a finite number in [0, 100], got {speed!r}")
    if not (isinstance(lateral_offset_m, (int, float)) and math.isfinite(lateral_offset_m)
            and abs(lateral_offset_m) <= 1e3):
        raise ConfigError(f"lateral_offset_m: must be a finite number of metres, got {lateral_offset_m!r}")
    P = poses.detach().to(torch.float64)
    ts = torch.as_tensor(times, dtype=torch.float64)[time_indices]
    out = P.clone()
    if speed != 1.0 and len(P) > 1:
        t0 = float(ts[0])
        for k in range(len(P)):
            t = t0 + speed * (float(ts[k]) - t0)
            j = int(torch.searchsorted(ts, torch.tensor([t], dtype=torch.float64))[0])
            if j <= 0:
                i0, i1 = 0, 1
            elif j >= len(ts):
                i0, i1 = len(ts) - 2, len(ts) - 1
            else:
                i0, i1 = j - 1, j
            w = (t - float(ts[i0])) / max(float(ts[i1] - ts[i0]), 1e-12)
            out[k, :3, 3] = P[i0, :3, 3] + w * (P[i1, :3, 3] - P[i0, :3, 3])
            wr = min(max(w, 0.0), 1.0)
            q = quat_slerp(rotmat_to_quat(P[i0, :3, :3]), rotmat_to_quat(P[i1, :3, :3]), wr)
            out[k, :3, :3] = quat_to_rotmat(q)
    if lateral_offset_m:
        out[:, :3, 3] = out[:, :3, 3] + lateral_offset_m * out[:, :3, 1]
    return out


__all__ = ["VEHICLE_CLASSES", "is_vehicle", "describe_objects", "attach_sizes", "object_box", "crop_to_box",
           "solid_filler", "prepare_edited", "vehicle_lights", "export_asset", "load_asset", "retime_poses"]
