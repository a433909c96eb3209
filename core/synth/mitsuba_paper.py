"""The paper's BRDF inside Mitsuba 3, for ground truth with the same material model as the PBR
pass (paper supplement "Cook-Torrance BRDF derivation"; agreement with an independent renderer).

The synthetic street's parts carry albedo / roughness / metallic. :mod:`core.synth.mitsuba_backend`
renders them with Mitsuba's ``principled`` BSDF (Disney-style diffuse with retro-reflection,
exact Smith masking, its own Fresnel blend); the PBR pass evaluates the paper's Cook-Torrance
(Lambert + GGX with ``alpha = R^2``, Schlick-Smith ``k = (R+1)^2 / 8``, Schlick Fresnel with
``F0 = 0.04 (1-M) + M A``). To compare *renderers* rather than material models, this module
registers the paper's BRDF as a Mitsuba BSDF plugin (``"paper_brdf"``) and renders the mesh scene
with Mitsuba's own ``path`` integrator (``max_depth = 2``: direct illumination with Mitsuba's
environment-map importance sampling, its BSDF sampling and MIS, and its triangle ray tracing).
Nothing of this project's renderer runs here: the GGX distribution, its visible-normal sampling and
the cosine warp are Mitsuba's (``mi.MicrofacetDistribution``, ``mi.warp``); only the two closed-form
factors the paper defines (Schlick-Smith masking, Schlick Fresnel) are written out.

The plugin is vectorised with Dr.Jit, so it needs Mitsuba's ``llvm_ad_rgb`` variant (LLVM present
on the machine). The variant is process-global: :func:`render_direct_paper` switches to it and
back to ``scalar_rgb`` (what the rest of :mod:`core.synth.mitsuba_backend` uses), so call it from
one thread only.

Local frame (Mitsuba): ``si.wi`` points from the surface toward the camera (the paper's ``w_o``),
``wo`` toward the light (the paper's ``w_i``); both away from the surface. The BSDF is two-sided
(a back-facing hit is shaded as if its normal were flipped), as the PBR pass faces its normals
toward the camera.
"""

from __future__ import annotations

import glob
import os

import numpy as np

from core.camera import Camera
from core.errors import ConfigError, DependencyError, ShapeError
from core.numerics import GGX_ALPHA_MIN, require_finite_np
from core.synth.mitsuba_backend import _envmap, _sensor, mitsuba
from core.synth.street import Part

VARIANT = "llvm_ad_rgb"
PLUGIN = "paper_brdf"
_REGISTERED = False


