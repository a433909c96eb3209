"""The scene corrector: a small per-scene network that corrects the denoised PBR frame, fitted on
the capture alone (a departure from the paper, ``docs/DESIGN.md``).

The PBR pass of a reconstruction misses what the reconstruction got wrong in a way its G-buffers
predict: albedo that baked the capture's sun in, walls the approximate bounce leaves too dark,
glass whose reflections it cannot trace. The shipped forward model, trained on other streets,
cannot learn a given street's own mistakes (``benchmarks/results/forward_ceiling.json``: +0.1 dB
over OIDN across streets). The capture can: the training views re-rendered under the recovered
map should reproduce the captured frames. The corrector is fitted there, on the denoised PBR
frame and the frame's G-buffers against the captured frame, and applied to later renders of the
scene under that same light (a new path, an edit), where it sees that render's own G-buffers and
LDR frame. It learns the capture's light along with the reconstruction's mistakes, so it is not
applied under another map, rotation, sky scale or added lights (:attr:`SceneCorrector.fitted_light`,
:func:`light_fingerprint`): on three development streets it made every relit FLIP worse
(``benchmarks/results/corrector.json``).

    features [H, W, 13] = LDR frame (3, denoised, [0, 1]) | albedo (3) | camera-frame normal (3) |
                          roughness | metallic | opacity | log(1 + depth / 1 m)
    corrected = clip(LDR + head(body(features)), 0, 1)

``body``: eight 3x3 convolutions dilated 1, 2, 4, 8, 8, 4, 2, 1 (receptive field 61 px) with
GELU; ``head``: a 1x1 convolution to RGB, zero at the start (the corrector starts as the identity).
Fitted by Adam with a cosine schedule on random crops, L1 loss. The network is a few tens of
thousands of weights, kept with the run (``<run>/corrector/corrector.pt``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from core.errors import ConfigError, ModelLoadError, NumericalError, ShapeError
from core.numerics import safe_normalize

#: Feature channels, in order (the network's input).
FEATURES = ("ldr_r", "ldr_g", "ldr_b", "albedo_r", "albedo_g", "albedo_b", "normal_cam_x", "normal_cam_y",
            "normal_cam_z", "roughness", "metallic", "opacity", "log1p_depth_m")
#: Dilations of the body's convolutions (receptive field 1 + 2 * sum = 61 px).
DILATIONS = (1, 2, 4, 8, 8, 4, 2, 1)
FORMAT = "brdfusion-scene-corrector"


@dataclass(frozen=True)
class CorrectorSettings:
    """How the scene corrector is built and fitted."""

    width: int = 32
    """Channels of the body's convolutions."""
    steps: int = 800
    """Adam steps (each a batch of random crops of the training views)."""
    crop: int = 64
    """Side of the square crops, pixels (at most the frame's smaller side)."""
    batch: int = 4
    """Crops per step."""
    lr: float = 1e-3
    """Adam learning rate (cosine-annealed to 0 over ``steps``)."""
    seed: int = 0
    """Seed of the weights and the crops."""

    def __post_init__(self) -> None:
        bad = [n for n, ok in (("width", isinstance(self.width, int) and 1 <= self.width <= 512),
                               ("steps", isinstance(self.steps, int) and self.steps >= 0),
                               ("crop", isinstance(self.crop, int) and 8 <= self.crop <= 4096),
                               ("batch", isinstance(self.batch, int) and self.batch >= 1),
                               ("lr", isinstance(self.lr, (int, float)) and math.isfinite(self.lr) and self.lr > 0))
               if not ok]
        if bad:
            raise ConfigError(f"CorrectorSettings: out of range: {', '.join(bad)} ({self})")


