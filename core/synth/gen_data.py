"""Training data of the generative models, read from generated scene bundles' ground truth
(:mod:`core.bundle`); in :mod:`core.synth` because it reads ground truth, which the product path
never does.

A *clip* is the frames of one trajectory (``train`` or ``test`` split) of one bundle, in time
order. Every frame is converted once into the contracts' data spaces (:mod:`core.gen.encoding`),
channels-first float32:

    target_ldr [3, H, W]  forward target: the Mitsuba ground truth ``rgb`` (HDR) tone-mapped with
                          the bundle's exposure / gamma, then 2 ldr - 1
    input_ldr  [3, H, W]  forward input: this project's PBR render of the frame (``pbr`` source)
                          or a synthetic Monte-Carlo-like degradation of the ground truth
                          (``degrade`` source: scaffolding and tests only, see :func:`degrade_mc`)
    cond       forward conditioning (normal, depth, albedo, roughness, metallic, env_ldr, env_log,
               env_dir): from the PBR render's own G-buffers when it carries them (the imperfect
               reconstruction, as at inference), else from the ground truth
    gbuffer    [9, H, W]  inverse target: ground-truth G-buffer data space
    rgb        [3, H, W]  inverse conditioning: the bundle's LDR image (``images/``, 8-bit), 2 ldr - 1
    view       [6, H, W]  inverse conditioning (optional contract input): the frame's camera, ray
               directions and world up in the camera frame (:func:`core.gen.encoding.view_conditioning`)
    sky        [1, H, W]  1 = sky (from the bundle's sky mask, or depth 0)

PBR renders (``pbr`` source) are looked up as ``<pbr_root>/<bundle name>/<frame id>.exr`` (layers
as :func:`core.pbr.render.write_frame_exr` writes them: ``rgb`` HDR beauty + G-buffers), with
``pbr_root`` defaulting to ``<bundle>/derived/pbr``. The training session renders them
(16 rays per pixel, reconstructed and perturbed-oracle scenes) before training.

Held-out data: :func:`split_bundles` reads each bundle's generator seed and environment rotation
(``bundle.json`` ``source.config``) and puts every bundle whose seed is in ``held_out_seeds`` or
whose rotation is in ``held_out_rotations`` into the evaluation set, never into training.

:class:`ClipDataset` draws training batches: B windows of F consecutive frames, a random crop
(same position in every frame of a window), optional horizontal flip (x of camera-frame normals
and env directions negated with the pixels). With ``rare_fraction`` > 0 (inverse model), that
fraction of the batch's windows is the rarest-material crop among ``rare_candidates`` random ones
(:func:`rarity_table`): windows, glass, metal-clad facades and paint are a few percent of the
pixels, road and plain walls most of them. With ``rare_loss_max`` > 0 each inverse sample also
carries ``pixel_weight [F, 1, crop, crop]``: its pixels' material weights clipped to
``[1 / rare_loss_max, rare_loss_max]`` (sky 1), which :func:`core.synth.gen_train.edm_loss`
multiplies into the loss.
"""

from __future__ import annotations

import json
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from core.bundle import open_bundle
from core.errors import ConfigError, ShapeError
from core.gen import encoding as E
from core.gen.contract import GBUFFER_CHANNELS, GBUFFER_SLICES
from core.gen.gbuffer_ensemble import NORMAL_X, VIEW_X
from core.io.exr import read_exr
from core.tonemap import hdr_to_ldr

SOURCES = ("pbr", "degrade")
FORWARD_COND = ("normal", "depth", "albedo", "roughness", "metallic", "env_ldr", "env_log", "env_dir")


@dataclass(frozen=True)
class DataSettings:
    """How bundles become training tensors."""

    forward_source: str = "degrade"
    """Forward input: ``"pbr"`` (PBR renders, the real training data) or ``"degrade"``
    (ground truth with synthetic Monte-Carlo noise; scaffolding/tests only)."""
    pbr_root: str | None = None
    """Directory of PBR renders (``<pbr_root>/<bundle name>/<frame id>.exr``); None =
    ``<bundle>/derived/pbr``."""
    degrade_spp: int = 4
    """Samples per pixel imitated by :func:`degrade_mc`."""
    held_out_seeds: tuple[int, ...] = ()
    """Generator seeds reserved for evaluation."""
    held_out_rotations: tuple[float, ...] = ()
    """Environment rotations (degrees) reserved for evaluation."""
    splits: tuple[str, ...] = ("train", "test")
    """Trajectories of a bundle used as clips."""
    max_frames_per_clip: int | None = None
    """Keep only the first n frames of each clip (tests)."""
    seed: int = 0
    """Seed of the synthetic degradation."""

    def __post_init__(self) -> None:
        if self.forward_source not in SOURCES:
            raise ConfigError(f"forward_source: must be one of {SOURCES}, got {self.forward_source!r}")
        if self.degrade_spp < 1:
            raise ConfigError(f"degrade_spp: must be >= 1, got {self.degrade_spp!r}")


