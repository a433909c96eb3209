"""The randomised street generator: :func:`make_random_street` builds a street from a
:class:`~core.synth.randomise.SceneSpec` (layout style, widths, palette, traffic) and draws every
per-building, per-tree and per-car value from the spec's seed within its settings' ranges.

It reuses the fixed generator's primitives and types (:mod:`core.synth.street`), but not its
constants: road width, sidewalk width and building line come from the spec. World frame as in
:mod:`core.synth.street` (z up, street along x, ego lane at y = -road_half_width / 2).
Facades, road, sidewalks, curbs and planters carry procedural albedo textures
(:mod:`core.synth.textures`); glass, foliage, poles and vehicles are flat per part.
"""

from __future__ import annotations

import math

import numpy as np

from core.synth import geometry as geo
from core.synth.street import (
    CURB_HEIGHT,
    CURB_WIDTH,
    CarTrack,
    Material,
    Part,
    StreetScene,
    _pose,
)
from core.synth.textures import PALETTES, AlbedoTexture, palette_colour, planar_uvs


def ego_lane_y(spec) -> float:
    """y of the ego lane's centre (right-hand traffic, driving +x)."""
    return -spec.road_half_width_m / 2.0


def _u(rng, r) -> float:
    return float(rng.uniform(r[0], r[1])) if r[1] > r[0] else float(r[0])


def _textured(name: str, mesh, mat: Material, repeat_m: float) -> Part:
    v, f, uv = planar_uvs(mesh[0], mesh[1], repeat_m)
    return Part(name, v, f, mat, uv)


def _tex_material(rng, name: str, pattern: str, albedo, noise: float, repeat_m: float, roughness: float,
                  metallic: float = 0.0) -> tuple[Material, float]:
    tex = AlbedoTexture(pattern, tuple(float(a) for a in albedo), round(float(noise), 4), round(float(repeat_m), 4),
                        int(rng.integers(2**31)))
    return Material(name, tuple(float(a) for a in albedo), round(float(roughness), 4), round(float(metallic), 4),
                    texture=tex), repeat_m


def _car_parts(rng, idx: int, s, length: float) -> tuple[tuple[float, float, float], list[Part]]:
    k = length / 4.4
    l, w, h = length, 1.8 * min(1.15, max(0.9, k)), 1.5 * min(1.3, max(0.9, k))
    hue = rng.uniform()
    rgb = 0.5 + 0.5 * np.cos(2 * np.pi * (hue + np.array([0.0, 1 / 3, 2 / 3])))
    sat, val = rng.uniform(0.0, 1.0), rng.uniform(0.03, 0.85)
    colour = np.clip(val * ((1 - sat) + sat * rgb), 0.02, 0.95)
    paint = Material(f"paint{idx}", tuple(float(c) for c in colour.round(4)), round(_u(rng, s.paint_roughness), 4),
                     round(_u(rng, s.paint_metallic), 4))
    glass = Material(f"car_glass{idx}", (0.04, 0.04, 0.05), round(float(rng.uniform(0.02, 0.12)), 4), 0.0)
    rubber = Material("rubber", (0.03, 0.03, 0.03), 0.9, 0.0)
    zb = -h / 2.0
    body_h, cabin_h = 0.5 * h, 0.3 * h
    body = geo.box((0.0, 0.0, zb + 0.2 * h + body_h / 2), (l, w, body_h))
    cabin = geo.box((-0.06 * l, 0.0, zb + 0.7 * h + cabin_h / 2), (0.52 * l, 0.89 * w, cabin_h))
    r = 0.22 * h
    wheels = geo.merge([geo.cylinder((sx * 0.32 * l, sy * 0.44 * w, zb + r), r, 0.25, 14, axis="y")
                        for sx in (-1, 1) for sy in (-1, 1)])
    return (l, w, h), [Part("body", *body, paint), Part("cabin", *cabin, glass), Part("wheels", *wheels, rubber)]


