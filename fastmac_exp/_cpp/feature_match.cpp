// Exact nearest rows in feature space (fpfh.hpp, nearest_rows_fast): a float32 screen, then float64 for the
// few columns the screen cannot tell apart.
//
// For a row a and a column b_j the screen computes v'_j = ||b_j||^2 - 2 a.b_j in float32. Rounding a and b
// to float32 and a float32 dot product of length d move v' from the exact value by at most
// E = 2 gamma_(d+8) ||a|| max||b|| + 2 u max||b||^2 (u = 2^-24, gamma_k = k u / (1 - k u)). The true
// nearest and runner-up therefore have v' within 2E of the screen's second smallest v' (order statistics
// move by at most E), so the screen keeps, per row, every column within 2E of its running second smallest
// (a handful a row; a few hundred on rows with many near-equal targets), and those are compared in float64
// exactly as nearest_rows does it (with FMA where nearest_rows' AVX-512 kernel runs, without where its
// portable loop runs), ties to the lowest index. That gives nearest_rows' index and the runner-up's squared
// distance in float64.
//
// Large b is cut into tiles of 16 similar rows (the leaves of a principal-axis tree), and the rows of a in
// blocks of 8 similar rows the same way. A tile whose centre c and radius R give ||a - c|| - R above the
// distance the row's running runner-up can have (sqrt(v'_2 + E + ||a||^2)) holds neither the nearest nor
// the runner-up (triangle inequality) and is skipped for that row; a block computes a tile when one of its
// rows needs it. On FPFH a block computes about a third of the tiles.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <utility>
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

constexpr int64_t kTile = 16;   // columns of b per vector (and rows of b per tile)
constexpr int64_t kRowsF = 8;   // rows of a per block
constexpr int64_t kTilesF = 2;  // tiles per step
constexpr int64_t kPruneFrom = 64;  // tiles of b from which the tree and the bound pay

struct Screen {
    int64_t nb = 0, ntiles = 0, dim = 0;
    std::vector<float> bt;  // ntiles x dim x 16 (b, in tile order, transposed per tile; padding 0)
    std::vector<float> bb;  // ntiles * 16 squared norms (+inf in the padding)
    std::vector<int64_t> col;  // the row of b in each tile slot (-1 in the padding)
    // the pruning bound: per tile its radius (rounded up) about its centre, the centres transposed per 16
    // tiles (ceil(ntiles / 16) x dim x 16) and their squared norms
    std::vector<float> radius, ct, cc;
    double cmax2 = 0.0;
};

// A row's scan: the smallest and second smallest screen values so far, every column whose value was within
// 2E of the second smallest when the scan reached it, and the largest distance the true runner-up can have.
struct RowScan {
    float s1, s2, thr, reach;
    double e, an2;
    std::vector<std::pair<int32_t, float>> cand;

    void reset(double bound, double norm2) {
        s1 = s2 = thr = reach = std::numeric_limits<float>::infinity();
        e = bound;
        an2 = norm2;
        cand.clear();
    }
    void take(int32_t slot, float v) {
        cand.emplace_back(slot, v);
        if (v < s1) {
            s2 = s1;
            s1 = v;
        } else if (v < s2) {
            s2 = v;
        } else {
            return;
        }
        // never below s2 + 2E and sqrt(s2 + E + |a|^2), whatever float32 rounds
        thr = std::nextafter(float(double(s2) + 2.0 * e), std::numeric_limits<float>::infinity());
        reach = std::nextafter(float(std::sqrt(std::max(0.0, double(s2) + e + an2))),
                               std::numeric_limits<float>::infinity());
    }
};

