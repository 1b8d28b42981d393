// Node-guided selection computed directly: for every node, the heaviest clique of size >= min_size that
// contains it, by branch and bound, without enumerating every maximal clique.
//
// Why this is the selection (spec 4): every edge weight G_ij is positive, so a clique of size >= m
// that is heaviest among the cliques of size >= m containing node v is maximal (adding a vertex adds
// weight and keeps the size >= m). Node-guided selection gives v exactly that clique, the earliest in
// canonical order among equally heavy ones. So the selection is a per-node maximum-edge-weight clique
// problem; NodeChoice (selection.hpp) applies the tie rule to whatever cliques the search offers, and
// the search offers every clique that is at least as heavy as the best one known for some member.
//
// The search, in three steps:
//  1. Lower bounds. For every node, a greedy clique through it (add the candidate most attached to the
//     clique so far); each clique raises the lower bound lb of all its members.
//  2. The heaviest clique overall, w*. Branch and bound from every vertex in degeneracy order (each
//     clique searched from its lowest-ranked vertex, as in Eppstein, Loeffler and Strash), against the
//     best weight so far. Every clique of weight >= w* (ties included) is offered, so a node whose
//     lower bound reaches w* is done: no clique through it can be heavier.
//  3. Every other node: one more pass over the same roots with a target per node (its lower bound,
//     raised by what is found): a branch is explored only while it can still hold a clique that beats
//     the target of one of its members. On near-cliques (the nodes that can be in a clique linked at a
//     density >= 0.9) instead one search per node v left to do, over all of N(v) with v's target alone:
//     there every other candidate may be dropped when dominated (below), which the shared pass can do
//     only for nodes already done. Steps 2 and 3 run serially, so their work (hence the node
//     budget) does not depend on the thread count or on timing. (Parallel rounds that freeze the
//     targets between them were tried: 1.6x the speed per node on 2 cores, but up to 2.3x the nodes on
//     dense synthetic KITTI-like graphs, where the first roots raise many targets.)
// Near-cliques (issue 11): every maximal clique is the nodes adjacent to all others plus a maximal
// independent set of the sparse "conflict" graph of missing edges, and the selection is a quadratic
// choice over the conflicts. Two prunings for branches with few conflicts (at most 16 per candidate):
//  - Dominance: candidates y and x not adjacent, every candidate adjacent to y adjacent to x, and
//    a_x - a_y + sum over y's candidate neighbours z of min(0, G_xz - G_yz) clearly positive (a: the
//    attachment to the clique so far). Swapping y for x in any clique of the branch is then strictly
//    heavier for every member but y, so y leaves the candidates (into X) unless y itself still needs a
//    clique. It is the reduction of branch and reduce for vertex cover/independent set (e.g. Akiba and
//    Iwata, "Branch-and-reduce exponential/FPT algorithms in practice", TCS 2016: dominance rule),
//    weighted here by the worst case of the quadratic terms.
//  - Matching colouring: a greedy colouring splits conflict paths badly (a path of 6 into two pairs
//    and two single classes) and each extra class adds a whole candidate to the bound; classes from a
//    matching of the conflicts grown by augmenting paths (Kuhn) are used where they bound tighter.
// On the reduced outdoor graphs of bench_search.py they cut the search nodes 10-250x (the 50,000-pair
// cases at 5 % from over 1e6 nodes, capped, to 2,500-5,500, exact).
// On near-cliques every root's local graph is nearly the whole graph: steps 1-3 then share one graph
// built once (Searcher::make_global) instead of building one per root, which was cubic in its size.
// The default search ("auto", mac.cpp) runs the enumeration first, under a work budget: on sparse
// graphs it is 1.5-3x faster than this search; this one takes over where the enumeration explodes.
// The branch and bound (per search): candidates P with a greedy colouring in independent sets (Tomita's
// MCQ/MCS), a clique takes one vertex per colour class at most; visiting the classes in order, each
// member contributes its attachment to R (sum of G to the chosen vertices) plus at most, for every
// earlier class, its heaviest edge into that class. The bound for the branch on the vertex at position
// i is the sum over the classes up to i of the largest such contribution (an edge-weighted colouring
// bound in the spirit of San Segundo, Coniglio, Furini and Ljubic, "A new branch-and-bound algorithm
// for the maximum edge-weighted clique problem", EJOR 2019). Branches whose bound is below the target
// (with a relative slack of 1e-9 for summation order) cannot hold a clique anyone needs.
//
// Without a cap hit the result equals the full enumeration's selection, ties included.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <string>

#include "interrupt.hpp"
#include "mac_core.hpp"
#include "parallel.hpp"
#include "selection.hpp"

namespace fastmac {

namespace {

constexpr double kSlack = 1e-9;  // bounds sum in another order than the canonical weight: cut only clearly
// A dominated candidate must lose by this much relative to the clique's weight (summation order, ties).
constexpr double kDominanceMargin = 1e-9;
// A branch is a near-clique while its candidates have at most this many conflicts (non-adjacent ordered
// pairs) per candidate; there dominance and the matching colouring pay, elsewhere their checks would cost
// more than they save.
constexpr int64_t kNearCliqueConflicts = 16;

// Step 3 runs one search per node left to do where the nodes that can be in a clique are at least this
// dense (near-cliques: 0.95-0.999 on the reduced outdoor graphs; sparse indoor graphs ~0.01).
constexpr double kPerNodeDensity = 0.9;
// Step 1 skips the nodes an earlier greedy clique covers on graphs at least this dense (see step 1).
constexpr double kCoverDensity = 0.5;
// The work counted (Searcher::work) in units of about a nanosecond of one core: a counted step took
// 2.5-4.2 ns on the graphs measured (the greedy cliques of a dense 2,476-node graph, per-root set-ups and
// branches there and on 50,000 real 3DMatch FPFH matches), so each counts 3 units (0.8-1.4 ns).
constexpr int64_t kWorkScale = 3;
// Steps 2 and 3 on a near-clique search one graph built once (Searcher::make_global) up to this many
// nodes (its weight matrix: 8 bytes per pair, 128 MB at the cap); above it, one local graph per root.
constexpr int64_t kGlobalMax = 4096;

inline int popcount64(uint64_t x) { return __builtin_popcountll(x); }

inline double ms_between(std::chrono::steady_clock::time_point a, std::chrono::steady_clock::time_point b) {
    return std::chrono::duration<double, std::milli>(b - a).count();
}

struct Control {
    int64_t max_nodes = 0;  // for steps 2 and 3 together (they run serially on one searcher)
    int64_t max_work = 0;   // likewise, in work units (Searcher::work)
    bool timed = false;
    std::chrono::steady_clock::time_point deadline;
    std::atomic<bool> stop{false};
    std::atomic<int> why{0};  // 1 = max_nodes, 2 = time limit, 3 = interrupted, 4 = max_work
    void halt(int reason) {
        int expected = 0;
        why.compare_exchange_strong(expected, reason);
        stop.store(true);
    }
};

class Searcher {
   public:
    Searcher(const AdjGraph &g, const std::vector<double> &vals, int min_size, NodeChoice &choice, Control &ctl,
             int tid)
        : g_(g), vals_(vals), min_size_(min_size), choice_(choice), ctl_(ctl), tid_(tid), loc_(g.n, -1) {}

