// BUFFER's patch preparation (buffer_patches.hpp). numpy's version sorts a radius query's hits and groups
// points into cells by a sort over (keypoint, cell); here both are one pass per keypoint.
#include "buffer_patches.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <utility>
#include <vector>

namespace fastmac {

namespace {

constexpr int64_t kAxisBits = 21;
constexpr int64_t kAxisCells = int64_t(1) << (kAxisBits - 1);  // cells each side of the origin cell

int64_t cell_key(int64_t x, int64_t y, int64_t z) {
    return ((x + kAxisCells) << (2 * kAxisBits)) | ((y + kAxisCells) << kAxisBits) | (z + kAxisCells);
}

}  // namespace

PatchIndex buffer_patch_index(const double *cloud, int64_t n, double radius, int64_t k) {
    PatchIndex ix;
    ix.n = n;
    ix.radius = radius;
    const double inv = 1.0 / radius;
    std::vector<int64_t> key_of(n);
    for (int64_t i = 0; i < n; ++i) {
        int64_t c[3];
        for (int d = 0; d < 3; ++d) {
            const double f = std::floor(cloud[3 * i + d] * inv);
            if (!(std::fabs(f) < double(kAxisCells - 1)))
                throw std::invalid_argument("buffer_cut_patches: the cloud spans too many cells of the radius");
            c[d] = int64_t(f);
        }
        key_of[i] = cell_key(c[0], c[1], c[2]);
    }
    // prefixes n, n/4, n/16, ... down to about 4 k points, smallest first
    std::vector<int64_t> sizes{n};
    while (sizes.back() / 4 >= 4 * std::max<int64_t>(k, 1)) sizes.push_back(sizes.back() / 4);
    std::reverse(sizes.begin(), sizes.end());
    std::vector<std::pair<int64_t, int64_t>> keyed;
    for (const int64_t s : sizes) {
        keyed.resize(s);
        for (int64_t i = 0; i < s; ++i) keyed[i] = {key_of[i], i};
        std::sort(keyed.begin(), keyed.end());  // by cell, index order kept within a cell
        ix.level_start.push_back(int64_t(ix.keys.size()));
        ix.level_size.push_back(s);
        for (const auto &kv : keyed) ix.keys.push_back(kv.first), ix.order.push_back(kv.second);
    }
    ix.level_start.push_back(int64_t(ix.keys.size()));
    return ix;
}

void buffer_cut_patches(const double *cloud, const PatchIndex &ix, const double *keypoints, int64_t m,
                        int64_t k, double *out) {
    const double r2 = ix.radius * ix.radius;
    const double inv = 1.0 / ix.radius;
    const int64_t levels = int64_t(ix.level_size.size());
    std::vector<int64_t> hits;
    const int64_t take_max = k - 1;
    for (int64_t j = 0; j < m; ++j) {
        const double *q = keypoints + 3 * j;
        double *o = out + 3 * k * j;
        hits.clear();
        int64_t c[3];
        bool inside = true;
        for (int d = 0; d < 3; ++d) {
            const double f = std::floor(q[d] * inv);
            inside = inside && std::fabs(f) < double(kAxisCells - 2);
            c[d] = inside ? int64_t(f) : 0;
        }
        // the first k - 1 hits in index order: all lie in the smallest prefix [0, size) that holds k - 1
        // hits (every index in it is below every index outside it), so a dense ball reads a few thousand
        // points of a small prefix instead of every point of its 27 cells
        for (int64_t l = 0; inside && l < levels; ++l) {
            hits.clear();
            const int64_t *keys = ix.keys.data() + ix.level_start[l];
            const int64_t *order = ix.order.data() + ix.level_start[l];
            const int64_t *end = ix.keys.data() + ix.level_start[l + 1];
            for (int64_t dx = -1; dx <= 1; ++dx)
                for (int64_t dy = -1; dy <= 1; ++dy)
                    for (int64_t dz = -1; dz <= 1; ++dz) {
                        const int64_t key = cell_key(c[0] + dx, c[1] + dy, c[2] + dz);
                        const int64_t *lo = std::lower_bound(keys, end, key);
                        for (const int64_t *it = lo; it != end && *it == key; ++it) {
                            const int64_t i = order[it - keys];
                            const double *p = cloud + 3 * i;
                            const double ex = p[0] - q[0], ey = p[1] - q[1], ez = p[2] - q[2];
                            if (ex * ex + ey * ey + ez * ez <= r2) hits.push_back(i);
                        }
                    }
            if (int64_t(hits.size()) >= take_max) break;
        }
        int64_t take = int64_t(hits.size());
        if (take > take_max) {
            std::nth_element(hits.begin(), hits.begin() + take_max, hits.end());
            take = take_max;
        }
        std::sort(hits.begin(), hits.begin() + take);
        for (int64_t t = 0; t < take; ++t) std::memcpy(o + 3 * t, cloud + 3 * hits[t], 3 * sizeof(double));
        for (int64_t t = take; t < k; ++t) std::memcpy(o + 3 * t, q, 3 * sizeof(double));
    }
}

void buffer_cut_patches(const double *cloud, int64_t n, const double *keypoints, int64_t m, double radius,
                        int64_t k, double *out) {
    buffer_cut_patches(cloud, buffer_patch_index(cloud, n, radius, k), keypoints, m, k, out);
}

// The voxel of the cell table that holds point q (coordinates scaled by to_unit into the unit ball, then
// shifted by 1 and divided by the voxel size): numpy's astype(int32) truncation, clamped to the grid.
static inline int64_t cell_voxel(const float *q, float to_unit, float inv_h, int64_t g) {
    int64_t v[3];
    for (int d = 0; d < 3; ++d) {
        const float f = (q[d] * to_unit + 1.0f) * inv_h;
        const int64_t i = int64_t(int32_t(f));
        v[d] = std::min<int64_t>(std::max<int64_t>(i, 0), g - 1);
    }
    return (v[0] * g + v[1]) * g + v[2];
}

void buffer_group_cells(const float *pts, int64_t m, int64_t p, const float *centres, int64_t ncell, float r2,
                        const int64_t *ptr, const int16_t *cells, int64_t g, float inv_h, int64_t ns, float *out) {
    std::memset(out, 0, sizeof(float) * size_t(m * ncell * ns * 3));
    std::vector<int64_t> count(ncell);
    for (int64_t j = 0; j < m; ++j) {
        std::fill(count.begin(), count.end(), 0);
        float *o = out + j * ncell * ns * 3;
        int64_t run = 0;  // how many times in a row this point has come (the padding repeats the keypoint)
        for (int64_t s = 0; s < p; ++s) {
            const float *q = pts + (j * p + s) * 3;
            // a point repeated: each copy fills one more slot of every cell it is in that is not yet full,
            // so after ns copies all of them are full and further copies change nothing
            run = (s > 0 && q[0] == q[-3] && q[1] == q[-2] && q[2] == q[-1]) ? run + 1 : 1;
            if (run > ns) continue;
            const int64_t vox = cell_voxel(q, 1.0f, inv_h, g);  // q * 1.0f is q exactly
            for (int64_t t = ptr[vox]; t < ptr[vox + 1]; ++t) {
                const int64_t c = cells[t];
                if (count[c] >= ns) continue;
                const float dx = q[0] - centres[3 * c], dy = q[1] - centres[3 * c + 1], dz = q[2] - centres[3 * c + 2];
                const float d2 = dx * dx + dy * dy + dz * dz;
                if (d2 < r2) {
                    float *slot = o + (c * ns + count[c]) * 3;
                    if (s != 0) slot[0] = q[0], slot[1] = q[1], slot[2] = q[2];
                    ++count[c];
                }
            }
        }
    }
}

namespace {
// f[k] = max(f[k], v . w[:, k]) for the nf features (w: 3 x nf, row-major)
inline void max_features(float *f, const float v[3], const float *w, int64_t nf) {
    for (int64_t k = 0; k < nf; ++k) f[k] = std::max(f[k], v[0] * w[k] + v[1] * w[nf + k] + v[2] * w[2 * nf + k]);
}

inline void rotate(const float *r, float dx, float dy, float dz, float v[3]) {
    v[0] = r[0] * dx + r[1] * dy + r[2] * dz;
    v[1] = r[3] * dx + r[4] * dy + r[5] * dz;
    v[2] = r[6] * dx + r[7] * dy + r[8] * dz;
}

// SpinNet's ball query of keypoint j's aligned patch into its cells, rotated into each cell's frame:
// hit(c, k, v) for the k-th of at most ns samples of cell c, then, for every cell, done(c, count): a cell
// without a hit gets ball_query's patch slot 0 (its zero-initialised indices) as hit(c, 0, v) first.
template <class Hit, class Done>
void visit_cells(const float *base, int64_t p, const float *centres, int64_t ncell, float r2, const int64_t *ptr,
                 const int16_t *cells, int64_t g, float to_unit, float inv_h, int64_t ns, const float *rot,
                 int64_t azi_n, std::vector<int64_t> &count, Hit &&hit, Done &&done) {
    std::fill(count.begin(), count.end(), 0);
    for (int64_t s = 0; s < p; ++s) {
        const float *q = base + s * 3;
        const int64_t vox = cell_voxel(q, to_unit, inv_h, g);
        for (int64_t t = ptr[vox]; t < ptr[vox + 1]; ++t) {
            const int64_t c = cells[t];
            if (count[c] >= ns) continue;
            const float dx = q[0] - centres[3 * c], dy = q[1] - centres[3 * c + 1], dz = q[2] - centres[3 * c + 2];
            const float d2 = dx * dx + dy * dy + dz * dz;
            if (d2 < r2) {
                float v[3];
                rotate(rot + 9 * (c % azi_n), dx, dy, dz, v);
                hit(c, count[c], v);
                ++count[c];
            }
        }
    }
    for (int64_t c = 0; c < ncell; ++c) {
        if (count[c] == 0) {
            float v[3];
            rotate(rot + 9 * (c % azi_n), base[0] - centres[3 * c], base[1] - centres[3 * c + 1],
                   base[2] - centres[3 * c + 2], v);
            hit(c, 0, v);
        }
        done(c, count[c]);
    }
}
}  // namespace

void spinnet_group_cells(const float *pts, int64_t m, int64_t p, const float *centres, int64_t ncell, float r2,
                         const int64_t *ptr, const int16_t *cells, int64_t g, float to_unit, float inv_h, int64_t ns,
                         const float *rot, int64_t azi_n, float *out) {
    std::memset(out, 0, sizeof(float) * size_t(m * ncell * ns * 3));
    std::vector<int64_t> count(ncell);
    for (int64_t j = 0; j < m; ++j) {
        float *o = out + j * ncell * ns * 3;
        visit_cells(pts + j * p * 3, p, centres, ncell, r2, ptr, cells, g, to_unit, inv_h, ns, rot, azi_n, count,
                    [&](int64_t c, int64_t k, const float v[3]) { std::copy_n(v, 3, o + (c * ns + k) * 3); },
                    [](int64_t, int64_t) {});
    }
}

void spinnet_pool_cells(const float *pts, int64_t m, int64_t p, const float *centres, int64_t ncell, float r2,
                        const int64_t *ptr, const int16_t *cells, int64_t g, float to_unit, float inv_h, int64_t ns,
                        const float *rot, int64_t azi_n, const float *w, int64_t nf, float *out) {
    std::vector<int64_t> count(ncell);
    const float zero[3] = {0.0f, 0.0f, 0.0f};
    for (int64_t j = 0; j < m; ++j) {
        float *o = out + j * ncell * nf;
        std::fill(o, o + ncell * nf, -std::numeric_limits<float>::infinity());
        visit_cells(pts + j * p * 3, p, centres, ncell, r2, ptr, cells, g, to_unit, inv_h, ns, rot, azi_n, count,
                    [&](int64_t c, int64_t, const float v[3]) { max_features(o + c * nf, v, w, nf); },
                    [&](int64_t c, int64_t n) {  // the slots left empty hold zeros
                        if (n < ns && !(n == 0 && ns == 1)) max_features(o + c * nf, zero, w, nf);
                    });
    }
}

}  // namespace fastmac