def _register(mi) -> None:
    """Register the ``paper_brdf`` plugin for the current (vectorised) variant."""
    import drjit as dr

    # min/max through select: Dr.Jit lowers dr.minimum/maximum/clip to LLVM's fminimum/fmaximum,
    # which the system LLVM (14/15) cannot select for x86 in every case ("Cannot select: fminimum")
    def vmin(a, b):
        return dr.select(a < b, a, b)

    def vmax(a, b):
        return dr.select(a > b, a, b)

    class PaperBRDF(mi.BSDF):
        """The paper's Cook-Torrance BRDF: ``(1-M) A / pi + D F G / (4 n.l n.v)``."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            a = props.get("albedo", [0.5, 0.5, 0.5])
            self.albedo = mi.Color3f(float(a[0]), float(a[1]), float(a[2]))
            r = min(max(float(props.get("roughness", 0.5)), 0.0), 1.0)
            m = min(max(float(props.get("metallic", 0.0)), 0.0), 1.0)
            self.metal = m
            self.alpha = max(r * r, GGX_ALPHA_MIN)
            self.k = (r + 1.0) ** 2 / 8.0
            self.spec_scale = float(props.get("specular", 1.0))
            self.f0 = mi.Color3f(*[0.04 * (1.0 - m) + m * float(c) for c in a])
            # lobe selection: GGX visible normals with probability p_spec, else cosine
            self.p_spec = 1.0 if m >= 1.0 else min(0.9, max(0.1, 0.5 * (1.0 + m)))
            if self.spec_scale == 0.0:
                self.p_spec = 0.0
            self.distr = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, self.alpha, True)
            self.m_components = [mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide,
                                 mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide]
            self.m_flags = self.m_components[0] | self.m_components[1]

        # both directions on the side of si.wi (two-sided)
        @staticmethod
        def _flip(si, wo):
            s = dr.select(mi.Frame3f.cos_theta(si.wi) < 0, -1.0, 1.0)
            wi = mi.Vector3f(si.wi.x, si.wi.y, si.wi.z * s)
            wo_ = mi.Vector3f(wo.x, wo.y, wo.z * s)
            return wi, wo_

        def _f(self, v, l):
            nv, nl = mi.Frame3f.cos_theta(v), mi.Frame3f.cos_theta(l)
            front = (nv > 0) & (nl > 0)
            h = dr.normalize(v + l)
            d = self.distr.eval(h)
            k = self.k
            vis = 1.0 / (4.0 * (vmin(nl, 1.0) * (1.0 - k) + k) * (vmin(nv, 1.0) * (1.0 - k) + k))
            x = 1.0 - vmin(vmax(dr.dot(v, h), 0.0), 1.0)
            x5 = x * x * x * x * x
            fr = self.f0 + (1.0 - self.f0) * x5
            f = (1.0 - self.metal) * self.albedo * dr.inv_pi + self.spec_scale * d * vis * fr
            return dr.select(front, f, 0.0)

        def _pdf(self, v, l):
            nl = mi.Frame3f.cos_theta(l)
            h = dr.normalize(v + l)
            pdf_spec = self.distr.pdf(v, h) / vmax(4.0 * dr.abs(dr.dot(l, h)), 1e-12)
            pdf_cos = mi.warp.square_to_cosine_hemisphere_pdf(l)
            p = self.p_spec * pdf_spec + (1.0 - self.p_spec) * pdf_cos
            return dr.select((nl > 0) & (mi.Frame3f.cos_theta(v) > 0), p, 0.0)

        def sample(self, ctx, si, sample1, sample2, active=True):
            v, _ = self._flip(si, si.wi)
            s = dr.select(mi.Frame3f.cos_theta(si.wi) < 0, -1.0, 1.0)
            use_spec = sample1 < self.p_spec
            m, _ = self.distr.sample(v, sample2)
            l_spec = mi.reflect(v, m)
            l_cos = mi.warp.square_to_cosine_hemisphere(sample2)
            l = dr.select(use_spec, l_spec, l_cos)
            pdf = self._pdf(v, l)
            f = self._f(v, l)
            bs = mi.BSDFSample3f()
            bs.wo = mi.Vector3f(l.x, l.y, l.z * s)
            bs.pdf = pdf
            bs.eta = 1.0
            bs.sampled_type = dr.select(use_spec, mi.UInt32(+mi.BSDFFlags.GlossyReflection),
                                        mi.UInt32(+mi.BSDFFlags.DiffuseReflection))
            bs.sampled_component = dr.select(use_spec, mi.UInt32(0), mi.UInt32(1))
            ok = active & (pdf > 0) & (mi.Frame3f.cos_theta(l) > 0)
            w = f * mi.Frame3f.cos_theta(l) / vmax(pdf, 1e-20)
            return bs, dr.select(ok, w, 0.0)

        def eval(self, ctx, si, wo, active=True):
            v, l = self._flip(si, wo)
            return dr.select(active, self._f(v, l) * vmax(mi.Frame3f.cos_theta(l), 0.0), 0.0)

        def pdf(self, ctx, si, wo, active=True):
            v, l = self._flip(si, wo)
            return dr.select(active, self._pdf(v, l), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def traverse(self, callback):
            pass

        def to_string(self):
            return f"PaperBRDF[alpha={self.alpha}, metallic={self.metal}]"

    mi.register_bsdf(PLUGIN, lambda props: PaperBRDF(props))


def _find_llvm() -> str | None:
    """Path of a libLLVM new enough for Dr.Jit's kernels (>= 17; Debian's ``libllvm19``), or None."""
    for pat in ("/usr/lib/x86_64-linux-gnu/libLLVM.so.{v}*", "/usr/lib/x86_64-linux-gnu/libLLVM-{v}.so",
                "/usr/lib/llvm-{v}/lib/libLLVM*.so*", "/usr/lib/*/libLLVM-{v}.so"):
        for v in (21, 20, 19, 18, 17):
            hits = sorted(glob.glob(pat.format(v=v)))
            if hits:
                return hits[0]
    return None


class _Variant:
    """Context manager: Mitsuba in :data:`VARIANT` with the plugin registered, then back to scalar_rgb."""

    def __enter__(self):
        global _REGISTERED

        if not os.environ.get("DRJIT_LIBLLVM_PATH"):
            path = _find_llvm()
            if path is None:
                raise DependencyError("libLLVM >= 17 not found (Debian: apt-get install libllvm19); Mitsuba's "
                                      f"{VARIANT} variant needs it for the paper-BRDF ground truth")
            os.environ["DRJIT_LIBLLVM_PATH"] = path  # read once, when Dr.Jit's LLVM backend starts
        mi = mitsuba()
        if VARIANT not in mi.variants():
            raise DependencyError(f"Mitsuba variant {VARIANT} is not available (needed by the paper-BRDF ground truth)")
        try:
            mi.set_variant(VARIANT)
        except Exception as e:  # LLVM missing on the machine
            mi.set_variant("scalar_rgb")
            raise DependencyError(f"Mitsuba variant {VARIANT} cannot start (LLVM missing?): {e}") from e
        if not _REGISTERED:
            _register(mi)
            _REGISTERED = True
        return mi

    def __exit__(self, *exc):
        mitsuba().set_variant("scalar_rgb")
        return False


def _bsdf_dict(albedo, roughness: float, metallic: float, specular: float) -> dict:
    return {"type": PLUGIN, "albedo": [float(c) for c in albedo], "roughness": float(roughness),
            "metallic": float(metallic), "specular": float(specular)}


def plugin_eval_sample(albedo, roughness: float, metallic: float, v_local: np.ndarray, l_local: np.ndarray,
                       u1: np.ndarray, u2: np.ndarray) -> dict[str, np.ndarray]:
    """Run the plugin on arrays (for tests): ``v_local`` (camera side, ``si.wi``) and ``l_local``
    ``[N, 3]`` unit directions in the shading frame (normal +z), ``u1`` ``[N]`` and ``u2``
    ``[N, 2]`` uniforms. Returns ``eval`` ``[N, 3]`` (f cos(l)), ``pdf`` ``[N]`` of ``l``, and the
    sample drawn from ``v`` with ``(u1, u2)``: ``sample_dir`` ``[N, 3]``, ``sample_pdf`` ``[N]``,
    ``sample_weight`` ``[N, 3]`` (f cos / pdf), ``pdf_of_sample`` ``[N]`` (``pdf()`` at the sample)."""
    with _Variant() as mi:
        bsdf = mi.load_dict(_bsdf_dict(albedo, roughness, metallic, 1.0))
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*[np.ascontiguousarray(v_local[:, i], np.float32) for i in range(3)])
        ctx = mi.BSDFContext()
        lv = mi.Vector3f(*[np.ascontiguousarray(l_local[:, i], np.float32) for i in range(3)])
        ev = bsdf.eval(ctx, si, lv)
        pd = bsdf.pdf(ctx, si, lv)
        bs, w = bsdf.sample(ctx, si, mi.Float(np.ascontiguousarray(u1, np.float32)),
                            mi.Point2f(np.ascontiguousarray(u2[:, 0], np.float32),
                                       np.ascontiguousarray(u2[:, 1], np.float32)))
        pdf_s = bsdf.pdf(ctx, si, bs.wo)
        out = {"eval": np.array(ev), "pdf": np.array(pd), "sample_dir": np.array(bs.wo),
               "sample_pdf": np.array(bs.pdf), "sample_weight": np.array(w), "pdf_of_sample": np.array(pdf_s)}
    for k, a in out.items():
        if a.ndim == 2 and a.shape[0] == 3 and a.shape[1] != 3:
            out[k] = a.T
    return out


def _mesh(mi, part: Part, specular: float):
    v = np.ascontiguousarray(part.vertices, np.float32)
    f = np.ascontiguousarray(part.faces, np.uint32)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ShapeError(f"part {part.name}: vertices must be [V, 3] and faces [F, 3]")
    mat = part.material
    lam = mat.model == "lambert"
    bsdf = _bsdf_dict(mat.albedo, 1.0 if lam else mat.roughness, 0.0 if lam else mat.metallic,
                      0.0 if lam else specular)
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    m = mi.Mesh(part.name, vertex_count=len(v), face_count=len(f), has_vertex_normals=False,
                has_vertex_texcoords=False, props=props)
    params = mi.traverse(m)
    params["vertex_positions"] = type(params["vertex_positions"])(v.ravel())
    params["faces"] = type(params["faces"])(f.ravel())
    params.update()
    return m


def render_direct_paper(parts: list[Part], env: np.ndarray, cam: Camera, *, spp: int, seed: int = 0,
                        specular: float = 1.0) -> np.ndarray:
    """Mitsuba's direct illumination (``path``, ``max_depth = 2``) of ``parts`` lit by ``env``
    (``[H, 2H, 3]`` linear HDR, the project's equirect convention) with every part shaded by the
    paper's BRDF (``"lambert"`` parts: roughness 1, metallic 0, no microfacet term; ``specular``
    scales the microfacet term of the others). Returns HDR radiance ``[H, W, 3]`` float32; sky
    pixels show the environment. Box pixel filter, ``spp`` independent samples per pixel."""
    if isinstance(spp, bool) or not isinstance(spp, int) or spp < 1:
        raise ConfigError(f"spp: must be an int >= 1, got {spp!r}")
    if not 0.0 <= float(specular) <= 1.0:
        raise ConfigError(f"specular: must be in [0, 1], got {specular!r}")
    _envmap(env)  # raises on a malformed or non-finite map (scalar variant)
    with _Variant() as mi:
        d: dict = {"type": "scene", "integrator": {"type": "path", "max_depth": 2, "hide_emitters": False},
                   "sensor": _sensor(cam, {"type": "independent", "sample_count": int(spp), "seed": int(seed)}),
                   "emitter": _envmap(env)}
        names = set()
        for p in parts:
            if p.name in names:
                raise ConfigError(f"parts: duplicate part name {p.name!r}")
            names.add(p.name)
            d["shape_" + p.name.replace("/", "__")] = _mesh(mi, p, specular)
        scene = mi.load_dict(d)
        img = np.array(mi.render(scene, seed=int(seed)), dtype=np.float32)[..., :3]
    require_finite_np(img, "mitsuba render")
    return np.maximum(img, 0.0)
