"""Novel-view-synthesis trainer: the volume stage without generative priors (issue 3).

Fits the scene graph's Gaussians to the training frames with the paper's photometric loss
(L1 + SSIM), opacity-vs-sky BCE and LiDAR depth, with adaptive density control, and evaluates
PSNR / SSIM on the held-out (test) trajectory.
"""

from __future__ import annotations

import json
import math
import time
from typing import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from core.bundle import SceneBundle
from core.conventions import camera_ray_directions, project_points
from core.errors import ConfigError, FormatError
from core.gaussians import Gaussians
from core.raster import RasterSettings, rasterize_gaussians
from core.scene_graph import RigidNode, SceneGraph, transform_gaussians
from core.train.density import DensityConfig, DensityController, scene_extent
from core.train.init_lidar import LidarInitConfig, gaussians_from_lidar
from core.train.optim import GaussianAdam, GaussianLR
from core.train.sky import SkyDome


@dataclass(frozen=True)
class NVSConfig:
    """Settings of the NVS (volume) trainer."""

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
    threads: int = 2
    """CPU threads of the rasterizer kernels."""
    torch_threads: int = 1
    """Intra-op threads of torch for the rest of the step (losses, optimiser). One: the tensors
    are small, and torch's OpenMP workers spin between ops and steal the cores the rasterizer
    threads need (measured: a step 3-10x slower with 2)."""
    seed: int = 0
    """Random seed (frame order, density control)."""
    init: LidarInitConfig = field(default_factory=LidarInitConfig)
    """LiDAR initialisation."""
    density: DensityConfig = field(default_factory=DensityConfig)
    """Adaptive density control."""
    lr: GaussianLR = field(default_factory=GaussianLR)
    """Learning rates."""


NVS_PROFILES = {
    "tiny": NVSConfig(iterations=60, densify_from=20, densify_until=50, densify_every=15,
                      init=LidarInitConfig(max_background_points=3000, max_object_points=300)),
    "quick": NVSConfig(density=DensityConfig(max_gaussians=80_000)),
    "benchmark": NVSConfig(iterations=7000, densify_until=4000, opacity_reset_every=3000),
}


@dataclass
class _View:
    frame_id: str
    time: float
    cam_to_world: torch.Tensor
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
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
        dirs = torch.from_numpy(camera_ray_directions(f.cam_to_world, cam.fx, cam.fy, cam.cx, cam.cy,
                                                      cam.width, cam.height)).float()
        lpx = lz = None
        if with_lidar and any(s.time_index == f.time_index for s in m.lidar):
            pts = bundle.load_lidar(f.time_index)[:, 3:].astype(np.float64)
            uv, z = project_points(pts, f.cam_to_world, cam.fx, cam.fy, cam.cx, cam.cy)
            ok = (z > 0.5) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
            px = uv[ok, 1].astype(np.int64) * cam.width + uv[ok, 0].astype(np.int64)
            # keep the nearest point per pixel (LiDAR sees past thin occluders the camera sees)
            order = np.argsort(z[ok])
            px_s, z_s = px[order], z[ok][order]
            _, first = np.unique(px_s, return_index=True)
            lpx, lz = torch.from_numpy(px_s[first]), torch.from_numpy(z_s[first]).float()
        out.append(_View(f.id, m.times[f.time_index], torch.tensor(f.cam_to_world, dtype=torch.float32),
                         cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, img, nonsky, dirs, lpx, lz))
    return out


class NVSModel:
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
        out = rasterize_gaussians(world, v.cam_to_world, v.fx, v.fy, v.cx, v.cy, v.width, v.height,
                                  settings=settings)
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


def evaluate(model: NVSModel, views: list[_View], settings: RasterSettings) -> dict:
    """Mean PSNR / SSIM of the renders of ``views`` against their frames, plus the renders."""
    from core.metrics import psnr, ssim

    ps, ss, renders = [], [], []
    with torch.no_grad():
        for v in views:
            rgb, *_ = model.render(v, settings)
            rgb = rgb.clamp(0, 1)
            ps.append(float(psnr(rgb, v.image)))
            ss.append(float(ssim(rgb, v.image)))
            renders.append(rgb)
    return {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)), "per_frame_psnr": ps, "renders": renders}


