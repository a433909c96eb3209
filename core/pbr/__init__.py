"""The physically based rendering pass (paper Sec. 3.2, Eq. 2-3): environment light, the paper's Cook-Torrance
BRDF, Monte Carlo estimators with multiple importance sampling, point and spot lights, and
shadow rays through the Gaussians.

Modules
    :mod:`core.pbr.envmap`      :class:`EnvironmentMap` (lookup, rotation, exposure, sampling)
    :mod:`core.pbr.brdf`        :func:`cook_torrance`, GGX VNDF / cosine sampling and pdfs
    :mod:`core.pbr.mis`         :func:`estimate_reflected` (env-only, BRDF-only, MIS)
    :mod:`core.pbr.lights`      :class:`PointLight`, :class:`SpotLight`, :func:`lights_to_world`,
                                :func:`direct_lighting`
    :mod:`core.pbr.visibility`  :class:`GaussianTracer` (C++ BVH kernel), :func:`visibility_reference`
    :mod:`core.pbr.integrator`  the fused C++ integrator (:func:`integrate`, :class:`VisibilityCache`)
    :mod:`core.pbr.render`      the PBR pass (Eq. 3): :class:`PBRSettings`, :func:`render_pbr`,
                                :class:`ClipRenderer`, :func:`write_frame_exr`, :func:`write_clip_mp4`

The oracle that places Gaussians on a synthetic street's meshes (the pass's agreement with Mitsuba)
is part of the generator: :mod:`core.synth.oracle`.

Directions ``wi`` / ``wo`` point away from the surface; world frame z up, metres; roughness R
and GGX ``alpha = R^2`` are distinct; angles are degrees in the API and radians inside.
"""

from core.pbr.brdf import cook_torrance, face_forward, pdf_brdf, sample_brdf
from core.pbr.envmap import EnvironmentMap
from core.pbr.lights import LightSet, PointLight, SpotLight, direct_lighting, lights_to_world
from core.pbr.mis import estimate_reflected
from core.pbr.visibility import GaussianTracer, TraceSettings, visibility_reference
from core.pbr.render import (ClipRenderer, PBRResult, PBRSettings, render_pbr, sample_pixels,  # noqa: E402
                             write_clip_mp4, write_frame_exr)

__all__ = [
    "EnvironmentMap", "cook_torrance", "face_forward", "sample_brdf", "pdf_brdf", "estimate_reflected",
    "PointLight", "SpotLight", "LightSet", "lights_to_world", "direct_lighting", "GaussianTracer",
    "TraceSettings", "visibility_reference", "ClipRenderer", "PBRResult", "PBRSettings", "render_pbr",
    "sample_pixels", "write_clip_mp4", "write_frame_exr",
]
