"""The out-of-distribution protocol of the randomised streets, declared once.

:data:`HELD_OUT` names, per axis, a region of :class:`~core.synth.randomise.RandomisationSettings`
that training and validation never draw from. Splits:

- ``train``, ``val``, ``test_id``: every axis inside its training region (``val`` picks models
  and settings; ``test_id`` is the in-distribution figure reported beside the OOD ones). The
  three draw from disjoint seed streams.
- ``test_ood_<axis>``: that axis drawn from its held-out region only, every other axis from its
  training region, so each figure isolates one shift.

:func:`split_spec` makes the spec of scene ``index`` of a split, deterministically; it checks
the result with :func:`held_out_axes`, so a training or validation scene can never fall into a
held-out region (and a test scene always falls into its axis's region).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from core.errors import ConfigError
from core.synth.randomise import SUNSKY, RandomisationSettings, SceneSpec, sample_spec


@dataclass(frozen=True)
class HeldOut:
    """One held-out region: the scene-wide spec field it concerns, and either the held-out
    values (categorical axes) or the held-out interval (lo, hi] of a numeric axis."""

    axis: str
    """Name of the test split's axis (``test_ood_<axis>``)."""
    field: str
    """The :class:`SceneSpec` field (and :class:`RandomisationSettings` field) it constrains."""
    values: tuple[str, ...] = ()
    """Held-out names of a categorical axis."""
    interval: tuple[float, float] | None = None
    """Held-out interval (lo, hi] of a numeric axis; training draws below or at ``lo``."""
    why: str = ""
    """What the region tests."""

    def contains(self, spec: SceneSpec) -> bool:
        """True when ``spec`` lies in this held-out region (for the HDRI axis: lit by a held-out
        HDRI or relit under one)."""
        v = getattr(spec, self.field)
        if self.values:
            if self.field == "light":
                return v in self.values or any(r in self.values for r in spec.relight_envmaps)
            return v in self.values
        lo, hi = self.interval
        return lo < v <= hi


#: The held-out regions, one per axis.
HELD_OUT: dict[str, HeldOut] = {h.axis: h for h in (
    HeldOut("camera_height", "camera_height_m", interval=(2.2, 2.5),
            why="cameras mounted higher than any training capture (vans, roof racks)"),
    HeldOut("hdri", "light", values=("forest",),
            why="a real sky never seen in training, neither as light nor as relit target"),
    HeldOut("palette", "palette", values=("pastel",),
            why="facade colours (saturated pastels) outside the training palettes"),
    HeldOut("layout", "layout", values=("narrow",),
            why="narrow streets with tall buildings: little sky, deep shadows, close facades"),
)}

IN_DISTRIBUTION_SPLITS = ("train", "val", "test_id")
SPLITS = IN_DISTRIBUTION_SPLITS + tuple(f"test_ood_{a}" for a in HELD_OUT)
_SPLIT_IDS = {name: i for i, name in enumerate(SPLITS)}
#: Scenes per split (scene seeds stay distinct across splits and within Mitsuba's 32-bit seeds).
MAX_SCENES = 100_000


def held_out_axes(spec: SceneSpec) -> set[str]:
    """The axes whose held-out region ``spec`` falls into."""
    return {a for a, h in HELD_OUT.items() if h.contains(spec)}


def _training_overrides(settings: RandomisationSettings, skip: str | None = None) -> dict:
    """Settings narrowed to every axis's training region (except ``skip``)."""
    o: dict = {}
    for a, h in HELD_OUT.items():
        if a == skip:
            continue
        if h.axis == "hdri":
            o["hdris"] = tuple(n for n in settings.hdris if n not in h.values)
        elif h.axis == "palette":
            o["facade_palettes"] = tuple(p for p in settings.facade_palettes if p not in h.values)
        elif h.axis == "layout":
            o["layout_styles"] = tuple(s for s in settings.layout_styles if s not in h.values)
        else:
            lo, hi = getattr(settings, h.field)
            o[h.field] = (lo, min(hi, h.interval[0]))
    return o


