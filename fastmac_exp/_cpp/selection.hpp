// Node-guided clique selection (spec 4), shared by both clique searches.
//
// The reference walks the maximal cliques in canonical order and gives node k clique C when
// w_C > best_w[k] (strictly, starting from 0). Node k thus ends with the heaviest clique containing it,
// the earliest in canonical (lexicographic) order among equally heavy ones, provided its weight is > 0.
// That rule does not depend on the order the cliques arrive in, so each thread keeps its own per-node
// choice and the choices are merged by the same rule: the result is the reference's, whatever the
// thread count, and whichever search offered the cliques (every maximal clique, or only the ones that
// can be some node's heaviest).
#pragma once

#include <algorithm>
#include <memory>
#include <vector>

#include "mac_core.hpp"

namespace fastmac {

class NodeChoice {
   public:
    // cg: the clique graph (symmetric, sorted rows); cgw: the weight of each of its entries.
    NodeChoice(const AdjGraph &cg, const std::vector<double> &cgw) : cg_(cg), cgw_(cgw) {}

    void start(int nthreads) {
        threads_.clear();
        threads_.resize(nthreads);
        for (auto &t : threads_) {
            t.best_w.assign(cg_.n, 0.0);
            t.best.assign(cg_.n, Ref{nullptr, 0});
        }
    }

    // w_C = sum over b of sum over a < b of G_ab, members ascending: the one summation order both
    // searches use, so that equal cliques get bit-identical weights.
    double weight(const int32_t *m, size_t k) const {
        double s = 0.0;
        for (size_t b = 1; b < k; ++b) {
            // m[0..b) are all neighbours of m[b] below it: search row m[b] forward, galloping
            const int32_t *row = cg_.col.data() + cg_.ptr[m[b]];
            const int32_t *end = cg_.col.data() + cg_.ptr[m[b] + 1];
            for (size_t a = 0; a < b; ++a) {
                int64_t step = 1;
                while (row + step < end && row[step] < m[a]) step *= 2;
                row = std::lower_bound(row + step / 2, std::min(row + step + 1, end), m[a]);
                s += cgw_[row - cg_.col.data()];
            }
        }
        return s;
    }

    // Offers clique m (members ascending, weight w) to each of its members on thread tid; returns
    // whether some member took it.
    bool offer(int tid, const int32_t *m, size_t k, double w) {
        Thread &t = threads_[tid];
        const int32_t *stored = nullptr;
        for (size_t a = 0; a < k; ++a) {
            const int32_t v = m[a];
            if (better(w, m, k, t.best_w[v], t.best[v])) {
                if (!stored) stored = t.store(m, k);
                t.best_w[v] = w;
                t.best[v] = Ref{stored, k};
            }
        }
        return stored != nullptr;
    }

    const std::vector<double> &values() const { return cgw_; }

    // The heaviest weight thread tid has seen for node v (0 = none).
    double best_weight(int tid, int32_t v) const { return threads_[tid].best_w[v]; }
    int threads() const { return (int)threads_.size(); }

    // The hypotheses: each chosen clique once, at its smallest owner, in node order.
    CliqueList finish() const {
        const int64_t n = cg_.n;
        std::vector<Ref> owner(n, Ref{nullptr, 0});
        for (int64_t v = 0; v < n; ++v) {
            double bw = 0.0;
            for (const Thread &t : threads_)
                if (t.best[v].p && better(t.best_w[v], t.best[v].p, t.best[v].k, bw, owner[v])) {
                    bw = t.best_w[v];
                    owner[v] = t.best[v];
                }
        }
        // Equal cliques may be stored more than once (by different threads): compare by content.
        CliqueList out;
        std::vector<char> done(n, 0);
        for (int64_t v = 0; v < n; ++v) {
            const Ref r = owner[v];
            if (!r.p || done[v]) continue;
            out.data.insert(out.data.end(), r.p, r.p + r.k);
            out.off.push_back((int64_t)out.data.size());
            for (size_t a = 0; a < r.k; ++a) {
                const Ref o = owner[r.p[a]];
                if (o.p == r.p || (o.k == r.k && std::equal(o.p, o.p + o.k, r.p))) done[r.p[a]] = 1;
            }
        }
        return out;
    }

   private:
    struct Ref {
        const int32_t *p;
        size_t k;
    };
    struct Thread {
        std::vector<double> best_w;
        std::vector<Ref> best;
        std::vector<std::unique_ptr<int32_t[]>> blocks;  // stored cliques; blocks never move
        size_t used = 0, cap = 0;
        const int32_t *store(const int32_t *m, size_t k) {
            if (used + k > cap) {
                cap = std::max<size_t>(size_t(1) << 16, k);
                blocks.emplace_back(new int32_t[cap]);
                used = 0;
            }
            int32_t *dst = blocks.back().get() + used;
            std::copy(m, m + k, dst);
            used += k;
            return dst;
        }
    };

    // Does clique (w, m) beat the current choice (bw, b)? Heavier wins; equal weight: the
    // lexicographically smaller clique (the earlier in canonical order). Weight 0 never wins.
    static bool better(double w, const int32_t *m, size_t k, double bw, const Ref &b) {
        if (w > bw) return true;
        if (w < bw || !(w > 0.0) || !b.p) return false;
        return std::lexicographical_compare(m, m + k, b.p, b.p + b.k);
    }

    const AdjGraph &cg_;
    const std::vector<double> &cgw_;
    std::vector<Thread> threads_;
};

}  // namespace fastmac
