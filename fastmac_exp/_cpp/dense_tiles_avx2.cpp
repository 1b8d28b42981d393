// AVX2 dense-core tiles; CMakeLists.txt compiles this file with -mavx2 -mfma.
#define FASTMAC_W 256
#define FASTMAC_PD _mm256_
#define FASTMAC_PS _mm256_
#define FASTMAC_KERNELS avx2_kernels
#include "dense_tiles_simd.inc"
