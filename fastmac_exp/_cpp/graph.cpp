// First- and second-order compatibility graphs (spec 2.1-2.3) and the sampler signals (spec 7.2-7.3).
#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <thread>

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#endif

#include "mac_core.hpp"
#include "parallel.hpp"

namespace fastmac {

Kernel parse_kernel(const std::string &name) {
    if (name == "gaussian") return Kernel::Gaussian;
    if (name == "quadratic") return Kernel::Quadratic;
    throw std::invalid_argument("kernel must be 'gaussian' or 'quadratic', got '" + name + "'");
}

void check_params(const GraphParams &gp) {
    if (!(gp.threshold > 0.0 && gp.threshold <= 1.0))
        throw std::invalid_argument("threshold must be in (0, 1], got " + std::to_string(gp.threshold));
    if (!(gp.alpha > 0.0) || !(gp.tau > 0.0))
        throw std::invalid_argument("alpha and tau must be positive");
}

int default_threads() {
#ifdef FASTMAC_OPENMP
    return omp_get_max_threads();
#else
    if (const char *env = std::getenv("OMP_NUM_THREADS")) {
        const int v = std::atoi(env);
        if (v > 0) return v;
    }
    const unsigned hw = std::thread::hardware_concurrency();
    return hw > 0 ? (int)std::min(hw, 256u) : 1;
#endif
}

int resolve_threads(int num_threads, int64_t n) {
    if (num_threads > 0) return num_threads;
    if (n >= 0 && n < kSerialBelow) return 1;
    return default_threads();
}

double max_distance(const GraphParams &gp) {
    if (gp.kernel == Kernel::Gaussian)
        return gp.threshold < 1.0 ? gp.alpha * std::sqrt(-2.0 * std::log(gp.threshold)) : 0.0;
    return gp.tau * std::sqrt(1.0 - gp.threshold);
}

namespace {

// The kernel exactly as the Python reference evaluates it (fastmac_exp/graph.py::kernel).
inline double kernel_value(double d, const GraphParams &gp) {
    if (gp.kernel == Kernel::Gaussian) return std::exp(-(d * d) / (2.0 * (gp.alpha * gp.alpha)));
    return 1.0 - (d * d) / (gp.tau * gp.tau);
}

// Float32 copies of the coordinates, centred per cloud, for screening pairs before the exact test.
//
// With a = |p_i - p_j| and b = |q_i - q_j|, an edge needs |a - b| <= L (L: the kernel's largest
// distance plus a margin for the float rounding of the coordinates). Since a + b <= sqrt(2 (a^2 + b^2)),
// it then has (a^2 - b^2)^2 = (a - b)^2 (a + b)^2 <= 2 L^2 (a^2 + b^2): no square root, and nearly tight
// for the pairs that matter (a ~ b). Allowing for the float error e <= 3e-7 (a^2 + b^2) of a^2 - b^2,
// the screen keeps every pair with
//     (a^2 - b^2)^2 <= (a^2 + b^2) (k1 + k2 (a^2 + b^2)),   k1 = 2.02 L^2,  k2 = 1e-11
// ((x + e)^2 <= 1.01 x^2 + 101 e^2). Survivors are tested exactly in double.
struct ScreenData {
    std::vector<float> px, py, pz, qx, qy, qz;
    float k1 = 0.f, k2 = 1e-11f;
};

// Writes to out (room for j1 - j0 + 16 entries) every j in [j0, j1) that passes the screen for row i, in
// increasing order; returns how many.
using ScreenFn = size_t (*)(const ScreenData &, int64_t, int64_t, int64_t, int32_t *);

constexpr int64_t kBlock = 1024;

size_t screen_generic(const ScreenData &S, int64_t i, int64_t j0, int64_t j1, int32_t *out) {
    uint8_t flag[kBlock];
    const float pxi = S.px[i], pyi = S.py[i], pzi = S.pz[i], qxi = S.qx[i], qyi = S.qy[i], qzi = S.qz[i];
    const float k1 = S.k1, k2 = S.k2;
    size_t cnt = 0;
    for (int64_t b0 = j0; b0 < j1; b0 += kBlock) {
        const int64_t len = std::min(kBlock, j1 - b0);
        const float *px = S.px.data() + b0, *py = S.py.data() + b0, *pz = S.pz.data() + b0;
        const float *qx = S.qx.data() + b0, *qy = S.qy.data() + b0, *qz = S.qz.data() + b0;
        for (int64_t k = 0; k < len; ++k) {
            const float ax = px[k] - pxi, ay = py[k] - pyi, az = pz[k] - pzi;
            const float bx = qx[k] - qxi, by = qy[k] - qyi, bz = qz[k] - qzi;
            const float a2 = ax * ax + ay * ay + az * az;
            const float b2 = bx * bx + by * by + bz * bz;
            const float diff = a2 - b2, sum = a2 + b2;
            flag[k] = (uint8_t)(diff * diff <= sum * (k1 + k2 * sum));
        }
        for (int64_t k = 0; k < len; ++k)
            if (flag[k]) out[cnt++] = (int32_t)(b0 + k);
    }
    return cnt;
}

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define FASTMAC_HAVE_AVX2_KERNEL 1
// The same screen, 8 pairs per step, candidates taken from the comparison's bit mask.
__attribute__((target("avx2"))) size_t screen_avx2(const ScreenData &S, int64_t i, int64_t j0, int64_t j1,
                                                   int32_t *out) {
    const __m256 pxi = _mm256_set1_ps(S.px[i]), pyi = _mm256_set1_ps(S.py[i]), pzi = _mm256_set1_ps(S.pz[i]);
    const __m256 qxi = _mm256_set1_ps(S.qx[i]), qyi = _mm256_set1_ps(S.qy[i]), qzi = _mm256_set1_ps(S.qz[i]);
    const __m256 k1 = _mm256_set1_ps(S.k1), k2 = _mm256_set1_ps(S.k2);
    const float *px = S.px.data(), *py = S.py.data(), *pz = S.pz.data();
    const float *qx = S.qx.data(), *qy = S.qy.data(), *qz = S.qz.data();
    // No call inside the loop (one would make the compiler keep the broadcast constants in memory:
    // vector registers are caller-saved), hence the output buffer.
    size_t cnt = 0;
    int64_t j = j0;
    for (; j + 8 <= j1; j += 8) {
        const __m256 ax = _mm256_sub_ps(_mm256_loadu_ps(px + j), pxi);
        const __m256 ay = _mm256_sub_ps(_mm256_loadu_ps(py + j), pyi);
        const __m256 az = _mm256_sub_ps(_mm256_loadu_ps(pz + j), pzi);
        const __m256 bx = _mm256_sub_ps(_mm256_loadu_ps(qx + j), qxi);
        const __m256 by = _mm256_sub_ps(_mm256_loadu_ps(qy + j), qyi);
        const __m256 bz = _mm256_sub_ps(_mm256_loadu_ps(qz + j), qzi);
        const __m256 a2 = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(ax, ax), _mm256_mul_ps(ay, ay)),
                                        _mm256_mul_ps(az, az));
        const __m256 b2 = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(bx, bx), _mm256_mul_ps(by, by)),
                                        _mm256_mul_ps(bz, bz));
        const __m256 diff = _mm256_sub_ps(a2, b2), sum = _mm256_add_ps(a2, b2);
        const __m256 rhs = _mm256_mul_ps(sum, _mm256_add_ps(k1, _mm256_mul_ps(k2, sum)));
        int bits = _mm256_movemask_ps(_mm256_cmp_ps(_mm256_mul_ps(diff, diff), rhs, _CMP_LE_OQ));
        while (bits) {
            out[cnt++] = (int32_t)(j + __builtin_ctz(bits));
            bits &= bits - 1;
        }
    }
    if (j < j1) cnt += screen_generic(S, i, j, j1, out + cnt);
    return cnt;
}