    int64_t nodes = 0, offered = 0;
    // Work done: the inner-loop steps of the greedy cliques, set-ups, branches and bounds (each
    // kWorkScale units of ~1 ns; what max_work caps).
    int64_t work = 0;
    int64_t work_units() const { return work * kWorkScale; }
    bool capped = false;  // some search ran out of its node budget
    bool work_capped = false;  // ... of its work budget
    std::vector<std::pair<int32_t, double>> raised;  // (node, weight) of every clique offered
    Interrupt *interrupt = nullptr;                  // thread 0 only

    // Branch and bound over the maximal cliques that contain `root`, lie in root + cand and are not
    // extended by any vertex of excl (cand, excl: neighbours of root), offering every one whose weight
    // reaches `target`; target rises with what is found.
    void search(int32_t root, const std::vector<int32_t> &cand, const std::vector<int32_t> &excl, double &target) {
        if ((int)cand.size() + 1 < min_size_) return;
        if (!setup(root, cand, excl)) return;
        target_ = &target;
        targets_ = nullptr;
        aborted_ = false;
        R_.clear();
        expand(0, 0.0);
        capped = capped || aborted_;
    }

    // The same over the maximal cliques whose lowest-ranked vertex is root, with a target per node:
    // a clique is wanted when it reaches the target of one of its members (targets[v] = infinity:
    // v needs nothing more). Targets rise with what is found.
    void search_all(int32_t root, const std::vector<int32_t> &cand, const std::vector<int32_t> &excl,
                    std::vector<double> &targets) {
        if ((int)cand.size() + 1 < min_size_) return;
        if (!setup(root, cand, excl)) return;
        targets_ = &targets;
        aborted_ = false;
        R_.clear();
        expand(0, 0.0);
        capped = capped || aborted_;
    }

    // A heavy maximal clique through z, built greedily (each step adds the candidate most attached to
    // the clique so far), offered as a starting lower bound for its members.
    void greedy(int32_t z) {
        if (global_) {
            greedy_global(z);
            return;
        }
        C_.clear();
        ca_.clear();
        for (int64_t p = g_.ptr[z]; p < g_.ptr[z + 1]; ++p) {
            C_.push_back(g_.col[p]);
            ca_.push_back(vals_[p]);
        }
        members_.assign(1, z);
        while (!C_.empty()) {
            size_t k = 0;
            for (size_t q = 1; q < C_.size(); ++q)
                if (ca_[q] > ca_[k]) k = q;
            const int32_t x = C_[k];
            members_.push_back(x);
            work += 2 * (int64_t)C_.size() + (g_.ptr[x + 1] - g_.ptr[x]);
            // C = C n N(x), attachments += G(x, .): a merge of two sorted lists
            size_t out = 0, q = 0;
            int64_t p = g_.ptr[x];
            const int64_t pe = g_.ptr[x + 1];
            while (q < C_.size() && p < pe) {
                if (C_[q] < g_.col[p]) {
                    ++q;
                } else if (g_.col[p] < C_[q]) {
                    ++p;
                } else {
                    C_[out] = C_[q];
                    ca_[out] = ca_[q] + vals_[p];
                    ++out;
                    ++q;
                    ++p;
                }
            }
            C_.resize(out);
            ca_.resize(out);
        }
        if ((int)members_.size() < min_size_) return;
        std::sort(members_.begin(), members_.end());
        greedy_.push_back(members_);
    }

    std::vector<std::vector<int32_t>> greedy_;  // the greedy cliques of this thread, weighed later

    // greedy() on the global graph: the same picks (ties to the lowest node index, as the merge of sorted
    // rows keeps the first) and the same sums, so the same cliques.
    void greedy_global(int32_t z) {
        members_.assign(1, z);
        const int r = loc_[z];
        if (r >= 0) {
            U_.assign(adj_.begin() + (size_t)r * W_, adj_.begin() + (size_t)(r + 1) * W_);
            if (ca_.size() < (size_t)np_) ca_.resize(np_);
            const double *gr = gm_.data() + (size_t)r * np_;
            for (int w = 0; w < W_; ++w)
                for (uint64_t bits = U_[w]; bits; bits &= bits - 1) {
                    const int x = w * 64 + __builtin_ctzll(bits);
                    ca_[x] = gr[x];
                }
            for (;;) {
                int k = -1;
                for (int w = 0; w < W_; ++w)
                    for (uint64_t bits = U_[w]; bits; bits &= bits - 1) {
                        const int x = w * 64 + __builtin_ctzll(bits);
                        if (k < 0 || ca_[x] > ca_[k] || (ca_[x] == ca_[k] && L_[x] < L_[k])) k = x;
                        work += 2;  // this candidate's test here and its update below
                    }
                if (k < 0) break;
                members_.push_back(L_[k]);
                work += 2 * W_;
                const uint64_t *rk = adj_.data() + (size_t)k * W_;
                const double *gk = gm_.data() + (size_t)k * np_;
                for (int w = 0; w < W_; ++w) {
                    U_[w] &= rk[w];
                    for (uint64_t bits = U_[w]; bits; bits &= bits - 1) {
                        const int x = w * 64 + __builtin_ctzll(bits);
                        ca_[x] += gk[x];
                    }
                }
            }
        }
        if ((int)members_.size() < min_size_) return;
        std::sort(members_.begin(), members_.end());
        greedy_.push_back(members_);
    }

    // Offers a clique found outside the search (members ascending, weight w).
    void offer_clique(const std::vector<int32_t> &m, double w) {
        members_ = m;
        offer(w);
    }

