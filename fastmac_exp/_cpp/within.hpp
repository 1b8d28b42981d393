// The trust test's counts in the core (within.cpp; fastmac_exp/geometry/trust.py): chance, the points of a
// cloud within a radius of each query, and the correspondences each of a set of poses explains.
#pragma once

#include <cstdint>
#include <vector>

namespace fastmac {

// For each of m queries, how many of the n points lie within `radius` (squared distance <= radius^2).
// Queries that are not finite count 0; a point that is not finite is refused.
std::vector<int64_t> count_within(const double *queries, int64_t m, const double *points, int64_t n, double radius,
                                  int nthreads);
// For each of h row-major 4 x 4 poses, how many of the n correspondences (src_i, tgt_i) it maps within
// `threshold` (|R s + t - q| < threshold).
std::vector<int64_t> explained_counts(const double *src, const double *tgt, int64_t n, const double *poses, int64_t h,
                                      double threshold, int nthreads);

}  // namespace fastmac
