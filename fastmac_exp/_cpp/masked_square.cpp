// S_ij = V_ij * sum_k V_ik V_kj on the stored entries of a symmetric sparse matrix V: the second-order
// graph G = W * (W W) (spec 2.3), the sampler's degree signal (spec 7.2) and the clustering coefficients'
// triangle sums (V = G^(1/3), spec 2.4).
//
// Outdoor graphs have a dense core (the inliers, nearly all compatible with each other: on the real KITTI
// pairs ~1,250 of 5,000 nodes with half of all core pairs linked) and a sparse rest. A gather per (edge,
// common-neighbour candidate) costs ~m^3/2 random loads on a core of m nodes; the same sums as a dense
// matrix product run at the FMA units' speed. So:
//
// 1. The core C: the largest m such that the m-th highest degree is >= m / 4 (kept when m >= 128 and a
//    fifth of the core pairs are edges). K: every node with >= m / 4 neighbours in C.
// 2. P = D^T D over the core pairs, D = V[K, C] (rows k in K): sum_{k in K} V_ka V_kb, on the tiles above
//    the diagonal only, as a BLIS-style product: D packed twice (micro-panels of mr and of nr columns),
//    blocks of kc rows and nc columns kept in L2, and an mr x nr register-blocked micro-kernel (AVX-512 or
//    AVX2 FMA, else portable code; dense_tiles.hpp). On one Zen 4 core it runs at ~100 GFLOP/s in float32,
//    OpenBLAS's sgemm speed; the unpacked kernel it replaces read D with a stride of a whole row and ran at
//    a third of that.
// 3. The other k (few neighbours in C) add V_ka V_kb to P for each pair of their core neighbours.
//    Now P_ab = sum over all k of V_ka V_kb, and S_ab = V_ab P_ab on the core edges.
// 4. Every other edge by sparse gathers: the endpoint with the longer row is scattered densely and the
//    sum runs over the shorter row (cost: the smaller degree per edge). The sampler's graph, once it
//    outgrows the cache, lists the triangles instead (forward_products below).
//
// The sums are the same as the gather kernel's up to the order of the additions (and FMA rounding): a
// relative difference of ~1e-15 (float32 cores and the listing: ~1e-7; see Precision in mac_core.hpp). FASTMAC_DENSE_CORE=off forces the
// all-sparse path, FASTMAC_TRIANGLES=on | off the listing, FASTMAC_GEMM=amx | avx512 |
// avx2 | generic picks the kernel (tests; unknown or unsupported names fall back to what the CPU has; avx512
// keeps MAC's bfloat16 cores off AMX).
#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <new>
#include <numeric>
#include <string>
#include <utility>

#if defined(__GNUC__) && defined(__x86_64__)
#include <immintrin.h>
#endif

#include "dense_tiles.hpp"
#include "interrupt.hpp"
#include "mac_core.hpp"
#include "parallel.hpp"

namespace fastmac {

namespace {

constexpr int64_t kL2Bytes = 384 * 1024;  // the packed B block kept in L2 (kc x nc)
constexpr int64_t kSuper = 64;  // core rows one thread takes at a time in the pass over the nodes outside K

// An array on malloc's memory, not value-initialised (std::vector would write every byte once more):
// zeroed by the threads or left uninitialised (with the module's malloc setting, memory.cpp, a large one
// reuses the pages of the previous call). (Transparent huge pages for the triangle listing's arrays, tried:
// no faster on the 50,000-correspondence graphs.)
template <class T>
class Array {
  public:
    Array() = default;
    static Array uninitialised(size_t n) {
        return Array(static_cast<T *>(std::malloc(std::max<size_t>(n, 1) * sizeof(T))));
    }
    // Zeroed by the threads, for the dense cores' operands and products: calloc's fresh pages are the
    // shared zero page until written, and the products read before they write, so each page took a
    // copy-on-write fault with a TLB shootdown (~6 % of MAC on the 5,000-node near-clique), one thread.
    static Array zeroed_parallel(size_t n, int nthreads) {
        Array a = uninitialised(n);
        constexpr int64_t kSlice = int64_t(1) << 16;  // elements a task
        const int64_t slices = ((int64_t)n + kSlice - 1) / kSlice;
        parallel_for(0, slices, slices > 16 ? nthreads : 1, 4, [&](int64_t k, int) {
            const int64_t lo = k * kSlice, hi = std::min<int64_t>((int64_t)n, lo + kSlice);
            std::memset(static_cast<void *>(a.data() + lo), 0, (size_t)(hi - lo) * sizeof(T));
        });
        return a;
    }
    T *data() { return p_.get(); }
    const T *data() const { return p_.get(); }
    T &operator[](size_t i) { return p_[i]; }
    const T &operator[](size_t i) const { return p_[i]; }

