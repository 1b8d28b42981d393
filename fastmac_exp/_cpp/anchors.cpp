// Estimated sampler signals from anchor correspondences (docs/estimated_scores.md): every node is tested
// against m anchors only, so the cost is O(N m + sum_i nnz_i^2) instead of the N^2 / 2 pair tests and the
// triangle work of the exact graph.
//
// With W the first-order graph with self-loops (W_ii = 1), FastMAC's generalized degree is
//     s_i = (W^3)_ii = 1 + 3 d_i + T_i,   d_i = sum_{j != i} W_ij^2,   T_i = sum_{j != k; j, k != i} W_ij W_jk W_ki,
// and its high-pass response f_i = s_i^2 - t_i with t_i = sum_j SOG_ij s_j
//     = (1 + d_i) s_i + 2 sum_{j != i} W_ij^2 s_j + sum_{j != k} W_ij W_jk W_ki s_j.
// Anchors a_1..a_m are drawn i.i.d. from q (by the caller); with v_r = W_{i a_r} / q_{a_r} (0 when a_r = i),
//     d^_i = 1/m sum_r v_r W_{i a_r},   T^_i = 1/(m(m-1)) sum_{r != t} v_r v_t W_{a_r a_t}
// (W_{a_r a_t} = 0 when a_r = a_t), which are unbiased for d_i and T_i, and the same sums weighted by the
// anchors' own s^ estimate the terms of t_i. Each row is one thread's serial sum in anchor order: the
// result does not depend on the thread count.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstring>
#include <stdexcept>
#include <vector>

#if defined(__GNUC__) && defined(__x86_64__)
#include <immintrin.h>
#endif

#include "interrupt.hpp"
#include "mac_core.hpp"
#include "parallel.hpp"

