// BRDFusion tile rasterizer: CPU kernels (binning, forward, backward).
//
// Built at first use by core/raster/_native.py (g++ -O3 -march=native, std::thread) and loaded
// with ctypes; every entry point is `extern "C"` and takes raw pointers to contiguous arrays.
// Why C++ and not Warp: see the docstring of core/raster/_native.py.
//
// Layout contract (all row-major, contiguous):
//   gdata   [N, NG]  per Gaussian: mx, my (pixels), conic a, b, c (inverse 2D covariance
//                    [[a, b], [b, c]]), opacity o, then NF = 12 features
//                    (color 3, depth 1, normal 3, albedo 3, roughness 1, metallic 1).
//   aux     [N, 2]   written by bin: half height of the opacity-aware ellipse (pixels),
//                    and a power threshold below which o*exp(power) < alpha_min for sure.
//   out     [H, W, NO] NO = NF + 1: the 12 composited features then opacity O = 1 - T_final.
//                    Channels 0..2 (color) also get T_final * background.
//   tfinal  [H, W]   final transmittance; last [H, W] int32: 1 + local list index of the last
//                    Gaussian that contributed to the pixel (0: none).
//
// SIMD: a tile row of 16 pixels is one vector (GCC vector extensions: 16 x float = one AVX-512
// register; 16 x double = two; plain SSE/AVX2 code on other x86 CPUs). The same template code
// runs the float32 and float64 paths, so the float64 path (tested against the dense PyTorch
// reference to ~1e-12) checks the logic of the float32 path.
// Forward: per tile, the Gaussians are gathered into a contiguous buffer and bucketed per row;
// each row keeps its transmittance and 12 accumulators in registers and stops on its own.
// Backward: Gaussian-outer (back to front), row-inner with per-row state in L1, so each
// Gaussian's gradient is reduced across lanes once per tile (transpose-add of 16 vectors) into
// the thread's own gradient buffer.
// Threads: std::thread workers take tiles (largest lists first) from an atomic counter.

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <thread>
#include <vector>
#if defined(__AVX512F__)
#include <immintrin.h>
#endif

