// Maximal cliques: Bron-Kerbosch with Tomita pivoting, run from each vertex in degeneracy order
// (Eppstein, Loeffler and Strash 2010). Each root's subproblem (later neighbours P, earlier
// neighbours X) is solved on local bitsets, so set operations are word-parallel; roots are independent
// and run in parallel. The result is put in canonical order (members ascending, list lexicographic).
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstring>
#include <numeric>


#include "interrupt.hpp"
#include "mac_core.hpp"
#include "parallel.hpp"

namespace fastmac {

AdjGraph adj_from_edges(int64_t n, const int64_t *ei, const int64_t *ej, int64_t m) {
    if (n < 0) throw std::invalid_argument("n must be non-negative");
    if (n > INT32_MAX) throw std::invalid_argument("n must be below 2^31");
    AdjGraph g;
    g.n = n;
    g.ptr.assign(n + 1, 0);
    for (int64_t e = 0; e < m; ++e) {
        const int64_t a = ei[e], b = ej[e];
        if (a < 0 || a >= n || b < 0 || b >= n)
            throw std::invalid_argument("edge (" + std::to_string(a) + ", " + std::to_string(b) +
                                        ") is out of range for n = " + std::to_string(n));
        if (a == b) continue;
        ++g.ptr[a + 1];
        ++g.ptr[b + 1];
    }
    for (int64_t v = 0; v < n; ++v) g.ptr[v + 1] += g.ptr[v];
    g.col.resize(g.ptr[n]);
    std::vector<int64_t> cur(g.ptr.begin(), g.ptr.end() - 1);
    for (int64_t e = 0; e < m; ++e) {
        const int64_t a = ei[e], b = ej[e];
        if (a == b) continue;
        g.col[cur[a]++] = (int32_t)b;
        g.col[cur[b]++] = (int32_t)a;
    }
    // Sort and deduplicate each row, then compact.
    int64_t out = 0;
    std::vector<int64_t> newptr(n + 1, 0);
    for (int64_t v = 0; v < n; ++v) {
        auto first = g.col.begin() + g.ptr[v], last = g.col.begin() + g.ptr[v + 1];
        std::sort(first, last);
        auto uend = std::unique(first, last);
        const int64_t len = uend - first;
        std::memmove(g.col.data() + out, g.col.data() + g.ptr[v], (size_t)len * sizeof(int32_t));
        out += len;
        newptr[v + 1] = out;
    }
    g.col.resize(out);
    g.ptr.swap(newptr);
    return g;
}

double adj_lookup(const AdjGraph &g, const std::vector<double> &vals, int32_t a, int32_t b) {
    const int32_t *first = g.col.data() + g.ptr[a];
    const int32_t *last = g.col.data() + g.ptr[a + 1];
    const int32_t *it = std::lower_bound(first, last, b);
    if (it == last || *it != b) return 0.0;
    return vals[it - g.col.data()];
}

// Degeneracy (smallest-last) order by the bucket algorithm of Batagelj and Zaversnik.
std::vector<int32_t> degeneracy_order(const AdjGraph &g) {
    const int64_t n = g.n;
    std::vector<int32_t> deg(n), vert(n), pos(n);
    int32_t md = 0;
    for (int64_t v = 0; v < n; ++v) {
        deg[v] = (int32_t)(g.ptr[v + 1] - g.ptr[v]);
        md = std::max(md, deg[v]);
    }
    std::vector<int64_t> bin(md + 2, 0);
    for (int64_t v = 0; v < n; ++v) ++bin[deg[v] + 1];
    for (int32_t d = 0; d <= md; ++d) bin[d + 1] += bin[d];
    {
        std::vector<int64_t> next(bin.begin(), bin.end() - 1);
        for (int64_t v = 0; v < n; ++v) {
            pos[v] = (int32_t)next[deg[v]]++;
            vert[pos[v]] = (int32_t)v;
        }
    }
    // bin[d] = start of the degree-d bucket.
    for (int64_t i = 0; i < n; ++i) {
        const int32_t v = vert[i];
        for (int64_t p = g.ptr[v]; p < g.ptr[v + 1]; ++p) {
            const int32_t u = g.col[p];
            if (deg[u] > deg[v]) {
                const int32_t du = deg[u];
                const int64_t pu = pos[u], pw = bin[du];
                const int32_t w = vert[pw];
                if (u != w) {
                    vert[pu] = w;
                    pos[w] = (int32_t)pu;
                    vert[pw] = u;
                    pos[u] = (int32_t)pw;
                }
                ++bin[du];
                --deg[u];
            }
        }
    }
    return vert;
}

namespace {

inline int popcount64(uint64_t x) { return __builtin_popcountll(x); }

// Work units of the give-up budget, about a nanosecond each on one core (measured on real pairs): a search
// node ~160 ns; weighing a clique, per member pair, ~12 ns from the global rows and under 1 ns from a root's
// local weights.
constexpr int64_t kNodeWork = 160;
constexpr int64_t kGlobalPairWork = 12;
constexpr int64_t kWorkBatch = 4096;
constexpr int kLocalWeights = 96;  // roots with fewer candidates weigh their cliques locally

struct Shared {
    std::atomic<bool> stop{false};
    std::atomic<int64_t> found{0};  // cliques (max_cliques only)
    std::atomic<int64_t> work{0};   // work units (give_up_work only)
    std::atomic<int> why{0};  // 1 = max_cliques, 2 = time limit, 3 = interrupted, 4 = gave up
    int64_t max_cliques = 0;
    int64_t give_up_work = 0;  // kNodeWork a search node, 1 or kGlobalPairWork a pair; 0 = never
    Interrupt *interrupt = nullptr;  // polled by thread 0 (the caller) only
    bool timed = false;
    std::chrono::steady_clock::time_point deadline;
};

class Worker {
   public:
    Worker(const AdjGraph &g, int min_size, Shared &sh, CliqueSink &sink, int tid)
        : g_(g), min_size_(min_size), sh_(sh), sink_(sink), tid_(tid), loc_(g.n, -1), vals_(sink.weights()) {}