    // Near-cliques: the local graph of a root is nearly the whole graph, and building it per root (its
    // bits and an np x np weight matrix) is cubic over the roots; it dominated the search on the largest
    // reduced graphs (50,000 correspondences at 10 % inliers: 738 nodes, ~130 roots). Instead one graph of
    // `nodes` (the nodes that can be in a clique of size >= min_size, in rank order) is built once, and a
    // root's search takes its candidates and excluded vertices as bit masks over it. Nodes outside it can
    // be dropped: a clique of size >= min_size has no member, and no vertex extending it, of degree
    // < min_size - 1. The bits run in rank order, as the per-root graphs' candidates do.
    void make_global(const std::vector<int32_t> &nodes) {
        global_ = true;
        index_local(nodes, {});
        adj_.assign((size_t)nl_ * W_, 0);
        gm_.assign((size_t)np_ * np_, 0.0);
        for (int k = 0; k < np_; ++k) {
            const int32_t u = L_[k];
            uint64_t *row = adj_.data() + (size_t)k * W_;
            double *grow = gm_.data() + (size_t)k * np_;
            for (int64_t p = g_.ptr[u]; p < g_.ptr[u + 1]; ++p) {
                const int32_t x = loc_[g_.col[p]];
                if (x < 0) continue;
                row[x >> 6] |= uint64_t(1) << (x & 63);
                grow[x] = vals_[p];
            }
        }
    }

    bool is_global() const { return global_; }

    // NodeChoice::weight's sum, in its order (so bit-identical), from the global graph's weight matrix
    // where there is one: the cliques of a near-clique have hundreds of members, and a galloping search
    // per pair in the rows of the graph cost ~1-4 ms per clique (a third of the search at 50,000 / 10 %).
    double weigh(const std::vector<int32_t> &m) {
        if (!global_) return choice_.weight(m.data(), m.size());
        const size_t k = m.size();
        hit_.resize(k);
        for (size_t a = 0; a < k; ++a) hit_[a] = loc_[m[a]];
        double s = 0.0;
        for (size_t b = 1; b < k; ++b) {
            const double *row = gm_.data() + (size_t)hit_[b] * np_;
            for (size_t a = 0; a < b; ++a) s += row[hit_[a]];
        }
        return s;
    }

   private:
    struct Level {
        std::vector<uint64_t> P, X;       // candidates, excluded vertices (bits over the local indices)
        std::vector<double> a;            // attach(u) for u in P
        std::vector<int32_t> order, col;  // P in colour order, and each one's colour (1-based)
        std::vector<double> val;          // bound on each one's contribution to a clique (same order)
    };

    const AdjGraph &g_;
    const std::vector<double> &vals_;
    const int min_size_;
    NodeChoice &choice_;
    Control &ctl_;
    const int tid_;
    std::vector<int32_t> loc_, L_, R_, members_, C_, hit_;
    std::vector<double> ca_;
    std::vector<uint64_t> adj_, U_, Q_;
    std::vector<double> gm_;  // local weights, np x np (0 = no edge)
    std::vector<Level> levels_;
    int np_ = 0, nl_ = 0, W_ = 0;  // candidates are local 0..np-1, excluded np..nl-1
    int32_t root_ = 0;
    double *target_ = nullptr;             // one target for every node (search), or
    std::vector<double> *targets_ = nullptr;  // a target per node (search_all)
    bool aborted_ = false;
    bool global_ = false;  // make_global: one graph for every root
    const bool dominance_ = !env_is("FASTMAC_DOMINANCE", "off");
    const bool matching_ = !env_is("FASTMAC_MATCHING", "off");
    std::vector<int32_t> mv_, hp_, hc_, hdeg_, mate_, vis_, order2_, col2_;
    std::vector<std::pair<int, int>> by_degree_;
    std::vector<double> val2_;
    int stamp_ = 0;

    // The root's graph: candidates local 0..np-1, excluded np..nl-1 (or, after make_global, the masks over
    // the global graph). False when too few candidates are left to reach min_size.
    bool setup(int32_t root, const std::vector<int32_t> &cand, const std::vector<int32_t> &excl) {
        if (global_) return setup_global(root, cand, excl);
        index_local(cand, excl);
        // Local adjacency from the rows of the candidates only: candidate-candidate bits both ways,
        // candidate-excluded bits into both rows. Excluded-excluded bits are never read (pivots count
        // neighbours among the candidates; X is only ever intersected with candidates' rows), and
        // excluded vertices never join a clique here, so weights are among the candidates only.
        // Each candidate's row is first compacted to its local neighbours (local_neighbours), then
        // written (through a register for one-word rows).
        adj_.assign((size_t)nl_ * W_, 0);
        gm_.assign((size_t)np_ * np_, 0.0);
        work += (int64_t)nl_ * W_ + (int64_t)np_ * np_ / 4;
        for (int k = 0; k < np_; ++k) {
            const int32_t u = L_[k];
            work += g_.ptr[u + 1] - g_.ptr[u];
            const int64_t p0 = g_.ptr[u], c = local_neighbours(g_, loc_, u, hit_);
            const int32_t *hit = hit_.data();
            uint64_t *row = adj_.data() + (size_t)k * W_;
            double *grow = gm_.data() + (size_t)k * np_;
            const uint64_t bit_k = uint64_t(1) << (k & 63);
            uint64_t *col_k = adj_.data() + (k >> 6);
            uint64_t word = 0;
            for (int64_t h = 0; h < c; ++h) {
                const int64_t p = p0 + hit[h];
                const int32_t x = loc_[g_.col[p]];
                if (W_ == 1)
                    word |= uint64_t(1) << x;
                else
                    row[x >> 6] |= uint64_t(1) << (x & 63);
                col_k[(size_t)x * W_] |= bit_k;  // symmetric (a candidate x's own row sets it too)
                if (x < np_) grow[x] = vals_[p];
            }
            if (W_ == 1) row[0] |= word;
        }
        if ((int)levels_.size() < np_ + 2) levels_.resize(np_ + 2);
        Level &top = levels_[0];
        top.P.assign(W_, 0);
        top.X.assign(W_, 0);
        top.a.assign(np_, 0.0);
        for (int k = 0; k < np_; ++k) top.P[k >> 6] |= uint64_t(1) << (k & 63);
        for (int k = np_; k < nl_; ++k) top.X[k >> 6] |= uint64_t(1) << (k & 63);
        for (int64_t p = g_.ptr[root]; p < g_.ptr[root + 1]; ++p) {
            const int32_t x = loc_[g_.col[p]];
            if (x >= 0 && x < np_) top.a[x] = vals_[p];
        }
        for (int k = 0; k < nl_; ++k) loc_[L_[k]] = -1;
        root_ = root;
        return true;
    }

    // Local indices: cand as 0..np-1, then excl as np..nl-1 (loc_: node -> local index).
    void index_local(const std::vector<int32_t> &cand, const std::vector<int32_t> &excl) {
        L_ = cand;
        L_.insert(L_.end(), excl.begin(), excl.end());
        np_ = (int)cand.size();
        nl_ = (int)L_.size();
        W_ = (nl_ + 63) / 64;
        for (int k = 0; k < nl_; ++k) loc_[L_[k]] = k;
    }

