"""The volume rendering stage (paper Sec. 3.3, Eq. 4; supplement "Implementation Details").

Fits every Gaussian attribute (geometry, colour, normal, albedo, roughness, metallic) of the scene
graph to the training frames through the volume pass, minimising

    L_vol = L_rgb + l_O L_O + l_D L_D + l_N L_N + l_A L_A + l_R L_R + l_M L_M

* ``L_rgb = (1 - l_ssim) |C - C_gt| + l_ssim (1 - SSIM(C, C_gt))`` with ``C`` the composited
  colour over the learnable sky dome (:class:`core.train.sky.SkyDome`);
* ``L_O``: binary cross-entropy of the opacity against the non-sky mask (no sky floaters);
* ``L_D = |D - D_lidar| + |(u D + v) - D_g|``: LiDAR depth at the pixels a sweep projects to, and
  the prior depth with ``u, v`` the closed-form least-squares scale and shift per frame;
* ``L_N = |N - N_g|_1 - N . N_g`` against the prior normals (world frame);
* ``L_A, L_R, L_M``: L1 against the prior albedo, roughness, metallic.

``D``, ``N``, ``A``, ``R``, ``M`` are the composited G-buffers divided by the opacity (expected
values given a hit); the prior terms are averaged over pixels that are surface in the non-sky mask
(or, without a mask, in the prior) and covered by the render (``O > 0.5``). The priors
(:class:`core.stages.priors.GBufferPriors`) come from the inverse model (first stage) or from the
generative refinement (second stage, :mod:`core.stages.volume2`). With every prior weight at zero
this is the colour-only stage (novel-view synthesis; the ablation ``no_gen_optim``).

Also: adaptive density control, checkpoints that resume a killed run, a loss log, and PSNR / SSIM
on the held-out (test) trajectory.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from tqdm import tqdm

from core.bundle import SceneBundle
from core.camera import Camera
from core.errors import ConfigError, FormatError, NumericalError, ShapeError
from core.gaussians import Gaussians
from core.io.atomic import atomic_output
from core.io.images import write_png
from core.io.video import write_mp4
from core.metrics import psnr, ssim
from core.numerics import require_finite, safe_normalize
from core.raster import RasterSettings, rasterize_gaussians
from core.rotations import quat_to_rotmat
from core.scene_graph import SceneGraph, transform_gaussians
from core.stages.chain import scene_skips
from core.stages.early_stop import stalled
from core.stages.occluders import OccluderSettings, capture_views, complete_occluders
from core.train.density import DensityConfig, DensityController, scene_extent
from core.train.init_lidar import LidarInitConfig, gaussians_from_lidar, sweeps_from_depth
from core.train.optim import GaussianAdam, GaussianLR
from core.train.sky import SkyDome


@dataclass(frozen=True)
class VolumeSettings:
    """Settings of the volume stage (and, with ``init_from_graph``, the second volume stage)."""

    iterations: int = 2000
    """Optimisation steps (one training frame each)."""
    lambda_ssim: float = 0.2
    """Weight of (1 - SSIM) against L1 in the photometric loss (3DGS's 0.2)."""
    lambda_opacity: float = 0.05
    """Weight of the opacity-vs-sky BCE (the paper's lambda_O)."""
    lambda_depth: float = 0.01
    """Weight of the LiDAR depth L1 (the paper's lambda_D)."""
    densify_from: int = 200
    """First step of adaptive density control."""
    densify_until: int = 1400
    """Last step of adaptive density control."""
    densify_every: int = 100
    """Steps between density control passes."""
    opacity_reset_every: int = 0
    """Steps between opacity resets (0 = never; short runs do better without)."""
    means_lr_decay: float = 0.1
    """Final position learning rate as a fraction of the initial one (exponential decay)."""
    sky_lr: float = 0.05
    """Learning rate of the sky dome."""
    sky_height: int = 256
    """Rows of the sky dome texture (columns = 2 x rows). The frames' sky holds detail (distant
    buildings and trees of the environment); a coarse dome cannot show it and Gaussians are
    recruited instead: sky floaters."""
    threads: int = 2
    """CPU threads of the rasterizer kernels."""
    torch_threads: int = 1
    """Intra-op threads of torch for the rest of the step (losses, optimiser). One: the tensors
    are small, and torch's OpenMP workers spin between ops and steal the cores the rasterizer
    threads need (measured: a step 3-10x slower with 2)."""
    lambda_normal: float = 0.3
    """Weight of the normal prior term L_N (supplement: 0.3)."""
    lambda_albedo: float = 0.5
    """Weight of the albedo prior term L_A (supplement: 0.5)."""
    lambda_roughness: float = 0.3
    """Weight of the roughness prior term L_R (supplement: 0.3)."""
    lambda_metallic: float = 0.3
    """Weight of the metallic prior term L_M (supplement: 0.3)."""
    lambda_prior_depth: float = 0.01
    """Weight of the aligned prior depth term ``|(u D + v) - D_g|`` (the paper's lambda_D)."""
    lambda_align: float = 0.1
    """Weight of the disk-normal alignment ``mean(1 - |a . n|)`` (``a`` a Gaussian's shortest
    axis, ``n`` its normal): each Gaussian lies in the surface its normal describes, so tilted
    disks do not stand out of a surface and shadow it in the PBR pass (not in the paper: its
    Gaussians are traced by 3DGRT with the same problem; measured here on the default scene)."""
    prune_sky_floaters: bool = True
    """At the end of the stage, remove Gaussians whose centre projects into the sky mask in at
    least half of the training views that see it (floaters: they cast shadows and streak the sky
    of novel views); the count is in the summary."""
    prior_min_opacity: float = 0.5
    """Prior terms count only where the render covers the pixel at least this much."""
    priors_move_geometry: bool = False
    """The normal and material prior terms (L_N, L_A, L_R, L_M) move the geometry too (the
    blending weights of the G-buffers they compare), as well as the attributes they supervise:
    True, as Eq. 4 reads. False (the default, a departure): they are computed on a second render
    of the same Gaussians with the geometry detached
    (:meth:`core.gaussians.Gaussians.geometry_detached`), so only the normals and materials
    follow them, and the geometry answers to the frames, the LiDAR, the depth prior and the
    disk-normal alignment. An inverse model's albedo or normals that disagree with the frames
    pulled Gaussians off the surfaces the frames show: on development street dev1 (quick) the
    volume stage's held-out PSNR was 24.33 dB against the colour-only stage's 25.08. Measured at
    the quick profile, development scenes, True -> False: dev1 NVS 24.68 -> 25.93 dB, relit
    19.07 / 0.656 -> 19.85 / 0.676, re-render 18.13 -> 19.24, albedo 20.9 -> 21.1 dB, normals
    6.4 -> 6.2 deg; the default scene NVS 25.22 -> 25.44, relit 18.56 -> 18.83 dB. Costs a second
    rasterization per step."""
    init_from_graph: bool = False
    """Start from the previous stage's scene graph and sky (the second volume stage) instead of
    the LiDAR initialisation."""
    seed: int = 0
    """Random seed (frame order, density control)."""
    init: LidarInitConfig = field(default_factory=LidarInitConfig)
    """LiDAR initialisation."""
    density: DensityConfig = field(default_factory=DensityConfig)
    """Adaptive density control."""
    occluders: OccluderSettings = field(default_factory=OccluderSettings)
    """Facades completed above the captured field of view for shadow rays only, at the end of
    the stage (:mod:`core.stages.occluders`); the count is in the summary."""
    lr: GaussianLR = field(default_factory=GaussianLR)
    """Learning rates."""
    early_stop_every: int = 0
    """Skip: stop once the held-out error stops improving. Every this many steps after the
    density control window (``densify_until``), the PSNR of the held-out (test) frames is
    measured; after ``early_stop_patience`` measurements in a row without a gain of
    ``early_stop_min_delta_db`` over the best before them the stage stops, and its summary's
    ``skips_fired`` says when and why (:func:`core.stages.early_stop.stalled`). Without test
    frames it never fires. The summary's ``test_psnr`` is then measured on the frames that chose
    the stop. 0 = off, the default: not within noise (``benchmarks/bench_skips.py``, 6 tiny
    streets, 200 steps, a check every 10: stopped after 70-100 steps, 4.4 +- 0.7 s saved,
    held-out PSNR +0.19 +- 0.05 dB: better, beyond noise, but measured on the frames that chose
    the stop)."""
    early_stop_patience: int = 2
    """Held-out measurements without improvement before the stage stops."""
    early_stop_min_delta_db: float = 0.05
    """Gain of held-out PSNR (dB) that counts as an improvement."""

    def __post_init__(self) -> None:
        for name, ok in (("early_stop_every", isinstance(self.early_stop_every, int) and self.early_stop_every >= 0),
                         ("early_stop_patience", isinstance(self.early_stop_patience, int)
                          and self.early_stop_patience >= 1),
                         ("early_stop_min_delta_db", isinstance(self.early_stop_min_delta_db, (int, float))
                          and 0 <= self.early_stop_min_delta_db < 100)):
            if not ok:
                raise ConfigError(f"{name}: out of range, got {getattr(self, name)!r}")


@dataclass
class _View:
    frame_id: str
    time: float
    camera: Camera  # the frame's camera, pose float32 (the Gaussians' dtype)
    image: torch.Tensor  # [H, W, 3]
    nonsky: torch.Tensor | None  # [H, W, 1] float (1 = surface)
    dirs: torch.Tensor  # [H, W, 3] world
    lidar_px: torch.Tensor | None  # [K] flat pixel indices
    lidar_z: torch.Tensor | None  # [K] camera depth, metres


def _views(bundle: SceneBundle, split: str, with_lidar: bool) -> list[_View]:
    out = []
    m = bundle.manifest
    for f in bundle.frames(split):
        cam = bundle.camera(f)
        img = torch.from_numpy(bundle.load_image(f))
        sky = bundle.load_sky_mask(f)
        nonsky = None if sky is None else torch.from_numpy(~sky).float()[..., None]
        camera = Camera.from_bundle(cam, f)
        dirs = torch.from_numpy(camera.ray_directions()).float()
        lpx = lz = None
        if with_lidar and any(s.time_index == f.time_index for s in m.lidar):
            pts = bundle.load_lidar(f.time_index)[:, 3:].astype(np.float64)
            uv, z = camera.project(pts)
            ok = (z > 0.5) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
            px = uv[ok, 1].astype(np.int64) * cam.width + uv[ok, 0].astype(np.int64)
            # keep the nearest point per pixel (LiDAR sees past thin occluders the camera sees)
            order = np.argsort(z[ok])
            px_s, z_s = px[order], z[ok][order]
            _, first = np.unique(px_s, return_index=True)
            lpx, lz = torch.from_numpy(px_s[first]), torch.from_numpy(z_s[first]).float()
        out.append(_View(f.id, m.times[f.time_index], camera.to(torch.float32), img, nonsky, dirs, lpx, lz))
    return out


class VolumeModel:
    """Scene graph + sky + one optimiser and density controller per Gaussian container."""

    def __init__(self, graph: SceneGraph, sky: SkyDome):
        self.graph = graph
        self.sky = sky

    def containers(self) -> list[Gaussians]:
        return [self.graph.background] + [n.gaussians for n in self.graph.nodes]

    def set_container(self, i: int, g: Gaussians) -> None:
        if i == 0:
            self.graph.background = g
        else:
            self.graph.nodes[i - 1].gaussians = g
        self.graph.invalidate()

    def compose(self, time: float) -> tuple[Gaussians, list[tuple[int, int, int]]]:
        """World Gaussians and [(container index, start row, count)] of each part."""
        parts, spans, row = [self.graph.background], [(0, 0, self.graph.background.num)], self.graph.background.num
        for i, n in enumerate(self.graph.nodes):
            qt = n.pose_at(time, self.graph.times)
            if qt is None:
                continue
            parts.append(transform_gaussians(n.gaussians, *qt))
            spans.append((i + 1, row, n.gaussians.num))
            row += n.gaussians.num
        return (Gaussians.cat(parts) if len(parts) > 1 else parts[0]), spans

    def render(self, v: _View, settings: RasterSettings):
        world, spans = self.compose(v.time)
        out = rasterize_gaussians(world, v.camera, settings=settings)
        rgb = out.color + (1.0 - out.opacity) * self.sky(v.dirs)
        return rgb, out, world, spans

    def save(self, path: Path, extra: dict | None = None) -> None:
        path.mkdir(parents=True, exist_ok=True)
        self.graph.save(path / "scene_graph.pt")
        torch.save({"sky": self.sky.state_dict(), **(extra or {})}, path / "sky.pt")


def _mean_sky_colour(views: list[_View]) -> tuple[float, float, float]:
    sky = [v.image[v.nonsky[..., 0] < 0.5] for v in views if v.nonsky is not None]
    sky = [s for s in sky if len(s)]
    if not sky:
        return (0.6, 0.7, 0.8)
    return tuple(float(x) for x in torch.cat(sky).mean(0))


def _bce(o: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    o = o.clamp(1e-4, 1 - 1e-4)
    return -(target * torch.log(o) + (1 - target) * torch.log(1 - o)).mean()


def evaluate(model: VolumeModel, views: list[_View], settings: RasterSettings) -> dict:
    """Mean PSNR / SSIM of the renders of ``views`` against their frames, plus the renders."""
    ps, ss, renders = [], [], []
    with torch.no_grad():
        for v in views:
            rgb, *_ = model.render(v, settings)
            rgb = rgb.clamp(0, 1)
            ps.append(float(psnr(rgb, v.image)))
            ss.append(float(ssim(rgb, v.image)))
            renders.append(rgb)
    return {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)), "per_frame_psnr": ps, "renders": renders}


