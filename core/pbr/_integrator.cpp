// Fused PBR integrator for core.pbr.integrator / core.pbr.render (issue 4): per shading point,
// sample the environment (alias table over texels, uniform in solid angle inside a texel) and the
// paper's BRDF (GGX VNDF + cosine lobe mixture), evaluate the paper's Cook-Torrance BRDF, combine
// with the power heuristic (multi-sample MIS), cast one shadow ray per contributing sample through
// the Gaussians (3DGRT maximum response, BVH, early stop), add point/spot lights with one
// deterministic shadow ray each, all in one pass per point. Threads (std::thread) take chunks of
// points from an atomic counter; the environment tables, the BVHs and the visibility cache are
// shared read-only (the cache is a lock-free hash table).
//
// The PyTorch twin is core.pbr.mis.estimate_reflected + core.pbr.lights.direct_lighting (same
// formulas; tests compare expectations and the deterministic pieces exported below).
//
// Shadow rays: the binary SAH build of _visibility.cpp (included below) collapsed to an 8-wide BVH
// (one AVX box test per node, about half the node visits of the 4-wide one); the
// Gaussians of each leaf are stored SoA (14 float arrays in leaf order, padded by 16) so one
// AVX-512 pass tests up to 16 Gaussians of a leaf at once, in float32. Precision: each lane first
// moves the ray origin to the point of the ray closest to the Gaussian's mean (world metres), so
// the Mahalanobis terms stay small (no cancellation between ~1e4-sized terms in float32).
//
// Units: world metres; radiance in the environment map's units; directions point away from the
// surface. Plain C ABI (ctypes releases the GIL).

#include "_visibility.cpp"

#include <cstdio>

