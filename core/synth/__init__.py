"""Synthetic benchmark generator: procedural streets rendered by Mitsuba 3 as ground truth, and
everything that reads that ground truth (the one package that does; the product path never
imports it): the evaluation (``evaluate``), the generative models' training data and training
(``gen_data``, ``gen_train``), the dataset export (``export``), the oracle scenes (``oracle``,
``prepare``)."""

from core.synth.config import PROFILES, SynthConfig, profile
from core.synth.generate import generate_scene

__all__ = ["PROFILES", "SynthConfig", "profile", "generate_scene"]
