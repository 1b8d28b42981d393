// The dense-core tile in bfloat16 with float32 sums (AVX512_BF16's VDPBF16PS: two products a lane per
// instruction, twice the multiply-adds of an FMA; 115 against 59 G a second on one Zen 4 core, measured).
// CMakeLists.txt compiles this file with -mavx512f -mavx512bf16 where the compiler has them; the CPU is
// checked at run time (masked_square.cpp). The operands are packed in pairs of rows (see TileBf16 in
// dense_tiles.hpp).
#include <immintrin.h>

#include "dense_tiles.hpp"

namespace fastmac::tiles {
namespace {

constexpr int kRows = 12, kVectors = 2;  // as the float tile: 12 x 2 accumulators of 16 lanes

void tile_bf16(const uint32_t *a, const uint32_t *b, int64_t kc2, float *c, int64_t ldc) {
    __m512 acc[kRows][kVectors];
#pragma GCC unroll 16
    for (int t = 0; t < kRows; ++t)
        for (int u = 0; u < kVectors; ++u) acc[t][u] = _mm512_setzero_ps();
    for (int64_t r = 0; r < kc2; ++r) {
        const uint32_t *ar = a + r * kRows, *br = b + r * kVectors * 16;
        __m512bh bv[kVectors];
        for (int u = 0; u < kVectors; ++u) bv[u] = (__m512bh)_mm512_loadu_si512(br + u * 16);
#pragma GCC unroll 16
        for (int t = 0; t < kRows; ++t) {
            const __m512bh x = (__m512bh)_mm512_set1_epi32((int)ar[t]);
            for (int u = 0; u < kVectors; ++u) acc[t][u] = _mm512_dpbf16_ps(acc[t][u], x, bv[u]);
        }
    }
#pragma GCC unroll 16
    for (int t = 0; t < kRows; ++t)
        for (int u = 0; u < kVectors; ++u) {
            float *p = c + t * ldc + u * 16;
            _mm512_storeu_ps(p, _mm512_add_ps(_mm512_loadu_ps(p), acc[t][u]));
        }
}

}  // namespace

TileBf16 bf16_tile() { return {tile_bf16, kRows, kVectors * 16}; }

}  // namespace fastmac::tiles
