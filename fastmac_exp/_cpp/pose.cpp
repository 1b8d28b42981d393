// Kabsch fits (spec 5.1, 5.3) with a one-sided Jacobi SVD of the 3x3 cross-covariance, and the MAE
// hypothesis score (spec 5.2).
#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <string>

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#endif

#include "mac_core.hpp"

namespace fastmac {

Pose identity_pose() {
    Pose T{};
    T.R[0] = T.R[4] = T.R[8] = 1.0;
    return T;
}

namespace {

inline void cross(const double *a, const double *b, double *c) {
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}
inline double dot3(const double *a, const double *b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
inline double norm3(const double *a) { return std::sqrt(dot3(a, a)); }

// A unit vector orthogonal to the unit vector a.
void any_orthogonal(const double *a, double *out) {
    const double ax = std::fabs(a[0]), ay = std::fabs(a[1]), az = std::fabs(a[2]);
    double e[3] = {0, 0, 0};
    if (ax <= ay && ax <= az)
        e[0] = 1;
    else if (ay <= az)
        e[1] = 1;
    else
        e[2] = 1;
    cross(a, e, out);
    const double nn = norm3(out);
    for (int k = 0; k < 3; ++k) out[k] /= nn;
}

// R from H (row-major 3x3, H = sum (p - pbar)(q - qbar)^T): with H = U S V^T, R = V diag(1, 1, d) U^T,
// d = sign det(V U^T). Equivalently R = v1 u1^T + v2 u2^T + (v1 x v2)(u1 x u2)^T, which depends only on
// the two largest singular pairs; that makes it exact for the rank-2 H of three-point cliques.
void rotation_from_h(const double *H, double *R) {
    // One-sided Jacobi: rotate the columns of A = H until they are orthogonal; then A = H V = U S.
    double a[3][3], v[3][3];  // a[c] = column c of A, v[c] = column c of V
    for (int c = 0; c < 3; ++c)
        for (int r = 0; r < 3; ++r) {
            a[c][r] = H[3 * r + c];
            v[c][r] = r == c ? 1.0 : 0.0;
        }
    for (int sweep = 0; sweep < 60; ++sweep) {
        bool rotated = false;
        for (int p = 0; p < 2; ++p)
            for (int q = p + 1; q < 3; ++q) {
                const double alpha = dot3(a[p], a[p]), beta = dot3(a[q], a[q]), gamma = dot3(a[p], a[q]);
                if (gamma == 0.0 || std::fabs(gamma) <= 1e-15 * std::sqrt(alpha * beta)) continue;
                rotated = true;
                const double zeta = (beta - alpha) / (2.0 * gamma);
                const double t = (zeta >= 0 ? 1.0 : -1.0) / (std::fabs(zeta) + std::sqrt(1.0 + zeta * zeta));
                const double c = 1.0 / std::sqrt(1.0 + t * t), s = c * t;
                for (int r = 0; r < 3; ++r) {
                    const double ap = a[p][r], aq = a[q][r];
                    a[p][r] = c * ap - s * aq;
                    a[q][r] = s * ap + c * aq;
                    const double vp = v[p][r], vq = v[q][r];
                    v[p][r] = c * vp - s * vq;
                    v[q][r] = s * vp + c * vq;
                }
            }
        if (!rotated) break;
    }
    double sig[3] = {norm3(a[0]), norm3(a[1]), norm3(a[2])};
    int ord[3] = {0, 1, 2};
    std::sort(ord, ord + 3, [&](int x, int y) { return sig[x] > sig[y]; });
    const int i1 = ord[0], i2 = ord[1];
    if (!(sig[i1] > 0.0)) {  // H == 0: no information
        for (int k = 0; k < 9; ++k) R[k] = (k % 4 == 0) ? 1.0 : 0.0;
        return;
    }
    double u1[3], u2[3], v1[3], v2[3], u3[3], v3[3];
    for (int r = 0; r < 3; ++r) {
        u1[r] = a[i1][r] / sig[i1];
        v1[r] = v[i1][r];
        v2[r] = v[i2][r];
    }
    if (sig[i2] > 1e-14 * sig[i1]) {
        for (int r = 0; r < 3; ++r) u2[r] = a[i2][r] / sig[i2];
        // Re-orthogonalise against u1 (tiny drift only).
        const double d = dot3(u1, u2);
        for (int r = 0; r < 3; ++r) u2[r] -= d * u1[r];
        const double nn = norm3(u2);
        for (int r = 0; r < 3; ++r) u2[r] /= nn;
    } else {  // rank 1: the rotation about u1 is arbitrary
        any_orthogonal(u1, u2);
    }
    cross(u1, u2, u3);
    cross(v1, v2, v3);
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) R[3 * r + c] = v1[r] * u1[c] + v2[r] * u2[c] + v3[r] * u3[c];
}

}  // namespace

Pose kabsch(const double *src, const double *tgt, const int32_t *idx, int64_t m, const double *weights) {
    Pose T = identity_pose();
    if (m <= 0) return T;
    double pb[3] = {0, 0, 0}, qb[3] = {0, 0, 0};
    for (int64_t k = 0; k < m; ++k) {
        const int64_t i = idx ? idx[k] : k;
        for (int r = 0; r < 3; ++r) {
            pb[r] += src[3 * i + r];
            qb[r] += tgt[3 * i + r];
        }
    }
    for (int r = 0; r < 3; ++r) {
        pb[r] /= (double)m;
        qb[r] /= (double)m;
    }
    double H[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
    for (int64_t k = 0; k < m; ++k) {
        const int64_t i = idx ? idx[k] : k;
        const double wk = weights ? weights[k] : 1.0;
        const double dp[3] = {src[3 * i] - pb[0], src[3 * i + 1] - pb[1], src[3 * i + 2] - pb[2]};
        const double dq[3] = {tgt[3 * i] - qb[0], tgt[3 * i + 1] - qb[1], tgt[3 * i + 2] - qb[2]};
        for (int r = 0; r < 3; ++r)
            for (int c = 0; c < 3; ++c) H[3 * r + c] += wk * dp[r] * dq[c];
    }
    rotation_from_h(H, T.R);
    for (int r = 0; r < 3; ++r)
        T.t[r] = qb[r] - (T.R[3 * r] * pb[0] + T.R[3 * r + 1] * pb[1] + T.R[3 * r + 2] * pb[2]);
    return T;
}

Pose kabsch_weighted(const double *src, const double *tgt, const int32_t *idx, int64_t m, const double *weights,
                     double eps) {
    Pose T = identity_pose();
    if (m <= 0) return T;
    double pb[3] = {0, 0, 0}, qb[3] = {0, 0, 0}, ws = 0.0;
    for (int64_t k = 0; k < m; ++k) {
        const int64_t i = idx ? idx[k] : k;
        const double wk = weights ? weights[k] : 1.0;
        ws += wk;
        for (int r = 0; r < 3; ++r) {
            pb[r] += wk * src[3 * i + r];
            qb[r] += wk * tgt[3 * i + r];
        }
    }
    for (int r = 0; r < 3; ++r) {
        pb[r] /= ws + eps;
        qb[r] /= ws + eps;
    }
    double H[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
    for (int64_t k = 0; k < m; ++k) {
        const int64_t i = idx ? idx[k] : k;
        const double wk = weights ? weights[k] : 1.0;
        const double dp[3] = {src[3 * i] - pb[0], src[3 * i + 1] - pb[1], src[3 * i + 2] - pb[2]};
        const double dq[3] = {wk * (tgt[3 * i] - qb[0]), wk * (tgt[3 * i + 1] - qb[1]), wk * (tgt[3 * i + 2] - qb[2])};
        for (int r = 0; r < 3; ++r)
            for (int c = 0; c < 3; ++c) H[3 * r + c] += dp[r] * dq[c];
    }
    rotation_from_h(H, T.R);
    for (int r = 0; r < 3; ++r)
        T.t[r] = qb[r] - (T.R[3 * r] * pb[0] + T.R[3 * r + 1] * pb[1] + T.R[3 * r + 2] * pb[2]);
    return T;
}

void weighted_inliers(const double *e, int64_t n, double tau, std::vector<int32_t> &idx, std::vector<double> &w) {
    idx.clear();
    w.clear();
    for (int64_t i = 0; i < n; ++i)
        if (e[i] < tau) {
            idx.push_back((int32_t)i);
            const double r = e[i] / tau;
            w.push_back(1.0 / (1.0 + r * r));
        }
}

double mae_score(const Pose &T, const double *src, const double *tgt, int64_t n, double tau, double *e) {
    const double *R = T.R, *t = T.t;
    double score = 0.0;
    for (int64_t i = 0; i < n; ++i) {
        const double *p = src + 3 * i, *q = tgt + 3 * i;
        const double x = R[0] * p[0] + R[1] * p[1] + R[2] * p[2] + t[0] - q[0];
        const double y = R[3] * p[0] + R[4] * p[1] + R[5] * p[2] + t[1] - q[1];
        const double z = R[6] * p[0] + R[7] * p[1] + R[8] * p[2] + t[2] - q[2];
        const double err = std::sqrt(x * x + y * y + z * z);
        if (e) e[i] = err;
        if (err < tau) score += (tau - err) / tau;
    }
    return score;
}

namespace {

// Residual screens: write to out (room for n entries) every row k with |R p_k + t - q_k|^2 <= lim2 in
// float32, in increasing order; return how many.
struct ResidualInput {
    const float *px, *py, *pz, *qx, *qy, *qz;
    int64_t n;
};
using ResidualScreenFn = size_t (*)(const ResidualInput &, const float *, const float *, float, int32_t *);

size_t screen_residuals_generic(const ResidualInput &in, const float *R, const float *t, float lim2,
                                int32_t *out) {
    constexpr int64_t kBlock = 512;
    uint8_t flag[kBlock];
    const float r0 = R[0], r1 = R[1], r2 = R[2], r3 = R[3], r4 = R[4], r5 = R[5], r6 = R[6], r7 = R[7],
                r8 = R[8], t0 = t[0], t1 = t[1], t2 = t[2];
    size_t cnt = 0;
    for (int64_t b0 = 0; b0 < in.n; b0 += kBlock) {
        const int64_t len = std::min(kBlock, in.n - b0);
        const float *px = in.px + b0, *py = in.py + b0, *pz = in.pz + b0;
        const float *qx = in.qx + b0, *qy = in.qy + b0, *qz = in.qz + b0;
        for (int64_t k = 0; k < len; ++k) {
            const float x = r0 * px[k] + r1 * py[k] + r2 * pz[k] + t0 - qx[k];
            const float y = r3 * px[k] + r4 * py[k] + r5 * pz[k] + t1 - qy[k];
            const float z = r6 * px[k] + r7 * py[k] + r8 * pz[k] + t2 - qz[k];
            flag[k] = (uint8_t)(x * x + y * y + z * z <= lim2);
        }
        for (int64_t k = 0; k < len; ++k)
            if (flag[k]) out[cnt++] = (int32_t)(b0 + k);
    }
    return cnt;
}

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define FASTMAC_HAVE_SIMD_RESIDUALS 1
__attribute__((target("avx2,fma"))) size_t screen_residuals_avx2(const ResidualInput &in, const float *R,
                                                                 const float *t, float lim2, int32_t *out) {
    const __m256 r0 = _mm256_set1_ps(R[0]), r1 = _mm256_set1_ps(R[1]), r2 = _mm256_set1_ps(R[2]);
    const __m256 r3 = _mm256_set1_ps(R[3]), r4 = _mm256_set1_ps(R[4]), r5 = _mm256_set1_ps(R[5]);
    const __m256 r6 = _mm256_set1_ps(R[6]), r7 = _mm256_set1_ps(R[7]), r8 = _mm256_set1_ps(R[8]);
    const __m256 t0 = _mm256_set1_ps(t[0]), t1 = _mm256_set1_ps(t[1]), t2 = _mm256_set1_ps(t[2]);
    const __m256 l2 = _mm256_set1_ps(lim2);
    // Locals, not in.*: the pushes into cand could otherwise alias them and force reloads.
    const float *ipx = in.px, *ipy = in.py, *ipz = in.pz, *iqx = in.qx, *iqy = in.qy, *iqz = in.qz;
    const int64_t n = in.n;
    // No call inside the loop (one would make the compiler keep the broadcast constants in memory:
    // vector registers are caller-saved), hence the output buffer.
    size_t cnt = 0;
    int64_t k = 0;
    for (; k + 8 <= n; k += 8) {
        const __m256 px = _mm256_loadu_ps(ipx + k), py = _mm256_loadu_ps(ipy + k), pz = _mm256_loadu_ps(ipz + k);
        const __m256 x = _mm256_fmadd_ps(r0, px, _mm256_fmadd_ps(r1, py, _mm256_fmadd_ps(r2, pz,
                                         _mm256_sub_ps(t0, _mm256_loadu_ps(iqx + k)))));
        const __m256 y = _mm256_fmadd_ps(r3, px, _mm256_fmadd_ps(r4, py, _mm256_fmadd_ps(r5, pz,
                                         _mm256_sub_ps(t1, _mm256_loadu_ps(iqy + k)))));
        const __m256 z = _mm256_fmadd_ps(r6, px, _mm256_fmadd_ps(r7, py, _mm256_fmadd_ps(r8, pz,
                                         _mm256_sub_ps(t2, _mm256_loadu_ps(iqz + k)))));
        const __m256 e2 = _mm256_fmadd_ps(x, x, _mm256_fmadd_ps(y, y, _mm256_mul_ps(z, z)));
        int bits = _mm256_movemask_ps(_mm256_cmp_ps(e2, l2, _CMP_LE_OQ));
        while (bits) {
            out[cnt++] = (int32_t)(k + __builtin_ctz(bits));
            bits &= bits - 1;
        }
    }
    if (k < n) {
        ResidualInput tail{ipx + k, ipy + k, ipz + k, iqx + k, iqy + k, iqz + k, n - k};
        const size_t more = screen_residuals_generic(tail, R, t, lim2, out + cnt);
        for (size_t c = cnt; c < cnt + more; ++c) out[c] += (int32_t)k;
        cnt += more;
    }
    return cnt;
}

__attribute__((target("avx512f"))) size_t screen_residuals_avx512(const ResidualInput &in, const float *R,
                                                                  const float *t, float lim2, int32_t *out) {
    const __m512 r0 = _mm512_set1_ps(R[0]), r1 = _mm512_set1_ps(R[1]), r2 = _mm512_set1_ps(R[2]);
    const __m512 r3 = _mm512_set1_ps(R[3]), r4 = _mm512_set1_ps(R[4]), r5 = _mm512_set1_ps(R[5]);
    const __m512 r6 = _mm512_set1_ps(R[6]), r7 = _mm512_set1_ps(R[7]), r8 = _mm512_set1_ps(R[8]);
    const __m512 t0 = _mm512_set1_ps(t[0]), t1 = _mm512_set1_ps(t[1]), t2 = _mm512_set1_ps(t[2]);
    const __m512 l2 = _mm512_set1_ps(lim2);
    // Locals, not in.*: the pushes into cand could otherwise alias them and force reloads.
    const float *ipx = in.px, *ipy = in.py, *ipz = in.pz, *iqx = in.qx, *iqy = in.qy, *iqz = in.qz;
    const int64_t n = in.n;
    // No call inside the loop (one would make the compiler keep the broadcast constants in memory:
    // vector registers are caller-saved), hence the output buffer.
    size_t cnt = 0;
    int64_t k = 0;
    for (; k + 16 <= n; k += 16) {
        const __m512 px = _mm512_loadu_ps(ipx + k), py = _mm512_loadu_ps(ipy + k), pz = _mm512_loadu_ps(ipz + k);
        const __m512 x = _mm512_fmadd_ps(r0, px, _mm512_fmadd_ps(r1, py, _mm512_fmadd_ps(r2, pz,
                                         _mm512_sub_ps(t0, _mm512_loadu_ps(iqx + k)))));
        const __m512 y = _mm512_fmadd_ps(r3, px, _mm512_fmadd_ps(r4, py, _mm512_fmadd_ps(r5, pz,
                                         _mm512_sub_ps(t1, _mm512_loadu_ps(iqy + k)))));
        const __m512 z = _mm512_fmadd_ps(r6, px, _mm512_fmadd_ps(r7, py, _mm512_fmadd_ps(r8, pz,
                                         _mm512_sub_ps(t2, _mm512_loadu_ps(iqz + k)))));
        const __m512 e2 = _mm512_fmadd_ps(x, x, _mm512_fmadd_ps(y, y, _mm512_mul_ps(z, z)));
        unsigned bits = _mm512_cmp_ps_mask(e2, l2, _CMP_LE_OQ);
        while (bits) {
            out[cnt++] = (int32_t)(k + __builtin_ctz(bits));
            bits &= bits - 1;
        }
    }
    if (k < n) {
        ResidualInput tail{ipx + k, ipy + k, ipz + k, iqx + k, iqy + k, iqz + k, n - k};
        const size_t more = screen_residuals_generic(tail, R, t, lim2, out + cnt);
        for (size_t c = cnt; c < cnt + more; ++c) out[c] += (int32_t)k;
        cnt += more;
    }
    return cnt;
}
#endif

// Inlier-count screens (Metric::Inliers): the rows with e^2 <= lo2 in float32 are inliers for certain and
// only counted; those with lo2 < e^2 <= hi2 go to out (ascending) for the exact test. Returns the count of
// the certain ones; *n_out receives how many went to out.
using CountScreenFn = int64_t (*)(const ResidualInput &, const float *, const float *, float, float, int32_t *,
                                  size_t *);

int64_t count_residuals_generic(const ResidualInput &in, const float *R, const float *t, float lo2, float hi2,
                                int32_t *out, size_t *n_out) {
    const float r0 = R[0], r1 = R[1], r2 = R[2], r3 = R[3], r4 = R[4], r5 = R[5], r6 = R[6], r7 = R[7],
                r8 = R[8], t0 = t[0], t1 = t[1], t2 = t[2];
    int64_t sure = 0;
    size_t cnt = 0;
    for (int64_t k = 0; k < in.n; ++k) {
        const float x = r0 * in.px[k] + r1 * in.py[k] + r2 * in.pz[k] + t0 - in.qx[k];
        const float y = r3 * in.px[k] + r4 * in.py[k] + r5 * in.pz[k] + t1 - in.qy[k];
        const float z = r6 * in.px[k] + r7 * in.py[k] + r8 * in.pz[k] + t2 - in.qz[k];
        const float e2 = x * x + y * y + z * z;
        sure += e2 <= lo2;
        if (e2 > lo2 && e2 <= hi2) out[cnt++] = (int32_t)k;
    }
    *n_out = cnt;
    return sure;
}

#ifdef FASTMAC_HAVE_SIMD_RESIDUALS
__attribute__((target("avx512f"))) int64_t count_residuals_avx512(const ResidualInput &in, const float *R,
                                                                  const float *t, float lo2, float hi2,
                                                                  int32_t *out, size_t *n_out) {
    const __m512 r0 = _mm512_set1_ps(R[0]), r1 = _mm512_set1_ps(R[1]), r2 = _mm512_set1_ps(R[2]);
    const __m512 r3 = _mm512_set1_ps(R[3]), r4 = _mm512_set1_ps(R[4]), r5 = _mm512_set1_ps(R[5]);
    const __m512 r6 = _mm512_set1_ps(R[6]), r7 = _mm512_set1_ps(R[7]), r8 = _mm512_set1_ps(R[8]);
    const __m512 t0 = _mm512_set1_ps(t[0]), t1 = _mm512_set1_ps(t[1]), t2 = _mm512_set1_ps(t[2]);
    const __m512 l2 = _mm512_set1_ps(lo2), h2 = _mm512_set1_ps(hi2);
    const __m512i lane = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    const float *ipx = in.px, *ipy = in.py, *ipz = in.pz, *iqx = in.qx, *iqy = in.qy, *iqz = in.qz;
    const int64_t n = in.n;
    int64_t sure = 0;
    size_t cnt = 0;
    int64_t k = 0;
    for (; k + 16 <= n; k += 16) {
        const __m512 px = _mm512_loadu_ps(ipx + k), py = _mm512_loadu_ps(ipy + k), pz = _mm512_loadu_ps(ipz + k);
        const __m512 x = _mm512_fmadd_ps(r0, px, _mm512_fmadd_ps(r1, py, _mm512_fmadd_ps(r2, pz,
                                         _mm512_sub_ps(t0, _mm512_loadu_ps(iqx + k)))));
        const __m512 y = _mm512_fmadd_ps(r3, px, _mm512_fmadd_ps(r4, py, _mm512_fmadd_ps(r5, pz,
                                         _mm512_sub_ps(t1, _mm512_loadu_ps(iqy + k)))));
        const __m512 z = _mm512_fmadd_ps(r6, px, _mm512_fmadd_ps(r7, py, _mm512_fmadd_ps(r8, pz,
                                         _mm512_sub_ps(t2, _mm512_loadu_ps(iqz + k)))));
        const __m512 e2 = _mm512_fmadd_ps(x, x, _mm512_fmadd_ps(y, y, _mm512_mul_ps(z, z)));
        const __mmask16 lo = _mm512_cmp_ps_mask(e2, l2, _CMP_LE_OQ);
        const __mmask16 band = _mm512_mask_cmp_ps_mask((__mmask16)~lo, e2, h2, _CMP_LE_OQ);
        sure += __builtin_popcount((unsigned)lo);
        if (band) {
            _mm512_storeu_si512(out + cnt, _mm512_maskz_compress_epi32(band, _mm512_add_epi32(
                                                                                _mm512_set1_epi32((int)k), lane)));
            cnt += (size_t)__builtin_popcount((unsigned)band);
        }
    }
    if (k < n) {
        ResidualInput tail{ipx + k, ipy + k, ipz + k, iqx + k, iqy + k, iqz + k, n - k};
        size_t more = 0;
        sure += count_residuals_generic(tail, R, t, lo2, hi2, out + cnt, &more);
        for (size_t c = cnt; c < cnt + more; ++c) out[c] += (int32_t)k;
        cnt += more;
    }
    *n_out = cnt;
    return sure;
}
#endif

CountScreenFn pick_count_screen() {
#ifdef FASTMAC_HAVE_SIMD_RESIDUALS
    const char *env = std::getenv("FASTMAC_SCREEN");
    const std::string want = env ? env : "";
    if (want != "generic" && want != "avx2" && __builtin_cpu_supports("avx512f")) return count_residuals_avx512;
#endif
    return count_residuals_generic;
}

ResidualScreenFn pick_residual_screen() {
#ifdef FASTMAC_HAVE_SIMD_RESIDUALS
    const char *env = std::getenv("FASTMAC_SCREEN");  // for tests: avx512 | avx2 | generic
    const std::string want = env ? env : "";
    if (want == "generic") return screen_residuals_generic;
    if (want != "avx2" && __builtin_cpu_supports("avx512f")) return screen_residuals_avx512;
    if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma")) return screen_residuals_avx2;
#endif
    return screen_residuals_generic;
}

}  // namespace

Scorer::Scorer(const double *src, const double *tgt, int64_t n, double tau)
    : src_(src), tgt_(tgt), n_(n), tau_(tau), px_(n), py_(n), pz_(n), qx_(n), qy_(n), qz_(n) {
    screen_ = reinterpret_cast<void (*)()>(pick_residual_screen());
    count_ = reinterpret_cast<void (*)()>(pick_count_screen());
    for (int64_t i = 0; i < n; ++i)
        for (int r = 0; r < 3; ++r) {
            cp_[r] += src[3 * i + r];
            cq_[r] += tgt[3 * i + r];
        }
    for (int r = 0; r < 3; ++r) {
        cp_[r] /= (double)std::max<int64_t>(n, 1);
        cq_[r] /= (double)std::max<int64_t>(n, 1);
    }
    for (int64_t i = 0; i < n; ++i) {
        const double a[3] = {src[3 * i] - cp_[0], src[3 * i + 1] - cp_[1], src[3 * i + 2] - cp_[2]};
        const double b[3] = {tgt[3 * i] - cq_[0], tgt[3 * i + 1] - cq_[1], tgt[3 * i + 2] - cq_[2]};
        px_[i] = (float)a[0];
        py_[i] = (float)a[1];
        pz_[i] = (float)a[2];
        qx_[i] = (float)b[0];
        qy_[i] = (float)b[1];
        qz_[i] = (float)b[2];
        rp_ = std::max(rp_, norm3(a));
        rq_ = std::max(rq_, norm3(b));
    }
}

double Scorer::score(const Pose &T, std::vector<int32_t> &buf, Metric metric) const {
    // R p + t - q = R p' + t' - q' with p' = p - cp, q' = q - cq and t' = R cp + t - cq.
    float Rf[9], tf[3];
    double tc[3];
    for (int r = 0; r < 3; ++r) {
        tc[r] = T.R[3 * r] * cp_[0] + T.R[3 * r + 1] * cp_[1] + T.R[3 * r + 2] * cp_[2] + T.t[r] - cq_[r];
        tf[r] = (float)tc[r];
    }
    for (int k = 0; k < 9; ++k) Rf[k] = (float)T.R[k];
    // Float rounding of the inputs, the products and the sums stays far below 1e-5 of the magnitudes.
    const double lim = tau_ + 1e-5 * (rp_ + rq_ + norm3(tc)) + 1e-12;
    const float lim2 = (float)(lim * lim);
    if ((int64_t)buf.size() < n_ + 16) buf.resize(n_ + 16);
    const ResidualInput in{px_.data(), py_.data(), pz_.data(), qx_.data(), qy_.data(), qz_.data(), n_};
    if (metric == Metric::Inliers) {
        // Below tau - margin in float32 means below tau exactly: counted without the exact test.
        const double lo = tau_ - (lim - tau_);
        const float lo2 = lo > 0.0 ? (float)(lo * lo * (1.0 - 1e-6)) : -1.0f;
        size_t n_band = 0;
        const int64_t sure =
            reinterpret_cast<CountScreenFn>(count_)(in, Rf, tf, lo2, lim2, buf.data(), &n_band);
        int64_t exact = 0;
        for (size_t c = 0; c < n_band; ++c) {
            const int32_t i = buf[c];
            const double *p = src_ + 3 * (int64_t)i, *q = tgt_ + 3 * (int64_t)i;
            const double *R = T.R, *t = T.t;
            const double x = R[0] * p[0] + R[1] * p[1] + R[2] * p[2] + t[0] - q[0];
            const double y = R[3] * p[0] + R[4] * p[1] + R[5] * p[2] + t[1] - q[1];
            const double z = R[6] * p[0] + R[7] * p[1] + R[8] * p[2] + t[2] - q[2];
            exact += std::sqrt(x * x + y * y + z * z) < tau_;
        }
        return (double)(sure + exact);
    }
    const size_t n_cand = reinterpret_cast<ResidualScreenFn>(screen_)(in, Rf, tf, lim2, buf.data());
    // Exactly as mae_score, over the candidates in increasing order (the others are not inliers).
    const double *R = T.R, *t = T.t;
    const double tau = tau_;
    double score = 0.0;
    for (size_t c = 0; c < n_cand; ++c) {
        const int32_t i = buf[c];
        const double *p = src_ + 3 * (int64_t)i, *q = tgt_ + 3 * (int64_t)i;
        const double x = R[0] * p[0] + R[1] * p[1] + R[2] * p[2] + t[0] - q[0];
        const double y = R[3] * p[0] + R[4] * p[1] + R[5] * p[2] + t[1] - q[1];
        const double z = R[6] * p[0] + R[7] * p[1] + R[8] * p[2] + t[2] - q[2];
        const double err = std::sqrt(x * x + y * y + z * z);
        if (err < tau) {
            const double v = (tau - err) / tau;
            score += metric == Metric::Mae ? v : metric == Metric::Mse ? v * v : 1.0;
        }
    }
    return score;
}

}  // namespace fastmac
