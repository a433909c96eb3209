"""Synthetic benchmark generator: procedural streets rendered by Mitsuba 3 as ground truth."""

from core.synth.config import PROFILES, SynthConfig, profile

__all__ = ["PROFILES", "SynthConfig", "profile", "generate_scene"]


def generate_scene(*args, **kwargs):
    """See :func:`core.synth.generate.generate_scene`."""
    from core.synth.generate import generate_scene as _g

    return _g(*args, **kwargs)