// One step of the screen: the rows of a block (at: dim x 8, interleaved) against up to kTilesF tiles
// (portable).
void step_generic(const float *at, const Screen &S, const int64_t *tiles, int64_t nt, int64_t rows,
                  RowScan *rs) {
    float dots[kTile];
    for (int64_t c = 0; c < nt; ++c) {
        const float *bt = S.bt.data() + tiles[c] * S.dim * kTile;
        for (int64_t t = 0; t < rows; ++t) {
            for (int64_t l = 0; l < kTile; ++l) dots[l] = 0.0f;
            for (int64_t d = 0; d < S.dim; ++d)
                for (int64_t l = 0; l < kTile; ++l) dots[l] += at[d * kRowsF + t] * bt[d * kTile + l];
            for (int64_t l = 0; l < kTile; ++l) {
                const float v = S.bb[tiles[c] * kTile + l] - 2.0f * dots[l];
                if (v <= rs[t].thr) rs[t].take(int32_t(tiles[c] * kTile + l), v);
            }
        }
    }
}

#ifdef FASTMAC_FM_X86
// The step on AVX-512: 8 rows x 32 columns of products in 16 registers; a tile's values are compared with
// each row's threshold in one instruction, and only the (rare, after the first tiles) columns under it
// leave the registers.
__attribute__((target("avx512f"))) void step_avx512(const float *at, const Screen &S, const int64_t *tiles,
                                                    int64_t nt, int64_t rows, RowScan *rs) {
    const __m512 m2 = _mm512_set1_ps(-2.0f);
    const int64_t dim = S.dim;
    const float *b0 = S.bt.data() + tiles[0] * dim * kTile;
    const float *b1 = nt > 1 ? S.bt.data() + tiles[1] * dim * kTile : b0;
    __m512 c00 = _mm512_setzero_ps(), c01 = c00, c10 = c00, c11 = c00, c20 = c00, c21 = c00, c30 = c00,
           c31 = c00, c40 = c00, c41 = c00, c50 = c00, c51 = c00, c60 = c00, c61 = c00, c70 = c00, c71 = c00;
    for (int64_t d = 0; d < dim; ++d) {
        const __m512 bv0 = _mm512_loadu_ps(b0 + d * kTile);
        const __m512 bv1 = _mm512_loadu_ps(b1 + d * kTile);
        const float *q = at + d * kRowsF;
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
        const __m512 bb = _mm512_loadu_ps(S.bb.data() + tiles[c] * kTile);
        for (int64_t t = 0; t < rows; ++t) {
            const __m512 v = _mm512_fmadd_ps(m2, acc[t][c], bb);
            __mmask16 m = _mm512_cmp_ps_mask(v, _mm512_set1_ps(rs[t].thr), _CMP_LE_OQ);
            if (!m) continue;
            alignas(64) float vals[kTile];
            _mm512_store_ps(vals, v);
            while (m) {
                const int l = __builtin_ctz(m);
                m &= m - 1;
                if (vals[l] <= rs[t].thr)  // the threshold may have fallen since the mask was taken
                    rs[t].take(int32_t(tiles[c] * kTile + l), vals[l]);
            }
        }
    }
}

__attribute__((target("avx512f,fma"))) double exact_value_fma(const double *ar, const double *bj, double bbj,
                                                            int64_t dim) {
    double dot = 0.0;
    for (int64_t d = 0; d < dim; ++d) dot = __builtin_fma(ar[d], bj[d], dot);
    return __builtin_fma(-2.0, dot, bbj);
}
#endif

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

// The principal axes of the rows of b (up to kAxes of them, as rows of `axes`, and the mean), from the
// covariance of ~1,024 evenly spaced rows by subspace iteration. The axes only order the trees (the
// matches are exact in any order); from 4,096 rows the covariance, on one thread, was 0.4-0.5 ms of a
// 4.7 ms fragment match and a 14.6 ms KITTI one, with no better pruning.
constexpr int kAxes = 8;

