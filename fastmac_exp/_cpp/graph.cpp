// First- and second-order compatibility graphs (spec 2.1-2.3) and the sampler signals (spec 7.2-7.3).
#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>

#include "mac_core.hpp"
#include "parallel.hpp"

namespace fastmac {

Kernel parse_kernel(const std::string &name) {
    if (name == "gaussian") return Kernel::Gaussian;
    if (name == "quadratic") return Kernel::Quadratic;
    throw std::invalid_argument("kernel must be 'gaussian' or 'quadratic', got '" + name + "'");
}

void check_params(const GraphParams &gp) {
    if (!(gp.threshold > 0.0 && gp.threshold <= 1.0))
        throw std::invalid_argument("threshold must be in (0, 1], got " + std::to_string(gp.threshold));
    if (!(gp.alpha > 0.0) || !(gp.tau > 0.0))
        throw std::invalid_argument("alpha and tau must be positive");
}

int default_threads() {
#ifdef FASTMAC_OPENMP
    return omp_get_max_threads();
#else
    if (const char *env = std::getenv("OMP_NUM_THREADS")) {
        const int v = std::atoi(env);
        if (v > 0) return v;
    }
    const unsigned hw = std::thread::hardware_concurrency();
    return hw > 0 ? (int)std::min(hw, 256u) : 1;
#endif
}

int resolve_threads(int num_threads, int64_t n) {
    if (num_threads > 0) return num_threads;
    if (n >= 0 && n < kSerialBelow) return 1;
    return default_threads();
}

namespace {

// The kernel exactly as the Python reference evaluates it (fastmac_exp/graph.py::kernel).
inline double kernel_value(double d, const GraphParams &gp) {
    if (gp.kernel == Kernel::Gaussian) return std::exp(-(d * d) / (2.0 * (gp.alpha * gp.alpha)));
    return 1.0 - (d * d) / (gp.tau * gp.tau);
}

// The largest inconsistency that can still make an edge.
double max_distance(const GraphParams &gp) {
    if (gp.kernel == Kernel::Gaussian)
        return gp.threshold < 1.0 ? gp.alpha * std::sqrt(-2.0 * std::log(gp.threshold)) : 0.0;
    return gp.tau * std::sqrt(1.0 - gp.threshold);
}

constexpr int64_t kBlock = 1024;

// Screen of one row block in float32: flag[k] = | |p_i - p_j| - |q_i - q_j| | <= lim, on coordinates
// centred per cloud. lim includes a bound on the float rounding, so every pair that can make an edge
// is flagged; flagged pairs are then tested exactly in double.
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
__attribute__((target_clones("avx2", "default")))
#endif
void screen_block(const float *__restrict px, const float *__restrict py, const float *__restrict pz,
                  const float *__restrict qx, const float *__restrict qy, const float *__restrict qz, float pxi,
                  float pyi, float pzi, float qxi, float qyi, float qzi, float lim, int64_t len,
                  uint8_t *__restrict flag) {
    for (int64_t k = 0; k < len; ++k) {
        const float ax = px[k] - pxi, ay = py[k] - pyi, az = pz[k] - pzi;
        const float bx = qx[k] - qxi, by = qy[k] - qyi, bz = qz[k] - qzi;
        const float a = std::sqrt(ax * ax + ay * ay + az * az);
        const float b = std::sqrt(bx * bx + by * by + bz * bz);
        flag[k] = (uint8_t)(std::fabs(a - b) <= lim);
    }
}

}  // namespace

Csr first_order(const double *src, const double *tgt, int64_t n, const GraphParams &gp, int nthreads) {
    check_params(gp);
    nthreads = resolve_threads(nthreads, n);
    Csr W;
    W.n = n;
    W.ptr.assign(n + 1, 0);
    W.upper.assign(n, 0);
    if (n == 0) return W;

    // Centred float32 copies for the screen; Rmax bounds the coordinates' magnitude.
    double cs[3] = {0, 0, 0}, ct[3] = {0, 0, 0};
    for (int64_t i = 0; i < n; ++i)
        for (int r = 0; r < 3; ++r) {
            cs[r] += src[3 * i + r];
            ct[r] += tgt[3 * i + r];
        }
    for (int r = 0; r < 3; ++r) {
        cs[r] /= (double)n;
        ct[r] /= (double)n;
    }
    std::vector<float> px(n), py(n), pz(n), qx(n), qy(n), qz(n);
    double rmax = 0.0;
    for (int64_t i = 0; i < n; ++i) {
        px[i] = (float)(src[3 * i] - cs[0]);
        py[i] = (float)(src[3 * i + 1] - cs[1]);
        pz[i] = (float)(src[3 * i + 2] - cs[2]);
        qx[i] = (float)(tgt[3 * i] - ct[0]);
        qy[i] = (float)(tgt[3 * i + 1] - ct[1]);
        qz[i] = (float)(tgt[3 * i + 2] - ct[2]);
        for (float v : {px[i], py[i], pz[i], qx[i], qy[i], qz[i]}) rmax = std::max(rmax, (double)std::fabs(v));
    }
    // Float rounding moves each distance by well under 2e-6 * rmax (coordinates, differences, squares,
    // sum and sqrt); 1e-5 * rmax is a safe margin.
    const double m = max_distance(gp) * (1.0 + 1e-7) + 1e-12;
    const float lim = (float)((m + 1e-5 * rmax) * (1.0 + 1e-6));
    const double thr = gp.threshold;

    // Upper-triangle neighbours of each row, found in parallel.
    std::vector<std::vector<int32_t>> ucol(n);
    std::vector<std::vector<double>> uw(n);
    DynamicRange rows(0, n - 1, 16);
    parallel_region(nthreads, [&](int) {
        std::vector<uint8_t> flag(kBlock + 8);
        int64_t lo, hi;
        while (rows.next(lo, hi)) for (int64_t i = lo; i < hi; ++i) {
            auto &cols = ucol[i];
            auto &ws = uw[i];
            for (int64_t j0 = i + 1; j0 < n; j0 += kBlock) {
                const int64_t len = std::min(kBlock, n - j0);
                screen_block(px.data() + j0, py.data() + j0, pz.data() + j0, qx.data() + j0, qy.data() + j0,
                             qz.data() + j0, px[i], py[i], pz[i], qx[i], qy[i], qz[i], lim, len, flag.data());
                std::memset(flag.data() + len, 0, 8);
                for (int64_t k8 = 0; k8 < len; k8 += 8) {
                    uint64_t word;
                    std::memcpy(&word, flag.data() + k8, 8);
                    if (!word) continue;
                    for (int64_t k = k8; k < k8 + 8 && k < len; ++k) {
                        if (!flag[k]) continue;
                        const int64_t j = j0 + k;
                        // Exact test, as the reference computes it: norms of the differences, in double.
                        const double ax = src[3 * i] - src[3 * j], ay = src[3 * i + 1] - src[3 * j + 1],
                                     az = src[3 * i + 2] - src[3 * j + 2];
                        const double bx = tgt[3 * i] - tgt[3 * j], by = tgt[3 * i + 1] - tgt[3 * j + 1],
                                     bz = tgt[3 * i + 2] - tgt[3 * j + 2];
                        const double dp = std::sqrt(ax * ax + ay * ay + az * az);
                        const double dq = std::sqrt(bx * bx + by * by + bz * bz);
                        const double s = kernel_value(std::fabs(dp - dq), gp);
                        if (s >= thr) {
                            cols.push_back((int32_t)j);
                            ws.push_back(s);
                        }
                    }
                }
            }
        }
    });

    // Assemble the symmetric CSR: row i = [neighbours j < i ascending | neighbours j > i ascending].
    std::vector<int64_t> nlow(n, 0);
    for (int64_t i = 0; i < n; ++i)
        for (int32_t j : ucol[i]) ++nlow[j];
    for (int64_t i = 0; i < n; ++i) W.ptr[i + 1] = W.ptr[i] + nlow[i] + (int64_t)ucol[i].size();
    W.col.resize(W.ptr[n]);
    W.w.resize(W.ptr[n]);
    std::vector<int64_t> cursor(W.ptr.begin(), W.ptr.end() - 1);
    for (int64_t i = 0; i < n; ++i) {
        W.upper[i] = W.ptr[i] + nlow[i];
        // cursor[i] == W.upper[i] here: all lower neighbours of i (rows < i) are already placed.
        const int64_t base = W.upper[i];
        const auto &cols = ucol[i];
        const auto &ws = uw[i];
        for (size_t k = 0; k < cols.size(); ++k) {
            W.col[base + k] = cols[k];
            W.w[base + k] = ws[k];
            const int64_t p = cursor[cols[k]]++;
            W.col[p] = (int32_t)i;
            W.w[p] = ws[k];
        }
        std::vector<int32_t>().swap(ucol[i]);
        std::vector<double>().swap(uw[i]);
    }
    return W;
}

std::vector<double> second_order(const Csr &W, int nthreads) {
    nthreads = resolve_threads(nthreads, W.n);
    const int64_t n = W.n;
    std::vector<double> G(W.nnz(), 0.0);
    const int64_t *ptr = W.ptr.data();
    const int32_t *col = W.col.data();
    const double *w = W.w.data();
    DynamicRange rows(0, n, 8);
    parallel_region(nthreads, [&](int) {
        // Row i of W scattered densely; zero elsewhere (so k = i contributes nothing, W_ii = 0).
        std::vector<double> dense(n, 0.0);
        double *d = dense.data();
        int64_t lo, hi;
        while (rows.next(lo, hi)) for (int64_t i = lo; i < hi; ++i) {
            if (W.upper[i] == ptr[i + 1]) continue;
            for (int64_t p = ptr[i]; p < ptr[i + 1]; ++p) d[col[p]] = w[p];
            for (int64_t p = W.upper[i]; p < ptr[i + 1]; ++p) {
                const int32_t j = col[p];
                double acc = 0.0;
                for (int64_t q = ptr[j]; q < ptr[j + 1]; ++q) acc += d[col[q]] * w[q];
                // d[j] = W_ij is never read: j is not its own neighbour.
                G[p] = w[p] * acc;
            }
            for (int64_t p = ptr[i]; p < ptr[i + 1]; ++p) d[col[p]] = 0.0;
        }
    });
    // Mirror the upper entries into the lower parts (row j's lower part is ordered by i).
    std::vector<int64_t> cursor(W.ptr.begin(), W.ptr.end() - 1);
    for (int64_t i = 0; i < n; ++i)
        for (int64_t p = W.upper[i]; p < ptr[i + 1]; ++p) G[cursor[col[p]]++] = G[p];
    return G;
}

double csr_lookup(const Csr &W, const std::vector<double> &vals, int32_t a, int32_t b) {
    const int32_t *first = W.col.data() + W.ptr[a];
    const int32_t *last = W.col.data() + W.ptr[a + 1];
    const int32_t *it = std::lower_bound(first, last, b);
    if (it == last || *it != b) return 0.0;
    return vals[it - W.col.data()];
}

Signals graph_signals(const Csr &W, const std::vector<double> &G, bool self_loops, int nthreads) {
    nthreads = resolve_threads(nthreads, W.n);
    const int64_t n = W.n;
    Signals out;
    out.n_edges = W.n_edges();
    out.degree.assign(n, 0.0);
    out.highpass.assign(n, 0.0);
    out.lowpass.assign(n, 0.0);
    std::vector<double> diag(n, 0.0);
    const double loop = self_loops ? 2.0 : 0.0;
    // Off-diagonal SOG_ij = G_ij + 2 W_ij^2 with self-loops, G_ij without; SOG_ii = 1 + sum_k W_ik^2.
    parallel_for(0, n, nthreads, 512, [&](int64_t i, int) {
        double off = 0.0, sq = 0.0;
        for (int64_t p = W.ptr[i]; p < W.ptr[i + 1]; ++p) {
            const double wv = W.w[p];
            off += G[p] + loop * wv * wv;
            sq += wv * wv;
        }
        diag[i] = self_loops ? 1.0 + sq : 0.0;
        out.degree[i] = diag[i] + off;
    });
    const double *s = out.degree.data();
    parallel_for(0, n, nthreads, 512, [&](int64_t i, int) {
        double hp = 0.0, ns = 0.0;
        for (int64_t p = W.ptr[i]; p < W.ptr[i + 1]; ++p) {
            const double wv = W.w[p];
            const double sog = G[p] + loop * wv * wv;
            const double sj = s[W.col[p]];
            hp += sog * (s[i] - sj);
            ns += sog * sj;
        }
        out.highpass[i] = hp;
        out.lowpass[i] = s[i] > 0.0 ? s[i] + (diag[i] * s[i] + ns) / s[i] : 0.0;
    });
    return out;
}

}  // namespace fastmac