def bundle_identity(root: str | Path) -> dict:
    """{name, seed, envmap, rotation} of a bundle, from ``bundle.json`` (None when unknown)."""
    p = Path(root) / "bundle.json"
    try:
        d = json.loads(p.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{p}: not a scene bundle (no bundle.json)") from None
    cfg = (d.get("source") or {}).get("config") or {}
    return {"name": d.get("name"), "seed": cfg.get("seed"), "envmap": cfg.get("envmap"),
            "rotation": cfg.get("envmap_rotation_deg", 0.0)}


def split_bundles(dirs, held_out_seeds=(), held_out_rotations=()) -> tuple[list[Path], list[Path]]:
    """(training bundles, held-out bundles): held out = seed in ``held_out_seeds`` or rotation in
    ``held_out_rotations``."""
    train, held = [], []
    for d in dirs:
        ident = bundle_identity(d)
        rot = float(ident["rotation"] or 0.0)
        if ident["seed"] in set(held_out_seeds) or any(abs(rot - r) < 1e-6 for r in held_out_rotations):
            held.append(Path(d))
        else:
            train.append(Path(d))
    return train, held


def degrade_mc(hdr: np.ndarray, spp: int, rng: np.random.Generator) -> np.ndarray:
    """Monte-Carlo-like noise on a linear HDR image [H, W, 3]: each pixel is the mean of ``spp``
    heavy-tailed unit-mean samples (Gamma(0.5, 2): variance 2, a few bright outliers like
    fireflies) times a mild per-channel colour jitter (Gamma(8, 1/8)); unbiased (mean = hdr)."""
    h, w, _ = hdr.shape
    lum = rng.gamma(0.5, 2.0, size=(h, w, spp)).mean(-1)[..., None]
    col = rng.gamma(8.0, 1.0 / 8.0, size=(h, w, 3))
    return (hdr * lum * col).astype(np.float32)


def _chw(a) -> np.ndarray:
    a = np.asarray(a, np.float32)
    if a.ndim == 2:
        a = a[..., None]
    return np.ascontiguousarray(a.transpose(2, 0, 1))


def load_clips(root: str | Path, settings: DataSettings | None = None, kinds=("forward", "inverse")) -> list[list[dict]]:
    """All clips of one bundle as lists of per-frame dicts of channels-first float32 arrays (module
    docstring). ``kinds`` limits what is built (the env encoding costs ~30 ms a frame)."""
    s = settings or DataSettings()
    b = open_bundle(root, validate=False)
    m = b.manifest
    env = b.load_envmap() if "forward" in kinds else None
    # crc32, not hash(): str hashes are salted per process (PYTHONHASHSEED), which made the degraded
    # inputs - and a test's loss curve - differ from run to run
    rng = np.random.default_rng([s.seed, zlib.crc32(b.name.encode())])
    pbr_root = Path(s.pbr_root) / b.name if s.pbr_root else Path(root) / "derived" / "pbr"
    clips = []
    for split in s.splits:
        frames = sorted(b.frames(split), key=lambda f: f.time_index)
        if s.max_frames_per_clip:
            frames = frames[: s.max_frames_per_clip]
        clip = []
        for fr in frames:
            gt = b.load_ground_truth(fr)
            c2w = fr.cam_to_world
            sky = b.load_sky_mask(fr)
            if sky is None:
                sky = gt["depth"][..., 0] <= 0
            rec = {"id": f"{b.name}/{fr.id}", "sky": _chw(sky.astype(np.float32))}
            n_cam = E.world_to_camera_dirs(gt["normal"], c2w)
            if "inverse" in kinds:
                rec["gbuffer"] = E.encode_gbuffer(gt["albedo"], gt["roughness"], gt["metallic"], n_cam, gt["depth"])
                rec["rgb"] = _chw(E.ldr_to_data(b.load_image(fr)))
                cam = m.cameras[fr.camera]
                rec["view"] = E.view_conditioning(c2w, cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)
            if "forward" in kinds:
                target = hdr_to_ldr(gt["rgb"], m.ldr_exposure, m.ldr_gamma)
                g = gt
                if s.forward_source == "pbr":
                    p = pbr_root / f"{fr.id}.exr"
                    if not p.is_file():
                        raise ConfigError(f"{p}: PBR render missing (forward_source='pbr'; render the "
                                          f"bundle's frames with core.pbr first, or use 'degrade')")
                    pb = read_exr(p)
                    if "rgb" not in pb:
                        raise ShapeError(f"{p}: no 'rgb' layer (has {sorted(pb)})")
                    inp = pb["rgb"]
                    if all(k in pb for k in ("albedo", "roughness", "metallic", "normal", "depth")):
                        g = pb
                else:
                    inp = degrade_mc(gt["rgb"], s.degrade_spp, rng)
                rec["target_ldr"] = _chw(E.ldr_to_data(target))
                rec["input_ldr"] = _chw(E.ldr_to_data(hdr_to_ldr(np.maximum(inp, 0), m.ldr_exposure, m.ldr_gamma)))
                rec.update(E.forward_conditioning(g["albedo"], g["roughness"], g["metallic"], g["normal"],
                                                  g["depth"], c2w, env_hdr=env))
            clip.append(rec)
        if clip:
            clips.append(clip)
    return clips


#: Roughness bin edges of the material bins of :func:`material_bins` (five bins of 0.2); the
#: metallic splits each bin in two at 0.5, so there are ten bins.
RARITY_ROUGH_EDGES = (0.2, 0.4, 0.6, 0.8)
RARITY_BINS = 2 * (len(RARITY_ROUGH_EDGES) + 1)
_ROUGH = GBUFFER_SLICES["roughness"].start
_METAL = GBUFFER_SLICES["metallic"].start


def material_bins(gbuffer: np.ndarray) -> np.ndarray:
    """Material bin per pixel of G-buffers in the data space, ``gbuffer: [..., 9, H, W]`` ->
    ``[..., H, W]`` int64 in ``[0, RARITY_BINS)``: roughness bin (edges ``RARITY_ROUGH_EDGES``)
    times two, plus one where metallic >= 0.5."""
    g = np.asarray(gbuffer)
    if g.ndim < 3 or g.shape[-3] != GBUFFER_CHANNELS:
        raise ShapeError(f"gbuffer: expected [..., {GBUFFER_CHANNELS}, H, W], got {g.shape}")
    rough = (g[..., _ROUGH, :, :] + 1) / 2
    metal = (g[..., _METAL, :, :] + 1) / 2
    return np.digitize(rough, RARITY_ROUGH_EDGES).astype(np.int64) * 2 + (metal >= 0.5)


def rarity_table(clips: list[list[dict]], stride: int = 4) -> np.ndarray:
    """Weight per material bin ``[RARITY_BINS]``: ``freq ** -0.5`` over the non-sky pixels of
    every frame of ``clips`` (every ``stride``-th pixel in x and y), scaled so that the
    pixel-weighted mean weight is 1; a bin no pixel falls in weighs 0."""
    if stride < 1:
        raise ConfigError(f"stride: must be >= 1, got {stride}")
    counts = np.zeros(RARITY_BINS)
    for clip in clips:
        for f in clip:
            b = material_bins(f["gbuffer"][:, ::stride, ::stride])
            keep = f["sky"][0, ::stride, ::stride] < 0.5
            counts += np.bincount(b[keep], minlength=RARITY_BINS)
    if counts.sum() == 0:
        raise ConfigError("rarity_table: the clips have no non-sky pixel")
    freq = counts / counts.sum()
    w = np.where(freq > 0, 1.0 / np.sqrt(np.maximum(freq, 1e-12)), 0.0)
    return w / float((w * freq).sum())


class ClipDataset:
    """Random windows of F frames with random crops from a list of clips (see module docstring).

    ``kind``: ``forward_denoiser`` -> batches with ``x0`` (target), ``x_in`` (PBR input) and the
    forward conditioning; ``inverse_gbuffer`` -> ``x0`` (G-buffer) and ``rgb``. Every tensor is
    [B, F, C, crop, crop] except the env encodings [B, F, 3, 64, 128]."""

    def __init__(self, clips: list[list[dict]], kind: str, frames: int = 1, crop: int = 64, flip: bool = True,
                 view: bool = False, rare_fraction: float = 0.0, rare_candidates: int = 4,
                 rare_loss_max: float = 0.0):
        if kind not in ("forward_denoiser", "inverse_gbuffer"):
            raise ConfigError(f"kind: no dataset for {kind!r}")
        if not 0.0 <= rare_fraction <= 1.0:
            raise ConfigError(f"rare_fraction: must be in [0, 1], got {rare_fraction!r}")
        if rare_candidates < 2:
            raise ConfigError(f"rare_candidates: must be >= 2, got {rare_candidates!r}")
        if rare_loss_max != 0 and not rare_loss_max >= 1:
            raise ConfigError(f"rare_loss_max: must be 0 (off) or >= 1, got {rare_loss_max!r}")
        if (rare_fraction > 0 or rare_loss_max > 0) and kind != "inverse_gbuffer":
            raise ConfigError(f"rare_fraction / rare_loss_max: only the inverse model's data has materials to "
                              f"weigh, not {kind!r}")
        self.rare_fraction, self.rare_candidates, self.rare_loss_max = rare_fraction, rare_candidates, rare_loss_max
        if crop % 8:
            raise ConfigError(f"crop: must be a multiple of 8, got {crop}")
        self.kind, self.frames, self.crop, self.flip, self.view = kind, frames, crop, flip, view
        self.clips = [c for c in clips if len(c) >= frames]
        if not self.clips:
            raise ConfigError(f"no clip has >= {frames} frames ({len(clips)} clip(s) given)")
        h, w = self.clips[0][0]["sky"].shape[1:]
        if crop > min(h, w):
            raise ConfigError(f"crop {crop} larger than the frames ({h}x{w})")
        need = ("target_ldr", "input_ldr", *FORWARD_COND) if kind == "forward_denoiser" else \
            ("gbuffer", "rgb", *(("view",) if view else ()))
        missing = [k for k in need if k not in self.clips[0][0]]
        if missing:
            raise ConfigError(f"clips lack {missing} (load them with kinds including "
                              f"{'forward' if kind == 'forward_denoiser' else 'inverse'})")
        self.rarity = rarity_table(self.clips) if rare_fraction > 0 or rare_loss_max > 0 else None

    def __len__(self) -> int:
        return sum(len(c) - self.frames + 1 for c in self.clips)

    def sample(self, batch: int, rng: np.random.Generator) -> dict[str, torch.Tensor]:
        out: dict[str, list] = {}
        for _ in range(batch):
            clip, t0, y, x, flip = self._draw(rng)
            if self.rare_fraction > 0 and rng.random() < self.rare_fraction:
                cands = [(clip, t0, y, x, flip)] + [self._draw(rng) for _ in range(self.rare_candidates - 1)]
                clip, t0, y, x, flip = max(cands, key=self._crop_rarity)
            win = clip[t0:t0 + self.frames]
            items = self._items(win, y, x, flip)
            for k, v in items.items():
                out.setdefault(k, []).append(v)
        return {k: torch.from_numpy(np.stack(v)) for k, v in out.items()}

    def _draw(self, rng: np.random.Generator) -> tuple:
        """A random window: (clip, first frame, crop y, crop x, flip)."""
        clip = self.clips[rng.integers(len(self.clips))]
        t0 = int(rng.integers(len(clip) - self.frames + 1))
        h, w = clip[0]["sky"].shape[1:]
        y, x = int(rng.integers(h - self.crop + 1)), int(rng.integers(w - self.crop + 1))
        flip = self.flip and bool(rng.integers(2))
        return clip, t0, y, x, flip

    def _crop_rarity(self, cand: tuple) -> float:
        """Mean material weight (:func:`rarity_table`) over the non-sky pixels of a window's crop
        (0 for an all-sky crop)."""
        clip, t0, y, x, _ = cand
        c = self.crop
        num = den = 0.0
        for f in clip[t0:t0 + self.frames]:
            keep = f["sky"][0, y:y + c, x:x + c] < 0.5
            w = self.rarity[material_bins(f["gbuffer"][:, y:y + c, x:x + c])]
            num += float(w[keep].sum())
            den += float(keep.sum())
        return num / den if den > 0 else 0.0

    def _items(self, win, y, x, flip) -> dict[str, np.ndarray]:
        c = self.crop

        def img(key, negate_x=False):
            a = np.stack([f[key][:, y:y + c, x:x + c] for f in win])
            if flip:
                a = a[..., ::-1].copy()
                if negate_x:
                    a[:, 0] *= -1
            return np.ascontiguousarray(a, np.float32)

        def env(key, negate_x=False):
            a = np.stack([f[key] for f in win]).astype(np.float32)
            if flip and negate_x:
                a = a.copy()
                a[:, 0] *= -1
            return a

        if self.kind == "inverse_gbuffer":
            g = img("gbuffer")
            if flip:
                g[:, NORMAL_X] *= -1  # normal x (camera frame) of the G-buffer data space
            out = {"x0": g, "rgb": img("rgb"), "sky": img("sky")}
            if self.rare_loss_max > 0:
                w = np.clip(self.rarity[material_bins(g)], 1 / self.rare_loss_max, self.rare_loss_max)
                out["pixel_weight"] = np.where(out["sky"][:, 0] > 0.5, 1.0, w)[:, None].astype(np.float32)
            if self.view:
                v = img("view")
                if flip:  # a mirrored image is seen by a mirrored camera: x of the ray and of up
                    v[:, list(VIEW_X)] *= -1
                out["view"] = v
            return out
        d = {"x0": img("target_ldr"), "x_in": img("input_ldr"), "sky": img("sky"),
             "normal": img("normal", True), "depth": img("depth"), "albedo": img("albedo"),
             "roughness": img("roughness"), "metallic": img("metallic"),
             "env_ldr": env("env_ldr"), "env_log": env("env_log"), "env_dir": env("env_dir", True)}
        return d
