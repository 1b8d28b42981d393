// TurboReg on the CPU (turboreg.hpp, docs/turboreg.md): the steps of upstream's runRegCXX, each computed
// without its N x N dense matrices.
//
//  1. C: the length-consistency graph of the first max_N correspondences (length_graph, float32 as upstream).
//  2. SC^2 = C (.) (C C) on C's support: common_neighbour_counts (bitset AND + popcount, exact) for the
//     hard graph, masked_square for the soft one (FASTMAC_TURBO_SC2=masked: masked_square for both).
//  3. Pivots: torch.topk(triu(SC^2, 1).flatten(), K1), reproduced with its tie order (below).
//  4. TurboCliques: for pivot (a, b) the two c maximising SC2_ab + SC2_ac + SC2_bc over the c with
//     SC2_ac > 0 and SC2_bc > 0 in the upper triangle (c > a, b), again torch.topk(.., 2) with its ties;
//     cliques = [(a, b, first) for each pivot] + [(a, b, second) for each pivot].
//  5. One Kabsch hypothesis per clique, the metric (IN / MAE / MSE) over all correspondences, the first
//     best (argmax), then upstream's post-refinement (weighted Kabsch on the inliers, up to 20 rounds,
//     stopping when the inlier count repeats).
// Poses and residuals are float64 (upstream: float32); docs/turboreg.md gives the parity this keeps.
#include "turboreg.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <unordered_map>
#include <utility>

#include "parallel.hpp"