namespace {

constexpr int TS = 16;        // tile size (pixels per side) == SIMD lanes
constexpr int NF = 12;        // composited features
constexpr int NG = 6 + NF;    // floats per Gaussian in gdata
constexpr int NO = NF + 1;    // output channels (features + opacity)

template <class T> struct VT;
template <> struct VT<float> {
  typedef float V __attribute__((vector_size(64)));
  typedef int32_t I __attribute__((vector_size(64)));
  typedef int32_t IS;
  static constexpr int MANT = 23, BIAS = 127;
  static constexpr float LO = -87.0f;
};
template <> struct VT<double> {
  typedef double V __attribute__((vector_size(128)));
  typedef int64_t I __attribute__((vector_size(128)));
  typedef int64_t IS;
  static constexpr int MANT = 52, BIAS = 1023;
  static constexpr double LO = -700.0;
};

// ---- mask helpers -------------------------------------------------------------------------
inline bool any(VT<float>::I m) {
#if defined(__AVX512F__)
  __m512i v = (__m512i)m;
  return _mm512_test_epi32_mask(v, v) != 0;
#else
  int32_t r = 0;
  for (int l = 0; l < TS; ++l) r |= m[l];
  return r != 0;
#endif
}
inline bool any(VT<double>::I m) {
  int64_t r = 0;
  for (int l = 0; l < TS; ++l) r |= m[l];
  return r != 0;
}
template <class I> inline bool all(I m) { return !any(~m); }

// Sums of 16 vectors at once: lane l of the result is the sum of the lanes of v[l] (a
// transpose-and-add tree: 4 levels of 2 shuffles + 1 add per pair, instead of 16 reductions).
template <class V, class I> inline V level(V a, V b, int h) {
  I lo, hi;
  for (int j = 0; j < TS; ++j) {
    const int base = j - j % (2 * h), w = j % (2 * h);
    lo[j] = w < h ? base + w : TS + base + w - h;
    hi[j] = w < h ? base + w + h : TS + base + w;
  }
  return __builtin_shuffle(a, b, lo) + __builtin_shuffle(a, b, hi);
}
template <class T> inline typename VT<T>::V hsum16(typename VT<T>::V *v) {
  typedef typename VT<T>::V V;
  typedef typename VT<T>::I I;
  V t[8];
  for (int k = 0; k < 8; ++k) t[k] = level<V, I>(v[2 * k], v[2 * k + 1], 1);
  for (int k = 0; k < 4; ++k) t[k] = level<V, I>(t[2 * k], t[2 * k + 1], 2);
  for (int k = 0; k < 2; ++k) t[k] = level<V, I>(t[2 * k], t[2 * k + 1], 4);
  return level<V, I>(t[0], t[1], 8);
}

template <class V> inline auto hsum(V v) -> decltype(v[0] + v[1]) {
  decltype(v[0] + v[1]) s = 0;
  for (int l = 0; l < TS; ++l) s += v[l];
  return s;
}

// exp(x) for x <= ~0 (power of a Gaussian). Cody-Waite range reduction + Taylor polynomial:
// relative error ~1e-7 (float, degree 7) and ~1e-16 (double, degree 14). Inputs below LO are
// clamped (exp(LO) is still a normal number, and far below any alpha threshold).
template <class T> inline typename VT<T>::V vexp(typename VT<T>::V x) {
  typedef typename VT<T>::V V;
  typedef typename VT<T>::I I;
  const T lo = VT<T>::LO;
  x = x < lo ? V{} + lo : x;
  x = x > T(80) ? V{} + T(80) : x;
  V y = x * T(1.4426950408889634);
  I n = __builtin_convertvector(y + (y < T(0) ? V{} - T(0.5) : V{} + T(0.5)), I);
  V nf = __builtin_convertvector(n, V);
  V r;
  V p;
  if (sizeof(T) == 4) {
    r = x - nf * T(0.693359375) - nf * T(-2.12194440e-4);
    p = V{} + T(1.0 / 5040.0);
    p = p * r + T(1.0 / 720.0);
    p = p * r + T(1.0 / 120.0);
    p = p * r + T(1.0 / 24.0);
    p = p * r + T(1.0 / 6.0);
    p = p * r + T(0.5);
    p = p * r + T(1.0);
    p = p * r + T(1.0);
  } else {
    r = x - nf * T(6.93147180369123816490e-01) - nf * T(1.90821492927058770002e-10);
    const double inv_fact[15] = {1.0, 1.0, 1.0 / 2, 1.0 / 6, 1.0 / 24, 1.0 / 120, 1.0 / 720,
                                 1.0 / 5040, 1.0 / 40320, 1.0 / 362880, 1.0 / 3628800,
                                 1.0 / 39916800, 1.0 / 479001600, 1.0 / 6227020800.0,
                                 1.0 / 87178291200.0};
    p = V{} + T(inv_fact[14]);
    for (int k = 13; k >= 0; --k) p = p * r + T(inv_fact[k]);
  }
  I bits = (n + VT<T>::BIAS) << VT<T>::MANT;
  return p * (V)bits;
}

template <class F> void run_parallel(int n_threads, int n_items, F fn) {
  // Dynamic scheduling: item indices handed out one by one from an atomic counter.
  std::atomic<int> next{0};
  auto worker = [&](int tid) {
    for (;;) {
      int i = next.fetch_add(1, std::memory_order_relaxed);
      if (i >= n_items) break;
      fn(i, tid);
    }
  };
  n_threads = std::max(1, std::min(n_threads, n_items));
  std::vector<std::thread> pool;
  for (int t = 1; t < n_threads; ++t) pool.emplace_back(worker, t);
  worker(0);
  for (auto &th : pool) th.join();
}

struct Footprint {
  double t;             // ellipse level: q <= t  <=>  o * g >= alpha_min
  int tx0, tx1, ty0, ty1;
  bool ok;
};

template <class T>
inline Footprint footprint(const T *g, uint8_t valid, double alpha_min, int W, int H) {
  Footprint f{0, 0, -1, 0, -1, false};
  double mx = g[0], my = g[1], a = g[2], b = g[3], c = g[4], o = g[5];
  if (!valid || !(o >= (double)(T)alpha_min)) return f;
  double det = a * c - b * b;
  if (!(det > 0) || !(a > 0) || !(c > 0) || !std::isfinite(det) || !std::isfinite(mx) ||
      !std::isfinite(my))
    return f;
  // Slightly enlarged level so that rounding never culls a pixel the exact test keeps.
  double t = std::max(0.0, 2.0 * std::log(o / alpha_min)) * (1.0 + 1e-5) + 1e-6;
  double ex = std::sqrt(t * c / det) + 1e-3, ey = std::sqrt(t * a / det) + 1e-3;
  // pixel columns i with centre i + 0.5 in [mx - ex, mx + ex]
  double i0 = std::max(0.0, std::ceil(mx - ex - 0.5)), i1 = std::min(W - 1.0, std::floor(mx + ex - 0.5));
  double j0 = std::max(0.0, std::ceil(my - ey - 0.5)), j1 = std::min(H - 1.0, std::floor(my + ey - 0.5));
  if (!(i0 <= i1) || !(j0 <= j1)) return f;
  f.t = t;
  f.tx0 = (int)i0 / TS;
  f.tx1 = (int)i1 / TS;
  f.ty0 = (int)j0 / TS;
  f.ty1 = (int)j1 / TS;
  f.ok = true;
  return f;
}

// Calls emit(tile) for every tile whose pixel-centre rectangle meets the ellipse q <= t.
// Exact and cheap: per row of tiles, the ellipse cut by the row's band of pixel-centre y values
// is convex, so its x-extent is an interval [mx + L, mx + R]; R(dy) is concave and L(dy) convex,
// so their extremes over the band are at the clamped stationary points dy = -/+ b ex / c.
template <class T, class Emit>
inline int for_each_tile(const T *g, const Footprint &f, int W, int H, Emit emit) {
  int n = 0;
  if (!f.ok) return 0;
  const double mx = g[0], my = g[1], a = g[2], b = g[3], c = g[4], t = f.t;
  const double det = a * c - b * b;
  const double ex = std::sqrt(t * c / det), ey = std::sqrt(t * a / det);
  const double dyR = -b * ex / c, dyL = b * ex / c;
  const int tiles_x = (W + TS - 1) / TS;
  for (int ty = f.ty0; ty <= f.ty1; ++ty) {
    const double Y0 = ty * TS + 0.5, Y1 = std::min(ty * TS + TS - 1, H - 1) + 0.5;
    const double d0 = std::max(Y0 - my, -ey), d1 = std::min(Y1 - my, ey);
    if (d0 > d1) continue;
    const double yr = std::min(std::max(dyR, d0), d1), yl = std::min(std::max(dyL, d0), d1);
    const double xr = mx + (-b * yr + std::sqrt(std::max(a * t - det * yr * yr, 0.0))) / a + 1e-3;
    const double xl = mx + (-b * yl - std::sqrt(std::max(a * t - det * yl * yl, 0.0))) / a - 1e-3;
    // pixel columns with centre in [xl, xr]
    const double i0 = std::max(0.0, std::ceil(xl - 0.5)), i1 = std::min(W - 1.0, std::floor(xr - 0.5));
    if (!(i0 <= i1)) continue;
    const int tx0 = std::max((int)i0 / TS, f.tx0), tx1 = std::min((int)i1 / TS, f.tx1);
    for (int tx = tx0; tx <= tx1; ++tx) {
      emit(ty * tiles_x + tx);
      ++n;
    }
  }
  return n;
}

// ---- projection -----------------------------------------------------------------------------
struct Camera {
  double W[3][3], t[3];  // world -> camera rotation and translation
  double fx, fy, cx, cy;
  double lx0, lx1, ly0, ly1;  // guard band on x/z and y/z
  double near, low_pass, max_scale;
};

inline Camera make_camera(const double *w2c, double fx, double fy, double cx, double cy, int width,
                          int height, double near, double guard, double low_pass,
                          double max_scale) {
  Camera c;
  for (int r = 0; r < 3; ++r) {
    for (int k = 0; k < 3; ++k) c.W[r][k] = w2c[4 * r + k];
    c.t[r] = w2c[4 * r + 3];
  }
  c.fx = fx, c.fy = fy, c.cx = cx, c.cy = cy;
  const double e = 0.5 * (guard - 1.0);
  c.lx0 = (-e * width - cx) / fx, c.lx1 = ((1.0 + e) * width - cx) / fx;
  c.ly0 = (-e * height - cy) / fy, c.ly1 = ((1.0 + e) * height - cy) / fy;
  c.near = near, c.low_pass = low_pass, c.max_scale = max_scale;
  return c;
}

inline void quat_rot(const double q[4], double R[3][3]) {
  const double w = q[0], x = q[1], y = q[2], z = q[3];
  R[0][0] = 1 - 2 * (y * y + z * z), R[0][1] = 2 * (x * y - w * z), R[0][2] = 2 * (x * z + w * y);
  R[1][0] = 2 * (x * y + w * z), R[1][1] = 1 - 2 * (x * x + z * z), R[1][2] = 2 * (y * z - w * x);
  R[2][0] = 2 * (x * z - w * y), R[2][1] = 2 * (y * z + w * x), R[2][2] = 1 - 2 * (x * x + y * y);
}

// Everything the backward needs is recomputed from the inputs (cheap, ~100 flops).
struct Proj {
  double pc[3], xz, yz, txz, tyz;
  double m0[3], m1[3], R[3][3], s[3], L[3][3], t0[3], t1[3];
  double s00, s01, s11, det;
  double qn[4], qlen;
  bool qok, valid;
};

template <class T>
inline void project_one(const Camera &c, const T *p, const T *q, const T *sc, Proj &P) {
  for (int r = 0; r < 3; ++r)
    P.pc[r] = c.W[r][0] * p[0] + c.W[r][1] * p[1] + c.W[r][2] * p[2] + c.t[r];
  const double z = P.pc[2];
  P.valid = z > c.near && std::isfinite(z);
  if (!P.valid) return;
  P.xz = P.pc[0] / z, P.yz = P.pc[1] / z;
  P.txz = std::min(std::max(P.xz, c.lx0), c.lx1);
  P.tyz = std::min(std::max(P.yz, c.ly0), c.ly1);
  const double k0 = c.fx / z, k1 = c.fy / z;
  for (int j = 0; j < 3; ++j) {
    P.m0[j] = k0 * (c.W[0][j] - P.txz * c.W[2][j]);
    P.m1[j] = k1 * (c.W[1][j] - P.tyz * c.W[2][j]);
  }
  const double n2 = (double)q[0] * q[0] + (double)q[1] * q[1] + (double)q[2] * q[2] + (double)q[3] * q[3];
  P.qok = n2 > 1e-12;
  P.qlen = std::sqrt(n2);
  for (int j = 0; j < 4; ++j) P.qn[j] = P.qok ? q[j] / P.qlen : (j == 0 ? 1.0 : 0.0);
  quat_rot(P.qn, P.R);
  for (int j = 0; j < 3; ++j) P.s[j] = std::min(std::max((double)sc[j], 0.0), c.max_scale);
  for (int r = 0; r < 3; ++r)
    for (int j = 0; j < 3; ++j) P.L[r][j] = P.R[r][j] * P.s[j];
  for (int j = 0; j < 3; ++j) {
    P.t0[j] = P.m0[0] * P.L[0][j] + P.m0[1] * P.L[1][j] + P.m0[2] * P.L[2][j];
    P.t1[j] = P.m1[0] * P.L[0][j] + P.m1[1] * P.L[1][j] + P.m1[2] * P.L[2][j];
  }
  P.s00 = P.t0[0] * P.t0[0] + P.t0[1] * P.t0[1] + P.t0[2] * P.t0[2] + c.low_pass;
  P.s01 = P.t0[0] * P.t1[0] + P.t0[1] * P.t1[1] + P.t0[2] * P.t1[2];
  P.s11 = P.t1[0] * P.t1[0] + P.t1[1] * P.t1[1] + P.t1[2] * P.t1[2] + c.low_pass;
  P.det = P.s00 * P.s11 - P.s01 * P.s01;
  if (!(P.det > 0)) P.det = 1.0;
}

// Fills gdata rows [N, NG] (mean2d, conic, clamped opacity, features) and valid [N].
// Returns a bit mask: bit j set when input j (means, quats, scales, opac, colors, normals,
// albedo, rough, metal) holds a NaN or Inf (then gdata is not meaningful).
template <class T>
int project(const T *means, const T *quats, const T *scales, const T *opac, const T *colors,
            const T *normals, const T *albedo, const T *rough, const T *metal, const Camera &c,
            int64_t N, int n_threads, T *gdata, uint8_t *valid) {
  const int64_t CH = 4096;
  std::atomic<int> bad{0};
  run_parallel(n_threads, (int)((N + CH - 1) / CH), [&](int ci, int) {
    const int64_t i0 = ci * CH, i1 = std::min(N, (ci + 1) * CH);
    const T *arr[9] = {means, quats, scales, opac, colors, normals, albedo, rough, metal};
    const int width[9] = {3, 4, 3, 1, 3, 3, 3, 1, 1};
    int mask = 0;
    for (int j = 0; j < 9; ++j) {
      int b = 0;  // x - x != 0 exactly when x is NaN or Inf
      for (int64_t e = i0 * width[j]; e < i1 * width[j]; ++e) b |= (arr[j][e] - arr[j][e]) != T(0);
      if (b) mask |= 1 << j;
    }
    if (mask) bad.fetch_or(mask);
    for (int64_t i = i0; i < i1; ++i) {
      Proj P{};
      project_one(c, means + 3 * i, quats + 4 * i, scales + 3 * i, P);
      T *g = gdata + i * NG;
      valid[i] = P.valid ? 1 : 0;
      if (P.valid) {
        g[0] = (T)(c.fx * P.xz + c.cx);
        g[1] = (T)(c.fy * P.yz + c.cy);
        g[2] = (T)(P.s11 / P.det);
        g[3] = (T)(-P.s01 / P.det);
        g[4] = (T)(P.s00 / P.det);
      } else {
        for (int j = 0; j < 5; ++j) g[j] = 0;
      }
      g[5] = std::min(std::max(opac[i], T(0)), T(1));
      for (int j = 0; j < 3; ++j) g[6 + j] = colors[3 * i + j];
      g[9] = (T)P.pc[2];
      for (int j = 0; j < 3; ++j) g[10 + j] = normals[3 * i + j];
      for (int j = 0; j < 3; ++j) g[13 + j] = albedo[3 * i + j];
      g[16] = rough[i];
      g[17] = metal[i];
    }
  });
  return bad.load();
}

// Chain rule from grad_g [N, NG] (mean2d, conic, depth feature) to means, quats, scales and the
// world->camera transform (pose_grad [12]: dL/dW row-major then dL/dt). Appearance and opacity
// gradients are plain copies of grad_g columns (done by the caller).
template <class T>
void project_backward(const T *means, const T *quats, const T *scales, const Camera &c,
                      const T *opac, int64_t N, int n_threads, const T *grad_g, T *g_means,
                      T *g_quats, T *g_scales, T *g_opac, T *g_feat[5], double *pose_grad) {
  const int64_t CH = 4096;
  const int n_chunks = (int)((N + CH - 1) / CH);
  n_threads = std::max(1, std::min(n_threads, n_chunks));
  std::vector<double> pose(12 * (size_t)n_threads, 0.0);
  run_parallel(n_threads, n_chunks, [&](int ci, int tid) {
    double *gpose = pose.data() + 12 * tid;
    for (int64_t i = ci * CH; i < std::min(N, (ci + 1) * CH); ++i) {
      const T *p = means + 3 * i, *sc = scales + 3 * i;
      Proj P{};
      project_one(c, p, quats + 4 * i, sc, P);
      T *gm = g_means + 3 * i, *gq = g_quats + 4 * i, *gs = g_scales + 3 * i;
      const T *G = grad_g + i * NG;
      g_opac[i] = (opac[i] >= T(0) && opac[i] <= T(1)) ? G[5] : T(0);
      for (int j = 0; j < 3; ++j) {
        g_feat[0][3 * i + j] = G[6 + j];   // colors
        g_feat[1][3 * i + j] = G[10 + j];  // normals
        g_feat[2][3 * i + j] = G[13 + j];  // albedo
      }
      g_feat[3][i] = G[16];  // roughness
      g_feat[4][i] = G[17];  // metallic
      if (!P.valid) {
        for (int j = 0; j < 3; ++j) gm[j] = 0, gs[j] = 0;
        for (int j = 0; j < 4; ++j) gq[j] = 0;
        continue;
      }
      const double z = P.pc[2];
      const double ga = G[2], gb = G[3], gc = G[4];
      // conic = (s11, -s01, s00) / det
      const double d2 = P.det * P.det;
      const double gdet = -(ga * P.s11 - gb * P.s01 + gc * P.s00) / d2;
      const double gs00 = gc / P.det + gdet * P.s11;
      const double gs11 = ga / P.det + gdet * P.s00;
      const double gs01 = -gb / P.det - 2.0 * gdet * P.s01;
      double gt0[3], gt1[3], gm0[3] = {0, 0, 0}, gm1[3] = {0, 0, 0}, gL[3][3];
      for (int j = 0; j < 3; ++j) {
        gt0[j] = 2.0 * gs00 * P.t0[j] + gs01 * P.t1[j];
        gt1[j] = 2.0 * gs11 * P.t1[j] + gs01 * P.t0[j];
      }
      for (int r = 0; r < 3; ++r)
        for (int j = 0; j < 3; ++j) {
          gm0[r] += gt0[j] * P.L[r][j];
          gm1[r] += gt1[j] * P.L[r][j];
          gL[r][j] = P.m0[r] * gt0[j] + P.m1[r] * gt1[j];
        }
      double gR[3][3];
      for (int j = 0; j < 3; ++j) {
        double acc = 0;
        for (int r = 0; r < 3; ++r) {
          gR[r][j] = gL[r][j] * P.s[j];
          acc += gL[r][j] * P.R[r][j];
        }
        gs[j] = (sc[j] >= 0 && sc[j] <= c.max_scale) ? (T)acc : T(0);
      }
      const double w = P.qn[0], x = P.qn[1], y = P.qn[2], zq = P.qn[3];
      double gqn[4];
      gqn[0] = 2 * (-zq * gR[0][1] + y * gR[0][2] + zq * gR[1][0] - x * gR[1][2] - y * gR[2][0] + x * gR[2][1]);
      gqn[1] = 2 * (y * gR[0][1] + zq * gR[0][2] + y * gR[1][0] - 2 * x * gR[1][1] - w * gR[1][2] +
                    zq * gR[2][0] + w * gR[2][1] - 2 * x * gR[2][2]);
      gqn[2] = 2 * (-2 * y * gR[0][0] + x * gR[0][1] + w * gR[0][2] + x * gR[1][0] + zq * gR[1][2] -
                    w * gR[2][0] + zq * gR[2][1] - 2 * y * gR[2][2]);
      gqn[3] = 2 * (-2 * zq * gR[0][0] - w * gR[0][1] + x * gR[0][2] + w * gR[1][0] - 2 * zq * gR[1][1] +
                    y * gR[1][2] + x * gR[2][0] + y * gR[2][1]);
      if (P.qok) {
        const double dot = gqn[0] * w + gqn[1] * x + gqn[2] * y + gqn[3] * zq;
        for (int j = 0; j < 4; ++j) gq[j] = (T)((gqn[j] - P.qn[j] * dot) / P.qlen);
      } else {
        for (int j = 0; j < 4; ++j) gq[j] = 0;
      }
      // m0 = (fx/z)(W0 - txz W2), m1 = (fy/z)(W1 - tyz W2)
      const double k0 = c.fx / z, k1 = c.fy / z;
      double gk0 = 0, gk1 = 0, gtx = 0, gty = 0;
      for (int j = 0; j < 3; ++j) {
        gk0 += gm0[j] * (c.W[0][j] - P.txz * c.W[2][j]);
        gk1 += gm1[j] * (c.W[1][j] - P.tyz * c.W[2][j]);
        gtx -= k0 * gm0[j] * c.W[2][j];
        gty -= k1 * gm1[j] * c.W[2][j];
        gpose[0 * 3 + j] += k0 * gm0[j];
        gpose[1 * 3 + j] += k1 * gm1[j];
        gpose[2 * 3 + j] -= k0 * P.txz * gm0[j] + k1 * P.tyz * gm1[j];
      }
      double gz = -(gk0 * c.fx + gk1 * c.fy) / (z * z) + G[9];
      double gxz = c.fx * G[0] + ((P.xz >= c.lx0 && P.xz <= c.lx1) ? gtx : 0.0);
      double gyz = c.fy * G[1] + ((P.yz >= c.ly0 && P.yz <= c.ly1) ? gty : 0.0);
      const double gpc[3] = {gxz / z, gyz / z, gz - (gxz * P.pc[0] + gyz * P.pc[1]) / (z * z)};
      for (int j = 0; j < 3; ++j) {
        gm[j] = (T)(c.W[0][j] * gpc[0] + c.W[1][j] * gpc[1] + c.W[2][j] * gpc[2]);
        for (int r = 0; r < 3; ++r) gpose[3 * r + j] += gpc[r] * (double)p[j];
        gpose[9 + j] += gpc[j];
      }
    }
  });
  for (int k = 0; k < 12; ++k) {
    pose_grad[k] = 0;
    for (int t = 0; t < n_threads; ++t) pose_grad[k] += pose[12 * t + k];
  }
}

// ---- binning --------------------------------------------------------------------------------
// Visible Gaussians (vis[i] != 0) sorted front to back by camera depth (gdata col 9), ties by
// index: a stable sort. float: 4-pass LSD radix sort on the (positive) float bit patterns.
template <class T>
void sort_by_depth(const T *gdata, const uint8_t *vis, int64_t N, int32_t *order, int64_t &n_vis) {
  n_vis = 0;
  for (int64_t i = 0; i < N; ++i)
    if (vis[i]) order[n_vis++] = (int32_t)i;
  if (sizeof(T) == 8) {
    std::stable_sort(order, order + n_vis, [&](int32_t u, int32_t v) {
      return gdata[(int64_t)u * NG + 9] < gdata[(int64_t)v * NG + 9];
    });
    return;
  }
  std::vector<uint32_t> key(n_vis), key2(n_vis);
  std::vector<int32_t> tmp(n_vis);
  for (int64_t k = 0; k < n_vis; ++k) {
    float d = (float)gdata[(int64_t)order[k] * NG + 9];
    std::memcpy(&key[k], &d, 4);
  }
  int32_t *src = order, *dst = tmp.data();
  uint32_t *ks = key.data(), *kd = key2.data();
  for (int pass = 0; pass < 4; ++pass) {
    const int sh = 8 * pass;
    int64_t cnt[257] = {0};
    for (int64_t k = 0; k < n_vis; ++k) cnt[((ks[k] >> sh) & 255) + 1]++;
    for (int b = 0; b < 256; ++b) cnt[b + 1] += cnt[b];
    for (int64_t k = 0; k < n_vis; ++k) {
      const int64_t pos = cnt[(ks[k] >> sh) & 255]++;
      dst[pos] = src[k];
      kd[pos] = ks[k];
    }
    std::swap(src, dst);
    std::swap(ks, kd);
  }
  // 4 passes: the result is back in `order`.
}

// One pass over the Gaussians computes each footprint (aux) once and emits its (tile, Gaussian)
// pairs; visible Gaussians are radix-sorted by depth; pairs are bucketed by tile and each tile's
// depth ranks sorted: the global sort by (tile, depth) of 3DGS. Writes tile_offsets
// [n_tiles + 1], tile_ids [total] (Gaussian ids, per tile front to back) and tile_order [n_tiles]
// (tiles by decreasing list length, for load balancing) if total <= cap. Returns total.
template <class T>
int64_t bin(const T *gdata, const uint8_t *valid, int64_t N, int W, int H, double alpha_min,
            int n_threads, T *aux, int64_t cap, int64_t *tile_offsets, int32_t *tile_ids,
            int32_t *tile_order, int64_t *n_vis_out) {
  const int tiles_x = (W + TS - 1) / TS, tiles_y = (H + TS - 1) / TS, n_tiles = tiles_x * tiles_y;
  const int64_t CH = 2048;
  const int n_chunks = (int)((N + CH - 1) / CH);
  std::vector<std::vector<uint64_t>> pairs(n_chunks);
  std::vector<uint8_t> vis(N);
  run_parallel(n_threads, n_chunks, [&](int ci, int) {
    auto &out = pairs[ci];
    for (int64_t i = ci * CH; i < std::min(N, (ci + 1) * CH); ++i) {
      const T *g = gdata + i * NG;
      Footprint f = footprint(g, valid[i], alpha_min, W, H);
      if (f.ok) {
        double det = (double)g[2] * g[4] - (double)g[3] * g[3];
        aux[2 * i] = (T)(std::sqrt(f.t * g[2] / det) + 1e-3);
        aux[2 * i + 1] = (T)(-0.5 * f.t - 1e-3);
      } else {
        aux[2 * i] = 0;
        aux[2 * i + 1] = 0;
      }
      const int n = for_each_tile(g, f, W, H, [&](int tile) { out.push_back(((uint64_t)tile << 32) | (uint64_t)i); });
      vis[i] = n > 0;
    }
  });
  std::vector<int64_t> coff(n_chunks + 1, 0);
  for (int c = 0; c < n_chunks; ++c) coff[c + 1] = coff[c] + (int64_t)pairs[c].size();
  const int64_t total = coff[n_chunks];
  std::vector<int32_t> order(N);
  int64_t n_vis = 0;
  sort_by_depth(gdata, vis.data(), N, order.data(), n_vis);
  *n_vis_out = n_vis;
  if (total > cap) return total;
  std::vector<int32_t> rank(N, 0);
  for (int64_t k = 0; k < n_vis; ++k) rank[order[k]] = (int32_t)k;
  // Bucket the pairs by tile (counting sort), then sort each tile's depth ranks (a Gaussian
  // appears once per tile, so ranks are unique) in parallel over tiles, and map rank -> id.
  for (int t = 0; t <= n_tiles; ++t) tile_offsets[t] = 0;
  for (int c = 0; c < n_chunks; ++c)
    for (uint64_t v : pairs[c]) tile_offsets[(v >> 32) + 1]++;
  for (int t = 0; t < n_tiles; ++t) tile_offsets[t + 1] += tile_offsets[t];
  {
    std::vector<int64_t> cur(tile_offsets, tile_offsets + n_tiles);
    for (int c = 0; c < n_chunks; ++c)
      for (uint64_t v : pairs[c]) tile_ids[cur[v >> 32]++] = rank[v & 0xffffffffu];
  }
  int rank_bits = 1;
  while ((int64_t(1) << rank_bits) < n_vis) ++rank_bits;
  const int passes = (rank_bits + 7) / 8;
  std::vector<std::vector<int32_t>> scratch(std::max(1, n_threads));
  run_parallel(n_threads, n_tiles, [&](int t, int tid) {
    int32_t *b = tile_ids + tile_offsets[t];
    const int64_t m = tile_offsets[t + 1] - tile_offsets[t];
    if (m < 64) {
      std::sort(b, b + m);
    } else {  // LSD radix sort on the rank bytes
      auto &tmp = scratch[tid];
      tmp.resize(m);
      int32_t *src = b, *dst = tmp.data();
      for (int pass = 0; pass < passes; ++pass) {
        const int sh = 8 * pass;
        int64_t cnt[257] = {0};
        for (int64_t k = 0; k < m; ++k) cnt[((src[k] >> sh) & 255) + 1]++;
        for (int d = 0; d < 256; ++d) cnt[d + 1] += cnt[d];
        for (int64_t k = 0; k < m; ++k) dst[cnt[(src[k] >> sh) & 255]++] = src[k];
        std::swap(src, dst);
      }
      if (src != b) std::memcpy(b, src, sizeof(int32_t) * m);
    }
    for (int64_t k = 0; k < m; ++k) b[k] = order[b[k]];
  });
  for (int t = 0; t < n_tiles; ++t) tile_order[t] = t;
  std::stable_sort(tile_order, tile_order + n_tiles, [&](int32_t u, int32_t v) {
    return tile_offsets[u + 1] - tile_offsets[u] > tile_offsets[v + 1] - tile_offsets[v];
  });
  return total;
}

// ---- forward ------------------------------------------------------------------------------
struct Params {
  double alpha_min, alpha_max, t_min;
};

// One tile, row by row: the row's state (T, 12 accumulators, masks) lives in registers while
// the row walks the tile's Gaussians front to back (gathered once per tile into a contiguous
// local buffer); each row stops as soon as all 16 of its pixels are saturated.
constexpr int NL = 8 + NF;  // floats per Gaussian in the tile-local buffer

template <class T>
void forward_tile(int tile, const T *gdata, const T *aux, const int64_t *tile_offsets,
                  const int32_t *tile_ids, int W, int H, const T *bg, const Params &P, T *out,
                  T *tfinal, int32_t *last_out, int32_t *stats, std::vector<T> &local,
                  std::vector<int32_t> &rowlist) {
  typedef typename VT<T>::V V;
  typedef typename VT<T>::I I;
  const int tiles_x = (W + TS - 1) / TS;
  const int x0 = (tile % tiles_x) * TS, y0 = (tile / tiles_x) * TS;
  const int nrows = std::min(TS, H - y0);
  const T amin = (T)P.alpha_min, amax = (T)P.alpha_max, tmin = (T)P.t_min;
  V X;
  I inside;
  for (int l = 0; l < TS; ++l) {
    X[l] = T(x0 + l) + T(0.5);
    inside[l] = (x0 + l < W) ? -1 : 0;
  }
  const int64_t start = tile_offsets[tile], count = tile_offsets[tile + 1] - start;
  local.resize((size_t)count * NL);
  for (int64_t k = 0; k < count; ++k) {
    if (k + 8 < count) {
      const int64_t gp = tile_ids[start + k + 8];
      __builtin_prefetch(gdata + gp * NG);
      __builtin_prefetch(gdata + gp * NG + NG - 1);
      __builtin_prefetch(aux + 2 * gp);
    }
    const int32_t gi = tile_ids[start + k];
    const T *g = gdata + (int64_t)gi * NG;
    T *d = local.data() + k * NL;
    d[0] = g[0], d[1] = g[1], d[2] = g[2], d[3] = g[3], d[4] = g[4], d[5] = g[5];
    d[6] = aux[2 * gi], d[7] = aux[2 * gi + 1];
    for (int ch = 0; ch < NF; ++ch) d[8 + ch] = g[6 + ch];
  }
  // Per-row lists of the Gaussians whose footprint reaches the row (front to back), so the row
  // loops below have no data-dependent skip branch.
  rowlist.resize((size_t)count * TS);
  int64_t row_n[TS] = {0};
  for (int64_t k = 0; k < count; ++k) {
    const T *d = local.data() + k * NL;
    T rlo = std::ceil(d[1] - d[6] - T(y0) - T(0.5)), rhi = std::floor(d[1] + d[6] - T(y0) - T(0.5));
    rlo = std::max(rlo, T(0));
    rhi = std::min(rhi, T(nrows - 1));
    if (!(rlo <= rhi)) continue;
    for (int r = (int)rlo; r <= (int)rhi; ++r) rowlist[r * count + row_n[r]++] = (int32_t)k;
  }
  for (int r = 0; r < nrows; ++r) {
    const T py = T(y0 + r) + T(0.5);
    V Tr = V{} + T(1);
    V acc[NF];
    for (int ch = 0; ch < NF; ++ch) acc[ch] = V{};
    I last = I{}, done = ~inside, ncontrib = I{}, neval = I{};
    const int32_t *rl = rowlist.data() + r * count;
    for (int64_t j = 0; j < row_n[r]; ++j) {
      const int64_t k = rl[j];
      const T *d = local.data() + k * NL;
      const T dy = py - d[1];
      const V dx = X - d[0];
      const V power = T(-0.5) * (d[2] * dx * dx + d[4] * dy * dy) - d[3] * dx * dy;
      neval -= ~done;
      if (!any((power > d[7]) & ~done)) continue;
      V alpha = d[5] * vexp<T>(power);
      alpha = alpha > amax ? V{} + amax : alpha;
      I m = (alpha >= amin) & ~done;
      if (!any(m)) continue;
      const V test = Tr * (T(1) - alpha);
      const I stop = m & (test < tmin);
      m &= ~stop;
      const V w = m ? alpha * Tr : V{};
      for (int ch = 0; ch < NF; ++ch) acc[ch] += w * d[8 + ch];
      Tr = m ? test : Tr;
      last = m ? I{} + (typename VT<T>::IS)(k + 1) : last;
      ncontrib -= m;
      if (any(stop)) {
        done |= stop;
        if (all(done)) break;
      }
    }
    const int y = y0 + r;
    for (int l = 0; l < TS && x0 + l < W; ++l) {
      const int64_t pix = (int64_t)y * W + x0 + l;
      T *o = out + pix * NO;
      for (int ch = 0; ch < NF; ++ch) o[ch] = acc[ch][l];
      for (int ch = 0; ch < 3; ++ch) o[ch] += Tr[l] * bg[ch];
      o[NF] = T(1) - Tr[l];
      tfinal[pix] = Tr[l];
      last_out[pix] = (int32_t)last[l];
      if (stats) {
        stats[2 * pix] = (int32_t)neval[l];
        stats[2 * pix + 1] = (int32_t)ncontrib[l];
      }
    }
  }
}

// ---- backward -----------------------------------------------------------------------------
template <class T> struct alignas(64) RowB {
  // SG = sum_ch S_ch * g_ch, where S_ch is what lies behind the current Gaussian (composited
  // from just after it): S' = a f + (1 - a) S is linear, so one running value replaces 13.
  typename VT<T>::V T_, SG, g[NO], bgterm;
  typename VT<T>::I last;
  int64_t maxlast;
};

template <class T>
void backward_tile(int tile, const T *gdata, const T *aux, const int64_t *tile_offsets,
                   const int32_t *tile_ids, int W, int H, const T *bg, const Params &P,
                   const T *tfinal, const int32_t *last_in, const T *grad_out, T *grad_g) {
  typedef typename VT<T>::V V;
  typedef typename VT<T>::I I;
  const int tiles_x = (W + TS - 1) / TS;
  const int x0 = (tile % tiles_x) * TS, y0 = (tile / tiles_x) * TS;
  const int nrows = std::min(TS, H - y0);
  const T amin = (T)P.alpha_min, amax = (T)P.alpha_max;
  V X;
  for (int l = 0; l < TS; ++l) X[l] = T(x0 + l) + T(0.5);
  RowB<T> rows[TS];
  int64_t kmax = 0;
  for (int r = 0; r < nrows; ++r) {
    RowB<T> &s = rows[r];
    s.T_ = V{};
    s.SG = V{};
    s.last = I{};
    for (int ch = 0; ch < NO; ++ch) s.g[ch] = V{};
    s.maxlast = 0;
    const int y = y0 + r;
    for (int l = 0; l < TS && x0 + l < W; ++l) {
      const int64_t pix = (int64_t)y * W + x0 + l;
      s.T_[l] = tfinal[pix];
      s.last[l] = last_in[pix];
      s.maxlast = std::max<int64_t>(s.maxlast, last_in[pix]);
      for (int ch = 0; ch < NO; ++ch) s.g[ch][l] = grad_out[pix * NO + ch];
    }
    s.bgterm = s.T_ * (s.g[0] * bg[0] + s.g[1] * bg[1] + s.g[2] * bg[2]);
    kmax = std::max(kmax, s.maxlast);
  }
  const int64_t start = tile_offsets[tile];
  constexpr int64_t PF = 6;  // software prefetch distance (Gaussians are visited in random order)
  for (int64_t kl = kmax - 1; kl >= 0; --kl) {
    if (kl >= PF) {
      const int64_t gp = tile_ids[start + kl - PF];
      __builtin_prefetch(gdata + gp * NG);
      __builtin_prefetch(gdata + gp * NG + NG - 1);
      __builtin_prefetch(aux + 2 * gp);
      __builtin_prefetch(grad_g + gp * NG, 1);
      __builtin_prefetch(grad_g + gp * NG + NG - 1, 1);
    }
    const int32_t gi = tile_ids[start + kl];
    const T *g = gdata + (int64_t)gi * NG;
    const T mx = g[0], my = g[1], a = g[2], b = g[3], c = g[4], o = g[5];
    const T ey = aux[2 * gi], pthr = aux[2 * gi + 1];
    T rlo = std::ceil(my - ey - T(y0) - T(0.5)), rhi = std::floor(my + ey - T(y0) - T(0.5));
    rlo = std::max(rlo, T(0));
    rhi = std::min(rhi, T(nrows - 1));
    if (!(rlo <= rhi)) continue;
    const int r0 = (int)rlo, r1 = (int)rhi;
    const V dx = X - mx;
    const V qa = T(-0.5) * a * dx * dx;
    const V bdx = b * dx;
    const I kk = I{} + (typename VT<T>::IS)kl;
    T f[NF];
    for (int ch = 0; ch < NF; ++ch) f[ch] = g[6 + ch];
    V gf[NF];
    for (int ch = 0; ch < NF; ++ch) gf[ch] = V{};
    V go = V{}, gmx = V{}, gmy = V{}, ga = V{}, gb = V{}, gc = V{};
    bool touched = false;
    for (int r = r0; r <= r1; ++r) {
      RowB<T> &s = rows[r];
      if (kl >= s.maxlast) continue;
      const T dy = T(y0 + r) + T(0.5) - my;
      const V power = qa - T(0.5) * c * dy * dy - bdx * dy;
      const I act = kk < s.last;
      if (!any((power > pthr) & act)) continue;
      const V G = vexp<T>(power);
      const V oG = o * G;
      V alpha = oG > amax ? V{} + amax : oG;
      const I m = act & (alpha >= amin);
      if (!any(m)) continue;
      touched = true;
      alpha = m ? alpha : V{};  // masked lanes: alpha = 0 leaves T and SG unchanged
      const V one_m = T(1) - alpha;
      const V inv = T(1) / one_m;
      const V Ti = s.T_ * inv;
      s.T_ = Ti;
      const V w = alpha * Ti;
      V FG = s.g[NF];  // opacity channel: f = 1
      for (int ch = 0; ch < NF; ++ch) {
        FG += f[ch] * s.g[ch];
        gf[ch] += w * s.g[ch];
      }
      V dA = (FG - s.SG) * Ti - s.bgterm * inv;
      s.SG = alpha * FG + one_m * s.SG;
      dA = (m & (oG <= amax)) ? dA : V{};
      go += dA * G;
      const V dP = dA * oG;
      gmx += dP * (a * dx + b * dy);
      gmy += dP * (bdx + c * dy);
      ga += dP * (T(-0.5) * dx * dx);
      gb += dP * (-dx * dy);
      gc += dP * (T(-0.5) * dy * dy);
    }
    if (touched) {
      T *gg = grad_g + (int64_t)gi * NG;
      V acc[TS] = {gmx, gmy, ga, gb, gc, go};
      for (int ch = 0; ch < TS - 6; ++ch) acc[6 + ch] = gf[ch];
      V red = hsum16<T>(acc), cur;
      std::memcpy(&cur, gg, sizeof(V));
      cur += red;
      std::memcpy(gg, &cur, sizeof(V));
      for (int ch = TS - 6; ch < NF; ++ch) gg[6 + ch] += hsum(gf[ch]);
    }
  }
}

}  // namespace

