"""Heights of the walls whose tops the capture never saw, chosen by the capture's own shading.

A forward camera never sees the roofs of the walls beside and behind its first position. It also
misses the roofs of facades that rise above its frames' top edge and that no frame saw end against
the sky. The occluders (:mod:`core.stages.occluders`) guess those heights from the roof lines the
side showed elsewhere. Any roof line counts, including one the depth test stopped at a window.
The guess decides where the street lies in shadow, and so which sun the lighting prior finds.
An example, the default scene's quick reconstruction (development):

* the right-hand wall beside and behind the first frame was capped at 6.0 m;
* the true building there stands above 13.6 m;
* at the true sun, the occluders lit 54% of the ground pixels that lie in that building's shadow;
* the prior's sun search ended 35.1 deg off.

The depth test that carves the facade columns has a blind spot of its own: it reads a window's
reflection, reconstructed metres behind the glass, as free space, and stops the facade below its
roof (on dev1, windows of the right-hand buildings stopped the walls whose shadow lies on the road).

Here the capture decides. The prior's sun search runs once per hypothesis of :data:`HYPOTHESES`
(each side's unseen walls at their guessed height or at ``max_height_m``; the wall lines carved by
the depth test or by sky pixels only), every time over the same surface samples. The hypothesis
whose best sun leaves the smallest shading residual wins, and its sun and sky are the prior's.
Whose occluders cast the shadows afterwards is :attr:`core.stages.pbr_settings.PBRStageConfig.wall_shadows`:

* ``"auto"`` (the default): the winner's walls when its residual beats the guess's by at least
  ``wall_shadows_min_gain``, else the guess's (below);
* ``"guess"``: the volume stage's own occluders, for the rest of the pbr stage, the joint stage and
  every later render. A winning hypothesis's walls stand at ``max_height_m`` where the true
  buildings may be half as tall, and their shadows darkened relit streets (dev3: the courtyard
  road at 0.06-0.27x Mitsuba's light);
* ``"chosen"``: the winner's occluders. Whenever they cast the shadows, the pbr stage writes them
  to ``<run>/pbr/occluders.pt`` (:func:`save_occluders`) and
  :meth:`core.stages.chain.RunDir.load_scene` applies them.

Not in the paper: its capture saw the facades whole.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from core.camera import Camera
from core.errors import ConfigError
from core.gaussians import Gaussians
from core.io.atomic import atomic_output
from core.io.torchfile import read_torch_file
from core.stages.occluders import TALL_UNSEEN, OccluderSettings, complete_occluders

#: The hypotheses, in order of preference on a tie (the volume stage's guess first): which sides'
#: unseen walls stand ``max_height_m`` tall (:attr:`OccluderSettings.tall_unseen`), and with
#: ``sky``, facade columns on the wall lines carved by sky pixels only
#: (:attr:`OccluderSettings.wall_line_sky_only`: the depth test reads a window's reflection as free
#: space and stops a facade below its roof).
HYPOTHESES = TALL_UNSEEN + tuple("sky" if t == "none" else f"sky+{t}" for t in TALL_UNSEEN)
#: File of the chosen occluders in a stage directory.
OCCLUDERS_FILE = "occluders.pt"
_FORMAT = "brdfusion-occluders"
_VERSION = 1


@dataclass(frozen=True)
class CaptureFrame:
    """What :func:`core.stages.occluders.capture_views` needs of a frame."""

    camera: Camera
    """The frame's camera, pose in float32 (the Gaussians' dtype)."""
    time: float
    """Seconds (the bundle's ``times`` of the frame)."""
    nonsky: torch.Tensor | None
    """[H, W, 1] float, 1 = surface (the bundle's sky mask), or None."""


def capture_frames(bundle, split: str = "train") -> list[CaptureFrame]:
    """The frames of ``split`` as the volume stage hands them to the occluders (its sky masks;
    never ground truth)."""
    frames = bundle.frames(split)
    if not frames:
        raise ConfigError(f"bundle: no {split!r} frames to build occluders from")
    out = []
    for f in frames:
        sky = bundle.load_sky_mask(f)
        nonsky = None if sky is None else torch.from_numpy(~np.asarray(sky, bool)).float()[..., None]
        cam = Camera.from_bundle(bundle.camera(f), f).to(torch.float32)
        out.append(CaptureFrame(cam, float(bundle.manifest.times[f.time_index]), nonsky))
    return out


def hypothesis_settings(settings: OccluderSettings, hypothesis: str) -> OccluderSettings:
    """``settings`` under one of :data:`HYPOTHESES`."""
    if hypothesis not in HYPOTHESES:
        raise ConfigError(f"hypothesis: expected one of {HYPOTHESES}, got {hypothesis!r}")
    sky = hypothesis.startswith("sky")
    side = hypothesis.split("+", 1)[1] if "+" in hypothesis else ("none" if sky else hypothesis)
    return replace(settings, tall_unseen=side, wall_line_sky_only=settings.wall_line_sky_only or sky)


def hypothesis_occluders(graph, views, settings: OccluderSettings) -> dict[str, Gaussians]:
    """Occluders of ``graph`` per hypothesis of :data:`HYPOTHESES` (name -> shadow-only Gaussians).

    ``"none"`` is the graph's own occluders, as its volume stage built them with ``settings``.
    The others are rebuilt from the graph's static part with :func:`hypothesis_settings`.
    ``views`` are the (camera, sky, depth) tuples of :func:`core.stages.occluders.capture_views`.
    """
    if not isinstance(settings, OccluderSettings):
        raise ConfigError(f"settings: expected OccluderSettings, got {type(settings).__name__}")
    own = graph.occluders if graph.occluders is not None else Gaussians.empty(graph.background.dtype)
    out = {"none": own.detach()}
    static = graph._static_part().detach()
    for h in HYPOTHESES[1:]:
        out[h] = complete_occluders(static, views, hypothesis_settings(settings, h))
    return out


def choose(residuals: dict[str, float], min_gain: float = 0.0) -> str:
    """The first hypothesis of :data:`HYPOTHESES` (the guess first, then one change, ...)
    whose finite residual is within a factor ``1 + min_gain`` of the smallest: a side is lifted
    only when that explains the capture's shading better by more than ``min_gain`` (relative).
    ConfigError when no residual is finite (no search found a sun) or ``min_gain`` < 0."""
    bad = [k for k in residuals if k not in HYPOTHESES]
    if bad:
        raise ConfigError(f"residuals: unknown hypotheses {bad} (expected some of {HYPOTHESES})")
    if not (isinstance(min_gain, (int, float)) and math.isfinite(min_gain) and min_gain >= 0):
        raise ConfigError(f"min_gain: expected a finite number >= 0, got {min_gain!r}")
    finite = {k: float(v) for k, v in residuals.items() if v is not None and math.isfinite(v)}
    if not finite:
        raise ConfigError("residuals: no hypothesis has a finite residual")
    best = min(finite.values())
    return next(h for h in HYPOTHESES if h in finite and finite[h] <= best * (1.0 + min_gain))


def save_occluders(path: str | Path, occluders: Gaussians, meta: dict) -> None:
    """Write the chosen occluders (world frame, metres) and ``meta`` (how they were chosen)."""
    payload = {"format": _FORMAT, "version": _VERSION, "meta": dict(meta),
               "occluders": {k: v.detach().cpu().contiguous() for k, v in occluders.tensors().items()}}
    with atomic_output(Path(path)) as tmp:
        torch.save(payload, tmp)


def load_occluders(path: str | Path) -> Gaussians:
    """The occluders written by :func:`save_occluders`; FormatError names a bad file."""
    d = read_torch_file(path, _FORMAT, (_VERSION,), "occluders file")
    return Gaussians(**d["occluders"])


__all__ = ["HYPOTHESES", "OCCLUDERS_FILE", "CaptureFrame", "capture_frames", "choose", "hypothesis_occluders",
           "hypothesis_settings", "load_occluders", "save_occluders"]
