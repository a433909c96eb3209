"""Settings of the physically based stages: :class:`StageShading` (how the pbr and joint stages
render their physical term, as a relight renders it) and :class:`PBRStageConfig` (the
lighting-only pbr stage, :mod:`core.stages.pbr`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from core.errors import ConfigError
from core.lighting.prior_gains import PriorGainSettings
from core.lighting.sky_evidence import SkyEvidenceSettings
from core.pbr.brdf import DIFFUSE_MODELS, MASKING_MODELS
from core.pbr.render import (PRODUCT_DIFFUSE, PRODUCT_INDIRECT_SPECULAR_RAYS, PRODUCT_MASKING, PRODUCT_OPAQUE_ABOVE,
                             PBRSettings)
from core.pbr.visibility import TraceSettings

@dataclass(frozen=True)
class StageShading:
    """How the pbr and joint stages render their physical term: as a relight renders it
    (:class:`core.render.scenario.Scenario`), so the map is fitted under the visibility and the
    indirect light it is rendered with. Both stages' settings extend this."""

    shadow_t_min_m: float = 0.5
    """Shadow rays of the stage ignore Gaussians nearer than this, metres
    (:attr:`core.render.scenario.Scenario.shadow_t_min_m`)."""
    normal_offset_m: float = 0.1
    """Shadow rays start this far along the normal, metres
    (:attr:`core.render.scenario.Scenario.normal_offset_m`)."""
    indirect_bounces: int = 2
    """Approximate diffuse bounces of the PBR pass (:attr:`core.pbr.render.PBRSettings.indirect_bounces`;
    0 = direct light only, the paper)."""
    indirect_specular_rays: int = PRODUCT_INDIRECT_SPECULAR_RAYS
    """GGX shadow rays per pixel of the specular bounce of the stage's PBR pass
    (:attr:`core.pbr.render.PBRSettings.indirect_specular_rays`; as a relight renders it)."""
    diffuse: str = PRODUCT_DIFFUSE
    """The BRDF's diffuse lobe of the stage's PBR pass (:attr:`core.pbr.render.PBRSettings.diffuse`;
    the one a relight renders with, :attr:`core.render.scenario.Scenario.diffuse`)."""
    opaque_above: float = PRODUCT_OPAQUE_ABOVE
    """Surface pixels of the stage's PBR pass (:attr:`core.pbr.render.PBRSettings.opaque_above`;
    as a relight renders them)."""
    masking: str = PRODUCT_MASKING
    """The BRDF's masking term of the stage's PBR pass (:attr:`core.pbr.render.PBRSettings.masking`;
    the one a relight renders with, :attr:`core.render.scenario.Scenario.masking`)."""

    def shading_errors(self) -> list[str]:
        """Names of the out-of-range shading fields."""
        b = self.indirect_bounces
        return [n for n, ok in (("shadow_t_min_m", 0 <= self.shadow_t_min_m <= 100),
                                ("normal_offset_m", 0 <= self.normal_offset_m <= 10),
                                ("indirect_bounces", isinstance(b, int) and not isinstance(b, bool) and 0 <= b <= 16),
                                ("indirect_specular_rays", isinstance(self.indirect_specular_rays, int)
                                 and not isinstance(self.indirect_specular_rays, bool)
                                 and 0 <= self.indirect_specular_rays <= 1024),
                                ("diffuse", self.diffuse in DIFFUSE_MODELS),
                                ("masking", self.masking in MASKING_MODELS),
                                ("opaque_above", 0 < self.opaque_above <= 1))
                if not ok]

    def trace_settings(self) -> TraceSettings:
        """The shadow rays of the stage."""
        return TraceSettings(leaf_size=16, t_min=self.shadow_t_min_m)

    def pbr_settings(self, **kw) -> PBRSettings:
        """The stage's (differentiable, torch) PBR pass; ``kw``: the other :class:`PBRSettings` fields."""
        return PBRSettings(backend="torch", normal_offset=self.normal_offset_m, indirect_bounces=self.indirect_bounces,
                           indirect_specular_rays=self.indirect_specular_rays, diffuse=self.diffuse, masking=self.masking, opaque_above=self.opaque_above, **kw)