def _prior_tensors(priors, views: list[_View]) -> dict[str, dict[str, torch.Tensor]]:
    """Per training view: the prior layers as tensors plus the pixel mask the terms average over
    (non-sky per the bundle's mask when it has one, else where the prior sees a surface)."""
    out = {}
    for v in views:
        layers = priors.frame(v.frame_id) if priors is not None else None
        if layers is None:
            continue
        t = {k: torch.from_numpy(np.ascontiguousarray(a, np.float32)) for k, a in layers.items()}
        surf = t["depth"][..., 0] > 0
        if v.nonsky is not None:
            surf = v.nonsky[..., 0] > 0.5
        t["mask"] = surf.clone()
        out[v.frame_id] = t
    return out


def prior_losses(out, prior: dict[str, torch.Tensor], min_opacity: float) -> dict[str, torch.Tensor]:
    """The prior terms of Eq. 4 for one frame: ``normal`` (|N - N_g|_1 - N . N_g), ``albedo``,
    ``roughness``, ``metallic`` (L1) and ``depth`` (``|(u D + v) - D_g|`` with the closed-form
    least-squares ``u, v``, detached), each a mean over the covered prior mask. ``out``: the
    :class:`core.raster.RasterOutput` of the frame; ``prior``: :func:`_prior_tensors` of it.
    Empty masks give zeros (with the graph kept), never NaN."""
    o = out.opacity
    cover = o[..., 0].detach() > min_opacity
    m = prior["mask"] & cover
    zero = (o * 0).sum()
    if int(m.sum()) < 16:
        return {k: zero for k in ("normal", "albedo", "roughness", "metallic", "depth")}
    inv = 1.0 / o.clamp_min(min_opacity)  # expected value given a hit (o > min_opacity on m)
    res = {}
    n = out.normal * inv
    ng = prior["normal"].to(n.dtype)
    res["normal"] = ((n - ng).abs().sum(-1) - (n * ng).sum(-1))[m].mean()
    for k in ("albedo", "roughness", "metallic"):
        res[k] = ((getattr(out, k) * inv - prior[k].to(n.dtype)).abs().mean(-1))[m].mean()
    d = (out.depth * inv)[..., 0]
    dg = prior["depth"][..., 0].to(d.dtype)
    md = m & (dg > 0)
    if int(md.sum()) >= 16:
        # the closed-form fit in float64: in float32, depths past ~1e19 square to Inf and the
        # scale became Inf / Inf = NaN (stress tests); a fit that is still not finite is identity
        x, y = d.detach()[md].double(), dg[md].double()
        xm, ym = x.mean(), y.mean()
        var = ((x - xm) ** 2).mean()
        u = ((x - xm) * (y - ym)).mean() / var.clamp_min(1e-8)
        u = torch.where(var > 1e-8, u, torch.ones_like(u))
        vshift = ym - u * xm
        fit_ok = torch.isfinite(u) & torch.isfinite(vshift)
        u = torch.where(fit_ok, u, torch.ones_like(u)).to(d.dtype)
        vshift = torch.where(fit_ok, vshift, torch.zeros_like(vshift)).to(d.dtype)
        res["depth"] = (u * d[md] + vshift - y.to(d.dtype)).abs().mean()
    else:
        res["depth"] = zero
    return res


