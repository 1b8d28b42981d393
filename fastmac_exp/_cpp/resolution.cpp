// Each point's distance to its nearest other point (MAC's mesh resolution is their mean;
// fastmac_exp/geometry/resolution.py), exactly, from a uniform grid: a 3DMatch fragment at full resolution has
// 300,000 points, where a single-threaded k-d tree took ~0.3 s a cloud.
//
// The cell is sized for about four points an occupied cell. A query looks at its own cell and the 26
// around it; a point outside those is at least one cell away, so a nearest distance below one cell is
// final, and otherwise the search widens ring by ring until the next ring cannot hold anything closer.
#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <vector>

#if defined(__GNUC__) && defined(__x86_64__)
#include <immintrin.h>
#endif

#include "mac_core.hpp"
#include "parallel.hpp"
#include "point_grid.hpp"

namespace fastmac {

namespace {

using grid::CellGrid;
using grid::build_cells;
using grid::index_columns;
using grid::run_range;
using grid::kReach;

// Points an occupied cell aims at: gathering a cell's 27 neighbours is shared by its points, the distances
// are a vectorised loop: eight a cell took 25-40 ms on 120-300k-point scans where four took 27-61 ms.
constexpr double kPerCell = 8.0;

// The smallest squared distance from (x, y, z) to the candidates other than position `self`: the distances
// into `dd`, then their minimum as integers (the bits of non-negative doubles order as the values), so that
// both loops vectorise without fast-math.
#if defined(__GNUC__) && defined(__x86_64__) && !defined(__clang__)
__attribute__((target_clones("avx512f", "avx2", "default")))
#endif
double min_other_d2(double x, double y, double z, const double *__restrict qx, const double *__restrict qy,
                    const double *__restrict qz, int64_t m, int64_t self, double *__restrict dd) {
    for (int64_t t = 0; t < m; ++t) {
        const double ex = x - qx[t], ey = y - qy[t], ez = z - qz[t];
        dd[t] = ex * ex + ey * ey + ez * ez;
    }
    if (self < m) dd[self] = std::numeric_limits<double>::infinity();
    const int64_t *bits = reinterpret_cast<const int64_t *>(dd);
    int64_t best = std::numeric_limits<int64_t>::max();
    for (int64_t t = 0; t < m; ++t) best = std::min(best, bits[t]);
    double out;
    std::memcpy(&out, &best, 8);
    return best == std::numeric_limits<int64_t>::max() ? std::numeric_limits<double>::infinity() : out;
}

#if defined(__GNUC__) && defined(__x86_64__)
// min_other_d2 in one pass of AVX-512: the same squared distances (the same operations in the same order,
// no FMA: -ffp-contract=off) and their exact minimum, the query's own position masked to +inf.
__attribute__((target("avx512f"))) double min_other_d2_avx512(double x, double y, double z, const double *qx,
                                                               const double *qy, const double *qz, int64_t m,
                                                               int64_t self) {
    const __m512d px = _mm512_set1_pd(x), py = _mm512_set1_pd(y), pz = _mm512_set1_pd(z);
    const __m512d inf = _mm512_set1_pd(std::numeric_limits<double>::infinity());
    __m512d best = inf;
    for (int64_t t = 0; t < m; t += 8) {
        __mmask8 lanes = m - t >= 8 ? __mmask8(0xff) : __mmask8((1u << (m - t)) - 1u);
        if (self >= t && self < t + 8) lanes &= __mmask8(~(1u << (self - t)));
        const __m512d ex = _mm512_sub_pd(px, _mm512_maskz_loadu_pd(lanes, qx + t));
        const __m512d ey = _mm512_sub_pd(py, _mm512_maskz_loadu_pd(lanes, qy + t));
        const __m512d ez = _mm512_sub_pd(pz, _mm512_maskz_loadu_pd(lanes, qz + t));
        const __m512d d2 = _mm512_add_pd(_mm512_add_pd(_mm512_mul_pd(ex, ex), _mm512_mul_pd(ey, ey)), _mm512_mul_pd(ez, ez));
        best = _mm512_mask_min_pd(best, lanes, best, d2);
    }
    return _mm512_reduce_min_pd(best);
}

// FASTMAC_RESOLUTION_MIN=generic: the portable loops (read each call, for tests and benchmarks)
bool min_avx512() {
    static const bool cpu = __builtin_cpu_supports("avx512f");
    return cpu && !env_is("FASTMAC_RESOLUTION_MIN", "generic");
}
#else
bool min_avx512() { return false; }
double min_other_d2_avx512(double, double, double, const double *, const double *, const double *, int64_t,
                           int64_t) {
    return 0.0;
}
#endif

}  // namespace

std::vector<double> nearest_other_distances(const double *p, int64_t n, int nthreads) {
    if (n < 2) throw std::invalid_argument("nearest_other_distances: needs at least 2 points");
    double lo[3], hi[3];
    grid::cloud_min(p, n, lo);
    for (int d = 0; d < 3; ++d) hi[d] = -std::numeric_limits<double>::infinity();
    for (int64_t i = 0; i < n; ++i)
        for (int d = 0; d < 3; ++d) hi[d] = std::max(hi[d], p[3 * i + d]);
    for (int64_t i = 0; i < 3 * n; ++i)
        if (!std::isfinite(p[i])) throw std::invalid_argument("nearest_other_distances: a coordinate is not finite");
    double ext = 0.0;
    for (int d = 0; d < 3; ++d) {
        if (!std::isfinite(lo[d]) || !std::isfinite(hi[d]))
            throw std::invalid_argument("nearest_other_distances: a coordinate is not finite");
        ext = std::max(ext, hi[d] - lo[d]);
    }
    std::vector<double> out(n, 0.0);
    if (ext == 0.0) return out;  // every point the same
    // the cell: start from a volume-filling guess and rescale (as for a surface, points ~ h^2) until an
    // occupied cell holds 2-8 points
    double vol = 1.0;
    for (int d = 0; d < 3; ++d) vol *= std::max(hi[d] - lo[d], ext * 1e-3);
    double h = std::cbrt(vol / double(n)) * 2.0;
    // coarse rounds on every 16th point while the cells are far too full (a sixteenth of the points fills
    // a cell about a sixteenth as much where cells hold many points)
    if (n >= 65536) {
        std::vector<double> sub;
        for (int64_t i = 0; i < n; i += 16) sub.insert(sub.end(), p + 3 * i, p + 3 * i + 3);
        const int64_t ns = int64_t(sub.size() / 3);
        CellGrid gs;
        for (int round = 0; round < 6; ++round) {
            if (!build_cells(sub.data(), ns, h, lo, gs)) break;
            const double per_cell = 16.0 * double(ns) / double(gs.cell_key.size());
            if (per_cell <= 8 * kPerCell) break;
            h *= std::max(0.25, std::sqrt(kPerCell / per_cell));
        }
    }
    CellGrid g;
    for (int round = 0; round < 4; ++round) {
        if (!build_cells(p, n, h, lo, g)) {
            h *= 4.0;
            continue;
        }
        const double per_cell = double(n) / double(g.cell_key.size());
        if (per_cell >= kPerCell / 2 && per_cell <= kPerCell * 2) break;
        const double scale = std::sqrt(kPerCell / per_cell);
        if (round == 3 || std::fabs(scale - 1.0) < 0.05) break;
        h *= std::min(4.0, std::max(0.25, scale));
    }
    if (g.cell_key.empty() && !build_cells(p, n, h, lo, g))
        throw std::invalid_argument("nearest_other_distances: the cloud spans too many cells");
    index_columns(g);

    const int64_t ncell = int64_t(g.cell_key.size());
    nthreads = resolve_threads(nthreads, n);
    const bool use512 = min_avx512();
    DynamicRange range(0, ncell, 64);
    parallel_region(nthreads, [&](int) {
        std::vector<double> qx, qy, qz, dd;
        int64_t c0, c1;
        while (range.next(c0, c1)) {
            for (int64_t c = c0; c < c1; ++c) {
                const int64_t first = g.cell_start[c], last = g.cell_start[c + 1];
                const int64_t *cc = &g.cx[3 * g.order[first]];
                qx.clear(), qy.clear(), qz.clear();
                int64_t own = 0;  // where the cell's own points start among the candidates
                for (int64_t dx = -1; dx <= 1; ++dx)
                    for (int64_t dy = -1; dy <= 1; ++dy) {
                        int64_t s0, s1;
                        run_range(g, cc[0] + dx, cc[1] + dy, cc[2] - 1, cc[2] + 1, s0, s1);
                        if (s0 <= first && first < s1) own = int64_t(qx.size()) + (first - s0);
                        qx.insert(qx.end(), g.sx.begin() + s0, g.sx.begin() + s1);
                        qy.insert(qy.end(), g.sy.begin() + s0, g.sy.begin() + s1);
                        qz.insert(qz.end(), g.sz.begin() + s0, g.sz.begin() + s1);
                    }
                const int64_t m = int64_t(qx.size());
                dd.resize(m);
                for (int64_t s = first; s < last; ++s) {
                    const double x = g.sx[s], y = g.sy[s], z = g.sz[s];
                    // the query itself sits at one position of the candidates: the minimum of both sides
                    const int64_t self = own + (s - first);
                    double best = use512 ? min_other_d2_avx512(x, y, z, qx.data(), qy.data(), qz.data(), m, self)
                                         : min_other_d2(x, y, z, qx.data(), qy.data(), qz.data(), m, self, dd.data());
                    // rings 2, 3, ... while a point there could be closer (ring r is >= (r - 1) h away, less a
                    // hair for a point that rounding put in the next cell)
                    const double hh = g.h * (1.0 - 1e-9);
                    for (int64_t r = 2; !(best < double(r - 1) * hh * double(r - 1) * hh); ++r) {
                        if (r > 64) {  // an outlier far from everything: every point
                            for (int64_t t = 0; t < n; ++t) {
                                if (t == s) continue;
                                const double ex = x - g.sx[t], ey = y - g.sy[t], ez = z - g.sz[t];
                                best = std::min(best, ex * ex + ey * ey + ez * ez);
                            }
                            break;
                        }
                        auto take = [&](int64_t x0, int64_t y0, int64_t z0, int64_t z1) {
                            int64_t s0, s1;
                            run_range(g, x0, y0, z0, z1, s0, s1);
                            for (int64_t u = s0; u < s1; ++u) {
                                const double ex = x - g.sx[u], ey = y - g.sy[u], ez = z - g.sz[u];
                                best = std::min(best, ex * ex + ey * ey + ez * ez);
                            }
                        };
                        for (int64_t dx = -r; dx <= r; ++dx)
                            for (int64_t dy = -r; dy <= r; ++dy) {
                                if (std::max(std::abs(dx), std::abs(dy)) == r) {
                                    take(cc[0] + dx, cc[1] + dy, cc[2] - r, cc[2] + r);
                                } else {  // only the two z ends of this column are in ring r
                                    take(cc[0] + dx, cc[1] + dy, cc[2] - r, cc[2] - r);
                                    take(cc[0] + dx, cc[1] + dy, cc[2] + r, cc[2] + r);
                                }
                            }
                    }
                    out[g.order[s]] = std::sqrt(best);
                }
            }
        }
    });
    return out;
}

}  // namespace fastmac