    int64_t delivered = 0;
    int64_t unflushed = 0;  // work not yet added to sh_.work (give_up_work only)

    // Adds the unflushed work to the shared total; true when the total is above give_up_work.
    bool flush() {
        const int64_t k = sh_.work.fetch_add(unflushed) + unflushed;
        unflushed = 0;
        return k > sh_.give_up_work;
    }

    // give_up_work: the shared total is updated in batches (an atomic per search node would cost more
    // than the node). Whether the total exceeds the budget is settled after the search anyway, so the
    // answer is a property of the graph, not of the threads or their timing.
    bool over_budget(int64_t work) {
        if (sh_.give_up_work <= 0) return false;
        unflushed += work;
        if (unflushed < kWorkBatch || !flush()) return false;
        int expected = 0;
        sh_.why.compare_exchange_strong(expected, 4);
        sh_.stop.store(true);
        return true;
    }

    void run_root(int32_t v, const std::vector<int32_t> &rank) {
        const int32_t rv = rank[v];
        L_.clear();
        for (int64_t p = g_.ptr[v]; p < g_.ptr[v + 1]; ++p)
            if (rank[g_.col[p]] > rv) L_.push_back(g_.col[p]);
        const int np = (int)L_.size();
        if (np + 1 < min_size_) return;
        for (int64_t p = g_.ptr[v]; p < g_.ptr[v + 1]; ++p)
            if (rank[g_.col[p]] < rv) L_.push_back(g_.col[p]);
        const int nl = (int)L_.size();
        W_ = (nl + 63) / 64;
        Wp_ = (np + 63) / 64;
        for (int k = 0; k < nl; ++k) loc_[L_[k]] = k;
        // Local adjacency from the rows of P only: P-P bits both ways, P-X bits into both rows. X-X bits
        // are never read (pivots count neighbours in P; X is only ever intersected with rows of P).
        // Each row is first compacted to its local neighbours, then written (through a register for
        // one-word rows).
        adj_.assign((size_t)nl * W_, 0);
        // With the sink's weights (node-guided selection), small roots keep their local weights, so
        // that each clique is weighed from them (same values, same order: bit-identical to
        // NodeChoice::weight, which searches the global rows and is used for larger roots)
        local_w = vals_ != nullptr && np < kLocalWeights;
        if (local_w) wl_.assign((size_t)(np + 1) * (np + 1), 0.0);
        np_ = np;
        for (int k = 0; k < np; ++k) {
            uint64_t *row = adj_.data() + (size_t)k * W_;
            const int32_t u = L_[k];
            const int64_t p0 = g_.ptr[u], c = local_neighbours(g_, loc_, u, hit_);
            const int32_t *hit = hit_.data();
            const uint64_t bit_k = uint64_t(1) << (k & 63);
            uint64_t word = 0;
            double *wrow = local_w ? wl_.data() + (size_t)k * (np + 1) : nullptr;
            for (int64_t h = 0; h < c; ++h) {
                const int32_t x = loc_[g_.col[p0 + hit[h]]];
                if (W_ == 1)
                    word |= uint64_t(1) << x;
                else
                    row[x >> 6] |= uint64_t(1) << (x & 63);
                if (x >= np)
                    adj_[(size_t)x * W_ + (k >> 6)] |= bit_k;
                else if (wrow)
                    wrow[x] = (*vals_)[p0 + hit[h]];
            }
            if (W_ == 1) row[0] |= word;
        }
        if (local_w)  // the root's weights, as local index np
            for (int64_t p = g_.ptr[v]; p < g_.ptr[v + 1]; ++p) {
                const int32_t x = loc_[g_.col[p]];
                if (x < 0 || x >= np) continue;
                wl_[(size_t)np * (np + 1) + x] = wl_[(size_t)x * (np + 1) + np] = (*vals_)[p];
            }
        for (int k = 0; k < nl; ++k) loc_[L_[k]] = -1;

        root_ = v;
        R_.clear();
        uint64_t *P = level(0, 0), *X = level(0, 1);
        std::fill(P, P + W_, 0);
        std::fill(X, X + W_, 0);
        for (int k = 0; k < np; ++k) P[k >> 6] |= uint64_t(1) << (k & 63);
        for (int k = np; k < nl; ++k) X[k >> 6] |= uint64_t(1) << (k & 63);
        expand(0);
    }