// ---- C entry points -------------------------------------------------------------------------
#define BR_EXPORT extern "C" __attribute__((visibility("default")))

#define BR_DEFINE(T, SUF)                                                                      \
  BR_EXPORT int br_project_##SUF(const T *means, const T *quats, const T *scales,              \
                                  const T *opac, const T *colors, const T *normals,            \
                                  const T *albedo, const T *rough, const T *metal,             \
                                  const double *cam /* w2c[16], fx, fy, cx, cy, near, guard,   \
                                                       low_pass, max_scale */,                 \
                                  int W, int H, int64_t N, int n_threads, T *gdata,            \
                                  uint8_t *valid) {                                            \
    Camera c = make_camera(cam, cam[16], cam[17], cam[18], cam[19], W, H, cam[20], cam[21],    \
                           cam[22], cam[23]);                                                  \
    return project<T>(means, quats, scales, opac, colors, normals, albedo, rough, metal, c, N, \
                      n_threads, gdata, valid);                                                \
  }                                                                                            \
  BR_EXPORT void br_project_backward_##SUF(const T *means, const T *quats, const T *scales,     \
                                           const T *opac, const double *cam, int W, int H,     \
                                           int64_t N, int n_threads, const T *grad_g,          \
                                           T *g_means, T *g_quats, T *g_scales, T *g_opac,     \
                                           T *g_colors, T *g_normals, T *g_albedo, T *g_rough, \
                                           T *g_metal, double *pose_grad) {                    \
    T *g_feat[5] = {g_colors, g_normals, g_albedo, g_rough, g_metal};                         \
    Camera c = make_camera(cam, cam[16], cam[17], cam[18], cam[19], W, H, cam[20], cam[21],    \
                           cam[22], cam[23]);                                                  \
    project_backward<T>(means, quats, scales, c, opac, N, n_threads, grad_g, g_means, g_quats, \
                        g_scales, g_opac, g_feat, pose_grad);                                  \
  }                                                                                            \
  BR_EXPORT int64_t br_bin_##SUF(const T *gdata, const uint8_t *valid, int64_t N, int W, int H,  \
                                 double alpha_min, int n_threads, T *aux, int64_t cap,         \
                                 int64_t *tile_offsets, int32_t *tile_ids, int32_t *tile_order, \
                                 int64_t *n_vis) {                                             \
    return bin<T>(gdata, valid, N, W, H, alpha_min, n_threads, aux, cap, tile_offsets,         \
                  tile_ids, tile_order, n_vis);                                                \
  }                                                                                            \
  BR_EXPORT void br_forward_##SUF(const T *gdata, const T *aux, const int64_t *tile_offsets,    \
                                  const int32_t *tile_ids, const int32_t *tile_order,          \
                                  int n_tiles, int W, int H, const T *bg, double alpha_min,    \
                                  double alpha_max, double t_min, int n_threads, T *out,       \
                                  T *tfinal, int32_t *last, int32_t *stats) {                  \
    Params P{alpha_min, alpha_max, t_min};                                                     \
    n_threads = std::max(1, std::min(n_threads, n_tiles));                                     \
    std::vector<std::vector<T>> local(n_threads);                                              \
    std::vector<std::vector<int32_t>> rowlist(n_threads);                                      \
    run_parallel(n_threads, n_tiles, [&](int i, int tid) {                                     \
      forward_tile<T>(tile_order[i], gdata, aux, tile_offsets, tile_ids, W, H, bg, P, out,      \
                      tfinal, last, stats, local[tid], rowlist[tid]);                          \
    });                                                                                        \
  }                                                                                            \
  BR_EXPORT void br_backward_##SUF(const T *gdata, const T *aux, const int64_t *tile_offsets,   \
                                   const int32_t *tile_ids, const int32_t *tile_order,         \
                                   int n_tiles, int W, int H, const T *bg, double alpha_min,   \
                                   double alpha_max, double t_min, int n_threads,              \
                                   const T *tfinal, const int32_t *last, const T *grad_out,    \
                                   int64_t N, T *grad_g /* [n_threads, N, NG], zeroed */) {    \
    Params P{alpha_min, alpha_max, t_min};                                                     \
    /* grad_g holds n_threads buffers of N * NG (uninitialised); each thread zeroes its own */ \
    const int n_alloc = n_threads;                                                             \
    n_threads = std::max(1, std::min(n_threads, n_tiles));                                     \
    run_parallel(n_alloc, n_alloc, [&](int t, int) {                                           \
      std::memset(grad_g + (int64_t)t * N * NG, 0, sizeof(T) * N * NG);                        \
    });                                                                                        \
    run_parallel(n_threads, n_tiles, [&](int i, int tid) {                                     \
      backward_tile<T>(tile_order[i], gdata, aux, tile_offsets, tile_ids, W, H, bg, P, tfinal,  \
                       last, grad_out, grad_g + (int64_t)tid * N * NG);                        \
    });                                                                                        \
    /* reduce the per-thread buffers into buffer 0 */                                          \
    const int64_t total = N * NG, CH = 65536;                                                  \
    if (n_threads > 1) {                                                                       \
      run_parallel(n_threads, (int)((total + CH - 1) / CH), [&](int ci, int) {                 \
        for (int64_t j = ci * CH; j < std::min(total, (ci + 1) * CH); ++j)                     \
          for (int t = 1; t < n_threads; ++t) grad_g[j] += grad_g[t * total + j];              \
      });                                                                                      \
    }                                                                                          \
  }

BR_DEFINE(float, f32)
BR_DEFINE(double, f64)

BR_EXPORT int br_abi_version() { return 6; }
