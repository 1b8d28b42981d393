// MAC end to end (spec 2-5): graphs, clustering/reduction, maximal cliques, node-guided selection,
// hypotheses, MAE scoring and refinement. Mirrors fastmac_exp/backends/python_mac.py.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <ctime>
#include <functional>
#include <memory>

#include "mac_core.hpp"
#include "parallel.hpp"
#include "selection.hpp"

namespace fastmac {

namespace {

#ifdef FASTMAC_THREAD_CPU_CLOCK
// Profiling builds (-DFASTMAC_THREAD_CPU_CLOCK): stage times in CPU time of the calling thread, which
// a busy machine does not inflate. Meaningful with num_threads=1 only.
struct Clock {
    using time_point = double;
    static double now() {
        timespec ts;
        clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
        return ts.tv_sec * 1e3 + ts.tv_nsec * 1e-6;
    }
};
inline double ms_since(double t0) { return Clock::now() - t0; }
#else
using Clock = std::chrono::steady_clock;
inline double ms_since(Clock::time_point t0) {
    return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}
#endif

// The reference code's Otsu threshold on the clustering coefficients, quirks included (spec 2.4, 9.7).
double otsu(const std::vector<double> &cc) {
    const double lo = *std::min_element(cc.begin(), cc.end());
    const double hi = *std::max_element(cc.begin(), cc.end());
    const double dflt = (hi - lo) / 2.0;
    if (hi == 0.0 || hi == lo) return dflt;
    const double h = (hi - lo) / 100.0;
    double hist[100] = {0}, sums[100] = {0};
    for (double v : cc) {
        double b = std::floor(v / h);
        int bi = b >= 99.0 ? 99 : (b < 0.0 ? 0 : (int)b);
        hist[bi] += 1.0;
        sums[bi] += v;
    }
    double total_n = 0, total_s = 0;
    for (int i = 0; i < 100; ++i) {
        total_n += hist[i];
        total_s += sums[i];
    }
    double n1 = 0, s1 = 0, best = -1000.0;
    int best_i = -1;
    for (int i = 0; i < 100; ++i) {
        n1 += hist[i];
        s1 += sums[i];
        if (n1 == 0) continue;
        const double n2 = total_n - n1;
        if (n2 == 0) break;
        const double m1 = s1 / n1, m2 = (total_s - s1) / n2;
        const double score = n1 * n2 * (m1 - m2) * (m1 - m2);
        if (score > best) {
            best = score;
            best_i = i;
        }
    }
    return best_i < 0 ? dflt : best_i * (hi - lo) / 100.0;
}

// Cube roots of x[0, len) to a few ulp (measured: at most 7.8e-15 relative over 23 M values from 2^-90
// to 2^12), ~5x faster than a scalar version with a guess from the double's exponent and ~20x faster
// than std::cbrt: a guess from the float's bits divided by 3 (Kahan's constant), then two of Halley's
// steps, each of which cubes the relative error; branch-free, so the loop vectorises. Right for x >=
// 2^-100 (a normal float); cube_roots_of fixes the others. Used on graphs with more entries than 300 nodes
// can have (the 1,000 FastMAC@20 keeps of a dense KITTI pair: std::cbrt was ~15 % of MAC; the ~500 that
// register(samples="auto") keeps there: 6 % of a call); smaller graphs, among them every C++/Python parity
// test (<= 300 nodes), keep std::cbrt.
constexpr int64_t kFastCbrtEdges = 300 * 299 + 1;

#if defined(__GNUC__) && defined(__x86_64__) && !defined(__clang__)
__attribute__((target_clones("avx512f", "avx2", "default")))
#endif
void cube_roots(const double *x, int64_t len, double *y) {
    for (int64_t p = 0; p < len; ++p) {
        const double v = x[p];
        const float f = (float)v;
        uint32_t u;
        std::memcpy(&u, &f, sizeof(u));
        u = u / 3 + 0x2A5137A0u;
        float g;
        std::memcpy(&g, &u, sizeof(g));
        double r = g;
        const double r3 = r * r * r;
        r = r * (r3 + 2.0 * v) / (2.0 * r3 + v);
        const double s3 = r * r * r;
        y[p] = r * (s3 + 2.0 * v) / (2.0 * s3 + v);
    }
}

// C = G^(1/3) entry by entry (0 where G is 0), rows in parallel.
std::vector<double> cube_roots_of(const Csr &W, const std::vector<double> &G, int nthreads) {
    const int64_t *ptr = W.ptr.data();
    std::vector<double> C(G.size());
    if (W.nnz() >= kFastCbrtEdges) {
        parallel_for(0, W.n, nthreads, 64, [&](int64_t i, int) {
            cube_roots(G.data() + ptr[i], ptr[i + 1] - ptr[i], C.data() + ptr[i]);
            for (int64_t p = ptr[i]; p < ptr[i + 1]; ++p)
                if (!(G[p] >= 0x1p-100)) C[p] = G[p] != 0.0 ? std::cbrt(G[p]) : 0.0;
        });
    } else {
        parallel_for(0, W.n, nthreads, 64, [&](int64_t i, int) {
            for (int64_t p = ptr[i]; p < ptr[i + 1]; ++p) C[p] = G[p] != 0.0 ? std::cbrt(G[p]) : 0.0;
        });
    }
    return C;
}

// The enumeration's side of node-guided selection: each maximal clique, as it is found, is offered
// to its members (selection.hpp), so no clique list is ever stored.
class SelectSink : public CliqueSink {
   public:
    explicit SelectSink(NodeChoice &choice) : choice_(choice) {}
    void start(int nthreads) override { choice_.start(nthreads); }
    void add(int tid, const int32_t *m, size_t k) override { choice_.offer(tid, m, k, choice_.weight(m, k)); }
    const std::vector<double> *weights() const override { return &choice_.values(); }
    void add_weighted(int tid, const int32_t *m, size_t k, double w) override { choice_.offer(tid, m, k, w); }

