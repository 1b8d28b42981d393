// Register-blocked tiles of the dense-core product (masked_square.cpp):
//     c[t * ld + u] += sum_{r < kc} a[r * ld + t] * b[r * ld + u],   t < kMR, u < kNR<T>,
// i.e. one kMR x kNR tile of D^T D from kc rows of D. One template body; each instruction set instantiates
// it in its own translation unit, compiled for that set (dense_tiles_avx512.cpp, dense_tiles_avx2.cpp),
// and masked_square.cpp picks one at run time. No standard-library templates are instantiated in those
// units, so no code compiled for AVX-512 can be merged into code that runs on CPUs without it.
#pragma once
#include <cstdint>

namespace fastmac::tiles {

constexpr int64_t kMR = 8;
template <class T>
constexpr int64_t kNR = 128 / sizeof(T);  // two 64-byte vectors: 16 doubles or 32 floats

template <class T>
using TileFn = void (*)(const T *a, const T *b, int64_t kc, int64_t ld, T *c);

struct Kernels {
    TileFn<double> d = nullptr;
    TileFn<float> f = nullptr;
};

Kernels avx512_kernels();  // dense_tiles_avx512.cpp (x86-64 builds only)
Kernels avx2_kernels();    // dense_tiles_avx2.cpp

// The tile in slices of O::NV vectors of O::L lanes (kMR x NV accumulators): O provides the vector type V,
// L, NV and zero / load / set1 / fma / add_to.
template <class O>
inline void tile_slices(const typename O::T *a, const typename O::T *b, int64_t kc, int64_t ld,
                        typename O::T *c) {
    using T = typename O::T;
    using V = typename O::V;
    constexpr int64_t W = O::NV * O::L;
    for (int64_t s = 0; s < kNR<T>; s += W) {
        V acc[kMR][O::NV];
#pragma GCC unroll 8
        for (int t = 0; t < kMR; ++t)
#pragma GCC unroll 4
            for (int u = 0; u < O::NV; ++u) acc[t][u] = O::zero();
        for (int64_t r = 0; r < kc; ++r) {
            const T *ar = a + r * ld, *br = b + r * ld + s;
            V bv[O::NV];
#pragma GCC unroll 4
            for (int u = 0; u < O::NV; ++u) bv[u] = O::load(br + u * O::L);
#pragma GCC unroll 8
            for (int t = 0; t < kMR; ++t) {
                const V x = O::set1(ar[t]);
#pragma GCC unroll 4
                for (int u = 0; u < O::NV; ++u) acc[t][u] = O::fma(x, bv[u], acc[t][u]);
            }
        }
#pragma GCC unroll 8
        for (int t = 0; t < kMR; ++t)
#pragma GCC unroll 4
            for (int u = 0; u < O::NV; ++u) O::add_to(c + t * ld + s + u * O::L, acc[t][u]);
    }
}

}  // namespace fastmac::tiles
