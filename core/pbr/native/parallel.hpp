// Work sharing of the kernels: items [0, n) in chunks taken from an atomic counter by the calling
// thread and nthreads - 1 std::threads (so one launch uses every core; no Python threads needed).

#pragma once

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <thread>
#include <vector>

namespace {

// Call range(tid, begin, end) for consecutive chunks of at most `chunk` items until [0, n) is
// done; tid in [0, nthreads) names the worker (for per-thread counters). One thread when
// nthreads <= 1 or n <= chunk.
template <class Range>
void parallel_chunks(int64_t n, int64_t chunk, int nthreads, const Range& range) {
    std::atomic<int64_t> next{0};
    auto work = [&](int tid) {
        for (;;) {
            int64_t b = next.fetch_add(chunk);
            if (b >= n) break;
            range(tid, b, std::min(n, b + chunk));
        }
    };
    if (nthreads <= 1 || n <= chunk) {
        work(0);
    } else {
        std::vector<std::thread> th;
        for (int t = 1; t < nthreads; ++t) th.emplace_back(work, t);
        work(0);
        for (auto& t : th) t.join();
    }
}

}  // namespace
