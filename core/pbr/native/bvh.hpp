// The BVH of the shadow-ray kernels (trace4.hpp, shadow.hpp): one header-only template
// over the node width W.
//
// Build: binary, binned SAH (16 bins) over the Gaussians' truncation boxes, leaves of ~leaf_size
// primitives (SAH may keep up to 4x that when splitting does not pay); then collapsed to a W-wide
// tree whose nodes hold their children's boxes in SoA layout (one SIMD register per plane), so a
// ray tests W boxes with one slab test. Collapse: starting from a binary node's two children,
// repeatedly open the internal child with the largest surface area until W slots are filled.
// W = 4 (SSE, 128-byte nodes: the exact shadow rays of core.pbr.visibility) and W = 8 (AVX,
// 256-byte nodes: the integrator's, about half the node visits of W = 4).
//
// Traversal (traverse<W>): unordered in principle (the transmittance product commutes) but hit
// children are visited nearest first, so an occluder stops the ray early; the leaf test is the
// caller's (a functor returning false to stop the ray).
//
// The headers of core/pbr/native are included into each kernel's translation unit; their
// definitions have internal linkage (anonymous namespace), as when they lived in the .cpp files.

#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

namespace {

// binary BVH node (build only)
struct Node {
    float lo[3];
    int32_t first;  // leaf: first primitive; internal: index of the left child (right = +1)
    float hi[3];
    int32_t count;  // > 0: leaf with `count` primitives; 0: internal
};
static_assert(sizeof(Node) == 32, "Node must be 32 bytes");

constexpr int kBins = 16;
// Traversal stack: a W-wide node visited adds at most W - 1 entries. The Python side refuses
// binary trees deeper than 120, so 512 suffices for W = 4 (3 x 120); a ray that would overflow it
// (W = 8 on a degenerate tree) stops with the transmittance so far.
constexpr int kStack = 512;

struct Box {
    float lo[3], hi[3];
    void reset() {
        for (int i = 0; i < 3; ++i) { lo[i] = INFINITY; hi[i] = -INFINITY; }
    }
    void grow(const float* l, const float* h) {
        for (int i = 0; i < 3; ++i) { lo[i] = std::min(lo[i], l[i]); hi[i] = std::max(hi[i], h[i]); }
    }
    void grow(const Box& b) { grow(b.lo, b.hi); }
    float area() const {
        float d0 = hi[0] - lo[0], d1 = hi[1] - lo[1], d2 = hi[2] - lo[2];
        if (!(d0 >= 0.f)) return 0.f;
        return 2.f * (d0 * d1 + d1 * d2 + d2 * d0);
    }
};

struct Builder {
    const float* lo;
    const float* hi;
    std::vector<float> cen;
    std::vector<int32_t>& perm;
    std::vector<Node>& nodes;
    int leaf_size;

    Builder(const float* l, const float* h, int64_t n, int leaf, std::vector<int32_t>& p, std::vector<Node>& nd)
        : lo(l), hi(h), cen(3 * n), perm(p), nodes(nd), leaf_size(leaf) {
        for (int64_t i = 0; i < n; ++i)
            for (int k = 0; k < 3; ++k) cen[3 * i + k] = 0.5f * (lo[3 * i + k] + hi[3 * i + k]);
    }

    void set_bounds(Node& nd, int64_t b, int64_t e) {
        Box bx; bx.reset();
        for (int64_t i = b; i < e; ++i) bx.grow(lo + 3 * perm[i], hi + 3 * perm[i]);
        for (int k = 0; k < 3; ++k) { nd.lo[k] = bx.lo[k]; nd.hi[k] = bx.hi[k]; }
    }

    void build(int64_t n) {
        nodes.reserve(2 * n + 1);
        nodes.push_back(Node{});
        struct Item { int32_t node; int64_t b, e; };
        std::vector<Item> stack;
        stack.push_back({0, 0, n});
        while (!stack.empty()) {
            Item it = stack.back();
            stack.pop_back();
            Node nd{};
            set_bounds(nd, it.b, it.e);
            int64_t cnt = it.e - it.b;
            int64_t mid = -1;
            if (cnt > leaf_size) mid = split(it.b, it.e);
            if (mid < 0) {
                nd.first = (int32_t)it.b;
                nd.count = (int32_t)cnt;
                nodes[it.node] = nd;
                continue;
            }
            int32_t left = (int32_t)nodes.size();
            nodes.push_back(Node{});
            nodes.push_back(Node{});
            nd.first = left;
            nd.count = 0;
            nodes[it.node] = nd;
            stack.push_back({left, it.b, mid});
            stack.push_back({left + 1, mid, it.e});
        }
    }

