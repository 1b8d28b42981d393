// Micro-kernels of the dense-core product (masked_square.cpp), on packed operands as in BLIS (Van Zee and
// van de Geijn, "BLIS: A Framework for Rapidly Instantiating BLAS Functionality", ACM TOMS 2015):
//     c[t * ldc + u] += sum_{r < kc} a[r * MR + t] * b[r * NR + u],   t < MR, u < NR,
// one MR x NR tile of D^T D from kc rows of D, where a is the packed micro-panel of D's columns i0..i0+MR-1
// (MR values per row, contiguous) and b that of columns j0..j0+NR-1. The MR x NR accumulators stay in
// vector registers; each row costs NR / lanes vector loads, MR broadcasts and MR * NR / lanes FMAs.
//
// One template body; each instruction set instantiates it in its own translation unit, compiled for that
// set (dense_tiles_avx512.cpp, dense_tiles_avx2.cpp), and masked_square.cpp picks one at run time. No
// standard-library templates are instantiated in those units, so no code compiled for AVX-512 can be
// merged into code that runs on CPUs without it.
#pragma once
#include <cstdint>

namespace fastmac::tiles {

template <class T>
using TileFn = void (*)(const T *a, const T *b, int64_t kc, T *c, int64_t ldc);

template <class T>
struct Tile {
    TileFn<T> fn = nullptr;
    int64_t mr = 0, nr = 0;  // the tile's rows (broadcast operand) and columns (vector operand)
};

struct Kernels {
    Tile<double> d;
    Tile<float> f;
};

// The bfloat16 tile: c[t * ldc + u] += sum_{r < kc2} sum_{h < 2} a_h[r * MR + t] * b_h[r * NR + u], where
// each uint32_t of a and b holds two bfloat16 values, rows 2r (low half, h = 0) and 2r + 1 (high half) of
// D: the packed micro-panels of the float tile with pairs of rows in place of rows.
using TileBf16Fn = void (*)(const uint32_t *a, const uint32_t *b, int64_t kc2, float *c, int64_t ldc);
// kgroup: how a holds its mr columns. 1: [kc2][mr] (the VDPBF16PS tile); 16: [kc2 / 16][mr][16], each column's
// 16 pairs contiguous (the AMX tile's A operand; kc2 then a multiple of 16).
struct TileBf16 {
    TileBf16Fn fn = nullptr;  // nullptr: not built (the compiler lacks AVX512_BF16), or not usable here
    int64_t mr = 0, nr = 0;
    int64_t kgroup = 1;
};

Kernels avx512_kernels();  // dense_tiles_avx512.cpp (x86-64 builds only)
TileBf16 bf16_tile();      // dense_tiles_bf16.cpp (x86-64 builds whose compiler has -mavx512bf16)
TileBf16 amx_tile();       // dense_tiles_amx.cpp (x86-64 builds whose compiler has -mamx-bf16)
Kernels avx2_kernels();    // dense_tiles_avx2.cpp

// The tile with MR x NV accumulators of O::L lanes: O provides the vector type V, L and zero / load /
// set1 / fma / add_to.
template <class O, int MR, int NV>
inline void tile_packed(const typename O::T *a, const typename O::T *b, int64_t kc, typename O::T *c,
                        int64_t ldc) {
    using V = typename O::V;
    constexpr int64_t NR = NV * O::L;
    V acc[MR][NV];
#pragma GCC unroll 16
    for (int t = 0; t < MR; ++t)
#pragma GCC unroll 4
        for (int u = 0; u < NV; ++u) acc[t][u] = O::zero();
    for (int64_t r = 0; r < kc; ++r) {
        const typename O::T *ar = a + r * MR, *br = b + r * NR;
        V bv[NV];
#pragma GCC unroll 4
        for (int u = 0; u < NV; ++u) bv[u] = O::load(br + u * O::L);
#pragma GCC unroll 16
        for (int t = 0; t < MR; ++t) {
            const V x = O::set1(ar[t]);
#pragma GCC unroll 4
            for (int u = 0; u < NV; ++u) acc[t][u] = O::fma(x, bv[u], acc[t][u]);
        }
    }
#pragma GCC unroll 16
    for (int t = 0; t < MR; ++t)
#pragma GCC unroll 4
        for (int u = 0; u < NV; ++u) O::add_to(c + t * ldc + u * O::L, acc[t][u]);
}

}  // namespace fastmac::tiles