void principal_axes(const double *b, int64_t nb, int64_t dim, std::vector<double> &mean, std::vector<double> &axes) {
    const int64_t stride = std::max<int64_t>(1, nb / 1024);
    mean.assign(size_t(dim), 0.0);
    int64_t ns = 0;
    for (int64_t i = 0; i < nb; i += stride, ++ns)
        for (int64_t d = 0; d < dim; ++d) mean[size_t(d)] += b[i * dim + d];
    for (double &m : mean) m /= double(ns);
    std::vector<double> cov(size_t(dim * dim), 0.0), y(static_cast<size_t>(dim));
    for (int64_t i = 0; i < nb; i += stride) {
        for (int64_t d = 0; d < dim; ++d) y[size_t(d)] = b[i * dim + d] - mean[size_t(d)];
        for (int64_t d = 0; d < dim; ++d)
            for (int64_t e = d; e < dim; ++e) cov[size_t(d * dim + e)] += y[size_t(d)] * y[size_t(e)];
    }
    for (int64_t d = 0; d < dim; ++d)  // the lower triangle: the same products summed in the same order
        for (int64_t e = 0; e < d; ++e) cov[size_t(d * dim + e)] = cov[size_t(e * dim + d)];
    const int k = int(std::min<int64_t>(kAxes, dim));
    axes.assign(size_t(k * dim), 0.0);
    for (int q = 0; q < k; ++q)
        for (int64_t d = 0; d < dim; ++d) axes[size_t(q * dim + d)] = (d % k == q ? 1.0 : 0.0) + 1e-3 * double((d * 7 + q * 3) % 11);
    std::vector<double> next(axes.size());
    for (int it = 0; it < 12; ++it) {
        for (int q = 0; q < k; ++q)
            for (int64_t d = 0; d < dim; ++d) {
                double acc = 0.0;
                for (int64_t e = 0; e < dim; ++e) acc += cov[size_t(d * dim + e)] * axes[size_t(q * dim + e)];
                next[size_t(q * dim + d)] = acc;
            }
        for (int q = 0; q < k; ++q) {  // Gram-Schmidt
            double *v = next.data() + q * dim;
            for (int p = 0; p < q; ++p) {
                const double *w = next.data() + p * dim;
                double dot = 0.0;
                for (int64_t d = 0; d < dim; ++d) dot += v[d] * w[d];
                for (int64_t d = 0; d < dim; ++d) v[d] -= dot * w[d];
            }
            double n2 = 0.0;
            for (int64_t d = 0; d < dim; ++d) n2 += v[d] * v[d];
            const double inv = n2 > 1e-300 && std::isfinite(n2) ? 1.0 / std::sqrt(n2) : 0.0;
            for (int64_t d = 0; d < dim; ++d) v[d] *= inv;
        }
        axes.swap(next);
    }
}

