"""The scene graph: a static background node and one rigid node per tracked object.

Each rigid node holds its Gaussians in its own frame (origin at the centre of the object's box,
x forward, z up, metres) and an ``obj_to_world`` pose per observed time index (from the bundle's
boxes). :meth:`SceneGraph.compose` places every node at a time (seconds) and returns the world
Gaussians the rasterizer draws. A time between two keyframes interpolates the pose (linear
translation, slerp rotation), as test frames between training frames need; outside a node's
observed range the node is hidden (it was not seen there). Node poses may carry learnable
corrections (``pose_delta_*``), so gradients reach the poses through ordinary autograd.

File format (:meth:`SceneGraph.save`): ``torch.save`` of
``{"format": "brdfusion.scene_graph", "version": 1, "times": [T], "background": <Gaussians dict>,
"nodes": [{"name", "cls", "time_indices": [K], "poses": [K, 4, 4], "gaussians": <dict>,
"size"?: [l, w, h]}], "occluders"?: <Gaussians dict>}`` (``size``, the tracked box, and
``occluders``, shadow-only Gaussians, are optional: older files have neither).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from core.errors import ConfigError, FormatError, NumericalError, ShapeError
from core.gaussians import Gaussians
from core.io.atomic import atomic_output
from core.io.torchfile import read_torch_file
from core.numerics import require_finite
from core.rotations import axis_angle_to_quat, quat_mul, quat_slerp, quat_to_rotmat, rotmat_to_quat

FORMAT_NAME = "brdfusion.scene_graph"
FORMAT_VERSION = 1
#: A node counts as static when all its keyframe poses agree within this (metres / rotation-matrix
#: entries): parked cars then cost no per-frame work.
STATIC_TOL = 1e-6


@dataclass
class RigidNode:
    """A tracked rigid object: Gaussians in the node frame and keyframe poses.

    time_indices: [K] long, sorted, the bundle time indices with a pose.
    poses: [K, 4, 4] obj_to_world (rigid).
    """

    name: str
    cls: str
    gaussians: Gaussians
    time_indices: torch.Tensor
    poses: torch.Tensor
    pose_delta_trans: torch.Tensor | None = None  # [K, 3] metres, learnable
    pose_delta_rot: torch.Tensor | None = None  # [K, 3] rotation vectors, radians, learnable
    size: tuple[float, float, float] | None = None  # the tracked box (l, w, h) metres, when known
    #: Placed by an object edit (:func:`core.relight.apply_edits`: inserted or moved), not as the
    #: capture saw it: its shadow rays start at ``TraceSettings.t_min_objects`` (not saved).
    edited: bool = False
    _static: bool = field(init=False, default=False)

    def __post_init__(self) -> None:
        if self.poses.dim() != 3 or self.poses.shape[1:] != (4, 4):
            raise ShapeError(f"poses (node {self.name}): expected [K, 4, 4], got {list(self.poses.shape)}")
        if self.time_indices.dim() != 1 or len(self.time_indices) != len(self.poses):
            raise ShapeError(f"time_indices (node {self.name}): expected [{len(self.poses)}]")
        if len(self.poses) == 0:
            raise ConfigError(f"poses (node {self.name}): a node needs at least one pose")
        require_finite(self.poses, f"poses (node {self.name})")
        order = torch.argsort(self.time_indices)
        self.time_indices = self.time_indices[order]
        self.poses = self.poses[order]
        self._static = bool((self.poses - self.poses[:1]).abs().max() <= STATIC_TOL)
        if self.size is not None:
            sz = tuple(float(x) for x in self.size)
            if len(sz) != 3 or not all(np.isfinite(x) and x > 0 for x in sz):
                raise ConfigError(f"size (node {self.name}): expected 3 finite lengths > 0, got {self.size!r}")
            self.size = sz

    @property
    def is_static(self) -> bool:
        """True when the node never moves and has no learnable pose correction."""
        return self._static and self.pose_delta_trans is None and self.pose_delta_rot is None

    def enable_pose_refinement(self) -> list[torch.Tensor]:
        """Create zero pose corrections with requires_grad and return them (for an optimizer)."""
        k = len(self.poses)
        self.pose_delta_trans = torch.zeros(k, 3, dtype=self.poses.dtype, requires_grad=True)
        self.pose_delta_rot = torch.zeros(k, 3, dtype=self.poses.dtype, requires_grad=True)
        return [self.pose_delta_trans, self.pose_delta_rot]

    def _key(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(quaternion [4], translation [3]) of keyframe i, with corrections applied."""
        p = self.poses[i].to(self.gaussians.dtype)
        q = rotmat_to_quat(p[:3, :3])
        t = p[:3, 3]
        if self.pose_delta_rot is not None:
            q = quat_mul(axis_angle_to_quat(self.pose_delta_rot[i].to(q.dtype)), q)
        if self.pose_delta_trans is not None:
            t = t + self.pose_delta_trans[i].to(t.dtype)
        return q, t

    def pose_at(self, time: float, times: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
        """(rotation quaternion [4], translation [3]) at ``time`` seconds, or None when the time
        lies outside the node's observed range. ``times``: [T] seconds of the bundle's indices."""
        ts = times[self.time_indices].to(torch.float64)
        t = float(time)
        eps = 1e-6
        if t < float(ts[0]) - eps or t > float(ts[-1]) + eps:
            return None
        j = int(torch.searchsorted(ts, torch.tensor([t], dtype=torch.float64), right=False)[0])
        if j < len(ts) and abs(float(ts[j]) - t) <= eps:
            return self._key(j)
        if j == 0:
            return self._key(0)
        i = j - 1
        w = (t - float(ts[i])) / (float(ts[j]) - float(ts[i]))
        qa, ta = self._key(i)
        qb, tb = self._key(j)
        return quat_slerp(qa, qb, w), ta + (tb - ta) * w


def transform_gaussians(g: Gaussians, q: torch.Tensor, t: torch.Tensor) -> Gaussians:
    """Gaussians moved by the rigid transform (rotation quaternion q [4] wxyz, translation t [3]):
    means, rotations, normals and the view-dependent colour matrix change; scales, opacity and
    materials do not. Differentiable in g, q and t."""
    r = quat_to_rotmat(q)
    if not (bool(torch.isfinite(q).all()) and bool(torch.isfinite(t).all())):
        raise NumericalError("transform_gaussians: pose (q, t) holds NaN or Inf")
    return Gaussians._trusted(
        means=g.means @ r.T + t,
        quats=quat_mul(q.expand_as(g.quats), g.quats),
        log_scales=g.log_scales,
        opacity_logits=g.opacity_logits,
        normals=g.normals @ r.T,
        color_logits=g.color_logits,
        albedo_logits=g.albedo_logits,
        roughness_logits=g.roughness_logits,
        metallic_logits=g.metallic_logits,
        view_dep=(g.view_dep.reshape(-1, 3, 3) @ r.T).reshape(-1, 9),  # W -> W R^T
    )


class SceneGraph:
    """Background Gaussians (world frame) plus rigid nodes. ``times``: [T] seconds per time index."""

    def __init__(self, background: Gaussians, nodes: list[RigidNode], times: torch.Tensor):
        names = [n.name for n in nodes]
        if len(set(names)) != len(names):
            raise ConfigError(f"nodes: duplicate node names {names}")
        self.background = background
        self.nodes = list(nodes)
        self.times = torch.as_tensor(times, dtype=torch.float64)
        if self.times.dim() != 1 or len(self.times) == 0:
            raise ShapeError("times: expected a non-empty [T] tensor of seconds")
        for n in nodes:
            if int(n.time_indices.max()) >= len(self.times) or int(n.time_indices.min()) < 0:
                raise ConfigError(f"node {n.name}: time index outside 0..{len(self.times) - 1}")
        self._static_cache: Gaussians | None = None
        #: Shadow-only Gaussians (world frame): cast shadows in the PBR pass, never rasterized
        #: (:mod:`core.stages.occluders`: facades completed above the captured field of view).
        self.occluders: Gaussians | None = None
        self._solid_cache: dict[str, tuple[Gaussians, Gaussians]] = {}

    def node_solid(self, n: RigidNode) -> Gaussians:
        """Shadow-only Gaussians filling node ``n``'s inside, in its own frame
        (:func:`core.object_solids.solid_filler` in its tracked box; cached while its Gaussians
        are the same object). Empty for a node without a box, and for an edited one, which
        carries its filler among its own Gaussians (:func:`core.render.objects.prepare_edited`)."""
        from core.object_solids import solid_filler

        hit = self._solid_cache.get(n.name)
        if hit is not None and hit[0] is n.gaussians:
            return hit[1]
        solid = (solid_filler(n.gaussians.detach(), n.size) if n.size is not None and not n.edited
                 else Gaussians.empty(n.gaussians.dtype))
        self._solid_cache[n.name] = (n.gaussians, solid)  # the object itself: an id() can be reused
        return solid

    def solids_at(self, time: float, names) -> Gaussians | None:
        """World-space interior fills (:meth:`node_solid`) of the nodes in ``names`` observed at
        ``time`` seconds; None when there are none."""
        parts = []
        for n in self.nodes:
            if n.name in names:
                qt = n._key(0) if n.is_static else n.pose_at(time, self.times)  # as compose places it
                if qt is not None:
                    sol = self.node_solid(n)
                    if sol.num:
                        parts.append(transform_gaussians(sol, *(x.detach() for x in qt)))
        if not parts:
            return None
        return Gaussians.cat(parts) if len(parts) > 1 else parts[0]

    def _static_solids(self, exclude: frozenset[str]) -> Gaussians | None:
        """World-space interior fills of the static nodes not in ``exclude`` (placed as
        :meth:`_static_part` places them), or None."""
        parts = []
        for n in self.nodes:
            if n.is_static and n.name not in exclude:
                sol = self.node_solid(n)
                if sol.num:
                    parts.append(transform_gaussians(sol, *(x.detach() for x in n._key(0))))
        if not parts:
            return None
        return Gaussians.cat(parts) if len(parts) > 1 else parts[0]

    def shadow_nodes_at(self, time: float, names, solids: bool = False) -> Gaussians | None:
        """What shadow rays see of the nodes in ``names`` at ``time`` seconds: :meth:`nodes_at`
        plus, with ``solids``, their interior fills (:meth:`solids_at`); detached."""
        parts = [g.detach() for g in (self.nodes_at(time, names), self.solids_at(time, names) if solids else None)
                 if g is not None and g.num]
        if not parts:
            return None
        return Gaussians.cat([p.to(parts[0].dtype) for p in parts]) if len(parts) > 1 else parts[0]

    def node(self, name: str) -> RigidNode:
        for n in self.nodes:
            if n.name == name:
                return n
        raise ConfigError(f"name: no node {name!r} (nodes: {[n.name for n in self.nodes]})")

    def node_poses(self, time: float) -> dict[str, torch.Tensor]:
        """obj_to_world [4, 4] of each node visible at ``time`` (seconds), detached."""
        out = {}
        for n in self.nodes:
            qt = n.pose_at(time, self.times)
            if qt is None:
                continue
            m = torch.eye(4, dtype=torch.float64)
            m[:3, :3] = quat_to_rotmat(qt[0].detach().to(torch.float64))
            m[:3, 3] = qt[1].detach().to(torch.float64)
            out[n.name] = m
        return out

    def _static_part(self) -> Gaussians:
        """Background plus every static node in world space, composed once and cached (static
        nodes need no per-frame work). Not cached while anything in it requires grad."""
        if self._static_cache is not None:
            return self._static_cache
        parts = [self.background]
        for n in self.nodes:
            if n.is_static:
                q, t = n._key(0)
                parts.append(transform_gaussians(n.gaussians, q, t))
        out = Gaussians.cat(parts) if len(parts) > 1 else self.background
        if not any(p.requires_grad for p in out.tensors().values()):
            self._static_cache = out
        return out

    def shadow_static(self, solids: bool = False) -> Gaussians:
        """What static shadow rays see: :meth:`_static_part` plus :attr:`occluders` and, with
        ``solids``, the static nodes' interior fills (:meth:`node_solid`); detached."""
        st = self._static_part().detach()
        extra = [self.occluders] if self.occluders is not None and self.occluders.num else []
        if solids:
            sol = self._static_solids(frozenset())
            extra += [sol] if sol is not None else []
        if not extra:
            return st
        return Gaussians.cat([st] + [e.detach().to(st.dtype) for e in extra])

    def edited_nodes(self) -> frozenset[str]:
        """Names of the nodes an object edit placed (:attr:`RigidNode.edited`)."""
        return frozenset(n.name for n in self.nodes if n.edited)

    def shadow_static_except(self, names: frozenset[str], solids: bool = False) -> Gaussians:
        """:meth:`shadow_static` without the static nodes in ``names`` (detached, not cached)."""
        if not names:
            return self.shadow_static(solids)
        parts = [self.background.detach()]
        for n in self.nodes:
            if n.is_static and n.name not in names:
                q, t = n._key(0)
                parts.append(transform_gaussians(n.gaussians, q, t).detach())
        if self.occluders is not None and self.occluders.num:
            parts.append(self.occluders.detach().to(self.background.dtype))
        if solids:
            sol = self._static_solids(names)
            if sol is not None:
                parts.append(sol.detach().to(self.background.dtype))
        return Gaussians.cat(parts) if len(parts) > 1 else parts[0]

    def nodes_at(self, time: float, names) -> Gaussians | None:
        """World-space Gaussians of the nodes in ``names`` observed at ``time`` seconds, in node
        order (static or not); None when none of them is."""
        parts = []
        for n in self.nodes:
            if n.name in names:
                qt = n.pose_at(time, self.times)
                if qt is not None:
                    parts.append(transform_gaussians(n.gaussians, *qt))
        if not parts:
            return None
        return Gaussians.cat(parts) if len(parts) > 1 else parts[0]

    def invalidate(self) -> None:
        """Drop cached compositions (call after editing Gaussians in place)."""
        self._static_cache = None
        self._solid_cache = {}

    def compose(self, time: float, *, hidden: set[str] | frozenset[str] = frozenset()) -> Gaussians:
        """World-space Gaussians of the whole scene at ``time`` seconds (nodes in ``hidden`` and
        nodes not observed at that time are left out)."""
        if hidden:
            parts = [self.background]
            movers = [n for n in self.nodes if n.name not in hidden]
        else:
            parts = [self._static_part()]
            movers = [n for n in self.nodes if not n.is_static]
        for n in movers:
            qt = n.pose_at(time, self.times)
            if qt is not None:
                parts.append(transform_gaussians(n.gaussians, *qt))
        return Gaussians.cat(parts) if len(parts) > 1 else parts[0]

    # -- construction from a bundle -------------------------------------------------------------
    @classmethod
    def from_bundle_objects(cls, manifest, background: Gaussians,
                            node_gaussians: dict[str, Gaussians]) -> "SceneGraph":
        """Build the graph from a bundle manifest's tracked objects; ``node_gaussians`` maps an
        object id to its Gaussians in the object frame (objects without Gaussians are skipped)."""
        nodes = []
        for obj in manifest.objects:
            if obj.id not in node_gaussians:
                continue
            ti = sorted(obj.poses)
            poses = torch.from_numpy(np.stack([obj.poses[t] for t in ti])).to(torch.float64)
            nodes.append(RigidNode(obj.id, obj.cls, node_gaussians[obj.id], torch.tensor(ti), poses,
                                   size=tuple(obj.size)))
        return cls(background, nodes, torch.tensor(manifest.times, dtype=torch.float64))

    # -- files -----------------------------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        def gd(g: Gaussians) -> dict:
            return {k: v.detach().cpu().contiguous() for k, v in g.tensors().items()}

        payload = {
            "format": FORMAT_NAME, "version": FORMAT_VERSION, "times": self.times,
            "background": gd(self.background),
            "nodes": [{"name": n.name, "cls": n.cls, "time_indices": n.time_indices,
                       "poses": n.poses, "gaussians": gd(n.gaussians),
                       **({"size": list(n.size)} if n.size is not None else {})} for n in self.nodes],
        }
        if self.occluders is not None and self.occluders.num:
            payload["occluders"] = gd(self.occluders)
        path = Path(path)

        with atomic_output(path) as tmp:
            torch.save(payload, tmp)

    @classmethod
    def load(cls, path: str | Path) -> "SceneGraph":
        path = Path(path)
        d = read_torch_file(path, FORMAT_NAME, (FORMAT_VERSION,), "scene graph")
        try:
            bg = Gaussians(**d["background"])
            nodes = [RigidNode(n["name"], n["cls"], Gaussians(**n["gaussians"]), n["time_indices"], n["poses"],
                               size=tuple(n["size"]) if n.get("size") is not None else None)
                     for n in d["nodes"]]
            graph = cls(bg, nodes, d["times"])
            if d.get("occluders") is not None:
                graph.occluders = Gaussians(**d["occluders"])
            return graph
        except (KeyError, TypeError) as exc:
            raise FormatError(f"{path}: missing or malformed field ({exc})") from exc
