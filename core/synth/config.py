"""Settings of the synthetic benchmark generator (frozen dataclasses, one docstring per field)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from core.errors import ConfigError


@dataclass(frozen=True)
class SynthConfig:
    """How a synthetic street scene is generated and rendered."""

    seed: int = 0
    """Random seed: the whole scene (layout, materials, traffic) is a function of it."""
    width: int = 240
    """Image width in pixels."""
    height: int = 160
    """Image height in pixels."""
    hfov_deg: float = 75.0
    """Horizontal field of view of the camera, degrees."""
    num_frames: int = 10
    """Time steps per trajectory (the train and test trajectories share the time steps)."""
    frame_dt: float = 0.1
    """Seconds between time steps (10 Hz like Waymo)."""
    ego_speed: float = 8.0
    """Speed of the capturing vehicle along +x, m/s."""
    test_offset_m: float = 1.0
    """Lateral offset (+y, metres) of the novel-view test trajectory from the train trajectory."""
    camera_height_m: float = 1.6
    """Camera height above the road, metres."""
    camera_pitch_deg: float = 4.0
    """Downward pitch of the camera, degrees."""
    street_length_m: float = 90.0
    """Length of the generated street along x, metres (centred on the trajectory)."""
    num_moving_cars: int = 2
    """Cars driving along the street: tracked objects with per-frame poses."""
    num_parked_cars: int = 4
    """Static cars parked along the curbs."""
    envmap: str = "city"
    """Training environment map: a name of data/hdri/*.exr, or a path to an .exr/.hdr."""
    envmap_rotation_deg: float = 0.0
    """Rotation of the environment about +z (rounded to whole columns of the map), degrees."""
    relight_envmaps: tuple[str, ...] = ("sunset", "forest", "courtyard")
    """Environment maps of the relit ground truth (rendered for the test trajectory)."""
    relight_every: int = 1
    """Render relit ground truth for every n-th test frame."""
    spp: int = 64
    """Samples per pixel of the path-traced ground-truth frames."""
    relight_spp: int = 0
    """Samples per pixel of the relit reference frames (0 = 4 x ``spp``). They are references,
    not inputs: at 64 spp their noise alone held a perfect render to SSIM 0.67-0.87 (default
    scene, measured against 1024 spp), below the relighting target."""
    max_depth: int = 4
    """Path length limit of Mitsuba's path tracer (2 = direct light only)."""
    exposure: float = 1.0
    """LDR exposure: ldr = (exposure * hdr)^(1/gamma), clipped to [0, 1]."""
    gamma: float = 2.2
    """LDR gamma (the paper's tone map)."""
    lidar_beams: int = 32
    """LiDAR vertical beams (elevation -25..+5 degrees)."""
    lidar_azimuth_steps: int = 360
    """LiDAR rays per beam per sweep."""
    lidar_range_m: float = 75.0
    """LiDAR maximum range, metres."""
    lidar_height_m: float = 1.9
    """LiDAR sensor height above the road, metres."""
    scene_spec: object = None
    """A :class:`core.synth.randomise.SceneSpec` (randomised street, materials, lens, light and
    sensor; see :func:`core.synth.randomise.spec_config`), or None for the fixed generator of
    the profiles. Opt-in: None leaves every profile's output unchanged."""

    def __post_init__(self) -> None:
        checks = {
            "width": self.width >= 8, "height": self.height >= 8, "num_frames": self.num_frames >= 1,
            "hfov_deg": 10 <= self.hfov_deg <= 150, "spp": self.spp >= 1, "relight_spp": self.relight_spp >= 0, "max_depth": self.max_depth >= 2,
            "frame_dt": self.frame_dt > 0, "exposure": self.exposure > 0, "gamma": self.gamma > 0,
            "lidar_beams": self.lidar_beams >= 0, "lidar_azimuth_steps": self.lidar_azimuth_steps >= 1,
            "relight_every": self.relight_every >= 1, "street_length_m": self.street_length_m >= 20,
            "num_moving_cars": self.num_moving_cars >= 0, "num_parked_cars": self.num_parked_cars >= 0,
        }
        for name, ok in checks.items():
            if not ok:
                raise ConfigError(f"{name}: out of range ({getattr(self, name)!r})")
        if self.scene_spec is not None and type(self.scene_spec).__name__ != "SceneSpec":
            raise ConfigError(f"scene_spec: a core.synth.randomise.SceneSpec or None, got {type(self.scene_spec).__name__}")


#: Named profiles. ``tiny`` is for tests; ``quick`` makes the bundled default scene;
#: ``benchmark`` makes the figures' scenes on demand.
PROFILES: dict[str, SynthConfig] = {
    "tiny": SynthConfig(width=48, height=32, num_frames=2, spp=8, max_depth=3, lidar_beams=8,
                        lidar_azimuth_steps=90, relight_envmaps=("sunset",), num_parked_cars=2,
                        num_moving_cars=1),
    "quick": SynthConfig(relight_every=3, lidar_beams=16),
    "benchmark": SynthConfig(width=320, height=213, num_frames=24, spp=256, max_depth=5),
}


def profile(name: str, **overrides) -> SynthConfig:
    """A named profile with field overrides (e.g. ``profile("quick", seed=3)``)."""
    if name not in PROFILES:
        raise ConfigError(f"profile: unknown profile {name!r} (known: {sorted(PROFILES)})")
    try:
        return replace(PROFILES[name], **overrides)
    except TypeError as e:
        raise ConfigError(f"profile overrides: {e}") from None