namespace fastmac {

namespace {

// The anchors' coordinates, contiguous and in float, centred on the first anchor. The estimate works in
// float throughout: its own sampling error is many orders above float rounding.
struct AnchorSet {
    int64_t m = 0;
    std::vector<int64_t> idx;
    std::vector<float> px, py, pz, qx, qy, qz;
    double cp[3] = {0, 0, 0}, cq[3] = {0, 0, 0};
    float max_d = 0.f;  // an edge needs d <= max_d (the kernels are decreasing in d)
    float inv_2a2 = 0.f, inv_t2 = 0.f;
    bool gaussian = true;
    float threshold = 1.f;
};

AnchorSet make_anchors(const double *src, const double *tgt, int64_t n, const int64_t *anchors, int64_t m,
                       const GraphParams &gp) {
    AnchorSet A;
    A.m = m;
    A.idx.assign(anchors, anchors + m);
    for (int64_t r = 0; r < m; ++r)
        if (A.idx[r] < 0 || A.idx[r] >= n) throw std::invalid_argument("anchor index out of range");
    if (m > 0)
        for (int c = 0; c < 3; ++c) A.cp[c] = src[3 * A.idx[0] + c], A.cq[c] = tgt[3 * A.idx[0] + c];
    A.px.resize(m), A.py.resize(m), A.pz.resize(m), A.qx.resize(m), A.qy.resize(m), A.qz.resize(m);
    for (int64_t r = 0; r < m; ++r) {
        const double *p = src + 3 * A.idx[r], *q = tgt + 3 * A.idx[r];
        A.px[r] = (float)(p[0] - A.cp[0]), A.py[r] = (float)(p[1] - A.cp[1]), A.pz[r] = (float)(p[2] - A.cp[2]);
        A.qx[r] = (float)(q[0] - A.cq[0]), A.qy[r] = (float)(q[1] - A.cq[1]), A.qz[r] = (float)(q[2] - A.cq[2]);
    }
    A.max_d = (float)max_distance(gp);
    A.gaussian = gp.kernel == Kernel::Gaussian;
    A.inv_2a2 = (float)(1.0 / (2.0 * gp.alpha * gp.alpha));
    A.inv_t2 = (float)(1.0 / (gp.tau * gp.tau));
    A.threshold = (float)gp.threshold;
    return A;
}

inline float weight_of(float d, const AnchorSet &A) {
    return A.gaussian ? std::exp(-d * d * A.inv_2a2) : 1.f - d * d * A.inv_t2;
}

// dist[r] = | |p_i - p_{a_r}| - |q_i - q_{a_r}| | for r in [r0, r1): branch-free, so it vectorises; built
// for AVX-512 and AVX2 besides the baseline and picked by the CPU at load time (half the estimate's time is
// here). Every lane does the same IEEE operations (no FMA contraction, no reassociation), so each clone
// gives the same distances.
#if defined(__GNUC__) && defined(__x86_64__) && !defined(__clang__)
__attribute__((target_clones("avx512f", "avx2", "default")))
#endif
void anchor_distances(const double *src, const double *tgt, int64_t i, const AnchorSet &A,
                      std::vector<float> &dist, int64_t r0, int64_t r1) {
    const double *p = src + 3 * i, *q = tgt + 3 * i;
    const float pxi = (float)(p[0] - A.cp[0]), pyi = (float)(p[1] - A.cp[1]), pzi = (float)(p[2] - A.cp[2]);
    const float qxi = (float)(q[0] - A.cq[0]), qyi = (float)(q[1] - A.cq[1]), qzi = (float)(q[2] - A.cq[2]);
    dist.resize(r1);
    float *dd = dist.data();
    const float *ax = A.px.data(), *ay = A.py.data(), *az = A.pz.data();
    const float *bx = A.qx.data(), *by = A.qy.data(), *bz = A.qz.data();
    for (int64_t r = r0; r < r1; ++r) {
        const float dx = ax[r] - pxi, dy = ay[r] - pyi, dz = az[r] - pzi;
        const float ex = bx[r] - qxi, ey = by[r] - qyi, ez = bz[r] - qzi;
        dd[r] = std::fabs(std::sqrt(dx * dx + dy * dy + dz * dz) - std::sqrt(ex * ex + ey * ey + ez * ez));
    }
}

#if defined(__GNUC__) && defined(__x86_64__)
// Whether the quadratic kernel's rows take the AVX-512 paths below (read once a process; FASTMAC_ANCHORS=generic
// forces the portable loops, for tests).
bool wide_rows() {
    static const bool wide = __builtin_cpu_supports("avx512f") && !env_is("FASTMAC_ANCHORS", "generic");
    return wide;
}
#endif

#if defined(__GNUC__) && defined(__x86_64__)
// Row i's point pair, centred as the anchors are, for the AVX-512 rows below: distances() gives 16 lanes of
// anchor_distances' values (the same operations in the same order).
struct LaneRow {
    __m512 px, py, pz, qx, qy, qz;
    __attribute__((target("avx512f"))) LaneRow(const double *src, const double *tgt, int64_t i, const AnchorSet &A) {
        const double *p = src + 3 * i, *q = tgt + 3 * i;
        px = _mm512_set1_ps((float)(p[0] - A.cp[0])), py = _mm512_set1_ps((float)(p[1] - A.cp[1]));
        pz = _mm512_set1_ps((float)(p[2] - A.cp[2]));
        qx = _mm512_set1_ps((float)(q[0] - A.cq[0])), qy = _mm512_set1_ps((float)(q[1] - A.cq[1]));
        qz = _mm512_set1_ps((float)(q[2] - A.cq[2]));
    }
    __attribute__((target("avx512f"), always_inline)) inline __m512 distances(const AnchorSet &A, int64_t r,
                                                                            __mmask16 lanes) const {
        const __m512 dx = _mm512_sub_ps(_mm512_maskz_loadu_ps(lanes, A.px.data() + r), px);
        const __m512 dy = _mm512_sub_ps(_mm512_maskz_loadu_ps(lanes, A.py.data() + r), py);
        const __m512 dz = _mm512_sub_ps(_mm512_maskz_loadu_ps(lanes, A.pz.data() + r), pz);
        const __m512 ex = _mm512_sub_ps(_mm512_maskz_loadu_ps(lanes, A.qx.data() + r), qx);
        const __m512 ey = _mm512_sub_ps(_mm512_maskz_loadu_ps(lanes, A.qy.data() + r), qy);
        const __m512 ez = _mm512_sub_ps(_mm512_maskz_loadu_ps(lanes, A.qz.data() + r), qz);
        const __m512 sp = _mm512_sqrt_ps(
            _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(dx, dx), _mm512_mul_ps(dy, dy)), _mm512_mul_ps(dz, dz)));
        const __m512 sq = _mm512_sqrt_ps(
            _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(ex, ex), _mm512_mul_ps(ey, ey)), _mm512_mul_ps(ez, ez)));
        return _mm512_abs_ps(_mm512_sub_ps(sp, sq));
    }
};
#endif