// AVX-512F: 16 pairs per step, the comparison gives the candidate mask directly.
__attribute__((target("avx512f"))) size_t screen_avx512(const ScreenData &S, int64_t i, int64_t j0, int64_t j1,
                                                       int32_t *out) {
    const __m512 pxi = _mm512_set1_ps(S.px[i]), pyi = _mm512_set1_ps(S.py[i]), pzi = _mm512_set1_ps(S.pz[i]);
    const __m512 qxi = _mm512_set1_ps(S.qx[i]), qyi = _mm512_set1_ps(S.qy[i]), qzi = _mm512_set1_ps(S.qz[i]);
    const __m512 k1 = _mm512_set1_ps(S.k1), k2 = _mm512_set1_ps(S.k2);
    const float *px = S.px.data(), *py = S.py.data(), *pz = S.pz.data();
    const float *qx = S.qx.data(), *qy = S.qy.data(), *qz = S.qz.data();
    const __m512i lane = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    size_t cnt = 0;
    int64_t j = j0;
    for (; j + 16 <= j1; j += 16) {
        const __m512 ax = _mm512_sub_ps(_mm512_loadu_ps(px + j), pxi);
        const __m512 ay = _mm512_sub_ps(_mm512_loadu_ps(py + j), pyi);
        const __m512 az = _mm512_sub_ps(_mm512_loadu_ps(pz + j), pzi);
        const __m512 bx = _mm512_sub_ps(_mm512_loadu_ps(qx + j), qxi);
        const __m512 by = _mm512_sub_ps(_mm512_loadu_ps(qy + j), qyi);
        const __m512 bz = _mm512_sub_ps(_mm512_loadu_ps(qz + j), qzi);
        const __m512 a2 = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(ax, ax), _mm512_mul_ps(ay, ay)),
                                        _mm512_mul_ps(az, az));
        const __m512 b2 = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(bx, bx), _mm512_mul_ps(by, by)),
                                        _mm512_mul_ps(bz, bz));
        const __m512 diff = _mm512_sub_ps(a2, b2), sum = _mm512_add_ps(a2, b2);
        const __m512 rhs = _mm512_mul_ps(sum, _mm512_add_ps(k1, _mm512_mul_ps(k2, sum)));
        const __mmask16 bits = _mm512_cmp_ps_mask(_mm512_mul_ps(diff, diff), rhs, _CMP_LE_OQ);
        // Branch free: the candidates' indices packed to the front of a vector, all 16 lanes stored (out has
        // room for j1 - j0 + 16 entries).
        const __m512i idx = _mm512_add_epi32(_mm512_set1_epi32((int)j), lane);
        _mm512_storeu_si512(out + cnt, _mm512_maskz_compress_epi32(bits, idx));
        cnt += (size_t)__builtin_popcount((unsigned)bits);
    }
    if (j < j1) cnt += screen_avx2(S, i, j, j1, out + cnt);
    return cnt;
}
#endif

