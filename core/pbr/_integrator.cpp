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
// The pieces live in the headers of native/: bvh.hpp (the BVH, here 8-wide: one AVX box test per
// node, about half the node visits of the 4-wide one of trace4.hpp), shadow.hpp (shadow rays
// with the 16-wide AVX-512 leaf test over SoA Gaussians), brdf.hpp, envmap.hpp, rng.hpp,
// vis_cache.hpp, parallel.hpp and vec.hpp; this file holds the per-point estimator and the C
// entry points of both kernels.
//
// Units: world metres; radiance in the environment map's units; directions point away from the
// surface. Plain C ABI (ctypes releases the GIL).

// One shared object holds both kernels: the 4-wide shadow rays of core.pbr.visibility
// (native/trace4.hpp, entry points bv_* below) and the integrator (pi_*).
#include "native/trace4.hpp"
#include "native/shadow.hpp"
#include "native/rng.hpp"
#include "native/vec.hpp"
#include "native/brdf.hpp"
#include "native/envmap.hpp"
#include "native/vis_cache.hpp"
#include "native/parallel.hpp"

#include <atomic>
#include <cstdio>
#include <vector>

namespace {

constexpr float kLightDistSqMin = 1e-4f;

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
    int model;                  // BRDF model bits (brdf.hpp: Burley's diffuse, exact Smith G); 0 = the paper
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
    float tmin_own[kMaxBvhs];   // each BVH's tmin for points on an edited object (PointIn::on_object)
};

struct Light {
    float pos[3], axis[3], radiant[3], cos_inner, cos_outer, range, spot;
};