    bool setup_global(int32_t root, const std::vector<int32_t> &cand, const std::vector<int32_t> &excl) {
        const int r = loc_[root];
        if (r < 0) return false;
        work += 2 * W_ + (int64_t)(cand.size() + excl.size()) + np_;
        if ((int)levels_.size() < np_ + 2) levels_.resize(np_ + 2);
        Level &top = levels_[0];
        top.P.assign(W_, 0);
        top.X.assign(W_, 0);
        int count = 0;
        for (int32_t x : cand)
            if (loc_[x] >= 0) {
                top.P[loc_[x] >> 6] |= uint64_t(1) << (loc_[x] & 63);
                ++count;
            }
        if (count + 1 < min_size_) return false;
        for (int32_t x : excl)
            if (loc_[x] >= 0) top.X[loc_[x] >> 6] |= uint64_t(1) << (loc_[x] & 63);
        top.a.assign(np_, 0.0);
        const double *gr = gm_.data() + (size_t)r * np_;
        for (int w = 0; w < W_; ++w)
            for (uint64_t bits = top.P[w]; bits; bits &= bits - 1) {
                const int x = w * 64 + __builtin_ctzll(bits);
                top.a[x] = gr[x];
            }
        root_ = root;
        return true;
    }

    int popcount_words(const uint64_t *x) const {
        int c = 0;
        for (int w = 0; w < W_; ++w) c += popcount64(x[w]);
        return c;
    }

    bool should_stop() {
        if (aborted_ || ctl_.stop.load(std::memory_order_relaxed)) return true;
        // The budget of the whole selection is spent (steps 2 and 3 are serial, on this searcher): stop
        // every search, not only this one (the roots left would each pay their set-up for nothing).
        if (ctl_.max_nodes > 0 && nodes > ctl_.max_nodes) {
            aborted_ = true;
            ctl_.halt(1);
            return true;
        }
        if (ctl_.max_work > 0 && work_units() > ctl_.max_work) {
            aborted_ = true;
            work_capped = true;
            ctl_.halt(4);
            return true;
        }
        if ((nodes & 255) == 0) {
            if (ctl_.timed && std::chrono::steady_clock::now() > ctl_.deadline) {
                ctl_.halt(2);
                return true;
            }
            if (interrupt && interrupt->check()) {
                ctl_.halt(3);
                return true;
            }
        }
        return false;
    }

    // members_ (ascending) is a clique of weight w: offer it to its members, note the lower bounds.
    void offer(double w) {
        ++offered;
        choice_.offer(tid_, members_.data(), members_.size(), w);
        for (int32_t x : members_) raised.emplace_back(x, w);
    }

    // R (with the root) is a clique that no candidate extends.
    void leaf(double w_upper) {
        if ((int)R_.size() + 1 < min_size_) return;
        if (w_upper < need_r() * (1.0 - kSlack)) return;
        members_.clear();
        members_.push_back(root_);
        for (int32_t r : R_) members_.push_back(L_[r]);
        std::sort(members_.begin(), members_.end());
        const double w = weigh(members_);
        offer(w);
        if (!targets_) {
            *target_ = std::max(*target_, w);
        } else {
            for (int32_t x : members_)
                if ((*targets_)[x] < w) (*targets_)[x] = w;
        }
    }

    double need_r() const {
        if (!targets_) return *target_;
        double m = (*targets_)[root_];
        for (int32_t r : R_) m = std::min(m, (*targets_)[L_[r]]);
        return m;
    }

    // Can this branch (R, the colouring of P in lv, bound ub) hold a clique that someone needs? With
    // one target: ub must reach it. With a target per node: ub must reach the target of a member of
    // R, or, for some candidate z, the bound on the cliques through z must reach z's target (the same
    // sum with z in its class and, in every other class, the best member adjacent to z).
    bool wanted(const Level &lv, double wR, double ub) {
        if (!targets_) return ub >= *target_ * (1.0 - kSlack);
        const std::vector<double> &t = *targets_;
        if (ub >= need_r() * (1.0 - kSlack)) return true;
        const int cnt = (int)lv.order.size();
        for (int i = 0; i < cnt; ++i) {
            const int z = lv.order[i];
            const double tz = t[L_[z]];
            if (!(ub >= tz * (1.0 - kSlack))) continue;  // infinite or out of reach anyway
            const uint64_t *rz = adj_.data() + (size_t)z * W_;
            work += cnt;
            double uz = wR + lv.val[i], best = 0.0;
            int c = lv.col[0];
            for (int j = 0; j < cnt; ++j) {
                if (lv.col[j] != c) {
                    uz += best;
                    best = 0.0;
                    c = lv.col[j];
                }
                const int x = lv.order[j];
                if (rz[x >> 6] >> (x & 63) & 1) best = std::max(best, lv.val[j]);
            }
            uz += best;
            if (uz >= tz * (1.0 - kSlack)) return true;
        }
        return false;
    }

    // Dominance (near-cliques): candidates x and y that are not adjacent, where every candidate adjacent
    // to y is adjacent to x, and x's attachment to R plus the worst case over y's candidate neighbours z,
    // a_x - a_y + sum_z min(0, G_xz - G_yz), is clearly positive. Then swapping y for x in any clique of
    // this branch that holds y gives a clique that is strictly heavier for every other member, so a
    // clique through y can only be needed by y itself; when y needs nothing (its target is met), y moves
    // from P to X (leaves it extends are not maximal; their swap with x is searched). The condition is
    // inherited by the branch's descendants (P shrinks; members of P that join R turn their worst case
    // into the exact term). Chains are sound: a dominator must still be in P, and each swap is strictly
    // heavier. Returns the number of candidates dropped.
    int drop_dominated(Level &lv) {
        uint64_t *P = lv.P.data(), *X = lv.X.data();
        int dropped = 0;
        for (int w = 0; w < W_; ++w)
            for (uint64_t bits = P[w]; bits; bits &= bits - 1) {
                const int y = w * 64 + __builtin_ctzll(bits);
                if (targets_ && !std::isinf((*targets_)[L_[y]])) continue;  // y still needs its best clique
                const uint64_t *ry = adj_.data() + (size_t)y * W_;
                const double *gy = gm_.data() + (size_t)y * np_;
                work += W_;
                bool gone = false;
                for (int k = 0; k < W_ && !gone; ++k)
                    for (uint64_t xb = P[k] & ~ry[k]; xb && !gone; xb &= xb - 1) {
                        const int x = k * 64 + __builtin_ctzll(xb);
                        if (x == y) continue;
                        const uint64_t *rx = adj_.data() + (size_t)x * W_;
                        bool subset = true;
                        for (int q = 0; q < W_ && subset; ++q) subset = (P[q] & ry[q] & ~rx[q]) == 0;
                        if (!subset) continue;
                        const double *gx = gm_.data() + (size_t)x * np_;
                        work += 4 * W_;
                        double gain = lv.a[x] - lv.a[y], scale = lv.a[x];
                        for (int q = 0; q < W_; ++q)
                            for (uint64_t zb = P[q] & ry[q]; zb; zb &= zb - 1) {
                                const int z = q * 64 + __builtin_ctzll(zb);
                                gain += std::min(0.0, gx[z] - gy[z]);
                                scale += gx[z];
                            }
                        if (gain > kDominanceMargin * scale) {
                            P[w] &= ~(uint64_t(1) << (y & 63));
                            X[w] |= uint64_t(1) << (y & 63);
                            ++dropped;
                            gone = true;
                        }
                    }
            }
        return dropped;
    }

