// The FPFH front end in the core (fpfh.cpp): voxel keypoints, normals, SPFH and FPFH with Open3D's
// definitions and bins (Open3D 0.20's VoxelDownSample, EstimateNormals with a hybrid search,
// OrientNormalsTowardsCameraLocation and ComputeFPFHFeature are the reference; tests/test_fpfh_core.py
// holds them equal), and the exact feature matcher (feature_match.cpp).
#pragma once

#include <cstdint>
#include <memory>
#include <new>
#include <utility>
#include <vector>

namespace fastmac {

// Open3D's voxel_down_sample of the finite points: the centroid of the points of every occupied voxel of the
// grid anchored at
// min(points) - voxel / 2 (sums in input order, as Open3D). Keypoints are ordered by a scrambled voxel key
// (grid::scramble): deterministic, and like Open3D's hash-map order without spatial runs, so that no prefix
// or tie-break downstream sees one corner of the scene first. Throws std::invalid_argument when the cloud spans more
// than 2^21 voxels along an axis.
std::vector<double> voxel_downsample(const double *points, int64_t n, double voxel, int nthreads);

// A std::allocator that leaves new elements uninitialised (no memset of storage that is written before it
// is read).
template <class T>
struct NoInit : std::allocator<T> {
    template <class U>
    struct rebind {
        using other = NoInit<U>;
    };
    NoInit() = default;
    template <class U>
    NoInit(const NoInit<U> &) noexcept {}
    template <class U>
    void construct(U *p) noexcept {
        ::new (static_cast<void *>(p)) U;
    }
    template <class U, class... A>
    void construct(U *p, A &&...a) {
        ::new (static_cast<void *>(p)) U(std::forward<A>(a)...);
    }
};

// Neighbourhoods of a cloud within a radius, as Open3D's hybrid search returns them: the points with squared
// distance < radius^2 (the query itself included), nearest first (ties: lower index), at most max_nn.
// Point i's are idx/d2[ptr[i], end[i]): radius_neighbours gives each point max_nn slots (ptr[i] = i max_nn),
// written in place by the search, so nothing is zeroed or compacted; the slots past end[i] are unset.
struct Neighbours {
    std::vector<int64_t> ptr;  // n + 1: where each point's neighbours start (ptr[n]: the storage's size)
    std::vector<int64_t> end;  // n: where they end
    std::vector<int32_t, NoInit<int32_t>> idx;
    std::vector<double, NoInit<double>> d2;
};
Neighbours radius_neighbours(const double *points, int64_t n, double radius, int64_t max_nn, int nthreads);

// The ends of the neighbourhoods of a smaller radius and count within those of a larger one (their
// nearest-first prefixes): with nb's starts, the same lists as radius_neighbours(radius, max_nn) when
// radius <= nb's radius and max_nn <= nb's max_nn.
std::vector<int64_t> nearest_prefix(const Neighbours &nb, double radius, int64_t max_nn, int nthreads);

// Unit normals from the neighbourhoods idx[ptr[i], ends[i]) of nb (PCA: the eigenvector of the smallest
// eigenvalue of the covariance of >= 3 neighbours, else (0, 0, 1)), flipped towards `viewpoint` when it is
// given (Open3D's orient_normals_towards_camera_location); n x 3.
std::vector<double> pca_normals(const double *points, int64_t n, const Neighbours &nb, const int64_t *ends,
                                const double *viewpoint, int nthreads);

// Open3D's FPFH (33 bins: 11 for each of the three pair angles) of the rows `rows` (all when null) of a
// cloud with normals, from the neighbourhoods `nb` of the feature radius; rows x 33, row-major. SPFH is
// computed for every point that a described row reaches.
std::vector<double> fpfh_features(const double *points, const double *normals, int64_t n, const Neighbours &nb,
                                  const int64_t *rows, int64_t nrows, int nthreads);

// The whole front end of one keypoint cloud: the neighbourhoods (one search when the normals' is a prefix of
// the feature's), normals (unless `normals` comes filled, n x 3; filled on return) and the FPFH of `rows`
// (all when null), rows x 33. Works on the keypoints in the order of a grid of the feature radius, so that
// neighbours are near in memory whatever the keypoints' order; the results are in the caller's order.
std::vector<double> describe_fpfh(const double *keypoints, int64_t n, double normal_radius, int64_t normal_max_nn,
                                  double feature_radius, int64_t feature_max_nn, const double *viewpoint,
                                  const int64_t *rows, int64_t nrows, std::vector<double> &normals, int nthreads);

// Each row of x (rows x dim) divided by its Euclidean norm (rows of norm 0 left as they are), bit for bit as
// numpy's `x / np.linalg.norm(x, axis=1, keepdims=True)` (its pairwise sum of the squares), on the threads.
void unit_rows(double *x, int64_t rows, int64_t dim, int nthreads);

// Exact nearest rows in feature space, fast (feature_match.cpp): for every row of a (na x dim) the index of
// the nearest row of b (nb x dim), equal to nearest_rows' (the same float64 arithmetic decides, ties to the
// lowest index), and the squared distance to the runner-up in float64 (inf when nb < 2). Float32 products
// screen b (large b in tiles of similar rows, skipped where a triangle bound shows they hold neither), and
// the columns the float32 error bound cannot tell from the winner or the runner-up are compared in float64.
struct Matches {
    std::vector<int64_t> idx;
    std::vector<double> d2_second;
    int64_t settled_in_float64 = 0;  // rows whose winner the screen could not decide alone
};
Matches nearest_rows_fast(const double *a, int64_t na, const double *b, int64_t nb, int64_t dim, int nthreads);

// Each point's distance to its nearest other point (resolution.cpp; 0 for a repeated point).
std::vector<double> nearest_other_distances(const double *points, int64_t n, int nthreads);


}  // namespace fastmac