   private:
    NodeChoice &choice_;
};

}  // namespace

Clustering clustering(const Csr &W, const std::vector<double> &G, int nthreads) {
    const int64_t n = W.n;
    const int64_t *ptr = W.ptr.data();
    // w_i = sum over neighbour pairs {a, b} of i with G_ab != 0 of (G_ia G_ib G_ab)^(1/3)
    //     = 1/2 sum_a C_ia (C C)_ia with C = G^(1/3) on G's support: the second-order product of C.
    // Rows in parallel (cbrt is ~20 ns a value, and an outdoor graph has ~10^5-10^6 of them); the sums
    // over rows run serially in row order, so the result does not depend on the number of threads.
    const int rt = resolve_threads(nthreads, std::max<int64_t>(n, W.nnz() / 64));
    const std::vector<double> C = cube_roots_of(W, G, rt);
    const std::vector<double> S = masked_square(W, C, nthreads);
    Clustering out;
    out.cc.assign(n, 0.0);
    std::vector<double> tri(n, 0.0), pairs(n, 0.0);
    parallel_for(0, n, rt, 64, [&](int64_t i, int) {
        double t = 0.0;
        int64_t deg = 0;
        for (int64_t p = ptr[i]; p < ptr[i + 1]; ++p) {
            t += S[p];
            deg += G[p] != 0.0;
        }
        tri[i] = t * 0.5;
        if (deg > 1) pairs[i] = (double)deg * (double)(deg - 1) / 2.0;
    });
    double tri_sum = 0.0, pair_sum = 0.0, cc_sum = 0.0;
    for (int64_t i = 0; i < n; ++i) {
        if (pairs[i] > 0.0) {
            out.cc[i] = tri[i] / pairs[i];
            tri_sum += tri[i];
            pair_sum += pairs[i];
        }
        cc_sum += out.cc[i];
    }
    out.avg = n > 0 ? cc_sum / (double)n : 0.0;
    out.total = pair_sum > 0 ? tri_sum / pair_sum : 0.0;
    out.otsu = n > 0 ? otsu(out.cc) : 0.0;
    return out;
}

Search parse_search(const std::string &name) {
    if (name == "bnb") return Search::Heaviest;
    if (name == "enumerate") return Search::Enumerate;
    if (name == "auto") return Search::Auto;
    throw std::invalid_argument("search must be 'auto', 'bnb' or 'enumerate', got '" + name + "'");
}

const char *search_name(Search s) {
    switch (s) {
        case Search::Heaviest: return "bnb";
        case Search::Enumerate: return "enumerate";
        default: return "auto";
    }
}

int64_t clique_search(const AdjGraph &g, const std::vector<double> &vals, int min_size, Search search,
                      const CliqueCaps &caps, std::string &cap_hit, int64_t &search_nodes, int nthreads,
                      NodeChoice &choice, Search *used, int64_t *work, int64_t *bnb_work) {
    search_nodes = 0;
    if (work) *work = 0;
    if (bnb_work) *bnb_work = 0;
    SelectSink sink(choice);
    if (search == Search::Enumerate) {
        if (used) *used = Search::Enumerate;
        return enumerate_maximal_cliques(g, min_size, caps, cap_hit, nthreads, sink);
    }
    CliqueCaps rest = caps;
    if (search == Search::Auto && caps.enumerate_work_per_node > 0) {
        // the enumeration under its work budget (max_cliques is for search=enumerate: a partial list is
        // never used here)
        CliqueCaps first = caps;
        first.max_cliques = 0;
        GiveUp give_up;
        int64_t active = 0;  // the nodes that can be in a clique
        for (int64_t v = 0; v < g.n; ++v) active += g.ptr[v + 1] - g.ptr[v] + 1 >= min_size;
        give_up.above = caps.enumerate_work_per_node * active;
        const auto t0 = Clock::now();
        const int64_t found = enumerate_maximal_cliques(g, min_size, first, cap_hit, nthreads, sink, &give_up);
        if (work) *work = give_up.work;
        if (!give_up.gave_up) {
            if (used) *used = Search::Enumerate;
            return found;
        }
        // the time limit covers both searches together
        if (rest.time_limit_s > 0) rest.time_limit_s = std::max(1e-6, rest.time_limit_s - ms_since(t0) / 1e3);
    }
    if (used) *used = Search::Heaviest;
    return heaviest_cliques(g, vals, min_size, rest, cap_hit, search_nodes, nthreads, choice, bnb_work);
}

CliqueList node_guided_selection(const AdjGraph &g, const std::vector<double> &vals, int min_size, Search search,
                                 const CliqueCaps &caps, std::string &cap_hit, int64_t &n_cliques,
                                 int64_t &search_nodes, int nthreads) {
    NodeChoice choice(g, vals);
    n_cliques = clique_search(g, vals, min_size, search, caps, cap_hit, search_nodes, nthreads, choice, nullptr);
    return choice.finish();
}

MacResult mac(const double *src, const double *tgt, int64_t n, const MacParams &p, int nthreads) {
    const int requested = nthreads;  // 0 = automatic: each stage decides by its own amount of work
    if (n < 3) throw RegistrationFailed("need at least 3 correspondences, got " + std::to_string(n));
    if (!(p.inlier_threshold > 0)) throw std::invalid_argument("inlier_threshold must be positive");
    if (n > INT32_MAX) throw std::invalid_argument("too many correspondences");
    MacResult res;
    const double tau = p.inlier_threshold;

    // ---- graph: W and G
    auto t0 = Clock::now();
    // By each stage's own work: FastMAC@20's 1,000 keeps of a dense outdoor pair are under kSerialBelow
    // correspondences, but their 500,000 pairs and their 200,000-edge clique graph are worth two threads.
    Csr W = first_order(src, tgt, n, p.graph, requested);
    std::vector<double> G = second_order(W, requested);
    res.t_graph = ms_since(t0);
    res.n_edges = W.n_edges();
    double gmax = 0.0;
    for (int64_t i = 0; i < n; ++i)
        for (int64_t q = W.upper[i]; q < W.ptr[i + 1]; ++q)
            if (G[q] > 0.0) {
                ++res.n_sog_edges;
                gmax = std::max(gmax, G[q]);
            }
    if (res.n_sog_edges == 0)
        throw RegistrationFailed("graph has no second-order edge (" + std::to_string(res.n_edges) +
                                 " first-order edges among " + std::to_string(n) + " correspondences)");

    // ---- cliques: optional reduction (spec 2.5), then the search on G's support
    t0 = Clock::now();
    std::vector<char> good;  // empty = no reduction
    // Each triangle term is (G_ia G_ib G_ab)^(1/3) <= (rowmax_i^2 gmax)^(1/3), so
    // cc_i <= rowmax_i^(2/3) gmax^(1/3); when the mean of that bound is <= 3, avg <= 3 and the
    // condition min(otsu, avg, total) > 3 cannot hold: the clustering coefficients are not needed.
    double avg_bound = 0.0;
    for (int64_t i = 0; i < n; ++i) {
        double rowmax = 0.0;
        for (int64_t q = W.ptr[i]; q < W.ptr[i + 1]; ++q) rowmax = std::max(rowmax, G[q]);
        avg_bound += std::cbrt(rowmax * rowmax * gmax);
    }
    avg_bound /= (double)n;
    if (p.reduction && n > 50 && avg_bound > 3.0 * (1.0 - 1e-9)) {
        Clustering cl = clustering(W, G, requested);
        const double cmax = *std::max_element(cl.cc.begin(), cl.cc.end());
        if (cmax != 0.0 && std::min(cl.otsu, std::min(cl.avg, cl.total)) > 3.0) {
            const double m = std::max(cl.otsu, cl.total);
            std::vector<double> sorted = cl.cc;
            std::sort(sorted.begin(), sorted.end(), std::greater<double>());
            const double c50 = sorted[std::min<int64_t>(49, n - 1)];
            double f = 10.0;
            while (f * m > c50) f -= 0.05;
            const double cut = f * m;
            good.assign(n, 0);
            for (int64_t i = 0; i < n; ++i) good[i] = cl.cc[i] > cut;
            res.reduced = true;
        }
    }
    // The clique graph: G's support (reduced or not), with G's values alongside for the clique weights
    // (reduction removes edges but never changes the values of those it keeps).
    AdjGraph cg;
    std::vector<double> cgw;
    cg.n = n;
    cg.ptr.assign(n + 1, 0);
    cg.col.reserve(2 * res.n_sog_edges);
    cgw.reserve(2 * res.n_sog_edges);
    for (int64_t i = 0; i < n; ++i) {
        for (int64_t q = W.ptr[i]; q < W.ptr[i + 1]; ++q) {
            if (G[q] > 0.0 && (good.empty() || (good[i] && good[W.col[q]]))) {
                cg.col.push_back(W.col[q]);
                cgw.push_back(G[q]);
            }
        }
        cg.ptr[i + 1] = (int64_t)cg.col.size();
    }
    // The weights need only the clique graph from here on: free W and G before the search.
    W = Csr();
    std::vector<double>().swap(G);
    CliqueCaps caps;
    caps.max_cliques = p.max_cliques;
    caps.max_nodes = p.max_nodes;
    caps.max_work = p.max_work;
    caps.time_limit_s = p.time_limit_s;
    caps.enumerate_work_per_node = p.enumerate_budget;
    NodeChoice choice(cg, cgw);
    // Threads by the graph's edges as well as its nodes: FastMAC@20's 791 keeps of a 3DMatch fragment make
    // a 12,825-edge graph with 14,726 maximal cliques (4.9 ms on one thread, 3.4 on two); on the real pairs
    // two threads paid from ~1,500 edges and cost at most ~0.02 ms below (docs/clique_search.md).
    const bool search_pays = n >= kSerialBelow || (int64_t)cg.col.size() >= 2 * kSearchThreadsFromEdges;
    res.n_cliques = clique_search(cg, cgw, p.min_clique_size, p.search, caps, res.cap_hit, res.search_nodes,
                                  threads_if(requested, search_pays), choice, &res.search_used,
                                  &res.enumerate_work, &res.search_work);
    res.t_cliques = ms_since(t0);
    if (res.n_cliques == 0)
        throw RegistrationFailed("no maximal clique of size >= " + std::to_string(p.min_clique_size));

    // ---- node-guided selection (spec 4): merge the per-thread choices, deduplicate by first owner
    t0 = Clock::now();
    CliqueList selected = choice.finish();
    res.n_selected = (int64_t)selected.size();
    if (p.return_selected) res.selected = selected;
    res.t_selection = ms_since(t0);

    // ---- hypotheses, scores, refinement (spec 5)
    t0 = Clock::now();
    const int64_t nh = (int64_t)selected.size();
    double best_score = 0.0;
    int64_t best_h = -1;
    const Scorer scorer(src, tgt, n, tau);
    // Per thread: the best (score, -index); chunks are handed out in increasing order, so within a
    // thread a strict > keeps the earliest of equal scores. Reduced the same way: deterministic.
    // Threads by the work (nh fits, each scored over n rows): a fragment's FastMAC@20, 0.80 -> 0.44 ms.
    const int hyp_threads = threads_if(requested, nh > 16 && nh * n >= kHypothesisThreadsFromWork);
    std::vector<double> t_score(hyp_threads, 0.0);
    std::vector<int64_t> t_h(hyp_threads, -1);
    if (p.return_hypotheses) {
        res.hyp_poses.resize(nh);
        res.hyp_scores.resize(nh);
    }
    DynamicRange hyps(0, nh, 16);
    parallel_region(hyp_threads, [&](int tid) {
        std::vector<int32_t> scratch;
        int64_t lo, hi;
        while (hyps.next(lo, hi)) for (int64_t h = lo; h < hi; ++h) {
            const Pose T = kabsch(src, tgt, selected.begin(h), (int64_t)selected.len(h), nullptr);
            const double s = scorer.score(T, scratch);
            if (p.return_hypotheses) {
                res.hyp_poses[h] = T;
                res.hyp_scores[h] = s;
            }
            if (s > t_score[tid]) {
                t_score[tid] = s;
                t_h[tid] = h;
            }
        }
    });
    for (int t = 0; t < hyp_threads; ++t) {
        if (t_h[t] < 0) continue;
        if (best_h < 0 || t_score[t] > best_score || (t_score[t] == best_score && t_h[t] < best_h)) {
            best_score = t_score[t];
            best_h = t_h[t];
        }
    }
    if (best_h < 0 || !(best_score > 0.0)) throw RegistrationFailed("no hypothesis has a positive score");
    res.score = best_score;
    res.clique.assign(selected.begin(best_h), selected.begin(best_h) + selected.len(best_h));
    res.pose_unrefined = kabsch(src, tgt, selected.begin(best_h), (int64_t)selected.len(best_h), nullptr);

    Pose pose = res.pose_unrefined;
    std::vector<double> e(n);
    std::vector<int32_t> inl;
    std::vector<double> wts;
    double prev = best_score;
    for (int it = 0; it < p.refine_iters; ++it) {
        const double s = mae_score(pose, src, tgt, n, tau, e.data());
        if (s < prev) break;
        prev = s;
        weighted_inliers(e.data(), n, tau, inl, wts);
        if (inl.size() < 3) break;
        pose = kabsch(src, tgt, inl.data(), (int64_t)inl.size(), wts.data());
    }
    res.pose = pose;
    res.t_pose = ms_since(t0);
    return res;
}

}  // namespace fastmac