ScreenFn pick_screen() {
#ifdef FASTMAC_HAVE_AVX2_KERNEL
    if (const char *env = std::getenv("FASTMAC_SCREEN"))  // for benchmarks: avx512 | avx2 | generic
        return std::string(env) == "generic" ? screen_generic
               : std::string(env) == "avx2" ? screen_avx2
               : (__builtin_cpu_supports("avx512f") ? screen_avx512 : screen_avx2);
    if (__builtin_cpu_supports("avx512f")) return screen_avx512;
    if (__builtin_cpu_supports("avx2")) return screen_avx2;
#endif
    return screen_generic;
}

// The exact test of row i's candidates, in double as the reference computes it (norms of the differences,
// then the kernel): writes the candidates j with W_ij >= threshold and their weights to col / w (room for
// n_cand + 8 entries), in order; returns how many. The coordinates are the caller's doubles in SoA form.
struct ExactData {
    std::vector<double> sx, sy, sz, tx, ty, tz;
};
using TestFn = size_t (*)(const ExactData &, const GraphParams &, int64_t, const int32_t *, size_t, int32_t *,
                          double *);

size_t test_generic(const ExactData &E, const GraphParams &gp, int64_t i, const int32_t *cand, size_t n_cand,
                    int32_t *col, double *w) {
    const double pix = E.sx[i], piy = E.sy[i], piz = E.sz[i], qix = E.tx[i], qiy = E.ty[i], qiz = E.tz[i];
    const double thr = gp.threshold;
    size_t cnt = 0;
    for (size_t c = 0; c < n_cand; ++c) {
        const int32_t j = cand[c];
        const double ax = pix - E.sx[j], ay = piy - E.sy[j], az = piz - E.sz[j];
        const double bx = qix - E.tx[j], by = qiy - E.ty[j], bz = qiz - E.tz[j];
        const double dp = std::sqrt(ax * ax + ay * ay + az * az);
        const double dq = std::sqrt(bx * bx + by * by + bz * bz);
        const double v = kernel_value(std::fabs(dp - dq), gp);
        if (v >= thr) {
            col[cnt] = j;
            w[cnt++] = v;
        }
    }
    return cnt;
}