// The rows of x (n x dim) in an order whose every run of `leaf` holds near rows: a k-d split at the median of
// the coordinate (on the principal axes) of largest spread, recursively, the first part a multiple of
// `leaf`. Deterministic.
std::vector<int64_t> tree_order(const double *x, int64_t n, int64_t dim, int64_t leaf, const std::vector<double> &mean,
                                const std::vector<double> &axes, int nthreads) {
    struct Item {
        float p[kAxes];
        int64_t row;
    };
    const int k = int(axes.size() / size_t(dim));
    std::vector<double> at(size_t(dim * kAxes), 0.0);  // the axes transposed: the products vectorise
    for (int q = 0; q < k; ++q)
        for (int64_t d = 0; d < dim; ++d) at[size_t(d * kAxes + q)] = axes[size_t(q * dim + d)];
    std::vector<Item> it(static_cast<size_t>(n));
    parallel_for(0, n, nthreads, 1024, [&](int64_t i, int) {
        double acc[kAxes] = {0};
        for (int64_t d = 0; d < dim; ++d) {
            const double y = x[i * dim + d] - mean[size_t(d)];
            for (int q = 0; q < kAxes; ++q) acc[q] += y * at[size_t(d * kAxes + q)];
        }
        Item &t = it[size_t(i)];
        t.row = i;
        for (int q = 0; q < kAxes; ++q) t.p[q] = std::isfinite(acc[q]) ? float(acc[q]) : 0.0f;
    });
    // A range's split depends on its rows alone, so the ranges below a split are independent: the top
    // levels split here, the subtrees below them in parallel, the same order as splitting one at a time.
    std::vector<std::pair<int64_t, int64_t>> top{{0, n}}, below;
    const int64_t want = nthreads > 1 && n >= 64 * leaf ? 4 * int64_t(nthreads) : 1;
    std::vector<uint64_t> keys;
    std::vector<Item> tmp;
    // splits [lo, hi) at its median (a leaf: not at all), the two halves appended to `out`
    auto split = [&](int64_t lo, int64_t hi, std::vector<uint64_t> &kbuf, std::vector<Item> &ibuf,
                     std::vector<std::pair<int64_t, int64_t>> &out) {
        const int64_t m = hi - lo;
        if (m <= leaf) return;
        double s1[kAxes] = {0}, s2[kAxes] = {0};
        for (int64_t i = lo; i < hi; ++i)
            for (int q = 0; q < kAxes; ++q) s1[q] += it[size_t(i)].p[q], s2[q] += double(it[size_t(i)].p[q]) * it[size_t(i)].p[q];
        int axis = 0;
        for (int q = 1; q < kAxes; ++q)
            if (s2[q] - s1[q] * s1[q] / double(m) > s2[axis] - s1[axis] * s1[axis] / double(m)) axis = q;
        const int64_t half = std::max(leaf, (m / 2) / leaf * leaf);
        // the median by integer keys: the coordinate's bits in an order-preserving form, then the position
        kbuf.resize(size_t(m));
        for (int64_t i = 0; i < m; ++i) {
            uint32_t u;
            std::memcpy(&u, &it[size_t(lo + i)].p[axis], sizeof u);
            u = (u & 0x80000000u) ? ~u : (u | 0x80000000u);
            kbuf[size_t(i)] = (uint64_t(u) << 32) | uint64_t(i);
        }
        std::nth_element(kbuf.begin(), kbuf.begin() + half, kbuf.end());
        ibuf.resize(size_t(m));
        for (int64_t i = 0; i < m; ++i) ibuf[size_t(i)] = it[size_t(lo + int64_t(kbuf[size_t(i)] & 0xffffffffu))];
        std::copy(ibuf.begin(), ibuf.end(), it.begin() + lo);
        out.push_back({lo, lo + half});
        out.push_back({lo + half, hi});
    };
    while (int64_t(top.size()) < want) {
        below.clear();
        for (const auto &[lo, hi] : top) split(lo, hi, keys, tmp, below);
        if (below.empty()) break;
        top.swap(below);
    }
    parallel_for(0, int64_t(top.size()), nthreads, 1, [&](int64_t r, int) {
        std::vector<std::pair<int64_t, int64_t>> stack{top[size_t(r)]}, halves;
        std::vector<uint64_t> k;
        std::vector<Item> t;
        while (!stack.empty()) {
            const auto [lo, hi] = stack.back();
            stack.pop_back();
            halves.clear();
            split(lo, hi, k, t, halves);
            for (const auto &h : halves) stack.push_back(h);
        }
    });
    std::vector<int64_t> order(static_cast<size_t>(n));
    for (int64_t i = 0; i < n; ++i) order[size_t(i)] = it[size_t(i)].row;
    return order;
}