    // The bound of a colouring (lv.order, lv.col: classes in order, colours 1, 2, ...): over the classes
    // in order, each member contributes attach(u) plus, for every earlier class, at most its heaviest edge
    // into that class; a clique takes one member per class. Fills lv.val (each member's contribution).
    double colour_bound(Level &lv, double wR) {
        const int cnt = (int)lv.order.size();
        lv.val.resize(cnt);
        double ub = wR, curA = 0.0;
        int cur = 0, class_start = 0;
        for (int i = 0; i < cnt; ++i) {
            const int u = lv.order[i];
            if (lv.col[i] != cur) {
                ub += curA;
                curA = 0.0;
                cur = lv.col[i];
                class_start = i;
            }
            const double *gu = gm_.data() + (size_t)u * np_;
            work += class_start;
            double beta = 0.0, best = 0.0;
            int c = 1;
            for (int j = 0; j < class_start; ++j) {
                if (lv.col[j] != c) {
                    beta += best;
                    best = 0.0;
                    c = lv.col[j];
                }
                best = std::max(best, gu[lv.order[j]]);
            }
            beta += best;
            lv.val[i] = lv.a[u] + beta;
            curA = std::max(curA, lv.val[i]);
        }
        return ub + curA;
    }

    // Colour classes of one or two candidates: the pairs of a matching of the conflict graph on P (two
    // non-adjacent candidates are an independent set), grown greedily (fewest conflicts first) and then
    // by augmenting paths (Kuhn's search with every vertex of the path marked, so that a path found in a
    // non-bipartite conflict graph is still a simple alternating path; it may miss some, which only
    // costs tightness). Classes in candidate order. Returns their number.
    int matching_classes(const uint64_t *P, Level &lv) {
        mv_.clear();
        for (int w = 0; w < W_; ++w)
            for (uint64_t bits = P[w]; bits; bits &= bits - 1) mv_.push_back(w * 64 + __builtin_ctzll(bits));
        if ((int)mate_.size() < np_) {
            mate_.assign(np_, -1);
            vis_.assign(np_, 0);
        }
        hp_.assign(np_, 0);  // conflict lists (hc_ from hp_[u], ended by -1), by local vertex
        hdeg_.assign(np_, 0);
        hc_.clear();
        for (int u : mv_) {
            const uint64_t *ru = adj_.data() + (size_t)u * W_;
            hp_[u] = (int32_t)hc_.size();
            for (int k = 0; k < W_; ++k)
                for (uint64_t b = P[k] & ~ru[k]; b; b &= b - 1) {
                    const int x = k * 64 + __builtin_ctzll(b);
                    if (x != u) hc_.push_back(x);
                }
            hdeg_[u] = (int32_t)hc_.size() - hp_[u];
            mate_[u] = -1;
            hc_.push_back(-1);
        }
        by_degree_.clear();
        for (int u : mv_) by_degree_.emplace_back(hdeg_[u], u);
        std::sort(by_degree_.begin(), by_degree_.end());
        for (auto [d, u] : by_degree_) {
            if (d == 0 || mate_[u] >= 0) continue;
            int best = -1;
            for (int32_t q = hp_[u]; hc_[q] >= 0; ++q) {
                const int x = hc_[q];
                if (mate_[x] < 0 && (best < 0 || hdeg_[x] < hdeg_[best])) best = x;
            }
            if (best >= 0) mate_[u] = best, mate_[best] = u;
        }
        for (auto [d, s] : by_degree_) {
            if (d == 0 || mate_[s] >= 0) continue;
            if (++stamp_ == 0) {
                std::fill(vis_.begin(), vis_.end(), 0);
                stamp_ = 1;
            }
            vis_[s] = stamp_;
            augment(s);
        }
        lv.order.clear();
        lv.col.clear();
        int colour = 0;
        for (int u : mv_) {
            if (mate_[u] >= 0 && mate_[u] < u) continue;  // listed with its mate
            lv.order.push_back(u);
            lv.col.push_back(++colour);
            if (mate_[u] >= 0) {
                lv.order.push_back(mate_[u]);
                lv.col.push_back(colour);
            }
        }
        return colour;
    }

    bool augment(int u) {
        for (int32_t q = hp_[u]; hc_[q] >= 0; ++q) {
            const int x = hc_[q];
            if (vis_[x] == stamp_) continue;
            vis_[x] = stamp_;
            if (mate_[x] < 0) {
                mate_[x] = u;
                mate_[u] = x;
                return true;
            }
            const int w = mate_[x];
            if (vis_[w] == stamp_) continue;
            vis_[w] = stamp_;
            if (augment(w)) {
                mate_[x] = u;
                mate_[u] = x;
                return true;
            }
        }
        return false;
    }

    void expand(int depth, double wR) {
        ++nodes;
        if (should_stop()) return;
        const size_t r_size = R_.size();
        branch(depth, wR);
        R_.resize(r_size);  // drop the vertices absorbed at this level
    }

