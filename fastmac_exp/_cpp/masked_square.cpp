// S_ij = V_ij * sum_k V_ik V_kj on the stored entries of a symmetric sparse matrix V: the second-order
// graph G = W * (W W) (spec 2.3) and the clustering coefficients' triangle sums (V = G^(1/3), spec 2.4).
//
// Row i of V is scattered into a dense array d, then every upper entry (i, j) takes sum_k d[k] V_jk
// over row j: one gather per (edge, neighbour of j). Measured alternatives that lost on the real KITTI
// graphs (5,000 nodes, 394k edges, a dense core of ~1,000 nodes): dense float64 rows over the core with
// SIMD dot products per edge (memory-bound: 1.0-2.5x slower), and bit rows over the core with
// popcount-ranked values per common neighbour (1.5-2.5x slower); see benchmarks/bench_core.py.
#include <algorithm>

#include "mac_core.hpp"
#include "parallel.hpp"

namespace fastmac {

std::vector<double> masked_square(const Csr &V, const std::vector<double> &vals, int nthreads) {
    // The work is ~ sum over edges of deg(j): serial only for small graphs.
    nthreads = resolve_threads(nthreads, std::max<int64_t>(V.n, V.nnz() / 16));
    const int64_t n = V.n;
    std::vector<double> S(V.nnz(), 0.0);
    const int64_t *ptr = V.ptr.data();
    const int32_t *col = V.col.data();
    const double *v = vals.data();
    DynamicRange rows(0, n, 8);
    parallel_region(nthreads, [&](int) {
        // Row i of V scattered densely; zero elsewhere (k = i contributes nothing: no self-loops).
        std::vector<double> dense(n, 0.0);
        double *d = dense.data();
        int64_t lo, hi;
        while (rows.next(lo, hi)) for (int64_t i = lo; i < hi; ++i) {
            if (V.upper[i] == ptr[i + 1]) continue;
            for (int64_t p = ptr[i]; p < ptr[i + 1]; ++p) d[col[p]] = v[p];
            for (int64_t p = V.upper[i]; p < ptr[i + 1]; ++p) {
                if (v[p] == 0.0) continue;  // no entry here (e.g. C where G = 0)
                // d[j] = V_ij is never read: j is not its own neighbour. Four partial sums keep the
                // loop from waiting on one addition chain (most terms are zero: d is sparse).
                const int32_t j = col[p];
                const int64_t q0 = ptr[j], q1 = ptr[j + 1];
                if (p + 2 < ptr[i + 1]) {  // rows j are scattered in memory: start fetching one ahead
                    const int64_t r = ptr[col[p + 2]];
                    for (int line = 0; line < 8; ++line) {
                        __builtin_prefetch(col + r + 16 * line);
                        __builtin_prefetch(v + r + 8 * line);
                    }
                }
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
            for (int64_t p = ptr[i]; p < ptr[i + 1]; ++p) d[col[p]] = 0.0;
        }
    });
    // Mirror the upper entries into the lower parts (row j's lower part is ordered by i).
    std::vector<int64_t> cursor(V.ptr.begin(), V.ptr.end() - 1);
    for (int64_t i = 0; i < n; ++i)
        for (int64_t p = V.upper[i]; p < ptr[i + 1]; ++p) S[cursor[col[p]]++] = S[p];
    return S;
}

std::vector<double> second_order(const Csr &W, int nthreads) { return masked_square(W, W.w, nthreads); }

}  // namespace fastmac
