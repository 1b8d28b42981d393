// The trust test's counts (fastmac_exp/geometry/trust.py). count_within: how many points of a cloud lie within
// a radius of each query point (the chance count): a grid of cells of the radius over the cloud; the queries,
// grouped by the cell they fall in, share the candidates of the 3 x 3 x 3 cells around it, and a point counts
// when its squared distance ((dx^2 + dy^2) + dz^2) is <= radius^2, as scipy's cKDTree.query_ball_point(...,
// return_length=True) counts, which this replaces (one thread there, ~6 ms for 4,000 matches of a 3DMatch
// pair at tau = 10 cm).
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <stdexcept>
#include <utility>
#include <vector>

#include "mac_core.hpp"
#include "parallel.hpp"
#include "point_grid.hpp"
#include "within.hpp"

namespace fastmac {

namespace {

// How many of the nc candidates lie within r2 of (x, y, z): built for AVX-512 and AVX2 besides the baseline
// (the loop vectorises; each lane does the same IEEE operations, so every clone counts the same).
#if defined(__GNUC__) && defined(__x86_64__) && !defined(__clang__)
__attribute__((target_clones("avx512f", "avx2", "default")))
#endif
int64_t count_near(double x, double y, double z, const double *__restrict ax, const double *__restrict ay,
                   const double *__restrict az, int64_t nc, double r2) {
    int64_t cnt = 0;
    for (int64_t t = 0; t < nc; ++t) {
        const double ex = x - ax[t], ey = y - ay[t], ez = z - az[t];
        cnt += (ex * ex + ey * ey + ez * ez) <= r2;
    }
    return cnt;
}

// Queries of one cell from which its candidates are gathered into one list (below: each run counted in place)
constexpr int64_t kGatherFrom = 4;

}  // namespace

std::vector<int64_t> count_within(const double *queries, int64_t m, const double *points, int64_t n, double radius,
                                  int nthreads) {
    if (!(radius > 0) || !std::isfinite(radius)) throw std::invalid_argument("count_within: radius must be positive");
    std::vector<int64_t> out(m, 0);
    if (m == 0 || n == 0) return out;
    for (int64_t i = 0; i < 3 * n; ++i)
        if (!std::isfinite(points[i])) throw std::invalid_argument("count_within: a point is not finite");
    // Cells a hair wider than r: the points within r of a query lie in the 3^3 cells around its cell, even
    // where the rounding of (x - lo) / h (~1e-9 of a cell at 2^20 cells) moves a point across a boundary.
    // (Cells of r / 2, 5^3 around, tested the fewer candidates and cost twice as much: a query's 25 column
    // lookups, not its distances, were the work; 9 here.)
    constexpr int64_t reach = 1;
    const double h = radius * (1.0 + 1e-6), r2 = radius * radius;
    double lo[3];
    grid::cloud_min(points, n, lo);
    grid::CellGrid g;
    if (!grid::build_cells(points, n, h, lo, g))
        throw std::invalid_argument("count_within: the cloud spans more than 2^20 radii");
    grid::index_columns(g);
    int64_t top[3] = {0, 0, 0};
    for (int64_t i = 0; i < n; ++i)
        for (int d = 0; d < 3; ++d) top[d] = std::max(top[d], g.cx[3 * i + d]);
    // the queries by cell; one farther than `reach` cells from every occupied cell (or not finite) counts 0
    std::vector<std::pair<uint64_t, int64_t>> keyed;
    std::vector<int64_t> qc(3 * m);
    keyed.reserve(m);
    for (int64_t i = 0; i < m; ++i) {
        bool inside = true;
        for (int d = 0; d < 3; ++d) {
            const double f = std::floor((queries[3 * i + d] - lo[d]) / h) + grid::kReach;
            inside = inside && f >= -reach && f <= double(top[d] + reach);  // false for NaN
            qc[3 * i + d] = inside ? int64_t(f) : 0;
        }
        if (!inside) continue;
        const int64_t *c = &qc[3 * i];
        keyed.push_back({(uint64_t(c[0] + reach) * (g.ny + 2 * reach) + uint64_t(c[1] + reach)) *
                                 (g.nz + 2 * reach) + uint64_t(c[2] + reach), i});
    }
    grid::sort_keyed(keyed);
    std::vector<int64_t> group;  // where each run of queries of one cell starts
    for (int64_t k = 0; k < int64_t(keyed.size()); ++k)
        if (k == 0 || keyed[k].first != keyed[k - 1].first) group.push_back(k);
    const int64_t ngroup = int64_t(group.size());
    group.push_back(int64_t(keyed.size()));
    nthreads = resolve_threads(nthreads, m);
    DynamicRange range(0, ngroup, 16);
    parallel_region(nthreads, [&](int) {
        std::vector<double> px, py, pz;
        int64_t g0, g1;
        while (range.next(g0, g1))
            for (int64_t gi = g0; gi < g1; ++gi) {
                const int64_t *c = &qc[3 * keyed[group[gi]].second];
                int64_t s0[9], s1[9], nc = 0;
                for (int64_t dx = -reach, k = 0; dx <= reach; ++dx)
                    for (int64_t dy = -reach; dy <= reach; ++dy, ++k) {
                        grid::run_range(g, c[0] + dx, c[1] + dy, c[2] - reach, c[2] + reach, s0[k], s1[k]);
                        nc += s1[k] - s0[k];
                    }
                const int64_t nq = group[gi + 1] - group[gi];
                if (nq < kGatherFrom) {  // a few queries (sparse outdoor keypoints): each of the 9 runs in place
                    for (int64_t k = group[gi]; k < group[gi + 1]; ++k) {
                        const int64_t i = keyed[k].second;
                        int64_t cnt = 0;
                        for (int64_t r = 0; r < 9; ++r)
                            if (s1[r] > s0[r])
                                cnt += count_near(queries[3 * i], queries[3 * i + 1], queries[3 * i + 2], g.sx.data() + s0[r],
                                                  g.sy.data() + s0[r], g.sz.data() + s0[r], s1[r] - s0[r], r2);
                        out[i] = cnt;
                    }
                    continue;
                }
                // many: the runs gathered once into one candidate list that every query of the cell reads
                px.resize(size_t(nc)), py.resize(size_t(nc)), pz.resize(size_t(nc));
                for (int64_t r = 0, at = 0; r < 9; at += s1[r] - s0[r], ++r) {
                    std::copy(g.sx.begin() + s0[r], g.sx.begin() + s1[r], px.begin() + at);
                    std::copy(g.sy.begin() + s0[r], g.sy.begin() + s1[r], py.begin() + at);
                    std::copy(g.sz.begin() + s0[r], g.sz.begin() + s1[r], pz.begin() + at);
                }
                const double *__restrict ax = px.data(), *__restrict ay = py.data(), *__restrict az = pz.data();
                for (int64_t k = group[gi]; k < group[gi + 1]; ++k) {
                    const int64_t i = keyed[k].second;
                    out[i] = count_near(queries[3 * i], queries[3 * i + 1], queries[3 * i + 2], ax, ay, az, nc, r2);
                }
            }
    });
    return out;
}

// explained_counts: for each of h poses (row-major 4 x 4), how many correspondences it maps within
// `threshold` of their target: |R s_i + t - q_i| < threshold, the residual's norm as numpy's (the trust test's `explained`, which
// ran one numpy pass a pose: ~0.1 ms of interpreter and temporaries each on 4,000 matches, sixteen of them for
// the rivals). Chunks of (pose, rows) across the threads; a pose's count is the sum of its chunks'.
std::vector<int64_t> explained_counts(const double *src, const double *tgt, int64_t n, const double *poses, int64_t h,
                                      double threshold, int nthreads) {
    std::vector<int64_t> out(h, 0);
    if (n == 0 || h == 0) return out;
    constexpr int64_t kRows = 8192;  // rows a task
    const int64_t chunks = (n + kRows - 1) / kRows;
    std::vector<int64_t> part(h * chunks, 0);
    nthreads = resolve_threads(nthreads, n * h);
    parallel_for(0, h * chunks, nthreads, 1, [&](int64_t task, int) {
        const int64_t k = task / chunks, c = task % chunks;
        const double *T = poses + 16 * k;
        const double r00 = T[0], r01 = T[1], r02 = T[2], t0 = T[3], r10 = T[4], r11 = T[5], r12 = T[6],
                     t1 = T[7], r20 = T[8], r21 = T[9], r22 = T[10], t2 = T[11];
        const int64_t i0 = c * kRows, i1 = std::min(n, i0 + kRows);
        int64_t cnt = 0;
        for (int64_t i = i0; i < i1; ++i) {
            const double *s = src + 3 * i, *q = tgt + 3 * i;
            const double ex = r00 * s[0] + r01 * s[1] + r02 * s[2] + t0 - q[0];
            const double ey = r10 * s[0] + r11 * s[1] + r12 * s[2] + t1 - q[1];
            const double ez = r20 * s[0] + r21 * s[1] + r22 * s[2] + t2 - q[2];
            cnt += std::sqrt(ex * ex + ey * ey + ez * ez) < threshold;  // false for NaN, as numpy's
        }
        part[task] = cnt;
    });
    for (int64_t task = 0; task < h * chunks; ++task) out[task / chunks] += part[task];
    return out;
}

}  // namespace fastmac
