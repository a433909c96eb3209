// The integrator's shadow rays: transmittance through the Gaussians (3DGRT maximum response) of
// up to three 8-wide BVHs (native/bvh.hpp: the static scene, moving nodes, edited objects), each
// with its own minimum ray distance t_min, with the Gaussians of each leaf stored SoA (14 float
// arrays in leaf order, padded by 16) so one AVX-512 pass tests up to 16 Gaussians of a leaf at
// once, in float32. Precision: each lane first moves the ray origin to the point of the ray
// closest to the Gaussian's mean (world metres), so the Mahalanobis terms stay small (no
// cancellation between ~1e4-sized terms in float32).

#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "bvh.hpp"
#include "simd.hpp"

namespace {

constexpr int kSoaArrays = 14;  // mux muy muz m00..m22 opacity r2max

typedef WideNode<8> Node8;

// Most BVHs one shadow ray goes through.
constexpr int kMaxBvhs = 3;

struct Bvh {
    const Node8* nodes;
    int64_t num_nodes;
    const float* soa;  // [14][npad]
    int64_t npad;
    float tmin;        // a ray ignores this BVH's Gaussians closer than this (metres)
};

struct TraceParams {
    float early_stop, max_alpha;
};

struct TStats {
    int64_t rays = 0, nodes = 0, leaves = 0;
};

// Multiply V by the transmittance of the Gaussians [first, first + cnt) of the SoA arrays.
inline float leaf_simd(const Bvh& b, int32_t first, int32_t cnt, const float o[3], const float d[3], float tmin,
                       float tmax, float max_alpha, float V) {
    const float* s = b.soa;
    const int64_t np = b.npad;
    const v16f lane = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15};
    for (int32_t base = first; base < first + cnt; base += 16) {
        v16f mx, my, mz, a0, a1, a2, a3, a4, a5, a6, a7, a8, op, r2;
        __builtin_memcpy(&mx, s + 0 * np + base, 64);
        __builtin_memcpy(&my, s + 1 * np + base, 64);
        __builtin_memcpy(&mz, s + 2 * np + base, 64);
        __builtin_memcpy(&a0, s + 3 * np + base, 64);
        __builtin_memcpy(&a1, s + 4 * np + base, 64);
        __builtin_memcpy(&a2, s + 5 * np + base, 64);
        __builtin_memcpy(&a3, s + 6 * np + base, 64);
        __builtin_memcpy(&a4, s + 7 * np + base, 64);
        __builtin_memcpy(&a5, s + 8 * np + base, 64);
        __builtin_memcpy(&a6, s + 9 * np + base, 64);
        __builtin_memcpy(&a7, s + 10 * np + base, 64);
        __builtin_memcpy(&a8, s + 11 * np + base, 64);
        __builtin_memcpy(&op, s + 12 * np + base, 64);
        __builtin_memcpy(&r2, s + 13 * np + base, 64);
        // closest approach to the mean in world space: t0 = (mu - o).d
        v16f ex = mx - o[0], ey = my - o[1], ez = mz - o[2];
        v16f t0 = ex * d[0] + ey * d[1] + ez * d[2];
        v16f rx = t0 * d[0] - ex, ry = t0 * d[1] - ey, rz = t0 * d[2] - ez;  // o + t0 d - mu
        v16f p0 = a0 * rx + a1 * ry + a2 * rz;
        v16f p1 = a3 * rx + a4 * ry + a5 * rz;
        v16f p2 = a6 * rx + a7 * ry + a8 * rz;
        v16f q0 = a0 * d[0] + a1 * d[1] + a2 * d[2];
        v16f q1 = a3 * d[0] + a4 * d[1] + a5 * d[2];
        v16f q2 = a6 * d[0] + a7 * d[1] + a8 * d[2];
        v16f aa = q0 * q0 + q1 * q1 + q2 * q2;
        v16f bb = p0 * q0 + p1 * q1 + p2 * q2;
        v16f safe_a = aa > splat(0.f) ? aa : splat(1.f);
        v16f tl = aa > splat(0.f) ? -bb / safe_a : splat(0.f);  // offset from t0
        v16f t = t0 + tl;
        t = t < splat(tmin) ? splat(tmin) : t;
        t = t > splat(tmax) ? splat(tmax) : t;
        v16f dt = t - t0;
        v16f x0 = p0 + dt * q0, x1 = p1 + dt * q1, x2 = p2 + dt * q2;
        v16f rr = x0 * x0 + x1 * x1 + x2 * x2;
        v16f alpha = op * vexp(splat(-0.5f) * rr);
        alpha = alpha > splat(max_alpha) ? splat(max_alpha) : alpha;
        v16i ok = (rr <= r2) & (lane < (float)(first + cnt - base));
        v16f tr = ok ? splat(1.f) - alpha : splat(1.f);
        // horizontal product (tree)
        typedef float v8f __attribute__((vector_size(32)));
        typedef float v4f_ __attribute__((vector_size(16)));
        v8f lo8 = __builtin_shufflevector(tr, tr, 0, 1, 2, 3, 4, 5, 6, 7);
        v8f hi8 = __builtin_shufflevector(tr, tr, 8, 9, 10, 11, 12, 13, 14, 15);
        v8f p8 = lo8 * hi8;
        v4f_ p4 = __builtin_shufflevector(p8, p8, 0, 1, 2, 3) * __builtin_shufflevector(p8, p8, 4, 5, 6, 7);
        V *= (p4[0] * p4[1]) * (p4[2] * p4[3]);
    }
    return V;
}

// Multiply V by the transmittance of one BVH along [b.tmin, tmax]; stops once V < early_stop.
inline float trace_bvh(const Bvh& b, const float o[3], const float d[3], float tmax, const TraceParams& tp, float V,
                       TStats& st) {
    const float tmin = b.tmin;
    if (b.num_nodes <= 0 || V < tp.early_stop || !(tmax >= tmin)) return V;
    float inv[3];
    for (int k = 0; k < 3; ++k) inv[k] = slab_inv(d[k]);
    const SlabRay<8> ray(o, inv, tmin, tmax);
    traverse<8>(b.nodes, ray, st.nodes, [&](int32_t first, int32_t cnt) {
        st.leaves++;
        V = leaf_simd(b, first, cnt, o, d, tmin, tmax, tp.max_alpha, V);
        return !(V < tp.early_stop);
    });
    return V;
}

// Visibility through up to kMaxBvhs BVHs (static background, moving nodes, edited objects): the
// product, each BVH over [its tmin, tmax].
inline float trace_bvhs(const Bvh* bv, int nb, const float o[3], const float d[3], float tmax, const TraceParams& tp,
                        TStats& st) {
    st.rays++;
    float V = 1.f;
    for (int i = 0; i < nb; ++i) {
        V = trace_bvh(bv[i], o, d, tmax, tp, V, st);
        if (V < tp.early_stop) break;
    }
    return V;
}

}  // namespace