  private:
    explicit Array(T *p) : p_(p) {
        if (!p_) throw std::bad_alloc();
    }
    struct Free {
        void operator()(T *p) const { std::free(p); }
    };
    std::unique_ptr<T[], Free> p_;
};

constexpr int64_t kGenericMR = 4, kGenericNR = 8;

template <class T>
void tile_generic(const T *a, const T *b, int64_t kc, T *c, int64_t ldc) {
    T acc[kGenericMR][kGenericNR] = {};
    for (int64_t r = 0; r < kc; ++r) {
        const T *ar = a + r * kGenericMR, *br = b + r * kGenericNR;
        for (int64_t t = 0; t < kGenericMR; ++t)
            for (int64_t u = 0; u < kGenericNR; ++u) acc[t][u] += ar[t] * br[u];
    }
    for (int64_t t = 0; t < kGenericMR; ++t)
        for (int64_t u = 0; u < kGenericNR; ++u) c[t * ldc + u] += acc[t][u];
}

tiles::Kernels pick_kernels() {
    const char *env = std::getenv("FASTMAC_GEMM");
    const std::string want = env ? env : "";
    if (want != "generic") {
#ifdef FASTMAC_X86_TILES
        if (want != "avx2" && __builtin_cpu_supports("avx512f")) return tiles::avx512_kernels();
        if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma")) return tiles::avx2_kernels();
#endif
    }
    return {{tile_generic<double>, kGenericMR, kGenericNR}, {tile_generic<float>, kGenericMR, kGenericNR}};
}

template <class T>
tiles::Tile<T> pick_tile() {
    const tiles::Kernels k = pick_kernels();
    if constexpr (sizeof(T) == sizeof(double)) return k.d;
    else return k.f;
}

#if defined(__GNUC__) && defined(__x86_64__)
// The 16 x 16 block of 32-bit values at src (rows lds apart) transposed into dst (rows ldd apart): four rounds
// of shuffles in registers, which move bits and never round. symmetrize's scalar copy read a column of 16
// rows whose stride is often a multiple of 4 KB (ld = 1,024 for a 1,000-node core), all in one L1 set: ~8 %
// of MAC on FastMAC@20's KITTI keeps; the AMX packing's A operand is B's transposed.
__attribute__((target("avx512f"))) inline __m512 unpack_lo64(__m512 a, __m512 b) {
    return _mm512_castpd_ps(_mm512_unpacklo_pd(_mm512_castps_pd(a), _mm512_castps_pd(b)));
}
__attribute__((target("avx512f"))) inline __m512 unpack_hi64(__m512 a, __m512 b) {
    return _mm512_castpd_ps(_mm512_unpackhi_pd(_mm512_castps_pd(a), _mm512_castps_pd(b)));
}

__attribute__((target("avx512f"))) void transpose16_avx512(const float *src, int64_t lds, float *dst, int64_t ldd) {
    __m512 r[16], t[16];
    for (int k = 0; k < 16; ++k) r[k] = _mm512_loadu_ps(src + k * lds);
    for (int k = 0; k < 8; ++k) {
        t[2 * k] = _mm512_unpacklo_ps(r[2 * k], r[2 * k + 1]);
        t[2 * k + 1] = _mm512_unpackhi_ps(r[2 * k], r[2 * k + 1]);
    }
    for (int k = 0; k < 4; ++k) {
        r[4 * k] = unpack_lo64(t[4 * k], t[4 * k + 2]);
        r[4 * k + 1] = unpack_hi64(t[4 * k], t[4 * k + 2]);
        r[4 * k + 2] = unpack_lo64(t[4 * k + 1], t[4 * k + 3]);
        r[4 * k + 3] = unpack_hi64(t[4 * k + 1], t[4 * k + 3]);
    }
    for (int h = 0; h < 2; ++h)
        for (int q = 0; q < 4; ++q) {
            t[8 * h + q] = _mm512_shuffle_f32x4(r[8 * h + q], r[8 * h + 4 + q], 0x88);
            t[8 * h + 4 + q] = _mm512_shuffle_f32x4(r[8 * h + q], r[8 * h + 4 + q], 0xdd);
        }
    for (int q = 0; q < 8; ++q) {
        _mm512_storeu_ps(dst + q * ldd, _mm512_shuffle_f32x4(t[q], t[8 + q], 0x88));
        _mm512_storeu_ps(dst + (8 + q) * ldd, _mm512_shuffle_f32x4(t[q], t[8 + q], 0xdd));
    }
}
#endif

// The bfloat16 tile: AMX where the build, the CPU and Linux allow it, else AVX512_BF16 where the build and
// the CPU have it (fn nullptr otherwise, and with FASTMAC_GEMM set to a kernel other than amx or avx512;
// FASTMAC_GEMM=avx512 takes the AVX512_BF16 tile on a CPU with AMX).
tiles::TileBf16 pick_bf16_tile() {
#ifdef FASTMAC_BF16_TILES
    const char *env = std::getenv("FASTMAC_GEMM");
    const std::string want = env ? env : "";
#ifdef FASTMAC_AMX_TILES
    if (want.empty() || want == "amx") {
        const tiles::TileBf16 amx = tiles::amx_tile();
        if (amx.fn) return amx;
    }
#endif
    if ((want.empty() || want == "avx512" || want == "amx") && __builtin_cpu_supports("avx512f") &&
        __builtin_cpu_supports("avx512bf16"))
        return tiles::bf16_tile();
#endif
    return {};
}


struct Core {
    int64_t m = 0;
    std::vector<int32_t> pos;    // node -> index in C, or -1
    std::vector<int32_t> nodes;  // C by index: core index -> node
    std::vector<int32_t> rows;   // K, the rows of D
    int64_t inside = 0;          // entries of V with both ends in C (each core edge twice)
};

// The nodes by decreasing degree (ties: by index); the core, when there is one, is a prefix of it.
// A counting sort (degrees are below n): the stable sort's order in O(n), not O(n log n) (~2 % of the
// sampler graph's time on a fragment's 3,955 nodes, on one thread).
std::vector<int32_t> degree_order(const Csr &V) {
    const int64_t n = V.n;
    auto deg = [&](int64_t i) { return V.ptr[i + 1] - V.ptr[i]; };
    int64_t dmax = 0;
    for (int64_t i = 0; i < n; ++i) dmax = std::max(dmax, deg(i));
    std::vector<int64_t> start(size_t(dmax) + 2, 0);  // by decreasing degree: bucket dmax - d
    for (int64_t i = 0; i < n; ++i) ++start[size_t(dmax - deg(i)) + 1];
    for (size_t b = 1; b < start.size(); ++b) start[b] += start[b - 1];
    std::vector<int32_t> order(static_cast<size_t>(n));
    for (int64_t i = 0; i < n; ++i) order[size_t(start[size_t(dmax - deg(i))]++)] = (int32_t)i;
    return order;
}

// The cost of one multiply-add of the core's product, in sparse steps (a gather of the all-sparse path, or
// a pair that add_outside_rows adds): measured with perf on Zen 4 (MAC on the 1,000 FastMAC@20 keeps of
// KITTI 95->94: bfloat16 tiles ~1/80 of a gather); rounded towards the sparse side.
// float64 arithmetic (MAC's cores under kSingleCore nodes) costs 1/16.
constexpr double kDoubleStep = 1.0 / 16;
double dense_step_cost(int64_t m, Precision precision) {
    if (precision == Precision::Double) return kDoubleStep;
    if (precision == Precision::Mac) {
        if (m < kSingleCore || env_is("FASTMAC_MAC_PRECISION", "double")) return kDoubleStep;
        if (m >= kHalfCore && !env_is("FASTMAC_MAC_PRECISION", "single") && pick_bf16_tile().fn) return 1.0 / 64;
    }
    return 1.0 / 32;
}

// The rows of D: the nodes whose core neighbours cost more as pairs added one by one (add_outside_rows,
// ~2 sparse steps a pair) than as a row of the product (m^2 / 2 multiply-adds). MAC's float64 graphs
// and the float64 cores (< kSingleCore nodes; the C++/Python parity tests among them) keep the rule they were
// checked with, >= m / 4.
bool in_rows(int64_t deg_core, int64_t m, double step) {
    if (step >= kDoubleStep) return 4 * deg_core >= m;
    return 2.0 * (double)deg_core * (double)deg_core >= step * (double)m * (double)m / 2.0;
}

// The whole graph as the core (m = n): where a small graph is dense all over (FastMAC's 1,000 keeps of
// a dense outdoor pair: 46 % of all pairs linked), the product over every node costs less than the
// core's product plus the gathers of the edges outside it, the pairs of the nodes outside K and the
// mirror; and every entry of S then reads P. Compared by the same cost model, from cores whose product
// is not in float64 (a float64 core keeps the sums it was checked with).
constexpr int64_t kWholeMax = 4096;  // P of n x n floats: 64 MB

struct CoreCost {
    double dense = 0.0, pairs = 0.0;
    double total() const { return dense + pairs; }
};

CoreCost core_cost(const std::vector<int64_t> &deg_core, int64_t m, double step) {
    CoreCost c;
    for (int64_t d : deg_core) {
        if (in_rows(d, m, step)) c.dense += step * (double)m * (double)m / 2.0;
        else c.pairs += (double)d * (double)d;
    }
    return c;
}

// The core and K (m = 0: no dense core worth a matrix product). order: set to degree_order(V) when the
// search gets that far (else left empty), its first m entries then sorted by index.
Core find_core(const Csr &V, std::vector<int32_t> &order, Precision precision) {
    Core core;
    const int64_t n = V.n;
    if (n < 256 || env_is("FASTMAC_DENSE_CORE", "off")) return core;
    order = degree_order(V);
    auto deg = [&](int32_t i) { return V.ptr[i + 1] - V.ptr[i]; };
    int64_t m = 0;
    for (int64_t t = 1; t <= n; ++t)
        if (4 * deg(order[t - 1]) >= t) m = t;
    if (m < 128) return core;
    core.pos.assign(n, -1);
    // Core indices in node order, so that a row's core neighbours read one row of P in order.
    std::sort(order.begin(), order.begin() + m);
    for (int64_t a = 0; a < m; ++a) core.pos[order[a]] = (int32_t)a;
    int64_t inside = 0;
    std::vector<int64_t> deg_core(n, 0);
    for (int64_t k = 0; k < n; ++k)
        for (int64_t p = V.ptr[k]; p < V.ptr[k + 1]; ++p) deg_core[k] += core.pos[V.col[p]] >= 0;
    for (int64_t a = 0; a < m; ++a) inside += deg_core[order[a]];
    if (5 * inside < m * m) {  // inside counts each core edge twice: fewer than a fifth of the pairs linked
        core.pos.clear();
        return core;
    }
    const double step = dense_step_cost(m, precision);
    if (m < n && n <= kWholeMax && step < kDoubleStep && !env_is("FASTMAC_DENSE_CORE", "core")) {
        // The edges outside the core: a gather over the shorter row each, then the mirror (~1 step an
        // entry). The core holds the highest degrees, so an edge's shorter row is (about) that of its end
        // outside the core: ~ sum over those nodes of deg^2.
        double rest = 0.0;
        for (int64_t t = m; t < n; ++t) rest += (double)deg(order[t]) * (double)(deg(order[t]) + 1);
        std::vector<int64_t> deg_all(n);
        for (int64_t k = 0; k < n; ++k) deg_all[k] = deg(k);
        const double step_n = dense_step_cost(n, precision);
        if (core_cost(deg_all, n, step_n).total() < core_cost(deg_core, m, step).total() + rest) {
            std::sort(order.begin(), order.end());
            for (int64_t a = 0; a < n; ++a) core.pos[order[a]] = (int32_t)a;
            m = n;
            deg_core.swap(deg_all);
            inside = V.nnz();
        }
    }
    core.m = m;
    core.nodes.assign(order.begin(), order.begin() + m);
    core.inside = inside;
    const double step_m = dense_step_cost(m, precision);
    for (int64_t k = 0; k < n; ++k)
        if (in_rows(deg_core[k], m, step_m)) core.rows.push_back((int32_t)k);
    return core;
}

// Rows r0..r1 of D = V[K, C] scattered into `dense` (rows of ld entries, zero where V has none), the first
// step of both packings.
template <class T>
void scatter_core_rows(const Csr &V, const std::vector<double> &vals, const Core &core, int64_t r0, int64_t r1,
                       int64_t ld, T *dense) {
    for (int64_t r = r0; r < r1; ++r) {
        const int32_t k = core.rows[r];
        T *dr = dense + (r - r0) * ld;
        for (int64_t p = V.ptr[k]; p < V.ptr[k + 1]; ++p) {
            const int64_t c = core.pos[V.col[p]];
            if (c >= 0) dr[c] = (T)vals[p];
        }
    }
}

// Blocked as in BLIS: a block of kc rows of D and nc columns, whose packed B part (kc x nc) stays in
// L2 while a thread runs over its row panels of P; for each row panel the A micro-panel (kc x mr) stays
// in L1 across the block's column panels. Threads take groups of consecutive row panels of about equal
// work, in one parallel region, and run each group in the blocked order; a group owns its rows of P,
// and every tile sums its blocks of rows in the same order, so P is the same for any thread count.
// TA: a packed element (a value, or a pair of bfloat16 rows); nk: the packed rows (elements per column).
template <class TA, class TC, class Fn>
void blocked_product(const TA *A, const TA *B, int64_t nk, int64_t m, int64_t mr, int64_t nr, int64_t ld, Fn fn,
                     TC *P, int nthreads, InterruptibleRegion &ctrl_c) {
    const int64_t n_ip = (m + mr - 1) / mr, n_jp = ld / nr;
    const int64_t kc_max = std::min<int64_t>(nk, 256);
    const int64_t nc_panels = std::max<int64_t>(1, kL2Bytes / (kc_max * nr * (int64_t)sizeof(TA)));
    auto panel_work = [&](int64_t ip) { return n_jp - (ip * mr) / nr; };  // column panels right of the diagonal
    int64_t total_work = 0;
    for (int64_t ip = 0; ip < n_ip; ++ip) total_work += panel_work(ip);
    const int64_t n_groups = nthreads > 1 ? std::min<int64_t>(n_ip, 4 * nthreads) : 1;
    std::vector<int64_t> group_start{0};
    for (int64_t ip = 0, acc = 0; ip < n_ip; ++ip) {
        acc += panel_work(ip);
        if (acc * n_groups >= total_work * (int64_t)group_start.size() && ip + 1 < n_ip &&
            (int64_t)group_start.size() < n_groups)
            group_start.push_back(ip + 1);
    }
    group_start.push_back(n_ip);
    DynamicRange groups(0, (int64_t)group_start.size() - 1, 1);
    parallel_region(nthreads, [&](int tid) {
        int64_t g, g_hi;
        while (!ctrl_c.stopped(tid) && groups.next(g, g_hi)) {
            const int64_t ip0 = group_start[g], ip1 = group_start[g + 1];
            for (int64_t jc = (ip0 * mr) / nr; jc < n_jp; jc += nc_panels) {
                const int64_t jc_end = std::min(n_jp, jc + nc_panels);
                for (int64_t k0 = 0; k0 < nk; k0 += kc_max) {
                    const int64_t kc = std::min(kc_max, nk - k0);
                    for (int64_t ip = ip0; ip < ip1; ++ip) {
                        const int64_t i0 = ip * mr;
                        const TA *ap = A + ((size_t)ip * nk + k0) * mr;
                        for (int64_t jp = std::max(jc, i0 / nr); jp < jc_end; ++jp)
                            fn(ap, B + ((size_t)jp * nk + k0) * nr, kc, P + (size_t)i0 * ld + jp * nr, ld);
                    }
                }
            }
        }
    });
}

// P_ab += V_ka V_kb for the nodes k outside K: each pair of their core neighbours, a < b (a thread owns a
// range of rows a).
template <class T>
void add_outside_rows(const Csr &V, const std::vector<double> &vals, const Core &core, T *P, int64_t ld,
                      int nthreads, InterruptibleRegion &ctrl_c) {
    const int64_t m = core.m;
    std::vector<uint8_t> in_rows(V.n, 0);
    for (int32_t k : core.rows) in_rows[k] = 1;
    // Each such k's core neighbours (core positions ascending, with V_ka), k ascending, for those with two
    // or more: counted, then gathered and sorted, on the threads (a serial gather was ~1 % of MAC's time).
    const auto listed = [&](int64_t p) { return core.pos[V.col[p]] >= 0 && vals[p] != 0.0; };
    std::vector<int64_t> len(V.n, 0);
    parallel_for(0, V.n, nthreads, 256, [&](int64_t k, int) {
        if (in_rows[k]) return;
        int64_t c = 0;
        for (int64_t p = V.ptr[k]; p < V.ptr[k + 1]; ++p) c += listed(p);
        len[k] = c >= 2 ? c : 0;
    });
    std::vector<int64_t> nb_ptr{0}, ks;
    for (int64_t k = 0; k < V.n; ++k)
        if (len[k]) ks.push_back(k), nb_ptr.push_back(nb_ptr.back() + len[k]);
    const int64_t n_rest = (int64_t)ks.size();
    std::vector<int32_t> nb_a((size_t)nb_ptr.back());
    std::vector<T> nb_v((size_t)nb_ptr.back());
    parallel_for(0, n_rest, nthreads, 64, [&](int64_t t, int) {
        std::vector<std::pair<int32_t, T>> tmp;
        tmp.reserve((size_t)len[ks[t]]);
        for (int64_t p = V.ptr[ks[t]]; p < V.ptr[ks[t] + 1]; ++p)
            if (listed(p)) tmp.emplace_back(core.pos[V.col[p]], (T)vals[p]);
        std::sort(tmp.begin(), tmp.end());
        for (size_t q = 0; q < tmp.size(); ++q)
            nb_a[nb_ptr[t] + q] = tmp[q].first, nb_v[nb_ptr[t] + q] = tmp[q].second;
    });
    if (n_rest > 0) {
        DynamicRange blocks(0, (m + kSuper - 1) / kSuper, 1);
        parallel_region(nthreads, [&](int tid) {
            int64_t lo, hi;
            while (!ctrl_c.stopped(tid) && blocks.next(lo, hi)) {
                const int32_t a0 = (int32_t)(lo * kSuper), a1 = (int32_t)std::min<int64_t>(m, a0 + kSuper);
                for (int64_t t = 0; t < n_rest; ++t) {
                    const int32_t *na = nb_a.data() + nb_ptr[t], *ne = nb_a.data() + nb_ptr[t + 1];
                    const T *nv = nb_v.data() + nb_ptr[t];
                    const int32_t *q = std::lower_bound(na, ne, a0);
                    for (; q < ne && *q < a1; ++q) {
                        const T x = nv[q - na];
                        T *pr = P + (int64_t)*q * ld;
                        for (const int32_t *u = q + 1; u < ne; ++u) pr[*u] += x * nv[u - na];
                    }
                }
            }
        });
    }
}

// P (m x ld, the tiles that hold entries a < b) = sum over all k of V_ka V_kb for core nodes a, b, in T
// arithmetic. ld: the row stride of P, a multiple of the tile's columns (tile.nr).
template <class T>
Array<T> core_products(const Csr &V, const std::vector<double> &vals, const Core &core,
                             const tiles::Tile<T> &tile, int64_t ld, int nthreads, InterruptibleRegion &ctrl_c) {
    const int64_t m = core.m, nk = (int64_t)core.rows.size();
    const int64_t mr = tile.mr, nr = tile.nr;
    const int64_t n_ip = (m + mr - 1) / mr, n_jp = ld / nr;  // row panels (mr wide), column panels (nr)
    // D = V[K, C] packed twice: A[ip][r][t] = D[r][ip * mr + t] (the broadcast operand) and
    // B[jp][r][u] = D[r][jp * nr + u] (the vector operand); calloc's zeros pad the last panels.
    Array<T> A = Array<T>::zeroed_parallel((size_t)n_ip * nk * mr, nthreads),
             B = Array<T>::zeroed_parallel((size_t)n_jp * nk * nr, nthreads),
             P = Array<T>::zeroed_parallel((size_t)n_ip * mr * ld, nthreads);
    // A chunk of rows at a time: scattered into a dense block (rows of ld entries, cache-local writes),
    // then copied panel by panel (contiguous runs of mr or nr entries).
    constexpr int64_t kChunk = 32;
    DynamicRange chunks(0, (nk + kChunk - 1) / kChunk, 1);
    parallel_region(nthreads, [&](int) {
        std::vector<T> dense((size_t)kChunk * ld, T(0));
        int64_t lo, hi;
        while (chunks.next(lo, hi)) {
            const int64_t r0 = lo * kChunk, r1 = std::min(nk, r0 + kChunk);
            scatter_core_rows(V, vals, core, r0, r1, ld, dense.data());
            for (int64_t ip = 0; ip < n_ip; ++ip) {
                const int64_t c0 = ip * mr, w = std::min(mr, ld - c0);
                T *dst = A.data() + ((size_t)ip * nk + r0) * mr;
                for (int64_t r = r0; r < r1; ++r, dst += mr)
                    std::memcpy(dst, dense.data() + (r - r0) * ld + c0, (size_t)w * sizeof(T));
            }
            for (int64_t jp = 0; jp < n_jp; ++jp) {
                T *dst = B.data() + ((size_t)jp * nk + r0) * nr;
                for (int64_t r = r0; r < r1; ++r, dst += nr)
                    std::memcpy(dst, dense.data() + (r - r0) * ld + jp * nr, (size_t)nr * sizeof(T));
            }
            std::fill(dense.begin(), dense.end(), T(0));
        }
    });
    blocked_product(A.data(), B.data(), nk, m, mr, nr, ld, tile.fn, P.data(), nthreads, ctrl_c);
    add_outside_rows(V, vals, core, P.data(), ld, nthreads, ctrl_c);
    return P;
}

// Round to bfloat16 stochastically: add 16 random bits below the kept ones and truncate, so that the
// rounding is unbiased (E[bf16(x)] = x) and the errors of a sum of many products average out. Rounding to
// nearest is biased on a core's weights, which crowd just below 1 (a relative error of ~4e-4 in every
// core entry of G, the same sign throughout; ~3e-5 with this). The bits are the top 16 of a Weyl sequence
// over the entry's position (key = row k * ld + core column c: h = (key + 1) * 0x9E3779B97F4A7C15), so the
// result depends neither on the thread count nor on the run. A row at a time, h stepping by the constant:
// the loop vectorises. Finite, non-negative x (so u + 2^16 < 2^32: no carry into the sign); 0 stays 0.
constexpr uint64_t kWeyl = 0x9E3779B97F4A7C15ull;

#if defined(__GNUC__) && defined(__x86_64__) && !defined(__clang__)
__attribute__((target_clones("avx512f", "avx2", "default")))
#endif
void round_row_bf16(const float *x, int64_t len, uint64_t key0, uint16_t *out) {
    uint64_t h = (key0 + 1) * kWeyl;
    for (int64_t c = 0; c < len; ++c, h += kWeyl) {
        uint32_t u;
        std::memcpy(&u, x + c, sizeof(u));
        out[c] = (uint16_t)((u + (uint32_t)(h >> 48)) >> 16);
    }
}

// One micro-panel row of a bfloat16 packing: entries c0 .. c0 + w of two rounded rows of D interleaved
// (the even row in the low half of each uint32_t), zeros up to `width`, `step` apart in dst (1: a row of the
// panel; 16: a pair of AMX's A operand, whose columns hold 16 pairs each).
inline void pack_pair(const uint16_t *even, const uint16_t *odd, int64_t c0, int64_t w, int64_t width,
                      uint32_t *dst, int64_t step = 1) {
    for (int64_t t = 0; t < w; ++t) dst[t * step] = (uint32_t)even[c0 + t] | ((uint32_t)odd[c0 + t] << 16);
    for (int64_t t = w; t < width; ++t) dst[t * step] = 0;
}

// core_products in bfloat16 with float32 sums: D rounded to bfloat16 (stochastically), packed in pairs of rows (rows 2r
// and 2r + 1 of D in one uint32_t, a zero row padding an odd count), the products summed in float32 by
// the bfloat16 tile; the nodes outside K add in float32 as in core_products<float>.
Array<float> core_products_bf16(const Csr &V, const std::vector<double> &vals, const Core &core,
                                const tiles::TileBf16 &tile, int64_t ld, int nthreads, InterruptibleRegion &ctrl_c) {
    const int64_t m = core.m, nk = (int64_t)core.rows.size(), nk2 = (nk + 1) / 2;
    const int64_t mr = tile.mr, nr = tile.nr, kg = tile.kgroup;
    const int64_t nkp = (nk2 + kg - 1) / kg * kg;  // packed pairs: zero pairs pad the last group of the A operand
    const int64_t n_ip = (m + mr - 1) / mr, n_jp = ld / nr;
    // every entry of A and B is written below (padding included)
    Array<uint32_t> A = Array<uint32_t>::uninitialised((size_t)n_ip * nkp * mr),
                    B = Array<uint32_t>::uninitialised((size_t)n_jp * nkp * nr);
    Array<float> P = Array<float>::zeroed_parallel((size_t)n_ip * mr * ld, nthreads);
    // A's pair r2 of row panel ip (its columns kg apart)
    auto a_pair = [&](int64_t ip, int64_t r2) {
        return A.data() + (size_t)ip * nkp * mr + (size_t)(r2 / kg) * kg * mr + (size_t)(r2 % kg);
    };
    constexpr int64_t kChunk = 32;  // even: a chunk holds whole pairs of rows (and one group of 16 pairs)
    static_assert(kChunk == 32);
    // AMX's A (groups of 16 pairs) from B's panels, transposed, where the panels are the same columns
    bool a_from_b = false;
#if defined(__GNUC__) && defined(__x86_64__)
    a_from_b = kg == 16 && mr == 32 && nr == 32 && __builtin_cpu_supports("avx512f");
#endif
    DynamicRange chunks(0, (nk + kChunk - 1) / kChunk, 1);
    parallel_region(nthreads, [&](int) {
        std::vector<float> dense((size_t)kChunk * ld, 0.0f);
        std::vector<uint16_t> even(ld), odd(ld);
        int64_t lo, hi;
        while (chunks.next(lo, hi)) {
            const int64_t r0 = lo * kChunk, r1 = std::min(nk, r0 + kChunk);
            scatter_core_rows(V, vals, core, r0, r1, ld, dense.data());
            for (int64_t r = r0; r < r1; r += 2) {
                // one rounding of each entry of D, used in both packings
                round_row_bf16(dense.data() + (r - r0) * ld, ld, (uint64_t)r * ld, even.data());
                if (r + 1 < r1) round_row_bf16(dense.data() + (r + 1 - r0) * ld, ld, (uint64_t)(r + 1) * ld, odd.data());
                else std::fill(odd.begin(), odd.end(), uint16_t(0));
                const int64_t r2 = r / 2;
                if (!a_from_b)
                    for (int64_t ip = 0; ip < n_ip; ++ip)
                        pack_pair(even.data(), odd.data(), ip * mr, std::min(mr, ld - ip * mr), mr, a_pair(ip, r2), kg);
                for (int64_t jp = 0; jp < n_jp; ++jp)
                    pack_pair(even.data(), odd.data(), jp * nr, nr, nr, B.data() + ((size_t)jp * nkp + r2) * nr);
            }
            if (r1 == nk)  // the zero pairs after the last (one chunk holds them: nkp - nk2 < 16)
                for (int64_t r2 = nk2; r2 < nkp; ++r2) {
                    if (!a_from_b)
                        for (int64_t ip = 0; ip < n_ip; ++ip)
                            for (int64_t t = 0; t < mr; ++t) a_pair(ip, r2)[t * kg] = 0;
                    for (int64_t jp = 0; jp < n_jp; ++jp)
                        std::fill_n(B.data() + ((size_t)jp * nkp + r2) * nr, nr, uint32_t(0));
                }
#if defined(__GNUC__) && defined(__x86_64__)
            if (a_from_b)  // the chunk is one group of 16 pairs: A's 32 x 16 block is B's 16 x 32 one transposed
                for (int64_t ip = 0; ip < n_ip; ++ip) {
                    const uint32_t *bg = B.data() + ((size_t)ip * nkp + r0 / 2) * nr;
                    uint32_t *ag = a_pair(ip, r0 / 2);
                    for (int64_t h = 0; h < 2; ++h)
                        transpose16_avx512(reinterpret_cast<const float *>(bg + 16 * h), nr,
                                           reinterpret_cast<float *>(ag + 16 * kg * h), kg);
                }
#endif
            std::fill(dense.begin(), dense.end(), 0.0f);
        }
    });
    blocked_product(A.data(), B.data(), nkp, m, mr, nr, ld, tile.fn, P.data(), nthreads, ctrl_c);
    add_outside_rows(V, vals, core, P.data(), ld, nthreads, ctrl_c);
    return P;
}

// The listing's probe: the offsets i in cols[0, len) whose bit is set in bits, written to hits (room for
// len); returns their count. Branch-free: ~1.4 % of the probes hit on the 50,000-correspondence graphs.
inline int64_t probe(const int32_t *cols, int64_t len, const uint64_t *bits, int32_t *hits) {
    int64_t nh = 0;
    for (int64_t i = 0; i < len; ++i) {
        const int32_t k = cols[i];
        hits[nh] = (int32_t)i;
        nh += (bits[k >> 6] >> (k & 63)) & 1;
    }
    return nh;
}

// The sampler's graph on large graphs (the first-order graph no longer in the last-level cache): the
// products P_ab = sum_k V_ak V_bk of every edge with an endpoint outside the core by listing each
// triangle once (forward listing; Schank and Wagner, "Finding, counting and listing all triangles in large
// graphs", WEA 2005; Latapy, TCS 2008). Nodes are ranked by degree, the core on top; a triangle is found
// from its lowest node u, which is outside the core unless all three are in it (the dense product's): the
// out-neighbours N+(u) (higher rank) are marked in a bitset (L1), and each N+(v), v in N+(u) and outside
// the core, is probed against it, reading its columns only (4 bytes a probe); the weights of the ~1.4 % of
// probes that hit are prefetched and read once all of u's rows are probed. On 50,000 outdoor
// correspondences at 2 % inliers: 1.03 G probes and 14 M hits, against ~3.3 G gathers of 12 bytes for the
// per-edge sums. (Tried and dropped, side by side: the rows probed in blocks of ranks that fit the
// last-level cache, 4-24 MB, which was slower at every size, and an AVX-512 probe with gathers.)
// Triangles (u, a, b) with a and b in the core are summed core row by core row (core_pair_sums) instead
// of probing the core's long rows.
//
// A triangle (u, v, k) adds V_uk V_vk to P_uv and V_uv V_vk to P_uk, both edges of u, summed by the thread
// that owns u in a fixed order, and V_uv V_uk to P_vk, an edge of v that other threads may list too: those
// terms are kept and summed afterwards in fixed point (int64, a quantum of ~1e-14 of the largest possible
// sum; integer sums do not depend on the order), so P is the same for any number of threads. The weights
// are read in float32, as the reference computes this graph (spec 7.2).
struct Forward {
    std::vector<int32_t> rank;  // node -> rank (n - 1: the highest degree)
    std::vector<int64_t> ptr;   // forward CSR: u -> edges (u, k), rank k > rank u, in V's order
    Array<int32_t> col;         // the probes read the columns only (4 bytes each)
    Array<float> val;           // the sampler's graph is float32 (spec 7.2); read on hits
};

Forward forward_graph(const Csr &V, const std::vector<double> &vals, const std::vector<int32_t> &order,
                      int nthreads) {
    const int64_t n = V.n;
    Forward f;
    f.rank.resize(n);
    for (int64_t t = 0; t < n; ++t) f.rank[order[t]] = (int32_t)(n - 1 - t);
    f.ptr.assign(n + 1, 0);
    parallel_for(0, n, nthreads, 1024, [&](int64_t u, int) {
        int64_t c = 0;
        for (int64_t p = V.ptr[u]; p < V.ptr[u + 1]; ++p) c += f.rank[V.col[p]] > f.rank[u];
        f.ptr[u + 1] = c;
    });
    for (int64_t u = 0; u < n; ++u) f.ptr[u + 1] += f.ptr[u];
    f.col = Array<int32_t>::uninitialised(f.ptr[n]);
    f.val = Array<float>::uninitialised(f.ptr[n]);
    parallel_for(0, n, nthreads, 1024, [&](int64_t u, int) {
        int64_t e = f.ptr[u];
        for (int64_t p = V.ptr[u]; p < V.ptr[u + 1]; ++p)
            if (f.rank[V.col[p]] > f.rank[u]) f.col[e] = V.col[p], f.val[e++] = (float)vals[p];
    });
    return f;
}

// The triangles (u, a, b) of a node u outside the core with two core nodes a, b (skipped by the listing,
// which does not probe the core's long rows): P_ua += sum over u's core neighbours b of W_ub W_ab. Core
// row by core row: row a of V scattered densely over the core (m entries, in L1 / L2) against the short
// lists of core neighbours of each u next to a (kept compact, in L3). Each P_ua is one sum, by one
// thread. Weights in float32, as in the listing.
void core_pair_sums(const Csr &V, const std::vector<double> &vals, const Forward &f, const Core &core,
                    std::vector<double> &own, int nthreads, InterruptibleRegion &ctrl_c) {
    const int64_t n = (int64_t)f.rank.size(), m = core.m, top = n - m;
    const int32_t *fcol = f.col.data();
    const float *fval = f.val.data();
    // For each u outside the core: its core neighbours (core index, weight); for each core node a: the
    // edges (u, a) as (u, forward position).
    std::vector<int64_t> cptr(n + 1, 0), aptr(m + 1, 0);
    for (int64_t u = 0; u < n; ++u) {
        if (f.rank[u] < top)
            for (int64_t e = f.ptr[u]; e < f.ptr[u + 1]; ++e)
                if (f.rank[fcol[e]] >= top) ++cptr[u + 1], ++aptr[core.pos[fcol[e]] + 1];
    }
    for (int64_t u = 0; u < n; ++u) cptr[u + 1] += cptr[u];
    for (int64_t a = 0; a < m; ++a) aptr[a + 1] += aptr[a];
    struct CoreEntry {
        int32_t col;
        float val;
    };
    std::vector<CoreEntry> cn(cptr[n]);
    std::vector<std::pair<int32_t, int64_t>> by_a(aptr[m]);
    std::vector<int64_t> fill(aptr.begin(), aptr.end() - 1);
    for (int64_t u = 0, c = 0; u < n; ++u) {
        if (f.rank[u] >= top) continue;
        for (int64_t e = f.ptr[u]; e < f.ptr[u + 1]; ++e)
            if (f.rank[fcol[e]] >= top) {
                const int32_t a = core.pos[fcol[e]];
                cn[c++] = {a, fval[e]};
                by_a[fill[a]++] = {(int32_t)u, e};
            }
    }
    DynamicRange rows(0, m, 4);
    parallel_region(nthreads, [&](int tid) {
        std::vector<double> dense(m, 0.0);
        int64_t lo, hi;
        while (!ctrl_c.stopped(tid) && rows.next(lo, hi)) for (int64_t a = lo; a < hi; ++a) {
            if (aptr[a + 1] == aptr[a]) continue;
            const int32_t k = core.nodes[a];
            for (int64_t p = V.ptr[k]; p < V.ptr[k + 1]; ++p)
                if (core.pos[V.col[p]] >= 0) dense[core.pos[V.col[p]]] = (float)vals[p];
            for (int64_t r = aptr[a]; r < aptr[a + 1]; ++r) {
                const int32_t u = by_a[r].first;
                double s0 = 0.0, s1 = 0.0;
                const CoreEntry *c = cn.data() + cptr[u], *ce = cn.data() + cptr[u + 1];
                for (; c + 2 <= ce; c += 2) {
                    s0 += dense[c[0].col] * (double)c[0].val;
                    s1 += dense[c[1].col] * (double)c[1].val;
                }
                if (c < ce) s0 += dense[c->col] * (double)c->val;
                own[by_a[r].second] += s0 + s1;  // dense[a] = 0: no self term
            }
            for (int64_t p = V.ptr[k]; p < V.ptr[k + 1]; ++p)
                if (core.pos[V.col[p]] >= 0) dense[core.pos[V.col[p]]] = 0.0;
        }
    });
}

std::vector<double> forward_products(const Csr &V, const std::vector<double> &vals, const Forward &f,
                                     const Core &core, int nthreads, InterruptibleRegion &ctrl_c) {
    const int64_t n = (int64_t)f.rank.size(), ne = f.ptr[n];
    const int64_t top = n - core.m;  // ranks >= top: the core
    double vmax = 0.0;
    for (int64_t e = 0; e < ne; ++e) vmax = std::max(vmax, (double)std::abs(f.val[e]));
    // |a fixed-point sum| <= vmax^2 * (n - 2) < 2^62: scale = the largest power of two that keeps it so
    // (1 when every weight is 0: no term to add then).
    const double bound = vmax * vmax * (double)std::max<int64_t>(n, 1);
    const double scale =
        bound > 0.0 ? std::ldexp(1.0, (int)std::floor(std::log2(std::ldexp(1.0, 62) / bound))) : 1.0;
    std::vector<double> own(ne, 0.0);
    Array<int64_t> shared = Array<int64_t>::uninitialised(ne);
    std::memset(shared.data(), 0, (size_t)ne * sizeof(int64_t));
    constexpr int64_t kAhead = 4;
    const int32_t *fcol = f.col.data();
    const float *fval = f.val.data();
    // P_vk's terms: kept for later and summed in fixed point, each thread those of its own range of edges
    // (no atomics, and the same sums for any number of threads).
    // 8 bytes a term (use_triangles keeps the edge count below 2^32), in blocks: no copy as they grow.
    struct Deferred {
        uint32_t e;
        float x;
    };
    constexpr size_t kBlock = size_t(1) << 16;
    std::vector<std::vector<std::vector<Deferred>>> deferred(std::max(1, nthreads));
    DynamicRange nodes(0, n, 64);
    parallel_region(nthreads, [&](int tid) {
        std::vector<uint64_t> bits((n + 63) / 64, 0);
        std::vector<int32_t> slot(n, 0);  // k -> offset of (u, k) in N+(u), read on hits only
        std::vector<int32_t> hits;        // offsets in N+(v) of the probes that hit
        std::vector<std::pair<uint32_t, uint32_t>> found;  // u's hits: (edge (v, k), edge (u, v))
        std::vector<std::vector<Deferred>> &later = deferred[tid];
        later.emplace_back().reserve(kBlock);
        int64_t lo, hi;
        while (!ctrl_c.stopped(tid) && nodes.next(lo, hi)) for (int64_t u = lo; u < hi; ++u) {
            if (f.rank[u] >= top) continue;
            const int64_t u0 = f.ptr[u], u1 = f.ptr[u + 1];
            if (u1 - u0 < 2) continue;
            for (int64_t e = u0; e < u1; ++e) {
                const int32_t k = fcol[e];
                bits[k >> 6] |= uint64_t(1) << (k & 63);
                slot[k] = (int32_t)(e - u0);
            }
            for (int64_t e1 = u0; e1 < u1; ++e1) {
                // The rows N+(v) lie at random: fetch the one kAhead steps ahead, a line at a time.
                if (e1 + kAhead < u1) {
                    const int32_t w = fcol[e1 + kAhead];
                    if (f.rank[w] < top) {
                        const char *r0 = reinterpret_cast<const char *>(fcol + f.ptr[w]);
                        const char *r1 = reinterpret_cast<const char *>(fcol + f.ptr[w + 1]);
                        for (const char *r = r0; r < r1; r += 64) __builtin_prefetch(r);
                    }
                }
                const int32_t v = fcol[e1];
                if (f.rank[v] >= top) continue;  // N+(v) is all core: the pairs above
                const int64_t v0 = f.ptr[v], len = f.ptr[v + 1] - v0;
                if ((int64_t)hits.size() < len) hits.resize(len);
                const int64_t nh = probe(fcol + v0, len, bits.data(), hits.data());
                // The weights of the hits lie at random too: fetched now, read once all of u's rows are
                // probed (a load at each hit stalled the listing: ~40 % of its time).
                for (int64_t h = 0; h < nh; ++h) {
                    const uint32_t e2 = (uint32_t)(v0 + hits[h]);
                    __builtin_prefetch(fval + e2);
                    found.push_back({e2, (uint32_t)e1});
                }
            }
            for (const auto &[e2, e1] : found) {  // the triangle (u, v, k): e1 = (u, v), e2 = (v, k)
                const int64_t e3 = u0 + slot[fcol[e2]];
                const double wuv = fval[e1], wvk = fval[e2], wuk = fval[e3];
                own[e1] += wuk * wvk;
                own[e3] += wuv * wvk;
                if (later.back().size() == kBlock) later.emplace_back().reserve(kBlock);
                later.back().push_back({e2, (float)(wuv * wuk)});
            }
            found.clear();
            for (int64_t e = u0; e < u1; ++e) bits[fcol[e] >> 6] = 0;
        }
    });
    ctrl_c.throw_if_hit();
    if (core.m > 0) core_pair_sums(V, vals, f, core, own, nthreads, ctrl_c);
    ctrl_c.throw_if_hit();
    // Fixed point: the sum of a thread's share is the same whichever thread listed each term.
    const int64_t nparts = std::max(1, nthreads);
    DynamicRange parts(0, nparts, 1);
    parallel_region(nthreads, [&](int) {
        int64_t part, part_end;
        int64_t *sh = shared.data();
        while (parts.next(part, part_end)) {
            const int64_t e_lo = ne * part / nparts, e_hi = ne * (part + 1) / nparts;
            for (const auto &blocks : deferred)
                for (const auto &list : blocks)
                    for (const Deferred &d : list)
                        if (d.e >= e_lo && d.e < e_hi) sh[d.e] += (int64_t)std::nearbyint((double)d.x * scale);
        }
    });
    const double inv = 1.0 / scale;
    parallel_for(0, ne, nthreads, 1 << 16, [&](int64_t e, int) { own[e] += (double)shared[e] * inv; });
    return own;
}

// P's entries below the diagonal from those above (P_ba = P_ab), in 16 x 16 blocks (cache-local both
// ways): then every entry of S reads its own row of P and no mirror is needed. Whole off-diagonal float
// blocks are transposed in registers where the CPU has AVX-512 (a copy: the same values).
template <class T>
void symmetrize(T *P, int64_t m, int64_t ld, int nthreads) {
    constexpr int64_t kB = 16;
    const int64_t nb = (m + kB - 1) / kB;
    bool wide = false;
#if defined(__GNUC__) && defined(__x86_64__)
    if constexpr (sizeof(T) == sizeof(float)) wide = __builtin_cpu_supports("avx512f");
#endif
    parallel_for(0, nb, nthreads, 1, [&](int64_t bi, int) {
        const int64_t a0 = bi * kB, a1 = std::min(m, a0 + kB);
        for (int64_t bj = 0; bj <= bi; ++bj) {
            const int64_t b0 = bj * kB, b1 = std::min(m, b0 + kB);
#if defined(__GNUC__) && defined(__x86_64__)
            if constexpr (sizeof(T) == sizeof(float))
                if (wide && bj < bi && a1 - a0 == kB) {  // rows b0.. of the upper block into rows a0.. below
                    transpose16_avx512(P + b0 * ld + a0, ld, P + a0 * ld + b0, ld);
                    continue;
                }
#endif
            for (int64_t a = a0; a < a1; ++a)
                for (int64_t b = b0; b < std::min(b1, a); ++b) P[a * ld + b] = P[b * ld + a];
        }
    });
}

}  // namespace

// Each edge was computed at one of its two entries (done): copy it to the other. Row j's lower part is
// ordered by i, so a cursor per row finds the mirror of every upper entry. Blocks of rows run in parallel
// (distinct edges, distinct entries): a block's cursors start where the rows before it left them, the
// first column >= the block's first row (one binary search per row and block).
static void mirror_block(const Csr &V, std::vector<double> &S, const std::vector<uint8_t> &done, int64_t i0,
                         int64_t i1) {
    std::vector<int64_t> cursor(V.n);
    for (int64_t j = 0; j < V.n; ++j) {
        const int32_t *b = V.col.data() + V.ptr[j], *e = V.col.data() + V.upper[j];
        cursor[j] = std::lower_bound(b, e, (int32_t)i0) - V.col.data();
    }
    for (int64_t i = i0; i < i1; ++i)
        for (int64_t p = V.upper[i]; p < V.ptr[i + 1]; ++p) {
            const int64_t q = cursor[V.col[p]]++;
            if (done[p]) S[q] = S[p];
            else S[p] = S[q];
        }
}

void mirror_entries(const Csr &V, std::vector<double> &S, const std::vector<uint8_t> &done, int nthreads) {
    const int64_t n = V.n, half = V.nnz() / 2;
    // ~4 blocks a thread of about equal upper entries, each of >= 2^14 edges and >= 4 n (a block's set-up
    // is n binary searches)
    const int64_t blocks = std::max<int64_t>(
        1, std::min({(int64_t)4 * std::max(nthreads, 1), half >> 14, half / std::max<int64_t>(4 * n, 1)}));
    std::vector<int64_t> start{0};
    int64_t seen = 0;
    for (int64_t i = 0; i < n; ++i) {
        seen += V.ptr[i + 1] - V.upper[i];
        if (seen * blocks >= half * (int64_t)start.size() && (int64_t)start.size() < blocks) start.push_back(i + 1);
    }
    if (start.back() != n) start.push_back(n);
    parallel_for(0, (int64_t)start.size() - 1, blocks > 1 ? nthreads : 1, 1,
                 [&](int64_t b, int) { mirror_block(V, S, done, start[b], start[b + 1]); });
}

namespace {

// The listing pays where the entries outside the core (12 bytes each for the gathers) outgrow a
// last-level cache: from 2^21 of them (1.8 M edges at 20,000 nodes: 1.3-1.5x faster; 0.45 M at 10,000 and
// the real 5,000-node outdoor pairs: slower). FASTMAC_TRIANGLES=on | off forces it (tests, benchmarks).
bool use_triangles(const Csr &V, const Core &core) {
    if (env_is("FASTMAC_TRIANGLES", "off")) return false;
    if (env_is("FASTMAC_TRIANGLES", "on")) return V.nnz() / 2 < (int64_t(1) << 32);
    // (and below 2^32 forward edges: the listing's deferred terms index them in 32 bits)
    return V.nnz() - core.inside >= (int64_t(1) << 21) && V.nnz() / 2 < (int64_t(1) << 32);
}

}  // namespace

std::vector<double> masked_square(const Csr &V, const std::vector<double> &vals, int nthreads, int64_t *core_size,
                                  Precision precision) {
    const int64_t n = V.n;
    const int64_t *ptr = V.ptr.data();
    const int32_t *col = V.col.data();
    const double *v = vals.data();
    auto deg = [&](int64_t i) { return ptr[i + 1] - ptr[i]; };
    // The work is ~ sum over edges of the smaller degree: serial only for small graphs.
    nthreads = resolve_threads(nthreads, std::max<int64_t>(n, V.nnz() / 16));
    std::vector<int32_t> order;
    const Core core = find_core(V, order, precision);
    if (core_size) *core_size = core.m;
    InterruptibleRegion ctrl_c;  // Ctrl-C: a 50,000-node graph takes seconds
    const bool listing_ok = precision == Precision::Single;  // the sampler's graph
    const bool single = precision == Precision::Single ||
                        (precision == Precision::Mac && core.m >= kSingleCore &&
                         !env_is("FASTMAC_MAC_PRECISION", "double"));
    const tiles::TileBf16 tile16 = precision == Precision::Mac && core.m >= kHalfCore &&
                                           !env_is("FASTMAC_MAC_PRECISION", "double") &&
                                           !env_is("FASTMAC_MAC_PRECISION", "single")
                                       ? pick_bf16_tile()
                                       : tiles::TileBf16{};
    // P in double, or in float (see Precision), from float or bfloat16 operands
    Array<double> Pd;
    Array<float> Pf;
    int64_t ld = 0;
    if (core.m > 0) {
        if (tile16.fn) {
            ld = (core.m + tile16.nr - 1) / tile16.nr * tile16.nr;
            // rows of P a multiple of 4 KB apart put a column of 16 rows in one L1 set (the tiles' sums and
            // symmetrize read and write such columns): one more panel of zeros then
            if (ld * (int64_t)sizeof(float) % 4096 == 0) ld += tile16.nr;
            Pf = core_products_bf16(V, vals, core, tile16, ld, nthreads, ctrl_c);
        } else if (single) {
            const tiles::Tile<float> tile = pick_tile<float>();
            ld = (core.m + tile.nr - 1) / tile.nr * tile.nr;
            Pf = core_products<float>(V, vals, core, tile, ld, nthreads, ctrl_c);
        } else {
            const tiles::Tile<double> tile = pick_tile<double>();
            ld = (core.m + tile.nr - 1) / tile.nr * tile.nr;
            Pd = core_products<double>(V, vals, core, tile, ld, nthreads, ctrl_c);
        }
    }
    // Every edge in the core (the whole graph as the core): both entries of each edge from P.
    const auto core_value = [&](int64_t a, int64_t b) {  // P_ab, a < b
        return single ? (double)Pf[a * ld + b] : Pd[a * ld + b];
    };
    const auto in_core = [&](int64_t i) { return core.m > 0 && core.pos[i] >= 0; };

    std::vector<double> S(V.nnz(), 0.0);
    if (core.m > 0 && core.inside == V.nnz()) {
        // Every edge in the core (the whole graph as the core): P made symmetric, both entries of each edge
        // read their own row of it; no gathers, no mirror.
        if (single) symmetrize(Pf.data(), core.m, ld, nthreads);
        else symmetrize(Pd.data(), core.m, ld, nthreads);
        parallel_for(0, n, nthreads, 64, [&](int64_t i, int) {
            for (int64_t p = ptr[i]; p < ptr[i + 1]; ++p) S[p] = v[p] * core_value(core.pos[i], core.pos[col[p]]);
        });
        return S;
    }
    std::vector<uint8_t> done(V.nnz(), 0);  // S[p] computed at p (else at its mirror)
    // The sampler's graph (single) on a large graph: every edge outside the core from the triangle
    // listing. MAC's graph keeps the per-edge sums below, whose order of additions the Python backend's
    // parity rests on; so do small graphs, where the gathers hit the cache and the listing's set-up costs
    // more than it saves (measured on the 5,000-correspondence outdoor pairs: 10-25 % slower there).
    if (listing_ok && use_triangles(V, core)) {
        if (order.empty()) order = degree_order(V);  // no core search ran (small or switched off)
        const Forward f = forward_graph(V, vals, order, nthreads);
        ctrl_c.throw_if_hit();
        const std::vector<double> P = forward_products(V, vals, f, core, nthreads, ctrl_c);
        const int64_t top = n - core.m;
        parallel_for(0, n, nthreads, 512, [&](int64_t i, int) {
            int64_t e = f.ptr[i];
            for (int64_t p = ptr[i]; p < ptr[i + 1]; ++p) {
                const int32_t j = col[p];
                if (f.rank[j] < f.rank[i]) continue;
                const double pij = P[e++];
                done[p] = 1;
                if (f.rank[i] >= top) {  // both in the core (j ranks above i)
                    const int64_t a = core.pos[i], b = core.pos[j];
                    S[p] = v[p] * core_value(std::min(a, b), std::max(a, b));
                } else {
                    S[p] = v[p] * pij;
                }
            }
        });
        mirror_entries(V, S, done, nthreads);
        return S;
    }
    DynamicRange rows(0, n, 8);
    ctrl_c.throw_if_hit();
    parallel_region(nthreads, [&](int tid) {
        // Row i of V scattered densely; zero elsewhere (k = i contributes nothing: no self-loops).
        std::vector<double> dense(n, 0.0);
        double *d = dense.data();
        int64_t lo, hi;
        while (!ctrl_c.stopped(tid) && rows.next(lo, hi)) for (int64_t i = lo; i < hi; ++i) {
            const bool ci = in_core(i);
            const int64_t di = deg(i);
            bool scattered = false;
            for (int64_t p = ptr[i]; p < ptr[i + 1]; ++p) {
                const int32_t j = col[p];
                if (ci && in_core(j)) {
                    if (j > i) {  // a core edge: from P
                        const int64_t a = core.pos[i], b = core.pos[j];
                        S[p] = v[p] * core_value(std::min(a, b), std::max(a, b));
                        done[p] = 1;
                    }
                    continue;
                }
                // Owned by the endpoint with the longer row (ties: the smaller index), summed over the other.
                const int64_t dj = deg(j);
                if (dj > di || (dj == di && j < i)) continue;
                done[p] = 1;
                if (v[p] == 0.0) continue;  // no entry here (e.g. C where G = 0)
                if (!scattered) {
                    for (int64_t q = ptr[i]; q < ptr[i + 1]; ++q) d[col[q]] = v[q];
                    scattered = true;
                }
                const int64_t q0 = ptr[j], q1 = ptr[j + 1];
                // Four partial sums keep the loop from waiting on one addition chain.
                double a0 = 0.0, a1 = 0.0, a2 = 0.0, a3 = 0.0;
                int64_t q = q0;
                for (; q + 4 <= q1; q += 4) {
                    a0 += d[col[q]] * v[q];
                    a1 += d[col[q + 1]] * v[q + 1];
                    a2 += d[col[q + 2]] * v[q + 2];
                    a3 += d[col[q + 3]] * v[q + 3];
                }
                for (; q < q1; ++q) a0 += d[col[q]] * v[q];
                S[p] = v[p] * ((a0 + a1) + (a2 + a3));
            }
            if (scattered)
                for (int64_t p = ptr[i]; p < ptr[i + 1]; ++p) d[col[p]] = 0.0;
        }
    });
    ctrl_c.throw_if_hit();
    mirror_entries(V, S, done, nthreads);
    return S;
}

bool bf16_cores() { return pick_bf16_tile().fn != nullptr; }

std::string bf16_kernel() {
    const tiles::TileBf16 t = pick_bf16_tile();
    return !t.fn ? "" : t.kgroup == 16 ? "amx" : "avx512_bf16";
}

std::vector<double> second_order(const Csr &W, int nthreads, int64_t *core_size, Precision precision) {
    return masked_square(W, W.w, nthreads, core_size, precision);
}

}  // namespace fastmac
