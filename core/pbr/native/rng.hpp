// Random numbers of the integrator: PCG32 per point, seeded by hash(seed, point id).

#pragma once

#include <cstdint>

namespace {

inline uint64_t mix64(uint64_t x) {
    x ^= x >> 30; x *= 0xbf58476d1ce4e5b9ULL;
    x ^= x >> 27; x *= 0x94d049bb133111ebULL;
    x ^= x >> 31;
    return x;
}

struct Rng {
    uint64_t state, inc;
    Rng(uint64_t seed, uint64_t stream) : state(0), inc((mix64(stream) << 1u) | 1u) {
        next(); state += mix64(seed ^ 0x9e3779b97f4a7c15ULL); next();
    }
    uint32_t next() {
        uint64_t old = state;
        state = old * 6364136223846793005ULL + inc;
        uint32_t xs = (uint32_t)(((old >> 18u) ^ old) >> 27u);
        uint32_t rot = (uint32_t)(old >> 59u);
        return (xs >> rot) | (xs << ((-rot) & 31));
    }
    float uniform() { return (float)(next() >> 8) * (1.0f / 16777216.0f); }  // [0, 1)
};

}  // namespace