    // Binned SAH split of perm[b, e); returns the split position or -1 for "make a leaf".
    int64_t split(int64_t b, int64_t e) {
        float clo[3] = {INFINITY, INFINITY, INFINITY}, chi[3] = {-INFINITY, -INFINITY, -INFINITY};
        for (int64_t i = b; i < e; ++i)
            for (int k = 0; k < 3; ++k) {
                float c = cen[3 * perm[i] + k];
                clo[k] = std::min(clo[k], c);
                chi[k] = std::max(chi[k], c);
            }
        int64_t cnt = e - b;
        float best = INFINITY;
        int best_axis = -1, best_bin = -1;
        for (int ax = 0; ax < 3; ++ax) {
            float ext = chi[ax] - clo[ax];
            if (!(ext > 0.f)) continue;
            Box bins[kBins];
            int64_t counts[kBins] = {0};
            for (auto& bb : bins) bb.reset();
            float scale = kBins / ext;
            for (int64_t i = b; i < e; ++i) {
                int32_t p = perm[i];
                int bi = std::min(kBins - 1, (int)((cen[3 * p + ax] - clo[ax]) * scale));
                counts[bi]++;
                bins[bi].grow(lo + 3 * p, hi + 3 * p);
            }
            float right_area[kBins];
            int64_t right_cnt[kBins];
            Box acc; acc.reset();
            int64_t c = 0;
            for (int i = kBins - 1; i > 0; --i) {
                acc.grow(bins[i]);
                c += counts[i];
                right_area[i] = acc.area();
                right_cnt[i] = c;
            }
            acc.reset();
            c = 0;
            for (int i = 0; i < kBins - 1; ++i) {
                acc.grow(bins[i]);
                c += counts[i];
                if (c == 0 || right_cnt[i + 1] == 0) continue;
                float cost = acc.area() * c + right_area[i + 1] * right_cnt[i + 1];
                if (cost < best) { best = cost; best_axis = ax; best_bin = i; }
            }
        }
        if (best_axis < 0) {
            // all centroids coincide: split in the middle if the leaf would be too big
            return cnt > 4 * leaf_size ? b + cnt / 2 : -1;
        }
        Box all; all.reset();
        for (int64_t i = b; i < e; ++i) all.grow(lo + 3 * perm[i], hi + 3 * perm[i]);
        // SAH with traversal cost 1 and intersection cost 1: leaf cost = cnt
        float leaf_cost = (float)cnt;
        float split_cost = 1.0f + best / std::max(all.area(), 1e-30f);
        if (split_cost >= leaf_cost && cnt <= 4 * leaf_size) return -1;
        float ext = chi[best_axis] - clo[best_axis];
        float scale = kBins / ext;
        auto mid = std::partition(perm.begin() + b, perm.begin() + e, [&](int32_t p) {
            int bi = std::min(kBins - 1, (int)((cen[3 * p + best_axis] - clo[best_axis]) * scale));
            return bi <= best_bin;
        });
        int64_t m = mid - perm.begin();
        if (m == b || m == e) return b + cnt / 2;
        return m;
    }
};

inline float node_area(const Node& n) {
    float d0 = n.hi[0] - n.lo[0], d1 = n.hi[1] - n.lo[1], d2 = n.hi[2] - n.lo[2];
    return 2.f * (d0 * d1 + d1 * d2 + d2 * d0);
}

// ------------------------------------------------------------------------------------------
// the W-wide tree
// ------------------------------------------------------------------------------------------
template <int W>
struct WideNode {
    static_assert(W == 4 || W == 8 || W == 16, "node width: 4, 8 or 16");
    static constexpr int kShift = W == 4 ? 2 : (W == 8 ? 3 : 4);  // log2(W)
    float b[6][W];      // lo x, y, z then hi x, y, z of the W children (empty: lo = +inf, hi = -inf)
    int32_t child[W];   // internal: node index; leaf: first primitive
    int32_t count[W];   // 0: internal; > 0: leaf with that many primitives; -1: empty slot
};
static_assert(sizeof(WideNode<4>) == 128, "WideNode<4> must be 128 bytes (core.pbr._native.NODE_BYTES)");
static_assert(sizeof(WideNode<8>) == 256, "WideNode<8> must be 256 bytes (core.pbr._native.NODE8_BYTES)");

// W floats / int32s in one GCC vector (SSE for 4, AVX for 8, AVX-512 for 16)
template <int W>
struct Lanes {
    typedef float f __attribute__((vector_size(4 * W)));
    typedef int32_t i __attribute__((vector_size(4 * W)));
    static f load(const float* p) {  // unaligned load (node buffers come from numpy)
        f v;
        __builtin_memcpy(&v, p, sizeof(v));
        return v;
    }
};

// Collapse the binary subtree at n2[i2] into out (depth first, a node before its children);
// returns the index of its root.
template <int W>
int32_t collapse(const std::vector<Node>& n2, int32_t i2, std::vector<WideNode<W>>& out) {
    int32_t me = (int32_t)out.size();
    out.push_back(WideNode<W>{});
    int32_t slots[W];
    int ns = 0;
    if (n2[i2].count > 0) {
        slots[ns++] = i2;  // a leaf root
    } else {
        slots[ns++] = n2[i2].first;
        slots[ns++] = n2[i2].first + 1;
        while (ns < W) {  // open the internal child with the largest surface area
            int best = -1;
            float ba = -1.f;
            for (int k = 0; k < ns; ++k)
                if (n2[slots[k]].count == 0 && node_area(n2[slots[k]]) > ba) { ba = node_area(n2[slots[k]]); best = k; }
            if (best < 0) break;
            int32_t c = n2[slots[best]].first;
            slots[best] = c;
            slots[ns++] = c + 1;
        }
    }
    WideNode<W> nd{};
    for (int k = 0; k < W; ++k) {
        if (k < ns) {
            const Node& c = n2[slots[k]];
            for (int a = 0; a < 3; ++a) { nd.b[a][k] = c.lo[a]; nd.b[3 + a][k] = c.hi[a]; }
            nd.count[k] = c.count;
            nd.child[k] = c.count > 0 ? c.first : -1;
        } else {
            for (int a = 0; a < 3; ++a) { nd.b[a][k] = INFINITY; nd.b[3 + a][k] = -INFINITY; }
            nd.count[k] = -1;
            nd.child[k] = -1;
        }
    }
    for (int k = 0; k < ns; ++k)
        if (nd.count[k] == 0) nd.child[k] = collapse<W>(n2, slots[k], out);  // may reallocate `out`
    out[me] = nd;
    return me;
}

// The W-wide BVH over n boxes (lo, hi: [n, 3] float32). perm_out: [n] int32 (primitive order in
// the leaves); nodes_out: capacity n + 1 WideNode<W>; depth_out: depth of the deepest leaf of the
// binary tree (root = 1). Returns the node count.
template <int W>
int64_t build_wide(const float* lo, const float* hi, int64_t n, int32_t leaf_size, int32_t* perm_out,
                   void* nodes_out, int32_t* depth_out) {
    *depth_out = 0;
    if (n <= 0) return 0;
    std::vector<int32_t> perm(n);
    for (int64_t i = 0; i < n; ++i) perm[i] = (int32_t)i;
    std::vector<Node> nodes;
    Builder bld(lo, hi, n, std::max(1, (int)leaf_size), perm, nodes);
    bld.build(n);
    std::memcpy(perm_out, perm.data(), sizeof(int32_t) * n);
    std::vector<WideNode<W>> wide;
    wide.reserve(nodes.size() / (W / 2) + 2);
    collapse<W>(nodes, 0, wide);
    std::memcpy(nodes_out, wide.data(), sizeof(WideNode<W>) * wide.size());
    std::vector<int32_t> depth(nodes.size(), 0);
    depth[0] = 1;
    int32_t dmax = 1;
    for (size_t i = 0; i < nodes.size(); ++i) {  // children always come after their parent
        if (nodes[i].count == 0) {
            depth[nodes[i].first] = depth[nodes[i].first + 1] = depth[i] + 1;
            dmax = std::max(dmax, depth[i] + 1);
        }
    }
    *depth_out = dmax;
    return (int64_t)wide.size();
}

// ------------------------------------------------------------------------------------------
// traversal
// ------------------------------------------------------------------------------------------
// 1 / d of one direction component for the slab test; a zero component gets a huge (finite)
// inverse: t is +-huge off the slab, 0 on its plane. T = double rounds the quotient to float.
template <class T>
inline float slab_inv(T d) {
    return d != T(0) ? (float)(T(1) / d) : (std::signbit(d) ? -1e30f : 1e30f);
}

// Per-ray constants of the W-wide slab test: t = (plane - o) * inv, with the near plane chosen by
// the sign of the direction (so no min/max per axis is needed).
template <int W>
struct SlabRay {
    typedef typename Lanes<W>::f vf;
    int near_[3], far_[3];
    vf ox, oy, oz, ix, iy, iz, t0v, t1v;