    void branch(int depth, double wR) {
        Level &lv = levels_[depth];
        uint64_t *P = lv.P.data(), *X = lv.X.data();

        int left = 0;
        for (int w = 0; w < W_; ++w) left += popcount64(P[w]);
        work += 2 * (int64_t)left * W_ + W_;  // the universal check and the colouring
        // A candidate adjacent to every other candidate is in every maximal clique of this branch:
        // move it into R (near-cliques have many).
        for (int w = 0; w < W_; ++w)
            for (uint64_t bits = P[w]; bits; bits &= bits - 1) {
                const int u = w * 64 + __builtin_ctzll(bits);
                const uint64_t *ru = adj_.data() + (size_t)u * W_;
                int c = 0;
                for (int k = 0; k < W_; ++k) c += popcount64(P[k] & ru[k]);
                if (c != left - 1) continue;
                P[w] &= ~(uint64_t(1) << (u & 63));
                --left;
                for (int k = 0; k < W_; ++k) X[k] &= ru[k];
                wR += lv.a[u];
                const double *gu = gm_.data() + (size_t)u * np_;
                for (int k = 0; k < W_; ++k)
                    for (uint64_t b2 = P[k]; b2; b2 &= b2 - 1) {
                        const int x = k * 64 + __builtin_ctzll(b2);
                        lv.a[x] += gu[x];
                    }
                R_.push_back(u);
                work += W_ + left;
            }
        if (left == 0) {
            for (int w = 0; w < W_; ++w)
                if (X[w]) return;  // an excluded vertex extends R: not maximal, searched elsewhere
            leaf(wR);
            return;
        }
        // Greedy sequential colouring of P: classes are independent sets, listed class by class.
        U_.assign(P, P + W_);
        Q_.resize(W_);
        lv.order.clear();
        lv.col.clear();
        int colour = 0;
        while (left > 0) {
            ++colour;
            std::copy(U_.begin(), U_.end(), Q_.begin());
            for (int w = 0; w < W_; ++w) {
                while (Q_[w]) {
                    const int u = w * 64 + __builtin_ctzll(Q_[w]);
                    const uint64_t *ru = adj_.data() + (size_t)u * W_;
                    for (int k = w; k < W_; ++k) Q_[k] &= ~ru[k];
                    Q_[w] &= ~(uint64_t(1) << (u & 63));
                    U_[w] &= ~(uint64_t(1) << (u & 63));
                    lv.order.push_back(u);
                    lv.col.push_back(colour);
                    --left;
                }
            }
        }
        if ((int)R_.size() + 1 + colour < min_size_) return;
        double ub = colour_bound(lv, wR);
        if (!wanted(lv, wR, ub)) return;
        // Near-cliques (few conflicts, i.e. non-adjacent candidate pairs), only where the greedy bound did
        // not cut: (1) the greedy colouring pairs conflicting candidates greedily and each class it leaves
        // over adds a whole candidate to the bound; classes from a larger matching of the conflicts often
        // bound much tighter (the smaller bound is kept); (2) dominated candidates leave P.
        if ((matching_ || dominance_) && (int)lv.order.size() > 2) {
            const int cnt0 = (int)lv.order.size();
            work += (int64_t)cnt0 * W_;
            int64_t conflicts = 0;
            for (int w = 0; w < W_; ++w)
                for (uint64_t bits = P[w]; bits; bits &= bits - 1) {
                    const uint64_t *ru = adj_.data() + (size_t)(w * 64 + __builtin_ctzll(bits)) * W_;
                    int c = 0;
                    for (int k = 0; k < W_; ++k) c += popcount64(P[k] & ru[k]);
                    conflicts += cnt0 - 1 - c;
                }
            if (conflicts <= kNearCliqueConflicts * (int64_t)cnt0) {
                if (matching_ && colour > (cnt0 + 1) / 2) {
                    order2_.swap(lv.order);
                    col2_.swap(lv.col);
                    val2_.swap(lv.val);
                    const int classes = matching_classes(P, lv);
                    const double ub2 = classes < colour ? colour_bound(lv, wR) : INFINITY;
                    if (ub2 < ub) {
                        ub = ub2;
                        colour = classes;
                    } else {
                        order2_.swap(lv.order);
                        col2_.swap(lv.col);
                        val2_.swap(lv.val);
                    }
                    if ((int)R_.size() + 1 + colour < min_size_ || !wanted(lv, wR, ub)) return;
                }
                if (dominance_ && drop_dominated(lv) > 0) {
                    // the classes without the dropped candidates (still a colouring of the new P)
                    size_t out = 0;
                    for (size_t i = 0; i < lv.order.size(); ++i) {
                        const int u = lv.order[i];
                        if (!(P[u >> 6] >> (u & 63) & 1)) continue;
                        lv.order[out] = u;
                        lv.col[out] = lv.col[i];
                        ++out;
                    }
                    lv.order.resize(out);
                    lv.col.resize(out);
                    ub = colour_bound(lv, wR);
                    if (!wanted(lv, wR, ub)) return;
                }
            }
        }
        const int cnt = (int)lv.order.size();

        // Pivot (Tomita): the vertex of P u X with the most neighbours in P. A maximal clique of this
        // branch contains a non-neighbour of the pivot, so only those are branched on.
        int pivot = -1, most = -1;
        work += (int64_t)(cnt + popcount_words(X)) * W_;
        for (int w = 0; w < W_ && most < cnt; ++w)
            for (uint64_t bits = P[w] | X[w]; bits; bits &= bits - 1) {
                const int u = w * 64 + __builtin_ctzll(bits);
                const uint64_t *ru = adj_.data() + (size_t)u * W_;
                int c = 0;
                for (int k = 0; k < W_; ++k) c += popcount64(P[k] & ru[k]);
                if (c > most) {
                    most = c;
                    pivot = u;
                    if (c == cnt) break;
                }
            }
        const uint64_t *rp = adj_.data() + (size_t)pivot * W_;
        Level &ch = levels_[depth + 1];
        ch.P.resize(W_);
        ch.X.resize(W_);
        ch.a.resize(np_);
        // Branch on the pivot's non-neighbours, heaviest colour classes last (as MCQ), i.e. in reverse
        // colour order.
        for (int i = cnt - 1; i >= 0; --i) {
            const int u = lv.order[i];
            if (u != pivot && (rp[u >> 6] >> (u & 63) & 1)) continue;
            const uint64_t *ru = adj_.data() + (size_t)u * W_;
            uint64_t *NP = ch.P.data(), *NX = ch.X.data();
            P = lv.P.data();
            X = lv.X.data();
            for (int w = 0; w < W_; ++w) {
                NP[w] = P[w] & ru[w];
                NX[w] = X[w] & ru[w];
            }
            const double *gu = gm_.data() + (size_t)u * np_;
            work += 2 * W_ + cnt;
            for (int w = 0; w < W_; ++w)
                for (uint64_t bits = NP[w]; bits; bits &= bits - 1) {
                    const int x = w * 64 + __builtin_ctzll(bits);
                    ch.a[x] = lv.a[x] + gu[x];
                }
            R_.push_back(u);
            expand(depth + 1, wR + lv.a[u]);
            R_.pop_back();
            if (aborted_ || ctl_.stop.load(std::memory_order_relaxed)) return;
            P[u >> 6] &= ~(uint64_t(1) << (u & 63));
            X[u >> 6] |= uint64_t(1) << (u & 63);
        }
    }
};

// Runs body(item, searcher) for item in [0, count) on the threads; the caller (thread 0) then waits for
// the others where Ctrl-C can still be seen.
template <class F>
void run_parallel(int64_t count, int64_t chunk, int nthreads, std::vector<std::unique_ptr<Searcher>> &searchers,
                  Control &ctl, Interrupt &interrupt, F &&body) {
    DynamicRange range(0, count, chunk);
    Inside inside;
    parallel_region(nthreads, [&](int tid) {
        inside.enter();
        int64_t lo, hi;
        while (!ctl.stop.load(std::memory_order_relaxed) && range.next(lo, hi))
            for (int64_t k = lo; k < hi && !ctl.stop.load(std::memory_order_relaxed); ++k)
                body(k, *searchers[tid]);
        inside.leave();
        if (tid == 0)
            inside.wait([&] {
                if (interrupt.check()) ctl.halt(3);
            });
    });
}

}  // namespace

int64_t heaviest_cliques(const AdjGraph &g, const std::vector<double> &vals, int min_size, const CliqueCaps &caps,
                         std::string &cap_hit, int64_t &search_nodes, int nthreads, NodeChoice &choice,
                         int64_t *work) {
    const auto t_setup = std::chrono::steady_clock::now();
    cap_hit.clear();
    search_nodes = 0;
    if (work) *work = 0;
    if (min_size < 1) min_size = 1;
    nthreads = resolve_threads(nthreads, g.n);
    const int64_t n = g.n;

    Control ctl;
    ctl.max_nodes = caps.max_nodes;
    ctl.max_work = caps.max_work;
    if (caps.time_limit_s > 0) {
        ctl.timed = true;
        ctl.deadline = std::chrono::steady_clock::now() +
                       std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                           std::chrono::duration<double>(caps.time_limit_s));
    }
    choice.start(nthreads);
    Interrupt interrupt;
    std::vector<std::unique_ptr<Searcher>> searchers;
    for (int t = 0; t < nthreads; ++t) searchers.emplace_back(new Searcher(g, vals, min_size, choice, ctl, t));
    searchers[0]->interrupt = &interrupt;
    std::vector<double> lb(n, 0.0);
    auto collect = [&]() {  // the lower bounds raised by the cliques offered so far (max: any order)
        for (auto &s : searchers) {
            for (auto [v, w] : s->raised) lb[v] = std::max(lb[v], w);
            s->raised.clear();
        }
    };
    auto degree = [&](int64_t v) { return g.ptr[v + 1] - g.ptr[v]; };