   private:
    const AdjGraph &g_;
    const int min_size_;
    Shared &sh_;
    CliqueSink &sink_;
    const int tid_;
    std::vector<int32_t> loc_, L_, R_, hit_;
    const std::vector<double> *vals_;  // the sink's edge weights (parallel to g_.col), or null
    bool local_w = false;              // this root weighs its cliques from wl_
    int np_ = 0;
    std::vector<double> wl_;  // (np + 1)^2 local weights, the root last
    std::vector<uint64_t> pairs_;  // a member's node id (high 32 bits) and local index (low 32)
    std::vector<uint64_t> adj_;
    std::vector<std::vector<uint64_t>> levels_;  // per depth: P | X | candidates
    int W_ = 0, Wp_ = 0;
    int32_t root_ = 0;
    uint64_t calls_ = 0;
    std::vector<int32_t> tmp_;

    uint64_t *level(int depth, int which) {
        if ((int)levels_.size() <= depth) levels_.resize(depth + 1);
        auto &buf = levels_[depth];
        if (buf.size() < (size_t)3 * W_) buf.resize((size_t)3 * W_);
        return buf.data() + (size_t)which * W_;
    }
    const uint64_t *row(int u) const { return adj_.data() + (size_t)u * W_; }

    bool should_stop() {
        if (sh_.stop.load(std::memory_order_relaxed)) return true;
        if ((++calls_ & 255) != 0) return false;
        int reason = 0;
        if (sh_.timed && std::chrono::steady_clock::now() > sh_.deadline) reason = 2;
        if (tid_ == 0 && sh_.interrupt && sh_.interrupt->check()) reason = 3;
        if (reason == 0) return false;
        int expected = 0;
        sh_.why.compare_exchange_strong(expected, reason);
        sh_.stop.store(true);
        return true;
    }

