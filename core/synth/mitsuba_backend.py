"""Ground truth by Mitsuba 3 (CPU variant ``scalar_rgb``): an independent physically based renderer.

Nothing here uses this project's own renderer. Cameras come in the project's OpenCV convention and
are converted with :data:`core.conventions.OPENCV_TO_MITSUBA`; environment maps come in the
project's equirect convention and are handed to Mitsuba's ``envmap`` emitter with
``to_world = rotate(x, 90 deg)``, which reads them the same way (see core/conventions.py).
"""

from __future__ import annotations

import math

import numpy as np

from core.camera import Camera
from core.conventions import MITSUBA_ENVMAP_TO_WORLD_ROTATION_X_DEG, OPENCV_TO_MITSUBA
from core.errors import ConfigError, DependencyError, ShapeError
from core.numerics import require_finite_np
from core.synth.street import Material, Part
from core.synth.textures import texture_image

_MI = None


def mitsuba():
    """The ``mitsuba`` module with the ``scalar_rgb`` variant set (imported on first use)."""
    global _MI
    if _MI is None:
        try:
            import mitsuba as mi
        except ImportError as e:  # pragma: no cover - mitsuba is a declared dependency
            raise DependencyError("Mitsuba 3 is needed for ground truth: pip install mitsuba") from e
        mi.set_variant("scalar_rgb")
        mi.set_log_level(mi.LogLevel.Warn)
        _MI = mi
    return _MI


_TEXTURES: dict = {}


def albedo_texture(tex):
    """The Mitsuba ``bitmap`` texture (linear, bilinear, repeating) of a procedural
    :class:`core.synth.textures.AlbedoTexture`; one object per texture and process, shared by the
    BSDF and the albedo G-buffer."""
    if tex not in _TEXTURES:
        mi = mitsuba()
        if len(_TEXTURES) > 512:
            _TEXTURES.clear()
        _TEXTURES[tex] = mi.load_dict({"type": "bitmap", "bitmap": mi.Bitmap(texture_image(tex)), "raw": True,
                                       "filter_type": "bilinear", "wrap_mode": "repeat"})
    return _TEXTURES[tex]


def _bsdf(mat: Material) -> dict:
    colour = albedo_texture(mat.texture) if mat.texture is not None else {"type": "rgb", "value": list(mat.albedo)}
    if mat.model == "lambert":
        return {"type": "diffuse", "reflectance": colour}
    if mat.model != "principled":
        raise ConfigError(f"material.model: unknown model {mat.model!r}")
    return {
        "type": "principled",
        "base_color": colour,
        "roughness": float(mat.roughness),
        "metallic": float(mat.metallic),
        "specular": 0.5,  # F0 = 0.08 * specular = 0.04 for dielectrics, as the paper's BRDF
    }


def _mesh(part: Part):
    mi = mitsuba()
    v = np.ascontiguousarray(part.vertices, np.float32)
    f = np.ascontiguousarray(part.faces, np.uint32)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ShapeError(f"part {part.name}: vertices must be [V, 3] and faces [F, 3]")
    has_uv = part.uvs is not None
    if part.material.texture is not None and not has_uv:
        raise ConfigError(f"part {part.name}: a textured material needs uvs")
    if has_uv and np.shape(part.uvs) != (len(v), 2):
        raise ShapeError(f"part {part.name}: uvs must be [V, 2], got {list(np.shape(part.uvs))}")
    m = mi.Mesh(part.name, vertex_count=len(v), face_count=len(f), has_vertex_normals=False,
                has_vertex_texcoords=has_uv, props=_props_with_bsdf(part.material))
    params = mi.traverse(m)
    params["vertex_positions"] = type(params["vertex_positions"])(v.ravel())
    params["faces"] = type(params["faces"])(f.ravel())
    if has_uv:
        params["vertex_texcoords"] = type(params["vertex_texcoords"])(
            np.ascontiguousarray(part.uvs, np.float32).ravel())
    params.update()
    return m


