// C++ core of fastmac_exp: compatibility graphs, maximal cliques and MAC (spec sections 2-5, 7.2-7.3).
//
// Memory grows with the number of graph edges, never with N^2: the first-order graph W is found by an
// O(N^2) pair test that stores only edges, and the second-order weights G_ij = W_ij * sum_k W_ik W_kj
// are computed on W's support from sorted neighbour lists (CSR).
#pragma once

#include <algorithm>
#include <cstdlib>

#include <cstdint>
#include <stdexcept>
#include <string>
#include <vector>

namespace fastmac {

enum class Kernel { Gaussian, Quadratic };

struct GraphParams {
    Kernel kernel = Kernel::Gaussian;
    double alpha = 0.06;
    double tau = 0.1;
    double threshold = 0.995;
};

// Thrown when MAC cannot produce a pose; Python sees fastmac_exp.errors.RegistrationFailed.
struct RegistrationFailed : std::runtime_error {
    using std::runtime_error::runtime_error;
};

Kernel parse_kernel(const std::string &name);  // throws std::invalid_argument
void check_params(const GraphParams &gp);       // throws std::invalid_argument
double max_distance(const GraphParams &gp);     // the largest inconsistency that can still make an edge

// Threads to use: num_threads > 0 is taken as given; 0 means automatic: default_threads() (the
// std::thread pool of parallel.hpp, or OpenMP in a -DFASTMAC_OPENMP=ON build), but one thread for
// small problems (n < kSerialBelow), where starting threads costs more than it saves.
constexpr int64_t kSerialBelow = 1500;
int resolve_threads(int num_threads, int64_t n = -1);
// The size resolve_threads weighs for a stage that tests all n (n - 1) / 2 pairs: n, or kSerialBelow
// from 2^18 pairs (n >= 725), where two threads already pay.
inline int64_t pair_work_size(int64_t n) {
    return n * (n - 1) / 2 >= (int64_t(1) << 18) ? std::max(n, kSerialBelow) : n;
}
int default_threads();  // OMP_NUM_THREADS if set, else the hardware's thread count
// num_threads when set (> 0), else every thread where the stage's own measure of work says they pay.
inline int threads_if(int num_threads, bool pays) { return num_threads > 0 ? num_threads : pays ? default_threads() : 1; }
// MAC's clique search and hypotheses: where two threads paid on the real pairs (mac.cpp).
constexpr int64_t kSearchThreadsFromEdges = 1536;
constexpr int64_t kHypothesisThreadsFromWork = int64_t(1) << 16;  // hypotheses x correspondences

// The core's switches for tests and comparisons (FASTMAC_DENSE_CORE, FASTMAC_DOMINANCE, ...): the
// environment variable `name` equals `value`.
inline bool env_is(const char *name, const char *value) {
    const char *env = std::getenv(name);
    return env && std::string(env) == value;
}

// For every row of a (na x dim, row-major) the index of the nearest row of b (nb x dim) in Euclidean
// distance, by brute force in float64 (nearest.cpp); ties go to the lowest index.
std::vector<int64_t> nearest_rows(const double *a, int64_t na, const double *b, int64_t nb, int64_t dim,
                                  int nthreads);

// Called once when the module loads (glibc only; FASTMAC_MALLOC_TUNE=0 skips it): large blocks come from
// the heap and freed memory stays mapped (mallopt M_MMAP_THRESHOLD 256 MiB, M_TRIM_THRESHOLD 512 MiB), so
// a call reuses the pages of the previous one. Each call on an outdoor pair allocates and frees ~35 MB
// (edge lists, products); with glibc's defaults these went back to the kernel and came back as ~9,000
// page faults per call, each ~1.7 us in a VM (a fault exits to the hypervisor): ~15 ms of a ~60 ms
// sampler graph (measured on KITTI 95->94). The cost: the process keeps up to 512 MiB of freed memory
// mapped instead of returning it. Returns whether the setting took effect.
bool keep_freed_memory();

// ---------------------------------------------------------------------------------------------
// Graphs

// Symmetric weighted graph in CSR form: rows sorted ascending, no self-loops. upper[i] is the first
// position of row i whose column is > i, so row i = [lower part | upper part].
struct Csr {
    int64_t n = 0;
    std::vector<int64_t> ptr;    // n + 1
    std::vector<int64_t> upper;  // n
    std::vector<int32_t> col;
    std::vector<double> w;  // aligned with col; empty for an unweighted graph (every weight 1)
    int64_t nnz() const { return (int64_t)col.size(); }
    std::vector<double> weights() const { return w.empty() ? std::vector<double>(col.size(), 1.0) : w; }
    int64_t n_edges() const { return nnz() / 2; }
};

// The first-order graph W (spec 2.1-2.2). src, tgt: row-major (n, 3).
Csr first_order(const double *src, const double *tgt, int64_t n, const GraphParams &gp, int nthreads);

// TurboReg's compatibility graph (turboreg.cpp), from float32 coordinates in float32 as its LibTorch code
// computes it: an edge iff |a - b| < tau and a + b > cut (a = |p_i - p_j|, b = |q_i - q_j|; cut is
// upstream's radiu_nms length-consistency cut), unweighted (hard, upstream's default; W.w empty) or of
// weight relu(1 - (|a - b| / tau)^2) (soft).
Csr length_graph(const float *src, const float *tgt, int64_t n, float tau, float cut, bool hard, int nthreads);

// The arithmetic of the dense core's matrix product (masked_square.cpp; the sums outside the core are
// always float64).
//   Double: float64 everywhere (tests, and the reference for the others).
//   Single: float32 in the core, and the triangle listing on large graphs (the sampler's graph; spec 7.2
//           computes it in float32).
//   Mac:    MAC's graphs (G and the clustering coefficients' sums): float64, except float32 in cores of
//           at least kSingleCore nodes, where the product's m^3/2 multiply-adds are most of MAC's cost (the
//           1,000 FastMAC@20 keeps of a dense KITTI pair: a core of ~900; the near-cliques it keeps at
//           50,000: ~2,500; the 500 that samples=auto keeps of a dense KITTI pair: ~450), and the
//           reference computes G in float32 too (spec 2.3). Small graphs (the C++/Python parity tests, up
//           to 300 correspondences, so no core of kSingleCore) stay float64. FASTMAC_MAC_PRECISION=double
//           keeps float64 everywhere. (From 512 nodes until 2026-12-07: from 320, register()'s
//           samples=auto on KITTI 95->94 took 9.8 -> 8.3 ms, its MAC 4.3 -> 2.9, with the same poses,
//           trust and confidences on all 13 real pairs at samples=auto, 250 and 500.)
//           On CPUs with AVX512_BF16 those cores' operands are rounded (stochastically) to bfloat16 and
//           summed in float32 instead: twice the multiply-adds a second, G within ~3e-5 relative (median;
//           unbiased). The near-clique of 5,000 that samples=5000 keeps of 200,000 correspondences spends
//           ~6e10 of them in each of MAC's two products: MAC there 4.8 -> 2.9 s of one core; the 1,000
//           kept of KITTI 95->94: 38 -> 29 ms of one core with the fast cube root (mac.cpp).
//           FASTMAC_MAC_PRECISION=single stops at float32.
enum class Precision { Double, Single, Mac };
constexpr int64_t kSingleCore = 320;  // > 300: the parity tests' graphs stay float64
constexpr int64_t kHalfCore = 320;

// G_ij = W_ij * sum_{k != i, j} W_ik W_kj for every stored entry of W (same positions as W.col).
std::vector<double> second_order(const Csr &W, int nthreads, int64_t *core_size = nullptr,
                                 Precision precision = Precision::Mac);

// S_ij = V_ij * sum_k V_ik V_kj for every stored entry of the pattern V (values vals, aligned with
// V.col; zero values are allowed and give 0). Dense dot products inside the dense core (masked_square.cpp).
std::vector<double> masked_square(const Csr &V, const std::vector<double> &vals, int nthreads,
                                  int64_t *core_size = nullptr, Precision precision = Precision::Mac);

// Whether this build and CPU run MAC's cores of >= kHalfCore nodes in bfloat16 (FASTMAC_GEMM permitting).
bool bf16_cores();
// Which tile runs them: "amx", "avx512_bf16" or "" (none; FASTMAC_GEMM=avx512 passes over AMX).
std::string bf16_kernel();

// masked_square for an unweighted graph (every value 1): S_ij = |N(i) and N(j)|, exactly, by AND + popcount of
// bitset rows, tiled for the caches (common_neighbours.cpp; AVX-512 VPOPCNTDQ where the CPU has it).
std::vector<double> common_neighbours(const Csr &V, int nthreads);
// The same counts at the upper entries j > i only (the others 0), as integers.
std::vector<int32_t> common_neighbour_counts(const Csr &V, int nthreads);

// Each edge of V computed at one of its two entries (done[p]): copies it to the other (masked_square.cpp).
void mirror_entries(const Csr &V, std::vector<double> &S, const std::vector<uint8_t> &done, int nthreads);

// Lookup of an entry of a per-position array (e.g. G) at (a, b); 0 when (a, b) is not an edge.
double csr_lookup(const Csr &W, const std::vector<double> &vals, int32_t a, int32_t b);

struct Signals {
    std::vector<double> degree, highpass, lowpass;
    int64_t n_edges = 0;
    int64_t dense_core = 0;  // nodes of the dense core of the second-order product (0: all sparse)
};

// Sampler signals (spec 7.2-7.3) on the SOG with (FastMAC) or without (MAC) self-loops.
Signals graph_signals(const Csr &W, const std::vector<double> &G, bool self_loops, int nthreads);

// Estimated sampler signals (anchors.cpp, docs/estimated_scores.md). anchor_degree: sum_r W_{i a_r} over
// the anchors a (a_r != i) for every node, the pilot of the estimate. anchor_signals: unbiased estimates
// of the degree and of the terms of the high-pass and low-pass responses (FastMAC's self-loop graph) from
// m anchors drawn i.i.d. from q, with inv_q[r] = 1 / q(a_r); n_edges is -1 (the graph is never built).
std::vector<double> anchor_degree(const double *src, const double *tgt, int64_t n, const GraphParams &gp,
                                  const int64_t *anchors, int64_t m, int nthreads);
Signals anchor_signals(const double *src, const double *tgt, int64_t n, const GraphParams &gp,
                       const int64_t *anchors, const double *inv_q, int64_t m, int nthreads);
// The most anchors (a prefix of the draws: min_anchors * 2^k, or all m) whose pair work
// sum_i nnz_i^2 / 2 stays within pair_budget; min_anchors when none does.
int64_t anchors_within(const double *src, const double *tgt, int64_t n, const GraphParams &gp,
                       const int64_t *anchors, int64_t m, int64_t min_anchors, double pair_budget, int nthreads);

// ---------------------------------------------------------------------------------------------
// Maximal cliques

// Unweighted undirected graph: sorted rows, symmetric, no self-loops.
struct AdjGraph {
    int64_t n = 0;
    std::vector<int64_t> ptr;
    std::vector<int32_t> col;
};

// The offsets q (within row u) of u's neighbours x = g.col[g.ptr[u] + q] that have loc[x] >= 0, written to
// hit (grown as needed) without a branch; returns how many. The clique searches build each root's local
// graph with it: on sparse graphs that is most of their time, and the branchy loop mispredicted.
inline int64_t local_neighbours(const AdjGraph &g, const std::vector<int32_t> &loc, int32_t u,
                                std::vector<int32_t> &hit) {
    const int64_t p0 = g.ptr[u], len = g.ptr[u + 1] - p0;
    if ((int64_t)hit.size() < len) hit.resize(len);
    int64_t c = 0;
    for (int64_t q = 0; q < len; ++q) {
        hit[c] = (int32_t)q;
        c += loc[g.col[p0 + q]] >= 0;
    }
    return c;
}

// vals[position of (a, b)] for a parallel array of values; 0 when (a, b) is not an edge.
double adj_lookup(const AdjGraph &g, const std::vector<double> &vals, int32_t a, int32_t b);

// Builds an AdjGraph from an arbitrary edge list (either direction, duplicates, self-loops ignored).
AdjGraph adj_from_edges(int64_t n, const int64_t *i, const int64_t *j, int64_t m);

struct CliqueList {
    std::vector<int32_t> data;        // members, concatenated
    std::vector<int64_t> off{0};      // clique c = data[off[c] .. off[c+1])
    size_t size() const { return off.size() - 1; }
    size_t len(size_t c) const { return (size_t)(off[c + 1] - off[c]); }
    const int32_t *begin(size_t c) const { return data.data() + off[c]; }
};

// Bounds on a clique search. max_cliques (enumeration) and max_nodes (branch and bound) are work
// budgets: a capped result is the same for any thread count and machine load. time_limit_s is a
// wall-clock safety net: a result it cuts short depends on timing.
struct CliqueCaps {
    int64_t max_cliques = 0;    // enumeration: stop after this many maximal cliques; 0 = no cap
    int64_t max_nodes = 0;      // branch and bound: search-tree nodes; 0 = no cap
    int64_t max_work = 0;       // branch and bound: work units (~1 ns of one core each); 0 = no cap
    double time_limit_s = 0.0;  // 0 = no limit
    // search "auto" (clique_search): the enumeration's work budget per node that can be in a clique
    // (degree >= min_size - 1); 0 = the branch and bound at once
    int64_t enumerate_work_per_node = 0;
};

// An enumeration that is given up once its work is above `above` (in units of about a nanosecond of a
// core: 160 a search node, 1-12 a member pair of each clique found, which the selection weighs; see
// cliques.cpp). Whether it is given up is a property of the graph, the same for any thread count and load.
struct GiveUp {
    int64_t above = 0;
    bool gave_up = false;  // out
    int64_t work = 0;      // out: the work counted (all of it unless the enumeration gave up)
};

// Vertices in degeneracy (smallest-last) order.
std::vector<int32_t> degeneracy_order(const AdjGraph &g);

// Receives the maximal cliques as they are found: members ascending, from thread tid (0 .. nthreads-1),
// in no particular order. Each maximal clique is delivered exactly once.
class CliqueSink {
   public:
    virtual ~CliqueSink() = default;
    virtual void start(int nthreads) = 0;  // before the search
    virtual void add(int tid, const int32_t *members, size_t k) = 0;
    // A sink that weighs cliques (node-guided selection) may give its edge weights (parallel to the
    // graph's col); the search then passes some cliques with their weight, summed as NodeChoice::weight.
    virtual const std::vector<double> *weights() const { return nullptr; }
    virtual void add_weighted(int tid, const int32_t *members, size_t k, double) { add(tid, members, k); }
};

// Bron-Kerbosch with pivoting, run from each vertex in degeneracy order (Eppstein-Loeffler-Strash),
// over every maximal clique of size >= min_size. Returns how many were delivered; when a cap stops the
// search, cap_hit names it. With max_cliques the search runs serially (a reproducible partial set).
// With give_up, the search stops once its work is above give_up->above, sets give_up->gave_up and
// returns 0; what the sink received is then to be discarded.
int64_t enumerate_maximal_cliques(const AdjGraph &g, int min_size, const CliqueCaps &caps, std::string &cap_hit,
                                  int nthreads, CliqueSink &sink, GiveUp *give_up = nullptr);

// Every maximal clique of size >= min_size, members ascending, the list in lexicographic (canonical)
// order. When a cap stops the search, cap_hit names it and the partial list is returned.
CliqueList maximal_cliques(const AdjGraph &g, int min_size, const CliqueCaps &caps, std::string &cap_hit,
                           int nthreads);

class NodeChoice;  // selection.hpp

// Node-guided selection without enumeration (heaviest.cpp): offers to `choice` (started here) every
// clique that may be some node's heaviest clique of size >= min_size, by branch and bound; without a
// cap hit, choice.finish() then equals the selection over all maximal cliques. Returns the number of
// cliques offered; search_nodes receives the search-tree nodes visited. Throws Interrupted on Ctrl-C.
// work (optional): the work units of steps 2 and 3 (what CliqueCaps::max_work caps).
int64_t heaviest_cliques(const AdjGraph &g, const std::vector<double> &vals, int min_size, const CliqueCaps &caps,
                         std::string &cap_hit, int64_t &search_nodes, int nthreads, NodeChoice &choice,
                         int64_t *work = nullptr);

// ---------------------------------------------------------------------------------------------
// Poses

struct Pose {
    double R[9];  // row-major
    double t[3];
};

Pose identity_pose();

// Kabsch over the rows idx (or all rows when idx is null) with optional weights; centroids are the
// UNWEIGHTED means, H = sum w (p - pbar)(q - qbar)^T = U S V^T, R = V diag(1, 1, +-1) U^T, t = qbar - R pbar.
Pose kabsch(const double *src, const double *tgt, const int32_t *idx, int64_t m, const double *weights);

// Kabsch as TurboReg (and SC2-PCR / PointDSC) write it: weighted centroids sum w p / (sum w + eps) (w = 1
// when weights is null), H = sum w (p - pbar)(q - qbar)^T, then R and t as kabsch.
Pose kabsch_weighted(const double *src, const double *tgt, const int32_t *idx, int64_t m, const double *weights,
                     double eps);

// What a hypothesis scores over the correspondences with residual e < tau: their number (TurboReg's
// "IN"), sum (tau - e) / tau (MAC's score, spec 5.2; TurboReg's "MAE") or sum ((tau - e) / tau)^2 ("MSE").
enum class Metric { Inliers, Mae, Mse };

// MAE score (spec 5.2) over all n correspondences; e (optional, size n) receives the residuals.
double mae_score(const Pose &T, const double *src, const double *tgt, int64_t n, double tau, double *e);
// The refinements' inlier set (MAC's and TurboReg's): every i with e[i] < tau, in order, with the weight
// 1 / (1 + (e_i / tau)^2); idx and w are cleared first.
void weighted_inliers(const double *e, int64_t n, double tau, std::vector<int32_t> &idx, std::vector<double> &w);

// The same score, fast: residuals are screened in float32 (centred coordinates, a conservative
// rounding margin; SIMD kernels picked at run time) and only the rows that can be inliers are
// evaluated exactly as mae_score does, in the same order, so the result equals mae_score's bit for bit.
class Scorer {
   public:
    Scorer(const double *src, const double *tgt, int64_t n, double tau);
    double score(const Pose &T, std::vector<int32_t> &scratch, Metric metric = Metric::Mae) const;