#if defined(__GNUC__) && defined(__x86_64__)
// anchor_row's quadratic kernel on AVX-512: the distances (anchor_distances' operations), the weights and
// the test of each lane, then the kept lanes compressed in registers and stored whole (cc and vv need 16
// slots past the count): the same entries in the same order as the portable loop.
__attribute__((target("avx512f"))) size_t quadratic_row_avx512(const double *src, const double *tgt, int64_t i,
                                                              const AnchorSet &A, int32_t *cc, double *vv,
                                                              int64_t r0, int64_t r1) {
    const LaneRow row(src, tgt, i, A);
    const __m512 one = _mm512_set1_ps(1.f), inv_t2 = _mm512_set1_ps(A.inv_t2), thr = _mm512_set1_ps(A.threshold);
    const __m512 lim = _mm512_set1_ps(A.max_d);
    const __m512i self = _mm512_set1_epi64(i);
    const __m512i iota = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    const int64_t *idx = A.idx.data();
    size_t k = 0;
    for (int64_t r = r0; r < r1; r += 16) {
        const __mmask16 lanes = r1 - r >= 16 ? __mmask16(0xffff) : __mmask16((1u << (r1 - r)) - 1u);
        const __m512 d = row.distances(A, r, lanes);
        const __m512 w = _mm512_sub_ps(one, _mm512_mul_ps(_mm512_mul_ps(d, d), inv_t2));
        const __mmask8 lo = __mmask8(lanes), hi = __mmask8(lanes >> 8);
        const __mmask16 other =
            __mmask16(_mm512_mask_cmpneq_epi64_mask(lo, _mm512_maskz_loadu_epi64(lo, idx + r), self)) |
            __mmask16(__mmask16(_mm512_mask_cmpneq_epi64_mask(hi, _mm512_maskz_loadu_epi64(hi, idx + r + 8), self))
                      << 8);
        const __mmask16 keep = _mm512_mask_cmp_ps_mask(
            _mm512_mask_cmp_ps_mask(other, d, lim, _CMP_LE_OQ), w, thr, _CMP_GE_OQ);
        if (!keep) continue;
        const __m512i cols = _mm512_add_epi32(_mm512_set1_epi32(int32_t(r)), iota);
        _mm512_storeu_si512(cc + k, _mm512_maskz_compress_epi32(keep, cols));
        const __mmask8 klo = __mmask8(keep), khi = __mmask8(keep >> 8);
        const size_t nlo = size_t(__builtin_popcount(unsigned(klo)));
        _mm512_storeu_pd(vv + k, _mm512_maskz_compress_pd(klo, _mm512_cvtps_pd(_mm512_castps512_ps256(w))));
        _mm512_storeu_pd(vv + k + nlo,
                         _mm512_maskz_compress_pd(khi, _mm512_cvtps_pd(_mm256_castpd_ps(_mm512_extractf64x4_pd(
                                                           _mm512_castps_pd(w), 1)))));
        k += nlo + size_t(__builtin_popcount(unsigned(khi)));
    }
    return k;
}
#endif

// W_{i a_r} for every anchor r in [r0, r1) with a nonzero weight (a_r != i), in increasing r, into the first
// entries of cols/vals (which keep at least r1 - r0 slots); returns how many. Weights only for the anchors
// within the edge distance. Branch-free for the quadratic kernel (the Gaussian's exp only for the anchors
// within the edge distance).
size_t anchor_row(const double *src, const double *tgt, int64_t i, const AnchorSet &A, std::vector<float> &dist,
                  std::vector<int32_t> &cols, std::vector<double> &vals, int64_t r0 = 0, int64_t r1 = -1) {
    const int64_t m = r1 < 0 ? A.m : r1;
    // 16 slots past the most entries, for the vector path's whole stores
    if (cols.size() < size_t(m - r0 + 16)) cols.resize(size_t(m - r0 + 16)), vals.resize(size_t(m - r0 + 16));
    int32_t *cc = cols.data();
    double *vv = vals.data();
#if defined(__GNUC__) && defined(__x86_64__)
    const bool wide = wide_rows();
    if (wide && !A.gaussian) return quadratic_row_avx512(src, tgt, i, A, cc, vv, r0, m);
#endif
    anchor_distances(src, tgt, i, A, dist, r0, m);
    const float *dd = dist.data();
    const int64_t *idx = A.idx.data();
    const float lim = A.max_d, thr = A.threshold;
    size_t k = 0;
    if (!A.gaussian) {
        const float inv_t2 = A.inv_t2;
        for (int64_t r = r0; r < m; ++r) {
            const float w = 1.f - dd[r] * dd[r] * inv_t2;  // weight_of's quadratic kernel
            cc[k] = int32_t(r);
            vv[k] = double(w);
            k += (dd[r] <= lim) & (w >= thr) & (idx[r] != i);
        }
        return k;
    }
    for (int64_t r = r0; r < m; ++r) {
        if (dd[r] > lim || idx[r] == i) continue;
        const float w = weight_of(dd[r], A);
        if (w >= thr) cc[k] = int32_t(r), vv[k] = double(w), ++k;
    }
    return k;
}

