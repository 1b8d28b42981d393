// Each point's distance to its nearest other point (MAC's mesh resolution is their mean;
// fastmac_exp/geometry/resolution.py), exactly, from a uniform grid: a 3DMatch fragment at full resolution has
// 300,000 points, where a single-threaded k-d tree took ~0.3 s a cloud.
//
// The cell is sized for about eight points an occupied cell. A query looks at its own cell and the 26
// around it (their columns that can still hold something nearer); a point outside those is at least one
// cell away, so a nearest distance below one cell is final, and otherwise the search widens ring by ring
// until the next ring cannot hold anything closer.
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

// The smallest squared distance from (x, y, z) to the points at sorted positions [s0, s1) of the grid other
// than position `self`, folded into `best`: the distances, then their minimum as integers (the bits of
// non-negative doubles order as the values), so that both loops vectorise without fast-math.
#if defined(__GNUC__) && defined(__x86_64__) && !defined(__clang__)
__attribute__((target_clones("avx512f", "avx2", "default")))
#endif
double min_other_d2(double x, double y, double z, const double *__restrict qx, const double *__restrict qy,
                    const double *__restrict qz, int64_t s0, int64_t s1, int64_t self, double best,
                    double *__restrict dd) {
    const int64_t m = s1 - s0;
    qx += s0, qy += s0, qz += s0;
    for (int64_t t = 0; t < m; ++t) {
        const double ex = x - qx[t], ey = y - qy[t], ez = z - qz[t];
        dd[t] = ex * ex + ey * ey + ez * ez;
    }
    if (self >= s0 && self < s1) dd[self - s0] = std::numeric_limits<double>::infinity();
    const int64_t *bits = reinterpret_cast<const int64_t *>(dd);
    int64_t low;
    std::memcpy(&low, &best, 8);
    for (int64_t t = 0; t < m; ++t) low = std::min(low, bits[t]);
    std::memcpy(&best, &low, 8);
    return best;
}

#if defined(__GNUC__) && defined(__x86_64__)
// The smallest squared distance from each point of a cell (sorted positions [q0, q1)) to the points of the
// runs [r0[k], r1[k]) (the cell's 9 columns of 3 cells) other than itself, eight points of the cell a vector
// and every candidate broadcast: the same squared distances as min_other_d2, their minimum over all 27 cells
// (the per-point search skips the columns that cannot be nearer, so its minimum is the same). One pass over
// the candidates serves eight queries: ~5x the distances of the per-point search, at a fraction of the
// cost each (no per-column setup, masks or reductions). Both clouds of the full-resolution 3DMatch pair 4->0
// (313k + 258k points, Intel Xeon VM): 52.8 -> 49 ms on two threads, 83.9 -> 78.1 ms on one.
__attribute__((target("avx512f"))) void cell_min_d2_avx512(const double *sx, const double *sy, const double *sz,
                                                           int64_t q0, int64_t q1, const int64_t *r0,
                                                           const int64_t *r1, double *best_out) {
    for (int64_t g = q0; g < q1; g += 8) {
        const __mmask8 lanes = q1 - g >= 8 ? __mmask8(0xff) : __mmask8((1u << (q1 - g)) - 1u);
        const __m512d px = _mm512_maskz_loadu_pd(lanes, sx + g), py = _mm512_maskz_loadu_pd(lanes, sy + g),
                      pz = _mm512_maskz_loadu_pd(lanes, sz + g);
        const __m512i pos = _mm512_add_epi64(_mm512_set1_epi64(g), _mm512_setr_epi64(0, 1, 2, 3, 4, 5, 6, 7));
        __m512d best = _mm512_set1_pd(std::numeric_limits<double>::infinity());
        for (int k = 0; k < 9; ++k)
            for (int64_t t = r0[k]; t < r1[k]; ++t) {
                const __m512d ex = _mm512_sub_pd(px, _mm512_set1_pd(sx[t]));
                const __m512d ey = _mm512_sub_pd(py, _mm512_set1_pd(sy[t]));
                const __m512d ez = _mm512_sub_pd(pz, _mm512_set1_pd(sz[t]));
                const __m512d d2 =
                    _mm512_add_pd(_mm512_add_pd(_mm512_mul_pd(ex, ex), _mm512_mul_pd(ey, ey)), _mm512_mul_pd(ez, ez));
                const __mmask8 other = _mm512_cmpneq_epi64_mask(pos, _mm512_set1_epi64(t));
                best = _mm512_mask_min_pd(best, other, best, d2);
            }
        _mm512_mask_storeu_pd(best_out + (g - q0), lanes, best);
    }
}