def train_nvs(bundle: SceneBundle, cfg: NVSConfig, out_dir: str | Path | None = None, *,
              progress: bool = True, log_every: int = 50, checkpoint_dir: str | Path | None = None,
              checkpoint_every: int = 500, on_progress: Callable[[int, int, dict], None] | None = None) -> dict:
    """Train on the bundle's train split; evaluate on its test split. Returns a summary dict
    (held-out PSNR/SSIM, train PSNR, Gaussians, seconds) and writes renders, a checkpoint and
    ``summary.json`` into ``out_dir`` when given.

    ``checkpoint_dir``: the full training state (Gaussians, sky, optimiser moments, density
    statistics, random state, loss history) is saved there every ``checkpoint_every`` steps, and a
    run started with a directory that holds a state resumes from it: a crashed or killed run
    continues where its last checkpoint left off. ``on_progress(it, iterations, record)`` is
    called every ``log_every`` steps (an exception raised there stops the run, e.g. a cancel)."""
    from tqdm import tqdm

    from core.metrics import ssim

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
        if state is not None:
            graph = SceneGraph.load(ckpt / state["graph_file"])
        else:
            bg, nodes = gaussians_from_lidar(bundle, cfg.init)
            graph = SceneGraph.from_bundle_objects(bundle.manifest, bg, nodes)
        model = NVSModel(graph, SkyDome(64, 128, _mean_sky_colour(train)))
        settings = RasterSettings(threads=cfg.threads)
        extent = scene_extent(torch.stack([v.cam_to_world[:3, 3] for v in train]))
        opts = [GaussianAdam(g, cfg.lr) for g in model.containers()]
        dens = [DensityController(cfg.density, extent, g.num) for g in model.containers()]
        sky_opt = torch.optim.Adam(model.sky.parameters(), lr=cfg.sky_lr)
        history = []
        start_it = 1
        if state is not None:
            start_it = _restore(state, model, opts, dens, sky_opt, rng) + 1
            history = state["history"]
        bar = tqdm(range(start_it, cfg.iterations + 1), desc="train nvs", unit="it", disable=not progress,
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
                d = out.depth.reshape(-1)[v.lidar_px]
                loss = loss + cfg.lambda_depth * (d - v.lidar_z).abs().mean()
            if not torch.isfinite(loss):
                raise ConfigError(f"training diverged at iteration {it} (loss {float(loss)})")
            loss.backward()
            decay = cfg.means_lr_decay ** (it / cfg.iterations)
            for o in opts:
                o.step({"means": decay})
            sky_opt.step()
            in_window = cfg.densify_from <= it <= cfg.densify_until
            if in_window and world.means.grad is not None:
                w2c = torch.linalg.inv(v.cam_to_world.double())
                for ci, start, cnt in spans:
                    dens[ci].accumulate(world.means.grad[start:start + cnt], world.means.detach()[start:start + cnt],
                                        w2c, v.fx, v.fy, v.width, v.height)
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
                                "s": round(time.time() - t0, 2)})
                bar.set_postfix(loss=f"{float(loss.detach()):.4f}", n=n)
                if on_progress is not None:
                    on_progress(it, cfg.iterations, history[-1])
            if ckpt is not None and (it % checkpoint_every == 0 or it == cfg.iterations):
                _save_state(ckpt, it, model, opts, dens, sky_opt, rng, history)
        train_s = time.time() - t0
        ev_test = evaluate(model, test, settings) if test else {"psnr": float("nan"), "ssim": float("nan"), "renders": []}
        ev_train = evaluate(model, train[:: max(1, len(train) // 5)], settings)
        summary = {
            "scene": bundle.name, "iterations": cfg.iterations, "train_seconds": round(train_s, 1),
            "total_seconds": round(time.time() - t0, 1),
            "gaussians": sum(g.num for g in model.containers()),
            "test_psnr": round(ev_test["psnr"], 3), "test_ssim": round(ev_test["ssim"], 4),
            "train_psnr": round(ev_train["psnr"], 3), "train_ssim": round(ev_train["ssim"], 4),
            "threads": cfg.threads, "resumed_from_iteration": start_it - 1, "history": history,
        }
        if out_dir is not None:
            from core.io.images import write_png
            from core.io.video import write_mp4

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
            (out / "summary.json").write_text(json.dumps(summary, indent=1))
        return summary
    finally:
        torch.set_num_threads(old_threads)


STATE_FILE = "train_state.pt"


def _save_state(ckpt: Path, it: int, model: NVSModel, opts, dens, sky_opt, rng, history) -> None:
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
    }
    tmp = ckpt / (STATE_FILE + ".tmp")
    torch.save(payload, tmp)
    tmp.replace(ckpt / STATE_FILE)
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


def _restore(state: dict, model: NVSModel, opts, dens, sky_opt, rng) -> int:
    model.sky.load_state_dict(state["sky"])
    sky_opt.load_state_dict(state["sky_opt"])
    for o, st in zip(opts, state["opt"]):
        o.m, o.v, o.step_count = st["m"], st["v"], st["step"]
    for d, st in zip(dens, state["density"]):
        d.grad_accum, d.count = st["grad"], st["count"]
    rng.bit_generator.state = state["rng"]
    torch.set_rng_state(state["torch_rng"])
    return int(state["iteration"])


def _cfg_dict(cfg: NVSConfig) -> dict:
    return json.loads(json.dumps(asdict(cfg)))