#if defined(__GNUC__) && defined(__x86_64__)
// anchor_sum's quadratic kernel in one pass on AVX-512: the distances (anchor_distances' operations, into
// dd) and the 16 lane sums and counts together, lane l taking the anchors r0 + l, r0 + 16 + l, ..., then the
// lanes added in order: the same bits as the portable loops.
__attribute__((target("avx512f"))) float quadratic_sum_avx512(const double *src, const double *tgt, int64_t i,
                                                             const AnchorSet &A, float *dd, int64_t r0,
                                                             int64_t r1, int64_t &count) {
    const LaneRow row(src, tgt, i, A);
    const __m512 one = _mm512_set1_ps(1.f), inv_t2 = _mm512_set1_ps(A.inv_t2), thr = _mm512_set1_ps(A.threshold);
    const __m512i inc = _mm512_set1_epi32(1);
    __m512 sum = _mm512_setzero_ps();
    __m512i cnt = _mm512_setzero_si512();
    for (int64_t r = r0; r < r1; r += 16) {
        const __mmask16 lanes = r1 - r >= 16 ? __mmask16(0xffff) : __mmask16((1u << (r1 - r)) - 1u);
        const __m512 d = row.distances(A, r, lanes);
        _mm512_mask_storeu_ps(dd + r, lanes, d);
        const __m512 w = _mm512_sub_ps(one, _mm512_mul_ps(_mm512_mul_ps(d, d), inv_t2));
        const __mmask16 keep = _mm512_mask_cmp_ps_mask(lanes, w, thr, _CMP_GE_OQ);
        sum = _mm512_mask_add_ps(sum, keep, sum, w);
        cnt = _mm512_mask_add_epi32(cnt, keep, cnt, inc);
    }
    alignas(64) float ls[16];
    alignas(64) int32_t lc[16];
    _mm512_store_ps(ls, sum);
    _mm512_store_si512(lc, cnt);
    float total = 0.f;
    int64_t c = 0;
    for (int l = 0; l < 16; ++l) total += ls[l], c += lc[l];
    count = c;
    return total;
}
#endif