    // Near-cliques: the nodes that can be in a clique are nearly all linked (0.95-0.999 on the reduced
    // outdoor graphs, ~0.01 on sparse indoor ones). There step 1 skips covered nodes and step 3 runs per
    // node (see the top of this file).
    int64_t active = 0, active_edges = 0;
    for (int64_t v = 0; v < n; ++v)
        if (degree(v) + 1 >= min_size) {
            ++active;
            active_edges += degree(v);
        }
    const bool near_clique =
        (double)active_edges >= kPerNodeDensity * (double)active * (double)(active - 1) && active > 1;
    // Step 1's greedy cliques cost ~degree x clique size each, cubic in the graph's size where it is
    // dense: above this density each node an earlier greedy clique covers takes its bound from that one.
    const bool dense =
        (double)active_edges >= kCoverDensity * (double)active * (double)(active - 1) && active > 1;
    const bool per_node =
        env_is("FASTMAC_STEP3", "pernode") || (near_clique && !env_is("FASTMAC_STEP3", "shared"));

    // The rank order of steps 2 and 3 (each clique searched from its lowest-ranked vertex), and on a
    // near-clique the one graph they search (Searcher::make_global; step 1 weighs its cliques on it).
    const std::vector<int32_t> order = degeneracy_order(g);
    std::vector<int32_t> rank(n);
    for (int64_t i = 0; i < n; ++i) rank[order[i]] = (int32_t)i;
    if (near_clique && active <= kGlobalMax && !env_is("FASTMAC_GLOBAL_GRAPH", "off")) {
        std::vector<int32_t> nodes;
        nodes.reserve(active);
        for (int32_t v : order)
            if (degree(v) + 1 >= min_size) nodes.push_back(v);
        searchers[0]->make_global(nodes);
    }

    const auto t_start = std::chrono::steady_clock::now();
    // 1. a greedy clique through every node; cliques from neighbouring seeds often coincide, so each
    // distinct one is weighed and offered once (in node order: the count does not depend on threads).
    // On a near-clique the greedy cliques are huge and nearly all the same: serially, a node that an
    // earlier one covers takes its lower bound from it.
    if (dense) {
        std::vector<char> covered(n, 0);
        Searcher &s0 = *searchers[0];
        for (int64_t v = 0; v < n && !ctl.stop.load(); ++v) {
            if (degree(v) + 1 < min_size || covered[v]) continue;
            if (ctl.max_work > 0 && s0.work_units() > ctl.max_work) {  // serial here, so counted as steps 2-3 are
                s0.capped = s0.work_capped = true;
                ctl.halt(4);
                break;
            }
            const size_t before = s0.greedy_.size();
            s0.greedy((int32_t)v);
            if (s0.greedy_.size() > before)
                for (int32_t x : s0.greedy_.back()) covered[x] = 1;
            if (interrupt.check()) ctl.halt(3);
        }
    } else {
        run_parallel(n, 64, nthreads, searchers, ctl, interrupt, [&](int64_t v, Searcher &s) {
            if (degree(v) + 1 >= min_size) s.greedy((int32_t)v);
        });
        // how it split between the threads depends on timing: the work budget counts steps 2 and 3 only
        // here (each greedy clique of a sparse graph is cheap)
        for (auto &s : searchers) s->work = 0;
    }
    {
        std::vector<const std::vector<int32_t> *> all;
        for (auto &s : searchers)
            for (const auto &m : s->greedy_) all.push_back(&m);
        std::sort(all.begin(), all.end(), [](const auto *a, const auto *b) { return *a < *b; });
        all.erase(std::unique(all.begin(), all.end(), [](const auto *a, const auto *b) { return *a == *b; }),
                  all.end());
        Searcher &s0 = *searchers[0];
        for (const auto *m : all) s0.offer_clique(*m, s0.weigh(*m));
        for (auto &s : searchers) std::vector<std::vector<int32_t>>().swap(s->greedy_);
    }
    collect();