def attribute_prior_losses(world: Gaussians, camera, settings, prior: dict[str, torch.Tensor],
                           min_opacity: float) -> dict[str, torch.Tensor]:
    """The normal and material terms of :func:`prior_losses` on a second render of ``world`` with
    its geometry detached (:meth:`core.gaussians.Gaussians.geometry_detached`): they move the
    normals and materials only (``priors_move_geometry`` False)."""
    out = rasterize_gaussians(world.geometry_detached(), camera, settings=settings)
    t = prior_losses(out, prior, min_opacity)
    return {k: t[k] for k in ("normal", "albedo", "roughness", "metallic")}


def lidar_depth_loss(out, px: torch.Tensor, z: torch.Tensor, min_opacity: float = 0.05) -> torch.Tensor:
    """``mean |D / O - z_lidar|`` at the pixels a sweep hits: the expected depth given a hit
    (the composited depth ``D`` is a sum weighted by the opacity; compared undivided, a pixel of
    opacity 0.95 pulls its Gaussians 5% deeper than the LiDAR: below the road).

    A sweep that projects to no pixel gives 0 (with the graph kept): the mean of an empty set is
    NaN, which would leave silently. Non-finite ``z`` is a NumericalError naming it."""
    if px.numel() != z.numel():
        raise ShapeError(f"px, z: {px.numel()} pixel indices but {z.numel()} LiDAR depths")
    if px.numel() == 0:  # mean over nothing is NaN (the numerical stress tests)
        return (out.depth * 0).sum()
    require_finite(z, "z (LiDAR depth)")
    o = out.opacity.reshape(-1)[px]
    d = out.depth.reshape(-1)[px] / o.clamp_min(min_opacity)
    return (d - z).abs().mean()


