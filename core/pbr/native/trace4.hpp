// Shadow-ray transmittance through 3D Gaussians (3DGRT response) with a 4-wide BVH, for
// core.pbr.visibility (its C entry points bv_* are in _integrator.cpp, one shared object).
//
// V(ray) = prod_k (1 - alpha_k),  alpha_k = min(max_alpha, o_k * exp(-r2_k / 2)),
// r2_k = min over t in [tmin, tmax] of |M_k (origin + t dir - mu_k)|^2  (M_k = S^-1 R^T),
// counted only when r2_k <= r2max_k (the Gaussian's truncation radius, see visibility.py).
//
// BVH: native/bvh.hpp with 4-wide nodes (binned SAH binary build over the truncation boxes,
// collapsed so a ray tests 4 boxes with one SSE slab test; nearest hit child first so an
// occluder stops the ray early, V < early_stop). Per-Gaussian arithmetic is in double (float32 gave no measurable
// speed-up here); storage is float32 (64-byte records in leaf order). Rays are split over
// std::threads in chunks of 256 (native/parallel.hpp). No torch headers: plain C ABI, loaded with ctypes (which releases
// the GIL).
//
// Measured (2-core Xeon VM at ~2.5 GHz, shared with other jobs; synthetic street, 50k flat
// Gaussians, cosine rays from surface points): ~12.6 node visits, ~15.7 Gaussian tests and
// ~8.3 counted Gaussians per ray; ~1.1-1.5 us per ray per core, about 45% traversal and 55%
// Gaussian tests (exp, division, record cache misses).

#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "bvh.hpp"

namespace {

constexpr int kGaussFloats = 16;  // mu[3], M[9], opacity, r2max, pad[2]
typedef WideNode<4> Node4;

struct Stats { int64_t nodes = 0, tests = 0, hits = 0; };

// Count Gaussian j on the ray; returns false when the ray may stop (V < early_stop).
inline bool gaussian(const float* q, const double o[3], const double d[3], double tmin, double tmax,
                     double early_stop, double max_alpha, double& V, Stats& st) {
    st.tests++;
    double r0 = o[0] - q[0], r1 = o[1] - q[1], r2 = o[2] - q[2];
    double op0 = q[3] * r0 + q[4] * r1 + q[5] * r2;
    double op1 = q[6] * r0 + q[7] * r1 + q[8] * r2;
    double op2 = q[9] * r0 + q[10] * r1 + q[11] * r2;
    double dp0 = q[3] * d[0] + q[4] * d[1] + q[5] * d[2];
    double dp1 = q[6] * d[0] + q[7] * d[1] + q[8] * d[2];
    double dp2 = q[9] * d[0] + q[10] * d[1] + q[11] * d[2];
    double a = dp0 * dp0 + dp1 * dp1 + dp2 * dp2;
    double b = op0 * dp0 + op1 * dp1 + op2 * dp2;
    double t = a > 0.0 ? -b / a : tmin;
    t = std::min(std::max(t, tmin), tmax);
    double p0 = op0 + t * dp0, p1 = op1 + t * dp1, p2 = op2 + t * dp2;
    double rr = p0 * p0 + p1 * p1 + p2 * p2;
    if (rr <= (double)q[13]) {
        double alpha = std::min(max_alpha, (double)q[12] * std::exp(-0.5 * rr));
        V *= 1.0 - alpha;
        st.hits++;
        if (V < early_stop) return false;
    }
    return true;
}

float trace_one(const Node4* nodes, const float* g, const double o[3], const double d[3], double tmin,
                double tmax, double early_stop, double max_alpha, Stats& st) {
    float inv[3], of[3];
    for (int k = 0; k < 3; ++k) {
        inv[k] = slab_inv(d[k]);
        of[k] = (float)o[k];
    }
    const SlabRay<4> ray(of, inv, (float)tmin, (float)tmax);
    double V = 1.0;
    traverse<4>(nodes, ray, st.nodes, [&](int32_t first, int32_t cnt) {
        for (int32_t j = first; j < first + cnt; ++j)
            if (!gaussian(g + (int64_t)j * kGaussFloats, o, d, tmin, tmax, early_stop, max_alpha, V, st)) return false;
        return true;
    });
    return (float)V;
}

}  // namespace