   private:
    const double *src_, *tgt_;
    int64_t n_;
    double tau_, rp_ = 0, rq_ = 0, cp_[3] = {0, 0, 0}, cq_[3] = {0, 0, 0};
    std::vector<float> px_, py_, pz_, qx_, qy_, qz_;
    void (*screen_)() = nullptr;  // the residual screen picked for this CPU (cast back in pose.cpp)
    void (*count_)() = nullptr;   // the same for the inlier count (Metric::Inliers)
};

// ---------------------------------------------------------------------------------------------
// MAC

// How node-guided selection finds its cliques: per-node heaviest cliques by branch and bound (exact),
// every maximal clique (the reference enumeration), or Auto (the default): the enumeration while its
// work stays within CliqueCaps::enumerate_work_per_node a node (sparse graphs, where it is the faster
// of the two), else the branch and bound. All three give the same selection where they finish.
enum class Search { Heaviest, Enumerate, Auto };
// Auto's default enumerate_work_per_node (mac.enumerate_budget). Sparse real graphs take 2,000-3,000 units a
// node (5,000 nodes: 10-15M units, ~10-15 ms of a core); real graphs with ~100k maximal cliques take 10,000-
// 13,000 and still enumerate faster than the branch and bound (3DMatch 6->0 with 3,955 FPFH correspondences:
// 42 against 94 ms; KITTI 15->0). 16,000 enumerates them and spends at most ~80 ms of a core on a 5,000-node
// graph (~16 ms on FastMAC@20's 1,000) before the branch and bound takes over.
constexpr int64_t kEnumerateBudget = 16000;
Search parse_search(const std::string &name);  // "bnb" | "enumerate" | "auto"; throws std::invalid_argument
const char *search_name(Search s);

// The clique search of node-guided selection, into choice (started here). Returns n_cliques (see
// MacResult); *used: the search that produced the result (Auto resolves to one of the other two);
// *work: Auto's enumeration work (GiveUp::work), partial when it gave up; *bnb_work: the branch and
// bound's work units.
int64_t clique_search(const AdjGraph &g, const std::vector<double> &vals, int min_size, Search search,
                      const CliqueCaps &caps, std::string &cap_hit, int64_t &search_nodes, int nthreads,
                      NodeChoice &choice, Search *used, int64_t *work = nullptr, int64_t *bnb_work = nullptr);

struct MacParams {
    GraphParams graph;
    double inlier_threshold = 0.1;
    int min_clique_size = 3;
    int refine_iters = 20;
    bool reduction = true;
    Search search = Search::Auto;
    int64_t max_cliques = 0;  // enumeration budget
    int64_t max_nodes = 0;    // branch-and-bound budget, in search nodes
    int64_t max_work = 0;     // branch-and-bound budget, in work units
    int64_t enumerate_budget = kEnumerateBudget;  // Auto: CliqueCaps::enumerate_work_per_node
    double time_limit_s = 0.0;
    bool return_selected = false;  // copy the selected cliques (hypotheses, in order) into the result
    bool return_hypotheses = false;  // keep every hypothesis' pose and score (the trust check's rivals)
};

struct MacResult {
    Pose pose, pose_unrefined;
    std::vector<int64_t> clique;
    double score = 0.0;
    // n_cliques: maximal cliques enumerated, or (branch and bound) cliques offered to the selection
    int64_t n_cliques = 0, n_selected = 0, n_edges = 0, n_sog_edges = 0, search_nodes = 0;
    bool reduced = false;
    Search search_used = Search::Heaviest;
    int64_t enumerate_work = 0;  // Auto: the enumeration's work (all of it unless it gave up)
    int64_t search_work = 0;     // the branch and bound's work units (0 when it did not run)
    std::string cap_hit;
    CliqueList selected;  // only with MacParams::return_selected
    // only with MacParams::return_hypotheses: each selected clique's pose and its MAE score, in order
    std::vector<Pose> hyp_poses;
    std::vector<double> hyp_scores;
    // Wall-clock milliseconds. graph: W and G. cliques: clustering/reduction, the clique graph and the
    // search, which also computes each clique's weight and updates the per-node choice (streamed
    // selection). selection: merging the per-thread choices and deduplicating. pose: hypotheses,
    // scores and refinement.
    double t_graph = 0, t_cliques = 0, t_selection = 0, t_pose = 0;
};

MacResult mac(const double *src, const double *tgt, int64_t n, const MacParams &p, int nthreads);

// Node-guided selection (spec 4) over the maximal cliques (size >= min_size) of a weighted graph:
// the hypotheses' cliques in order. g: symmetric, sorted rows; vals: the weight of each entry.
// n_cliques and search_nodes as in MacResult.
CliqueList node_guided_selection(const AdjGraph &g, const std::vector<double> &vals, int min_size, Search search,
                                 const CliqueCaps &caps, std::string &cap_hit, int64_t &n_cliques,
                                 int64_t &search_nodes, int nthreads);

// Pieces of MAC, exposed for tests.
struct Clustering {
    std::vector<double> cc;  // clustering coefficients on G (spec 2.4)
    double otsu = 0, avg = 0, total = 0;
};
Clustering clustering(const Csr &W, const std::vector<double> &G, int nthreads);

}  // namespace fastmac