def alignment_loss(g: Gaussians) -> torch.Tensor:
    """``mean(1 - |a . n|)`` over Gaussians: ``a`` the unit axis of the smallest scale (world),
    ``n`` the unit normal. Differentiable in the quaternions and normals (the axis choice is not)."""
    if g.num == 0:
        return g.means.sum() * 0
    rot = quat_to_rotmat(g.quats)  # [N, 3, 3], columns = local axes in world
    ax = g.log_scales.detach().argmin(1)
    a = rot.gather(2, ax.view(-1, 1, 1).expand(-1, 3, 1))[..., 0]
    n = safe_normalize(g.normals)
    return (1.0 - (a * n).sum(-1).abs()).mean()


def sky_floaters(g: Gaussians, views: list[_View], min_fraction: float = 0.5) -> torch.Tensor:
    """[N] bool: Gaussians (world) whose centre falls on a sky pixel (mask eroded by one pixel)
    in at least ``min_fraction`` of the training views whose image it projects into."""
    means = g.means.detach().double()
    n_in = torch.zeros(g.num, dtype=torch.int32)
    n_sky = torch.zeros(g.num, dtype=torch.int32)
    for v in views:
        if v.nonsky is None:
            continue
        sky = v.nonsky[..., 0] < 0.5
        er = sky.clone()  # erode: a sky pixel next to a surface pixel is not counted
        er[1:] &= sky[:-1]
        er[:-1] &= sky[1:]
        er[:, 1:] &= sky[:, :-1]
        er[:, :-1] &= sky[:, 1:]
        c = v.camera
        w2c = torch.linalg.inv(c.cam_to_world.double())
        pc = means @ w2c[:3, :3].T + w2c[:3, 3]
        z = pc[:, 2]
        ok = z > 0.2
        u = (c.fx * pc[:, 0] / z.clamp_min(1e-6) + c.cx).floor().long()
        vv = (c.fy * pc[:, 1] / z.clamp_min(1e-6) + c.cy).floor().long()
        ok &= (u >= 0) & (u < c.width) & (vv >= 0) & (vv < c.height)
        idx = torch.nonzero(ok).reshape(-1)
        n_in[idx] += 1
        n_sky[idx] += er[vv[idx], u[idx]].to(torch.int32)
    return (n_sky > 0) & (n_sky.float() >= min_fraction * n_in.float().clamp_min(1))


