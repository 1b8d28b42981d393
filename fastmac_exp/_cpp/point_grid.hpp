// Helpers of the core's uniform grids over point clouds (fpfh.cpp, resolution.cpp): cell keys packed into
// 64 bits, the cloud's lower corner, and a stable sort of (key, index) pairs.
#pragma once

#include <algorithm>
#include <cstdint>
#include <limits>
#include <utility>
#include <vector>

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
// (stable, so equal keys keep index order).
inline void sort_keyed(std::vector<std::pair<uint64_t, int64_t>> &v) {
    if (v.size() < 2048) {
        std::sort(v.begin(), v.end());
        return;
    }
    uint64_t all = 0;
    for (const auto &e : v) all |= e.first;
    std::vector<std::pair<uint64_t, int64_t>> tmp(v.size());
    for (int shift = 0; shift < 64 && (all >> shift); shift += 8) {
        int64_t count[257] = {0};
        for (const auto &e : v) ++count[((e.first >> shift) & 0xff) + 1];
        for (int b = 0; b < 256; ++b) count[b + 1] += count[b];
        for (const auto &e : v) tmp[count[(e.first >> shift) & 0xff]++] = e;
        v.swap(tmp);
    }
}

}  // namespace grid
}  // namespace fastmac