// Fills the tiles' centres (float32, transposed per 16 tiles, with their squared norms) and radii.
void tile_bounds(const double *b, Screen &S, int nthreads) {
    const int64_t dim = S.dim, chunks = (S.ntiles + kTile - 1) / kTile;
    S.radius.assign(size_t(chunks * kTile), 0.0f);
    S.ct.assign(size_t(chunks * dim * kTile), 0.0f);
    S.cc.assign(size_t(chunks * kTile), std::numeric_limits<float>::infinity());
    parallel_for(0, S.ntiles, nthreads, 64, [&](int64_t t, int) {
        thread_local std::vector<double> c;
        c.assign(size_t(dim), 0.0);
        int64_t k = 0;
        for (int64_t l = 0; l < kTile; ++l) {
            const int64_t j = S.col[size_t(t * kTile + l)];
            if (j < 0) continue;
            ++k;
            for (int64_t d = 0; d < dim; ++d) c[size_t(d)] += b[j * dim + d];
        }
        double c2 = 0.0, r2 = 0.0;
        for (int64_t d = 0; d < dim; ++d) {
            const float cf = float(c[size_t(d)] / double(k));
            c[size_t(d)] = cf;  // the centre is the float32 one: the radius is measured from it
            c2 += double(cf) * cf;
            S.ct[size_t(((t / kTile) * dim + d) * kTile + t % kTile)] = cf;
        }
        for (int64_t l = 0; l < kTile; ++l) {
            const int64_t j = S.col[size_t(t * kTile + l)];
            if (j < 0) continue;
            double e2 = 0.0;
            for (int64_t d = 0; d < dim; ++d) e2 += (b[j * dim + d] - c[size_t(d)]) * (b[j * dim + d] - c[size_t(d)]);
            r2 = std::max(r2, e2);
        }
        S.radius[size_t(t)] = std::nextafter(float(std::sqrt(r2) * (1.0 + 1e-9)), std::numeric_limits<float>::infinity());
        S.cc[size_t(t)] = float(c2);
    });
    for (int64_t t = 0; t < S.ntiles; ++t) S.cmax2 = std::max(S.cmax2, double(S.cc[size_t(t)]) * (1.0 + 1e-6));
}

// lb2[r * stride + t]: a lower bound of the squared distance from row r of the block (at: dim x 8) to the
// centre of tile t: ||c||^2 - 2 a.c + ||a||^2 in float32 less its error bound (off[r] = ||a||^2 less the
// screen's E for the centres, already in float32); near[r]: the tile of the row's nearest centre.
void centre_bounds_generic(const float *at, const Screen &S, int64_t rows, const float *off, float *lb2,
                           int64_t stride, int64_t *near) {
    const int64_t dim = S.dim, chunks = (S.ntiles + kTile - 1) / kTile;
    for (int64_t r = 0; r < rows; ++r) {
        near[r] = 0;
        for (int64_t ch = 0; ch < chunks; ++ch) {
            const float *ct = S.ct.data() + ch * dim * kTile;
            float acc[kTile] = {0};
            for (int64_t d = 0; d < dim; ++d)
                for (int64_t l = 0; l < kTile; ++l) acc[l] += at[d * kRowsF + r] * ct[d * kTile + l];
            for (int64_t l = 0; l < kTile; ++l) {
                const int64_t t = ch * kTile + l;
                lb2[r * stride + t] = (S.cc[size_t(t)] - 2.0f * acc[l]) + off[r];
                if (t < S.ntiles && lb2[r * stride + t] < lb2[r * stride + near[r]]) near[r] = t;
            }
        }
    }
}