def _props_with_bsdf(mat: Material):
    mi = mitsuba()
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(_bsdf(mat))
    return props


def _envmap(env: np.ndarray) -> dict:
    mi = mitsuba()
    env = np.asarray(env, np.float32)
    if env.ndim != 3 or env.shape[2] != 3 or env.shape[1] != 2 * env.shape[0]:
        raise ShapeError(f"envmap: expected [H, 2H, 3], got {list(env.shape)}")
    require_finite_np(env, "envmap")
    return {
        "type": "envmap",
        "bitmap": mi.Bitmap(np.ascontiguousarray(env)),
        "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], MITSUBA_ENVMAP_TO_WORLD_ROTATION_X_DEG),
    }


def _sensor(cam: Camera, sampler: dict, pixel_format: str = "rgb") -> dict:
    mi = mitsuba()
    if abs(cam.fx - cam.fy) > 1e-6 * cam.fx:
        raise ConfigError("camera: Mitsuba ground truth needs square pixels (fx == fy)")
    if abs(cam.cx - cam.width / 2) > 1e-6 or abs(cam.cy - cam.height / 2) > 1e-6:
        raise ConfigError("camera: Mitsuba ground truth needs a centred principal point")
    fov = math.degrees(2.0 * math.atan(cam.width / (2.0 * cam.fx)))
    to_world = cam.pose_numpy() @ OPENCV_TO_MITSUBA
    return {
        "type": "perspective",
        "fov": fov,
        "fov_axis": "x",
        "near_clip": 0.01,
        "far_clip": 10000.0,
        "to_world": mi.ScalarTransform4f(to_world.tolist()),
        "film": {"type": "hdrfilm", "width": int(cam.width), "height": int(cam.height),
                 "rfilter": {"type": "box"}, "pixel_format": pixel_format},
        "sampler": sampler,
    }


def _scene(parts: list[Part], integrator: dict, sensor: dict | None, env: np.ndarray | None):
    mi = mitsuba()
    d: dict = {"type": "scene", "integrator": integrator}
    if sensor is not None:
        d["sensor"] = sensor
    if env is not None:
        d["emitter"] = _envmap(env)
    names = set()
    for p in parts:
        if p.name in names:
            raise ConfigError(f"parts: duplicate part name {p.name!r}")
        names.add(p.name)
        d["shape_" + p.name.replace("/", "__")] = _mesh(p)
    return mi.load_dict(d)


def render_beauty(parts: list[Part], env: np.ndarray, cam: Camera, *, spp: int, max_depth: int,
                  seed: int = 0) -> np.ndarray:
    """Path-traced HDR radiance [H, W, 3] float32 (environment light only, ``max_depth`` bounces;
    ``max_depth = 2`` is direct illumination). Sky pixels show the environment."""
    mi = mitsuba()
    sampler = {"type": "independent", "sample_count": int(spp), "seed": int(seed)}
    integ = {"type": "path", "max_depth": int(max_depth), "hide_emitters": False}
    scene = _scene(parts, integ, _sensor(cam, sampler), env)
    img = np.array(mi.render(scene, seed=int(seed)), dtype=np.float32)
    img = img[..., :3]
    require_finite_np(img, "mitsuba render")
    return np.maximum(img, 0.0)