class SceneCorrector(torch.nn.Module):
    """Dilated CNN: features ``[B, C, H, W]`` (the LDR frame first; ``C`` = ``channels``, the
    13 :data:`FEATURES` by default) -> corrected LDR ``[B, 3, H, W]`` (module docstring)."""

    def __init__(self, width: int = 32, channels: int = len(FEATURES)):
        super().__init__()
        layers, c = [], channels
        for d in DILATIONS:
            layers += [torch.nn.Conv2d(c, width, 3, padding=d, dilation=d), torch.nn.GELU()]
            c = width
        self.body = torch.nn.Sequential(*layers)
        self.head = torch.nn.Conv2d(width, 3, 1)
        torch.nn.init.zeros_(self.head.weight)
        torch.nn.init.zeros_(self.head.bias)
        self.width = width
        self.fitted_light: str | None = None
        """:func:`light_fingerprint` of the environment map it was fitted under (set by
        :func:`load_corrector` from the file, or by :func:`core.render.scenario.scene_corrector`
        for a file written before it was recorded); None: unknown, and the caller vouches that its
        renders are under the fitted light."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x[:, :3] + self.head(self.body(x))


def frame_features(ldr: np.ndarray, gbuffers: dict, world_to_cam: np.ndarray) -> np.ndarray:
    """Features ``[H, W, 13]`` float32 of one rendered frame (module docstring).

    ``ldr``: ``[H, W, 3]`` in [0, 1] (the denoised frame); ``gbuffers``: the PBR pass's layers
    (:class:`core.pbr.render.PBRResult` ``gbuffers``: ``albedo`` [H, W, 3], ``normal`` [H, W, 3]
    world, ``roughness``, ``metallic``, ``opacity``, ``depth`` [H, W, 1], depth in metres);
    ``world_to_cam``: ``[3, 3]`` rotation. Raises ShapeError naming a missing or misshapen layer."""
    ldr = np.asarray(ldr, np.float32)
    if ldr.ndim != 3 or ldr.shape[-1] != 3:
        raise ShapeError(f"ldr: expected [H, W, 3], got {list(ldr.shape)}")
    h, w = ldr.shape[:2]
    layers = {}
    for k, c in (("albedo", 3), ("normal", 3), ("roughness", 1), ("metallic", 1), ("opacity", 1), ("depth", 1)):
        if k not in gbuffers:
            raise ShapeError(f"gbuffers: missing layer {k!r} (has {sorted(gbuffers)})")
        t = gbuffers[k]
        a = t.detach().to(torch.float32).numpy() if isinstance(t, torch.Tensor) else np.asarray(t, np.float32)
        if a.shape != (h, w, c):
            raise ShapeError(f"gbuffers[{k!r}]: expected {[h, w, c]}, got {list(a.shape)}")
        layers[k] = a
    r = np.asarray(world_to_cam, np.float32)
    if r.shape != (3, 3):
        raise ShapeError(f"world_to_cam: expected [3, 3], got {list(r.shape)}")
    n_cam = safe_normalize(torch.from_numpy(layers["normal"] @ r.T)).numpy()
    feats = [np.clip(ldr, 0, 1), np.clip(layers["albedo"], 0, 1), n_cam, np.clip(layers["roughness"], 0, 1),
             np.clip(layers["metallic"], 0, 1), np.clip(layers["opacity"], 0, 1),
             np.log1p(np.clip(layers["depth"], 0, None))]
    out = np.concatenate(feats, -1).astype(np.float32)
    if not np.isfinite(out).all():
        raise NumericalError("frame_features: non-finite G-buffer values (albedo, normal, depth...)")
    return out


def _check_pairs(features: Sequence[np.ndarray], targets: Sequence[np.ndarray]) -> None:
    if not features or len(features) != len(targets):
        raise ConfigError(f"features / targets: need the same number (>= 1) of frames, got {len(features)} / "
                          f"{len(targets)}")
    for i, (x, y) in enumerate(zip(features, targets)):
        if x.ndim != 3 or x.shape[-1] != len(FEATURES):
            raise ShapeError(f"features[{i}]: expected [H, W, {len(FEATURES)}], got {list(x.shape)}")
        if y.shape != x.shape[:2] + (3,):
            raise ShapeError(f"targets[{i}]: expected {list(x.shape[:2]) + [3]}, got {list(y.shape)}")


def fit_corrector(features: Sequence[np.ndarray], targets: Sequence[np.ndarray], settings: CorrectorSettings,
                  *, net: SceneCorrector | None = None, optimizer: torch.optim.Adam | None = None, start_step: int = 0,
                  on_step: Callable[[int, float], None] | None = None) -> tuple[SceneCorrector, torch.optim.Adam]:
    """Fit (or continue fitting, from ``net`` / ``optimizer`` (Adam over ``net``) after
    ``start_step`` steps) the corrector
    on ``features`` ([H, W, 13]) against ``targets`` ([H, W, 3] captured LDR frames, [0, 1]).
    ``on_step(step, loss)`` after each step (checkpoints, progress; may raise to stop). Raises
    NumericalError naming the step when the loss turns non-finite."""
    s = settings
    _check_pairs(features, targets)
    crop = min(s.crop, min(min(x.shape[:2]) for x in features))
    g = torch.Generator().manual_seed(s.seed)
    if net is None:
        torch.manual_seed(s.seed)
        net = SceneCorrector(s.width)
    opt = optimizer if optimizer is not None else torch.optim.Adam(net.parameters(), lr=s.lr)
    xs = [torch.from_numpy(np.ascontiguousarray(x, np.float32)).permute(2, 0, 1) for x in features]
    ys = [torch.from_numpy(np.ascontiguousarray(y, np.float32)).permute(2, 0, 1) for y in targets]
    for step in range(start_step + 1, s.steps + 1):
        # crops of step k are drawn from a generator seeded by (seed, k): a resumed fit draws what
        # an uninterrupted one does
        g.manual_seed(s.seed * 1_000_003 + step)
        bx, by = [], []
        for _ in range(s.batch):
            i = int(torch.randint(len(xs), (1,), generator=g))
            h, w = xs[i].shape[1:]
            y0 = int(torch.randint(h - crop + 1, (1,), generator=g))
            x0 = int(torch.randint(w - crop + 1, (1,), generator=g))
            bx.append(xs[i][:, y0:y0 + crop, x0:x0 + crop])
            by.append(ys[i][:, y0:y0 + crop, x0:x0 + crop])
        for pg in opt.param_groups:  # cosine annealing from lr to 0 (a function of the step: resumable)
            pg["lr"] = 0.5 * s.lr * (1 + math.cos(math.pi * (step - 1) / max(1, s.steps)))
        loss = (net(torch.stack(bx)) - torch.stack(by)).abs().mean()
        if not torch.isfinite(loss):
            raise NumericalError(f"scene corrector: non-finite loss at step {step}")
        opt.zero_grad()
        loss.backward()
        opt.step()
        if on_step is not None:
            on_step(step, float(loss.detach()))
    return net, opt


def apply_corrector(net: SceneCorrector, features: np.ndarray) -> np.ndarray:
    """The corrected LDR frame ``[H, W, 3]`` in [0, 1] of one frame's features ``[H, W, 13]``."""
    if features.ndim != 3 or features.shape[-1] != len(FEATURES):
        raise ShapeError(f"features: expected [H, W, {len(FEATURES)}], got {list(features.shape)}")
    with torch.no_grad():
        y = net(torch.from_numpy(np.ascontiguousarray(features, np.float32)).permute(2, 0, 1)[None])[0]
    out = y.permute(1, 2, 0).clamp(0, 1).numpy()
    if not np.isfinite(out).all():
        raise NumericalError("scene corrector: non-finite output")
    return out


