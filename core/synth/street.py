"""Procedural urban street: road, lane markings, curbs, sidewalks, buildings with windows, poles,
trees in planters, parked and moving cars with metallic paint. Deterministic from a seed.

World frame: z up, metres; the street runs along x; the ego lane is centred at y = -1.75
(driving +x), the oncoming lane at y = +1.75; parking strips at |y| ~ 4.3; curbs at |y| = 5.5;
sidewalks up to |y| = 9; building facades at |y| = 9.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from core.synth import geometry as geo
from core.synth.config import SynthConfig

ROAD_HALF_WIDTH = 5.5
CURB_WIDTH = 0.2
CURB_HEIGHT = 0.15
FACADE_Y = 9.0
EGO_LANE_Y = -1.75
ONCOMING_LANE_Y = 1.75
PARKING_Y = 4.3


@dataclass(frozen=True)
class Material:
    """Known ground-truth material of a part (the paper's albedo / roughness / metallic).

    ``model`` is ``"principled"`` (Mitsuba's principled BSDF, GGX with alpha = roughness^2,
    specular 0.5 = F0 0.04 for dielectrics) or ``"lambert"`` (pure diffuse; roughness 1, metallic 0
    in the G-buffers). ``texture`` (randomised streets only): a procedural albedo texture
    (:class:`core.synth.textures.AlbedoTexture`) that replaces the flat ``albedo`` (then its mean
    colour); the part needs ``uvs``."""

    name: str
    albedo: tuple[float, float, float]
    roughness: float
    metallic: float
    model: str = "principled"
    texture: object = None


@dataclass
class Part:
    """A named mesh with one material. Vertices [V, 3] float32 in its node's frame, metres."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    material: Material
    uvs: np.ndarray | None = None
    """Texture coordinates [V, 2] (textured materials only)."""


@dataclass
class CarTrack:
    """A car: parts in the object frame (origin at the centre of its box, x forward, z up), the
    box size (l, w, h) and the obj_to_world pose of each time index."""

    id: str
    size: tuple[float, float, float]
    parts: list[Part]
    poses: dict[int, np.ndarray]
    moving: bool


@dataclass
class StreetScene:
    static_parts: list[Part]
    cars: list[CarTrack] = field(default_factory=list)

    def parts_at(self, time_index: int) -> list[Part]:
        """Every part in world coordinates at ``time_index`` (cars placed by their pose)."""
        out = list(self.static_parts)
        for car in self.cars:
            pose = car.poses[time_index]
            for p in car.parts:
                v, f = geo.transform((p.vertices, p.faces), pose)
                out.append(Part(f"{car.id}/{p.name}", v, f, p.material, p.uvs))
        return out

    def materials(self) -> dict[str, Material]:
        """Part name (as in :meth:`parts_at`) -> material."""
        out = {p.name: p.material for p in self.static_parts}
        for car in self.cars:
            out.update({f"{car.id}/{p.name}": p.material for p in car.parts})
        return out


def _pose(x: float, y: float, z: float, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    m = np.eye(4)
    m[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    m[:3, 3] = [x, y, z]
    return m


CAR_SIZE = (4.4, 1.8, 1.5)


def _car_parts(rng: np.random.Generator, idx: int) -> list[Part]:
    l, w, h = CAR_SIZE
    hue = rng.uniform(size=3)
    paint_colors = [(0.6, 0.05, 0.04), (0.05, 0.12, 0.45), (0.75, 0.75, 0.78), (0.05, 0.05, 0.06),
                    (0.55, 0.55, 0.2), (0.1, 0.35, 0.15)]
    base = np.array(paint_colors[int(rng.integers(len(paint_colors)))]) * (0.85 + 0.3 * hue[0])
    paint = Material(f"paint{idx}", tuple(np.clip(base, 0.02, 0.95).round(3)), round(float(rng.uniform(0.2, 0.4)), 3), 1.0)
    glass = Material("car_glass", (0.04, 0.04, 0.05), 0.08, 0.0)
    rubber = Material("rubber", (0.03, 0.03, 0.03), 0.9, 0.0)
    zb = -h / 2.0
    body = geo.box((0.0, 0.0, zb + 0.3 + 0.375), (l, w, 0.75))
    cabin = geo.box((-0.25, 0.0, zb + 1.05 + 0.225), (2.3, 1.6, 0.45))
    wheels = geo.merge([geo.cylinder((sx * 1.4, sy * 0.8, zb + 0.33), 0.33, 0.25, 14, axis="y")
                        for sx in (-1, 1) for sy in (-1, 1)])
    return [Part("body", *body, paint), Part("cabin", *cabin, glass), Part("wheels", *wheels, rubber)]


def make_street(cfg: SynthConfig, ego_x: np.ndarray) -> StreetScene:
    """Build the street for ``cfg``. ``ego_x``: [T] ego x positions (for placing traffic in view)."""
    rng = np.random.default_rng(cfg.seed)
    L = cfg.street_length_m
    x0, x1 = float(ego_x.mean()) - L / 2.0, float(ego_x.mean()) + L / 2.0
    parts: list[Part] = []

    asphalt = Material("asphalt", (0.09, 0.09, 0.1), 0.85, 0.0)
    marking = Material("marking", (0.75, 0.75, 0.7), 0.6, 0.0)
    concrete = Material("curb", (0.45, 0.44, 0.42), 0.8, 0.0)
    pavement = Material("sidewalk", (0.33, 0.31, 0.3), 0.75, 0.0)
    glass = Material("window", (0.05, 0.06, 0.07), 0.06, 0.0)
    pole_mat = Material("pole", (0.55, 0.56, 0.58), 0.35, 1.0)
    bark = Material("bark", (0.12, 0.08, 0.05), 0.9, 0.0)
    leaves = Material("foliage", (0.06, 0.2, 0.05), 0.8, 0.0)
    planter_mat = Material("planter", (0.3, 0.2, 0.15), 0.7, 0.0)

    parts.append(Part("road", *geo.quad([(x0, -ROAD_HALF_WIDTH, 0), (x1, -ROAD_HALF_WIDTH, 0),
                                         (x1, ROAD_HALF_WIDTH, 0), (x0, ROAD_HALF_WIDTH, 0)]), asphalt))
    dashes = []
    x = x0 + 1.0
    while x + 3.0 < x1:
        dashes.append(geo.quad([(x, -0.08, 0.005), (x + 3.0, -0.08, 0.005), (x + 3.0, 0.08, 0.005), (x, 0.08, 0.005)]))
        x += 6.0
    for y in (-ROAD_HALF_WIDTH + 0.3, ROAD_HALF_WIDTH - 0.3):
        dashes.append(geo.quad([(x0, y - 0.06, 0.005), (x1, y - 0.06, 0.005), (x1, y + 0.06, 0.005), (x0, y + 0.06, 0.005)]))
    parts.append(Part("markings", *geo.merge(dashes), marking))

    for side in (-1, 1):
        s = "L" if side > 0 else "R"
        cy = side * (ROAD_HALF_WIDTH + CURB_WIDTH / 2)
        parts.append(Part(f"curb{s}", *geo.box(((x0 + x1) / 2, cy, CURB_HEIGHT / 2), (L, CURB_WIDTH, CURB_HEIGHT)), concrete))
        sw = FACADE_Y - ROAD_HALF_WIDTH - CURB_WIDTH
        cy = side * (ROAD_HALF_WIDTH + CURB_WIDTH + sw / 2)
        parts.append(Part(f"sidewalk{s}", *geo.box(((x0 + x1) / 2, cy, CURB_HEIGHT / 2 - 0.001), (L, sw, CURB_HEIGHT)), pavement))

        # buildings with windows on the facade facing the road
        x = x0
        b = 0
        while x < x1:
            width = float(rng.uniform(7.0, 15.0))
            depth = float(rng.uniform(8.0, 12.0))
            height = float(rng.uniform(6.0, 18.0))
            tone = rng.uniform(0.25, 0.7)
            tint = rng.uniform(-0.08, 0.08, size=3)
            wall = Material(f"wall{s}{b}", tuple(np.clip(tone + tint, 0.05, 0.9).round(3)),
                            round(float(rng.uniform(0.6, 0.95)), 3), 0.0)
            bx = x + width / 2
            parts.append(Part(f"building{s}{b}", *geo.box((bx, side * (FACADE_Y + depth / 2), height / 2),
                                                          (width, depth, height)), wall))
            wins = []
            floors = int((height - 1.0) // 3.0)
            cols = int((width - 1.0) // 2.5)
            for fi in range(floors):
                for ci in range(cols):
                    wx = x + 1.25 + ci * 2.5 + 0.6
                    wz = 1.5 + fi * 3.0 + 0.75
                    wins.append(geo.box((wx, side * (FACADE_Y - 0.02), wz), (1.2, 0.06, 1.5)))
            if wins:
                parts.append(Part(f"windows{s}{b}", *geo.merge(wins), glass))
            x += width + float(rng.uniform(0.0, 2.0))
            b += 1

        # street light poles and trees on the sidewalk
        px = x0 + float(rng.uniform(2.0, 8.0))
        k = 0
        while px < x1:
            py = side * (ROAD_HALF_WIDTH + 0.7)
            pole = geo.merge([geo.cylinder((px, py, 0.0), 0.08, 6.0, 12),
                              geo.box((px, py - side * 0.75, 5.9), (0.15, 1.5, 0.1))])
            parts.append(Part(f"pole{s}{k}", *pole, pole_mat))
            tx = px + 7.0
            if tx < x1:
                ty = side * (ROAD_HALF_WIDTH + 2.0)
                parts.append(Part(f"planter{s}{k}", *geo.box((tx, ty, 0.35), (1.2, 1.2, 0.4)), planter_mat))
                parts.append(Part(f"trunk{s}{k}", *geo.cylinder((tx, ty, 0.5), 0.12, 2.6, 10), bark))
                parts.append(Part(f"crown{s}{k}", *geo.sphere((tx, ty, 3.8), float(rng.uniform(1.1, 1.6))), leaves))
            px += float(rng.uniform(16.0, 24.0))
            k += 1

    scene = StreetScene(parts)
    T = len(ego_x)
    zc = CAR_SIZE[2] / 2.0
    car_idx = 0
    # parked cars: static tracked objects, in front of the ego
    for i in range(cfg.num_parked_cars):
        side = 1 if i % 2 == 0 else -1
        px = float(ego_x[0]) + 8.0 + i * float(rng.uniform(5.5, 8.0))
        yaw = 0.0 if side < 0 else math.pi
        pose = _pose(px, side * PARKING_Y, zc, yaw)
        scene.cars.append(CarTrack(f"car{car_idx}", CAR_SIZE, _car_parts(rng, car_idx), {t: pose for t in range(T)}, False))
        car_idx += 1
    # moving cars: alternately oncoming and ahead in the ego lane
    for i in range(cfg.num_moving_cars):
        oncoming = i % 2 == 0
        if oncoming:
            speed = -float(rng.uniform(6.0, 10.0))
            start = float(ego_x[0]) + 25.0 + 10.0 * i
            y, yaw = ONCOMING_LANE_Y, math.pi
        else:
            speed = float(rng.uniform(0.6, 0.9)) * cfg.ego_speed
            start = float(ego_x[0]) + 10.0 + 6.0 * i
            y, yaw = EGO_LANE_Y, 0.0
        poses = {t: _pose(start + speed * t * cfg.frame_dt, y, zc, yaw) for t in range(T)}
        scene.cars.append(CarTrack(f"car{car_idx}", CAR_SIZE, _car_parts(rng, car_idx), poses, True))
        car_idx += 1
    return scene