def make_random_street(spec, ego_x: np.ndarray, street_length_m: float, frame_dt: float,
                       ego_speed: float) -> StreetScene:
    """Build the street of ``spec`` (:class:`~core.synth.randomise.SceneSpec`) around the ego
    positions ``ego_x`` [T] (metres along x). Deterministic in ``spec``."""
    s = spec.settings
    rng = np.random.default_rng([spec.seed, 7])
    L = street_length_m
    x0, x1 = float(ego_x.mean()) - L / 2.0, float(ego_x.mean()) + L / 2.0
    R = spec.road_half_width_m
    B = R + CURB_WIDTH + spec.sidewalk_width_m  # building line
    terraced = spec.layout in ("terraced", "narrow")
    parts: list[Part] = []

    g = _u(rng, s.road_albedo)
    asphalt, rep = _tex_material(rng, "asphalt", "asphalt", (g, g, g * 1.05), _u(rng, s.albedo_noise), 4.0,
                                 _u(rng, s.road_roughness))
    parts.append(_textured("road", geo.quad([(x0, -R, 0), (x1, -R, 0), (x1, R, 0), (x0, R, 0)]), asphalt, rep))
    marking = Material("marking", tuple(np.clip(rng.uniform(0.55, 0.8) + rng.uniform(-0.03, 0.03, 3), 0, 1).round(4)),
                       round(float(rng.uniform(0.4, 0.8)), 4), 0.0)
    dashes = []
    if R >= 4.0:
        x = x0 + 1.0
        dash, period = float(rng.uniform(2.0, 4.0)), float(rng.uniform(5.0, 9.0))
        while x + dash < x1:
            dashes.append(geo.quad([(x, -0.08, 0.005), (x + dash, -0.08, 0.005), (x + dash, 0.08, 0.005), (x, 0.08, 0.005)]))
            x += period
    for y in (-R + 0.3, R - 0.3):
        dashes.append(geo.quad([(x0, y - 0.06, 0.005), (x1, y - 0.06, 0.005), (x1, y + 0.06, 0.005), (x0, y + 0.06, 0.005)]))
    parts.append(Part("markings", *geo.merge(dashes), marking))

    c = rng.uniform(0.3, 0.6)
    curb_mat, _ = _tex_material(rng, "curb", "noise", (c, c * 0.98, c * 0.95), _u(rng, s.albedo_noise), 2.0,
                                _u(rng, s.road_roughness))
    c = rng.uniform(0.2, 0.55)
    walk_mat, walk_rep = _tex_material(rng, "sidewalk", str(rng.choice(["tiles", "noise"])),
                                       tuple(np.clip(c + rng.uniform(-0.04, 0.04, 3), 0.05, 0.9)),
                                       _u(rng, s.albedo_noise), float(rng.uniform(1.0, 3.0)), _u(rng, s.road_roughness))
    foliage_base = np.array([rng.uniform(0.04, 0.12), rng.uniform(0.12, 0.3), rng.uniform(0.02, 0.08)])
    bark = Material("bark", tuple(np.clip(rng.uniform(0.06, 0.2) * np.array([1.0, 0.7, 0.45]), 0, 1).round(4)), 0.9, 0.0)
    pole_mat = Material("pole", tuple(np.full(3, round(float(rng.uniform(0.2, 0.7)), 4))),
                        round(float(rng.uniform(0.2, 0.6)), 4), round(float(rng.choice([0.0, 1.0])), 1))
    palette = PALETTES[spec.palette]

    for side in (-1, 1):
        sd = "L" if side > 0 else "R"
        cy = side * (R + CURB_WIDTH / 2)
        parts.append(_textured(f"curb{sd}", geo.box(((x0 + x1) / 2, cy, CURB_HEIGHT / 2), (L, CURB_WIDTH, CURB_HEIGHT)),
                               curb_mat, 2.0))
        sw = spec.sidewalk_width_m + 8.0  # runs under the setbacks to the back of the buildings
        cy = side * (R + CURB_WIDTH + sw / 2)
        parts.append(_textured(f"sidewalk{sd}", geo.box(((x0 + x1) / 2, cy, CURB_HEIGHT / 2 - 0.001), (L, sw, CURB_HEIGHT)),
                               walk_mat, walk_rep))
        x, b = x0, 0
        while x < x1:
            width = _u(rng, s.building_width_m)
            depth = float(rng.uniform(8.0, 14.0))
            lo_h = s.building_height_m[0] if spec.layout != "narrow" else (s.building_height_m[0] + s.building_height_m[1]) / 2
            height = float(rng.uniform(lo_h, s.building_height_m[1]))
            setback = 0.0 if terraced else _u(rng, s.setback_m)
            fy = B + setback
            if rng.uniform() < s.metal_facade_prob:
                col = tuple(np.full(3, rng.uniform(0.4, 0.9)) * (1 + rng.uniform(-0.05, 0.05, 3)))
                wall, rep = _tex_material(rng, f"wall{sd}{b}", "panels", np.clip(col, 0.05, 0.95), _u(rng, s.albedo_noise) / 2,
                                          _u(rng, s.texture_repeat_m), rng.uniform(0.2, 0.6), rng.uniform(0.6, 1.0))
            else:
                pattern = str(palette["patterns"][int(rng.integers(len(palette["patterns"])))])
                wall, rep = _tex_material(rng, f"wall{sd}{b}", pattern, palette_colour(rng, spec.palette),
                                          _u(rng, s.albedo_noise), _u(rng, s.texture_repeat_m), _u(rng, s.facade_roughness))
            parts.append(_textured(f"building{sd}{b}", geo.box((x + width / 2, side * (fy + depth / 2), height / 2),
                                                               (width, depth, height)), wall, rep))
            ga = _u(rng, s.glass_albedo)
            glass = Material(f"window{sd}{b}", tuple(np.clip(ga * (1 + rng.uniform(-0.2, 0.2, 3)), 0.01, 0.5).round(4)),
                             round(_u(rng, s.glass_roughness), 4), round(_u(rng, s.glass_metallic), 4))
            floor_h, win_w = float(rng.uniform(2.8, 3.8)), float(rng.uniform(0.7, 1.8))
            pitch_x = win_w + float(rng.uniform(0.8, 2.0))
            fill = _u(rng, s.window_fill)
            wins = []
            for fi in range(int((height - 1.0) // floor_h)):
                for ci in range(int((width - 1.0) // pitch_x)):
                    if rng.uniform() < fill:
                        wins.append(geo.box((x + 0.5 + ci * pitch_x + pitch_x / 2, side * (fy - 0.02), 1.2 + fi * floor_h + 0.8),
                                            (win_w, 0.06, min(1.6, floor_h - 0.8))))
            if wins:
                parts.append(Part(f"windows{sd}{b}", *geo.merge(wins), glass))
            gap = 0.0 if terraced else _u(rng, s.building_gap_m)
            if (setback > 1.0 or gap > 1.5) and rng.uniform() < s.hedge_prob:
                hedge = Material(f"hedge{sd}{b}", tuple(np.clip(foliage_base * rng.uniform(0.7, 1.3, 3), 0.01, 0.6).round(4)),
                                 0.85, 0.0)
                parts.append(Part(f"hedge{sd}{b}", *geo.box((x + width / 2, side * (B + 0.5), 0.6), (width * 0.8, 0.8, 1.0)), hedge))
            x += width + gap
            b += 1

        # street lights and trees on the sidewalk
        px, k = x0 + float(rng.uniform(2.0, 8.0)), 0
        while px < x1:
            py = side * (R + 0.5)
            arm = min(1.5, R * 0.3)
            pole_h = float(rng.uniform(5.0, 8.0))
            parts.append(Part(f"pole{sd}{k}", *geo.merge([geo.cylinder((px, py, 0.0), 0.08, pole_h, 12),
                                                          geo.box((px, py - side * arm / 2, pole_h - 0.1), (0.15, arm, 0.1))]),
                              pole_mat))
            px += float(rng.uniform(18.0, 30.0))
            k += 1
        if spec.sidewalk_width_m >= 1.8:
            tx, k = x0 + float(rng.uniform(0.0, spec.tree_spacing_m)), 0
            ty = side * (R + CURB_WIDTH + min(1.5, spec.sidewalk_width_m / 2))
            while tx < x1:
                planter_c = rng.uniform(0.2, 0.45) * np.array([1.0, 0.8, 0.65])
                pm, _ = _tex_material(rng, f"planter{sd}{k}", "noise", planter_c, _u(rng, s.albedo_noise), 1.0, rng.uniform(0.6, 0.9))
                parts.append(_textured(f"planter{sd}{k}", geo.box((tx, ty, 0.35), (1.2, 1.2, 0.4)), pm, 1.0))
                trunk_h = float(rng.uniform(1.8, 3.5))
                parts.append(Part(f"trunk{sd}{k}", *geo.cylinder((tx, ty, 0.5), 0.12, trunk_h, 10), bark))
                cr = _u(rng, s.crown_radius_m)
                leaves = Material(f"foliage{sd}{k}", tuple(np.clip(foliage_base * rng.uniform(0.7, 1.4, 3), 0.01, 0.6).round(4)),
                                  round(float(rng.uniform(0.6, 0.95)), 4), 0.0)
                parts.append(Part(f"crown{sd}{k}", *geo.sphere((tx, ty, 0.5 + trunk_h + 0.8 * cr), cr), leaves))
                tx += spec.tree_spacing_m * float(rng.uniform(0.8, 1.2))
                k += 1

    scene = StreetScene(parts)
    T = len(ego_x)
    idx = 0
    park_y = R - 1.1
    for i in range(spec.num_parked_cars):
        side = 1 if (i % 2 == 0 or R < 4.5) else -1
        length = _u(rng, s.vehicle_length_m)
        size, cparts = _car_parts(rng, idx, s, length)
        one_side = R < 4.5  # narrow: park opposite the ego lane only
        px = float(ego_x[0]) + 8.0 + i * float(rng.uniform(length + 1.0, length + 4.0) if one_side else rng.uniform(3.0, 6.0))
        pose = _pose(px, side * park_y, size[2] / 2, 0.0 if side < 0 else math.pi)
        scene.cars.append(CarTrack(f"car{idx}", size, cparts, {t: pose for t in range(T)}, False))
        idx += 1
    for i in range(spec.num_moving_cars):
        length = _u(rng, s.vehicle_length_m)
        size, cparts = _car_parts(rng, idx, s, length)
        if i % 2 == 0:
            speed, start, y, yaw = -float(rng.uniform(6.0, 12.0)), float(ego_x[0]) + 25.0 + 10.0 * i, R / 2, math.pi
        else:
            speed, start, y, yaw = float(rng.uniform(0.6, 0.9)) * ego_speed, float(ego_x[0]) + 10.0 + 6.0 * i, -R / 2, 0.0
        poses = {t: _pose(start + speed * t * frame_dt, y, size[2] / 2, yaw) for t in range(T)}
        scene.cars.append(CarTrack(f"car{idx}", size, cparts, poses, True))
        idx += 1
    return scene
