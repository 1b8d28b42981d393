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

namespace {

// The kernel exactly as the Python reference evaluates it (fastmac_exp/graph.py::kernel).
inline double kernel_value(double d, const GraphParams &gp) {
    if (gp.kernel == Kernel::Gaussian) return std::exp(-(d * d) / (2.0 * (gp.alpha * gp.alpha)));
    return 1.0 - (d * d) / (gp.tau * gp.tau);
}

// The largest inconsistency that can still make an edge.
double max_distance(const GraphParams &gp) {
    if (gp.kernel == Kernel::Gaussian)
        return gp.threshold < 1.0 ? gp.alpha * std::sqrt(-2.0 * std::log(gp.threshold)) : 0.0;
    return gp.tau * std::sqrt(1.0 - gp.threshold);
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

// Writes to out (room for j1 - j0 entries) every j in [j0, j1) that passes the screen for row i, in
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
        unsigned bits = _mm512_cmp_ps_mask(_mm512_mul_ps(diff, diff), rhs, _CMP_LE_OQ);
        while (bits) {
            out[cnt++] = (int32_t)(j + __builtin_ctz(bits));
            bits &= bits - 1;
        }
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

}  // namespace

Csr first_order(const double *src, const double *tgt, int64_t n, const GraphParams &gp, int nthreads) {
    check_params(gp);
    nthreads = resolve_threads(nthreads, n);
    Csr W;
    W.n = n;
    W.ptr.assign(n + 1, 0);
    W.upper.assign(n, 0);
    if (n == 0) return W;

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
    const double m = max_distance(gp) * (1.0 + 1e-7) + 1e-12;
    const double lim = (m + 1e-5 * rmax) * (1.0 + 1e-6);
    S.k1 = (float)(2.02 * lim * lim * (1.0 + 1e-5));
    const ScreenFn screen = pick_screen();
    const double thr = gp.threshold;

    // Upper-triangle neighbours of each row, found in parallel; each thread appends its rows to its own
    // buffers (no allocation per row).
    struct Part {
        std::vector<int32_t> col;
        std::vector<double> w;
    };
    std::vector<Part> parts(nthreads);
    std::vector<int32_t> row_tid(n, 0);
    std::vector<int64_t> row_off(n, 0), row_len(n, 0);
    DynamicRange rows(0, n - 1, 16);
    parallel_region(nthreads, [&](int tid) {
        Part &part = parts[tid];
        std::vector<int32_t> buf(n);
        int64_t lo, hi;
        while (rows.next(lo, hi))
            for (int64_t i = lo; i < hi; ++i) {
                const size_t n_cand = screen(S, i, i + 1, n, buf.data());
                row_tid[i] = tid;
                row_off[i] = (int64_t)part.col.size();
                const double *pi = src + 3 * i, *qi = tgt + 3 * i;
                for (size_t c = 0; c < n_cand; ++c) {
                    const int32_t j = buf[c];
                    // Exact test, as the reference computes it: norms of the differences, in double.
                    const double *pj = src + 3 * (int64_t)j, *qj = tgt + 3 * (int64_t)j;
                    const double ax = pi[0] - pj[0], ay = pi[1] - pj[1], az = pi[2] - pj[2];
                    const double bx = qi[0] - qj[0], by = qi[1] - qj[1], bz = qi[2] - qj[2];
                    const double dp = std::sqrt(ax * ax + ay * ay + az * az);
                    const double dq = std::sqrt(bx * bx + by * by + bz * bz);
                    const double s = kernel_value(std::fabs(dp - dq), gp);
                    if (s >= thr) {
                        part.col.push_back(j);
                        part.w.push_back(s);
                    }
                }
                row_len[i] = (int64_t)part.col.size() - row_off[i];
            }
    });

    // Assemble the symmetric CSR: row i = [neighbours j < i ascending | neighbours j > i ascending].
    std::vector<int64_t> nlow(n, 0);
    for (int64_t i = 0; i < n; ++i) {
        const int32_t *c = parts[row_tid[i]].col.data() + row_off[i];
        for (int64_t k = 0; k < row_len[i]; ++k) ++nlow[c[k]];
    }
    for (int64_t i = 0; i < n; ++i) W.ptr[i + 1] = W.ptr[i] + nlow[i] + row_len[i];
    W.col.resize(W.ptr[n]);
    W.w.resize(W.ptr[n]);
    std::vector<int64_t> cursor(W.ptr.begin(), W.ptr.end() - 1);
    for (int64_t i = 0; i < n; ++i) {
        W.upper[i] = W.ptr[i] + nlow[i];
        // cursor[i] == W.upper[i] here: all lower neighbours of i (rows < i) are already placed.
        const int64_t base = W.upper[i];
        const int32_t *c = parts[row_tid[i]].col.data() + row_off[i];
        const double *ws = parts[row_tid[i]].w.data() + row_off[i];
        for (int64_t k = 0; k < row_len[i]; ++k) {
            W.col[base + k] = c[k];
            W.w[base + k] = ws[k];
            const int64_t p = cursor[c[k]]++;
            W.col[p] = (int32_t)i;
            W.w[p] = ws[k];
        }
    }
    return W;
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