// The weight sum and the count of row i's compatible anchors in [r0, r1) (a_r != i), without listing them:
// the pilot's degree and the budget's counts. Branch-free for the quadratic kernel (it vectorises); the
// Gaussian's exp only for the anchors within the edge distance.
#if defined(__GNUC__) && defined(__x86_64__) && !defined(__clang__)
__attribute__((target_clones("avx512f", "avx2", "default")))
#endif
double anchor_sum(const double *src, const double *tgt, int64_t i, const AnchorSet &A, std::vector<float> &dist,
                  int64_t r0, int64_t r1, int64_t &count) {
    float sum = 0.f;
    int64_t cnt = 0;
    bool fused = false;
#if defined(__GNUC__) && defined(__x86_64__)
    const bool wide = wide_rows();
    if (wide && !A.gaussian) {
        dist.resize(r1);
        sum = quadratic_sum_avx512(src, tgt, i, A, dist.data(), r0, r1, cnt);
        fused = true;
    }
#endif
    if (!fused) anchor_distances(src, tgt, i, A, dist, r0, r1);
    const float *dd = dist.data();
    if (fused) {
        // summed above
    } else if (!A.gaussian) {
        // 16 partial sums, one per lane, added in a fixed order at the end: the loop vectorises and the
        // sum is the same for every instruction set (a single running sum would not vectorise)
        const float thr = A.threshold, inv_t2 = A.inv_t2;
        constexpr int kLanes = 16;
        float lane_sum[kLanes] = {};
        int32_t lane_cnt[kLanes] = {};
        int64_t r = r0;
        for (; r + kLanes <= r1; r += kLanes)
            for (int l = 0; l < kLanes; ++l) {
                const float w = 1.f - dd[r + l] * dd[r + l] * inv_t2;
                const bool keep = w >= thr;
                lane_sum[l] += keep ? w : 0.f;
                lane_cnt[l] += keep;
            }
        for (int l = 0; r < r1; ++r, ++l) {
            const float w = 1.f - dd[r] * dd[r] * inv_t2;
            const bool keep = w >= thr;
            lane_sum[l] += keep ? w : 0.f;
            lane_cnt[l] += keep;
        }
        for (int l = 0; l < kLanes; ++l) sum += lane_sum[l], cnt += lane_cnt[l];
    } else {
        // the anchors within the edge distance first, in blocks by a branch-free loop (few pass on a sparse
        // graph), then the exp of those only, in increasing r as before: the same sum
        const float lim = A.max_d;
        constexpr int64_t kBlock = 256;
        int32_t near[kBlock];
        for (int64_t b = r0; b < r1; b += kBlock) {
            const int64_t e = std::min(r1, b + kBlock);
            int32_t k = 0;
            for (int64_t r = b; r < e; ++r) {
                near[k] = int32_t(r);
                k += dd[r] <= lim;
            }
            for (int32_t t = 0; t < k; ++t) {
                const float w = weight_of(dd[near[t]], A);
                if (w >= A.threshold) sum += w, ++cnt;
            }
        }
    }
    // the row's own draws (a_r == i) are no anchors of it: take them back out (found by a loop that
    // vectorises; most rows have none)
    int64_t own = 0;
    for (int64_t r = r0; r < r1; ++r) own += A.idx[r] == i;
    for (int64_t r = r0; own > 0 && r < r1; ++r)
        if (A.idx[r] == i) {
            --own;
            const float w = weight_of(dd[r], A);
            if (dd[r] <= A.max_d && w >= A.threshold) sum -= w, --cnt;
        }
    count = cnt;
    return (double)sum;
}

struct RowScratch {
    std::vector<float> dist;
    std::vector<int32_t> cols;
    std::vector<double> vals, u, us, v;
};

constexpr int64_t kPanel = 32;  // doubles of v held in registers while the rows of B stream past

// v = sum_x u[x] B[c[x]][:] over the k rows c of B (row stride `stride`, a multiple of kPanel, padded with
// 0), panel by panel so that each panel of v stays in registers (GCC's vector types: four vectors of eight
// doubles, lowered to whatever the clone has). Each element is the same products added in the same order
// (x increasing, no FMA) in every clone, so each gives the same bits.
typedef double Panel8 __attribute__((vector_size(64)));
#if defined(__GNUC__) && defined(__x86_64__) && !defined(__clang__)
__attribute__((target_clones("avx512f", "avx2", "default")))
#endif
void rows_times(const double *B, int64_t stride, const int32_t *c, const double *u, size_t k, double *v) {
    static_assert(kPanel == 32, "four vectors of eight doubles");
    for (int64_t p = 0; p < stride; p += kPanel) {
        Panel8 a0 = {}, a1 = {}, a2 = {}, a3 = {};
        for (size_t x = 0; x < k; ++x) {
            const double ux = u[x];
            const double *b = B + size_t(c[x]) * size_t(stride) + size_t(p);
            Panel8 b0, b1, b2, b3;
            std::memcpy(&b0, b, 64), std::memcpy(&b1, b + 8, 64);
            std::memcpy(&b2, b + 16, 64), std::memcpy(&b3, b + 24, 64);
            a0 += ux * b0, a1 += ux * b1, a2 += ux * b2, a3 += ux * b3;
        }
        std::memcpy(v + p, &a0, 64), std::memcpy(v + p + 8, &a1, 64);
        std::memcpy(v + p + 16, &a2, 64), std::memcpy(v + p + 24, &a3, 64);
    }
}


constexpr int64_t kRowChunk = 64;  // rows between two Ctrl-C polls
// a row takes the vectorised pair sums (rows_times) when its compatible anchors are at least 1 / kDenseShare
// of all anchors: the k m / 8 vector steps are then fewer cycles than the k^2 / 2 dependent scalar ones
constexpr int64_t kDenseShare = 16;

