// OpenMP when the compiler has it; the pragmas are ignored and these stubs used otherwise.
#pragma once
#ifdef _OPENMP
#include <omp.h>
#else
inline int omp_get_thread_num() { return 0; }
inline int omp_get_num_threads() { return 1; }
inline int omp_get_max_threads() { return 1; }
#endif