def render_gbuffers(parts: list[Part], cam: Camera, film_uv: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Ground-truth G-buffers sampled at pixel centres (one Mitsuba camera ray per pixel).

    ``film_uv`` [H', W', 2] (optional): sample these film positions of ``cam`` instead, as
    fractions (column, row) of its width and height in [0, 1]; the maps are then [H', W', ...]
    (a distorted lens's pixels, exactly on their rays: see core/synth/sensor.py).

    Returns albedo [H, W, 3], roughness [H, W, 1], metallic [H, W, 1], normal [H, W, 3] (world,
    unit, facing the camera), depth [H, W, 1] (camera z-depth, metres; 0 on sky), sky [H, W] bool.
    Camera rays come from Mitsuba's own sensor (so the camera convention is Mitsuba's, not ours)
    and materials from the hit shape's known :class:`Material`. (Mitsuba's ``aov`` integrator
    gives the same maps but is ~20x slower in scalar mode.)
    """
    mi = mitsuba()
    sampler = {"type": "independent", "sample_count": 1}
    scene = _scene(parts, {"type": "direct"}, _sensor(cam, sampler), None)
    sensor = scene.sensors()[0]
    by_id = {}
    for p_ in parts:
        by_id["shape_" + p_.name.replace("/", "__")] = p_.material
    if film_uv is None:
        H, W = cam.height, cam.width
        film_uv = np.stack(np.meshgrid((np.arange(W) + 0.5) / W, (np.arange(H) + 0.5) / H), -1)
    film_uv = np.asarray(film_uv, np.float64)
    if film_uv.ndim != 3 or film_uv.shape[2] != 2:
        raise ShapeError(f"film_uv: expected [H, W, 2], got {list(film_uv.shape)}")
    H, W = film_uv.shape[:2]
    hit = np.zeros((H, W), bool)
    n = np.zeros((H, W, 3))
    p = np.zeros((H, W, 3))
    albedo = np.zeros((H, W, 3))
    rough = np.zeros((H, W))
    metal = np.zeros((H, W))
    ap = mi.Point2f(0.5, 0.5)
    for r in range(H):
        for c in range(W):
            ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(float(film_uv[r, c, 0]), float(film_uv[r, c, 1])), ap)
            si = scene.ray_intersect(ray)
            if not si.is_valid():
                continue
            mat = by_id[si.shape.id()]
            hit[r, c] = True
            n[r, c] = si.sh_frame.n
            p[r, c] = si.p
            albedo[r, c] = mat.albedo if mat.texture is None else albedo_texture(mat.texture).eval(si)
            rough[r, c] = 1.0 if mat.model == "lambert" else mat.roughness
            metal[r, c] = 0.0 if mat.model == "lambert" else mat.metallic
    c2w = cam.pose_numpy()
    depth = np.where(hit, (p - c2w[:3, 3]) @ c2w[:3, 2], 0.0)
    # orient normals toward the camera (open meshes such as the road quad are one-sided anyway)
    flip = np.sum(n * (p - c2w[:3, 3]), axis=-1) > 0
    n = np.where(flip[..., None], -n, n)
    nn = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(hit[..., None] & (nn > 0), n / np.where(nn > 0, nn, 1.0), 0.0)
    return {
        "albedo": albedo.astype(np.float32),
        "roughness": rough[..., None].astype(np.float32),
        "metallic": metal[..., None].astype(np.float32),
        "normal": n.astype(np.float32),
        "depth": depth[..., None].astype(np.float32),
        "sky": ~hit,
    }


class RayCaster:
    """Mitsuba ray casting against a set of parts (for simulated LiDAR)."""

    def __init__(self, parts: list[Part]):
        self._scene = _scene(parts, {"type": "direct"}, None, None)

    def cast(self, origins: np.ndarray, dirs: np.ndarray, tmax: float) -> np.ndarray:
        """Distances [N] along unit ``dirs`` [N, 3] from ``origins`` [N, 3] (inf = no hit)."""
        mi = mitsuba()
        o = np.asarray(origins, np.float64)
        d = np.asarray(dirs, np.float64)
        out = np.full(len(d), np.inf)
        scene = self._scene
        for i in range(len(d)):
            ray = mi.Ray3f(mi.Point3f(*o[i]), mi.Vector3f(*d[i]))
            ray.maxt = tmax
            si = scene.ray_intersect_preliminary(ray)
            if si.is_valid():
                out[i] = si.t
        return out