namespace {

typedef float v16f __attribute__((vector_size(64)));
typedef int32_t v16i __attribute__((vector_size(64)));

constexpr float kPi = 3.14159265358979323846f;
constexpr float kInvPi = 0.31830988618379067154f;
constexpr int kSoaArrays = 14;  // mux muy muz m00..m22 opacity r2max
constexpr float kGgxAlphaMin = 1e-3f;
constexpr float kLightDistSqMin = 1e-4f;

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

// 8-wide BVH (AVX 8-lane box tests), collapsed from the same binary SAH build as Node4
typedef float v8f_ __attribute__((vector_size(32)));
typedef int32_t v8i_ __attribute__((vector_size(32)));

struct Node8 {
    float b[6][8];      // lo x, y, z then hi x, y, z of the 8 children (empty: lo = +inf, hi = -inf)
    int32_t child[8];   // internal: Node8 index; leaf: first primitive
    int32_t count[8];   // 0: internal; > 0: leaf; -1: empty slot
};
static_assert(sizeof(Node8) == 256, "Node8 must be 256 bytes");

inline v8f_ load8(const float* p) {
    v8f_ v;
    __builtin_memcpy(&v, p, sizeof(v));
    return v;
}

int32_t collapse8(const std::vector<Node>& n2, int32_t i2, std::vector<Node8>& out) {
    int32_t me = (int32_t)out.size();
    out.push_back(Node8{});
    int32_t slots[8];
    int ns = 0;
    if (n2[i2].count > 0) {
        slots[ns++] = i2;
    } else {
        slots[ns++] = n2[i2].first;
        slots[ns++] = n2[i2].first + 1;
        while (ns < 8) {
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
    Node8 nd{};
    for (int k = 0; k < 8; ++k) {
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
        if (nd.count[k] == 0) nd.child[k] = collapse8(n2, slots[k], out);
    out[me] = nd;
    return me;
}

struct Bvh {
    const Node8* nodes;
    int64_t num_nodes;
    const float* soa;  // [14][npad]
    int64_t npad;
};

struct TraceParams {
    float tmin, early_stop, max_alpha;
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

inline float trace_bvh(const Bvh& b, const float o[3], const float d[3], float tmin, float tmax,
                       const TraceParams& tp, float V, TStats& st) {
    if (b.num_nodes <= 0 || V < tp.early_stop) return V;
    float inv[3];
    int near_[3], far_[3];
    for (int k = 0; k < 3; ++k) {
        inv[k] = d[k] != 0.f ? 1.f / d[k] : (std::signbit(d[k]) ? -1e30f : 1e30f);
        near_[k] = inv[k] >= 0.f ? k : 3 + k;
        far_[k] = inv[k] >= 0.f ? 3 + k : k;
    }
    const float ft0 = tmin - 1e-4f * (1.0f + std::fabs(tmin));
    const float ft1 = std::isinf(tmax) ? INFINITY : tmax * (1.0f + 1e-4f) + 1e-4f;
    const v8f_ ox = v8f_{} + o[0], oy = v8f_{} + o[1], oz = v8f_{} + o[2];
    const v8f_ ix = v8f_{} + inv[0], iy = v8f_{} + inv[1], iz = v8f_{} + inv[2];
    const v8f_ t0v = v8f_{} + ft0, t1v = v8f_{} + ft1;
    int32_t stack[kStack];
    int sp = 0;
    stack[sp++] = 0;
    while (sp > 0) {
        int32_t e = stack[--sp];
        if (e < 0) {
            int32_t id = -e - 1;
            const Node8& nd = b.nodes[id >> 3];
            st.leaves++;
            V = leaf_simd(b, nd.child[id & 7], nd.count[id & 7], o, d, tmin, tmax, tp.max_alpha, V);
            if (V < tp.early_stop) return V;
            continue;
        }
        const Node8& nd = b.nodes[e];
        st.nodes++;
        v8f_ txn = (load8(nd.b[near_[0]]) - ox) * ix;
        v8f_ txf = (load8(nd.b[far_[0]]) - ox) * ix;
        v8f_ tyn = (load8(nd.b[near_[1]]) - oy) * iy;
        v8f_ tyf = (load8(nd.b[far_[1]]) - oy) * iy;
        v8f_ tzn = (load8(nd.b[near_[2]]) - oz) * iz;
        v8f_ tzf = (load8(nd.b[far_[2]]) - oz) * iz;
        v8f_ tn = txn > tyn ? txn : tyn;
        tn = tn > tzn ? tn : tzn;
        tn = tn > t0v ? tn : t0v;
        v8f_ tf = txf < tyf ? txf : tyf;
        tf = tf < tzf ? tf : tzf;
        tf = tf < t1v ? tf : t1v;
        v8i_ hit = tn <= tf;
        int idx[8];
        float key[8];
        int nh = 0;
        for (int k = 0; k < 8; ++k) {
            if (!hit[k]) continue;
            int p = nh++;
            while (p > 0 && key[p - 1] < tn[k]) { key[p] = key[p - 1]; idx[p] = idx[p - 1]; --p; }
            key[p] = tn[k];
            idx[p] = k;
        }
        if (sp + nh > kStack) return V;
        for (int h = 0; h < nh; ++h) {
            int k = idx[h];
            stack[sp++] = nd.count[k] > 0 ? -(e * 8 + k) - 1 : nd.child[k];
        }
    }
    return V;
}

// Visibility through up to two BVHs (e.g. static background + moving nodes): the product.
inline float trace2(const Bvh* bv, int nb, const float o[3], const float d[3], float tmin, float tmax,
                    const TraceParams& tp, TStats& st) {
    st.rays++;
    if (!(tmax >= tmin)) return 1.f;
    float V = 1.f;
    for (int i = 0; i < nb; ++i) {
        V = trace_bvh(bv[i], o, d, tmin, tmax, tp, V, st);
        if (V < tp.early_stop) break;
    }
    return V;
}

// ------------------------------------------------------------------------------------------
// random numbers: PCG32 per point, seeded by hash(seed, point id)
// ------------------------------------------------------------------------------------------
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

// ------------------------------------------------------------------------------------------
// vectors and the paper's BRDF (float32; twin of core.pbr.brdf)
// ------------------------------------------------------------------------------------------
struct V3 { float x, y, z; };
inline V3 operator+(V3 a, V3 b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
inline V3 operator-(V3 a, V3 b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
inline V3 operator*(V3 a, float s) { return {a.x * s, a.y * s, a.z * s}; }
inline float dot(V3 a, V3 b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline V3 cross(V3 a, V3 b) { return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x}; }
inline V3 normalize(V3 a) {
    float l2 = dot(a, a);
    if (!(l2 > 1e-24f)) return {0.f, 0.f, 0.f};
    return a * (1.f / std::sqrt(l2));
}
inline V3 load3(const float* p) { return {p[0], p[1], p[2]}; }

struct Material {
    float albedo[3];
    float rough, metal, spec;  // clamped to [0, 1]; spec = microfacet scale
    float alpha, k;            // GGX alpha = max(R^2, alpha_min), Schlick-Smith k = (R+1)^2/8
    float f0[3];
};

inline float clamp01(float x) { return x < 0.f ? 0.f : (x > 1.f ? 1.f : x); }

inline Material make_material(const float* a, float r, float m, float spec) {
    Material mt;
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
    float vis = 1.f / (4.f * (ci * (1.f - mt.k) + mt.k) * (co * (1.f - mt.k) + mt.k));
    float oh = clamp01(dot(wo, h));
    float x = 1.f - oh, x2 = x * x, x5 = x2 * x2 * x;
    float dv = d * vis * mt.spec;
    float diff = (1.f - mt.metal) * kInvPi;
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

// ------------------------------------------------------------------------------------------
// environment map
// ------------------------------------------------------------------------------------------
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

// ------------------------------------------------------------------------------------------
// visibility cache (clip reuse): lock-free open addressing over surface cells; each cell owns a
// block of `block` visibility values (uint16, V * 65533; 0xFFFF = not traced yet, 0xFFFE = retired), one per
// environment sample of the cell's run of pool directions
// ------------------------------------------------------------------------------------------
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

// ------------------------------------------------------------------------------------------
// the integrator
// ------------------------------------------------------------------------------------------
struct Params {
    int n_env, n_brdf;          // per pass (totals)
    int batch;                  // samples per adaptive batch (>= total: no adaptivity)
    float adapt_tol;            // LDR standard error to stop at (<= 0: off)
    int adapt_min_batches;
    float exposure, inv_gamma;
    float normal_offset;
    float specular;
    uint64_t seed;
    int cull_lights;
    // cache
    float cache_cell_px;        // cell size in pixel footprints (<= 0: no cache)
    float inv_fx;               // footprint per metre of depth
    int pool_size;              // env sample pool (cache mode)
    int cache_bvhs;             // leading BVHs (static) whose visibility the cache holds
    float mis_min_brdf;         // > 0: per-point MIS split, BRDF share clamp(ps, this, 1/2)
    float roulette;             // > 0: shadow-ray Russian roulette below this x the running mean
    float cache_check;          // > 0: re-trace a cache hit with this probability (unbiased correction)
};

struct Light {
    float pos[3], axis[3], radiant[3], cos_inner, cos_outer, range, spot;
};

struct PointIn {
    const float *pos, *nrm, *wo, *albedo, *rough, *metal, *weight, *bg, *depth;
    const int64_t* ids;  // random stream of each point (e.g. its pixel index), or null: the point index
};

struct Counters {
    int64_t samples = 0, shadow_rays = 0, cache_hits = 0, cache_lookups = 0, light_pairs = 0, light_evals = 0;
    int64_t roulette_skipped = 0;
    int64_t cache_checks = 0;
    TStats ts;
};

inline float ldr_slope(float y, const Params& P) {
    // d/dy (e y)^(1/g), capped where e y -> 0
    float ey = std::max(P.exposure * y, 1e-4f);
    if (ey >= 1.f) return 0.f;  // clipped to white: further error does not show
    return P.inv_gamma * std::pow(ey, P.inv_gamma - 1.f) * P.exposure;
}

void shade_point(int64_t i, const PointIn& in, const Env& env, const Bvh* bv, int nb, const TraceParams& tp,
                 const Light* lights, int nl, const Params& P, const float* pool_dir, const float* pool_pdf,
                 const float* pool_rad, VisCache* cache, float* out, int32_t* used, Counters& cnt) {
    V3 n = normalize(load3(in.nrm + 3 * i));
    V3 wo = normalize(load3(in.wo + 3 * i));
    V3 x = load3(in.pos + 3 * i);
    Material mt = make_material(in.albedo + 3 * i, in.rough[i], in.metal[i], P.specular);
    double acc[3] = {0, 0, 0};
    int used_samples = 0;
    bool degenerate = !(dot(n, n) > 0.5f);
    V3 org = x + n * P.normal_offset;
    float nwo = dot(n, wo);
    // ---- local lights (deterministic) ----
    for (int l = 0; l < nl && !degenerate; ++l) {
        const Light& L = lights[l];
        cnt.light_pairs++;
        V3 to = load3(L.pos) - x;
        float d2 = dot(to, to);
        V3 wl = normalize(to);
        float dist = std::sqrt(d2);
        float att = 1.f / std::max(d2, kLightDistSqMin);
        if (std::isfinite(L.range)) {
            float q = d2 / (L.range * L.range);
            float w = clamp01(1.f - q * q);
            att *= w * w;
        }
        if (L.spot > 0.5f) {
            float ca = -dot(wl, load3(L.axis));
            float e0 = L.cos_outer, e1 = L.cos_inner;
            float s;
            if (e1 <= e0) s = ca >= e0 ? 1.f : 0.f;
            else { float t = clamp01((ca - e0) / (e1 - e0)); s = t * t * (3.f - 2.f * t); }
            att *= s;
        }
        float cosl = dot(n, wl);
        if (P.cull_lights && (!(att > 0.f) || !(cosl > 0.f) || !(nwo > 0.f) ||
                              !(L.radiant[0] > 0.f || L.radiant[1] > 0.f || L.radiant[2] > 0.f)))
            continue;
        cnt.light_evals++;
        float f[3];
        brdf_eval(mt, n, wl, wo, f);
        float c = std::max(cosl, 0.f);
        float o[3] = {org.x, org.y, org.z}, dd[3] = {wl.x, wl.y, wl.z};
        float V = 1.f;
        if (dot(wl, wl) > 0.5f) {
            V = trace2(bv, nb, o, dd, tp.tmin, dist, tp, cnt.ts);
            cnt.shadow_rays++;
        }
        for (int ch = 0; ch < 3; ++ch) acc[ch] += (double)L.radiant[ch] * att * f[ch] * c * V;
    }
    // ---- environment (Monte Carlo, batches for adaptivity) ----
    const int total = P.n_env + P.n_brdf;
    double env_sum[3] = {0, 0, 0};
    double bsum = 0.0, bsum2 = 0.0;  // sums of per-batch luminance estimates
    int nbatches = 0;
    if (!degenerate && total > 0) {
        Rng rng(P.seed, in.ids ? (uint64_t)in.ids[i] : (uint64_t)i);
        V3 t, b;
        tangent_frame(n, t, b);
        float ps = spec_prob(mt, nwo);
        // per-point split (mis_min_brdf > 0): BRDF share = clamp(ps, min, 1/2) of the samples;
        // the MIS weights use the point's own counts, so any fixed split is unbiased (measured on
        // the benchmark street: no gain over the even split, so the PBR pass does not use it)
        int n_env_pt = P.n_env;
        if (P.mis_min_brdf > 0.f && P.n_env > 0 && P.n_brdf > 0) {
            float share = std::min(0.5f, std::max(P.mis_min_brdf, ps));
            int nbp = std::max(1, (int)std::lround(share * (float)total));
            n_env_pt = std::max(1, total - nbp);
        }
        // cache mode: a cell of the surface point and its pool offset
        bool use_cache = cache != nullptr && P.cache_cell_px > 0.f && pool_dir != nullptr && P.cache_bvhs > 0;
        uint64_t cell_key = 0;
        uint32_t pool_off = 0;
        int64_t cell_slot = -1;
        if (use_cache) {
            float size = std::max(P.cache_cell_px * in.depth[i] * P.inv_fx, 1e-3f);
            int level = (int)std::ceil(std::log2(size / 1e-3f));
            float cs = 1e-3f * std::ldexp(1.f, level);
            int64_t cx = (int64_t)std::floor(x.x / cs), cy = (int64_t)std::floor(x.y / cs),
                    cz = (int64_t)std::floor(x.z / cs);
            // the cell also keys the normal's octant so both sides of a thin wall never share
            int oct = (n.x > 0) | ((n.y > 0) << 1) | ((n.z > 0) << 2);
            cell_key = mix64(mix64(mix64((uint64_t)cx * 0x9E3779B97F4A7C15ULL ^ (uint64_t)cy) ^ (uint64_t)cz) ^
                             ((uint64_t)level << 8 | (uint64_t)oct));
            pool_off = (uint32_t)(cell_key % (uint64_t)P.pool_size);
            cell_slot = cache_cell(cache, cell_key);
        }
        int batch = std::max(1, std::min(P.batch, total));
        double g_sum = 0.0;
        int64_t g_count = 0;
        int done = 0, env_done = 0;
        while (done < total) {
            int nb_s = std::min(batch, total - done);
            // split this batch between env and BRDF samples in the overall ratio
            int ne = (int)((int64_t)(done + nb_s) * n_env_pt / total) - (int)((int64_t)done * n_env_pt / total);
            int nbr = nb_s - ne;
            double bacc[3] = {0, 0, 0};
            for (int s = 0; s < nb_s; ++s) {
                bool is_env = s < ne;
                V3 wi;
                float pe, pb;
                float rad[3];
                bool from_pool = false;
                if (is_env) {
                    if (use_cache) {
                        int j = (int)((pool_off + (uint32_t)(env_done)) % (uint32_t)P.pool_size);
                        wi = load3(pool_dir + 3 * j);
                        pe = pool_pdf[j];
                        rad[0] = pool_rad[3 * j]; rad[1] = pool_rad[3 * j + 1]; rad[2] = pool_rad[3 * j + 2];
                        from_pool = true;
                    } else {
                        float u0 = rng.uniform(), uc = rng.uniform(), u1 = rng.uniform(), u2 = rng.uniform();
                        wi = env_sample(env, u0, uc, u1, u2, pe, rad);
                    }
                    env_done++;
                    pb = nbr > 0 ? pdf_mix(mt, ps, n, wi, wo) : 0.f;
                } else {
                    float ul = rng.uniform(), u1 = rng.uniform(), u2 = rng.uniform();
                    wi = ul < ps ? sample_vndf(n, t, b, wo, mt.alpha, u1, u2) : sample_cos(n, t, b, u1, u2);
                    pb = pdf_mix(mt, ps, n, wi, wo);
                    if (!(dot(n, wi) > 0.f)) { cnt.samples++; continue; }  // below the horizon: f = 0
                    pe = env_eval(env, wi, rad);
                    if (ne == 0) pe = 0.f;
                }
                cnt.samples++;
                float cosi = dot(n, wi);
                if (!(cosi > 0.f)) continue;
                float f[3];
                brdf_eval(mt, n, wi, wo, f);
                float coef;
                float own = is_env ? (float)ne * pe : (float)nbr * pb;
                if (ne > 0 && nbr > 0) {
                    float a = (float)ne * pe, bq = (float)nbr * pb;
                    float den = a * a + bq * bq;
                    coef = den > 0.f ? own / den : 0.f;
                } else {
                    coef = own > 0.f ? 1.f / own : 0.f;
                }
                float g[3];
                float gmax = 0.f;
                for (int ch = 0; ch < 3; ++ch) {
                    g[ch] = f[ch] * rad[ch] * cosi * coef;
                    gmax = std::max(gmax, g[ch]);
                }
                if (!(gmax > 0.f) || !std::isfinite(gmax)) continue;
                // shadow-ray Russian roulette (unbiased): a sample whose unoccluded contribution is
                // small next to the point's running mean is traced with probability q and
                // weighted 1/q (PBRSettings.roulette; measured on the benchmark street at 0.5:
                // 23% fewer rays, 16% less time on an idle machine)
                float rr_w = 1.f;
                if (P.roulette > 0.f) {
                    float gl = 0.2126f * g[0] + 0.7152f * g[1] + 0.0722f * g[2];
                    double mean_g = g_count > 0 ? g_sum / g_count : 0.0;
                    g_sum += gl;
                    g_count++;
                    if (g_count > 4) {
                        float tau = (float)(P.roulette * mean_g);
                        float q = tau > 0.f ? std::min(1.f, gl / tau) : 1.f;
                        if (q < 1.f) {
                            q = std::max(q, 0.05f);
                            if (rng.uniform() >= q) { cnt.roulette_skipped++; continue; }
                            rr_w = 1.f / q;
                        }
                    }
                }
                float V = -1.f;
                std::atomic<uint16_t>* cv = nullptr;
                if (from_pool && cell_slot >= 0 && env_done - 1 < cache->block) {
                    cv = cache->vals + cell_slot * cache->block + (env_done - 1);
                    cnt.cache_lookups++;
                    uint16_t q = cv->load(std::memory_order_acquire);
                    if (q == kAlwaysTrace) {
                        cv = nullptr;  // retired entry: trace, never store
                    } else if (q != kUnknown) {
                        V = (float)q * (1.f / kVisScale);
                        cnt.cache_hits++;
                    }
                }
                float o[3] = {org.x, org.y, org.z}, dd[3] = {wi.x, wi.y, wi.z};
                if (from_pool) {
                    // the cache holds the visibility through the static BVHs only (the first
                    // P.cache_bvhs); moving nodes are traced every time
                    if (V < 0.f) {
                        V = trace2(bv, P.cache_bvhs, o, dd, tp.tmin, INFINITY, tp, cnt.ts);
                        cnt.shadow_rays++;
                        if (cv) cv->store((uint16_t)std::lround(clamp01(V) * kVisScale), std::memory_order_release);
                    } else if (P.cache_check > 0.f && rng.uniform() < P.cache_check) {
                        // spot check of a hit: trace this point's own visibility; an entry that
                        // disagrees (a shadow edge crosses the cell in this direction) is retired
                        // so every later lookup traces: the cache keeps only the cell/direction
                        // pairs whose visibility is the same across the cell
                        float Vt = trace2(bv, P.cache_bvhs, o, dd, tp.tmin, INFINITY, tp, cnt.ts);
                        cnt.shadow_rays++;
                        cnt.cache_checks++;
                        if (std::fabs(Vt - V) > kCheckDisagree) cv->store(kAlwaysTrace, std::memory_order_release);
                        V = Vt;
                    }
                    if (nb > P.cache_bvhs && V >= tp.early_stop) {
                        float Vd = trace2(bv + P.cache_bvhs, nb - P.cache_bvhs, o, dd, tp.tmin, INFINITY, tp, cnt.ts);
                        V *= Vd;
                        cnt.shadow_rays++;
                    }
                } else {
                    V = trace2(bv, nb, o, dd, tp.tmin, INFINITY, tp, cnt.ts);
                    cnt.shadow_rays++;
                }
                for (int ch = 0; ch < 3; ++ch) bacc[ch] += (double)g[ch] * V * rr_w;
            }
            done += nb_s;
            nbatches++;
            for (int ch = 0; ch < 3; ++ch) env_sum[ch] += bacc[ch] * nb_s;  // weight by batch size
            // batch estimate = bacc (already normalised per batch through coef)
            double y = 0.2126 * bacc[0] + 0.7152 * bacc[1] + 0.0722 * bacc[2];
            bsum += y;
            bsum2 += y * y;
            if (P.adapt_tol > 0.f && nbatches >= P.adapt_min_batches && done < total) {
                double mean = bsum / nbatches;
                double var = std::max(0.0, bsum2 / nbatches - mean * mean) * nbatches / std::max(1, nbatches - 1);
                double se = std::sqrt(var / nbatches);
                float w = in.weight[i];
                float ctot = in.bg[i] + w * (float)std::max(mean, 0.0);
                double err = ldr_slope(ctot, P) * w * se;
                if (err < P.adapt_tol) break;
            }
        }
        used_samples = done;
        if (done > 0)
            for (int ch = 0; ch < 3; ++ch) acc[ch] += env_sum[ch] / done;
    }
    for (int ch = 0; ch < 3; ++ch) {
        float v = (float)acc[ch];
        out[3 * i + ch] = std::isfinite(v) && v > 0.f ? v : (std::isinf(v) && v > 0.f ? 3.0e38f : 0.f);
    }
    if (used) used[i] = used_samples;
}

}  // namespace

extern "C" {

int pi_abi_version() { return 9; }

// Alias table (Vose) of n probabilities (float64, sum > 0): aprob [n] float32, aidx [n] int32
// (the caller interleaves them into the kernel's [n, 2] alias records).
void pi_build_alias(const double* prob, int64_t n, float* aprob, int32_t* aidx) {
    double tot = 0.0;
    for (int64_t i = 0; i < n; ++i) tot += prob[i];
    std::vector<double> q(n);
    std::vector<int64_t> small, large;
    small.reserve(n);
    large.reserve(n);
    for (int64_t i = 0; i < n; ++i) {
        q[i] = tot > 0 ? prob[i] / tot * (double)n : 1.0;
        (q[i] < 1.0 ? small : large).push_back(i);
    }
    while (!small.empty() && !large.empty()) {
        int64_t s = small.back(); small.pop_back();
        int64_t l = large.back();
        aprob[s] = (float)q[s];
        aidx[s] = (int32_t)l;
        q[l] = (q[l] + q[s]) - 1.0;
        if (q[l] < 1.0) { large.pop_back(); small.push_back(l); }
    }
    for (int64_t l : large) { aprob[l] = 1.0f; aidx[l] = (int32_t)l; }
    for (int64_t s : small) { aprob[s] = 1.0f; aidx[s] = (int32_t)s; }
}

// 8-wide BVH over n boxes (the binary SAH build of bv_build, collapsed to Node8): perm_out [n]
// int32 (leaf order), nodes_out capacity n + 1 Node8 (256 bytes each). Returns the Node8 count.
int64_t pi_build8(const float* lo, const float* hi, int64_t n, int32_t leaf_size, int32_t* perm_out, void* nodes_out,
                  int32_t* depth_out) {
    *depth_out = 0;
    if (n <= 0) return 0;
    std::vector<int32_t> perm(n);
    for (int64_t i = 0; i < n; ++i) perm[i] = (int32_t)i;
    std::vector<Node> nodes;
    Builder bld(lo, hi, n, std::max(1, (int)leaf_size), perm, nodes);
    bld.build(n);
    std::memcpy(perm_out, perm.data(), sizeof(int32_t) * n);
    std::vector<Node8> wide;
    wide.reserve(nodes.size() / 4 + 2);
    collapse8(nodes, 0, wide);
    std::memcpy(nodes_out, wide.data(), sizeof(Node8) * wide.size());
    std::vector<int32_t> depth(nodes.size(), 0);
    depth[0] = 1;
    int32_t dmax = 1;
    for (size_t i = 0; i < nodes.size(); ++i)
        if (nodes[i].count == 0) {
            depth[nodes[i].first] = depth[nodes[i].first + 1] = depth[i] + 1;
            dmax = std::max(dmax, depth[i] + 1);
        }
    *depth_out = dmax;
    return (int64_t)wide.size();
}

// A cache of 2^log2_cap surface cells with `block` visibility values each.
void* pi_cache_create(int64_t log2_cap, int32_t block) {
    VisCache* c = new VisCache();
    c->cap = (int64_t)1 << std::max<int64_t>(10, std::min<int64_t>(log2_cap, 30));
    c->block = std::max(1, (int)block);
    c->keys = new std::atomic<uint64_t>[c->cap];
    c->vals = new std::atomic<uint16_t>[c->cap * c->block];
    for (int64_t i = 0; i < c->cap; ++i) c->keys[i].store(0, std::memory_order_relaxed);
    for (int64_t i = 0; i < c->cap * c->block; ++i) c->vals[i].store(kUnknown, std::memory_order_relaxed);
    return c;
}

int64_t pi_cache_size(void* p) { return p ? static_cast<VisCache*>(p)->used.load() : 0; }

void pi_cache_free(void* p) {
    VisCache* c = static_cast<VisCache*>(p);
    if (!c) return;
    delete[] c->keys;
    delete[] c->vals;
    delete c;
}

// Shadow rays through up to 2 BVHs with the SIMD leaf test (for tests / benchmarks).
// bvh_nodes[2], bvh_num[2], bvh_soa[2], bvh_npad[2]; out [nrays]; stats int64[3]
void pi_trace(const void* const* bvh_nodes, const int64_t* bvh_num, const float* const* bvh_soa,
              const int64_t* bvh_npad, int32_t nbvh, const float* origins, const float* dirs, const float* tmax,
              int64_t nrays, float tmin, float early_stop, float max_alpha, int32_t nthreads, float* out,
              int64_t* stats) {
    Bvh bv[2];
    int nb = std::min(2, (int)nbvh);
    for (int k = 0; k < nb; ++k) bv[k] = {static_cast<const Node8*>(bvh_nodes[k]), bvh_num[k], bvh_soa[k], bvh_npad[k]};
    TraceParams tp{tmin, early_stop, max_alpha};
    std::atomic<int64_t> next{0};
    int nt = std::max(1, (int)nthreads);
    std::vector<TStats> st(nt);
    auto work = [&](int tid) {
        for (;;) {
            int64_t b0 = next.fetch_add(256);
            if (b0 >= nrays) break;
            int64_t e0 = std::min(nrays, b0 + 256);
            for (int64_t i = b0; i < e0; ++i) {
                float o[3] = {origins[3 * i], origins[3 * i + 1], origins[3 * i + 2]};
                V3 d = normalize(load3(dirs + 3 * i));
                float dd[3] = {d.x, d.y, d.z};
                float t1 = tmax ? tmax[i] : INFINITY;
                out[i] = dot(d, d) > 0.5f ? trace2(bv, nb, o, dd, tmin, t1, tp, st[tid]) : 1.f;
            }
        }
    };
    if (nt == 1 || nrays <= 256) work(0);
    else {
        std::vector<std::thread> th;
        for (int t = 1; t < nt; ++t) th.emplace_back(work, t);
        work(0);
        for (auto& t : th) t.join();
    }
    if (stats) {
        stats[0] = stats[1] = stats[2] = 0;
        for (auto& s : st) { stats[0] += s.rays; stats[1] += s.nodes; stats[2] += s.leaves; }
    }
}

// Deterministic pieces for the twin tests: f [m, 3], pdf_mix [m], env lookup [m, 3], env pdf [m].
void pi_eval(const float* n, const float* wi, const float* wo, const float* albedo, const float* rough,
             const float* metal, float specular, int64_t m, float* f_out, float* pdf_out) {
    for (int64_t i = 0; i < m; ++i) {
        Material mt = make_material(albedo + 3 * i, rough[i], metal[i], specular);
        V3 nn = normalize(load3(n + 3 * i)), a = normalize(load3(wi + 3 * i)), b = normalize(load3(wo + 3 * i));
        brdf_eval(mt, nn, a, b, f_out + 3 * i);
        if (pdf_out) pdf_out[i] = dot(nn, nn) > 0.5f ? pdf_mix(mt, spec_prob(mt, dot(nn, b)), nn, a, b) : 0.f;
    }
}

void pi_env_eval(int32_t H, int32_t W, const float* tex, const float* alias, const float* cos_edge, float rot_rad,
                 int32_t black, const float* dirs, int64_t m, float* rad_out, float* pdf_out) {
    Env e{H, W, tex, alias, cos_edge, std::cos(rot_rad), std::sin(rot_rad), black != 0};
    for (int64_t i = 0; i < m; ++i) {
        V3 d = load3(dirs + 3 * i);
        env_lookup(e, d, rad_out + 3 * i);
        pdf_out[i] = env_pdf(e, d);
    }
}

// Draw m environment samples (dirs [m, 3], pdf [m], radiance [m, 3]) with seed (pool of the cache).
void pi_env_sample(int32_t H, int32_t W, const float* tex, const float* alias, const float* cos_edge, float rot_rad,
                   int32_t black, uint64_t seed, int64_t m, float* dirs_out, float* pdf_out, float* rad_out) {
    Env e{H, W, tex, alias, cos_edge, std::cos(rot_rad), std::sin(rot_rad), black != 0};
    Rng rng(seed, 0x5EEDULL);
    for (int64_t i = 0; i < m; ++i) {
        float u0 = rng.uniform(), uc = rng.uniform(), u1 = rng.uniform(), u2 = rng.uniform();
        float p;
        V3 d = env_sample(e, u0, uc, u1, u2, p, rad_out + 3 * i);
        dirs_out[3 * i] = d.x; dirs_out[3 * i + 1] = d.y; dirs_out[3 * i + 2] = d.z;
        pdf_out[i] = p;
    }
}

// The fused integrator. Points: pos, nrm, wo, albedo [P, 3]; rough, metal, weight (O), bg
// (luminance of (1 - O) E(wo), for the adaptive criterion), depth (camera z, for cache cells) [P];
// ids [P] int64 (nullable): the random stream of each point (its pixel index: a pixel gets the same
// samples whichever subset of pixels is shaded).
// iparams int64[9]: n_env, n_brdf, batch, adapt_min_batches, cull_lights, pool_size, threads, nbvh,
//   cache_bvhs (leading BVHs whose visibility the cache may hold: the static ones)
// fparams float64[14]: adapt_tol, exposure, inv_gamma, normal_offset, specular, cache_cell_px,
//   inv_fx, tmin, early_stop, max_alpha, seed, mis_min_brdf (> 0: per-point env/BRDF split),
//   roulette (> 0: shadow-ray Russian roulette threshold, x the point's running mean contribution),
//   cache_check (> 0: probability of re-tracing a cache hit, unbiased correction)
// lights: [L, 16] float32 (pos3 axis3 radiant3 cos_inner cos_outer range spot pad3)
// env: H, W, rad, pdf, aprob, aidx, cos_edge, rot_rad, black
// out [P, 3] (L_r, not weighted by O), used [P] int32 samples spent; counters int64[10].
void pi_render(const float* pos, const float* nrm, const float* wo, const float* albedo, const float* rough,
               const float* metal, const float* weight, const float* bg, const float* depth, const int64_t* ids,
               int64_t npts,
               const int64_t* iparams, const double* fparams, const void* const* bvh_nodes, const int64_t* bvh_num,
               const float* const* bvh_soa, const int64_t* bvh_npad, const float* lights, int32_t nlights,
               int32_t H, int32_t W, const float* tex, const float* alias, const float* cos_edge, float rot_rad,
               int32_t black, const float* pool_dir, const float* pool_pdf,
               const float* pool_rad, void* cache, float* out, int32_t* used, int64_t* counters) {
    Params P{};
    P.n_env = (int)iparams[0];
    P.n_brdf = (int)iparams[1];
    P.batch = (int)iparams[2];
    P.adapt_min_batches = (int)iparams[3];
    P.cull_lights = (int)iparams[4];
    P.pool_size = (int)std::max<int64_t>(1, iparams[5]);
    int nthreads = (int)std::max<int64_t>(1, iparams[6]);
    int nb = (int)std::min<int64_t>(2, iparams[7]);
    P.cache_bvhs = (int)std::min<int64_t>(nb, std::max<int64_t>(0, iparams[8]));
    P.adapt_tol = (float)fparams[0];
    P.exposure = (float)fparams[1];
    P.inv_gamma = (float)fparams[2];
    P.normal_offset = (float)fparams[3];
    P.specular = (float)fparams[4];
    P.cache_cell_px = (float)fparams[5];
    P.inv_fx = (float)fparams[6];
    TraceParams tp{(float)fparams[7], (float)fparams[8], (float)fparams[9]};
    P.seed = (uint64_t)fparams[10];
    P.mis_min_brdf = (float)fparams[11];
    P.roulette = (float)fparams[12];
    P.cache_check = (float)fparams[13];
    Bvh bv[2];
    for (int k = 0; k < nb; ++k) bv[k] = {static_cast<const Node8*>(bvh_nodes[k]), bvh_num[k], bvh_soa[k], bvh_npad[k]};
    Env env{H, W, tex, alias, cos_edge, std::cos(rot_rad), std::sin(rot_rad), black != 0};
    std::vector<Light> L(nlights);
    for (int l = 0; l < nlights; ++l) {
        const float* q = lights + 16 * l;
        Light& x = L[l];
        for (int c = 0; c < 3; ++c) { x.pos[c] = q[c]; x.axis[c] = q[3 + c]; x.radiant[c] = q[6 + c]; }
        x.cos_inner = q[9]; x.cos_outer = q[10]; x.range = q[11]; x.spot = q[12];
    }
    PointIn in{pos, nrm, wo, albedo, rough, metal, weight, bg, depth, ids};
    VisCache* vc = static_cast<VisCache*>(cache);
    std::atomic<int64_t> next{0};
    std::vector<Counters> cs(nthreads);
    const int64_t chunk = 32;
    auto work = [&](int tid) {
        for (;;) {
            int64_t b0 = next.fetch_add(chunk);
            if (b0 >= npts) break;
            int64_t e0 = std::min(npts, b0 + chunk);
            for (int64_t i = b0; i < e0; ++i)
                shade_point(i, in, env, bv, nb, tp, L.data(), nlights, P, pool_dir, pool_pdf, pool_rad, vc, out, used,
                            cs[tid]);
        }
    };
    if (nthreads == 1 || npts <= chunk) work(0);
    else {
        std::vector<std::thread> th;
        for (int t = 1; t < nthreads; ++t) th.emplace_back(work, t);
        work(0);
        for (auto& t : th) t.join();
    }
    if (counters) {
        for (int k = 0; k < 11; ++k) counters[k] = 0;
        for (auto& c : cs) {
            counters[0] += c.samples; counters[1] += c.shadow_rays; counters[2] += c.cache_hits;
            counters[3] += c.cache_lookups; counters[4] += c.light_pairs; counters[5] += c.light_evals;
            counters[6] += c.ts.nodes; counters[7] += c.ts.leaves; counters[8] += c.ts.rays;
            counters[9] += c.roulette_skipped;
            counters[10] += c.cache_checks;
        }
    }
}

}  // extern "C"