    const auto t_step1 = std::chrono::steady_clock::now();
    // 2. the heaviest clique overall, from the dense core outwards (serial: one shared target)
    double best = 0.0;
    for (int64_t v = 0; v < n; ++v) best = std::max(best, lb[v]);
    double gmax = 0.0;
    for (double x : vals) gmax = std::max(gmax, x);
    {
        std::vector<int32_t> cand, excl;
        Searcher &s = *searchers[0];
        for (int64_t i = n - 1; i >= 0 && !ctl.stop.load(); --i) {
            const int32_t v = order[i];
            cand.clear();
            excl.clear();
            for (int64_t p = g.ptr[v]; p < g.ptr[v + 1]; ++p)
                (rank[g.col[p]] > i ? cand : excl).push_back(g.col[p]);
            // no clique of root + cand can reach best: skip the root's setup (costly on near-cliques)
            const double most = 0.5 * (double)cand.size() * (double)(cand.size() + 1) * gmax;
            if (most < best * (1.0 - kSlack)) continue;
            std::sort(cand.begin(), cand.end(), [&](int32_t a, int32_t b) { return rank[a] < rank[b]; });
            s.search(v, cand, excl, best);
        }
    }
    collect();

    const bool debug = std::getenv("FASTMAC_DEBUG_SEARCH") != nullptr;
    const auto t_step2 = std::chrono::steady_clock::now();
    int64_t step2_nodes = 0;
    for (auto &s : searchers) step2_nodes += s->nodes;
    // 3. the nodes whose lower bound is below the heaviest clique: one search over the maximal cliques
    // again, now wanting a clique only where it beats the target of one of its members
    std::vector<double> targets(n, INFINITY);
    int64_t n_todo = 0;
    for (int64_t v = 0; v < n; ++v)
        if (degree(v) + 1 >= min_size && lb[v] < best * (1.0 - kSlack)) {
            targets[v] = lb[v];
            ++n_todo;
        }
    if (n_todo > 0 && per_node) {
        std::vector<int32_t> cand;
        const std::vector<int32_t> none;
        Searcher &s = *searchers[0];
        for (int64_t v = 0; v < n && !ctl.stop.load(); ++v) {
            if (!std::isfinite(targets[v])) continue;
            collect();
            if (lb[v] >= best * (1.0 - kSlack)) continue;
            cand.assign(g.col.begin() + g.ptr[v], g.col.begin() + g.ptr[v + 1]);
            std::sort(cand.begin(), cand.end(), [&](int32_t a, int32_t b) { return rank[a] < rank[b]; });
            double t = lb[v];
            s.search((int32_t)v, cand, none, t);
        }
    } else if (n_todo > 0) {
        std::vector<int32_t> cand, excl;
        Searcher &s = *searchers[0];
        for (int64_t i = n - 1; i >= 0 && !ctl.stop.load(); --i) {
            const int32_t v = order[i];
            cand.clear();
            excl.clear();
            bool wanted = std::isfinite(targets[v]);
            for (int64_t p = g.ptr[v]; p < g.ptr[v + 1]; ++p) {
                const int32_t x = g.col[p];
                if (rank[x] > i) {
                    cand.push_back(x);
                    wanted = wanted || std::isfinite(targets[x]);
                } else {
                    excl.push_back(x);
                }
            }
            if (!wanted) continue;
            std::sort(cand.begin(), cand.end(), [&](int32_t a, int32_t b) { return rank[a] < rank[b]; });
            s.search_all(v, cand, excl, targets);
        }
    }

    if (debug && std::getenv("FASTMAC_DEBUG_REPEAT")) {  // step 3 again, starting from the final targets
        int64_t before = 0;
        for (auto &s : searchers) before += s->nodes;
        std::vector<double> t2(n, INFINITY);
        for (int64_t v = 0; v < n; ++v) if (std::isfinite(targets[v])) t2[v] = targets[v];
        std::vector<int32_t> cand, excl;
        Searcher &s = *searchers[0];
        for (int64_t i = n - 1; i >= 0; --i) {
            const int32_t v = order[i];
            cand.clear(); excl.clear();
            bool wanted = std::isfinite(t2[v]);
            for (int64_t p = g.ptr[v]; p < g.ptr[v + 1]; ++p) {
                const int32_t x = g.col[p];
                if (rank[x] > i) { cand.push_back(x); wanted = wanted || std::isfinite(t2[x]); } else excl.push_back(x);
            }
            if (!wanted) continue;
            std::sort(cand.begin(), cand.end(), [&](int32_t a, int32_t b) { return rank[a] < rank[b]; });
            s.search_all(v, cand, excl, t2);
        }
        int64_t after = 0;
        for (auto &s : searchers) after += s->nodes;
        std::fprintf(stderr, "repeat of step 3 with exact targets: %lld nodes\n", (long long)(after - before));
    }
    if (debug) {
        int64_t all = 0, all_work = 0;
        for (auto &s : searchers) all += s->nodes, all_work += s->work_units();
        std::fprintf(stderr,
                     "heaviest: best %.6g, step 2 nodes %lld, step 3: %lld nodes to do, %lld nodes; %s graph; "
                     "work %lld; ms: set-up %.1f, step 1 %.1f, step 2 %.1f, step 3 %.1f\n", best, (long long)step2_nodes, (long long)n_todo, (long long)(all - step2_nodes),
                     searchers[0]->is_global() ? "one global" : "per-root", (long long)all_work,
                     ms_between(t_setup, t_start), ms_between(t_start, t_step1), ms_between(t_step1, t_step2),
                     ms_between(t_step2, std::chrono::steady_clock::now()));
    }
    int64_t offered = 0;
    bool capped = false, work_capped = false;
    for (auto &s : searchers) {
        offered += s->offered;
        search_nodes += s->nodes;
        if (work) *work += s->work_units();
        capped = capped || s->capped;
        work_capped = work_capped || s->work_capped;
    }
    if (capped) ctl.halt(work_capped ? 4 : 1);
    switch (ctl.why.load()) {
        case 1: cap_hit = "max_nodes=" + std::to_string(caps.max_nodes); break;
        case 4: cap_hit = "max_work=" + std::to_string(caps.max_work); break;
        case 2: {
            char buf[64];
            std::snprintf(buf, sizeof buf, "time_limit=%gs", caps.time_limit_s);
            cap_hit = buf;
            break;
        }
        case 3: throw Interrupted();
        default: break;
    }
    return offered;
}

}  // namespace fastmac