// body(i, scratch of the thread, tid) for every row, in chunks, Ctrl-C polled between chunks.
template <class F>
void for_each_row(int64_t n, int nt, std::vector<RowScratch> &scratch, F &&body) {
    InterruptibleRegion stop;
    DynamicRange range(0, n, kRowChunk);
    parallel_region(nt, [&](int tid) {
        RowScratch &S = scratch[tid];
        int64_t lo, hi;
        while (!stop.stopped(tid) && range.next(lo, hi))
            for (int64_t i = lo; i < hi; ++i) body(i, S, tid);
    });
    stop.throw_if_hit();
}

}  // namespace

std::vector<double> anchor_degree(const double *src, const double *tgt, int64_t n, const GraphParams &gp,
                                  const int64_t *anchors, int64_t m, int nthreads) {
    check_params(gp);
    const AnchorSet A = make_anchors(src, tgt, n, anchors, m, gp);
    std::vector<double> deg(n, 0.0);
    const int nt = resolve_threads(nthreads, n);
    std::vector<RowScratch> scratch(std::max(nt, 1));
    for_each_row(n, nt, scratch, [&](int64_t i, RowScratch &S, int) {
        int64_t cnt = 0;
        deg[i] = anchor_sum(src, tgt, i, A, S.dist, 0, A.m, cnt);
    });
    return deg;
}

int64_t anchors_within(const double *src, const double *tgt, int64_t n, const GraphParams &gp,
                       const int64_t *anchors, int64_t m, int64_t min_anchors, double pair_budget, int nthreads) {
    check_params(gp);
    if (m <= min_anchors || !(pair_budget > 0.0)) return m;
    // prefixes of 2^k draws from min_anchors up (a prefix of i.i.d. draws is itself i.i.d.), screened one
    // block at a time, so a dense graph stops after its first few blocks
    std::vector<int64_t> sizes;
    for (int64_t s = std::max<int64_t>(min_anchors, 2); s < m; s *= 2) sizes.push_back(s);
    sizes.push_back(m);
    const AnchorSet A = make_anchors(src, tgt, n, anchors, m, gp);
    const int nt = resolve_threads(nthreads, n);
    std::vector<RowScratch> scratch(std::max(nt, 1));
    std::vector<int64_t> count(n, 0);  // compatible anchors of each row in the prefix so far
    int64_t best = sizes[0], prev = 0;
    for (const int64_t size : sizes) {
        // Twice the work, sum x^2, in integers per thread: the same total for any split of the rows among
        // threads. The counts only grow, so once the rows screened so far are over the budget the prefix is:
        // the block stops there (a dense graph's last block is its largest). Each thread publishes its share
        // every 64 rows (a shared counter per row made two threads slower than one); what is published
        // never exceeds the true sum, so stopping on it is exact.
        struct alignas(64) Share {
            int64_t twice = 0, unpublished = 0, rows = 0;
        };
        std::vector<Share> share(std::max(nt, 1));
        std::atomic<int64_t> twice_published{0};
        std::atomic<bool> over{false};
        const double twice_budget = 2.0 * pair_budget;
        for_each_row(n, nt, scratch, [&](int64_t i, RowScratch &S, int tid) {
            if (over.load(std::memory_order_relaxed)) return;
            int64_t cnt = 0;
            anchor_sum(src, tgt, i, A, S.dist, prev, size, cnt);
            count[i] += cnt;
            Share &sh = share[tid];
            sh.twice += count[i] * count[i];
            sh.unpublished += count[i] * count[i];
            if (++sh.rows % 64 == 0) {
                const int64_t seen = twice_published.fetch_add(sh.unpublished, std::memory_order_relaxed);
                if ((double)(seen + sh.unpublished) > twice_budget) over.store(true, std::memory_order_relaxed);
                sh.unpublished = 0;
            }
        });
        int64_t twice = 0;
        for (const Share &sh : share) twice += sh.twice;
        if (over.load() || (double)twice > twice_budget) break;
        best = size;
        prev = size;
    }
    return best;
}

