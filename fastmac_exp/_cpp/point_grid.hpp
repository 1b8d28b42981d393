// Helpers of the core's uniform grids over point clouds (fpfh.cpp, resolution.cpp): cell keys packed into
// 64 bits, the cloud's lower corner, and a stable sort of (key, index) pairs.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <utility>
#include <vector>

#include "parallel.hpp"

namespace fastmac {
namespace grid {

constexpr int64_t kAxisBits = 21;
constexpr int64_t kAxisMax = (int64_t(1) << kAxisBits) - 1;

inline uint64_t pack(int64_t x, int64_t y, int64_t z) {
    return (uint64_t(x) << (2 * kAxisBits)) | (uint64_t(y) << kAxisBits) | uint64_t(z);
}

// A bijection of 64-bit keys that scatters neighbouring cells (splitmix64's finaliser): sorting voxels by it
// gives a deterministic order with no spatial run in it, as Open3D's hash map gives.
inline uint64_t scramble(uint64_t x) {
    x ^= x >> 30;
    x *= 0xbf58476d1ce4e5b9ULL;
    x ^= x >> 27;
    x *= 0x94d049bb133111ebULL;
    x ^= x >> 31;
    return x;
}

inline void cloud_min(const double *p, int64_t n, double lo[3]) {
    lo[0] = lo[1] = lo[2] = std::numeric_limits<double>::infinity();
    for (int64_t i = 0; i < n; ++i)
        for (int d = 0; d < 3; ++d) lo[d] = std::min(lo[d], p[3 * i + d]);
}

// Sorts (key, index) pairs by key, then index: an LSD radix sort on the key's bytes that are used
// (stable, so equal keys keep index order). With nthreads > 1 on a large array, each pass counts and
// scatters fixed chunks in parallel (a chunk's entries keep their order within a digit, and the chunks
// theirs: the same stable order).
inline void sort_keyed(std::vector<std::pair<uint64_t, int64_t>> &v, int nthreads = 1) {
    if (v.size() < 2048) {
        std::sort(v.begin(), v.end());
        return;
    }
    uint64_t all = 0;
    for (const auto &e : v) all |= e.first;
    if (all == 0) return;
    // digits of up to 11 bits (2,048 counters stay in L1), as few passes as the key's used bits need:
    // a 26-bit voxel key takes 3 passes instead of 4 bytes
    const int bits = 64 - __builtin_clzll(all);
    const int passes = (bits + 10) / 11, digit = (bits + passes - 1) / passes;
    const uint64_t mask = (uint64_t(1) << digit) - 1;
    std::vector<std::pair<uint64_t, int64_t>> tmp(v.size());
    const int64_t n = int64_t(v.size());
    constexpr int64_t kParallelFrom = 65536, kChunks = 16;
    if (nthreads <= 1 || n < kParallelFrom) {
        std::vector<int64_t> count(size_t(mask) + 2);
        for (int shift = 0; shift < bits; shift += digit) {
            std::fill(count.begin(), count.end(), 0);
            for (const auto &e : v) ++count[((e.first >> shift) & mask) + 1];
            for (uint64_t b = 0; b <= mask; ++b) count[b + 1] += count[b];
            for (const auto &e : v) tmp[size_t(count[(e.first >> shift) & mask]++)] = e;
            v.swap(tmp);
        }
        return;
    }
    const int64_t buckets = int64_t(mask) + 1, per = (n + kChunks - 1) / kChunks;
    std::vector<int64_t> count(size_t(kChunks * buckets));
    for (int shift = 0; shift < bits; shift += digit) {
        std::fill(count.begin(), count.end(), 0);
        parallel_for(0, kChunks, nthreads, 1, [&](int64_t c, int) {
            int64_t *h = count.data() + c * buckets;
            for (int64_t k = c * per, e = std::min(n, k + per); k < e; ++k) ++h[(v[k].first >> shift) & mask];
        });
        int64_t at = 0;  // each (digit, chunk) starts after every smaller digit and, within its digit, the chunks before
        for (int64_t b = 0; b < buckets; ++b)
            for (int64_t c = 0; c < kChunks; ++c) {
                const int64_t m = count[c * buckets + b];
                count[c * buckets + b] = at;
                at += m;
            }
        parallel_for(0, kChunks, nthreads, 1, [&](int64_t c, int) {
            int64_t *h = count.data() + c * buckets;
            for (int64_t k = c * per, e = std::min(n, k + per); k < e; ++k) tmp[size_t(h[(v[k].first >> shift) & mask]++)] = v[k];
        });
        v.swap(tmp);
    }
}

// A grid of cubic cells of size h over a cloud (resolution.cpp's nearest distances, within.cpp's counts):
// the occupied cells by a dense key (x ny + y) nz + z, the points sorted by cell and stored by axis, so
// that the cells (x, y, z0..z1) are one contiguous range of positions (run_range). build_cells returns false
// when the cloud spans more than 2^20 cells along an axis.
struct CellGrid {
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

constexpr int64_t kReach = 1;  // cells shifted so that every coordinate is >= kReach
// The most (x, y) columns indexed densely (8 bytes each).
constexpr uint64_t kMaxColumns = uint64_t(1) << 22;

inline bool build_cells(const double *p, int64_t n, double h, const double lo[3], CellGrid &g, int nthreads = 1) {
    g.h = h;
    for (int d = 0; d < 3; ++d) g.lo[d] = lo[d];
    g.cx.resize(3 * n);
    // in blocks (the threads' share of a large cloud): each block's highest cell, and whether it left the range
    constexpr int64_t kBlock = 16384;
    const int64_t blocks = (n + kBlock - 1) / kBlock;
    std::vector<int64_t> block_top(3 * blocks, 0);
    std::vector<uint8_t> block_bad(blocks, 0);
    const int threads = n >= 4 * kBlock ? nthreads : 1;
    parallel_for(0, blocks, threads, 1, [&](int64_t b, int) {
        int64_t top[3] = {0, 0, 0};
        for (int64_t i = b * kBlock, e = std::min(n, i + kBlock); i < e; ++i) {
            for (int d = 0; d < 3; ++d) {
                const double f = std::floor((p[3 * i + d] - lo[d]) / h) + kReach;
                if (!(f < double(kAxisMax / 2))) {
                    block_bad[b] = 1;
                    return;
                }
                g.cx[3 * i + d] = int64_t(f);
                top[d] = std::max(top[d], int64_t(f));
            }
        }
        for (int d = 0; d < 3; ++d) block_top[3 * b + d] = top[d];
    });
    int64_t top[3] = {0, 0, 0};
    for (int64_t b = 0; b < blocks; ++b) {
        if (block_bad[b]) return false;
        for (int d = 0; d < 3; ++d) top[d] = std::max(top[d], block_top[3 * b + d]);
    }
    // a dense key, so that the radix sort makes as few passes as the grid needs; the cells a search can
    // reach (up to 64 rings beyond the cloud) fit in the extents, so any (x, y, z) of a search has one key
    const uint64_t margin = 2 * 64 + 2;
    const uint64_t nx = uint64_t(top[0]) + margin, ny = uint64_t(top[1]) + margin, nz = uint64_t(top[2]) + margin;
    if (double(nx) * double(ny) * double(nz) >= 9e18) return false;
    g.ny = ny, g.nz = nz;
    std::vector<std::pair<uint64_t, int64_t>> keyed(n);
    parallel_for(0, blocks, threads, 1, [&](int64_t b, int) {
        for (int64_t i = b * kBlock, e = std::min(n, i + kBlock); i < e; ++i) {
            const int64_t *c = &g.cx[3 * i];
            keyed[i] = {(uint64_t(c[0]) * ny + uint64_t(c[1])) * nz + uint64_t(c[2]), i};
        }
    });
    sort_keyed(keyed, threads);
    g.cell_key.clear();
    g.cell_start.clear();
    g.sx.resize(n), g.sy.resize(n), g.sz.resize(n);
    g.order.resize(n);
    for (int64_t k = 0; k < n; ++k)
        if (k == 0 || keyed[k].first != keyed[k - 1].first) {
            g.cell_key.push_back(keyed[k].first);
            g.cell_start.push_back(k);
        }
    parallel_for(0, blocks, threads, 1, [&](int64_t b, int) {
        for (int64_t k = b * kBlock, e = std::min(n, k + kBlock); k < e; ++k) {
            const int64_t i = keyed[k].second;
            g.order[k] = i;
            g.sx[k] = p[3 * i], g.sy[k] = p[3 * i + 1], g.sz[k] = p[3 * i + 2];
        }
    });
    g.cell_start.push_back(n);
    g.nx = nx;
    g.column.clear();
    return true;
}

// The column index of the grid the search uses (none when the columns are too many).
inline void index_columns(CellGrid &g) {
    g.column.clear();
    if (double(g.nx) * double(g.ny) >= double(kMaxColumns)) return;
    const uint64_t ncol = g.nx * g.ny;
    g.column.assign(ncol + 1, 0);
    for (const uint64_t key : g.cell_key) ++g.column[key / g.nz + 1];
    for (uint64_t c = 0; c < ncol; ++c) g.column[c + 1] += g.column[c];
}

// The (x, y, z) coordinates of occupied cell c, from its key (a point's cx, read through `order`, is a
// cache miss a cell on a large cloud).
inline void cell_coords(const CellGrid &g, int64_t c, int64_t out[3]) {
    const uint64_t key = g.cell_key[c], column = key / g.nz;
    out[0] = int64_t(column / g.ny), out[1] = int64_t(column % g.ny), out[2] = int64_t(key % g.nz);
}

// The sorted positions [s0, s1) of the points of the cells (x, y, z0..z1): consecutive keys, so one
// contiguous range; empty when none is occupied.
inline void run_range(const CellGrid &g, int64_t x, int64_t y, int64_t z0, int64_t z1, int64_t &s0, int64_t &s1) {
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

}  // namespace grid
}  // namespace fastmac
