// Exact nearest rows in feature space (fpfh.hpp, nearest_rows_fast): a float32 screen of every pair, then
// float64 only where float32 cannot tell.
//
// For a row a and a candidate b_j the screen computes v'_j = ||b_j||^2 - 2 a.b_j in float32 and keeps,
// per row, the smallest v' with its index and the second smallest. Rounding a and b to float32 and a
// float32 dot product of length d move v' from the exact value by at most
// E = 2 gamma_(d+8) ||a|| max||b|| + 2 u max||b||^2 (u = 2^-24, gamma_k = k u / (1 - k u)); so when the
// runner-up is more than 2E above the winner, the winner of the float64 reference (nearest_rows) is the
// same index. Otherwise the row is scanned again in float64 exactly as nearest_rows does it (with FMA
// where nearest_rows' AVX-512 kernel runs, without where its portable loop runs), ties to the lowest index.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <limits>
#include <string>
#include <vector>

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define FASTMAC_FM_X86 1
#endif

#include "fpfh.hpp"
#include "mac_core.hpp"
#include "parallel.hpp"

namespace fastmac {

namespace {

constexpr int64_t kTile = 16;   // columns of b per vector
constexpr int64_t kRowsF = 8;   // rows of a per block
constexpr int64_t kTilesF = 2;  // tiles per step

struct Screen {
    int64_t nb = 0, ntiles = 0, dim = 0;
    std::vector<float> bt;  // ntiles x dim x 16 (b transposed per tile; padding 0)
    std::vector<float> bb;  // ntiles * 16 squared norms (+inf in the padding)
};

struct RowState {
    float best, second;
    int64_t arg;
};

// The float32 screen of rows [r0, r0 + rows) (portable).
void screen_generic(const float *a, const Screen &S, int64_t r0, int64_t rows, RowState *st) {
    std::vector<float> dots(kTile);
    for (int64_t r = r0; r < r0 + rows; ++r) {
        const float *ar = a + r * S.dim;
        float best = std::numeric_limits<float>::infinity(), second = best;
        int64_t arg = 0;
        for (int64_t t = 0; t < S.ntiles; ++t) {
            const float *bt = S.bt.data() + t * S.dim * kTile;
            for (int64_t l = 0; l < kTile; ++l) dots[l] = 0.0f;
            for (int64_t d = 0; d < S.dim; ++d)
                for (int64_t l = 0; l < kTile; ++l) dots[l] += ar[d] * bt[d * kTile + l];
            for (int64_t l = 0; l < kTile; ++l) {
                const float v = S.bb[t * kTile + l] - 2.0f * dots[l];
                if (v < best) {
                    second = best;
                    best = v;
                    arg = t * kTile + l;
                } else if (v < second) {
                    second = v;
                }
            }
        }
        st[r - r0] = {best, second, arg};
    }
}

#ifdef FASTMAC_FM_X86
// The screen on AVX-512: 8 rows x 32 columns of products in 16 registers per step; the per-row state (best,
// runner-up, index per lane) lives in memory between steps so that the product loop does not spill.
__attribute__((target("avx512f"))) void screen_avx512(const float *a, const Screen &S, int64_t r0, int64_t rows,
                                                      RowState *st) {
    const float inf = std::numeric_limits<float>::infinity();
    alignas(64) float best[kRowsF][kTile], second[kRowsF][kTile];
    alignas(64) int32_t arg[kRowsF][kTile];
    for (int t = 0; t < kRowsF; ++t) {
        _mm512_store_ps(best[t], _mm512_set1_ps(inf));
        _mm512_store_ps(second[t], _mm512_set1_ps(inf));
        _mm512_store_si512((__m512i *)arg[t], _mm512_setzero_si512());
    }
    // the rows' values interleaved by dimension (dim x 8), so that one step reads one cache line
    std::vector<float> at(size_t(S.dim * kRowsF));
    for (int64_t d = 0; d < S.dim; ++d)
        for (int t = 0; t < kRowsF; ++t) at[d * kRowsF + t] = a[(r0 + std::min<int64_t>(t, rows - 1)) * S.dim + d];
    const __m512 m2 = _mm512_set1_ps(-2.0f);
    const __m512i lane = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    const int64_t dim = S.dim;
    const float *ap = at.data();
    for (int64_t t0 = 0; t0 < S.ntiles; t0 += kTilesF) {
        const int64_t nt = std::min<int64_t>(kTilesF, S.ntiles - t0);
        const float *b0 = S.bt.data() + t0 * dim * kTile;
        const float *b1 = nt > 1 ? b0 + dim * kTile : b0;
        __m512 c00 = _mm512_setzero_ps(), c01 = c00, c10 = c00, c11 = c00, c20 = c00, c21 = c00, c30 = c00,
               c31 = c00, c40 = c00, c41 = c00, c50 = c00, c51 = c00, c60 = c00, c61 = c00, c70 = c00, c71 = c00;
        for (int64_t d = 0; d < dim; ++d) {
            const __m512 bv0 = _mm512_loadu_ps(b0 + d * kTile);
            const __m512 bv1 = _mm512_loadu_ps(b1 + d * kTile);
            const float *q = ap + d * kRowsF;
            __m512 x;
            x = _mm512_set1_ps(q[0]), c00 = _mm512_fmadd_ps(x, bv0, c00), c01 = _mm512_fmadd_ps(x, bv1, c01);
            x = _mm512_set1_ps(q[1]), c10 = _mm512_fmadd_ps(x, bv0, c10), c11 = _mm512_fmadd_ps(x, bv1, c11);
            x = _mm512_set1_ps(q[2]), c20 = _mm512_fmadd_ps(x, bv0, c20), c21 = _mm512_fmadd_ps(x, bv1, c21);
            x = _mm512_set1_ps(q[3]), c30 = _mm512_fmadd_ps(x, bv0, c30), c31 = _mm512_fmadd_ps(x, bv1, c31);
            x = _mm512_set1_ps(q[4]), c40 = _mm512_fmadd_ps(x, bv0, c40), c41 = _mm512_fmadd_ps(x, bv1, c41);
            x = _mm512_set1_ps(q[5]), c50 = _mm512_fmadd_ps(x, bv0, c50), c51 = _mm512_fmadd_ps(x, bv1, c51);
            x = _mm512_set1_ps(q[6]), c60 = _mm512_fmadd_ps(x, bv0, c60), c61 = _mm512_fmadd_ps(x, bv1, c61);
            x = _mm512_set1_ps(q[7]), c70 = _mm512_fmadd_ps(x, bv0, c70), c71 = _mm512_fmadd_ps(x, bv1, c71);
        }
        const __m512 acc[kRowsF][kTilesF] = {{c00, c01}, {c10, c11}, {c20, c21}, {c30, c31},
                                             {c40, c41}, {c50, c51}, {c60, c61}, {c70, c71}};
        for (int64_t c = 0; c < nt; ++c) {
            const __m512 bb = _mm512_loadu_ps(S.bb.data() + (t0 + c) * kTile);
            const __m512i idx = _mm512_add_epi32(lane, _mm512_set1_epi32(int((t0 + c) * kTile)));
            for (int t = 0; t < kRowsF; ++t) {
                const __m512 v = _mm512_fmadd_ps(m2, acc[t][c], bb);
                const __m512 bt = _mm512_load_ps(best[t]);
                const __mmask16 lt = _mm512_cmp_ps_mask(v, bt, _CMP_LT_OQ);
                _mm512_store_ps(second[t], _mm512_min_ps(_mm512_load_ps(second[t]), _mm512_max_ps(bt, v)));
                _mm512_store_ps(best[t], _mm512_mask_mov_ps(bt, lt, v));
                _mm512_store_si512((__m512i *)arg[t],
                                   _mm512_mask_mov_epi32(_mm512_load_si512((const __m512i *)arg[t]), lt, idx));
            }
        }
    }
    for (int64_t t = 0; t < rows; ++t) {
        int64_t k = 0;
        for (int64_t l = 1; l < kTile; ++l)
            if (best[t][l] < best[t][k] || (best[t][l] == best[t][k] && arg[t][l] < arg[t][k])) k = l;
        float sec = second[t][k];
        for (int64_t l = 0; l < kTile; ++l)
            if (l != k) sec = std::min(sec, best[t][l]);
        st[t] = {best[t][k], sec, arg[t][k]};
    }
}
#endif

#if defined(__GNUC__) && defined(__x86_64__) && !defined(__clang__)
#define FASTMAC_FM_CLONES __attribute__((target_clones("avx512f", "avx2", "default")))
#else
#define FASTMAC_FM_CLONES
#endif

// v'_j for every column of b, in float32 (the screen's quantity; any order of operations is within E).
#ifdef FASTMAC_FM_X86
__attribute__((target("avx512f"))) void screen_row_avx512(const float *ar, const Screen &S, float *v) {
    const __m512 m2 = _mm512_set1_ps(-2.0f);
    const int64_t dim = S.dim;
    int64_t t = 0;
    for (; t + 4 <= S.ntiles; t += 4) {  // four independent chains: the FMA latency is hidden
        const float *bt = S.bt.data() + t * dim * kTile;
        __m512 c0 = _mm512_setzero_ps(), c1 = c0, c2 = c0, c3 = c0;
        for (int64_t d = 0; d < dim; ++d) {
            const __m512 x = _mm512_set1_ps(ar[d]);
            c0 = _mm512_fmadd_ps(x, _mm512_loadu_ps(bt + d * kTile), c0);
            c1 = _mm512_fmadd_ps(x, _mm512_loadu_ps(bt + (dim + d) * kTile), c1);
            c2 = _mm512_fmadd_ps(x, _mm512_loadu_ps(bt + (2 * dim + d) * kTile), c2);
            c3 = _mm512_fmadd_ps(x, _mm512_loadu_ps(bt + (3 * dim + d) * kTile), c3);
        }
        const float *bb = S.bb.data() + t * kTile;
        _mm512_storeu_ps(v + t * kTile, _mm512_fmadd_ps(m2, c0, _mm512_loadu_ps(bb)));
        _mm512_storeu_ps(v + (t + 1) * kTile, _mm512_fmadd_ps(m2, c1, _mm512_loadu_ps(bb + kTile)));
        _mm512_storeu_ps(v + (t + 2) * kTile, _mm512_fmadd_ps(m2, c2, _mm512_loadu_ps(bb + 2 * kTile)));
        _mm512_storeu_ps(v + (t + 3) * kTile, _mm512_fmadd_ps(m2, c3, _mm512_loadu_ps(bb + 3 * kTile)));
    }
    for (; t < S.ntiles; ++t) {
        const float *bt = S.bt.data() + t * dim * kTile;
        __m512 acc = _mm512_setzero_ps();
        for (int64_t d = 0; d < dim; ++d) acc = _mm512_fmadd_ps(_mm512_set1_ps(ar[d]), _mm512_loadu_ps(bt + d * kTile), acc);
        _mm512_storeu_ps(v + t * kTile, _mm512_fmadd_ps(m2, acc, _mm512_loadu_ps(S.bb.data() + t * kTile)));
    }
}

__attribute__((target("avx512f,fma"))) double exact_value_fma(const double *ar, const double *bj, double bbj,
                                                            int64_t dim) {
    double dot = 0.0;
    for (int64_t d = 0; d < dim; ++d) dot = __builtin_fma(ar[d], bj[d], dot);
    return __builtin_fma(-2.0, dot, bbj);
}
#endif

FASTMAC_FM_CLONES
void screen_row_generic(const float *__restrict ar, const Screen &S, float *__restrict v) {
    for (int64_t t = 0; t < S.ntiles; ++t) {
        const float *__restrict bt = S.bt.data() + t * S.dim * kTile;
        float acc[kTile] = {0};
        for (int64_t d = 0; d < S.dim; ++d)
            for (int64_t l = 0; l < kTile; ++l) acc[l] += ar[d] * bt[d * kTile + l];
        for (int64_t l = 0; l < kTile; ++l) v[t * kTile + l] = S.bb[t * kTile + l] - 2.0f * acc[l];
    }
}

// nearest_rows' float64 value of column j for row ar (nearest.cpp: an FMA chain in the AVX-512 kernel,
// plain products in the portable loop).
inline double exact_value(const double *ar, const double *bj, double bbj, int64_t dim, bool fma) {
    double dot = 0.0;
#ifdef FASTMAC_FM_X86
    if (fma) return exact_value_fma(ar, bj, bbj, dim);
#endif
    if (fma) {
        for (int64_t d = 0; d < dim; ++d) dot = std::fma(ar[d], bj[d], dot);
        return std::fma(-2.0, dot, bbj);
    }
    for (int64_t d = 0; d < dim; ++d) dot += ar[d] * bj[d];
    return bbj - 2.0 * dot;
}

// A row the screen could not decide: the columns within 2E of the smallest v' (the float64 winner is
// among them) are compared in float64, in index order with a strict <, so ties go to the lowest index.
int64_t settle_row(const double *ar, const float *ar32, const Screen &S, const double *b,
                   const std::vector<double> &bb, double E, bool fma, std::vector<float> &v) {
    v.resize(size_t(S.ntiles * kTile));
#ifdef FASTMAC_FM_X86
    if (__builtin_cpu_supports("avx512f"))
        screen_row_avx512(ar32, S, v.data());
    else
#endif
        screen_row_generic(ar32, S, v.data());
    float lo = std::numeric_limits<float>::infinity();
    for (int64_t j = 0; j < S.nb; ++j) lo = std::min(lo, v[j]);
    const double cut = double(lo) + 2.0 * E;
    double best = std::numeric_limits<double>::infinity();
    int64_t arg = -1;
    for (int64_t j = 0; j < S.nb; ++j) {
        if (!(double(v[j]) <= cut)) continue;
        const double x = exact_value(ar, b + j * S.dim, bb[j], S.dim, fma);
        if (arg < 0 || x < best) best = x, arg = j;
    }
    return arg < 0 ? 0 : arg;
}

}  // namespace

Matches nearest_rows_fast(const double *a, int64_t na, const double *b, int64_t nb, int64_t dim, int nthreads) {
    Matches out;
    out.idx.assign(na, 0);
    out.d2_second.assign(na, std::numeric_limits<double>::infinity());
    if (na == 0 || nb == 0) return out;
    if (nb >= (int64_t(1) << 31)) throw std::invalid_argument("nearest_rows_fast: b has too many rows");
    Screen S;
    S.nb = nb;
    S.dim = dim;
    S.ntiles = (nb + kTile - 1) / kTile;
    S.bt.assign(size_t(S.ntiles * dim * kTile), 0.0f);
    S.bb.assign(size_t(S.ntiles * kTile), std::numeric_limits<float>::infinity());
    std::vector<double> bb64(nb);
    double bmax2 = 0.0;
    for (int64_t j = 0; j < nb; ++j) {
        double s = 0.0;
        const int64_t t = j / kTile, l = j % kTile;
        for (int64_t d = 0; d < dim; ++d) {
            const double x = b[j * dim + d];
            S.bt[size_t((t * dim + d) * kTile + l)] = float(x);
            s += x * x;
        }
        bb64[j] = s;
        S.bb[j] = float(s);
        bmax2 = std::max(bmax2, s);
    }
    if (!std::isfinite(bmax2)) throw std::invalid_argument("nearest_rows_fast: b has a non-finite value");
    std::vector<float> a32(size_t(na * dim));
    for (int64_t i = 0; i < na * dim; ++i) a32[i] = float(a[i]);

    const double u = std::ldexp(1.0, -24);
    const double k = double(dim + 8) * u;
    const double gamma = k / (1 - k);
    const double bmax = std::sqrt(bmax2);

    auto screen = screen_generic;
    bool fma = false;  // what nearest_rows' kernel does on this CPU
#ifdef FASTMAC_FM_X86
    if (__builtin_cpu_supports("avx512f")) {
        if (!env_is("FASTMAC_NN", "generic")) fma = true;
        if (!env_is("FASTMAC_FM", "generic")) screen = screen_avx512;
    }
#endif
    nthreads = resolve_threads(nthreads, std::max<int64_t>(na, nb));
    const int64_t n_blocks = (na + kRowsF - 1) / kRowsF;
    std::atomic<int64_t> settled{0};
    parallel_for(0, n_blocks, nthreads, 2, [&](int64_t blk, int) {
        const int64_t r0 = blk * kRowsF, rows = std::min(kRowsF, na - r0);
        RowState st[kRowsF];
        thread_local std::vector<float> scratch;
        screen(a32.data(), S, r0, rows, st);
        for (int64_t t = 0; t < rows; ++t) {
            const int64_t r = r0 + t;
            double an2 = 0.0;
            for (int64_t d = 0; d < dim; ++d) an2 += a[r * dim + d] * a[r * dim + d];
            const double an = std::sqrt(an2);
            // the bound with a quarter to spare, and the float64 reference's own rounding
            const double E = 1.25 * (2.0 * gamma * an * bmax + 2.0 * u * bmax2) + 1e-12 * (an2 + bmax2);
            const double best = st[t].best, second = st[t].second;
            if (std::isfinite(best) && second - best > 2.0 * E) {
                out.idx[r] = st[t].arg;
            } else {
                out.idx[r] = settle_row(a + r * dim, a32.data() + r * dim, S, b, bb64, E, fma, scratch);
                settled.fetch_add(1, std::memory_order_relaxed);
            }
            out.d2_second[r] = std::isfinite(second) ? std::max(0.0, double(second) + an2) : second;
        }
    });
    out.settled_in_float64 = settled.load();
    return out;
}

}  // namespace fastmac
