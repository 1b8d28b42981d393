// AVX-512 dense-core tiles; CMakeLists.txt compiles this file with -mavx512f -mfma.
#define FASTMAC_W 512
#define FASTMAC_PD _mm512_
#define FASTMAC_PS _mm512_
#define FASTMAC_KERNELS avx512_kernels
#include "dense_tiles_simd.inc"
