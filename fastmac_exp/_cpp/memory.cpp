// Keeping freed memory for reuse (see mac_core.hpp: keep_freed_memory).
#include <cstdlib>
#include <string>

#if defined(__GLIBC__)
#include <malloc.h>
#endif

#include "mac_core.hpp"

namespace fastmac {

bool keep_freed_memory() {
    const char *env = std::getenv("FASTMAC_MALLOC_TUNE");
    if (env && std::string(env) == "0") return false;
#if defined(__GLIBC__) && defined(M_MMAP_THRESHOLD) && defined(M_TRIM_THRESHOLD)
    // Blocks up to 256 MiB come from the heap, and up to 512 MiB of free heap stay mapped.
    return mallopt(M_MMAP_THRESHOLD, 256 << 20) == 1 && mallopt(M_TRIM_THRESHOLD, 512 << 20) == 1;
#else
    return false;
#endif
}

}  // namespace fastmac