    void emit() {
        if (sh_.max_cliques > 0) {
            const int64_t k = sh_.found.fetch_add(1) + 1;
            if (k > sh_.max_cliques) {
                int expected = 0;
                sh_.why.compare_exchange_strong(expected, 1);
                sh_.stop.store(true);
                return;
            }
        }
        const int64_t k = (int64_t)R_.size() + 1;
        if (over_budget(k * (k - 1) / 2 * (local_w ? 1 : kGlobalPairWork))) return;  // weighing it
        // members ascending by node id, with their local indices (the root is local index np_)
        // (node, local) packed in one integer: the node ids are distinct, so its order is theirs, and a
        // short insertion sort of integers beats std::sort's of pairs (6 % of MAC on a sparse fragment)
        pairs_.clear();
        pairs_.push_back(uint64_t(uint32_t(root_)) << 32 | uint32_t(np_));
        for (int32_t r : R_) pairs_.push_back(uint64_t(uint32_t(L_[r])) << 32 | uint32_t(r));
        if (pairs_.size() > 32) {
            std::sort(pairs_.begin(), pairs_.end());
        } else {
            for (size_t b = 1; b < pairs_.size(); ++b) {
                const uint64_t key = pairs_[b];
                size_t a = b;
                for (; a > 0 && pairs_[a - 1] > key; --a) pairs_[a] = pairs_[a - 1];
                pairs_[a] = key;
            }
        }
        tmp_.clear();
        for (const uint64_t m : pairs_) tmp_.push_back(int32_t(m >> 32));
        if (!local_w) {
            sink_.add(tid_, tmp_.data(), tmp_.size());
        } else {  // NodeChoice::weight's order: pairs (a, b), a < b, by b then a
            double w = 0.0;
            const size_t stride = (size_t)np_ + 1;
            for (size_t b = 1; b < pairs_.size(); ++b) {
                const double *wb = wl_.data() + size_t(uint32_t(pairs_[b])) * stride;
                for (size_t a = 0; a < b; ++a) w += wb[uint32_t(pairs_[a])];
            }
            sink_.add_weighted(tid_, tmp_.data(), tmp_.size(), w);
        }
        ++delivered;
    }

    void expand(int depth) {
        if (should_stop() || over_budget(kNodeWork)) return;
        uint64_t *P = level(depth, 0), *X = level(depth, 1);
        int pc = 0;
        for (int w = 0; w < Wp_; ++w) pc += popcount64(P[w]);
        if (pc == 0) {
            for (int w = 0; w < W_; ++w)
                if (X[w]) return;
            if ((int)R_.size() + 1 >= min_size_) emit();
            return;
        }
        if ((int)R_.size() + 1 + pc < min_size_) return;

        // Pivot: the vertex of P u X with the most neighbours in P.
        int pivot = -1, best = -1;
        for (int w = 0; w < W_ && best < pc; ++w) {
            uint64_t bits = (w < Wp_ ? P[w] : 0) | X[w];
            while (bits) {
                const int u = w * 64 + __builtin_ctzll(bits);
                bits &= bits - 1;
                const uint64_t *ru = row(u);
                int c = 0;
                for (int k = 0; k < Wp_; ++k) c += popcount64(P[k] & ru[k]);
                if (c > best) {
                    best = c;
                    pivot = u;
                    if (c == pc) break;
                }
            }
        }
        uint64_t *cand = level(depth, 2);
        {
            const uint64_t *rp = row(pivot);
            for (int k = 0; k < Wp_; ++k) cand[k] = P[k] & ~rp[k];
        }
        uint64_t *NP = level(depth + 1, 0), *NX = level(depth + 1, 1);
        // level() may have grown levels_ (the outer vector); inner buffers never move once sized.
        P = level(depth, 0);
        X = level(depth, 1);
        cand = level(depth, 2);
        for (int w = 0; w < Wp_; ++w) {
            uint64_t bits = cand[w];
            while (bits) {
                const int u = w * 64 + __builtin_ctzll(bits);
                bits &= bits - 1;
                const uint64_t *ru = row(u);
                for (int k = 0; k < Wp_; ++k) NP[k] = P[k] & ru[k];
                for (int k = Wp_; k < W_; ++k) NP[k] = 0;
                for (int k = 0; k < W_; ++k) NX[k] = X[k] & ru[k];
                R_.push_back(u);
                expand(depth + 1);
                R_.pop_back();
                if (sh_.stop.load(std::memory_order_relaxed)) return;
                P[w] &= ~(uint64_t(1) << (u & 63));
                X[w] |= uint64_t(1) << (u & 63);
            }
        }
    }
};

}  // namespace

int64_t enumerate_maximal_cliques(const AdjGraph &g, int min_size, const CliqueCaps &caps, std::string &cap_hit,
                                  int nthreads, CliqueSink &sink, GiveUp *give_up) {
    cap_hit.clear();
    if (give_up) give_up->gave_up = false;
    if (min_size < 1) min_size = 1;
    nthreads = resolve_threads(nthreads, g.n);
    // With a count cap, run serially so that the partial set is reproducible.
    if (caps.max_cliques > 0) nthreads = 1;
    const int64_t n = g.n;
    const std::vector<int32_t> order = degeneracy_order(g);
    std::vector<int32_t> rank(n);
    for (int64_t i = 0; i < n; ++i) rank[order[i]] = (int32_t)i;

    Shared sh;
    sh.max_cliques = caps.max_cliques;
    sh.give_up_work = give_up ? std::max<int64_t>(1, give_up->above) : 0;
    if (caps.time_limit_s > 0) {
        sh.timed = true;
        sh.deadline = std::chrono::steady_clock::now() +
                      std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                          std::chrono::duration<double>(caps.time_limit_s));
    }

