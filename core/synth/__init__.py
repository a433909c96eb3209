"""Synthetic benchmark generator: procedural streets rendered by Mitsuba 3 as ground truth."""

from core.synth.config import PROFILES, SynthConfig, profile
from core.synth.generate import generate_scene

__all__ = ["PROFILES", "SynthConfig", "profile", "generate_scene"]
