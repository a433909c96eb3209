// The paper's BRDF in float32 (twin of core.pbr.brdf): Cook-Torrance with GGX D, Schlick-Smith
// visibility and Schlick Fresnel plus a Lambert lobe (or, with burley, Burley's 2015 diffuse with
// retro-reflection, core.pbr.brdf.burley_diffuse_factor) and, with smith, the exact Smith G in
// place of Schlick-Smith's; sampling by the mixture of GGX VNDF
// (Heitz 2018) and a cosine lobe, and the mixture's pdf. Unit vectors; directions point away from
// the surface.

#pragma once

#include <algorithm>
#include <cmath>

#include "vec.hpp"

namespace {

constexpr float kGgxAlphaMin = 1e-3f;

struct Material {
    float albedo[3];
    float rough, metal, spec;  // clamped to [0, 1]; spec = microfacet scale
    float alpha, k;            // GGX alpha = max(R^2, alpha_min), Schlick-Smith k = (R+1)^2/8
    float f0[3];
    int burley;                // 1: the diffuse lobe is Burley's (retro-reflection), 0: Lambert
    int smith;                 // 1: exact separable Smith G of GGX, 0: Schlick-Smith k (the paper)
};

// Model bits of make_material (twin of core.pbr.brdf): bit 0 Burley's diffuse, bit 1 exact Smith G.
constexpr int kModelBurley = 1, kModelSmith = 2;

inline float clamp01(float x) { return x < 0.f ? 0.f : (x > 1.f ? 1.f : x); }

inline Material make_material(const float* a, float r, float m, float spec, int model = 0) {
    Material mt;
    mt.burley = (model & kModelBurley) ? 1 : 0;
    mt.smith = (model & kModelSmith) ? 1 : 0;
    r = clamp01(r);
    m = clamp01(m);
    for (int c = 0; c < 3; ++c) {
        mt.albedo[c] = clamp01(a[c]);
        mt.f0[c] = 0.04f * (1.f - m) + m * mt.albedo[c];
    }
    mt.rough = r;
    mt.metal = m;
    mt.spec = spec;
    mt.alpha = std::max(r * r, kGgxAlphaMin);
    mt.k = (r + 1.f) * (r + 1.f) / 8.f;
    return mt;
}

inline float ggx_d(float nh, float sin2, float alpha) {
    if (!(nh > 0.f)) return 0.f;
    float a2 = alpha * alpha;
    float den = sin2 + nh * nh * a2;
    den = std::max(den, a2);
    return a2 / (kPi * den * den);
}

// f(wi, wo) (1/sr) for unit n, wi, wo; zero unless both are above the surface.
inline void brdf_eval(const Material& mt, V3 n, V3 wi, V3 wo, float out[3]) {
    float nwi = dot(n, wi), nwo = dot(n, wo);
    if (!(nwi > 0.f && nwo > 0.f)) { out[0] = out[1] = out[2] = 0.f; return; }
    V3 h = normalize(wi + wo);
    float nh = dot(n, h);
    V3 c = cross(n, h);
    float d = ggx_d(nh, dot(c, c), mt.alpha);
    float ci = std::min(nwi, 1.f), co = std::min(nwo, 1.f);
    float vis;
    if (mt.smith) {  // G / (4 nwi nwo) = 1 / ((ci + sqrt(a2 + (1 - a2) ci^2)) (co + ...))
        float a2 = mt.alpha * mt.alpha;
        vis = 1.f / ((ci + std::sqrt(a2 + (1.f - a2) * ci * ci)) * (co + std::sqrt(a2 + (1.f - a2) * co * co)));
    } else {
        vis = 1.f / (4.f * (ci * (1.f - mt.k) + mt.k) * (co * (1.f - mt.k) + mt.k));
    }
    float oh = clamp01(dot(wo, h));
    float x = 1.f - oh, x2 = x * x, x5 = x2 * x2 * x;
    float dv = d * vis * mt.spec;
    float diff = (1.f - mt.metal) * kInvPi;
    if (mt.burley) {  // Burley 2015: (1 - Fi/2)(1 - Fo/2) + Rr (Fi + Fo + Fi Fo (Rr - 1)), Rr = 2 R (wo.h)^2
        float a = 1.f - std::min(nwi, 1.f), b = 1.f - std::min(nwo, 1.f);
        float fi = a * a * a * a * a, fo = b * b * b * b * b;
        float rr = 2.f * mt.rough * oh * oh;
        diff *= (1.f - 0.5f * fi) * (1.f - 0.5f * fo) + rr * (fi + fo + fi * fo * (rr - 1.f));
    }
    for (int ch = 0; ch < 3; ++ch) {
        float fr = mt.f0[ch] + (1.f - mt.f0[ch]) * x5;
        out[ch] = diff * mt.albedo[ch] + dv * fr;
    }
}

inline void tangent_frame(V3 n, V3& t, V3& b) {
    float sign = n.z >= 0.f ? 1.f : -1.f;
    float a = -1.f / (sign + n.z);
    float bb = n.x * n.y * a;
    t = {1.f + sign * n.x * n.x * a, sign * bb, -sign * n.x};
    b = {bb, sign + n.y * n.y * a, -n.y};
}

inline float lum3(const float* c) { return 0.2126f * c[0] + 0.7152f * c[1] + 0.0722f * c[2]; }

// probability of the VNDF lobe in the mixture (twin of brdf.specular_probability)
inline float spec_prob(const Material& mt, float nwo) {
    float x = 1.f - clamp01(nwo), x2 = x * x, x5 = x2 * x2 * x;
    float fr[3], dif[3];
    for (int c = 0; c < 3; ++c) {
        fr[c] = mt.f0[c] + (1.f - mt.f0[c]) * x5;
        dif[c] = (1.f - mt.metal) * mt.albedo[c];
    }
    float s = lum3(fr) * mt.spec, d = lum3(dif);
    float tot = s + d;
    if (!(tot > 1e-8f)) return 1.f;
    return clamp01(s / tot);
}

// GGX VNDF sampling (Heitz 2018) in the local frame; returns wi in world
inline V3 sample_vndf(V3 n, V3 t, V3 b, V3 wo, float alpha, float u1, float u2) {
    V3 wl = {dot(wo, t), dot(wo, b), std::fabs(dot(wo, n))};
    V3 vh = normalize(V3{alpha * wl.x, alpha * wl.y, wl.z});
    if (dot(vh, vh) < 0.5f) vh = {0.f, 0.f, 1.f};
    float lensq = vh.x * vh.x + vh.y * vh.y;
    V3 t1 = lensq > 1e-12f ? V3{-vh.y, vh.x, 0.f} * (1.f / std::sqrt(lensq)) : V3{1.f, 0.f, 0.f};
    V3 t2 = cross(vh, t1);
    float r = std::sqrt(u1), phi = 2.f * kPi * u2;
    float p1 = r * std::cos(phi), p2 = r * std::sin(phi);
    float s = 0.5f * (1.f + vh.z);
    p2 = (1.f - s) * std::sqrt(std::max(0.f, 1.f - p1 * p1)) + s * p2;
    V3 nh = t1 * p1 + t2 * p2 + vh * std::sqrt(std::max(0.f, 1.f - p1 * p1 - p2 * p2));
    V3 hl = normalize(V3{alpha * nh.x, alpha * nh.y, std::max(0.f, nh.z)});
    V3 wil = hl * (2.f * dot(wl, hl)) - wl;
    return normalize(t * wil.x + b * wil.y + n * wil.z);
}

inline float pdf_vndf(V3 n, V3 wi, V3 wo, float alpha) {
    float nwo = dot(n, wo);
    float c = std::fabs(nwo);
    V3 wom = nwo < 0.f ? wo - n * (2.f * nwo) : wo;
    V3 h = normalize(wi + wom);
    if (!(dot(wom, h) > 0.f)) return 0.f;
    float nh = dot(n, h);
    V3 cr = cross(n, h);
    float d = ggx_d(nh, dot(cr, cr), alpha);
    float a2 = alpha * alpha;
    return d / (2.f * (c + std::sqrt(a2 * (1.f - c * c) + c * c)));
}

inline V3 sample_cos(V3 n, V3 t, V3 b, float u1, float u2) {
    float r = std::sqrt(u1), phi = 2.f * kPi * u2;
    float z = std::sqrt(std::max(0.f, 1.f - u1));
    return normalize(t * (r * std::cos(phi)) + b * (r * std::sin(phi)) + n * z);
}

inline float pdf_mix(const Material& mt, float ps, V3 n, V3 wi, V3 wo) {
    float pc = std::max(dot(n, wi), 0.f) * kInvPi;
    float pv = ps > 0.f ? pdf_vndf(n, wi, wo, mt.alpha) : 0.f;
    return ps * pv + (1.f - ps) * pc;
}

}  // namespace
