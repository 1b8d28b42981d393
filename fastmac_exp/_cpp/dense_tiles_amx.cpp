// The dense-core tile in bfloat16 on AMX (Intel's tile registers: one TDPBF16PS is a 16 x 16 x 32
// product into float32, 8,192 multiply-adds; on a Xeon VM of this project 350-570 G a second on one core
// against 34-37 G for AVX512_BF16's VDPBF16PS, measured side by side). The same products of the same
// bfloat16 operands, summed in float32 in the hardware's own order inside an instruction: not the bits of
// the VDPBF16PS tile (~1e-6 relative on a sum of 512 products), but the same arithmetic class.
//
// CMakeLists.txt compiles this file with -mavx512f -mamx-tile -mamx-bf16 where the compiler has them. The CPU
// and the kernel are checked at run time: the CPU must list AMX-TILE and AMX-BF16, and Linux must grant the
// process the tile data state (arch_prctl ARCH_REQ_XCOMP_PERM, Linux >= 5.16); otherwise amx_tile() has no fn.
//
// Operands (dense_tiles.hpp, TileBf16 with kgroup 16): a holds 32 columns of D as [kc2 / 16][32][16] pairs
// (each A tile: 16 columns x 16 row pairs, 64 bytes a column), b the usual [kc2][32] pairs (each B tile: 16
// row pairs x 16 columns, read with a stride of 128 bytes). The tile configuration is loaded and released on
// every call, so no tile state outlives a call (another library in the thread may configure its own).
#include <immintrin.h>
#include <cpuid.h>
#include <cstdint>
#include <cstring>
#include <sys/syscall.h>
#include <unistd.h>

#include "dense_tiles.hpp"

namespace fastmac::tiles {
namespace {

constexpr int kRows = 32, kCols = 32;

struct TileConfig {
    uint8_t palette = 1, start_row = 0;
    uint8_t reserved[14] = {};
    uint16_t colsb[16] = {};
    uint8_t rows[16] = {};
};

void tile_amx(const uint32_t *a, const uint32_t *b, int64_t kc2, float *c, int64_t ldc) {
    TileConfig cfg;
    for (int t = 0; t < 8; ++t) cfg.colsb[t] = 64, cfg.rows[t] = 16;
    // GCC 12 may not see the configuration's bytes as read by LDTILECFG and drop their stores (seen in a
    // test program: a #GP on the half-written configuration); the barrier keeps them
    __asm__ volatile("" : : "r"(&cfg) : "memory");
    _tile_loadconfig(&cfg);
    // tiles 0-3: the 2 x 2 blocks of 16 x 16 sums; 4, 5: A (columns 0-15, 16-31); 6, 7: B (the same)
    _tile_zero(0);
    _tile_zero(1);
    _tile_zero(2);
    _tile_zero(3);
    for (int64_t g = 0; g < kc2 / 16; ++g) {
        const uint32_t *ag = a + g * kRows * 16, *bg = b + g * 16 * kCols;
        _tile_loadd(4, ag, 64);
        _tile_loadd(5, ag + 16 * 16, 64);
        _tile_loadd(6, bg, kCols * 4);
        _tile_loadd(7, bg + 16, kCols * 4);
        _tile_dpbf16ps(0, 4, 6);
        _tile_dpbf16ps(1, 4, 7);
        _tile_dpbf16ps(2, 5, 6);
        _tile_dpbf16ps(3, 5, 7);
    }
    alignas(64) float sums[4][16 * 16];
    _tile_stored(0, sums[0], 64);
    _tile_stored(1, sums[1], 64);
    _tile_stored(2, sums[2], 64);
    _tile_stored(3, sums[3], 64);
    _tile_release();
    for (int q = 0; q < 4; ++q)
        for (int t = 0; t < 16; ++t) {
            float *p = c + ((q >> 1) * 16 + t) * ldc + (q & 1) * 16;
            _mm512_storeu_ps(p, _mm512_add_ps(_mm512_loadu_ps(p), _mm512_load_ps(sums[q] + t * 16)));
        }
}

bool amx_granted() {
    unsigned eax, ebx, ecx, edx;
    if (!__get_cpuid_count(7, 0, &eax, &ebx, &ecx, &edx)) return false;
    const bool tile = (edx >> 24) & 1, bf16 = (edx >> 22) & 1;
    // AVX-512 as the rest of the core checks it (the OS's ZMM state included; the cpuid bit alone is not)
    if (!(tile && bf16 && __builtin_cpu_supports("avx512f"))) return false;
    constexpr long kReqXcompPerm = 0x1023, kXtiledata = 18;  // <asm/prctl.h>; not in older headers
    return syscall(SYS_arch_prctl, kReqXcompPerm, kXtiledata) == 0;
}

}  // namespace

TileBf16 amx_tile() {
    static const bool granted = amx_granted();  // once a process: the permission is the process's
    if (!granted) return {};
    return {tile_amx, kRows, kCols, 16};
}

}  // namespace fastmac::tiles