#ifdef FASTMAC_FM_X86
__attribute__((target("avx512f"))) void centre_bounds_avx512(const float *at, const Screen &S, int64_t rows,
                                                             const float *off, float *lb2, int64_t stride,
                                                             int64_t *near) {
    const int64_t dim = S.dim, chunks = (S.ntiles + kTile - 1) / kTile;
    const __m512 m2 = _mm512_set1_ps(-2.0f);
    const __m512i lane = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    __m512 best[kRowsF];
    __m512i arg[kRowsF];
    for (int r = 0; r < kRowsF; ++r) best[r] = _mm512_set1_ps(std::numeric_limits<float>::infinity()), arg[r] = _mm512_setzero_si512();
    for (int64_t ch = 0; ch < chunks; ch += 2) {
        const float *c0 = S.ct.data() + ch * dim * kTile;
        const float *c1 = ch + 1 < chunks ? c0 + dim * kTile : c0;
        __m512 acc[kRowsF][2];
        for (int r = 0; r < kRowsF; ++r) acc[r][0] = acc[r][1] = _mm512_setzero_ps();
        for (int64_t d = 0; d < dim; ++d) {
            const __m512 v0 = _mm512_loadu_ps(c0 + d * kTile), v1 = _mm512_loadu_ps(c1 + d * kTile);
            const float *q = at + d * kRowsF;
#pragma GCC unroll 8
            for (int r = 0; r < kRowsF; ++r) {
                const __m512 x = _mm512_set1_ps(q[r]);
                acc[r][0] = _mm512_fmadd_ps(x, v0, acc[r][0]);
                acc[r][1] = _mm512_fmadd_ps(x, v1, acc[r][1]);
            }
        }
        for (int64_t c = 0; c < 2 && ch + c < chunks; ++c) {
            const __m512 cc = _mm512_loadu_ps(S.cc.data() + (ch + c) * kTile);
            const __m512i idx = _mm512_add_epi32(lane, _mm512_set1_epi32(int((ch + c) * kTile)));
            for (int64_t r = 0; r < rows; ++r) {
                const __m512 v = _mm512_add_ps(_mm512_fmadd_ps(m2, acc[r][c], cc), _mm512_set1_ps(off[r]));
                _mm512_storeu_ps(lb2 + r * stride + (ch + c) * kTile, v);
                const __mmask16 lt = _mm512_cmp_ps_mask(v, best[r], _CMP_LT_OQ);
                best[r] = _mm512_mask_mov_ps(best[r], lt, v);
                arg[r] = _mm512_mask_mov_epi32(arg[r], lt, idx);
            }
        }
    }
    for (int64_t r = 0; r < rows; ++r) {
        alignas(64) float bv[kTile];
        alignas(64) int32_t av[kTile];
        _mm512_store_ps(bv, best[r]);
        _mm512_store_si512(av, arg[r]);
        int64_t k = 0;
        for (int64_t l = 1; l < kTile; ++l)
            if (bv[l] < bv[k] || (bv[l] == bv[k] && av[l] < av[k])) k = l;
        near[r] = av[k];
    }
}

// need: bit l set where tile ch * 16 + l may hold the nearest or runner-up of one of the rows:
// lb2 <= (reach + R)^2 (rounded up). Rows past `rows` have reach < 0.
__attribute__((target("avx512f"))) uint32_t needed_avx512(const float *lb2, int64_t stride, int64_t ch,
                                                          const float *radius, const float *reach, int64_t rows) {
    const __m512 R = _mm512_loadu_ps(radius + ch * kTile), up = _mm512_set1_ps(1.0f + 1e-6f);
    __mmask16 m = 0;
    for (int64_t r = 0; r < rows; ++r) {
        const __m512 q = _mm512_add_ps(_mm512_set1_ps(reach[r]), R);
        m |= _mm512_cmp_ps_mask(_mm512_loadu_ps(lb2 + r * stride + ch * kTile), _mm512_mul_ps(_mm512_mul_ps(q, q), up),
                                _CMP_LE_OQ);
    }
    return m;
}
#endif

uint32_t needed_generic(const float *lb2, int64_t stride, int64_t ch, const float *radius, const float *reach,
                        int64_t rows) {
    uint32_t m = 0;
    for (int64_t l = 0; l < kTile; ++l)
        for (int64_t r = 0; r < rows; ++r) {
            const float q = reach[r] + radius[ch * kTile + l];
            if (lb2[r * stride + ch * kTile + l] <= q * q * (1.0f + 1e-6f)) m |= 1u << l;
        }
    return m;
}

}  // namespace