#ifdef FASTMAC_HAVE_AVX2_KERNEL
// Eight candidates per step: the same operations in the same order, lane by lane (IEEE sqrt and division
// are exactly rounded, no FMA), so the weights are bit-identical to test_generic's. The Gaussian's exp
// runs per lane in scalar code.
__attribute__((target("avx512f"))) size_t test_avx512(const ExactData &E, const GraphParams &gp, int64_t i,
                                                     const int32_t *cand, size_t n_cand, int32_t *col,
                                                     double *w) {
    const __m512d pix = _mm512_set1_pd(E.sx[i]), piy = _mm512_set1_pd(E.sy[i]), piz = _mm512_set1_pd(E.sz[i]);
    const __m512d qix = _mm512_set1_pd(E.tx[i]), qiy = _mm512_set1_pd(E.ty[i]), qiz = _mm512_set1_pd(E.tz[i]);
    const __m512d thr = _mm512_set1_pd(gp.threshold), one = _mm512_set1_pd(1.0);
    const __m512d tau2 = _mm512_set1_pd(gp.tau * gp.tau);
    const __m512i sign = _mm512_set1_epi64(0x7fffffffffffffffLL);
    const bool quadratic = gp.kernel == Kernel::Quadratic;
    size_t cnt = 0;
    for (size_t c = 0; c < n_cand; c += 8) {
        const __mmask8 live = n_cand - c >= 8 ? (__mmask8)0xff : (__mmask8)((1u << (n_cand - c)) - 1u);
        alignas(32) int32_t tail[8] = {0, 0, 0, 0, 0, 0, 0, 0};
        const int32_t *ip = cand + c;
        if (live != 0xff) {
            for (size_t t = 0; t < n_cand - c; ++t) tail[t] = cand[c + t];
            ip = tail;
        }
        const __m256i idx = _mm256_loadu_si256((const __m256i *)ip);
        const __m512d zero = _mm512_setzero_pd();
#define FASTMAC_GATHER(v) _mm512_mask_i32gather_pd(zero, live, idx, (v).data(), 8)
        const __m512d ax = _mm512_sub_pd(pix, FASTMAC_GATHER(E.sx)), ay = _mm512_sub_pd(piy, FASTMAC_GATHER(E.sy)),
                      az = _mm512_sub_pd(piz, FASTMAC_GATHER(E.sz));
        const __m512d bx = _mm512_sub_pd(qix, FASTMAC_GATHER(E.tx)), by = _mm512_sub_pd(qiy, FASTMAC_GATHER(E.ty)),
                      bz = _mm512_sub_pd(qiz, FASTMAC_GATHER(E.tz));
#undef FASTMAC_GATHER
        const __m512d dp = _mm512_sqrt_pd(
            _mm512_add_pd(_mm512_add_pd(_mm512_mul_pd(ax, ax), _mm512_mul_pd(ay, ay)), _mm512_mul_pd(az, az)));
        const __m512d dq = _mm512_sqrt_pd(
            _mm512_add_pd(_mm512_add_pd(_mm512_mul_pd(bx, bx), _mm512_mul_pd(by, by)), _mm512_mul_pd(bz, bz)));
        const __m512d d = _mm512_castsi512_pd(_mm512_and_si512(_mm512_castpd_si512(_mm512_sub_pd(dp, dq)), sign));
        __m512d v;
        if (quadratic) {
            v = _mm512_sub_pd(one, _mm512_div_pd(_mm512_mul_pd(d, d), tau2));
        } else {
            alignas(64) double dl[8];
            _mm512_store_pd(dl, d);
            for (int t = 0; t < 8; ++t) dl[t] = kernel_value(dl[t], gp);
            v = _mm512_load_pd(dl);
        }
        const __mmask8 keep = _mm512_mask_cmp_pd_mask(live, v, thr, _CMP_GE_OQ);
        _mm256_storeu_si256((__m256i *)(col + cnt), _mm512_castsi512_si256(_mm512_maskz_compress_epi32(
                                                         (__mmask16)keep, _mm512_castsi256_si512(idx))));
        _mm512_storeu_pd(w + cnt, _mm512_maskz_compress_pd(keep, v));
        cnt += (size_t)__builtin_popcount((unsigned)keep);
    }
    return cnt;
}
#endif

TestFn pick_test() {
#ifdef FASTMAC_HAVE_AVX2_KERNEL
    if (const char *env = std::getenv("FASTMAC_SCREEN"); env && std::string(env) != "avx512") return test_generic;
    if (__builtin_cpu_supports("avx512f")) return test_avx512;
#endif
    return test_generic;
}


