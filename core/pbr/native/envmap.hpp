// The environment map of the integrator (twin of core.pbr.envmap): bilinear radiance and the
// texel pdf of a direction, and importance sampling (alias table over texels, uniform in solid
// angle inside a texel).

#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "vec.hpp"

namespace {

struct Env {
    int H, W;
    const float* tex;    // [H, W, 4] radiance (exposure applied) and pdf (density over solid angle)
    const float* alias;  // [H * W, 2] alias probability, alias index (int32 bits)
    const float* cos_edge;  // [H + 1] cos(theta) of the row edges
    float cr, sr;        // cos / sin of the rotation about +z
    bool black;          // all zero: pdf is uniform, radiance 0
};

// world direction -> map direction (undo the rotation)
inline V3 to_map(const Env& e, V3 w) { return {e.cr * w.x + e.sr * w.y, -e.sr * w.x + e.cr * w.y, w.z}; }

inline void env_uv(const Env& e, V3 wm, float& u, float& v) {
    float l = std::sqrt(dot(wm, wm));
    float z = l > 0.f ? wm.z / l : 1.f;
    z = std::min(1.f, std::max(-1.f, z));
    float theta = std::acos(z);
    float phi = std::atan2(wm.y, wm.x);
    v = theta * kInvPi * e.H;
    float uu = 0.25f - phi * (0.5f * kInvPi);
    uu -= std::floor(uu);
    u = uu * e.W;
    if (u >= e.W) u -= e.W;
}

// bilinear radiance at continuous map coordinates (u in [0, W), v in [0, H])
inline void env_bilinear(const Env& e, float u, float v, float out[3]) {
    float x = u - 0.5f, y = v - 0.5f;
    float c0f = std::floor(x), r0f = std::floor(y);
    float fx = x - c0f, fy = y - r0f;
    int c0 = (int)c0f, r0 = (int)r0f;
    int ca = c0 < 0 ? c0 + e.W : (c0 >= e.W ? c0 - e.W : c0);
    int cb = ca + 1 == e.W ? 0 : ca + 1;
    int ra = std::min(std::max(r0, 0), e.H - 1), rb = std::min(std::max(r0 + 1, 0), e.H - 1);
    const float* p00 = e.tex + 4 * ((int64_t)ra * e.W + ca);
    const float* p01 = e.tex + 4 * ((int64_t)ra * e.W + cb);
    const float* p10 = e.tex + 4 * ((int64_t)rb * e.W + ca);
    const float* p11 = e.tex + 4 * ((int64_t)rb * e.W + cb);
    float w00 = (1 - fy) * (1 - fx), w01 = (1 - fy) * fx, w10 = fy * (1 - fx), w11 = fy * fx;
    for (int c = 0; c < 3; ++c) out[c] = w00 * p00[c] + w01 * p01[c] + w10 * p10[c] + w11 * p11[c];
}

inline float env_pdf_uv(const Env& e, float u, float v) {
    if (e.black) return 1.f / (4.f * kPi);
    int r = std::min(std::max((int)std::floor(v), 0), e.H - 1);
    int c = std::min(std::max((int)std::floor(u), 0), e.W - 1);
    return e.tex[4 * ((int64_t)r * e.W + c) + 3];
}

inline void env_lookup(const Env& e, V3 w, float out[3]) {
    float u, v;
    env_uv(e, to_map(e, w), u, v);
    env_bilinear(e, u, v, out);
}

inline float env_pdf(const Env& e, V3 w) {
    if (e.black) return 1.f / (4.f * kPi);
    float u, v;
    env_uv(e, to_map(e, w), u, v);
    return env_pdf_uv(e, u, v);
}

// radiance and pdf of a world direction with one (u, v) computation
inline float env_eval(const Env& e, V3 w, float out[3]) {
    float u, v;
    env_uv(e, to_map(e, w), u, v);
    env_bilinear(e, u, v, out);
    return env_pdf_uv(e, u, v);
}

// sample a direction; returns it with its pdf and (rad != nullptr) its bilinear radiance
inline V3 env_sample(const Env& e, float u0, float ucoin, float u1, float u2, float& pdf, float* rad = nullptr) {
    int64_t n = (int64_t)e.H * e.W;
    int64_t i;
    if (e.black) {  // uniform over the sphere
        float z = 1.f - 2.f * u1;
        float s = std::sqrt(std::max(0.f, 1.f - z * z));
        float ph = 2.f * kPi * u2;
        pdf = 1.f / (4.f * kPi);
        if (rad) rad[0] = rad[1] = rad[2] = 0.f;
        return {s * std::cos(ph), s * std::sin(ph), z};
    }
    i = std::min((int64_t)(u0 * (float)n), n - 1);
    const float* al = e.alias + 2 * i;
    if (ucoin >= al[0]) {
        int32_t j;
        __builtin_memcpy(&j, al + 1, 4);
        i = j;
    }
    int row = (int)(i / e.W), col = (int)(i - (int64_t)row * e.W);
    float c0 = e.cos_edge[row], c1 = e.cos_edge[row + 1];
    float ct = c0 + u1 * (c1 - c0);
    float st = std::sqrt(std::max(0.f, 1.f - ct * ct));
    float phi = 0.5f * kPi - 2.f * kPi * ((float)col + u2) / (float)e.W;
    float sp, cp;
    sincosf(phi, &sp, &cp);
    V3 wm = {st * cp, st * sp, ct};
    pdf = e.tex[4 * i + 3];
    if (rad) {
        // continuous map coordinates straight from the sample: u = col + u2, v from theta
        float v = std::acos(std::min(1.f, std::max(-1.f, ct))) * kInvPi * e.H;
        v = std::min(std::max(v, (float)row), (float)(row + 1));
        env_bilinear(e, (float)col + u2, v, rad);
    }
    return {e.cr * wm.x - e.sr * wm.y, e.sr * wm.x + e.cr * wm.y, wm.z};
}

}  // namespace