def light_fingerprint(envmap) -> str:
    """SHA-256 (hex) of an environment map ``[H, W, 3]`` as float32, shape included: which light a
    corrector was fitted under. Raises ShapeError for anything but an ``[H, W, 3]`` array."""
    import hashlib

    env = np.ascontiguousarray(np.asarray(envmap, np.float32))
    if env.ndim != 3 or env.shape[-1] != 3:
        raise ShapeError(f"envmap: expected [H, W, 3], got {env.shape}")
    h = hashlib.sha256(repr(env.shape).encode())
    h.update(env.tobytes())
    return h.hexdigest()


def save_corrector(path: str | Path, net: SceneCorrector, settings: CorrectorSettings, meta: dict | None = None) -> None:
    """Write the corrector (weights, settings, ``meta``) to ``path`` atomically."""
    from core.io.atomic import atomic_output

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(p) as tmp:
        torch.save({"format": FORMAT, "version": 1, "features": list(FEATURES), "settings": asdict(settings),
                    "state": net.state_dict(), "meta": meta or {}}, tmp)


def load_corrector(path: str | Path) -> SceneCorrector:
    """The corrector saved at ``path``; ModelLoadError naming the file when it is missing, not a
    corrector, or made for other features."""
    p = Path(path)
    if not p.is_file():
        raise ModelLoadError(f"{p}: no scene corrector here")
    try:
        d = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is reported as such
        raise ModelLoadError(f"{p}: unreadable scene corrector ({exc})") from exc
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise ModelLoadError(f"{p}: not a scene corrector (format {d.get('format') if isinstance(d, dict) else None!r})")
    if list(d.get("features", [])) != list(FEATURES):
        raise ModelLoadError(f"{p}: made for features {d.get('features')}, this build uses {list(FEATURES)}")
    net = SceneCorrector(int(d["settings"]["width"]))
    try:
        net.load_state_dict(d["state"])
    except Exception as exc:  # noqa: BLE001
        raise ModelLoadError(f"{p}: weights do not fit the network ({exc})") from exc
    net.eval()
    light = (d.get("meta") or {}).get("fitted_light")
    net.fitted_light = light if isinstance(light, str) else None
    return net


__all__ = ["FEATURES", "CorrectorSettings", "SceneCorrector", "frame_features", "fit_corrector", "apply_corrector",
           "light_fingerprint", "save_corrector", "load_corrector"]