namespace fastmac {

namespace {

using Clock = std::chrono::steady_clock;
double ms_since(Clock::time_point t0) {
    return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

// torch's CPU topk (ATen/native/TopKImpl.h, largest = sorted = true) sorts (value, position) pairs with
// comp = x.first > y.first: std::partial_sort when 64 k <= dim, else std::nth_element then std::sort of
// the first k - 1. partial_sort is libstdc++'s heap select (a heap of the first k, each later element that
// compares better than the heap's top replaces it) and sort_heap. Zeros never replace a top >= 0, so
// feeding the heap the first k positions and then only the positive entries gives torch's exact result.
using Elem = std::pair<double, int64_t>;
struct Greater {
    bool operator()(const Elem &x, const Elem &y) const { return x.first > y.first; }
};

// value_at(pos): the value at any position < k (dense path: unused); for_each(f): f(pos, v) for every
// positive entry, positions ascending. Writes the k positions to out.
template <class ValueAt, class ForEach>
void topk_like_torch(int64_t dim, int64_t k, ValueAt &&value_at, ForEach &&for_each, std::vector<Elem> &buf,
                     int64_t *out) {
    if (k <= 0) return;
    if (k * 64 <= dim) {
        buf.resize(k + 1);
        for (int64_t p = 0; p < k; ++p) buf[p] = Elem(value_at(p), p);
        std::make_heap(buf.begin(), buf.begin() + k, Greater());
        for_each([&](int64_t pos, double v) {
            if (pos < k || !(v > buf[0].first)) return;
            buf[k] = Elem(v, pos);
            std::pop_heap(buf.begin(), buf.begin() + k + 1, Greater());  // = __heap_select's __pop_heap
        });
        std::sort_heap(buf.begin(), buf.begin() + k, Greater());
    } else {
        buf.assign(dim, Elem(0.0, 0));
        for (int64_t p = 0; p < dim; ++p) buf[p].second = p;
        for_each([&](int64_t pos, double v) { buf[pos].first = v; });
        std::nth_element(buf.begin(), buf.begin() + k - 1, buf.end(), Greater());
        std::sort(buf.begin(), buf.begin() + k - 1, Greater());
    }
    for (int64_t p = 0; p < k; ++p) out[p] = buf[p].second;
}

// SC^2's positive entries in the upper triangle, row by row (columns ascending).
struct Upper {
    std::vector<int64_t> ptr;
    std::vector<int32_t> col;
    std::vector<double> val;
    double at(int64_t r, int64_t c) const {
        const int32_t *b = col.data() + ptr[r], *e = col.data() + ptr[r + 1];
        const int32_t *it = std::lower_bound(b, e, (int32_t)c);
        return it != e && *it == c ? val[it - col.data()] : 0.0;
    }
};

// S: SC^2 at W's entries (double or integer counts). Rows counted, then filled, in parallel.
template <class T>
Upper upper_positive(const Csr &W, const std::vector<T> &S, int nthreads) {
    Upper U;
    U.ptr.assign(W.n + 1, 0);
    parallel_for(0, W.n, nthreads, 512, [&](int64_t i, int) {
        U.ptr[i + 1] = std::count_if(S.begin() + W.upper[i], S.begin() + W.ptr[i + 1], [](T v) { return v > 0; });
    });
    for (int64_t i = 0; i < W.n; ++i) U.ptr[i + 1] += U.ptr[i];
    U.col.resize(U.ptr[W.n]);
    U.val.resize(U.ptr[W.n]);
    parallel_for(0, W.n, nthreads, 512, [&](int64_t i, int) {
        int64_t q = U.ptr[i];
        for (int64_t p = W.upper[i]; p < W.ptr[i + 1]; ++p)
            if (S[p] > 0) {
                U.col[q] = W.col[p];
                U.val[q++] = (double)S[p];
            }
    });
    return U;
}

// The residual of every correspondence under T.
void residuals(const Pose &T, const double *src, const double *tgt, int64_t n, std::vector<double> &e) {
    e.resize(n);
    const double *R = T.R, *t = T.t;
    for (int64_t i = 0; i < n; ++i) {
        const double *p = src + 3 * i, *q = tgt + 3 * i;
        const double x = R[0] * p[0] + R[1] * p[1] + R[2] * p[2] + t[0] - q[0];
        const double y = R[3] * p[0] + R[4] * p[1] + R[5] * p[2] + t[1] - q[1];
        const double z = R[6] * p[0] + R[7] * p[1] + R[8] * p[2] + t[2] - q[2];
        e[i] = std::sqrt(x * x + y * y + z * z);
    }
}

// Upstream's post_refinement: inliers e < tau; stop when their count equals the previous round's (0 at
// the start); else weighted Kabsch on them with w = 1 / (1 + (e / tau)^2).
Pose post_refinement(Pose T, const double *src, const double *tgt, int64_t n, double tau, int iters, int *rounds) {
    std::vector<double> e, w;
    std::vector<int32_t> idx;
    int64_t previous = 0;
    *rounds = 0;
    for (int it = 0; it < iters; ++it) {
        residuals(T, src, tgt, n, e);
        weighted_inliers(e.data(), n, tau, idx, w);
        const int64_t count = (int64_t)idx.size();
        if (count == previous) break;
        previous = count;
        T = kabsch_weighted(src, tgt, idx.data(), count, w.data(), 1e-6);
        ++*rounds;
    }
    return T;
}

}  // namespace

Metric parse_metric(const std::string &name) {
    if (name == "IN") return Metric::Inliers;
    if (name == "MAE") return Metric::Mae;
    if (name == "MSE") return Metric::Mse;
    throw std::invalid_argument("metric must be 'IN', 'MAE' or 'MSE', got '" + name + "'");
}

std::vector<int64_t> torch_topk_sparse(int64_t dim, int64_t k, const std::vector<int64_t> &pos,
                                       const std::vector<double> &val) {
    if (k < 0 || k > dim) throw std::invalid_argument("k must be in [0, dim]");
    if (pos.size() != val.size()) throw std::invalid_argument("pos and val must have the same length");
    std::vector<double> head(std::max<int64_t>(k, 0), 0.0);
    for (size_t q = 0; q < pos.size(); ++q) {
        if (pos[q] < 0 || pos[q] >= dim || (q && pos[q] <= pos[q - 1]) || !(val[q] > 0.0))
            throw std::invalid_argument("pos must ascend within [0, dim) and val be positive");
        if (pos[q] < k) head[pos[q]] = val[q];
    }
    std::vector<int64_t> out(k);
    std::vector<Elem> buf;
    topk_like_torch(
        dim, k, [&](int64_t p) { return head[p]; },
        [&](auto &&f) {
            for (size_t q = 0; q < pos.size(); ++q) f(pos[q], val[q]);
        },
        buf, out.data());
    return out;
}

TurboResult turboreg(const double *src, const double *tgt, int64_t n_all, const TurboParams &p, int nthreads) {
    if (!(p.tau > 0.0) || !(p.tau_inlier > 0.0) || !(p.radius_nms >= 0.0))
        throw std::invalid_argument("tau and tau_inlier must be positive and radius_nms >= 0");
    if (p.num_pivot < 1) throw std::invalid_argument("num_pivot must be at least 1");
    if (p.refine_iters < 0) throw std::invalid_argument("refine_iters must be >= 0");
    for (int64_t k = 0; k < 3 * n_all; ++k)
        if (!std::isfinite(src[k]) || !std::isfinite(tgt[k]))
            throw std::invalid_argument("correspondences must be finite (NaN or inf found)");
    const int64_t n = p.max_n > 0 ? std::min(n_all, p.max_n) : n_all;
    if (n < 3) throw RegistrationFailed("TurboReg needs at least 3 correspondences, got " + std::to_string(n));
    nthreads = resolve_threads(nthreads, n);
    TurboResult r;
    r.n_used = n;

    // 1-2. C and SC^2.
    auto t0 = Clock::now();
    std::vector<float> s32(3 * n), t32(3 * n);
    for (int64_t k = 0; k < 3 * n; ++k) {
        s32[k] = (float)src[k];
        t32[k] = (float)tgt[k];
    }
    const Csr W = length_graph(s32.data(), t32.data(), n, (float)p.tau, (float)p.radius_nms, p.hard, nthreads);
    r.n_edges = W.n_edges();
    const Upper U = p.hard && !env_is("FASTMAC_TURBO_SC2", "masked")
                        ? upper_positive(W, common_neighbour_counts(W, nthreads), nthreads)
                        : upper_positive(W, masked_square(W, W.weights(), nthreads, nullptr, Precision::Single),
                                         nthreads);
    r.n_sog_edges = (int64_t)U.col.size();
    r.t_graph = ms_since(t0);
    if (U.col.empty()) throw RegistrationFailed("TurboReg: SC^2 has no positive entry (no compatible triangle)");

    // 3. Pivots: topk over the flattened upper triangle (position a * n + b).
    t0 = Clock::now();
    const int64_t K = std::min<int64_t>(p.num_pivot, n * n);
    std::vector<int64_t> flat(K);
    std::vector<Elem> buf;
    topk_like_torch(
        n * n, K, [&](int64_t pos) { return U.at(pos / n, pos % n); },
        [&](auto &&f) {
            for (int64_t a = 0; a < n; ++a)
                for (int64_t q = U.ptr[a]; q < U.ptr[a + 1]; ++q) f(a * n + U.col[q], U.val[q]);
        },
        buf, flat.data());
    r.n_pivots = K;

    // 4. Two TurboCliques per pivot.
    std::vector<int64_t> third(2 * K);
    DynamicRange pivots(0, K, 64);
    parallel_region(nthreads, [&](int) {  // any tid but 0 may not run: work comes from the shared range
        std::vector<double> mark(n, 0.0);
        std::vector<Elem> rowbuf;
        int64_t lo, hi;
        while (pivots.next(lo, hi)) for (int64_t k = lo; k < hi; ++k) {
            const int64_t a = flat[k] / n, b = flat[k] % n;
            const double pivot = a < b ? U.at(a, b) : 0.0;
            for (int64_t q = U.ptr[a]; q < U.ptr[a + 1]; ++q) mark[U.col[q]] = U.val[q];
            // float32 as upstream: SC2_ab + (SC2_ac + SC2_bc)
            auto score = [&](int64_t c, double vbc) {
                return (double)((float)pivot + ((float)mark[c] + (float)vbc));
            };
            int64_t top[2];
            topk_like_torch(
                n, 2,
                [&](int64_t c) {
                    const double vbc = U.at(b, c);
                    return mark[c] > 0.0 && vbc > 0.0 ? score(c, vbc) : 0.0;
                },
                [&](auto &&f) {
                    for (int64_t q = U.ptr[b]; q < U.ptr[b + 1]; ++q)
                        if (mark[U.col[q]] > 0.0) f(U.col[q], score(U.col[q], U.val[q]));
                },
                rowbuf, top);
            for (int64_t q = U.ptr[a]; q < U.ptr[a + 1]; ++q) mark[U.col[q]] = 0.0;
            third[k] = top[0];
            third[K + k] = top[1];
        }
    });
    r.t_pivots = ms_since(t0);

    // 5. Hypotheses: clique h = (a, b, third[h]) with (a, b) = pivot h mod K. A clique that repeats (as a
    // set) gives the same hypothesis; only its first occurrence can be argmax's answer, so it is scored once.
    t0 = Clock::now();
    const int64_t H = 2 * K;
    r.n_hypotheses = H;
    std::vector<int64_t> uniq;
    uniq.reserve(H);
    {
        std::unordered_map<uint64_t, int64_t> seen;
        seen.reserve(2 * H);
        for (int64_t h = 0; h < H; ++h) {
            int64_t v[3] = {flat[h % K] / n, flat[h % K] % n, third[h]};
            std::sort(v, v + 3);
            const uint64_t key = ((uint64_t)v[0] * (uint64_t)n + (uint64_t)v[1]) * (uint64_t)n + (uint64_t)v[2];
            if (seen.emplace(key, h).second) uniq.push_back(h);
        }
    }
    r.n_unique = (int64_t)uniq.size();
    const Scorer scorer(src, tgt, n, p.tau_inlier);
    std::vector<double> best_score(nthreads, -1.0);
    std::vector<int64_t> best_h(nthreads, -1);
    std::vector<Pose> best_pose(nthreads);
    DynamicRange hyps(0, (int64_t)uniq.size(), 32);
    parallel_region(nthreads, [&](int tid) {
        std::vector<int32_t> scratch;
        int64_t lo, hi;
        while (hyps.next(lo, hi)) for (int64_t u = lo; u < hi; ++u) {
            const int64_t h = uniq[u];
            const int32_t idx[3] = {(int32_t)(flat[h % K] / n), (int32_t)(flat[h % K] % n), (int32_t)third[h]};
            const Pose T = kabsch_weighted(src, tgt, idx, 3, nullptr, 1e-6);
            const double s = scorer.score(T, scratch, p.metric);
            if (s > best_score[tid]) {  // each thread's chunks ascend: its first best stays
                best_score[tid] = s;
                best_h[tid] = h;
                best_pose[tid] = T;
            }
        }
    });
    int bt = -1;
    for (int t = 0; t < nthreads; ++t)
        if (best_h[t] >= 0 && (bt < 0 || best_score[t] > best_score[bt] ||
                               (best_score[t] == best_score[bt] && best_h[t] < best_h[bt])))
            bt = t;
    const int64_t h = best_h[bt];
    r.clique[0] = flat[h % K] / n;
    r.clique[1] = flat[h % K] % n;
    r.clique[2] = third[h];
    r.score = best_score[bt];
    r.pose_unrefined = best_pose[bt];
    r.t_hypotheses = ms_since(t0);

    t0 = Clock::now();
    r.pose = post_refinement(r.pose_unrefined, src, tgt, n, p.tau_inlier, p.refine_iters, &r.refine_iters_run);
    r.t_pose = ms_since(t0);
    return r;
}

}  // namespace fastmac