def _held_out_overrides(settings: RandomisationSettings, axis: str) -> dict:
    """Settings narrowed so that ``axis`` draws from its held-out region only."""
    h = HELD_OUT[axis]
    if axis == "hdri":
        # lit by the held-out HDRI (never the analytic sky); relit targets stay in training
        return {"hdris": h.values, "sky_prob": 0.0}
    if axis == "palette":
        return {"facade_palettes": h.values}
    if axis == "layout":
        return {"layout_styles": h.values}
    lo, hi = h.interval
    r = getattr(settings, h.field)
    lo2, hi2 = max(lo, r[0]), min(hi, r[1])
    if not lo2 < hi2:
        raise ConfigError(f"settings.{h.field}: range {r} does not reach the held-out region ({lo}, {hi}]")
    return {h.field: (lo2 + min(1e-3, (hi2 - lo2) / 2), hi2)}  # clear of lo after rounding


def split_spec(split: str, index: int, settings: RandomisationSettings | None = None) -> SceneSpec:
    """The spec of scene ``index`` (>= 0) of ``split`` (:data:`SPLITS`). Deterministic; distinct
    splits use distinct seed streams and scene seeds."""
    if split not in _SPLIT_IDS:
        raise ConfigError(f"split: unknown split {split!r} (known: {list(SPLITS)})")
    if not 0 <= int(index) < MAX_SCENES:
        raise ConfigError(f"index: must be in [0, {MAX_SCENES}), got {index!r}")
    settings = settings or RandomisationSettings()
    rng = np.random.default_rng(np.random.SeedSequence([int(index), _SPLIT_IDS[split], 0x5EED]))
    scene_seed = _SPLIT_IDS[split] * MAX_SCENES + int(index)  # distinct per split; x1000 fits Mitsuba
    if split in IN_DISTRIBUTION_SPLITS:
        overrides = _training_overrides(settings)
    else:
        axis = split[len("test_ood_"):]
        overrides = {**_training_overrides(settings, skip=axis), **_held_out_overrides(settings, axis)}
        if axis == "hdri":  # relit targets of the held-out HDRI's scenes: the training pool
            pool = _training_overrides(settings)["hdris"]
            spec = sample_spec(settings, scene_seed, split=split, overrides=overrides, rng=rng)
            relight = tuple(n for n in pool if n != spec.light)[: settings.relight_count]
            spec = _replace_relight(spec, relight)
            check_split(spec, split)
            return spec
    # relit targets come from the narrowed pool, so they never include a held-out HDRI
    spec = sample_spec(settings, scene_seed, split=split, overrides=overrides, rng=rng)
    check_split(spec, split)
    return spec


def _replace_relight(spec: SceneSpec, relight: tuple[str, ...]) -> SceneSpec:
    return replace(spec, relight_envmaps=relight)


def check_split(spec: SceneSpec, split: str) -> None:
    """ConfigError unless ``spec`` lies where ``split`` may draw: in no held-out region for the
    in-distribution splits, in exactly its own axis's region for ``test_ood_<axis>``."""
    if split not in _SPLIT_IDS:
        raise ConfigError(f"split: unknown split {split!r} (known: {list(SPLITS)})")
    axes = held_out_axes(spec)
    if split in IN_DISTRIBUTION_SPLITS:
        if axes:
            raise ConfigError(f"spec: split {split} may not lie in held-out regions, this one is in {sorted(axes)}")
        return
    axis = split[len("test_ood_"):]
    if axes != {axis}:
        raise ConfigError(f"spec: split {split} needs held-out axis {axis!r} alone, this one is in {sorted(axes)}")


def describe() -> list[dict]:
    """The protocol as data (for model cards): per axis, the field, the held-out region and why."""
    return [{"axis": h.axis, "split": f"test_ood_{h.axis}", "field": h.field,
             **({"values": list(h.values)} if h.values else {"interval_open_closed": list(h.interval)}),
             "why": h.why} for h in HELD_OUT.values()]


__all__ = [
    "HELD_OUT",
    "IN_DISTRIBUTION_SPLITS",
    "SPLITS",
    "SUNSKY",
    "HeldOut",
    "check_split",
    "describe",
    "held_out_axes",
    "split_spec",
]