Matches nearest_rows_fast(const double *a, int64_t na, const double *b, int64_t nb, int64_t dim, int nthreads) {
    Matches out;
    out.idx.assign(na, 0);
    out.d2_second.assign(na, std::numeric_limits<double>::infinity());
    if (na == 0 || nb == 0) return out;
    if (nb >= (int64_t(1) << 31)) throw std::invalid_argument("nearest_rows_fast: b has too many rows");
    std::vector<double> bb64(nb);
    double bmax2 = 0.0;
    for (int64_t j = 0; j < nb; ++j) {
        double s = 0.0;
        for (int64_t d = 0; d < dim; ++d) s += b[j * dim + d] * b[j * dim + d];
        // a NaN would pass std::max unseen
        if (!std::isfinite(s))
            throw std::invalid_argument("nearest_rows_fast: row " + std::to_string(j) + " of b has a non-finite value");
        bb64[j] = s;
        bmax2 = std::max(bmax2, s);
    }
    Screen S;
    S.nb = nb;
    S.dim = dim;
    S.ntiles = (nb + kTile - 1) / kTile;
    const bool prune = S.ntiles >= kPruneFrom && na >= 4 * kRowsF && !env_is("FASTMAC_FM_PRUNE", "off");
    std::vector<int64_t> border, aorder;
    nthreads = resolve_threads(nthreads, std::max<int64_t>(na, nb));
    if (prune) {  // the two trees, each on every thread
        std::vector<double> mean, axes;
        principal_axes(b, nb, dim, mean, axes);
        border = tree_order(b, nb, dim, kTile, mean, axes, nthreads);
        aorder = tree_order(a, na, dim, kRowsF, mean, axes, nthreads);
    }
    S.col.assign(size_t(S.ntiles * kTile), -1);
    S.bt.assign(size_t(S.ntiles * dim * kTile), 0.0f);
    S.bb.assign(size_t(S.ntiles * kTile), std::numeric_limits<float>::infinity());
    parallel_for(0, S.ntiles, nthreads, 64, [&](int64_t t, int) {
        for (int64_t slot = t * kTile; slot < std::min(nb, (t + 1) * kTile); ++slot) {
            const int64_t j = prune ? border[size_t(slot)] : slot, l = slot % kTile;
            S.col[size_t(slot)] = j;
            for (int64_t d = 0; d < dim; ++d) S.bt[size_t((t * dim + d) * kTile + l)] = float(b[j * dim + d]);
            S.bb[size_t(slot)] = float(bb64[j]);
        }
    });
    if (prune) tile_bounds(b, S, nthreads);

    const double u = std::ldexp(1.0, -24);
    const double k = double(dim + 8) * u;
    const double gamma = k / (1 - k);
    const double bmax = std::sqrt(bmax2);

    auto step = step_generic;
    auto centre = centre_bounds_generic;
    auto needed = needed_generic;
    bool fma = false;  // what nearest_rows' kernel does on this CPU
#ifdef FASTMAC_FM_X86
    if (__builtin_cpu_supports("avx512f")) {
        if (!env_is("FASTMAC_NN", "generic")) fma = true;
        if (!env_is("FASTMAC_FM", "generic")) step = step_avx512, centre = centre_bounds_avx512, needed = needed_avx512;
    }
#endif
    const int64_t n_blocks = (na + kRowsF - 1) / kRowsF;
    std::atomic<int64_t> settled{0};
    parallel_for(0, n_blocks, nthreads, 2, [&](int64_t blk, int) {
        const int64_t r0 = blk * kRowsF, rows = std::min(kRowsF, na - r0);
        thread_local std::vector<RowScan> rs(kRowsF);
        thread_local std::vector<float> at, lb;
        thread_local std::vector<char> seen;
        int64_t row[kRowsF];
        double E[kRowsF], an[kRowsF];
        at.assign(size_t(dim * kRowsF), 0.0f);
        for (int64_t t = 0; t < rows; ++t) {
            row[t] = prune ? aorder[size_t(r0 + t)] : r0 + t;
            const double *ar = a + row[t] * dim;
            double an2 = 0.0;
            for (int64_t d = 0; d < dim; ++d) an2 += ar[d] * ar[d], at[size_t(d * kRowsF + t)] = float(ar[d]);
            an[t] = std::sqrt(an2);
            // the bound with a quarter to spare, and the float64 reference's own rounding
            E[t] = 1.25 * (2.0 * gamma * an[t] * bmax + 2.0 * u * bmax2) + 1e-12 * (an2 + bmax2);
            rs[t].reset(E[t], an2);
        }
        if (!prune) {
            for (int64_t t0 = 0; t0 < S.ntiles; t0 += kTilesF) {
                const int64_t tiles[kTilesF] = {t0, t0 + 1};
                step(at.data(), S, tiles, std::min<int64_t>(kTilesF, S.ntiles - t0), rows, rs.data());
            }
        } else {
            const double cmax = std::sqrt(S.cmax2);
            double ec[kRowsF], an2[kRowsF];
            for (int64_t r = 0; r < rows; ++r) {
                an2[r] = rs[r].an2;
                ec[r] = 1.25 * (2.0 * gamma * an[r] * cmax + 2.0 * u * S.cmax2) +
                        4.0 * u * (an2[r] + S.cmax2 + 2.0 * an[r] * cmax);
            }
            const int64_t chunks = (S.ntiles + kTile - 1) / kTile, stride = chunks * kTile;
            float off[kRowsF];
            for (int64_t r = 0; r < rows; ++r) off[r] = float(an2[r] - ec[r]);
            lb.resize(size_t(kRowsF * stride));
            int64_t near[kRowsF];
            centre(at.data(), S, rows, off, lb.data(), stride, near);
            seen.assign(size_t(stride), 0);
            std::fill(seen.begin() + S.ntiles, seen.end(), 1);  // the padding
            int64_t pending[kTilesF], np = 0;
            auto visit = [&](int64_t t) {
                seen[size_t(t)] = 1;
                pending[np++] = t;
                if (np == kTilesF) step(at.data(), S, pending, np, rows, rs.data()), np = 0;
            };
            // first the tile of each row's nearest centre, so that the reach is short from the start
            for (int64_t r = 0; r < rows; ++r)
                if (!seen[size_t(near[r])]) visit(near[r]);
            if (np) step(at.data(), S, pending, np, rows, rs.data()), np = 0;
            // then every tile that one of the rows may still need: ||a - c|| - R <= reach
            float reach[kRowsF];
            for (int64_t ch = 0; ch < chunks; ++ch) {
                for (int64_t r = 0; r < rows; ++r) reach[r] = rs[r].reach;
                uint32_t m = needed(lb.data(), stride, ch, S.radius.data(), reach, rows);
                while (m) {
                    const int64_t t = ch * kTile + __builtin_ctz(m);
                    m &= m - 1;
                    if (!seen[size_t(t)]) visit(t);
                }
            }
            if (np) step(at.data(), S, pending, np, rows, rs.data());
        }
        for (int64_t t = 0; t < rows; ++t) {
            const int64_t r = row[t];
            const double *ar = a + r * dim;
            // the float32 threshold was rounded up; this is the exact one, on the final runner-up
            const double cut = double(rs[t].s2) + 2.0 * E[t], cut1 = double(rs[t].s1) + 2.0 * E[t];
            double best = std::numeric_limits<double>::infinity(), second = best;
            int64_t arg = -1, contenders = 0;
            for (const auto &[slot, v] : rs[t].cand) {
                if (!(double(v) <= cut)) continue;
                contenders += double(v) <= cut1;
                const int64_t j = S.col[size_t(slot)];
                const double x = exact_value(ar, b + j * dim, bb64[j], dim, fma);
                if (arg < 0 || x < best || (x == best && j < arg)) {  // ties: the lowest index
                    second = best;
                    best = x;
                    arg = j;
                } else if (x < second) {
                    second = x;
                }
            }
            out.idx[r] = arg < 0 ? 0 : arg;
            out.d2_second[r] = std::isfinite(second) ? std::max(0.0, second + rs[t].an2) : second;
            if (contenders > 1) settled.fetch_add(1, std::memory_order_relaxed);
        }
    });
    out.settled_in_float64 = settled.load();
    return out;
}

}  // namespace fastmac