// FASTMAC_RESOLUTION_MIN=generic: the portable loops (read each call, for tests and benchmarks)
bool min_avx512() {
    static const bool cpu = __builtin_cpu_supports("avx512f");
    return cpu && !env_is("FASTMAC_RESOLUTION_MIN", "generic");
}
#else
bool min_avx512() { return false; }
void cell_min_d2_avx512(const double *, const double *, const double *, int64_t, int64_t, const int64_t *,
                        const int64_t *, double *) {}
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
    // the cell: start from a surface's guess (the points spread over the box's three face areas, kPerCell of
    // them a cell: within the accepted 4-16 a cell at once on every 3DMatch-family cloud of ../shared/data,
    // where a volume-filling guess gave 44-131 and a second build) and rescale until an occupied cell holds 4-16
    double e[3];
    for (int d = 0; d < 3; ++d) e[d] = std::max(hi[d] - lo[d], ext * 1e-3);
    const double area = e[0] * e[1] + e[0] * e[2] + e[1] * e[2];
    double h = std::sqrt(area / double(n) * kPerCell);
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
    nthreads = resolve_threads(nthreads, n);
    CellGrid g;
    for (int round = 0; round < 4; ++round) {
        if (!build_cells(p, n, h, lo, g, nthreads)) {
            h *= 4.0;
            continue;
        }
        const double per_cell = double(n) / double(g.cell_key.size());
        if (per_cell >= kPerCell / 2 && per_cell <= kPerCell * 2) break;
        const double scale = std::sqrt(kPerCell / per_cell);
        if (round == 3 || std::fabs(scale - 1.0) < 0.05) break;
        h *= std::min(4.0, std::max(0.25, scale));
    }
    if (g.cell_key.empty() && !build_cells(p, n, h, lo, g, nthreads))
        throw std::invalid_argument("nearest_other_distances: the cloud spans too many cells");
    index_columns(g);
    const int64_t ncell = int64_t(g.cell_key.size());
    const bool use512 = min_avx512();
    DynamicRange range(0, ncell, 64);
    // A cell's 9 columns of 3 cells around it, each a run of sorted positions read in place. A query takes
    // its own column, then each other column only where that column's side is nearer than the best so far
    // (most queries: one or two of the eight; a point there is at least that far, so the minimum is the
    // same as over all 27 cells). The sides are moved out by a hair for a point that rounding put in the next
    // cell: 1e-6 of a cell, and a few units in the last place of the coordinates (far from the origin).
    double big = 0.0;
    for (int d = 0; d < 3; ++d) big = std::max({big, std::fabs(lo[d]), std::fabs(hi[d])});
    const double side_margin = g.h * 1e-6 + 64.0 * std::numeric_limits<double>::epsilon() * big;
    parallel_region(nthreads, [&](int) {
        std::vector<double> dd, cell_best;
        int64_t c0, c1;
        while (range.next(c0, c1)) {
            for (int64_t c = c0; c < c1; ++c) {
                const int64_t first = g.cell_start[c], last = g.cell_start[c + 1];
                int64_t cc[3];
                grid::cell_coords(g, c, cc);
                int64_t r0[9], r1[9];
                int64_t longest = 0;
                for (int64_t dx = -1; dx <= 1; ++dx)
                    for (int64_t dy = -1; dy <= 1; ++dy) {
                        const int64_t k = (dx + 1) * 3 + (dy + 1);
                        run_range(g, cc[0] + dx, cc[1] + dy, cc[2] - 1, cc[2] + 1, r0[k], r1[k]);
                        longest = std::max(longest, r1[k] - r0[k]);
                    }
                if (use512) {
                    cell_best.resize(size_t(last - first));
                    cell_min_d2_avx512(g.sx.data(), g.sy.data(), g.sz.data(), first, last, r0, r1, cell_best.data());
                } else {
                    dd.resize(size_t(longest));
                }
                const double x_lo = g.lo[0] + double(cc[0] - kReach) * g.h, x_hi = x_lo + g.h;
                const double y_lo = g.lo[1] + double(cc[1] - kReach) * g.h, y_hi = y_lo + g.h;
                for (int64_t s = first; s < last; ++s) {
                    const double x = g.sx[s], y = g.sy[s], z = g.sz[s];
                    double best;
                    if (use512) {
                        best = cell_best[size_t(s - first)];
                    } else {
                        auto fold = [&](int64_t k, double b) {
                            return min_other_d2(x, y, z, g.sx.data(), g.sy.data(), g.sz.data(), r0[k], r1[k], s, b,
                                                dd.data());
                        };
                        best = fold(4, std::numeric_limits<double>::infinity());
                        const double gx[3] = {std::max(0.0, x - x_lo - side_margin), 0.0,
                                              std::max(0.0, x_hi - x - side_margin)};
                        const double gy[3] = {std::max(0.0, y - y_lo - side_margin), 0.0,
                                              std::max(0.0, y_hi - y - side_margin)};
                        // the four sides, then the four corners
                        static constexpr int kOrder[8] = {1, 3, 5, 7, 0, 2, 6, 8};
                        for (const int k : kOrder) {
                            if (r1[k] == r0[k]) continue;
                            const double ax = gx[k / 3], ay = gy[k % 3];
                            if (ax * ax + ay * ay < best) best = fold(k, best);
                        }
                    }
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