// Centred float32 copies of the coordinates for the screen, which keeps every pair whose inconsistency
// can be at most max_dist (m: the largest inconsistency of an edge, before the rounding margin).
ScreenData make_screen(const double *src, const double *tgt, int64_t n, double max_dist) {
    // Centred float32 copies for the screen.
    double cs[3] = {0, 0, 0}, ct[3] = {0, 0, 0};
    for (int64_t i = 0; i < n; ++i)
        for (int r = 0; r < 3; ++r) {
            cs[r] += src[3 * i + r];
            ct[r] += tgt[3 * i + r];
        }
    for (int r = 0; r < 3; ++r) {
        cs[r] /= (double)n;
        ct[r] /= (double)n;
    }
    ScreenData S;
    for (auto *v : {&S.px, &S.py, &S.pz, &S.qx, &S.qy, &S.qz}) v->resize(n);
    double rmax = 0.0;
    for (int64_t i = 0; i < n; ++i) {
        S.px[i] = (float)(src[3 * i] - cs[0]);
        S.py[i] = (float)(src[3 * i + 1] - cs[1]);
        S.pz[i] = (float)(src[3 * i + 2] - cs[2]);
        S.qx[i] = (float)(tgt[3 * i] - ct[0]);
        S.qy[i] = (float)(tgt[3 * i + 1] - ct[1]);
        S.qz[i] = (float)(tgt[3 * i + 2] - ct[2]);
        for (float v : {S.px[i], S.py[i], S.pz[i], S.qx[i], S.qy[i], S.qz[i]})
            rmax = std::max(rmax, (double)std::fabs(v));
    }
    // Float rounding of the coordinates moves each distance by well under 2e-6 * rmax; 1e-5 * rmax is a
    // safe margin.
    const double m = max_dist * (1.0 + 1e-7) + 1e-12;
    const double lim = (m + 1e-5 * rmax) * (1.0 + 1e-6);
    S.k1 = (float)(2.02 * lim * lim * (1.0 + 1e-5));
    return S;
}

// The symmetric CSR graph whose upper rows row(i, buf, col, w) finds: it writes row i's neighbours j > i
// (ascending) and their weights to col / w (room for n - i + 16 entries) and returns how many; buf is
// scratch of n + 32 entries. Unweighted (weighted = false): w is null and W.w stays empty.
template <class Row>
Csr assemble_graph(int64_t n, int nthreads, Row &&row, bool weighted = true) {
    Csr W;
    W.n = n;
    W.ptr.assign(n + 1, 0);
    W.upper.assign(n, 0);
    if (n == 0) return W;
    // The upper part of each row (neighbours j > i), found in parallel; each thread appends its rows to its
    // own buffers (no allocation per row).
    struct Part {
        std::vector<int32_t> col;
        std::vector<double> w;
        size_t size = 0;
    };
    std::vector<Part> parts(nthreads);
    std::vector<int32_t> row_tid(n, 0);
    std::vector<int64_t> row_off(n, 0), row_len(n, 0);
    DynamicRange rows(0, n, 16);
    parallel_region(nthreads, [&](int tid) {
        Part &part = parts[tid];
        std::vector<int32_t> buf(n + 32);
        int64_t lo, hi;
        while (rows.next(lo, hi))
            for (int64_t i = lo; i < hi; ++i) {
                if (part.col.size() < part.size + (size_t)(n - i) + 16) {
                    const size_t cap = std::max(2 * part.col.size(), part.size + (size_t)(n - i) + 16);
                    part.col.resize(cap);
                    if (weighted) part.w.resize(cap);
                }
                row_tid[i] = tid;
                row_off[i] = (int64_t)part.size;
                row_len[i] = (int64_t)row(i, buf.data(), part.col.data() + part.size,
                                          weighted ? part.w.data() + part.size : nullptr);
                part.size += (size_t)row_len[i];
            }
    });

    // The symmetric CSR: row i = [neighbours j < i ascending | neighbours j > i ascending]. The lower parts
    // are the transpose of the upper ones: a thread fills a block of rows j, taking from every row i < j
    // the stretch of its upper part that falls in the block (rows i in increasing order, so each lower
    // part comes out sorted).
    std::vector<int64_t> nlow(n, 0);
    for (int64_t i = 0; i < n; ++i) {
        const int32_t *c = parts[row_tid[i]].col.data() + row_off[i];
        for (int64_t k = 0; k < row_len[i]; ++k) ++nlow[c[k]];
    }
    for (int64_t i = 0; i < n; ++i) {
        W.ptr[i + 1] = W.ptr[i] + nlow[i] + row_len[i];
        W.upper[i] = W.ptr[i] + nlow[i];
    }
    W.col.resize(W.ptr[n]);
    if (weighted) W.w.resize(W.ptr[n]);
    const int64_t block = std::max<int64_t>(64, (n + 8 * nthreads - 1) / (8 * nthreads));
    DynamicRange blocks(0, (n + block - 1) / block, 1);
    parallel_region(nthreads, [&](int) {
        std::vector<int64_t> cursor(block);
        int64_t lo, hi;
        while (blocks.next(lo, hi)) {
            const int64_t r0 = lo * block, r1 = std::min(n, r0 + block);
            for (int64_t j = r0; j < r1; ++j) cursor[j - r0] = W.ptr[j];
            for (int64_t i = 0; i < r1 - 1; ++i) {
                const Part &part = parts[row_tid[i]];
                const int32_t *c0 = part.col.data() + row_off[i], *c1 = c0 + row_len[i];
                const int32_t *c = i + 1 >= r0 ? c0 : std::lower_bound(c0, c1, (int32_t)r0);
                for (; c < c1 && *c < r1; ++c) {
                    const int64_t q = cursor[*c - r0]++;
                    W.col[q] = (int32_t)i;
                    if (weighted) W.w[q] = part.w[c - part.col.data()];
                }
            }
            for (int64_t j = r0; j < r1; ++j) {  // and the upper parts of the block's own rows
                const Part &part = parts[row_tid[j]];
                std::memcpy(W.col.data() + W.upper[j], part.col.data() + row_off[j], row_len[j] * sizeof(int32_t));
                if (weighted)
                    std::memcpy(W.w.data() + W.upper[j], part.w.data() + row_off[j], row_len[j] * sizeof(double));
            }
        }
    });
    return W;
}


}  // namespace