    Interrupt interrupt;
    sh.interrupt = &interrupt;
    sink.start(nthreads);
    std::vector<int64_t> counts(nthreads, 0);
    DynamicRange roots(0, n, 4);
    Inside inside;
    parallel_region(nthreads, [&](int tid) {
        inside.enter();
        Worker wk(g, min_size, sh, sink, tid);
        int64_t lo, hi;
        while (!sh.stop.load(std::memory_order_relaxed) && roots.next(lo, hi))
            for (int64_t i = lo; i < hi && !sh.stop.load(std::memory_order_relaxed); ++i)
                wk.run_root(order[i], rank);
        counts[tid] = wk.delivered;
        if (sh.give_up_work > 0 && wk.flush()) {
            int expected = 0;
            sh.why.compare_exchange_strong(expected, 4);
        }
        inside.leave();
        if (tid == 0)  // the caller: wait for the others here, where Ctrl-C can still be seen
            inside.wait([&] {
                if (interrupt.check()) {
                    int expected = 0;
                    sh.why.compare_exchange_strong(expected, 3);
                    sh.stop.store(true);
                }
            });
    });
    if (sh.why.load() == 3) throw Interrupted();
    if (give_up) {
        give_up->work = sh.work.load();
        if (sh.why.load() == 4) {  // more work than the budget: the caller searches otherwise
            give_up->gave_up = true;
            return 0;
        }
    }

    if (sh.why.load() == 1) cap_hit = "max_cliques=" + std::to_string(caps.max_cliques);
    if (sh.why.load() == 2) {
        char buf[64];
        std::snprintf(buf, sizeof buf, "time_limit=%gs", caps.time_limit_s);
        cap_hit = buf;
    }
    int64_t total = 0;
    for (int64_t c : counts) total += c;
    return total;
}

namespace {

// Keeps every clique, per thread.
class StoreSink : public CliqueSink {
   public:
    std::vector<CliqueList> parts;
    void start(int nthreads) override { parts.assign(nthreads, CliqueList()); }
    void add(int tid, const int32_t *m, size_t k) override {
        CliqueList &out = parts[tid];
        out.data.insert(out.data.end(), m, m + k);
        out.off.push_back((int64_t)out.data.size());
    }
};

}  // namespace

CliqueList maximal_cliques(const AdjGraph &g, int min_size, const CliqueCaps &caps, std::string &cap_hit,
                           int nthreads) {
    StoreSink sink;
    enumerate_maximal_cliques(g, min_size, caps, cap_hit, nthreads, sink);
    std::vector<CliqueList> &parts = sink.parts;

    // Canonical order: lexicographic over the (ascending) member lists.
    struct Ref {
        const int32_t *p;
        int64_t len;
    };
    std::vector<Ref> refs;
    size_t total = 0;
    for (auto &pt : parts) {
        for (size_t c = 0; c < pt.size(); ++c) refs.push_back({pt.begin(c), (int64_t)pt.len(c)});
        total += pt.data.size();
    }
    std::sort(refs.begin(), refs.end(), [](const Ref &a, const Ref &b) {
        return std::lexicographical_compare(a.p, a.p + a.len, b.p, b.p + b.len);
    });
    CliqueList out;
    out.data.reserve(total);
    out.off.reserve(refs.size() + 1);
    for (const Ref &r : refs) {
        out.data.insert(out.data.end(), r.p, r.p + r.len);
        out.off.push_back((int64_t)out.data.size());
    }
    return out;
}

}  // namespace fastmac