Signals anchor_signals(const double *src, const double *tgt, int64_t n, const GraphParams &gp,
                       const int64_t *anchors, const double *inv_q, int64_t m, int nthreads) {
    check_params(gp);
    if (m < 2) throw std::invalid_argument("the estimate needs at least 2 anchors");
    const AnchorSet A = make_anchors(src, tgt, n, anchors, m, gp);
    const int nt = resolve_threads(nthreads, n);
    // B_rt = W_{a_r a_t}, 0 on the diagonal and between two draws of the same node
    // (rows padded with 0 to a multiple of kPanel, for rows_times)
    const int64_t stride = (m + kPanel - 1) / kPanel * kPanel;
    std::vector<double> B((size_t)m * stride, 0.0);
    {
        RowScratch S;
        for (int64_t r = 0; r < m; ++r) {
            const size_t k = anchor_row(src, tgt, A.idx[r], A, S.dist, S.cols, S.vals);
            for (size_t x = 0; x < k; ++x)
                if (A.idx[S.cols[x]] != A.idx[r]) B[(size_t)r * stride + S.cols[x]] = S.vals[x];
        }
    }
    const double inv_m = 1.0 / (double)m, inv_mm = 1.0 / ((double)m * (double)(m - 1));

    // Row i's estimates; sa (the anchors' s^, or null in the first pass) adds the terms of t_i.
    struct RowEstimate {
        double s, d, e, g;
    };
    auto estimate_row = [&](int64_t i, RowScratch &S, const double *sa) -> RowEstimate {
        const size_t k = anchor_row(src, tgt, i, A, S.dist, S.cols, S.vals);
        const int32_t *c = S.cols.data();
        const double *w = S.vals.data();
        // u_x = W_{i a_x} / q(a_x), us_x = u_x s^(a_x)
        S.u.resize(k), S.us.resize(k);
        for (size_t x = 0; x < k; ++x) {
            S.u[x] = w[x] * inv_q[c[x]];
            S.us[x] = sa ? S.u[x] * sa[c[x]] : 0.0;
        }
        const double *u = S.u.data(), *us = S.us.data();
        double d = 0.0, T = 0.0, e = 0.0, g = 0.0;
        if (int64_t(k) * kDenseShare >= m) {
            // many compatible anchors (a dense graph): v = B u by whole rows of B, vectorised, then
            // T = u.v = sum over ordered pairs and g = us.v (B is symmetric with a zero diagonal); k m / 8
            // vector steps instead of k^2 / 2 dependent scalar ones
            S.v.resize(size_t(stride));
            double *v = S.v.data();
            rows_times(B.data(), stride, c, u, k, v);
            for (size_t x = 0; x < k; ++x) {
                d += u[x] * w[x];
                e += us[x] * w[x];
                T += u[x] * v[c[x]];
                g += us[x] * v[c[x]];
            }
            d *= inv_m;
            return {1.0 + 3.0 * d + T * inv_mm, d, e * inv_m, g * inv_mm};
        }
        for (size_t x = 0; x < k; ++x) {
            d += u[x] * w[x];
            e += us[x] * w[x];
            const double *Brow = B.data() + (size_t)c[x] * stride;
            double Tx = 0.0, Gx = 0.0;
            for (size_t y = x + 1; y < k; ++y) {
                const double b = Brow[c[y]];
                Tx += b * u[y];
                Gx += b * us[y];
            }
            T += 2.0 * u[x] * Tx;  // ordered pairs (r, t) and (t, r)
            // (r, t) weighs s^(a_r) and (t, r) s^(a_t): u_x u_y b (s_x + s_y) summed over x < y
            g += us[x] * Tx + u[x] * Gx;
        }
        d *= inv_m;
        return {1.0 + 3.0 * d + T * inv_mm, d, e * inv_m, g * inv_mm};
    };

    std::vector<RowScratch> scratch(std::max(nt, 1));
    // pass 1: the anchors' own s^ (they weigh the neighbours' degrees in t_i)
    std::vector<double> sa(m);
    for_each_row(m, nt, scratch,
                 [&](int64_t r, RowScratch &S, int) { sa[r] = estimate_row(A.idx[r], S, nullptr).s; });

    Signals out;
    out.degree.assign(n, 0.0), out.highpass.assign(n, 0.0), out.lowpass.assign(n, 0.0);
    for_each_row(n, nt, scratch, [&](int64_t i, RowScratch &S, int) {
        const RowEstimate r = estimate_row(i, S, sa.data());
        const double t = (1.0 + r.d) * r.s + 2.0 * r.e + r.g;
        out.degree[i] = r.s;
        out.highpass[i] = r.s * r.s - t;
        out.lowpass[i] = r.s + t / r.s;
    });
    out.n_edges = -1;  // not known: the estimate never builds the graph
    return out;
}

}  // namespace fastmac