Csr first_order(const double *src, const double *tgt, int64_t n, const GraphParams &gp, int nthreads) {
    check_params(gp);
    nthreads = resolve_threads(nthreads, pair_work_size(n));
    if (n == 0) return assemble_graph(0, nthreads, [](int64_t, int32_t *, int32_t *, double *) { return 0; });
    const ScreenData S = make_screen(src, tgt, n, max_distance(gp));
    const ScreenFn screen = pick_screen();
    const TestFn test = pick_test();
    ExactData E;
    for (auto *v : {&E.sx, &E.sy, &E.sz, &E.tx, &E.ty, &E.tz}) v->resize(n);
    for (int64_t i = 0; i < n; ++i) {
        E.sx[i] = src[3 * i], E.sy[i] = src[3 * i + 1], E.sz[i] = src[3 * i + 2];
        E.tx[i] = tgt[3 * i], E.ty[i] = tgt[3 * i + 1], E.tz[i] = tgt[3 * i + 2];
    }
    return assemble_graph(n, nthreads, [&](int64_t i, int32_t *buf, int32_t *col, double *w) {
        const size_t n_cand = screen(S, i, i + 1, n, buf);
        return test(E, gp, i, buf, n_cand, col, w);
    });
}

namespace {

// TurboReg's pair test in float32, as its LibTorch code evaluates it: a = |p_i - p_j| as
// sqrt(fma(dz, dz, fma(dy, dy, dx * dx))) (torch::norm's vectorised kernel; checked bit for bit against
// torch 2.13 on the CPU), d = |a - b|; an edge iff d < tau and not a + b <= cut. Every pair j > i of row i
// is tested (16 or 8 lanes at a time; IEEE sqrt and fma are exactly rounded, so all kernels agree bit for
// bit). Coordinates in SoA form.
struct LengthData {
    std::vector<float> px, py, pz, qx, qy, qz;
    float tau, cut;
    bool hard;
};

inline double soft_weight(float d, float tau) {
    const float r = d / tau;
    return (double)std::max(0.0f, 1.0f - r * r);
}

__attribute__((always_inline)) inline size_t length_row_scalar(const LengthData &L, int64_t i, int64_t j0,
                                                               int64_t j1, int32_t *col, double *w) {
    size_t cnt = 0;
    for (int64_t j = j0; j < j1; ++j) {
        const float ax = L.px[i] - L.px[j], ay = L.py[i] - L.py[j], az = L.pz[i] - L.pz[j];
        const float bx = L.qx[i] - L.qx[j], by = L.qy[i] - L.qy[j], bz = L.qz[i] - L.qz[j];
        const float a = std::sqrt(__builtin_fmaf(az, az, __builtin_fmaf(ay, ay, ax * ax)));
        const float b = std::sqrt(__builtin_fmaf(bz, bz, __builtin_fmaf(by, by, bx * bx)));
        const float d = std::fabs(a - b);
        if (d < L.tau && !(a + b <= L.cut)) {
            if (!L.hard) w[cnt] = soft_weight(d, L.tau);
            col[cnt++] = (int32_t)j;
        }
    }
    return cnt;
}

size_t length_row_generic(const LengthData &L, int64_t i, int32_t *col, double *w) {
    return length_row_scalar(L, i, i + 1, (int64_t)L.px.size(), col, w);
}

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
__attribute__((target("avx512f,fma"))) size_t length_row_avx512(const LengthData &L, int64_t i, int32_t *col,
                                                                double *w) {
    const int64_t n = (int64_t)L.px.size();
    const __m512 pxi = _mm512_set1_ps(L.px[i]), pyi = _mm512_set1_ps(L.py[i]), pzi = _mm512_set1_ps(L.pz[i]);
    const __m512 qxi = _mm512_set1_ps(L.qx[i]), qyi = _mm512_set1_ps(L.qy[i]), qzi = _mm512_set1_ps(L.qz[i]);
    const __m512 tau = _mm512_set1_ps(L.tau), cut = _mm512_set1_ps(L.cut);
    const __m512 k1 = _mm512_set1_ps(2.03f * L.tau * L.tau), k2 = _mm512_set1_ps(1e-11f);
    const __m512i lane = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    const __m512i absmask = _mm512_set1_epi32(0x7fffffff);
    const float *px = L.px.data(), *py = L.py.data(), *pz = L.pz.data();
    const float *qx = L.qx.data(), *qy = L.qy.data(), *qz = L.qz.data();
    size_t cnt = 0;
    int64_t j = i + 1;
    for (; j + 16 <= n; j += 16) {
        const __m512 ax = _mm512_sub_ps(pxi, _mm512_loadu_ps(px + j));
        const __m512 ay = _mm512_sub_ps(pyi, _mm512_loadu_ps(py + j));
        const __m512 az = _mm512_sub_ps(pzi, _mm512_loadu_ps(pz + j));
        const __m512 bx = _mm512_sub_ps(qxi, _mm512_loadu_ps(qx + j));
        const __m512 by = _mm512_sub_ps(qyi, _mm512_loadu_ps(qy + j));
        const __m512 bz = _mm512_sub_ps(qzi, _mm512_loadu_ps(qz + j));
        const __m512 a2 = _mm512_fmadd_ps(az, az, _mm512_fmadd_ps(ay, ay, _mm512_mul_ps(ax, ax)));
        const __m512 b2 = _mm512_fmadd_ps(bz, bz, _mm512_fmadd_ps(by, by, _mm512_mul_ps(bx, bx)));
        // Screen without the square roots (as first_order's): |a - b| < tau needs
        // (a^2 - b^2)^2 <= 2 tau^2 (a^2 + b^2), with room for the float rounding.
        const __m512 diff = _mm512_sub_ps(a2, b2), sum = _mm512_add_ps(a2, b2);
        if (!_mm512_cmp_ps_mask(_mm512_mul_ps(diff, diff), _mm512_mul_ps(sum, _mm512_fmadd_ps(k2, sum, k1)),
                                _CMP_LE_OQ))
            continue;
        const __m512 a = _mm512_sqrt_ps(a2), b = _mm512_sqrt_ps(b2);
        const __m512 d = _mm512_castsi512_ps(_mm512_and_si512(_mm512_castps_si512(_mm512_sub_ps(a, b)), absmask));
        const __mmask16 near = _mm512_cmp_ps_mask(d, tau, _CMP_LT_OQ);
        if (!near) continue;
        const __mmask16 keep = _mm512_mask_cmp_ps_mask(near, _mm512_add_ps(a, b), cut, _CMP_NLE_UQ);
        if (!keep) continue;
        _mm512_storeu_si512(col + cnt, _mm512_maskz_compress_epi32(keep, _mm512_add_epi32(_mm512_set1_epi32((int)j),
                                                                                            lane)));
        const size_t k = (size_t)__builtin_popcount((unsigned)keep);
        if (!L.hard) {
            alignas(64) float dl[16];
            _mm512_store_ps(dl, _mm512_maskz_compress_ps(keep, d));
            for (size_t c = 0; c < k; ++c) w[cnt + c] = soft_weight(dl[c], L.tau);
        }
        cnt += k;
    }
    return cnt + length_row_scalar(L, i, j, n, col + cnt, w + cnt);
}

__attribute__((target("fma"))) size_t length_row_fma(const LengthData &L, int64_t i, int32_t *col, double *w) {
    return length_row_scalar(L, i, i + 1, (int64_t)L.px.size(), col, w);
}
#endif

}  // namespace