@dataclass(frozen=True)
class PBRStageConfig(StageShading):
    """Settings of the lighting-only PBR stage."""

    iterations: int = 150
    """Optimisation steps (one training frame each)."""
    pixels: int = 2048
    """Random non-sky pixels per step (the paper's training subset)."""
    rays_per_pixel: int = 16
    """Rays per pixel of the PBR pass during the stage (MIS)."""
    lr: float = 0.03
    """Adam learning rate of the log-radiance parameter (a step of 0.03 is a 3% change)."""
    lambda_e_start: float = 1.0
    """Weight of the log-space prior at the first step (supplement: 1.0)."""
    lambda_e_end: float = 0.1
    """Weight of the log-space prior at the last step (supplement: 0.1)."""
    env_height: int = 512
    """Rows of the optimised map (columns = 2 x rows); the outputs are resampled to 512x1024."""
    coarse_height: int = 16
    """Rows of a coarse log-radiance residual optimised beside the per-texel one (0 = per-texel
    only, the paper). ``log E = log E_g + up(R_coarse) + R_fine``: a step's 2048 pixels x rays
    reach few of the 512x1024 texels, so per texel alone the fit barely moved in 150 steps
    (photometric PSNR 15.6 -> 16.1 dB on the default scene); every sample moves the coarse one."""
    coarse_lr: float = 0.05
    """Adam learning rate of the coarse residual."""
    max_frames: int = 24
    """Training frames used (evenly spaced; their G-buffers and shadow BVHs are built once)."""
    eval_pixels: int = 4096
    """Pixels per frame of the before/after photometric evaluation (fixed subset)."""
    prior_shadows: bool = True
    """The lighting prior's sun search models cast shadows through the reconstruction's static
    Gaussians and its completed facades (``SceneGraph.shadow_static``, the occluders a relight
    traces). Measured on the development scenes after the quick volume2 stage
    (``benchmarks/bench_sun.py``; default scene, dev1, dev2): the prior's sun 24.2 / 41.8 /
    47.9 deg off without shadows, 11.2 / 6.8 / 22.3 deg with them, ``prior_points`` 16000 and
    ``prior_basin_quantile`` 0.05. The whole pipeline (pbr and joint re-run from one volume2 per
    scene, ``brdf evaluate``; ``benchmarks/results/sun_prior.json``): development mean (the default
    scene twice, dev1, dev2) sun error 34.7 -> 12.1 deg, re-render 18.91 -> 20.10 dB; test streets
    46.4 -> 17.9 deg, re-render 16.67 -> 17.99 dB; relight unchanged. The low sunrise sun (7.9 deg
    high) stays 22-29 deg off on dev2 and test2: with the true albedo the search finds dev2's within
    17 deg, with the reconstruction's it does not. (Before the completed facades existed, the
    soft, incomplete Gaussians alone put the default scene's sun 94 deg off with the cue.)"""
    prior_sun_model: str = "lambert+transport"
    """Model of the prior's sun search (:attr:`core.lighting.prior.LightingSettings.sun_model`):
    ``"lambert"`` (ambient + uniform dome + sun, with cast shadows) or ``"lambert+transport"``:
    the lambert search finds the sun's region (and compares the wall hypotheses), then the
    sky-patch transport model places the sun within 30 deg of it, once, for the chosen
    hypothesis. A low sun's glow lights what faces it as a sun higher up would under a uniform
    dome: on dev6 (sunrise 7.9 deg high behind the camera) the lambert search put it at 27 deg
    elevation, 22.8 deg off; the transport model alone found it within 2.9 deg but put the
    default scene's 80 deg off (the patches stood in for a high sun), the cone keeps it at 25.3
    (lambert 24.5; ``benchmarks/bench_sun.py``, volume2 of one quick reconstruction each). The
    whole pipeline, pbr and joint re-run from one volume2 per development scene at quick
    (``benchmarks/results/sun_transport.json``): sun 16.8 -> 16.9 / 23.8 -> 12.7 / 8.1 -> 15.2
    deg (default, dev6, dev2; mean 16.2 -> 14.9), re-render 23.38 -> 23.46 / 20.59 -> 20.73 /
    20.60 -> 22.66 dB, relight 22.03 -> 22.05 / 20.48 -> 20.50 / 23.08 -> 22.79 dB. Costs one
    lambert and one transport search more (the default scene's prior 204 -> 340 s, shared cores)."""
    prior_points: int = 16000
    """Surface pixels (random subset of the training frames) of the prior's sun search
    (:attr:`core.lighting.prior.LightingSettings.max_points`). With shadows, 4000 left the
    default scene's answer to the subset: 34 deg off, 11 with 16000."""
    wall_hypotheses: bool = True
    """Choose the shadow casters the capture never saw whole by the capture's shading
    (:mod:`core.stages.wall_heights`): the prior's sun search runs once per hypothesis (each
    side's unseen walls at their neighbours' roof line or at the occluders' ``max_height_m``;
    the facades on the wall lines carved by the depth test or by sky pixels only). The
    hypothesis with the smallest residual gives the prior's sun; whether its occluders serve the
    stage, the joint stage and every later render (``occluders.pt``) is ``wall_shadows``. Needs ``prior_shadows`` and
    the volume stage's occluder settings; costs seven more searches."""
    wall_min_gain: float = 0.002
    """A wall hypothesis wins only when its residual is lower than every hypothesis before it in
    :data:`core.stages.wall_heights.HYPOTHESES` (the guess first, sky-only carving last) by more
    than this share (:func:`core.stages.wall_heights.choose`): taller walls and sky-only carving
    darken the street, so a near-tie keeps the simpler hypothesis. Chosen on development scenes
    (quick, pbr and joint re-run on one volume2 each; ``benchmarks/results/wall_min_gain.json``):
    at 0 dev4 took "right" over the guess by less than 1e-5 and the default scene "sky+right"
    over "right" by 0.2%; at 0.002 relight 22.67 -> 23.28 dB and 20.74 -> 22.05 dB, re-render
    22.35 -> 22.32 and 22.88 -> 23.67 dB, sun unchanged / 8.5 -> 8.9 deg; dev1 moves from
    "sky+left" to "sky" (the prior's sun 21.4 -> 21.5 deg), dev2, dev3 and the earlier default
    reconstruction keep theirs."""
    wall_shadows: str = "auto"
    """Whose occluders the stage, the joint stage and every later render use when a wall
    hypothesis is chosen: ``"chosen"`` (the hypothesis that gave the prior's sun), ``"guess"``
    (the volume stage's occluders, ``"none"``; the chosen hypothesis then only gives the prior's
    sun and sky) or ``"auto"``: the chosen one's when its shading residual beats the guess's by at
    least ``wall_shadows_min_gain``, else the guess's. Measured on development scenes at the quick
    profile, pbr and joint re-run from one volume2 each:

    * dev3 ("right", 0.4% below the guess's residual, raised unseen walls to ~20 m over 6-15 m
      true buildings; ``low_sun_dev_quick.json``): guess against chosen relight 22.00 / 19.06 dB,
      re-render 24.28 / 24.57; auto takes the guess;
    * the default scene ("sky+right", 4.2% below the guess; ``wall_shadows.json``): relight
      20.52 / 20.63 dB, re-render 22.90 / 22.62, and an inserted car's cast shadow under city 36
      (issue 16, ``benchmarks/bench_insertion.py``) IoU 0.600 / 0.811 against Mitsuba: with the
      guess the road near the camera stands in the sun where a 13.8 m building shadows it; auto
      takes the chosen walls. An earlier reconstruction: relight 20.96 / 20.43 dB.

    The sun is the chosen hypothesis's in every mode."""
    wall_shadows_min_gain: float = 0.02
    """``wall_shadows="auto"``: the share by which the chosen hypothesis's residual must beat the
    guess's (``residual_none / residual_chosen - 1``) for its walls to cast the shadows; between
    dev3's 0.4% and the default scene's 4.2-7.6% (its quick reconstructions since the
    hypotheses)."""
    prior_basin_quantile: float = 0.05
    """The prior's sun search refines only around the low region of its coarse grid
    (:attr:`core.lighting.prior.LightingSettings.basin_quantile`). Without it the default
    scene's sun was 10.8 / 31.5 / 78.9 deg off with three random subsets; with it 11.2 / 11.2."""
    seed: int = 0
    """Seed of the pixel subsets and the ray samples."""
    threads: int = 2
    """CPU threads of the rasterizer and the shadow-ray kernels."""
    skip_sun_search: bool = False
    """Skip: no sun search for an overcast or night capture. When the training frames show no
    sun (at most ``overcast_max_clipped_sky`` of their sky pixels clipped: no sun disc and no
    glare) or are dark (median LDR value at most ``night_max_median_ldr``), no surface sample
    reaches :func:`core.lighting.prior.estimate_lighting`, so its shading search over sun
    directions does not run: the lighting prior is the sky fit, with a sun only where a compact
    cluster of clipped sky pixels shows one; the summary's ``skips_fired`` says why. Off by
    default: within noise on overcast streets (``benchmarks/bench_skips.py``, tiny streets under
    the overcast courtyard map, seeds 0-2: photometric PSNR +1.04 +- 1.04 dB; the lighting prior
    0.055 +- 0.020 s faster) and it fired on none of six sunny and night streets, but "no clipped
    sky" does not tell an overcast sky from a sunny one whose sun is out of view: under the
    sunrise map at 300 deg (eval street test2, a 7.9 deg sun behind the camera, 0.05% of the
    sky clipped) it fired and the sun came out 153 deg off (71 with the search), and the
    development street dev2 (sunrise at 200 deg, no sky pixel clipped) reads as overcast too.
    It saves 0.06 s."""
    overcast_max_clipped_sky: float = 0.01
    """Largest fraction of clipped sky pixels (any channel at the LDR clip) of an overcast capture."""
    night_max_median_ldr: float = 0.05
    """Largest median LDR value (all pixels, all channels) of a night capture."""
    early_stop_every: int = 0
    """Skip: stop once the fit stops improving. Every this many steps the mean photometric L1 of
    those steps (the stage's validation error: fresh random pixels every step) is compared with
    the best window so far; after ``early_stop_patience`` windows without an improvement of
    ``early_stop_min_delta`` (relative) the stage stops and says so in ``skips_fired``. 0 = off,
    the default: not within noise (``benchmarks/bench_skips.py``, 6 tiny streets, a window of 5:
    fired on 4, 4.1 +- 1.6 s saved there, photometric PSNR -0.16 +- 0.03 dB)."""
    early_stop_patience: int = 2
    """Windows without improvement before the stage stops."""
    early_stop_min_delta: float = 0.01
    """Relative improvement of the window's mean L1 that counts (0.01 = 1%)."""
    sky_evidence: SkyEvidenceSettings = field(default_factory=SkyEvidenceSettings)
    """The sky the frames saw, held fixed in the map (:mod:`core.lighting.sky_evidence`): the
    reconstruction's sky dome where the training frames' sky pixels point and the dome is not
    clipped; the fit (and the joint stage after it) moves the rest. Needs the dome (the chain's
    runs have it); its coverage is in the summary."""

    prior_gains: PriorGainSettings = field(default_factory=PriorGainSettings)
    """The prior's sun and unseen sky rescaled by two gains fitted to the capture through this
    stage's PBR pass before its per-texel fit (:mod:`core.lighting.prior_gains`)."""
    sun_floor: float = 0.0
    """The sun of the lighting prior as a floor: texels within ``sun_floor_deg`` of the prior's
    sun direction may not fall below ``sun_floor`` times the prior's radiance there, in this stage
    and in the joint stage (the floor is part of the held sky evidence, ``sky_evidence.npz``);
    the sun may still grow. 0 = off. Why: with the reconstruction's albedo, which keeps part of
    the sun on sunlit walls, the fit moves light from the sun to the sky (default scene, quick:
    the sun's peak radiance 1577 in the prior, 508 after the fit, against a sun irradiance the
    prior had within 17%; ``benchmarks/results/rerender_diagnosis.json``). Measured at 1.0 on the
    development scenes (pbr and joint re-run on one volume2 each, ``brdf evaluate``;
    ``benchmarks/results/sun_floor.json``): relit PSNR 21.45 -> 21.74 (default, quick), 21.09 ->
    21.10 (dev1, benchmark), 21.76 -> 21.60 dB (dev2); re-render 22.20 -> 21.94, 21.14 -> 21.17,
    25.10 -> 24.93 dB; sun error 5.0 -> 3.6, 29.7 -> 29.7, 26.8 -> 27.6 deg: where the prior's
    sun is wrong the floor keeps it, and the fit's weaker sun re-renders the capture better: off."""
    sun_floor_deg: float = 2.0
    """Radius of the held sun region around the prior's sun direction (the prior's disc is
    :data:`core.lighting.prior.SUN_RADIUS_DEG` wide)."""

    def __post_init__(self) -> None:
        if not (0.0 <= self.sun_floor <= 10.0) or not (0.0 < self.sun_floor_deg <= 45.0):
            raise ConfigError(f"sun_floor / sun_floor_deg: expected [0, 10] / (0, 45], got {self.sun_floor} / "
                              f"{self.sun_floor_deg}")
        if not isinstance(self.sky_evidence, SkyEvidenceSettings):
            raise ConfigError(f"sky_evidence: expected SkyEvidenceSettings, got {type(self.sky_evidence).__name__}")
        if not isinstance(self.prior_gains, PriorGainSettings):
            raise ConfigError(f"prior_gains: expected PriorGainSettings, got {type(self.prior_gains).__name__}")
        if self.prior_sun_model not in ("lambert", "lambert+transport"):
            raise ConfigError(f"prior_sun_model: must be 'lambert' or 'lambert+transport', got {self.prior_sun_model!r}")
        if self.wall_shadows not in ("auto", "chosen", "guess"):
            raise ConfigError(f"wall_shadows: must be 'auto', 'chosen' or 'guess', got {self.wall_shadows!r}")
        if not isinstance(self.skip_sun_search, bool):
            raise ConfigError(f"skip_sun_search: expected true or false, got {self.skip_sun_search!r}")
        bad = [n for n, ok in (("iterations", self.iterations >= 0), ("pixels", self.pixels >= 1),
                               ("overcast_max_clipped_sky", 0 <= self.overcast_max_clipped_sky <= 1),
                               ("night_max_median_ldr", 0 <= self.night_max_median_ldr <= 1),
                               ("early_stop_every", self.early_stop_every >= 0),
                               ("early_stop_patience", self.early_stop_patience >= 1),
                               ("early_stop_min_delta", 0 <= self.early_stop_min_delta < 1),
                               ("rays_per_pixel", self.rays_per_pixel >= 1), ("lr", self.lr > 0),
                               ("lambda_e_start", self.lambda_e_start >= 0), ("lambda_e_end", self.lambda_e_end >= 0),
                               ("env_height", self.env_height >= 8), ("max_frames", self.max_frames >= 1),
                               ("coarse_height", self.coarse_height == 0 or 2 <= self.coarse_height <= self.env_height),
                               ("coarse_lr", self.coarse_lr > 0),
                               ("eval_pixels", self.eval_pixels >= 1), ("threads", self.threads >= 1),
                               ("prior_points", self.prior_points >= 50),
                               ("prior_basin_quantile", 0 <= self.prior_basin_quantile < 1),
                               ("wall_min_gain", math.isfinite(self.wall_min_gain) and self.wall_min_gain >= 0),
                               ("wall_shadows_min_gain",
                                math.isfinite(self.wall_shadows_min_gain) and self.wall_shadows_min_gain >= 0))
               if not ok]
        bad += self.shading_errors()
        if bad:
            raise ConfigError(f"PBRStageConfig: out of range: {', '.join(bad)} ({self})")