def run_volume(bundle: SceneBundle, cfg: VolumeSettings, out_dir: str | Path | None = None, *,
               priors=None, init_dir: str | Path | None = None, init_sweeps=None,
               progress: bool = True, log_every: int = 50, checkpoint_dir: str | Path | None = None,
               checkpoint_every: int = 500, on_progress: Callable[[int, int, dict], None] | None = None) -> dict:
    """Train on the bundle's train split; evaluate on its test split. Returns a summary dict
    (held-out PSNR/SSIM, NaN without test frames; train PSNR, Gaussians, seconds, the loss terms)
    and writes renders, the scene graph and sky (``checkpoint/``) and ``summary.json`` (NaN as
    null) into ``out_dir`` when given.

    ``priors``: :class:`core.stages.priors.GBufferPriors` of the training frames (None: the prior
    terms are off, whatever their weights: the colour-only stage). ``init_dir``: with
    ``cfg.init_from_graph``, the ``checkpoint/`` directory of the previous volume stage (its
    ``scene_graph.pt`` and ``sky.pt``) to start from.

    ``checkpoint_dir``: the full training state (Gaussians, sky, optimiser moments, density
    statistics, random state, loss history) is saved there every ``checkpoint_every`` steps, and a
    run started with a directory that holds a state resumes from it: a crashed or killed run
    continues where its last checkpoint left off. ``on_progress(it, iterations, record)`` is
    called every ``log_every`` steps (an exception raised there stops the run, e.g. a cancel)."""
    if cfg.iterations < 1:
        raise ConfigError(f"iterations: must be >= 1, got {cfg.iterations}")
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    old_threads = torch.get_num_threads()
    torch.set_num_threads(cfg.torch_threads)
    t0 = time.time()
    try:
        train = _views(bundle, "train", with_lidar=True)
        test = _views(bundle, "test", with_lidar=False)
        if not train:
            raise ConfigError("bundle: has no train frames")
        ckpt = Path(checkpoint_dir) if checkpoint_dir is not None else None
        state = _load_state(ckpt) if ckpt is not None else None
        sky = SkyDome(cfg.sky_height, 2 * cfg.sky_height, _mean_sky_colour(train))
        if state is not None:
            graph = SceneGraph.load(ckpt / state["graph_file"])
        elif cfg.init_from_graph:
            if init_dir is None or not (Path(init_dir) / "scene_graph.pt").is_file():
                raise ConfigError(f"init_dir: init_from_graph needs the previous stage's checkpoint/ with "
                                  f"scene_graph.pt, got {init_dir!r}")
            graph = SceneGraph.load(Path(init_dir) / "scene_graph.pt")
            sky_file = Path(init_dir) / "sky.pt"
            if sky_file.is_file():
                sky = SkyDome.from_state(torch.load(sky_file, map_location="cpu", weights_only=True)["sky"])
        else:
            bg, nodes = gaussians_from_lidar(bundle, cfg.init, sweeps=init_sweeps)
            graph = SceneGraph.from_bundle_objects(bundle.manifest, bg, nodes)
        model = VolumeModel(graph, sky)
        pri = _prior_tensors(priors, train)
        for v in train:  # no sky mask: the prior's sky (no surface) stands in for it
            if v.nonsky is None and v.frame_id in pri:
                v.nonsky = pri[v.frame_id]["mask"].to(torch.float32)[..., None]
        weights = {"normal": cfg.lambda_normal, "albedo": cfg.lambda_albedo, "roughness": cfg.lambda_roughness,
                   "metallic": cfg.lambda_metallic, "depth": cfg.lambda_prior_depth}
        use_priors = bool(pri) and any(w > 0 for w in weights.values())
        settings = RasterSettings(threads=cfg.threads)
        extent = scene_extent(torch.stack([v.camera.center for v in train]))
        opts = [GaussianAdam(g, cfg.lr) for g in model.containers()]
        dens = [DensityController(cfg.density, extent, g.num) for g in model.containers()]
        sky_opt = torch.optim.Adam(model.sky.parameters(), lr=cfg.sky_lr)
        history = []
        validation: list[dict] = []  # held-out PSNR of the early stop
        fired: list[dict] = []
        stopped_at = None
        start_it = 1
        if state is not None:
            start_it = _restore(state, model, opts, dens, sky_opt, rng) + 1
            history = state["history"]
            validation = list(state.get("validation", []))
        bar = tqdm(range(start_it, cfg.iterations + 1), desc="volume", unit="it", disable=not progress,
                   initial=start_it - 1, total=cfg.iterations)
        for it in bar:
            v = train[int(rng.integers(len(train)))]
            for o in opts:
                o.zero_grad()
            sky_opt.zero_grad()
            rgb, out, world, spans = model.render(v, settings)
            world.means.retain_grad()
            l1 = (rgb - v.image).abs().mean()
            loss = (1 - cfg.lambda_ssim) * l1 + cfg.lambda_ssim * (1 - ssim(rgb, v.image))
            if v.nonsky is not None and cfg.lambda_opacity > 0:
                loss = loss + cfg.lambda_opacity * _bce(out.opacity, v.nonsky)
            if v.lidar_px is not None and cfg.lambda_depth > 0 and len(v.lidar_px):
                loss = loss + cfg.lambda_depth * lidar_depth_loss(out, v.lidar_px, v.lidar_z)
            terms = {}
            if cfg.lambda_align > 0:
                terms["align"] = alignment_loss(world)
                loss = loss + cfg.lambda_align * terms["align"]
            if use_priors and v.frame_id in pri:
                # update, not replace: a non-finite alignment term must still be named below
                terms.update(prior_losses(out, pri[v.frame_id], cfg.prior_min_opacity))
                if not cfg.priors_move_geometry:
                    terms.update(attribute_prior_losses(world, v.camera, settings, pri[v.frame_id],
                                                        cfg.prior_min_opacity))
                for k, w in weights.items():
                    if w > 0:
                        loss = loss + w * terms[k]
            if not torch.isfinite(loss):
                bad = [k for k, t in terms.items() if not torch.isfinite(t)] or ["rgb/opacity/lidar"]
                raise NumericalError(f"volume stage: non-finite loss at iteration {it} (term(s) {bad}; "
                                     f"last good checkpoint kept)")
            loss.backward()
            decay = cfg.means_lr_decay ** (it / cfg.iterations)
            for o in opts:
                o.step({"means": decay})
            sky_opt.step()
            in_window = cfg.densify_from <= it <= cfg.densify_until
            if in_window and world.means.grad is not None:
                for ci, start, cnt in spans:
                    dens[ci].accumulate(world.means.grad[start:start + cnt], world.means.detach()[start:start + cnt],
                                        v.camera)
            if in_window and it % cfg.densify_every == 0:
                for ci, (o, dc) in enumerate(zip(opts, dens)):
                    others = sum(x.g.num for x in opts) - o.g.num  # one cap for the whole scene
                    dc.densify_and_prune(o, prune_large=cfg.opacity_reset_every > 0 and it > cfg.opacity_reset_every,
                                         max_gaussians=cfg.density.max_gaussians - others)
                    model.set_container(ci, o.g)
            if cfg.opacity_reset_every and it % cfg.opacity_reset_every == 0 and it < cfg.densify_until:
                for o, dc in zip(opts, dens):
                    dc.reset_opacity(o)
                model.graph.invalidate()
            if it % log_every == 0 or it == cfg.iterations:
                n = sum(g.num for g in model.containers())
                history.append({"it": it, "loss": float(loss.detach()), "l1": float(l1.detach()), "gaussians": n,
                                "s": round(time.time() - t0, 2),
                                **{f"prior_{k}": round(float(t.detach()), 5) for k, t in terms.items()}})
                bar.set_postfix(loss=f"{float(loss.detach()):.4f}", n=n)
                if on_progress is not None:
                    on_progress(it, cfg.iterations, history[-1])
            k = cfg.early_stop_every
            if k and test and it % k == 0 and it >= cfg.densify_until and it < cfg.iterations:
                validation.append({"it": it, "psnr": round(evaluate(model, test, settings)["psnr"], 4)})
                vals = [x["psnr"] for x in validation]
                if stalled(vals, cfg.early_stop_patience, cfg.early_stop_min_delta_db, higher_is_better=True):
                    stopped_at = it
                    fired.append({"skip": "early_stop", "stopped_at": it,
                                  "why": f"held-out PSNR did not gain {cfg.early_stop_min_delta_db:g} dB on the best "
                                         f"before it in {cfg.early_stop_patience} measurements every {k} steps "
                                         f"({', '.join(f'{v:.2f}' for v in vals[-cfg.early_stop_patience - 1:])}): "
                                         f"stopped after {it} of {cfg.iterations} steps"})
                    break
            if ckpt is not None and (it % checkpoint_every == 0 or it == cfg.iterations):
                _save_state(ckpt, it, model, opts, dens, sky_opt, rng, history, validation)
        bar.close()
        train_s = time.time() - t0
        pruned = 0
        if cfg.prune_sky_floaters:
            bg = model.graph.background.detach()
            drop = sky_floaters(bg, train)
            pruned = int(drop.sum())
            if pruned:
                model.set_container(0, bg.index(~drop))
        occ_t0 = time.time()
        model.graph.occluders = complete_occluders(model.graph._static_part().detach(),
                                                   capture_views(model.graph, train, settings), cfg.occluders)
        occ_s = time.time() - occ_t0
        ev_test = evaluate(model, test, settings) if test else {"psnr": float("nan"), "ssim": float("nan"), "renders": []}
        ev_train = evaluate(model, train[:: max(1, len(train) // 5)], settings)
        summary = {
            "scene": bundle.name, "iterations": cfg.iterations, "train_seconds": round(train_s, 1),
            "total_seconds": round(time.time() - t0, 1),
            "gaussians": sum(g.num for g in model.containers()),
            "test_psnr": round(ev_test["psnr"], 3), "test_ssim": round(ev_test["ssim"], 4),
            "train_psnr": round(ev_train["psnr"], 3), "train_ssim": round(ev_train["ssim"], 4),
            "threads": cfg.threads, "resumed_from_iteration": start_it - 1, "history": history,
            "priors": (priors.source if use_priors else None), "sky_floaters_pruned": pruned,
            "occluders": model.graph.occluders.num, "occluders_seconds": round(occ_s, 2),
            "iterations_run": stopped_at or cfg.iterations, "early_stopped_at": stopped_at,
            "validation": validation, "skips_fired": fired,
        }
        if out_dir is not None:
            out = Path(out_dir)
            model.save(out / "checkpoint", {"config": _cfg_dict(cfg)})
            (out / "renders").mkdir(parents=True, exist_ok=True)
            frames = []
            for v, r in zip(test, ev_test["renders"]):
                side = torch.cat([v.image, r], 1).numpy()
                write_png(out / "renders" / f"{v.frame_id}.png", side)
                frames.append((side * 255 + 0.5).astype(np.uint8))
            if frames:
                write_mp4(out / "test_renders.mp4", frames)
            from core.stages.chain import write_json

            # NaN (no test frames: test_psnr not measured) -> null: json.dumps wrote a bare NaN
            # token, which strict JSON readers (the dashboard's JSON.parse) reject
            write_json(out / "summary.json", summary)
        return summary
    finally:
        torch.set_num_threads(old_threads)


STATE_FILE = "train_state.pt"


def _save_state(ckpt: Path, it: int, model: VolumeModel, opts, dens, sky_opt, rng, history,
                validation=()) -> None:
    """Write the training state: the scene graph of this iteration first, then the state file
    (atomically, last) naming that graph; older graphs are removed afterwards. A crash at any
    point leaves a state file that names a complete graph."""
    ckpt.mkdir(parents=True, exist_ok=True)
    model.graph.save(ckpt / f"scene_graph.{it}.pt")
    payload = {
        "iteration": it,
        "graph_file": f"scene_graph.{it}.pt",
        "sky": model.sky.state_dict(),
        "sky_opt": sky_opt.state_dict(),
        "opt": [{"m": o.m, "v": o.v, "step": o.step_count} for o in opts],
        "density": [{"grad": d.grad_accum, "count": d.count} for d in dens],
        "rng": rng.bit_generator.state,
        "torch_rng": torch.get_rng_state(),
        "history": history,
        "validation": list(validation),
    }

    with atomic_output(ckpt / STATE_FILE) as tmp:
        torch.save(payload, tmp)
    for old in ckpt.glob("scene_graph.*.pt"):
        if old.name != payload["graph_file"]:
            old.unlink(missing_ok=True)


def _load_state(ckpt: Path) -> dict | None:
    f = ckpt / STATE_FILE
    if not f.is_file():
        return None
    try:
        state = torch.load(f, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - a corrupt state is reported, never silently reset
        raise FormatError(f"{f}: unreadable training state ({exc})") from exc
    if not (ckpt / state["graph_file"]).is_file():
        raise FormatError(f"{f}: its scene graph {state['graph_file']} is missing")
    return state


def _restore(state: dict, model: VolumeModel, opts, dens, sky_opt, rng) -> int:
    model.sky.load_state_dict(state["sky"])
    sky_opt.load_state_dict(state["sky_opt"])
    for o, st in zip(opts, state["opt"]):
        o.m, o.v, o.step_count = st["m"], st["v"], st["step"]
    for d, st in zip(dens, state["density"]):
        d.grad_accum, d.count = st["grad"], st["count"]
    rng.bit_generator.state = state["rng"]
    torch.set_rng_state(state["torch_rng"])
    return int(state["iteration"])


def _cfg_dict(cfg: VolumeSettings) -> dict:
    return json.loads(json.dumps(asdict(cfg)))


def _skips(bundle, stage: str, priors) -> tuple[list[str], bool]:
    """What this scene does not have (:func:`core.stages.chain.scene_skips`) plus how the
    Gaussians start without LiDAR, and whether they must start from the depth prior."""
    out = scene_skips(bundle, stage)
    no_lidar = not bundle.manifest.lidar
    if no_lidar:
        out.append("LiDAR initialisation: Gaussians start from the inverse model's depth prior" if priors is not None
                   else "LiDAR initialisation: no depth prior is available either")
    return out, no_lidar


def run_stage(ctx) -> dict:
    """The chain's entry point (:func:`core.stages.chain.run_stage`) for ``volume`` and
    ``volume2``: priors from the run (the inverse model's, or the latest refined ones), the
    previous graph for ``init_from_graph``, the checkpoint under ``<stage>/resume/``."""
    cfg: VolumeSettings = ctx.settings
    b = ctx.bundle
    wants_priors = any(w > 0 for w in (cfg.lambda_normal, cfg.lambda_albedo, cfg.lambda_roughness,
                                       cfg.lambda_metallic, cfg.lambda_prior_depth))
    priors, source = (None, None)
    if wants_priors or not b.manifest.lidar:
        priors, source = ctx.run.latest_priors(b, ctx.name, threads=cfg.threads)
    skipped, no_lidar = _skips(b, ctx.name, priors)
    init_dir = None
    if cfg.init_from_graph:
        found = ctx.run.latest_graph_dir(before=ctx.name)
        if found is None:
            raise ConfigError(f"stage {ctx.name!r}: init_from_graph needs a finished volume stage in {ctx.run.root}")
        init_dir = found[0]
    sweeps = None
    if no_lidar and not cfg.init_from_graph:
        if priors is None:
            raise ConfigError("bundle: has no LiDAR and no depth prior to initialise the Gaussians from")
        sweeps = sweeps_from_depth(b, {fid: d["depth"] for fid, d in priors.layers.items()})
    total = cfg.iterations
    summary = run_volume(b, cfg, ctx.out_dir, priors=priors if wants_priors else None, init_dir=init_dir,
                         init_sweeps=sweeps, progress=ctx.progress, log_every=max(1, total // 100),
                         checkpoint_dir=ctx.resume_dir, checkpoint_every=max(1, total // 10),
                         on_progress=ctx.on_progress)
    shutil.rmtree(ctx.resume_dir, ignore_errors=True)  # done: the resume state is not needed
    summary["prior_source"] = source if wants_priors else None
    summary["skipped"] = skipped
    summary["seconds"] = summary.get("total_seconds")
    return summary
