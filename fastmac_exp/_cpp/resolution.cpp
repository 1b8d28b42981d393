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

#include "mac_core.hpp"
#include "parallel.hpp"
#include "point_grid.hpp"

namespace fastmac {

namespace {

struct Grid {
    double lo[3], h;
    std::vector<uint64_t> cell_key;    // occupied cells, ascending
    std::vector<int64_t> cell_start;   // ncell + 1
    std::vector<double> sorted;        // points in cell order
    std::vector<int64_t> order;        // sorted position -> input index
    std::vector<int64_t> cx;           // each input point's cell coordinates
};

// Occupied cells of size h (cells shifted so that every coordinate is >= kReach).
constexpr int64_t kReach = 1;
// Points an occupied cell aims at: gathering a cell's 27 neighbours is shared by its points, the distances
// are a vectorised loop: eight a cell took 25-40 ms on 120-300k-point scans where four took 27-61 ms.
constexpr double kPerCell = 8.0;

bool build(const double *p, int64_t n, double h, const double lo[3], Grid &g) {
    g.h = h;
    for (int d = 0; d < 3; ++d) g.lo[d] = lo[d];
    std::vector<std::pair<uint64_t, int64_t>> keyed(n);
    g.cx.resize(3 * n);
    for (int64_t i = 0; i < n; ++i) {
        for (int d = 0; d < 3; ++d) {
            const double f = std::floor((p[3 * i + d] - lo[d]) / h) + kReach;
            if (!(f < double(grid::kAxisMax / 2))) return false;
            g.cx[3 * i + d] = int64_t(f);
        }
        keyed[i] = {grid::pack(g.cx[3 * i], g.cx[3 * i + 1], g.cx[3 * i + 2]), i};
    }
    grid::sort_keyed(keyed);
    g.cell_key.clear();
    g.cell_start.clear();
    g.sorted.resize(3 * n);
    g.order.resize(n);
    for (int64_t k = 0; k < n; ++k) {
        if (k == 0 || keyed[k].first != keyed[k - 1].first) {
            g.cell_key.push_back(keyed[k].first);
            g.cell_start.push_back(k);
        }
        g.order[k] = keyed[k].second;
        for (int d = 0; d < 3; ++d) g.sorted[3 * k + d] = p[3 * keyed[k].second + d];
    }
    g.cell_start.push_back(n);
    return true;
}

// The points of the cells (x, y, z0..z1): one binary search for the run of consecutive keys.
template <class F>
void visit_run(const Grid &g, int64_t x, int64_t y, int64_t z0, int64_t z1, F &&f) {
    if (x < 0 || y < 0) return;
    z0 = std::max<int64_t>(z0, 0);
    if (z1 < z0) return;
    const uint64_t k0 = grid::pack(x, y, z0), k1 = grid::pack(x, y, z1);
    auto it = std::lower_bound(g.cell_key.begin(), g.cell_key.end(), k0);
    for (; it != g.cell_key.end() && *it <= k1; ++it) {
        const int64_t c = it - g.cell_key.begin();
        for (int64_t s = g.cell_start[c]; s < g.cell_start[c + 1]; ++s) f(s);
    }
}

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
        Grid gs;
        for (int round = 0; round < 6; ++round) {
            if (!build(sub.data(), ns, h, lo, gs)) break;
            const double per_cell = 16.0 * double(ns) / double(gs.cell_key.size());
            if (per_cell <= 8 * kPerCell) break;
            h *= std::max(0.25, std::sqrt(kPerCell / per_cell));
        }
    }
    Grid g;
    for (int round = 0; round < 4; ++round) {
        if (!build(p, n, h, lo, g)) {
            h *= 4.0;
            continue;
        }
        const double per_cell = double(n) / double(g.cell_key.size());
        if (per_cell >= kPerCell / 2 && per_cell <= kPerCell * 2) break;
        const double scale = std::sqrt(kPerCell / per_cell);
        if (round == 3 || std::fabs(scale - 1.0) < 0.05) break;
        h *= std::min(4.0, std::max(0.25, scale));
    }
    if (g.cell_key.empty() && !build(p, n, h, lo, g))
        throw std::invalid_argument("nearest_other_distances: the cloud spans too many cells");

    const int64_t ncell = int64_t(g.cell_key.size());
    nthreads = resolve_threads(nthreads, n);
    DynamicRange range(0, ncell, 64);
    parallel_region(nthreads, [&](int) {
        std::vector<double> qx, qy, qz, dd;
        std::vector<int64_t> qs;
        int64_t c0, c1;
        while (range.next(c0, c1)) {
            for (int64_t c = c0; c < c1; ++c) {
                const int64_t first = g.cell_start[c], last = g.cell_start[c + 1];
                const int64_t *cc = &g.cx[3 * g.order[first]];
                qx.clear(), qy.clear(), qz.clear(), qs.clear();
                int64_t own = 0;  // where the cell's own points start among the candidates
                for (int64_t dx = -1; dx <= 1; ++dx)
                    for (int64_t dy = -1; dy <= 1; ++dy)
                        visit_run(g, cc[0] + dx, cc[1] + dy, cc[2] - 1, cc[2] + 1, [&](int64_t s) {
                            if (s == first) own = int64_t(qs.size());
                            qx.push_back(g.sorted[3 * s]);
                            qy.push_back(g.sorted[3 * s + 1]);
                            qz.push_back(g.sorted[3 * s + 2]);
                            qs.push_back(s);
                        });
                const int64_t m = int64_t(qx.size());
                dd.resize(m);
                for (int64_t s = first; s < last; ++s) {
                    const double x = g.sorted[3 * s], y = g.sorted[3 * s + 1], z = g.sorted[3 * s + 2];
                    // the query itself sits at one position of the candidates: the minimum of both sides
                    const int64_t self = own + (s - first);
                    double best = min_other_d2(x, y, z, qx.data(), qy.data(), qz.data(), m, self, dd.data());
                    // rings 2, 3, ... while a point there could be closer (ring r is >= (r - 1) h away, less a
                    // hair for a point that rounding put in the next cell)
                    const double hh = g.h * (1.0 - 1e-9);
                    for (int64_t r = 2; !(best < double(r - 1) * hh * double(r - 1) * hh); ++r) {
                        if (r > 64) {  // an outlier far from everything: every point
                            for (int64_t t = 0; t < n; ++t) {
                                if (t == s) continue;
                                const double ex = x - g.sorted[3 * t], ey = y - g.sorted[3 * t + 1],
                                             ez = z - g.sorted[3 * t + 2];
                                best = std::min(best, ex * ex + ey * ey + ez * ez);
                            }
                            break;
                        }
                        auto take = [&](int64_t u) {
                            const double ex = x - g.sorted[3 * u], ey = y - g.sorted[3 * u + 1],
                                         ez = z - g.sorted[3 * u + 2];
                            best = std::min(best, ex * ex + ey * ey + ez * ez);
                        };
                        for (int64_t dx = -r; dx <= r; ++dx)
                            for (int64_t dy = -r; dy <= r; ++dy) {
                                if (std::max(std::abs(dx), std::abs(dy)) == r) {
                                    visit_run(g, cc[0] + dx, cc[1] + dy, cc[2] - r, cc[2] + r, take);
                                } else {  // only the two z ends of this column are in ring r
                                    visit_run(g, cc[0] + dx, cc[1] + dy, cc[2] - r, cc[2] - r, take);
                                    visit_run(g, cc[0] + dx, cc[1] + dy, cc[2] + r, cc[2] + r, take);
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
