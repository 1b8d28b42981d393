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
    uint64_t nx = 0, ny = 0, nz = 0;   // extents of the dense cell key (x ny + y) nz + z
    std::vector<uint64_t> cell_key;    // occupied cells, ascending
    std::vector<int64_t> cell_start;   // ncell + 1
    std::vector<double> sx, sy, sz;    // points in cell order, by axis (a run of cells is a contiguous range)
    std::vector<int64_t> order;        // sorted position -> input index
    std::vector<int64_t> cx;           // each input point's cell coordinates
    // where the occupied cells of each (x, y) column start among cell_key (nx ny + 1 entries), when the
    // columns are few enough to index densely; else a column is found by binary search
    std::vector<int64_t> column;
};

// Occupied cells of size h (cells shifted so that every coordinate is >= kReach).
constexpr int64_t kReach = 1;
// Points an occupied cell aims at: gathering a cell's 27 neighbours is shared by its points, the distances
// are a vectorised loop: eight a cell took 25-40 ms on 120-300k-point scans where four took 27-61 ms.
constexpr double kPerCell = 8.0;
// The most (x, y) columns indexed densely (8 bytes each).
constexpr uint64_t kMaxColumns = uint64_t(1) << 22;

bool build(const double *p, int64_t n, double h, const double lo[3], Grid &g) {
    g.h = h;
    for (int d = 0; d < 3; ++d) g.lo[d] = lo[d];
    g.cx.resize(3 * n);
    int64_t top[3] = {0, 0, 0};
    for (int64_t i = 0; i < n; ++i) {
        for (int d = 0; d < 3; ++d) {
            const double f = std::floor((p[3 * i + d] - lo[d]) / h) + kReach;
            if (!(f < double(grid::kAxisMax / 2))) return false;
            g.cx[3 * i + d] = int64_t(f);
            top[d] = std::max(top[d], int64_t(f));
        }
    }
    // a dense key, so that the radix sort makes as few passes as the grid needs; the cells a search can
    // reach (up to 64 rings beyond the cloud) fit in the extents, so any (x, y, z) of a search has one key
    const uint64_t margin = 2 * 64 + 2;
    const uint64_t nx = uint64_t(top[0]) + margin, ny = uint64_t(top[1]) + margin, nz = uint64_t(top[2]) + margin;
    if (double(nx) * double(ny) * double(nz) >= 9e18) return false;
    g.ny = ny, g.nz = nz;
    std::vector<std::pair<uint64_t, int64_t>> keyed(n);
    for (int64_t i = 0; i < n; ++i) {
        const int64_t *c = &g.cx[3 * i];
        keyed[i] = {(uint64_t(c[0]) * ny + uint64_t(c[1])) * nz + uint64_t(c[2]), i};
    }
    grid::sort_keyed(keyed);
    g.cell_key.clear();
    g.cell_start.clear();
    g.sx.resize(n), g.sy.resize(n), g.sz.resize(n);
    g.order.resize(n);
    for (int64_t k = 0; k < n; ++k) {
        if (k == 0 || keyed[k].first != keyed[k - 1].first) {
            g.cell_key.push_back(keyed[k].first);
            g.cell_start.push_back(k);
        }
        const int64_t i = keyed[k].second;
        g.order[k] = i;
        g.sx[k] = p[3 * i], g.sy[k] = p[3 * i + 1], g.sz[k] = p[3 * i + 2];
    }
    g.cell_start.push_back(n);
    g.nx = nx;
    g.column.clear();
    return true;
}

// The column index of the grid the search uses (none when the columns are too many).
void index_columns(Grid &g) {
    g.column.clear();
    if (double(g.nx) * double(g.ny) >= double(kMaxColumns)) return;
    const uint64_t ncol = g.nx * g.ny;
    g.column.assign(ncol + 1, 0);
    for (const uint64_t key : g.cell_key) ++g.column[key / g.nz + 1];
    for (uint64_t c = 0; c < ncol; ++c) g.column[c + 1] += g.column[c];
}

// The sorted positions [s0, s1) of the points of the cells (x, y, z0..z1): consecutive keys, so one
// contiguous range; empty when none is occupied.
inline void run_range(const Grid &g, int64_t x, int64_t y, int64_t z0, int64_t z1, int64_t &s0, int64_t &s1) {
    s0 = s1 = 0;
    if (x < 0 || y < 0) return;
    z0 = std::max<int64_t>(z0, 0);
    if (z1 < z0) return;
    const uint64_t col = uint64_t(x) * g.ny + uint64_t(y);
    const uint64_t k0 = col * g.nz + uint64_t(z0), k1 = col * g.nz + uint64_t(z1);
    int64_t c0, c1;
    if (!g.column.empty()) {  // the column's few cells, walked
        c0 = g.column[col];
        const int64_t ce = g.column[col + 1];
        while (c0 < ce && g.cell_key[c0] < k0) ++c0;
        c1 = c0;
        while (c1 < ce && g.cell_key[c1] <= k1) ++c1;
    } else {
        c0 = std::lower_bound(g.cell_key.begin(), g.cell_key.end(), k0) - g.cell_key.begin();
        c1 = std::upper_bound(g.cell_key.begin() + c0, g.cell_key.end(), k1) - g.cell_key.begin();
    }
    if (c1 > c0) s0 = g.cell_start[c0], s1 = g.cell_start[c1];
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
    index_columns(g);

    const int64_t ncell = int64_t(g.cell_key.size());
    nthreads = resolve_threads(nthreads, n);
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
                    double best = min_other_d2(x, y, z, qx.data(), qy.data(), qz.data(), m, self, dd.data());
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
