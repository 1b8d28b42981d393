// FPFH in the core (fpfh.hpp): the same keypoints, normals and histograms as Open3D's path in
// fastmac_exp/descriptors/fpfh.py, from one grid per radius instead of a k-d tree, and threaded.
//
// Open3D is the reference, so its arithmetic is followed where the result depends on it: the voxel
// centroid sums in input order; squared distances as ((dx^2 + dy^2) + dz^2) with a strict `< r^2`
// (nanoflann's radius search); neighbours nearest first; the covariance from raw cumulants; the
// eigenvector by the same closed form (Eberly's robust 3x3 eigensolver) and its branch order; the
// pair features, their bins and the weighted sum in Open3D's order of operations.
#include "fpfh.hpp"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>
#include <utility>

#if defined(__GNUC__) && defined(__x86_64__)
#include <immintrin.h>
#endif

#include "mac_core.hpp"
#include "parallel.hpp"
#include "point_grid.hpp"

namespace fastmac {

namespace {

using grid::cloud_min;
using grid::kAxisMax;
using grid::pack;
using grid::sort_keyed;

// A hit of a radius search as one integer, ordered as (squared distance, index): the bits of a
// non-negative double order as its value, so the sort compares integers (no NaN-aware compares).
using Hit = unsigned __int128;
using Hits = std::vector<Hit, NoInit<Hit>>;  // resized, then written: not zeroed
inline Hit make_hit(double d2, int32_t idx) {
    uint64_t bits;
    std::memcpy(&bits, &d2, 8);
    return (Hit(bits) << 32) | Hit(uint32_t(idx));
}
inline double hit_d2(Hit h) {
    const uint64_t bits = uint64_t(h >> 32);
    double d2;
    std::memcpy(&d2, &bits, 8);
    return d2;
}
inline int32_t hit_idx(Hit h) { return int32_t(uint32_t(h)); }

// A query's hits go into 128 slices of [0, r2) by squared distance (a counting sort; ~n / 128 a slice on a
// surface, where the hits are uniform in d^2)
constexpr int kSlices = 128;

// The `cap` nearest of a query's nh hits (squared distances dd in [0, r2), indices ii, slices sl), nearest
// first by (squared distance, index), into d2o and io; returns how many. The slices past the cap-th hit are
// dropped before an insertion sort, which has little left to do (a few hits a slice).
int64_t nearest_hits(const double *dd, const int32_t *ii, const int32_t *sl, int64_t nh, int64_t cap,
                     Hits &spare, double *d2o, int32_t *io) {
    int64_t keep;
    if (nh < 24) {
        spare.resize(nh);
        for (int64_t k = 0; k < nh; ++k) spare[k] = make_hit(dd[k], ii[k]);
        std::sort(spare.begin(), spare.end());
        keep = std::min(nh, cap);
    } else {
        int32_t bucket[kSlices + 1] = {};
        for (int64_t k = 0; k < nh; ++k) ++bucket[sl[k] + 1];
        for (int b = 0; b < kSlices; ++b) bucket[b + 1] += bucket[b];
        // the hits of the slices up to the one holding the cap-th nearest (all of them when nh <= cap)
        int last = kSlices - 1;
        if (nh > cap) {
            last = 0;
            while (last < kSlices - 1 && bucket[last + 1] < cap) ++last;
        }
        const int64_t m = bucket[last + 1];
        spare.resize(m);
        for (int64_t k = 0; k < nh; ++k) {
            const int b = sl[k];
            if (b <= last) spare[bucket[b]++] = make_hit(dd[k], ii[k]);
        }
        for (int64_t k = 1; k < m; ++k) {
            const Hit h = spare[k];
            int64_t j = k;
            while (j > 0 && spare[j - 1] > h) spare[j] = spare[j - 1], --j;
            spare[j] = h;
        }
        keep = std::min(m, cap);
    }
    for (int64_t k = 0; k < keep; ++k) {
        d2o[k] = hit_d2(spare[k]);
        io[k] = hit_idx(spare[k]);
    }
    return keep;
}

// --- the closed-form eigenvector of the smallest eigenvalue (Open3D's FastEigen3x3) ---------------------

struct V3 {
    double x, y, z;
};
inline V3 cross(const V3 &a, const V3 &b) {
    return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
inline double dot(const V3 &a, const V3 &b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline V3 scale(const V3 &a, double s) { return {a.x * s, a.y * s, a.z * s}; }
inline V3 divide(const V3 &a, double s) { return {a.x / s, a.y / s, a.z / s}; }
inline V3 sub(const V3 &a, const V3 &b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }

// A symmetric 3x3 matrix by its upper triangle.
struct Sym3 {
    double a00, a01, a02, a11, a12, a22;
};

// The unit null vector of A - eval I: the largest cross product of two of its rows.
V3 null_vector(const Sym3 &A, double eval) {
    const V3 r0{A.a00 - eval, A.a01, A.a02}, r1{A.a01, A.a11 - eval, A.a12}, r2{A.a02, A.a12, A.a22 - eval};
    const V3 c01 = cross(r0, r1), c02 = cross(r0, r2), c12 = cross(r1, r2);
    const double d0 = dot(c01, c01), d1 = dot(c02, c02), d2 = dot(c12, c12);
    int pick = 0;
    double best = d0;
    if (d1 > best) best = d1, pick = 1;
    if (d2 > best) pick = 2;
    if (pick == 0) return divide(c01, std::sqrt(d0));
    if (pick == 1) return divide(c02, std::sqrt(d1));
    return divide(c12, std::sqrt(d2));
}

// The eigenvector of eval1 orthogonal to the known eigenvector e0: the null vector of the 2x2 restriction
// of A - eval1 I to the plane orthogonal to e0.
V3 second_vector(const Sym3 &A, const V3 &e0, double eval1) {
    V3 U;
    if (std::fabs(e0.x) > std::fabs(e0.y)) {
        const double inv = 1 / std::sqrt(e0.x * e0.x + e0.z * e0.z);
        U = {-e0.z * inv, 0, e0.x * inv};
    } else {
        const double inv = 1 / std::sqrt(e0.y * e0.y + e0.z * e0.z);
        U = {0, e0.z * inv, -e0.y * inv};
    }
    const V3 V = cross(e0, U);
    const V3 AU{A.a00 * U.x + A.a01 * U.y + A.a02 * U.z, A.a01 * U.x + A.a11 * U.y + A.a12 * U.z,
                A.a02 * U.x + A.a12 * U.y + A.a22 * U.z};
    const V3 AV{A.a00 * V.x + A.a01 * V.y + A.a02 * V.z, A.a01 * V.x + A.a11 * V.y + A.a12 * V.z,
                A.a02 * V.x + A.a12 * V.y + A.a22 * V.z};
    double m00 = U.x * AU.x + U.y * AU.y + U.z * AU.z - eval1;
    double m01 = U.x * AV.x + U.y * AV.y + U.z * AV.z;
    double m11 = V.x * AV.x + V.y * AV.y + V.z * AV.z - eval1;
    const double a00 = std::fabs(m00), a01 = std::fabs(m01), a11 = std::fabs(m11);
    if (a00 >= a11) {
        if (std::max(a00, a01) <= 0) return U;
        if (a00 >= a01) {
            m01 /= m00;
            m00 = 1 / std::sqrt(1 + m01 * m01);
            m01 *= m00;
        } else {
            m00 /= m01;
            m01 = 1 / std::sqrt(1 + m00 * m00);
            m00 *= m01;
        }
        return sub(scale(U, m01), scale(V, m00));
    }
    if (std::max(a11, a01) <= 0) return U;
    if (a11 >= a01) {
        m01 /= m11;
        m11 = 1 / std::sqrt(1 + m01 * m01);
        m01 *= m11;
    } else {
        m11 /= m01;
        m01 = 1 / std::sqrt(1 + m11 * m11);
        m11 *= m01;
    }
    return sub(scale(U, m11), scale(V, m01));
}

// The eigenvector of the smallest eigenvalue of a covariance (zero for the zero matrix).
V3 smallest_eigenvector(Sym3 A) {
    const double mx = std::max({A.a00, A.a01, A.a02, A.a11, A.a12, A.a22});
    if (mx == 0) return {0, 0, 0};
    A = {A.a00 / mx, A.a01 / mx, A.a02 / mx, A.a11 / mx, A.a12 / mx, A.a22 / mx};
    const double off = A.a01 * A.a01 + A.a02 * A.a02 + A.a12 * A.a12;
    if (!(off > 0)) {  // diagonal: the axis of the strictly smallest entry, else z
        if (A.a00 < A.a11 && A.a00 < A.a22) return {1, 0, 0};
        if (A.a11 < A.a00 && A.a11 < A.a22) return {0, 1, 0};
        return {0, 0, 1};
    }
    const double q = (A.a00 + A.a11 + A.a22) / 3;
    const double b00 = A.a00 - q, b11 = A.a11 - q, b22 = A.a22 - q;
    const double p = std::sqrt((b00 * b00 + b11 * b11 + b22 * b22 + off * 2) / 6);
    const double c00 = b11 * b22 - A.a12 * A.a12;
    const double c01 = A.a01 * b22 - A.a12 * A.a02;
    const double c02 = A.a01 * A.a12 - b11 * A.a02;
    const double det = (b00 * c00 - A.a01 * c01 + A.a02 * c02) / (p * p * p);
    const double half_det = std::min(std::max(det * 0.5, -1.0), 1.0);
    const double angle = std::acos(half_det) / double(3);
    const double two_thirds_pi = 2.09439510239319549;
    const double beta2 = std::cos(angle) * 2;
    const double beta0 = std::cos(angle + two_thirds_pi) * 2;
    const double beta1 = -(beta0 + beta2);
    const double e0 = q + p * beta0, e1 = q + p * beta1, e2 = q + p * beta2;
    if (half_det >= 0) {
        const V3 v2 = null_vector(A, e2);
        if (e2 < e0 && e2 < e1) return v2;
        const V3 v1 = second_vector(A, v2, e1);
        if (e1 < e0 && e1 < e2) return v1;
        return cross(v1, v2);
    }
    const V3 v0 = null_vector(A, e0);
    if (e0 < e1 && e0 < e2) return v0;
    const V3 v1 = second_vector(A, v0, e1);
    if (e1 < e0 && e1 < e2) return v1;
    return cross(v0, v1);
}

// --- pair features and their bins ------------------------------------------------------------------------

inline int bin_of(double t) {  // t already scaled to [0, 11)
    int h = int(std::floor(t));
    return h < 0 ? 0 : (h >= 11 ? 10 : h);
}

// The three bins of the pair (p1, n1) -> (p2, n2), 0-10, 11-21 and 22-32 (Open3D's
// ComputePairFeatures and ComputeSPFHFeature, with its acos and atan2): the exact path for the pairs that
// pair_features' fast one leaves undecided.
inline void pair_bins(const double *p1, const double *n1, const double *p2, const double *n2, int bins[3]) {
    const double f0 = 0, f2 = 0;
    double f1 = 0;
    V3 dp{p2[0] - p1[0], p2[1] - p1[1], p2[2] - p1[2]};
    const double len = std::sqrt(dot(dp, dp));
    if (len != 0.0) {
        V3 a{n1[0], n1[1], n1[2]}, b{n2[0], n2[1], n2[2]};
        const double a1 = dot(a, dp) / len, a2 = dot(b, dp) / len;
        double f2c;
        if (std::acos(std::fabs(a1)) > std::acos(std::fabs(a2))) {
            std::swap(a, b);
            dp = {-dp.x, -dp.y, -dp.z};
            f2c = -a2;
        } else {
            f2c = a1;
        }
        V3 v = cross(dp, a);
        const double vn = std::sqrt(dot(v, v));
        if (vn != 0.0) {
            v = divide(v, vn);
            const V3 w = cross(a, v);
            f1 = dot(v, b);
            bins[0] = bin_of(11 * (std::atan2(dot(w, b), dot(a, b)) + M_PI) / (2.0 * M_PI));
            bins[1] = 11 + bin_of(11 * (f1 + 1.0) * 0.5);
            bins[2] = 22 + bin_of(11 * (f2c + 1.0) * 0.5);
            return;
        }
    }
    bins[0] = bin_of(11 * (f0 + M_PI) / (2.0 * M_PI));
    bins[1] = 11 + bin_of(11 * (f1 + 1.0) * 0.5);
    bins[2] = 22 + bin_of(11 * (f2 + 1.0) * 0.5);
}


#if defined(__GNUC__) && defined(__x86_64__) && !defined(__clang__)
#define FASTMAC_FPFH_CLONES __attribute__((target_clones("avx512f", "avx2", "default")))
#else
#define FASTMAC_FPFH_CLONES
#endif

// Per-thread buffers of spfh_of: the neighbours' points and normals by axis, and each pair's results.
struct PairScratch {
    std::vector<double> px, py, pz, nx, ny, nz, ok;
    std::vector<int32_t> b0, b1, b2;
    std::vector<double> sums;  // the running sums of 100 / m
    void resize(int64_t m) {
        for (auto *v : {&px, &py, &pz, &nx, &ny, &nz, &ok}) v->resize(m);
        for (auto *v : {&b0, &b1, &b2}) v->resize(m);
    }
};

// The three pair features of point 1 with each of m neighbours (pair_bins' arithmetic, branch-free so that
// it vectorises; built for AVX-512 and AVX2 besides the baseline, each lane doing the same IEEE operations).
// b0, b1, b2 are the bins (b0 from the polynomial atan; bin_of's floor and clamps, in a form that
// vectorises); ok[k] = 0 marks the pairs whose bins this cannot settle
// (coincident points, a swap decided by rounding, a degenerate frame, f0 within 1e-3 of a bin edge): those
// go through pair_bins.
FASTMAC_FPFH_CLONES
void pair_features(int64_t m, const double *p1, const double *n1, PairScratch &w) {
    const double ux = n1[0], uy = n1[1], uz = n1[2], qx = p1[0], qy = p1[1], qz = p1[2];
    const double *__restrict px = w.px.data(), *__restrict py = w.py.data(), *__restrict pz = w.pz.data();
    const double *__restrict nx = w.nx.data(), *__restrict ny = w.ny.data(), *__restrict nz = w.nz.data();
    int32_t *__restrict b0 = w.b0.data(), *__restrict b1 = w.b1.data(), *__restrict b2 = w.b2.data();
    double *__restrict ok = w.ok.data();
#pragma GCC ivdep
    for (int64_t k = 0; k < m; ++k) {
        const double dx0 = px[k] - qx, dy0 = py[k] - qy, dz0 = pz[k] - qz;
        const double len = std::sqrt(dx0 * dx0 + dy0 * dy0 + dz0 * dz0);
        const double mx = nx[k], my = ny[k], mz = nz[k];
        const double a1 = (ux * dx0 + uy * dy0 + uz * dz0) / len;
        const double a2 = (mx * dx0 + my * dy0 + mz * dz0) / len;
        const double gap = std::fabs(a2) - std::fabs(a1);
        const bool sw = gap > 0;
        const double ax = sw ? mx : ux, ay = sw ? my : uy, az = sw ? mz : uz;  // the frame's normal
        const double bx = sw ? ux : mx, by = sw ? uy : my, bz = sw ? uz : mz;  // the other normal
        // both arms computed before each select: GCC if-converts (vectorises) only selects of ready values
        const double mdx = -dx0, mdy = -dy0, mdz = -dz0, ma2 = -a2;
        const double dx = sw ? mdx : dx0, dy = sw ? mdy : dy0, dz = sw ? mdz : dz0;
        const double f2 = sw ? ma2 : a1;
        double vx = dy * az - dz * ay, vy = dz * ax - dx * az, vz = dx * ay - dy * ax;
        const double vn = std::sqrt(vx * vx + vy * vy + vz * vz);
        vx /= vn, vy /= vn, vz /= vn;
        const double wx = ay * vz - az * vy, wy = az * vx - ax * vz, wz = ax * vy - ay * vx;
        const double f1 = vx * bx + vy * by + vz * bz;
        const double y = wx * bx + wy * by + wz * bz, x = ax * bx + ay * by + az * bz;
        const double fx = std::fabs(x), fy = std::fabs(y);
        const bool steep = fy > fx;
        const double hi = steep ? fy : fx, lo = steep ? fx : fy;
        const double a = lo / hi, s2 = a * a;
        const double r0 = ((-0.0464964749 * s2 + 0.15931422) * s2 - 0.327622764) * s2 * a + a;
        const double r0c = M_PI_2 - r0;
        const double r1 = steep ? r0c : r0;
        const double r1c = M_PI - r1;
        const double r2 = x < 0 ? r1c : r1;
        const double r2n = -r2;
        const double r = y < 0 ? r2n : r2;
        const double t = 11 * (r + M_PI) / (2.0 * M_PI);
        // floor(t) for |t| < 2^51 by rounding through 1.5 * 2^52 (std::floor does not vectorise); NaN stays NaN
        const double rn = (t + 6755399441055744.0) - 6755399441055744.0;
        const double rn1 = rn - 1.0;
        const double fl = rn > t ? rn1 : rn;
        // NaN (coincident points, a degenerate frame) fails every comparison, so it lands on the exact path
        const bool plain = (t - fl > 1e-3) & (fl + 1 - t > 1e-3) & (std::fabs(gap) > 1e-12) & (vn > 0);
        // f1's and f2's bins: bin_of(11 * (f + 1) * 0.5), the floor as above; a plain pair's features are
        // finite, the others' bins are not used (set to 0 before the conversion, which NaN would not survive)
        const double t1 = 11 * (f1 + 1.0) * 0.5, t2 = 11 * (f2 + 1.0) * 0.5;
        const double rn_1 = (t1 + 6755399441055744.0) - 6755399441055744.0, rn_2 = (t2 + 6755399441055744.0) - 6755399441055744.0;
        const double rn_1m = rn_1 - 1.0, rn_2m = rn_2 - 1.0;
        const double fl1 = rn_1 > t1 ? rn_1m : rn_1, fl2 = rn_2 > t2 ? rn_2m : rn_2;
        const double c0 = fl < 0 ? 0.0 : (fl >= 11 ? 10.0 : fl);
        const double c1 = fl1 < 0 ? 0.0 : (fl1 >= 11 ? 10.0 : fl1);
        const double c2 = fl2 < 0 ? 0.0 : (fl2 >= 11 ? 10.0 : fl2);
        b0[k] = int32_t(plain ? c0 : 0.0);
        b1[k] = 11 + int32_t(plain ? c1 : 0.0);
        b2[k] = 22 + int32_t(plain ? c2 : 0.0);
        ok[k] = plain ? 1.0 : 0.0;
    }
}

// SPFH of point i (Open3D's ComputeSPFHFeature) over its m neighbours `nbr` (the point itself excluded), into
// h (zeroed). Open3D adds 100 / m to a bin once per pair: every term is the same, so a bin that k pairs reach
// holds the k-th running sum of 100 / m whatever the order. The bins are counted (in four interleaved
// tallies, so that repeated bins do not wait on one another), then take those sums: the same bits.
void spfh_of(const double *points, const double *normals, int64_t i, const int32_t *nbr, int64_t m,
             PairScratch &w, double *h) {
    w.resize(m);
    for (int64_t k = 0; k < m; ++k) {
        const double *p = &points[3 * int64_t(nbr[k])], *nn = &normals[3 * int64_t(nbr[k])];
        w.px[k] = p[0], w.py[k] = p[1], w.pz[k] = p[2];
        w.nx[k] = nn[0], w.ny[k] = nn[1], w.nz[k] = nn[2];
    }
    pair_features(m, &points[3 * i], &normals[3 * i], w);
    int32_t tally[4][33] = {};
    for (int64_t k = 0; k < m; ++k) {
        int32_t *t = tally[k & 3];
        if (w.ok[k] == 0.0) {
            const int64_t j = nbr[k];
            int bins[3];
            pair_bins(&points[3 * i], &normals[3 * i], &points[3 * j], &normals[3 * j], bins);
            ++t[bins[0]], ++t[bins[1]], ++t[bins[2]];
            continue;
        }
        ++t[w.b0[k]], ++t[w.b1[k]], ++t[w.b2[k]];
    }
    int32_t count[33], most = 0;
    for (int j = 0; j < 33; ++j) {
        count[j] = tally[0][j] + tally[1][j] + tally[2][j] + tally[3][j];
        most = std::max(most, count[j]);
    }
    w.sums.resize(size_t(most) + 1);
    const double incr = 100.0 / double(m);
    w.sums[0] = 0.0;
    for (int32_t c = 1; c <= most; ++c) w.sums[c] = w.sums[c - 1] + incr;
    for (int j = 0; j < 33; ++j) h[j] = w.sums[count[j]];
}

// Open3D's weighted sum of the neighbours' SPFH (1 / squared distance) and the sum of each third. The
// thirds are summed from the result, not term by term as Open3D does, so that the loop vectorises: the
// same value up to rounding (~1e-16 relative).
FASTMAC_FPFH_CLONES
void weighted_sum(const int32_t *nbr, const double *d2, int64_t m, const double *spfh, double *__restrict f,
                  double sum[3]) {
    for (int64_t k = 0; k < m; ++k) {
        const double dist = d2[k];
        if (dist == 0.0) continue;
        const double inv = 1.0 / dist;
        const double *__restrict s = &spfh[size_t(nbr[k]) * 33];
        for (int j = 0; j < 33; ++j) f[j] += s[j] * inv;
    }
    for (int j = 0; j < 33; ++j) sum[j / 11] += f[j];
}

// The candidates within r2 of (x, y, z): their squared distances ((dx^2 + dy^2) + dz^2, Open3D's order;
// -ffp-contract=off keeps FMA out) into dd, their indices into ii and their slices (nearest_hits) into sl,
// in candidate order; returns how many.
int64_t hits_within(double x, double y, double z, const double *__restrict qx, const double *__restrict qy,
                    const double *__restrict qz, const int32_t *__restrict qi, int64_t m, double r2,
                    double *__restrict dd, int32_t *__restrict ii, int32_t *__restrict sl) {
    const double scale = kSlices / r2;
    int64_t nh = 0;
    for (int64_t t = 0; t < m; ++t) {  // branch-free compaction
        const double ex = x - qx[t], ey = y - qy[t], ez = z - qz[t];
        const double d = ex * ex + ey * ey + ez * ez;
        dd[nh] = d;
        ii[nh] = qi[t];
        sl[nh] = std::min(kSlices - 1, int(d * scale));
        nh += d < r2;
    }
    return nh;
}

#if defined(__GNUC__) && defined(__x86_64__)
// hits_within by eight lanes of AVX-512: the same products and sums, the lanes within r2 compressed in a
// register and stored whole (dd needs 8 and ii 16 slots past the count; a compressing store to memory is
// microcoded on some cores).
__attribute__((target("avx512f"))) int64_t hits_within_avx512(double x, double y, double z, const double *qx,
                                                              const double *qy, const double *qz,
                                                              const int32_t *qi, int64_t m, double r2, double *dd,
                                                              int32_t *ii, int32_t *sl) {
    const __m512d px = _mm512_set1_pd(x), py = _mm512_set1_pd(y), pz = _mm512_set1_pd(z);
    const __m512d lim = _mm512_set1_pd(r2), scale = _mm512_set1_pd(kSlices / r2);
    const __m256i top = _mm256_set1_epi32(kSlices - 1);
    int64_t nh = 0;
    for (int64_t t = 0; t < m; t += 8) {
        const __mmask8 lanes = m - t >= 8 ? __mmask8(0xff) : __mmask8((1u << (m - t)) - 1u);
        const __m512d ex = _mm512_sub_pd(px, _mm512_maskz_loadu_pd(lanes, qx + t));
        const __m512d ey = _mm512_sub_pd(py, _mm512_maskz_loadu_pd(lanes, qy + t));
        const __m512d ez = _mm512_sub_pd(pz, _mm512_maskz_loadu_pd(lanes, qz + t));
        const __m512d d2 =
            _mm512_add_pd(_mm512_add_pd(_mm512_mul_pd(ex, ex), _mm512_mul_pd(ey, ey)), _mm512_mul_pd(ez, ez));
        const __mmask8 in = _mm512_mask_cmp_pd_mask(lanes, d2, lim, _CMP_LT_OQ);
        const __m512i idx = _mm512_maskz_loadu_epi32(__mmask16(lanes), qi + t);
        _mm512_storeu_pd(dd + nh, _mm512_maskz_compress_pd(in, d2));
        _mm512_storeu_si512(ii + nh, _mm512_maskz_compress_epi32(__mmask16(in), idx));
        const __m256i b = _mm256_min_epi32(_mm512_cvttpd_epi32(_mm512_mul_pd(d2, scale)), top);
        _mm512_storeu_si512(sl + nh, _mm512_maskz_compress_epi32(__mmask16(in), _mm512_castsi256_si512(b)));
        nh += __builtin_popcount(unsigned(in));
    }
    return nh;
}

// FASTMAC_FPFH_LOOPS=generic: the portable loop of the radius search (read each call, for tests and
// benchmarks)
bool fpfh_avx512() {
    static const bool cpu = __builtin_cpu_supports("avx512f");
    return cpu && !env_is("FASTMAC_FPFH_LOOPS", "generic");
}
#else
bool fpfh_avx512() { return false; }
int64_t hits_within_avx512(double, double, double, const double *, const double *, const double *,
                           const int32_t *, int64_t, double, double *, int32_t *, int32_t *) {
    return 0;
}
#endif

}  // namespace

std::vector<double> voxel_downsample(const double *points, int64_t n, double voxel, int nthreads) {
    if (!(voxel > 0)) throw std::invalid_argument("voxel_downsample: voxel must be positive");
    // the finite points (a row with a NaN or an infinity is dropped, as the Python front ends do)
    std::vector<int64_t> finite;
    finite.reserve(n);
    double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (int64_t i = 0; i < n; ++i) {
        const double *q = points + 3 * i;
        if (!(std::isfinite(q[0]) && std::isfinite(q[1]) && std::isfinite(q[2]))) continue;
        finite.push_back(i);
        for (int d = 0; d < 3; ++d) lo[d] = std::min(lo[d], q[d]), hi[d] = std::max(hi[d], q[d]);
    }
    n = int64_t(finite.size());
    if (n == 0) return {};
    for (int d = 0; d < 3; ++d) lo[d] -= voxel * 0.5;
    // voxel indices as one dense integer (as few radix passes as the grid needs); the output order comes
    // after, on the occupied voxels only
    uint64_t extent[3];
    for (int d = 0; d < 3; ++d) {
        const double f = std::floor((hi[d] - lo[d]) / voxel);
        if (!(f <= double(kAxisMax)))
            throw std::invalid_argument("voxel_downsample: the cloud spans more than 2^21 voxels along an axis");
        extent[d] = uint64_t(f) + 1;
    }
    std::vector<std::pair<uint64_t, int64_t>> keyed(n);
    nthreads = resolve_threads(nthreads, n);
    parallel_for(0, n, nthreads, 8192, [&](int64_t k, int) {
        const int64_t i = finite[k];
        uint64_t c[3];
        for (int d = 0; d < 3; ++d) {
            const double f = std::floor((points[3 * i + d] - lo[d]) / voxel);
            c[d] = std::min(uint64_t(f), extent[d] - 1);
        }
        keyed[k] = {(c[0] * extent[1] + c[1]) * extent[2] + c[2], i};
    });
    sort_keyed(keyed, nthreads);
    // centroids (sums in input order), each with its voxel's scrambled key for the output order
    std::vector<std::pair<uint64_t, int64_t>> order;
    std::vector<double> centre;
    for (int64_t s = 0; s < n;) {
        int64_t e = s + 1;
        while (e < n && keyed[e].first == keyed[s].first) ++e;
        double acc[3] = {0, 0, 0};
        for (int64_t k = s; k < e; ++k)
            for (int d = 0; d < 3; ++d) acc[d] += points[3 * keyed[k].second + d];
        for (int d = 0; d < 3; ++d) centre.push_back(acc[d] / double(e - s));
        const uint64_t key = keyed[s].first;
        const uint64_t z = key % extent[2], y = (key / extent[2]) % extent[1], x = key / extent[2] / extent[1];
        order.push_back({grid::scramble(pack(int64_t(x), int64_t(y), int64_t(z))), int64_t(order.size())});
        s = e;
    }
    sort_keyed(order);  // the scrambled keys are distinct: the same order as std::sort, by radix
    std::vector<double> out(centre.size());
    for (size_t k = 0; k < order.size(); ++k)
        std::copy_n(&centre[3 * order[k].second], 3, &out[3 * k]);
    return out;
}

Neighbours radius_neighbours(const double *points, int64_t n, double radius, int64_t max_nn, int nthreads) {
    if (!(radius > 0) || max_nn < 1) throw std::invalid_argument("radius_neighbours: radius > 0, max_nn >= 1");
    Neighbours out;
    out.ptr.assign(n + 1, 0);
    if (n == 0) return out;
    if (n > std::numeric_limits<int32_t>::max()) throw std::invalid_argument("radius_neighbours: too many points");
    double lo[3];
    cloud_min(points, n, lo);
    const double r2 = radius * radius;
    // the grid: cells of half the radius, so that a query's neighbours lie within two cells of its own
    // (5^3 cells of r / 2 hold 58 % of the points of 3^3 cells of r); point_grid.hpp's, whose points are
    // stored by axis in cell order, so that each of a cell's 25 runs of cells is one contiguous copy
    constexpr int64_t reach = 2;
    grid::CellGrid g;
    if (!grid::build_cells(points, n, radius / reach, lo, g))
        throw std::invalid_argument("radius_neighbours: the cloud spans more than 2^19 radii");
    grid::index_columns(g);
    const int64_t ncell = int64_t(g.cell_key.size());

    const int64_t cap = max_nn;
    out.idx.resize(size_t(n) * cap);  // uninitialised (NoInit): each query writes its own slots
    out.d2.resize(size_t(n) * cap);
    out.end.resize(n);
    for (int64_t i = 0; i <= n; ++i) out.ptr[i] = i * cap;
    nthreads = resolve_threads(nthreads, n);
    const bool use512 = fpfh_avx512();
    constexpr int kRuns = (2 * reach + 1) * (2 * reach + 1);
    DynamicRange range(0, ncell, 16);
    parallel_region(nthreads, [&](int) {
        // the 25 runs of cells' points, gathered per cell of queries (coordinates by axis, so that the
        // distance loop vectorises), then each query's hits sorted nearest first
        std::vector<double, NoInit<double>> qx, qy, qz, dd;
        std::vector<int32_t, NoInit<int32_t>> qi, ii, sl;
        Hits spare;
        int64_t c0, c1;
        int64_t s0[kRuns], s1[kRuns];
        while (range.next(c0, c1)) {
            for (int64_t c = c0; c < c1; ++c) {
                const int64_t first = g.cell_start[c];
                int64_t q[3];
                grid::cell_coords(g, c, q);
                int64_t nc = 0;
                int run = 0;
                for (int64_t dx = -reach; dx <= reach; ++dx)
                    for (int64_t dy = -reach; dy <= reach; ++dy, ++run) {
                        grid::run_range(g, q[0] + dx, q[1] + dy, q[2] - reach, q[2] + reach, s0[run], s1[run]);
                        nc += s1[run] - s0[run];
                    }
                qx.resize(nc), qy.resize(nc), qz.resize(nc), qi.resize(nc);
                for (int64_t r = 0, o = 0; r < kRuns; o += s1[r] - s0[r], ++r) {
                    const int64_t len = s1[r] - s0[r];
                    std::copy_n(&g.sx[s0[r]], len, qx.data() + o);
                    std::copy_n(&g.sy[s0[r]], len, qy.data() + o);
                    std::copy_n(&g.sz[s0[r]], len, qz.data() + o);
                    std::copy_n(&g.order[s0[r]], len, qi.data() + o);  // int64 -> int32: n < 2^31
                }
                dd.resize(nc + 8), ii.resize(nc + 16), sl.resize(nc + 16);
                for (int64_t s = first; s < g.cell_start[c + 1]; ++s) {
                    const int64_t nh =
                        use512 ? hits_within_avx512(g.sx[s], g.sy[s], g.sz[s], qx.data(), qy.data(), qz.data(),
                                                    qi.data(), nc, r2, dd.data(), ii.data(), sl.data())
                               : hits_within(g.sx[s], g.sy[s], g.sz[s], qx.data(), qy.data(), qz.data(), qi.data(),
                                             nc, r2, dd.data(), ii.data(), sl.data());
                    const int64_t i = g.order[s];
                    const int64_t keep = nearest_hits(dd.data(), ii.data(), sl.data(), nh, cap, spare,
                                                      &out.d2[size_t(i) * cap], &out.idx[size_t(i) * cap]);
                    out.end[i] = i * cap + keep;
                }
            }
        }
    });
    return out;
}

std::vector<int64_t> nearest_prefix(const Neighbours &nb, double radius, int64_t max_nn, int nthreads) {
    const int64_t n = int64_t(nb.end.size());
    const double r2 = radius * radius;
    std::vector<int64_t> ends(n);
    parallel_for(0, n, resolve_threads(nthreads, n), 2048, [&](int64_t i, int) {
        int64_t k = nb.ptr[i];
        const int64_t e = std::min(nb.end[i], nb.ptr[i] + max_nn);
        while (k < e && nb.d2[k] < r2) ++k;
        ends[i] = k;
    });
    return ends;
}

std::vector<double> pca_normals(const double *points, int64_t n, const Neighbours &nb, const int64_t *ends,
                                const double *viewpoint, int nthreads) {
    std::vector<double> normals(3 * n);
    nthreads = resolve_threads(nthreads, n);
    parallel_for(0, n, nthreads, 512, [&](int64_t i, int) {
        const int64_t b = nb.ptr[i], e = ends[i];
        V3 nrm;
        if (e - b >= 3) {
            double c[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
            for (int64_t k = b; k < e; ++k) {
                const double *p = &points[3 * nb.idx[k]];
                c[0] += p[0];
                c[1] += p[1];
                c[2] += p[2];
                c[3] += p[0] * p[0];
                c[4] += p[0] * p[1];
                c[5] += p[0] * p[2];
                c[6] += p[1] * p[1];
                c[7] += p[1] * p[2];
                c[8] += p[2] * p[2];
            }
            const double cnt = double(e - b);
            for (double &v : c) v /= cnt;
            const Sym3 cov{c[3] - c[0] * c[0], c[4] - c[0] * c[1], c[5] - c[0] * c[2],
                           c[6] - c[1] * c[1], c[7] - c[1] * c[2], c[8] - c[2] * c[2]};
            nrm = smallest_eigenvector(cov);
        } else {
            nrm = {0, 0, 1};  // Open3D gives fewer than 3 neighbours the identity covariance, whose normal is z
        }
        if (dot(nrm, nrm) == 0.0) nrm = {0, 0, 1};
        if (viewpoint) {
            const V3 ref{viewpoint[0] - points[3 * i], viewpoint[1] - points[3 * i + 1],
                         viewpoint[2] - points[3 * i + 2]};
            if (dot(nrm, ref) < 0.0) nrm = {-nrm.x, -nrm.y, -nrm.z};
        }
        normals[3 * i] = nrm.x;
        normals[3 * i + 1] = nrm.y;
        normals[3 * i + 2] = nrm.z;
    });
    return normals;
}

std::vector<double> fpfh_features(const double *points, const double *normals, int64_t n, const Neighbours &nb,
                                  const int64_t *rows, int64_t nrows, int nthreads) {
    if (!rows) nrows = n;
    for (int64_t r = 0; rows && r < nrows; ++r)
        if (rows[r] < 0 || rows[r] >= n) throw std::invalid_argument("fpfh_features: a row is out of range");
    nthreads = resolve_threads(nthreads, n);
    // SPFH of every point a described row reaches (all of them when every row is described)
    std::vector<unsigned char> need(n, rows ? 0 : 1);
    if (rows)
        for (int64_t r = 0; r < nrows; ++r) {
            const int64_t i = rows[r];
            need[i] = 1;
            for (int64_t k = nb.ptr[i]; k < nb.end[i]; ++k) need[nb.idx[k]] = 1;
        }
    // rows not needed are never read: left unset (NoInit), the others zeroed by the thread that fills them
    std::vector<double, NoInit<double>> spfh(size_t(n) * 33);
    DynamicRange spfh_range(0, n, 256);
    parallel_region(nthreads, [&](int) {
        PairScratch w;
        int64_t lo, hi;
        while (spfh_range.next(lo, hi))
            for (int64_t i = lo; i < hi; ++i) {
                if (!need[i]) continue;
                std::fill_n(&spfh[size_t(i) * 33], 33, 0.0);
                const int64_t b = nb.ptr[i], e = nb.end[i];
                if (e - b <= 1) continue;
                spfh_of(points, normals, i, &nb.idx[b + 1], e - b - 1, w, &spfh[size_t(i) * 33]);
            }
    });
    std::vector<double> out(size_t(nrows) * 33, 0.0);
    parallel_for(0, nrows, nthreads, 256, [&](int64_t r, int) {
        const int64_t i = rows ? rows[r] : r;
        const int64_t b = nb.ptr[i], e = nb.end[i];
        if (e - b <= 1) return;
        double *f = &out[size_t(r) * 33];
        double sum[3] = {0.0, 0.0, 0.0};
        weighted_sum(&nb.idx[b + 1], &nb.d2[b + 1], e - b - 1, spfh.data(), f, sum);
        for (double &s : sum)
            if (s != 0.0) s = 100.0 / s;
        const double *own = &spfh[size_t(i) * 33];
        for (int j = 0; j < 33; ++j) {
            f[j] *= sum[j / 11];
            f[j] += own[j];
        }
    });
    return out;
}

namespace {

// numpy's pairwise summation (DOUBLE_pairwise_sum: eight running sums up to 128 terms, halves above) of
// the squares a[i] * a[i], term for term, so that a norm equals np.linalg.norm's (the build has no FMA
// contraction, so each square is rounded before it is added, as numpy's x * x is).
double numpy_sum_of_squares(const double *a, int64_t n) {
    if (n < 8) {
        double res = -0.0;
        for (int64_t i = 0; i < n; ++i) res += a[i] * a[i];
        return res;
    }
    if (n <= 128) {
        double r[8];
        for (int j = 0; j < 8; ++j) r[j] = a[j] * a[j];
        int64_t i = 8;
        for (; i < n - (n % 8); i += 8)
            for (int j = 0; j < 8; ++j) r[j] += a[i + j] * a[i + j];
        double res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
        for (; i < n; ++i) res += a[i] * a[i];
        return res;
    }
    int64_t half = n / 2;
    half -= half % 8;
    return numpy_sum_of_squares(a, half) + numpy_sum_of_squares(a + half, n - half);
}

}  // namespace

void unit_rows(double *x, int64_t rows, int64_t dim, int nthreads) {
    nthreads = resolve_threads(nthreads, rows);
    parallel_for(0, rows, nthreads, 512, [&](int64_t r, int) {
        double *row = x + r * dim;
        const double norm = std::sqrt(numpy_sum_of_squares(row, dim));
        if (norm > 0)
            for (int64_t j = 0; j < dim; ++j) row[j] /= norm;
    });
}

std::vector<double> describe_fpfh(const double *keypoints, int64_t n, double normal_radius, int64_t normal_max_nn,
                                  double feature_radius, int64_t feature_max_nn, const double *viewpoint,
                                  const int64_t *rows, int64_t nrows, std::vector<double> &normals, int nthreads) {
    if (!(feature_radius > 0)) throw std::invalid_argument("describe_fpfh: the feature radius must be positive");
    for (int64_t r = 0; rows && r < nrows; ++r)
        if (rows[r] < 0 || rows[r] >= n) throw std::invalid_argument("describe_fpfh: a row is out of range");
    // the keypoints in grid order (cells of the feature radius, index order within a cell)
    double lo[3];
    cloud_min(keypoints, n, lo);
    std::vector<std::pair<uint64_t, int64_t>> keyed(n);
    for (int64_t i = 0; i < n; ++i) {
        int64_t c[3];
        for (int d = 0; d < 3; ++d) {
            const double f = std::floor((keypoints[3 * i + d] - lo[d]) / feature_radius);
            c[d] = f < double(kAxisMax) ? int64_t(f) : kAxisMax;
        }
        keyed[i] = {pack(c[0], c[1], c[2]), i};
    }
    sort_keyed(keyed);
    std::vector<int64_t> pos(n);  // caller's index -> grid position
    std::vector<double> kp(3 * n), nin;
    const bool given = !normals.empty();
    if (given) nin.resize(3 * n);
    for (int64_t k = 0; k < n; ++k) {
        const int64_t i = keyed[k].second;
        pos[i] = k;
        for (int d = 0; d < 3; ++d) {
            kp[3 * k + d] = keypoints[3 * i + d];
            if (given) nin[3 * k + d] = normals[3 * i + d];
        }
    }
    std::vector<int64_t> sel;
    if (rows) {
        sel.resize(nrows);
        for (int64_t r = 0; r < nrows; ++r) sel[r] = pos[rows[r]];
    }
    const Neighbours fn = radius_neighbours(kp.data(), n, feature_radius, feature_max_nn, nthreads);
    if (!given) {
        if (normal_radius <= feature_radius && normal_max_nn <= feature_max_nn) {
            const std::vector<int64_t> ends = nearest_prefix(fn, normal_radius, normal_max_nn, nthreads);
            nin = pca_normals(kp.data(), n, fn, ends.data(), viewpoint, nthreads);
        } else {
            const Neighbours nn = radius_neighbours(kp.data(), n, normal_radius, normal_max_nn, nthreads);
            nin = pca_normals(kp.data(), n, nn, nn.end.data(), viewpoint, nthreads);
        }
    }
    std::vector<double> feat =
        fpfh_features(kp.data(), nin.data(), n, fn, rows ? sel.data() : nullptr, rows ? nrows : n, nthreads);
    normals.resize(3 * n);
    for (int64_t i = 0; i < n; ++i)
        for (int d = 0; d < 3; ++d) normals[3 * i + d] = nin[3 * pos[i] + d];
    if (!rows) {  // every row, back in the caller's order
        std::vector<double> out(feat.size());
        for (int64_t i = 0; i < n; ++i) std::copy_n(&feat[size_t(pos[i]) * 33], 33, &out[size_t(i) * 33]);
        return out;
    }
    return feat;
}

}  // namespace fastmac