Csr length_graph(const float *src, const float *tgt, int64_t n, float tau, float cut, bool hard, int nthreads) {
    if (!(tau > 0.0f)) throw std::invalid_argument("tau must be positive");
    nthreads = resolve_threads(nthreads, pair_work_size(n));
    LengthData L;
    for (auto *v : {&L.px, &L.py, &L.pz, &L.qx, &L.qy, &L.qz}) v->resize(n);
    for (int64_t i = 0; i < n; ++i) {
        L.px[i] = src[3 * i], L.py[i] = src[3 * i + 1], L.pz[i] = src[3 * i + 2];
        L.qx[i] = tgt[3 * i], L.qy[i] = tgt[3 * i + 1], L.qz[i] = tgt[3 * i + 2];
    }
    L.tau = tau;
    L.cut = cut;
    L.hard = hard;
    auto row = length_row_generic;
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
    const char *env = std::getenv("FASTMAC_SCREEN");  // avx512 | avx2 | generic, as the other kernels
    const std::string want = env ? env : "";
    if (want != "generic" && __builtin_cpu_supports("fma")) row = length_row_fma;
    if (want != "generic" && want != "avx2" && __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("fma"))
        row = length_row_avx512;
#endif
    return assemble_graph(
        n, nthreads, [&](int64_t i, int32_t *, int32_t *col, double *w) { return row(L, i, col, w); }, !hard);
}

