"""An analytic sun-and-sky environment map (Preetham et al. 1999 sky, a simplified sun), written
as an equirect map in the project's convention (:mod:`core.conventions`), so the synthetic
streets can be lit by a sun at any elevation, azimuth and turbidity.

Sky: Preetham's Perez distribution of luminance and chromaticity (x, y) for turbidity T and the
sun's zenith angle, converted to linear sRGB. Absolute scale: the sky's irradiance on a
horizontal plane is ``1.5 sqrt(sin(elevation) + 0.05)`` (the bundled HDRIs measure 1.7-6.9
including their sun). Sun: a disk of 0.6 degrees radius (wider than the real 0.27 degrees so
that it covers a few texels of a 512 x 1024 map) whose irradiance at normal incidence is
``6 exp(-0.2 (T - 2))`` times the sky's, reddened along the air mass (Kasten-Young) with a
Rayleigh-like per-channel extinction. Ground (below the horizon): grey-brown Lambertian ground
of albedo 0.2 under that light.
"""

from __future__ import annotations

import math

import numpy as np

from core.conventions import envmap_directions, envmap_solid_angles
from core.errors import ConfigError

SUN_RADIUS_DEG = 0.6

_XYZ_TO_RGB = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])


def _perez(theta, gamma, c):
    A, B, C, D, E = c
    cos_t = np.maximum(np.cos(theta), 0.01)
    return (1.0 + A * np.exp(B / cos_t)) * (1.0 + C * np.exp(D * gamma) + E * np.cos(gamma) ** 2)


def sun_direction(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """World unit vector toward the sun; azimuth from +x toward +y (the convention's phi)."""
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def sun_sky_map(elevation_deg: float, azimuth_deg: float, turbidity: float, *, height: int = 256,
                intensity: float = 1.0) -> np.ndarray:
    """Linear RGB radiance [height, 2 height, 3] float32 of a clear sky with the sun at
    ``elevation_deg`` (0-90) and ``azimuth_deg``; ``turbidity`` 1.7-10; ``intensity`` scales all."""
    if not 0.0 <= elevation_deg <= 90.0:
        raise ConfigError(f"elevation_deg: must be in [0, 90], got {elevation_deg!r}")
    if not 1.7 <= turbidity <= 12.0:
        raise ConfigError(f"turbidity: must be in [1.7, 12], got {turbidity!r}")
    if height < 8 or intensity <= 0:
        raise ConfigError(f"height/intensity: need height >= 8 and intensity > 0 ({height}, {intensity})")
    T = float(turbidity)
    H, W = int(height), 2 * int(height)
    d = envmap_directions(H, W)
    s = sun_direction(elevation_deg, azimuth_deg)
    ts = math.radians(90.0 - max(elevation_deg, 0.5))
    theta = np.arccos(np.clip(d[..., 2], -1, 1))
    gamma = np.arccos(np.clip(d @ s, -1, 1))
    cY = (0.1787 * T - 1.4630, -0.3554 * T + 0.4275, -0.0227 * T + 5.3251, 0.1206 * T - 2.5771, -0.0670 * T + 0.3703)
    cx = (-0.0193 * T - 0.2592, -0.0665 * T + 0.0008, -0.0004 * T + 0.2125, -0.0641 * T - 0.8989, -0.0033 * T + 0.0452)
    cy = (-0.0167 * T - 0.2608, -0.0950 * T + 0.0092, -0.0079 * T + 0.2102, -0.0441 * T - 1.6537, -0.0109 * T + 0.0529)
    chi = (4.0 / 9.0 - T / 120.0) * (math.pi - 2.0 * ts)
    Yz = max((4.0453 * T - 4.9710) * math.tan(chi) - 0.2155 * T + 2.4192, 0.05)
    t3, t2 = ts ** 3, ts ** 2
    xz = (T * T * (0.00166 * t3 - 0.00375 * t2 + 0.00209 * ts) + T * (-0.02903 * t3 + 0.06377 * t2 - 0.03202 * ts + 0.00394)
          + (0.11693 * t3 - 0.21196 * t2 + 0.06052 * ts + 0.25886))
    yz = (T * T * (0.00275 * t3 - 0.00610 * t2 + 0.00317 * ts) + T * (-0.04214 * t3 + 0.08970 * t2 - 0.04153 * ts + 0.00516)
          + (0.15346 * t3 - 0.26756 * t2 + 0.06670 * ts + 0.26688))
    th = np.minimum(theta, math.radians(89.5))
    Y = Yz * _perez(th, gamma, cY) / _perez(0.0, ts, cY)
    x = xz * _perez(th, gamma, cx) / _perez(0.0, ts, cx)
    y = np.maximum(yz * _perez(th, gamma, cy) / _perez(0.0, ts, cy), 1e-3)
    XYZ = np.stack([x / y * Y, Y, (1.0 - x - y) / y * Y], -1)
    sky = np.maximum(XYZ @ _XYZ_TO_RGB.T, 0.0)
    sa = envmap_solid_angles(H, W)[:, None]
    up = d[..., 2] > 0
    cos_up = np.where(up, d[..., 2], 0.0)
    sky_E = float((sky.mean(-1) * sa * cos_up).sum())
    elev = math.radians(max(elevation_deg, 0.0))
    sky *= 1.5 * math.sqrt(math.sin(elev) + 0.05) / max(sky_E, 1e-9)
    sky_E = 1.5 * math.sqrt(math.sin(elev) + 0.05)
    # sun: an equal-radiance disk, reddened by the air mass
    e_deg = max(elevation_deg, 0.0)
    airmass = 1.0 / (math.sin(elev) + 0.50572 * (e_deg + 6.07995) ** -1.6364)
    colour = np.exp(-np.array([0.02, 0.045, 0.1]) * airmass * T / 2.0)
    colour /= colour @ np.array([0.2126, 0.7152, 0.0722])
    sun_En = 6.0 * math.exp(-0.2 * (T - 2.0)) * sky_E
    disk = (gamma <= math.radians(SUN_RADIUS_DEG)) & up
    if not disk.any():  # the disk smaller than a texel: the nearest texel
        disk = np.zeros_like(up)
        disk[np.unravel_index(np.argmin(np.where(up, gamma, np.inf)), gamma.shape)] = True
    omega = float((np.broadcast_to(sa, gamma.shape)[disk]).sum())
    env = np.where(up[..., None], sky, 0.0)
    env[disk] += colour * sun_En / omega
    total_E = sky_E + sun_En * math.sin(elev)
    ground = 0.2 * total_E / math.pi * np.array([1.0, 0.92, 0.8])
    env[~up] = ground
    return (env * intensity).astype(np.float32)
