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
__attribute__((target("avx512f"))) void screen_avx512(const float *a, const Screen &S, int64_t r0, int64_t rows,
                                                      RowState *st) {
    const float inf = std::numeric_limits<float>::infinity();
    __m512 best[kRowsF], second[kRowsF];
    __m512i arg[kRowsF];
    for (int t = 0; t < kRowsF; ++t) {
        best[t] = second[t] = _mm512_set1_ps(inf);
        arg[t] = _mm512_setzero_si512();
    }
    const float *ar[kRowsF];
    for (int t = 0; t < kRowsF; ++t) ar[t] = a + (r0 + std::min<int64_t>(t, rows - 1)) * S.dim;
    const __m512 m2 = _mm512_set1_ps(-2.0f);
    const __m512i lane = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    const int64_t dim = S.dim;
    for (int64_t t0 = 0; t0 < S.ntiles; t0 += kTilesF) {
        const int64_t nt = std::min<int64_t>(kTilesF, S.ntiles - t0);
        __m512 acc[kRowsF][kTilesF];
        for (int t = 0; t < kRowsF; ++t)
            for (int c = 0; c < kTilesF; ++c) acc[t][c] = _mm512_setzero_ps();
        const float *b0 = S.bt.data() + t0 * dim * kTile;
        const float *b1 = nt > 1 ? b0 + dim * kTile : b0;
        for (int64_t d = 0; d < dim; ++d) {
            const __m512 bv0 = _mm512_loadu_ps(b0 + d * kTile);
            const __m512 bv1 = _mm512_loadu_ps(b1 + d * kTile);
#pragma GCC unroll 8
            for (int t = 0; t < kRowsF; ++t) {
                const __m512 av = _mm512_set1_ps(ar[t][d]);
                acc[t][0] = _mm512_fmadd_ps(av, bv0, acc[t][0]);
                acc[t][1] = _mm512_fmadd_ps(av, bv1, acc[t][1]);
            }
        }
        for (int64_t c = 0; c < nt; ++c) {
            const __m512 bb = _mm512_loadu_ps(S.bb.data() + (t0 + c) * kTile);
            const __m512i idx = _mm512_add_epi32(lane, _mm512_set1_epi32(int((t0 + c) * kTile)));
#pragma GCC unroll 8
            for (int t = 0; t < kRowsF; ++t) {
                const __m512 v = _mm512_fmadd_ps(m2, acc[t][c], bb);
                const __mmask16 lt = _mm512_cmp_ps_mask(v, best[t], _CMP_LT_OQ);
                second[t] = _mm512_min_ps(second[t], _mm512_max_ps(best[t], v));
                best[t] = _mm512_mask_mov_ps(best[t], lt, v);
                arg[t] = _mm512_mask_mov_epi32(arg[t], lt, idx);
            }
        }
    }
    for (int64_t t = 0; t < rows; ++t) {
        alignas(64) float bv[kTile], sv[kTile];
        alignas(64) int32_t av[kTile];
        _mm512_store_ps(bv, best[t]);
        _mm512_store_ps(sv, second[t]);
        _mm512_store_si512((__m512i *)av, arg[t]);
        int64_t k = 0;
        for (int64_t l = 1; l < kTile; ++l)
            if (bv[l] < bv[k] || (bv[l] == bv[k] && av[l] < av[k])) k = l;
        float sec = sv[k];
        for (int64_t l = 0; l < kTile; ++l)
            if (l != k) sec = std::min(sec, bv[l]);
        st[t] = {bv[k], sec, av[k]};
    }
}
#endif

// nearest_rows' float64 decision for one row (nearest.cpp: FMA chain in the AVX-512 kernel, plain
// products in the portable loop), ties to the lowest index.
int64_t exact_row(const double *ar, const double *b, const std::vector<double> &bb, int64_t nb, int64_t dim,
                  bool fma) {
    double best = std::numeric_limits<double>::infinity();
    int64_t arg = 0;
    for (int64_t j = 0; j < nb; ++j) {
        const double *bj = b + j * dim;
        double dot = 0.0, v;
        if (fma) {
            for (int64_t d = 0; d < dim; ++d) dot = std::fma(ar[d], bj[d], dot);
            v = std::fma(-2.0, dot, bb[j]);
        } else {
            for (int64_t d = 0; d < dim; ++d) dot += ar[d] * bj[d];
            v = bb[j] - 2.0 * dot;
        }
        if (v < best) best = v, arg = j;
    }
    return arg;
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
        screen(a32.data(), S, r0, rows, st);
        for (int64_t t = 0; t < rows; ++t) {
            const int64_t r = r0 + t;
            double an2 = 0.0;
            for (int64_t d = 0; d < dim; ++d) an2 += a[r * dim + d] * a[r * dim + d];
            const double an = std::sqrt(an2);
            // the bound, doubled for the float64 reference's own rounding and the norms' rounding
            const double E = 2.0 * (2.0 * gamma * an * bmax + 2.0 * u * bmax2) + 1e-12 * (an2 + bmax2);
            const double best = st[t].best, second = st[t].second;
            if (std::isfinite(best) && second - best > 2.0 * E) {
                out.idx[r] = st[t].arg;
            } else {
                out.idx[r] = exact_row(a + r * dim, b, bb64, nb, dim, fma);
                settled.fetch_add(1, std::memory_order_relaxed);
            }
            out.d2_second[r] = std::isfinite(second) ? std::max(0.0, double(second) + an2) : second;
        }
    });
    out.settled_in_float64 = settled.load();
    return out;
}

}  // namespace fastmac