double csr_lookup(const Csr &W, const std::vector<double> &vals, int32_t a, int32_t b) {
    const int32_t *first = W.col.data() + W.ptr[a];
    const int32_t *last = W.col.data() + W.ptr[a + 1];
    const int32_t *it = std::lower_bound(first, last, b);
    if (it == last || *it != b) return 0.0;
    return vals[it - W.col.data()];
}

Signals graph_signals(const Csr &W, const std::vector<double> &G, bool self_loops, int nthreads) {
    nthreads = resolve_threads(nthreads, W.n);
    const int64_t n = W.n;
    Signals out;
    out.n_edges = W.n_edges();
    out.degree.assign(n, 0.0);
    out.highpass.assign(n, 0.0);
    out.lowpass.assign(n, 0.0);
    std::vector<double> diag(n, 0.0);
    const double loop = self_loops ? 2.0 : 0.0;
    // Off-diagonal SOG_ij = G_ij + 2 W_ij^2 with self-loops, G_ij without; SOG_ii = 1 + sum_k W_ik^2.
    parallel_for(0, n, nthreads, 512, [&](int64_t i, int) {
        double off = 0.0, sq = 0.0;
        for (int64_t p = W.ptr[i]; p < W.ptr[i + 1]; ++p) {
            const double wv = W.w[p];
            off += G[p] + loop * wv * wv;
            sq += wv * wv;
        }
        diag[i] = self_loops ? 1.0 + sq : 0.0;
        out.degree[i] = diag[i] + off;
    });
    const double *s = out.degree.data();
    parallel_for(0, n, nthreads, 512, [&](int64_t i, int) {
        double hp = 0.0, ns = 0.0;
        for (int64_t p = W.ptr[i]; p < W.ptr[i + 1]; ++p) {
            const double wv = W.w[p];
            const double sog = G[p] + loop * wv * wv;
            const double sj = s[W.col[p]];
            hp += sog * (s[i] - sj);
            ns += sog * sj;
        }
        out.highpass[i] = hp;
        out.lowpass[i] = s[i] > 0.0 ? s[i] + (diag[i] * s[i] + ns) / s[i] : 0.0;
    });
    return out;
}

}  // namespace fastmac
