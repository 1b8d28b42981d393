// BUFFER's patch preparation (fastmac_exp.descriptors.buffer: cut_patches, group_cells) in C++; the numpy
// versions there are the reference (tests/test_buffer_descriptor.py holds both equal).
#pragma once

#include <cstdint>
#include <vector>

namespace fastmac {

// out (m x k x 3): for keypoint j the first k - 1 points of `cloud` (n x 3, in index order) within
// `radius` (squared distance <= radius^2, as scipy's query_ball_point), padded with the keypoint, the
// keypoint itself in the last slot. Throws std::invalid_argument when the cloud spans more than 2^20
// cells of `radius` along an axis.
void buffer_cut_patches(const double *cloud, int64_t n, const double *keypoints, int64_t m, double radius,
                        int64_t k, double *out);

// The grid buffer_cut_patches searches, built once per cloud: the points of the prefixes [0, size) of the
// cloud (size = n, n/4, n/16, ... down to about 4 k; smallest first), each sorted by their cell of
// `radius` (index order within a cell), keys and indices of every level back to back.
struct PatchIndex {
    int64_t n = 0;
    double radius = 0.0;
    std::vector<int64_t> keys, order;
    std::vector<int64_t> level_start;  // levels + 1 offsets into keys / order
    std::vector<int64_t> level_size;   // the prefix length of each level
};
PatchIndex buffer_patch_index(const double *cloud, int64_t n, double radius, int64_t k);
// buffer_cut_patches on a prebuilt index of `cloud` (the same patches).
void buffer_cut_patches(const double *cloud, const PatchIndex &index, const double *keypoints, int64_t m,
                        int64_t k, double *out);

// out (m x ncell x ns x 3, zeroed here): upstream's sphere_query on aligned patches `pts` (m x p x 3,
// float32, units of des_r): per cell the first `ns` patch points in slot order with squared distance to
// the cell centre below r2 (float32 arithmetic as numpy's), patch slot 0 contributing zeros. Candidate
// cells per point from the CSR table (ptr over a g^3 grid of [-1, 1]^3, cells ascending in a voxel).
void buffer_group_cells(const float *pts, int64_t m, int64_t p, const float *centres, int64_t ncell, float r2,
                        const int64_t *ptr, const int16_t *cells, int64_t g, float inv_h, int64_t ns, float *out);

// SpinNet's sphere_query + var_to_invar on aligned patches `pts` (m x p x 3, float32, metres): per cell the
// first `ns` patch points in slot order with squared distance to the centre below r2, written as the
// offset from the centre rotated by `rot` (azi_n x 3 x 3, row-major; cell c takes rot[c % azi_n]); empty
// slots 0; a cell without a hit holds patch slot 0's rotated offset in its first slot (pointnet2's
// ball_query). The CSR table is over a g^3 grid of [-1, 1]^3 in units of 1 / to_unit (the descriptor radius).
void spinnet_group_cells(const float *pts, int64_t m, int64_t p, const float *centres, int64_t ncell, float r2,
                         const int64_t *ptr, const int16_t *cells, int64_t g, float to_unit, float inv_h, int64_t ns,
                         const float *rot, int64_t azi_n, float *out);

// spinnet_group_cells followed by SpinNet's point MLP without its bias and the max over each cell's slots,
// without the (m x ncell x ns x 3) grouped cells: out (m x ncell x nf) = per cell the max over its ns slots of
// slot . w (w: 3 x nf, row-major; the grouped slots as spinnet_group_cells writes them, the empty ones 0).
// The bias commutes with the max (rounding is monotone), so adding it afterwards gives the same values.
void spinnet_pool_cells(const float *pts, int64_t m, int64_t p, const float *centres, int64_t ncell, float r2,
                        const int64_t *ptr, const int16_t *cells, int64_t g, float to_unit, float inv_h, int64_t ns,
                        const float *rot, int64_t azi_n, const float *w, int64_t nf, float *out);

}  // namespace fastmac