struct PointIn {
    const float *pos, *nrm, *wo, *albedo, *rough, *metal, *weight, *bg, *depth;
    const int64_t* ids;  // random stream of each point (e.g. its pixel index), or null: the point index
    const uint8_t* on_object;  // nullable: the point lies on an edited object (its BVHs use Params::tmin_own)
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

void shade_point(int64_t i, const PointIn& in, const Env& env, const Bvh* bv_in, int nb, const TraceParams& tp,
                 const Light* lights, int nl, const Params& P, const float* pool_dir, const float* pool_pdf,
                 const float* pool_rad, VisCache* cache, float* out, int32_t* used, Counters& cnt) {
    // a point on an edited object traces the objects' BVH from the scene's t_min, not from the
    // objects' own (their Gaussians would shadow their own surface)
    Bvh own[kMaxBvhs];
    const Bvh* bv = bv_in;
    if (in.on_object && in.on_object[i]) {
        for (int k = 0; k < nb; ++k) { own[k] = bv_in[k]; own[k].tmin = P.tmin_own[k]; }
        bv = own;
    }
    V3 n = normalize(load3(in.nrm + 3 * i));
    V3 wo = normalize(load3(in.wo + 3 * i));
    V3 x = load3(in.pos + 3 * i);
    Material mt = make_material(in.albedo + 3 * i, in.rough[i], in.metal[i], P.specular, P.model);
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
            V = trace_bvhs(bv, nb, o, dd, dist, tp, cnt.ts);
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
                        V = trace_bvhs(bv, P.cache_bvhs, o, dd, INFINITY, tp, cnt.ts);
                        cnt.shadow_rays++;
                        if (cv) cv->store((uint16_t)std::lround(clamp01(V) * kVisScale), std::memory_order_release);
                    } else if (P.cache_check > 0.f && rng.uniform() < P.cache_check) {
                        // spot check of a hit: trace this point's own visibility; an entry that
                        // disagrees (a shadow edge crosses the cell in this direction) is retired
                        // so every later lookup traces: the cache keeps only the cell/direction
                        // pairs whose visibility is the same across the cell
                        float Vt = trace_bvhs(bv, P.cache_bvhs, o, dd, INFINITY, tp, cnt.ts);
                        cnt.shadow_rays++;
                        cnt.cache_checks++;
                        if (std::fabs(Vt - V) > kCheckDisagree) cv->store(kAlwaysTrace, std::memory_order_release);
                        V = Vt;
                    }
                    if (nb > P.cache_bvhs && V >= tp.early_stop) {
                        float Vd = trace_bvhs(bv + P.cache_bvhs, nb - P.cache_bvhs, o, dd, INFINITY, tp, cnt.ts);
                        V *= Vd;
                        cnt.shadow_rays++;
                    }
                } else {
                    V = trace_bvhs(bv, nb, o, dd, INFINITY, tp, cnt.ts);
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

int bv_abi_version() { return 2; }

// Build the BVH over n boxes (lo, hi: [n, 3] float32): binary SAH build, collapsed to a 4-wide
// BVH. perm_out: [n] int32 (Gaussian order in the leaves). nodes_out: capacity n + 1 Node4
// (128 bytes each). Returns the Node4 count.
// depth_out: the depth of the deepest leaf (root = 1).
int64_t bv_build(const float* lo, const float* hi, int64_t n, int32_t leaf_size, int32_t* perm_out, void* nodes_out,
                 int32_t* depth_out) {
    return build_wide<4>(lo, hi, n, leaf_size, perm_out, nodes_out, depth_out);
}

// Trace nrays rays. origins, dirs: [nrays, 3] float32; tmax: [nrays] float32 or null (= inf).
// gauss: [*, 16] float32 in leaf order. out: [nrays] float32. stats (nullable): int64[3] =
// node visits, Gaussian tests, Gaussians counted.
void bv_trace(const void* nodes_v, int64_t num_nodes, const float* gauss, const float* origins, const float* dirs,
              const float* tmax, int64_t nrays, double tmin, double early_stop, double max_alpha, int32_t nthreads,
              float* out, int64_t* stats) {
    const Node4* nodes = static_cast<const Node4*>(nodes_v);
    if (num_nodes <= 0) {
        for (int64_t i = 0; i < nrays; ++i) out[i] = 1.0f;
        if (stats) stats[0] = stats[1] = stats[2] = 0;
        return;
    }
    int nt = std::max(1, (int)nthreads);
    std::vector<Stats> st(nt);
    parallel_chunks(nrays, 256, nt, [&](int tid, int64_t b, int64_t e) {
        Stats& s = st[tid];
        for (int64_t i = b; i < e; ++i) {
            double o[3] = {origins[3 * i], origins[3 * i + 1], origins[3 * i + 2]};
            double d[3] = {dirs[3 * i], dirs[3 * i + 1], dirs[3 * i + 2]};
            double t1 = tmax ? (double)tmax[i] : INFINITY;
            out[i] = t1 >= tmin ? trace_one(nodes, gauss, o, d, tmin, t1, early_stop, max_alpha, s) : 1.0f;
        }
    });
    if (stats) {
        stats[0] = stats[1] = stats[2] = 0;
        for (auto& s : st) { stats[0] += s.nodes; stats[1] += s.tests; stats[2] += s.hits; }
    }
}

// ------------------------------------------------------------------------------------------
// the integrator
// ------------------------------------------------------------------------------------------
int pi_abi_version() { return 10; }

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

// 8-wide BVH over n boxes (native/bvh.hpp: the binary SAH build of bv_build, collapsed to Node8):
// perm_out [n] int32 (leaf order), nodes_out capacity n + 1 Node8 (256 bytes each), depth_out the
// depth of the binary tree. Returns the Node8 count.
int64_t pi_build8(const float* lo, const float* hi, int64_t n, int32_t leaf_size, int32_t* perm_out, void* nodes_out,
                  int32_t* depth_out) {
    return build_wide<8>(lo, hi, n, leaf_size, perm_out, nodes_out, depth_out);
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

// Shadow rays through up to 3 BVHs with the SIMD leaf test (for tests / benchmarks).
// bvh_nodes[3], bvh_num[3], bvh_soa[3], bvh_npad[3], bvh_tmin[3] (each BVH's minimum ray
// distance); out [nrays]; stats int64[3]
void pi_trace(const void* const* bvh_nodes, const int64_t* bvh_num, const float* const* bvh_soa,
              const int64_t* bvh_npad, const float* bvh_tmin, int32_t nbvh, const float* origins, const float* dirs,
              const float* tmax, int64_t nrays, float early_stop, float max_alpha, int32_t nthreads, float* out,
              int64_t* stats) {
    Bvh bv[kMaxBvhs];
    int nb = std::max(0, std::min(kMaxBvhs, (int)nbvh));
    for (int k = 0; k < nb; ++k)
        bv[k] = {static_cast<const Node8*>(bvh_nodes[k]), bvh_num[k], bvh_soa[k], bvh_npad[k], bvh_tmin[k]};
    TraceParams tp{early_stop, max_alpha};
    int nt = std::max(1, (int)nthreads);
    std::vector<TStats> st(nt);
    parallel_chunks(nrays, 256, nt, [&](int tid, int64_t b0, int64_t e0) {
        for (int64_t i = b0; i < e0; ++i) {
            float o[3] = {origins[3 * i], origins[3 * i + 1], origins[3 * i + 2]};
            V3 d = normalize(load3(dirs + 3 * i));
            float dd[3] = {d.x, d.y, d.z};
            float t1 = tmax ? tmax[i] : INFINITY;
            out[i] = dot(d, d) > 0.5f ? trace_bvhs(bv, nb, o, dd, t1, tp, st[tid]) : 1.f;
        }
    });
    if (stats) {
        stats[0] = stats[1] = stats[2] = 0;
        for (auto& s : st) { stats[0] += s.rays; stats[1] += s.nodes; stats[2] += s.leaves; }
    }
}

// Deterministic pieces for the twin tests: f [m, 3], pdf_mix [m], env lookup [m, 3], env pdf [m].
void pi_eval(const float* n, const float* wi, const float* wo, const float* albedo, const float* rough,
             const float* metal, float specular, int32_t model, int64_t m, float* f_out, float* pdf_out) {
    for (int64_t i = 0; i < m; ++i) {
        Material mt = make_material(albedo + 3 * i, rough[i], metal[i], specular, model);
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
// iparams int64[9]: n_env, n_brdf, batch, adapt_min_batches, cull_lights, pool_size, threads, nbvh
//   (<= 3), cache_bvhs (leading BVHs whose visibility the cache may hold: the static ones)
// fparams float64[15]: adapt_tol, exposure, inv_gamma, normal_offset, specular, cache_cell_px,
//   inv_fx, tmin (every BVH's minimum ray distance when bvh_tmin is null), early_stop, max_alpha,
//   seed, mis_min_brdf (> 0: per-point env/BRDF split),
//   roulette (> 0: shadow-ray Russian roulette threshold, x the point's running mean contribution),
//   cache_check (> 0: probability of re-tracing a cache hit, unbiased correction),
//   model (BRDF model bits, brdf.hpp: 1 Burley's diffuse, 2 exact Smith G; 0 = the paper)
// bvh_nodes, bvh_num, bvh_soa, bvh_npad, bvh_tmin (nullable): [nbvh] each, bvh_tmin the minimum
//   ray distance of each BVH (metres); bvh_tmin_own (nullable): [nbvh], the minimum distance of
//   each BVH for the points that lie on an edited object (on_object [P] uint8, nullable)
// lights: [L, 16] float32 (pos3 axis3 radiant3 cos_inner cos_outer range spot pad3)
// env: H, W, rad, pdf, aprob, aidx, cos_edge, rot_rad, black
// out [P, 3] (L_r, not weighted by O), used [P] int32 samples spent; counters int64[10].
void pi_render(const float* pos, const float* nrm, const float* wo, const float* albedo, const float* rough,
               const float* metal, const float* weight, const float* bg, const float* depth, const int64_t* ids,
               int64_t npts,
               const int64_t* iparams, const double* fparams, const void* const* bvh_nodes, const int64_t* bvh_num,
               const float* const* bvh_soa, const int64_t* bvh_npad, const float* bvh_tmin,
               const float* bvh_tmin_own, const uint8_t* on_object, const float* lights, int32_t nlights,
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
    int nb = (int)std::max<int64_t>(0, std::min<int64_t>(kMaxBvhs, iparams[7]));
    P.cache_bvhs = (int)std::min<int64_t>(nb, std::max<int64_t>(0, iparams[8]));
    P.adapt_tol = (float)fparams[0];
    P.exposure = (float)fparams[1];
    P.inv_gamma = (float)fparams[2];
    P.normal_offset = (float)fparams[3];
    P.specular = (float)fparams[4];
    P.cache_cell_px = (float)fparams[5];
    P.inv_fx = (float)fparams[6];
    const float tmin_all = (float)fparams[7];
    TraceParams tp{(float)fparams[8], (float)fparams[9]};
    P.seed = (uint64_t)fparams[10];
    P.mis_min_brdf = (float)fparams[11];
    P.roulette = (float)fparams[12];
    P.cache_check = (float)fparams[13];
    P.model = (int)fparams[14];
    Bvh bv[kMaxBvhs];
    for (int k = 0; k < nb; ++k)
        bv[k] = {static_cast<const Node8*>(bvh_nodes[k]), bvh_num[k], bvh_soa[k], bvh_npad[k],
                 bvh_tmin ? bvh_tmin[k] : tmin_all};
    Env env{H, W, tex, alias, cos_edge, std::cos(rot_rad), std::sin(rot_rad), black != 0};
    std::vector<Light> L(nlights);
    for (int l = 0; l < nlights; ++l) {
        const float* q = lights + 16 * l;
        Light& x = L[l];
        for (int c = 0; c < 3; ++c) { x.pos[c] = q[c]; x.axis[c] = q[3 + c]; x.radiant[c] = q[6 + c]; }
        x.cos_inner = q[9]; x.cos_outer = q[10]; x.range = q[11]; x.spot = q[12];
    }
    for (int k = 0; k < nb; ++k) P.tmin_own[k] = bvh_tmin_own ? bvh_tmin_own[k] : bv[k].tmin;
    PointIn in{pos, nrm, wo, albedo, rough, metal, weight, bg, depth, ids, on_object};
    VisCache* vc = static_cast<VisCache*>(cache);
    std::vector<Counters> cs(nthreads);
    parallel_chunks(npts, 32, nthreads, [&](int tid, int64_t b0, int64_t e0) {
        for (int64_t i = b0; i < e0; ++i)
            shade_point(i, in, env, bv, nb, tp, L.data(), nlights, P, pool_dir, pool_pdf, pool_rad, vc, out, used,
                        cs[tid]);
    });
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
