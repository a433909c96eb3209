// The visibility cache of the integrator (clip reuse): lock-free open addressing over surface
// cells; each cell owns a block of `block` visibility values (uint16, V * 65533; 0xFFFF = not
// traced yet, 0xFFFE = retired), one per environment sample of the cell's run of pool directions.

#pragma once

#include <atomic>
#include <cstdint>

#include "rng.hpp"

namespace {

struct VisCache {
    int64_t cap;  // cells, a power of two
    int32_t block;
    std::atomic<uint64_t>* keys;
    std::atomic<uint16_t>* vals;  // [cap * block]
    std::atomic<int64_t> used{0};
};

constexpr uint16_t kUnknown = 0xFFFF;
constexpr uint16_t kAlwaysTrace = 0xFFFE;  // a cell/direction whose visibility differs across the cell
constexpr float kVisScale = 65533.f;       // stored visibility V -> round(V * kVisScale)
constexpr float kCheckDisagree = 0.25f;    // |V_true - V_cached| above which an entry is retired

// slot of a cell (inserted if new and the table is below 70% full), or -1
inline int64_t cache_cell(VisCache* c, uint64_t key) {
    if (key == 0) key = 1;
    int64_t mask = c->cap - 1;
    int64_t i = (int64_t)(mix64(key) & (uint64_t)mask);
    for (int probe = 0; probe < 64; ++probe) {
        uint64_t k = c->keys[i].load(std::memory_order_acquire);
        if (k == key) return i;
        if (k == 0) {
            if (c->used.load(std::memory_order_relaxed) * 10 > c->cap * 7) return -1;  // full: no insert
            uint64_t expected = 0;
            if (c->keys[i].compare_exchange_strong(expected, key, std::memory_order_acq_rel)) {
                c->used.fetch_add(1, std::memory_order_relaxed);
                return i;
            }
            if (expected == key) return i;
        }
        i = (i + 1) & mask;
    }
    return -1;
}

}  // namespace
