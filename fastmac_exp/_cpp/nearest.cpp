// Brute-force nearest neighbours in feature space (FPFH matching, fastmac_exp.descriptors.fpfh).
//
// In 33 dimensions a k-d tree visits most of its leaves, and numpy's float64 product with an inner
// dimension of 33 runs far below the FMA units' speed; this kernel computes ||b||^2 - 2 a.b (the squared
// distance up to the row's constant ||a||^2) for blocks of 8 rows of a against 8 columns of b at a time,
// b transposed so that each dimension is one contiguous load, and keeps a running minimum per lane.
#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <string>
#include <limits>
#include <vector>

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define FASTMAC_NN_X86 1
#endif

#include "mac_core.hpp"
#include "parallel.hpp"

namespace fastmac {

namespace {

constexpr int64_t kRows = 8;  // rows of a per block (broadcast operand)
constexpr int64_t kLanes = 8;  // columns of b per step (one vector of doubles)

struct Transposed {
    int64_t nb = 0, nbp = 0, dim = 0;
    std::vector<double> bt;  // dim x nbp, columns padded with +inf norms
    std::vector<double> bb;  // nbp squared norms (+inf in the padding: never the minimum)
};

// Rows [r0, r0 + rows) of a: for each, the index of the minimum of bb[j] - 2 a_r . b_j (ties: lowest j).
void block_generic(const double *a, int64_t dim, const Transposed &T, int64_t r0, int64_t rows, int64_t *out) {
    for (int64_t r = r0; r < r0 + rows; ++r) {
        const double *ar = a + r * dim;
        double best = std::numeric_limits<double>::infinity();
        int64_t arg = 0;
        for (int64_t j = 0; j < T.nb; ++j) {
            double dot = 0.0;
            for (int64_t d = 0; d < dim; ++d) dot += ar[d] * T.bt[d * T.nbp + j];
            const double v = T.bb[j] - 2.0 * dot;
            if (v < best) best = v, arg = j;
        }
        out[r] = arg;
    }
}

#ifdef FASTMAC_NN_X86
__attribute__((target("avx512f"))) void block_avx512(const double *a, int64_t dim, const Transposed &T,
                                                     int64_t r0, int64_t rows, int64_t *out) {
    __m512d best[kRows];
    __m512i arg[kRows];
    for (int t = 0; t < kRows; ++t) {
        best[t] = _mm512_set1_pd(std::numeric_limits<double>::infinity());
        arg[t] = _mm512_setzero_si512();
    }
    const __m512d m2 = _mm512_set1_pd(-2.0);
    const __m512i step = _mm512_set1_epi64(kLanes);
    __m512i idx = _mm512_setr_epi64(0, 1, 2, 3, 4, 5, 6, 7);
    for (int64_t j = 0; j < T.nbp; j += kLanes) {
        __m512d acc[kRows];
        for (int t = 0; t < kRows; ++t) acc[t] = _mm512_setzero_pd();
        for (int64_t d = 0; d < dim; ++d) {
            const __m512d bv = _mm512_loadu_pd(T.bt.data() + d * T.nbp + j);
#pragma GCC unroll 8
            for (int t = 0; t < kRows; ++t)
                acc[t] = _mm512_fmadd_pd(_mm512_set1_pd(a[(r0 + std::min<int64_t>(t, rows - 1)) * dim + d]), bv,
                                         acc[t]);
        }
        const __m512d bb = _mm512_loadu_pd(T.bb.data() + j);
#pragma GCC unroll 8
        for (int t = 0; t < kRows; ++t) {
            const __m512d v = _mm512_fmadd_pd(m2, acc[t], bb);
            const __mmask8 lt = _mm512_cmp_pd_mask(v, best[t], _CMP_LT_OQ);  // strict: earlier j wins ties
            best[t] = _mm512_mask_mov_pd(best[t], lt, v);
            arg[t] = _mm512_mask_mov_epi64(arg[t], lt, idx);
        }
        idx = _mm512_add_epi64(idx, step);
    }
    for (int64_t t = 0; t < rows; ++t) {
        alignas(64) double bv[kLanes];
        alignas(64) int64_t av[kLanes];
        _mm512_store_pd(bv, best[t]);
        _mm512_store_si512((__m512i *)av, arg[t]);
        int64_t k = 0;
        for (int64_t l = 1; l < kLanes; ++l)
            if (bv[l] < bv[k] || (bv[l] == bv[k] && av[l] < av[k])) k = l;
        out[r0 + t] = av[k];
    }
}
#endif

}  // namespace

std::vector<int64_t> nearest_rows(const double *a, int64_t na, const double *b, int64_t nb, int64_t dim,
                                  int nthreads) {
    std::vector<int64_t> out(na, 0);
    if (na == 0 || nb == 0) return out;
    Transposed T;
    T.nb = nb;
    T.dim = dim;
    T.nbp = (nb + kLanes - 1) / kLanes * kLanes;
    T.bt.assign(dim * T.nbp, 0.0);
    T.bb.assign(T.nbp, std::numeric_limits<double>::infinity());
    for (int64_t j = 0; j < nb; ++j) {
        double s = 0.0;
        for (int64_t d = 0; d < dim; ++d) {
            const double x = b[j * dim + d];
            T.bt[d * T.nbp + j] = x;
            s += x * x;
        }
        T.bb[j] = s;
    }
    auto block = block_generic;
#ifdef FASTMAC_NN_X86
    const char *env = std::getenv("FASTMAC_NN");  // tests: "generic" forces the portable loop
    if (!(env && std::string(env) == "generic") && __builtin_cpu_supports("avx512f")) block = block_avx512;
#endif
    nthreads = resolve_threads(nthreads, std::max<int64_t>(na, nb));
    const int64_t n_blocks = (na + kRows - 1) / kRows;
    parallel_for(0, n_blocks, nthreads, 4, [&](int64_t blk, int) {
        const int64_t r0 = blk * kRows;
        block(a, dim, T, r0, std::min(kRows, na - r0), out.data());
    });
    return out;
}

}  // namespace fastmac