    // o: origin; inv: slab_inv of the direction; the segment [tmin, tmax] (tmax may be inf).
    SlabRay(const float o[3], const float inv[3], float tmin, float tmax) {
        for (int k = 0; k < 3; ++k) {
            near_[k] = inv[k] >= 0.f ? k : 3 + k;
            far_[k] = inv[k] >= 0.f ? 3 + k : k;
        }
        // boxes are tested in float: widen the segment by a relative margin so rounding never
        // culls a box the exact segment touches (the leaf tests clamp to the exact segment)
        const float ft0 = tmin - 1e-4f * (1.0f + std::fabs(tmin));
        const float ft1 = std::isinf(tmax) ? INFINITY : tmax * (1.0f + 1e-4f) + 1e-4f;
        ox = vf{} + o[0]; oy = vf{} + o[1]; oz = vf{} + o[2];
        ix = vf{} + inv[0]; iy = vf{} + inv[1]; iz = vf{} + inv[2];
        t0v = vf{} + ft0; t1v = vf{} + ft1;
    }
};

// Visit the leaves of the tree (nodes[0] is the root) whose boxes the ray's segment touches, hit
// children nearest first. leaf(first, count) tests the primitives [first, first + count) and
// returns false to stop the ray. Counts the internal nodes visited in `visits`. Returns false
// when the ray was stopped (by the leaf test, or by a full stack, see kStack). Always inlined: the caller (one function per leaf test) is the unit GCC
// sees, as when each kernel had its own traversal loop.
template <int W, class Leaf>
__attribute__((always_inline)) inline bool traverse(const WideNode<W>* nodes, const SlabRay<W>& r, int64_t& visits, Leaf&& leaf) {
    typedef typename Lanes<W>::f vf;
    typedef typename Lanes<W>::i vi;
    constexpr int kShift = WideNode<W>::kShift;
    int32_t stack[kStack];  // >= 0: node index; < 0: leaf slot -(node * W + slot) - 1
    int sp = 0;
    stack[sp++] = 0;
    while (sp > 0) {
        int32_t e = stack[--sp];
        if (e < 0) {
            int32_t id = -e - 1;
            const WideNode<W>& nd = nodes[id >> kShift];
            if (!leaf(nd.child[id & (W - 1)], nd.count[id & (W - 1)])) return false;
            continue;
        }
        const WideNode<W>& nd = nodes[e];
        visits++;
        vf txn = (Lanes<W>::load(nd.b[r.near_[0]]) - r.ox) * r.ix;
        vf txf = (Lanes<W>::load(nd.b[r.far_[0]]) - r.ox) * r.ix;
        vf tyn = (Lanes<W>::load(nd.b[r.near_[1]]) - r.oy) * r.iy;
        vf tyf = (Lanes<W>::load(nd.b[r.far_[1]]) - r.oy) * r.iy;
        vf tzn = (Lanes<W>::load(nd.b[r.near_[2]]) - r.oz) * r.iz;
        vf tzf = (Lanes<W>::load(nd.b[r.far_[2]]) - r.oz) * r.iz;
        vf tn = txn > tyn ? txn : tyn;
        tn = tn > tzn ? tn : tzn;
        tn = tn > r.t0v ? tn : r.t0v;
        vf tf = txf < tyf ? txf : tyf;
        tf = tf < tzf ? tf : tzf;
        tf = tf < r.t1v ? tf : r.t1v;
        vi hit = tn <= tf;
        // push hit children farthest first (so the nearest is popped first): insertion sort of <= W
        int idx[W];
        float key[W];
        int nh = 0;
        for (int k = 0; k < W; ++k) {
            if (!hit[k]) continue;
            int p = nh++;
            while (p > 0 && key[p - 1] < tn[k]) { key[p] = key[p - 1]; idx[p] = idx[p - 1]; --p; }
            key[p] = tn[k];
            idx[p] = k;
        }
        if (sp + nh > kStack) return false;
        for (int h = 0; h < nh; ++h) {
            int k = idx[h];
            stack[sp++] = nd.count[k] > 0 ? -(e * W + k) - 1 : nd.child[k];
        }
    }
    return true;
}

}  // namespace
