// nanobind module fastmac_exp._mac_core: numpy in, numpy out; the GIL is released while computing.
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/string.h>

#include <cmath>
#include <cstring>

#include "buffer_patches.hpp"
#include "fpfh.hpp"
#include "interrupt.hpp"
#include "mac_core.hpp"
#include "selection.hpp"
#include "turboreg.hpp"
#include "within.hpp"

namespace nb = nanobind;
using namespace nb::literals;

namespace {

using Points = nb::ndarray<const double, nb::ndim<2>, nb::c_contig, nb::device::cpu>;
using Poses = nb::ndarray<const double, nb::ndim<3>, nb::c_contig, nb::device::cpu>;
using Indices = nb::ndarray<const int64_t, nb::ndim<1>, nb::c_contig, nb::device::cpu>;
using Weights = nb::ndarray<const double, nb::ndim<1>, nb::c_contig, nb::device::cpu>;

// Moves a std::vector into a numpy array that owns it.
template <class T>
nb::object to_numpy(std::vector<T> &&v, std::initializer_list<size_t> shape) {
    if (v.empty()) v.reserve(1);  // non-null data pointer
    auto *heap = new std::vector<T>(std::move(v));
    nb::capsule owner(heap, [](void *p) noexcept { delete static_cast<std::vector<T> *>(p); });
    return nb::ndarray<nb::numpy, T>(heap->data(), shape, owner).cast();
}
template <class T>
nb::object to_numpy(std::vector<T> &&v) {
    const size_t n = v.size();
    return to_numpy(std::move(v), {n});
}

nb::object pose_to_numpy(const fastmac::Pose &T) {
    std::vector<double> m(16, 0.0);
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) m[4 * r + c] = T.R[3 * r + c];
        m[4 * r + 3] = T.t[r];
    }
    m[15] = 1.0;
    return to_numpy(std::move(m), {4, 4});
}

// Hundreds of thousands of small arrays would trigger the cyclic GC over and over; none of them can
// form a cycle, so it is paused while the list is built.
struct GcPause {
#if PY_VERSION_HEX >= 0x030A0000
    int was_enabled = PyGC_Disable();
    ~GcPause() {
        if (was_enabled) PyGC_Enable();
    }
#endif
};

// The cliques as a list of int64 arrays: views (slices) of one flat array, which is much faster to
// build than one owning array per clique.
nb::list clique_list(const fastmac::CliqueList &cl) {
    GcPause pause;
    std::vector<int64_t> flat(cl.data.begin(), cl.data.end());
    nb::object all = to_numpy(std::move(flat));
    nb::list out;
    for (size_t c = 0; c < cl.size(); ++c) {
        nb::object sl = nb::steal(PySlice_New(nb::int_(cl.off[c]).ptr(), nb::int_(cl.off[c + 1]).ptr(), nullptr));
        if (!sl.is_valid()) throw nb::python_error();
        nb::object view = nb::steal(PyObject_GetItem(all.ptr(), sl.ptr()));
        if (!view.is_valid()) throw nb::python_error();
        out.append(view);
    }
    return out;
}

int64_t check_pair(const Points &src, const Points &tgt) {
    if (src.shape(1) != 3 || tgt.shape(1) != 3)
        throw std::invalid_argument("src and tgt must have shape (N, 3)");
    if (src.shape(0) != tgt.shape(0))
        throw std::invalid_argument("src and tgt must have the same number of rows, got " +
                                    std::to_string(src.shape(0)) + " and " + std::to_string(tgt.shape(0)));
    return (int64_t)src.shape(0);
}

fastmac::GraphParams graph_params(const std::string &kernel, double alpha, double tau, double threshold) {
    fastmac::GraphParams gp;
    gp.kernel = fastmac::parse_kernel(kernel);
    gp.alpha = alpha;
    gp.tau = tau;
    gp.threshold = threshold;
    fastmac::check_params(gp);
    return gp;
}

nb::dict graph_edges(const Points &src, const Points &tgt, const std::string &kernel, double alpha, double tau,
                     double threshold, int num_threads) {
    const int64_t n = check_pair(src, tgt);
    const auto gp = graph_params(kernel, alpha, tau, threshold);
    std::vector<int64_t> ei, ej;
    std::vector<double> ew, eg;
    int64_t dense_core = 0;
    {
        nb::gil_scoped_release nogil;
        fastmac::Csr W = fastmac::first_order(src.data(), tgt.data(), n, gp, num_threads);
        std::vector<double> G = fastmac::second_order(W, num_threads, &dense_core);
        const int64_t m = W.n_edges();
        ei.reserve(m);
        ej.reserve(m);
        ew.reserve(m);
        eg.reserve(m);
        for (int64_t i = 0; i < n; ++i)
            for (int64_t p = W.upper[i]; p < W.ptr[i + 1]; ++p) {
                ei.push_back(i);
                ej.push_back(W.col[p]);
                ew.push_back(W.w[p]);
                eg.push_back(G[p]);
            }
    }
    nb::dict d;
    d["i"] = to_numpy(std::move(ei));
    d["j"] = to_numpy(std::move(ej));
    d["w"] = to_numpy(std::move(ew));
    d["g"] = to_numpy(std::move(eg));
    d["dense_core"] = dense_core;
    return d;
}

nb::dict graph_signals(const Points &src, const Points &tgt, const std::string &kernel, double alpha, double tau,
                       double threshold, bool self_loops, bool single, int num_threads) {
    const int64_t n = check_pair(src, tgt);
    const auto gp = graph_params(kernel, alpha, tau, threshold);
    fastmac::Signals s;
    {
        nb::gil_scoped_release nogil;
        fastmac::Csr W = fastmac::first_order(src.data(), tgt.data(), n, gp, num_threads);
        int64_t dense_core = 0;
        std::vector<double> G = fastmac::second_order(W, num_threads, &dense_core,
                                                               single ? fastmac::Precision::Single : fastmac::Precision::Double);
        s = fastmac::graph_signals(W, G, self_loops, num_threads);
        s.dense_core = dense_core;
    }
    nb::dict d;
    d["degree"] = to_numpy(std::move(s.degree));
    d["highpass"] = to_numpy(std::move(s.highpass));
    d["lowpass"] = to_numpy(std::move(s.lowpass));
    d["n_edges"] = s.n_edges;
    d["dense_core"] = s.dense_core;
    return d;
}

nb::object anchor_degree(const Points &src, const Points &tgt, const std::string &kernel, double alpha, double tau,
                         double threshold, const Indices &anchors, int num_threads) {
    const int64_t n = check_pair(src, tgt);
    const auto gp = graph_params(kernel, alpha, tau, threshold);
    std::vector<double> deg;
    {
        nb::gil_scoped_release nogil;
        deg = fastmac::anchor_degree(src.data(), tgt.data(), n, gp, anchors.data(), (int64_t)anchors.shape(0),
                                     num_threads);
    }
    return to_numpy(std::move(deg));
}

int64_t anchors_within(const Points &src, const Points &tgt, const std::string &kernel, double alpha, double tau,
                       double threshold, const Indices &anchors, int64_t min_anchors, double pair_budget,
                       int num_threads) {
    const int64_t n = check_pair(src, tgt);
    const auto gp = graph_params(kernel, alpha, tau, threshold);
    nb::gil_scoped_release nogil;
    return fastmac::anchors_within(src.data(), tgt.data(), n, gp, anchors.data(), (int64_t)anchors.shape(0),
                                   min_anchors, pair_budget, num_threads);
}

nb::dict anchor_signals(const Points &src, const Points &tgt, const std::string &kernel, double alpha, double tau,
                        double threshold, const Indices &anchors, const Weights &inv_q, int num_threads) {
    const int64_t n = check_pair(src, tgt);
    const auto gp = graph_params(kernel, alpha, tau, threshold);
    const int64_t m = (int64_t)anchors.shape(0);
    if ((int64_t)inv_q.shape(0) != m) throw std::invalid_argument("anchors and inv_q must have the same length");
    for (int64_t r = 0; r < m; ++r)
        if (!(std::isfinite(inv_q.data()[r]) && inv_q.data()[r] > 0.0))
            throw std::invalid_argument("inv_q must be finite and positive");
    fastmac::Signals s;
    {
        nb::gil_scoped_release nogil;
        s = fastmac::anchor_signals(src.data(), tgt.data(), n, gp, anchors.data(), inv_q.data(), m, num_threads);
    }
    nb::dict d;
    d["degree"] = to_numpy(std::move(s.degree));
    d["highpass"] = to_numpy(std::move(s.highpass));
    d["lowpass"] = to_numpy(std::move(s.lowpass));
    d["n_edges"] = s.n_edges;
    d["dense_core"] = 0;
    return d;
}

nb::tuple maximal_cliques(int64_t n, const Indices &i, const Indices &j, int min_size, int64_t max_cliques,
                          double time_limit_s, int num_threads) {
    if (i.shape(0) != j.shape(0)) throw std::invalid_argument("i and j must have the same length");
    fastmac::CliqueList cl;
    std::string cap_hit;
    {
        nb::gil_scoped_release nogil;
        fastmac::AdjGraph g = fastmac::adj_from_edges(n, i.data(), j.data(), (int64_t)i.shape(0));
        fastmac::CliqueCaps caps;
        caps.max_cliques = max_cliques;
        caps.time_limit_s = time_limit_s;
        cl = fastmac::maximal_cliques(g, min_size, caps, cap_hit, num_threads);
    }
    return nb::make_tuple(clique_list(cl), cap_hit);
}

nb::dict select_cliques(int64_t n, const Indices &i, const Indices &j, const Weights &w, int min_size,
                        const std::string &search, int64_t max_cliques, int64_t max_nodes, int64_t max_work,
                        double time_limit_s, int64_t enumerate_budget, int num_threads) {
    const int64_t m = (int64_t)i.shape(0);
    if ((int64_t)j.shape(0) != m || (int64_t)w.shape(0) != m)
        throw std::invalid_argument("i, j and w must have the same length");
    const fastmac::Search how = fastmac::parse_search(search);
    fastmac::CliqueList sel;
    int64_t n_cliques = 0, nodes = 0;
    std::string cap_hit;
    fastmac::Search used = how;
    int64_t work = 0, bnb_work = 0;
    {
        nb::gil_scoped_release nogil;
        fastmac::AdjGraph g = fastmac::adj_from_edges(n, i.data(), j.data(), m);
        // weights onto the sorted rows (duplicates: the last one given wins)
        std::vector<double> vals(g.col.size(), 0.0);
        for (int64_t e = 0; e < m; ++e) {
            const int64_t a = i.data()[e], b = j.data()[e];
            if (a == b) continue;
            // finite too: an infinite weight breaks the branch and bound's dominance rule (inf - inf)
            if (!(w.data()[e] > 0.0) || !std::isfinite(w.data()[e]))
                throw std::invalid_argument("edge weights must be finite and positive (edge " + std::to_string(e) +
                                            ")");
            for (auto [x, y] : {std::pair<int64_t, int64_t>{a, b}, {b, a}}) {
                auto first = g.col.begin() + g.ptr[x], last = g.col.begin() + g.ptr[x + 1];
                vals[std::lower_bound(first, last, (int32_t)y) - g.col.begin()] = w.data()[e];
            }
        }
        fastmac::CliqueCaps caps;
        caps.max_cliques = max_cliques;
        caps.max_nodes = max_nodes;
        caps.max_work = max_work;
        caps.time_limit_s = time_limit_s;
        caps.enumerate_work_per_node = enumerate_budget;
        fastmac::NodeChoice choice(g, vals);
        n_cliques =
            fastmac::clique_search(g, vals, min_size, how, caps, cap_hit, nodes, num_threads, choice, &used, &work,
                                  &bnb_work);
        sel = choice.finish();
    }
    nb::dict d;
    d["cliques"] = clique_list(sel);
    d["n_cliques"] = n_cliques;
    d["search_nodes"] = nodes;
    d["search_used"] = fastmac::search_name(used);
    d["enumerate_work"] = work;
    d["search_work"] = bnb_work;
    d["cap_hit"] = cap_hit;
    return d;
}

nb::dict mac(const Points &src, const Points &tgt, const std::string &kernel, double alpha, double tau,
             double threshold, double inlier_threshold, int min_clique_size, int refine_iters, bool reduction,
             const std::string &search, int64_t max_cliques, int64_t max_nodes, int64_t max_work,
             double time_limit_s, int64_t enumerate_budget, int num_threads, bool return_selected,
             bool return_hypotheses) {
    const int64_t n = check_pair(src, tgt);
    fastmac::MacParams p;
    p.graph = graph_params(kernel, alpha, tau, threshold);
    p.inlier_threshold = inlier_threshold;
    p.min_clique_size = min_clique_size;
    p.refine_iters = refine_iters;
    p.reduction = reduction;
    p.search = fastmac::parse_search(search);
    p.max_cliques = max_cliques;
    p.max_nodes = max_nodes;
    p.max_work = max_work;
    p.time_limit_s = time_limit_s;
    p.enumerate_budget = enumerate_budget;
    p.return_selected = return_selected;
    p.return_hypotheses = return_hypotheses;
    if (min_clique_size < 3) throw std::invalid_argument("min_clique_size must be at least 3");
    fastmac::MacResult r;
    {
        nb::gil_scoped_release nogil;
        r = fastmac::mac(src.data(), tgt.data(), n, p, num_threads);
    }
    nb::dict d;
    d["pose"] = pose_to_numpy(r.pose);
    d["pose_unrefined"] = pose_to_numpy(r.pose_unrefined);
    d["clique"] = to_numpy(std::move(r.clique));
    d["score"] = r.score;
    d["n_cliques"] = r.n_cliques;
    d["n_selected"] = r.n_selected;
    d["n_edges"] = r.n_edges;
    d["n_sog_edges"] = r.n_sog_edges;
    d["search_nodes"] = r.search_nodes;
    d["search_used"] = fastmac::search_name(r.search_used);
    d["enumerate_work"] = r.enumerate_work;
    d["search_work"] = r.search_work;
    d["reduced"] = r.reduced;
    d["cap_hit"] = r.cap_hit;
    nb::dict t;
    t["graph"] = r.t_graph;
    t["cliques"] = r.t_cliques;
    t["selection"] = r.t_selection;
    t["pose"] = r.t_pose;
    d["timings"] = t;
    if (return_selected) d["selected"] = clique_list(r.selected);
    if (return_hypotheses) {
        const int64_t nh = (int64_t)r.hyp_poses.size();
        std::vector<double> poses(nh * 16);
        for (int64_t h = 0; h < nh; ++h) {
            const fastmac::Pose &T = r.hyp_poses[h];
            double *m = poses.data() + 16 * h;
            for (int i = 0; i < 3; ++i) {
                for (int j = 0; j < 3; ++j) m[4 * i + j] = T.R[3 * i + j];
                m[4 * i + 3] = T.t[i];
            }
            m[12] = m[13] = m[14] = 0.0;
            m[15] = 1.0;
        }
        d["hypothesis_poses"] = to_numpy(std::move(poses), {(size_t)nh, 4, 4});
        d["hypothesis_scores"] = to_numpy(std::move(r.hyp_scores));
    }
    return d;
}

nb::dict turboreg(const Points &src, const Points &tgt, int64_t max_n, double tau, int64_t num_pivot,
                  double radius_nms, double tau_inlier, const std::string &metric, bool hard, int refine_iters,
                  int num_threads) {
    const int64_t n = check_pair(src, tgt);
    fastmac::TurboParams p;
    p.max_n = max_n;
    p.tau = tau;
    p.num_pivot = num_pivot;
    p.radius_nms = radius_nms;
    p.tau_inlier = tau_inlier;
    p.metric = fastmac::parse_metric(metric);
    p.hard = hard;
    p.refine_iters = refine_iters;
    fastmac::TurboResult r;
    {
        nb::gil_scoped_release nogil;
        r = fastmac::turboreg(src.data(), tgt.data(), n, p, num_threads);
    }
    nb::dict d;
    d["pose"] = pose_to_numpy(r.pose);
    d["pose_unrefined"] = pose_to_numpy(r.pose_unrefined);
    d["clique"] = to_numpy(std::vector<int64_t>(r.clique, r.clique + 3));
    d["score"] = r.score;
    d["n_used"] = r.n_used;
    d["n_edges"] = r.n_edges;
    d["n_sog_edges"] = r.n_sog_edges;
    d["n_pivots"] = r.n_pivots;
    d["n_hypotheses"] = r.n_hypotheses;
    d["n_unique"] = r.n_unique;
    d["refine_iters_run"] = r.refine_iters_run;
    nb::dict t;
    t["graph"] = r.t_graph;
    t["pivots"] = r.t_pivots;
    t["hypotheses"] = r.t_hypotheses;
    t["pose"] = r.t_pose;
    d["timings"] = t;
    return d;
}

nb::dict length_graph_edges(const Points &src, const Points &tgt, double tau, double cut, bool hard,
                            int num_threads) {
    const int64_t n = check_pair(src, tgt);
    std::vector<float> s32(3 * n), t32(3 * n);
    for (int64_t k = 0; k < 3 * n; ++k) {
        s32[k] = (float)src.data()[k];
        t32[k] = (float)tgt.data()[k];
    }
    std::vector<int64_t> ei, ej;
    std::vector<double> ew, es, em;
    {
        nb::gil_scoped_release nogil;
        const fastmac::Csr W = fastmac::length_graph(s32.data(), t32.data(), n, (float)tau, (float)cut, hard,
                                                     num_threads);
        // TurboReg's SC^2: bitset counts for the hard graph, masked_square for the soft one (and as a check)
        const std::vector<double> w = W.weights();
        const std::vector<double> S = hard ? fastmac::common_neighbours(W, num_threads)
                                           : fastmac::masked_square(W, w, num_threads, nullptr,
                                                                    fastmac::Precision::Single);
        const std::vector<double> M = fastmac::masked_square(W, w, num_threads, nullptr,
                                                             fastmac::Precision::Double);
        for (int64_t i = 0; i < n; ++i)
            for (int64_t q = W.upper[i]; q < W.ptr[i + 1]; ++q) {
                ei.push_back(i);
                ej.push_back(W.col[q]);
                ew.push_back(w[q]);
                es.push_back(S[q]);
                em.push_back(M[q]);
            }
    }
    nb::dict d;
    d["i"] = to_numpy(std::move(ei));
    d["j"] = to_numpy(std::move(ej));
    d["w"] = to_numpy(std::move(ew));
    d["sc2"] = to_numpy(std::move(es));
    d["sc2_masked"] = to_numpy(std::move(em));
    return d;
}

nb::object torch_topk_sparse(int64_t dim, int64_t k, const Indices &pos, const Weights &val) {
    std::vector<int64_t> p(pos.data(), pos.data() + pos.shape(0));
    std::vector<double> v(val.data(), val.data() + val.shape(0));
    return to_numpy(fastmac::torch_topk_sparse(dim, k, p, v));
}

nb::object nearest_rows(const Points &a, const Points &b, int num_threads) {
    if (a.shape(1) != b.shape(1))
        throw std::invalid_argument("a and b must have the same number of columns, got " +
                                    std::to_string(a.shape(1)) + " and " + std::to_string(b.shape(1)));
    std::vector<int64_t> idx;
    {
        nb::gil_scoped_release nogil;
        idx = fastmac::nearest_rows(a.data(), (int64_t)a.shape(0), b.data(), (int64_t)b.shape(0),
                                    (int64_t)a.shape(1), num_threads);
    }
    return to_numpy(std::move(idx));
}

nb::object voxel_downsample(const Points &points, double voxel, int num_threads) {
    if (points.shape(1) != 3) throw std::invalid_argument("voxel_downsample: points must be (N, 3)");
    std::vector<double> kp;
    {
        nb::gil_scoped_release nogil;
        kp = fastmac::voxel_downsample(points.data(), (int64_t)points.shape(0), voxel, num_threads);
    }
    const size_t m = kp.size() / 3;
    return to_numpy(std::move(kp), {m, 3});
}

nb::object radius_neighbours(const Points &points, double radius, int64_t max_nn, int num_threads) {
    if (points.shape(1) != 3) throw std::invalid_argument("radius_neighbours: points must be (N, 3)");
    fastmac::Neighbours nbh;
    {
        nb::gil_scoped_release nogil;
        nbh = fastmac::radius_neighbours(points.data(), (int64_t)points.shape(0), radius, max_nn, num_threads);
    }
    // packed (CSR) for Python: point i's neighbours are idx[ptr[i]:ptr[i + 1]]
    const int64_t n = int64_t(nbh.end.size());
    std::vector<int64_t> ptr(n + 1, 0);
    for (int64_t i = 0; i < n; ++i) ptr[i + 1] = ptr[i] + (nbh.end[i] - nbh.ptr[i]);
    std::vector<int32_t> idx(ptr[n]);
    std::vector<double> d2(ptr[n]);
    for (int64_t i = 0; i < n; ++i) {
        std::copy(nbh.idx.begin() + nbh.ptr[i], nbh.idx.begin() + nbh.end[i], idx.begin() + ptr[i]);
        std::copy(nbh.d2.begin() + nbh.ptr[i], nbh.d2.begin() + nbh.end[i], d2.begin() + ptr[i]);
    }
    nb::dict d;
    d["ptr"] = to_numpy(std::move(ptr));
    d["idx"] = to_numpy(std::move(idx));
    d["d2"] = to_numpy(std::move(d2));
    return d;
}

// Normals and FPFH of a keypoint cloud (fpfh.hpp): the two neighbourhoods, PCA normals flipped towards
// `viewpoint` (None: as the eigensolver gives them), FPFH of `rows` (None: every keypoint).
nb::object fpfh_describe(const Points &keypoints, double normal_radius, int64_t normal_max_nn, double feature_radius,
                         int64_t feature_max_nn, nb::object viewpoint, nb::object rows, int num_threads,
                         nb::object normals_in, bool normalize) {
    if (keypoints.shape(1) != 3) throw std::invalid_argument("fpfh_describe: keypoints must be (N, 3)");
    const int64_t n = (int64_t)keypoints.shape(0);
    double vp[3] = {0, 0, 0};
    const bool has_vp = !viewpoint.is_none();
    if (has_vp) {
        auto v = nb::cast<Weights>(viewpoint);
        if (v.shape(0) != 3) throw std::invalid_argument("fpfh_describe: viewpoint must have 3 entries");
        for (int d = 0; d < 3; ++d) vp[d] = v.data()[d];
    }
    std::vector<int64_t> sel;
    const bool has_rows = !rows.is_none();
    if (has_rows) {
        auto r = nb::cast<Indices>(rows);
        sel.assign(r.data(), r.data() + r.shape(0));
    }
    std::vector<double> normals, feat;
    if (!normals_in.is_none()) {
        auto nn = nb::cast<Points>(normals_in);
        if ((int64_t)nn.shape(0) != n || nn.shape(1) != 3)
            throw std::invalid_argument("fpfh_describe: normals must be (N, 3) like the keypoints");
        normals.assign(nn.data(), nn.data() + 3 * n);
    }
    {
        nb::gil_scoped_release nogil;
        feat = fastmac::describe_fpfh(keypoints.data(), n, normal_radius, normal_max_nn, feature_radius,
                                      feature_max_nn, has_vp ? vp : nullptr, has_rows ? sel.data() : nullptr,
                                      (int64_t)sel.size(), normals, num_threads);
        if (normalize) fastmac::unit_rows(feat.data(), (int64_t)feat.size() / 33, 33, num_threads);
    }
    const size_t m = feat.size() / 33;
    return nb::make_tuple(to_numpy(std::move(normals), {(size_t)n, 3}), to_numpy(std::move(feat), {m, 33}));
}

nb::object unit_rows(const Points &x, int num_threads) {
    std::vector<double> y(x.data(), x.data() + x.size());
    {
        nb::gil_scoped_release nogil;
        fastmac::unit_rows(y.data(), (int64_t)x.shape(0), (int64_t)x.shape(1), num_threads);
    }
    return to_numpy(std::move(y), {(size_t)x.shape(0), (size_t)x.shape(1)});
}

nb::object nearest_other_distances(const Points &points, int num_threads) {
    if (points.shape(1) != 3) throw std::invalid_argument("nearest_other_distances: points must be (N, 3)");
    std::vector<double> d;
    {
        nb::gil_scoped_release nogil;
        d = fastmac::nearest_other_distances(points.data(), (int64_t)points.shape(0), num_threads);
    }
    return to_numpy(std::move(d));
}

nb::object count_within(const Points &queries, const Points &points, double radius, int num_threads) {
    if (queries.shape(1) != 3 || points.shape(1) != 3)
        throw std::invalid_argument("count_within: queries and points must be (N, 3)");
    std::vector<int64_t> c;
    {
        nb::gil_scoped_release nogil;
        c = fastmac::count_within(queries.data(), (int64_t)queries.shape(0), points.data(),
                                  (int64_t)points.shape(0), radius, num_threads);
    }
    return to_numpy(std::move(c));
}

nb::object explained_counts(const Points &src, const Points &tgt, const Poses &poses, double threshold,
                            int num_threads) {
    if (src.shape(1) != 3 || tgt.shape(1) != 3 || src.shape(0) != tgt.shape(0))
        throw std::invalid_argument("explained_counts: src and tgt must be (N, 3) with the same N");
    if (poses.shape(1) != 4 || poses.shape(2) != 4)
        throw std::invalid_argument("explained_counts: poses must be (H, 4, 4)");
    std::vector<int64_t> c;
    {
        nb::gil_scoped_release nogil;
        c = fastmac::explained_counts(src.data(), tgt.data(), (int64_t)src.shape(0), poses.data(),
                                      (int64_t)poses.shape(0), threshold, num_threads);
    }
    return to_numpy(std::move(c));
}

nb::object nearest_rows_fast(const Points &a, const Points &b, int num_threads) {
    if (a.shape(1) != b.shape(1))
        throw std::invalid_argument("a and b must have the same number of columns, got " +
                                    std::to_string(a.shape(1)) + " and " + std::to_string(b.shape(1)));
    fastmac::Matches mt;
    {
        nb::gil_scoped_release nogil;
        mt = fastmac::nearest_rows_fast(a.data(), (int64_t)a.shape(0), b.data(), (int64_t)b.shape(0),
                                        (int64_t)a.shape(1), num_threads);
    }
    return nb::make_tuple(to_numpy(std::move(mt.idx)), to_numpy(std::move(mt.d2_second)), mt.settled_in_float64);
}

nb::object kabsch(const Points &src, const Points &tgt, nb::object weights) {
    const int64_t n = check_pair(src, tgt);
    std::vector<double> w;
    if (!weights.is_none()) {
        auto wa = nb::cast<Weights>(weights);
        if ((int64_t)wa.shape(0) != n) throw std::invalid_argument("weights must have one entry per row");
        w.assign(wa.data(), wa.data() + n);
    }
    const fastmac::Pose T = fastmac::kabsch(src.data(), tgt.data(), nullptr, n, w.empty() ? nullptr : w.data());
    return pose_to_numpy(T);
}

fastmac::PatchIndex buffer_patch_index(const Points &cloud, double radius, int64_t k) {
    if (cloud.shape(1) != 3 || k < 1 || !(radius > 0))
        throw std::invalid_argument("buffer_patch_index: (N, 3) cloud, radius > 0, k >= 1");
    nb::gil_scoped_release nogil;
    return fastmac::buffer_patch_index(cloud.data(), (int64_t)cloud.shape(0), radius, k);
}

nb::object buffer_cut_patches(const Points &cloud, const Points &keypoints, double radius, int64_t k,
                              const fastmac::PatchIndex *index) {
    if (cloud.shape(1) != 3 || keypoints.shape(1) != 3 || k < 1)
        throw std::invalid_argument("buffer_cut_patches: (N, 3) cloud and (M, 3) keypoints, k >= 1");
    if (index && (index->n != (int64_t)cloud.shape(0) || index->radius != radius))
        throw std::invalid_argument("buffer_cut_patches: the index was built for another cloud or radius");
    const int64_t m = (int64_t)keypoints.shape(0);
    std::vector<double> out(size_t(m * k * 3));
    {
        nb::gil_scoped_release nogil;
        if (index)
            fastmac::buffer_cut_patches(cloud.data(), *index, keypoints.data(), m, k, out.data());
        else
            fastmac::buffer_cut_patches(cloud.data(), (int64_t)cloud.shape(0), keypoints.data(), m, radius, k,
                                        out.data());
    }
    return to_numpy(std::move(out), {size_t(m), size_t(k), 3});
}

using Floats3 = nb::ndarray<const float, nb::ndim<3>, nb::c_contig, nb::device::cpu>;
using Floats2 = nb::ndarray<const float, nb::ndim<2>, nb::c_contig, nb::device::cpu>;
using Shorts = nb::ndarray<const int16_t, nb::ndim<1>, nb::c_contig, nb::device::cpu>;

nb::object buffer_group_cells(const Floats3 &pts, const Floats2 &centres, float r2, const Indices &ptr,
                              const Shorts &cells, int64_t grid, float inv_h, int64_t samples) {
    const int64_t m = (int64_t)pts.shape(0), p = (int64_t)pts.shape(1), ncell = (int64_t)centres.shape(0);
    if (pts.shape(2) != 3 || centres.shape(1) != 3 || (int64_t)ptr.shape(0) != grid * grid * grid + 1)
        throw std::invalid_argument("buffer_group_cells: (M, P, 3) points, (C, 3) centres, g^3 + 1 pointers");
    for (size_t i = 0; i < cells.shape(0); ++i)
        if (cells.data()[i] < 0 || cells.data()[i] >= ncell)
            throw std::invalid_argument("buffer_group_cells: a cell index is out of range");
    std::vector<float> out(size_t(m * ncell * samples * 3));
    {
        nb::gil_scoped_release nogil;
        fastmac::buffer_group_cells(pts.data(), m, p, centres.data(), ncell, r2, ptr.data(), cells.data(), grid,
                                    inv_h, samples, out.data());
    }
    return to_numpy(std::move(out), {size_t(m), size_t(ncell * samples), 3});
}

nb::object spinnet_group_cells(const Floats3 &pts, const Floats2 &centres, float r2, const Indices &ptr,
                               const Shorts &cells, int64_t grid, float to_unit, float inv_h, int64_t samples,
                               const Floats3 &rot) {
    const int64_t m = (int64_t)pts.shape(0), p = (int64_t)pts.shape(1), ncell = (int64_t)centres.shape(0);
    const int64_t azi_n = (int64_t)rot.shape(0);
    if (pts.shape(2) != 3 || centres.shape(1) != 3 || (int64_t)ptr.shape(0) != grid * grid * grid + 1 ||
        rot.shape(1) != 3 || rot.shape(2) != 3 || azi_n < 1 || ncell % azi_n != 0 || p < 1 || samples < 1)
        throw std::invalid_argument(
            "spinnet_group_cells: (M, P, 3) points, (C, 3) centres, g^3 + 1 pointers, (A, 3, 3) rotations, A | C");
    for (size_t i = 0; i < cells.shape(0); ++i)
        if (cells.data()[i] < 0 || cells.data()[i] >= ncell)
            throw std::invalid_argument("spinnet_group_cells: a cell index is out of range");
    std::vector<float> out(size_t(m * ncell * samples * 3));
    {
        nb::gil_scoped_release nogil;
        fastmac::spinnet_group_cells(pts.data(), m, p, centres.data(), ncell, r2, ptr.data(), cells.data(), grid,
                                     to_unit, inv_h, samples, rot.data(), azi_n, out.data());
    }
    return to_numpy(std::move(out), {size_t(m), size_t(ncell * samples), 3});
}

nb::object spinnet_pool_cells(const Floats3 &pts, const Floats2 &centres, float r2, const Indices &ptr,
                              const Shorts &cells, int64_t grid, float to_unit, float inv_h, int64_t samples,
                              const Floats3 &rot, const Floats2 &weights) {
    const int64_t m = (int64_t)pts.shape(0), p = (int64_t)pts.shape(1), ncell = (int64_t)centres.shape(0);
    const int64_t azi_n = (int64_t)rot.shape(0), nf = (int64_t)weights.shape(1);
    if (pts.shape(2) != 3 || centres.shape(1) != 3 || (int64_t)ptr.shape(0) != grid * grid * grid + 1 ||
        rot.shape(1) != 3 || rot.shape(2) != 3 || azi_n < 1 || ncell % azi_n != 0 || p < 1 || samples < 1 ||
        weights.shape(0) != 3 || nf < 1)
        throw std::invalid_argument(
            "spinnet_pool_cells: (M, P, 3) points, (C, 3) centres, g^3 + 1 pointers, (A, 3, 3) rotations, A | C, "
            "(3, F) weights");
    for (size_t i = 0; i < cells.shape(0); ++i)
        if (cells.data()[i] < 0 || cells.data()[i] >= ncell)
            throw std::invalid_argument("spinnet_pool_cells: a cell index is out of range");
    std::vector<float> out(size_t(m * ncell * nf));
    {
        nb::gil_scoped_release nogil;
        fastmac::spinnet_pool_cells(pts.data(), m, p, centres.data(), ncell, r2, ptr.data(), cells.data(), grid,
                                    to_unit, inv_h, samples, rot.data(), azi_n, weights.data(), nf, out.data());
    }
    return to_numpy(std::move(out), {size_t(m), size_t(ncell), size_t(nf)});
}

}  // namespace

NB_MODULE(_mac_core, m) {
    m.doc() = "C++ core of fastmac_exp: compatibility graphs, maximal cliques and MAC (see fastmac_exp.backends.cpp)";
    m.attr("keeps_freed_memory") = fastmac::keep_freed_memory();

    // Ctrl-C inside the core: long searches poll this from the calling thread (interrupt.hpp).
    fastmac::set_interrupt_poll([]() -> bool {
        if (!Py_IsInitialized()) return false;
        nb::gil_scoped_acquire gil;
        return PyErr_CheckSignals() != 0;  // leaves the handler's exception (KeyboardInterrupt) set
    });

    nb::register_exception_translator([](const std::exception_ptr &p, void *) {
        try {
            std::rethrow_exception(p);
        } catch (const fastmac::Interrupted &) {
            if (!PyErr_Occurred()) PyErr_SetNone(PyExc_KeyboardInterrupt);
        } catch (const fastmac::RegistrationFailed &e) {
            PyObject *cls = PyExc_RuntimeError;
            nb::object holder;
            try {
                holder = nb::module_::import_("fastmac_exp.errors").attr("RegistrationFailed");
                cls = holder.ptr();
            } catch (...) {
                PyErr_Clear();
            }
            PyErr_SetString(cls, e.what());
        }
    });

    m.def("bf16_cores", &fastmac::bf16_cores,
          "Whether MAC's dense cores of >= mac_reduced_core nodes run in bfloat16 here (the build and the CPU have "
          "AVX512_BF16).");
    m.def("bf16_kernel", &fastmac::bf16_kernel,
          "The tile that runs those cores here: 'amx' (AMX-BF16, where Linux grants the tile state), 'avx512_bf16' "
          "or '' (none); FASTMAC_GEMM=avx512 takes the AVX512_BF16 tile over AMX.");
    m.def("graph_edges", &graph_edges, "src"_a, "tgt"_a, "kernel"_a, "alpha"_a, "tau"_a, "threshold"_a,
          "num_threads"_a = 0,
          "Upper-triangle edges (i < j) of W with their weights w and second-order weights g = G_ij.");
    m.def("graph_signals", &graph_signals, "src"_a, "tgt"_a, "kernel"_a, "alpha"_a, "tau"_a, "threshold"_a,
          "self_loops"_a = true, "single"_a = true, "num_threads"_a = 0,
          "Generalized degree, signed high-pass and low-pass responses of the SOG (spec 7.2-7.3). single: the "
          "dense core's products in float32, as the reference computes this graph (relative error ~1e-6); "
          "False: float64 throughout.");
    m.def("anchor_degree", &anchor_degree, "src"_a, "tgt"_a, "kernel"_a, "alpha"_a, "tau"_a, "threshold"_a,
          "anchors"_a, "num_threads"_a = 0,
          "sum_r W_{i a_r} over the anchors (a_r != i) for every node: the estimate's pilot degree.");
    m.def("anchors_within", &anchors_within, "src"_a, "tgt"_a, "kernel"_a, "alpha"_a, "tau"_a, "threshold"_a,
          "anchors"_a, "min_anchors"_a, "pair_budget"_a, "num_threads"_a = 0,
          "The longest prefix of the anchor draws (min_anchors * 2^k, or all) whose pair work "
          "sum_i nnz_i^2 / 2 fits pair_budget (min_anchors when none does).");
    m.def("anchor_signals", &anchor_signals, "src"_a, "tgt"_a, "kernel"_a, "alpha"_a, "tau"_a, "threshold"_a,
          "anchors"_a, "inv_q"_a, "num_threads"_a = 0,
          "Estimated degree, high-pass and low-pass responses of FastMAC's SOG from anchors drawn i.i.d. "
          "with probabilities q (inv_q = 1 / q of each draw); unbiased for the degree (anchors.cpp).");
    m.def("maximal_cliques", &maximal_cliques, "n"_a, "i"_a, "j"_a, "min_size"_a = 3, "max_cliques"_a = 0,
          "time_limit_s"_a = 0.0, "num_threads"_a = 0,
          "Every maximal clique of size >= min_size in canonical order, and the cap that stopped the search "
          "('' when none).");
    m.def("mac", &mac, "src"_a, "tgt"_a, "kernel"_a, "alpha"_a, "tau"_a, "threshold"_a, "inlier_threshold"_a,
          "min_clique_size"_a = 3, "refine_iters"_a = 20, "reduction"_a = true, "search"_a = "auto",
          "max_cliques"_a = 0, "max_nodes"_a = 0, "max_work"_a = 0, "time_limit_s"_a = 0.0,
          "enumerate_budget"_a = fastmac::kEnumerateBudget, "num_threads"_a = 0, "return_selected"_a = false,
          "return_hypotheses"_a = false,
          "MAC end to end (spec 2-5). return_selected adds 'selected': the hypotheses' cliques in order; "
          "return_hypotheses adds 'hypothesis_poses' (H, 4, 4) and 'hypothesis_scores' (H,), in the same order.");
    m.def("select_cliques", &select_cliques, "n"_a, "i"_a, "j"_a, "w"_a, "min_size"_a = 3, "search"_a = "auto",
          "max_cliques"_a = 0, "max_nodes"_a = 0, "max_work"_a = 0, "time_limit_s"_a = 0.0,
          "enumerate_budget"_a = fastmac::kEnumerateBudget, "num_threads"_a = 0,
          "Node-guided clique selection (spec 4) on the graph with positive edge weights w: a dict with "
          "'cliques' (the selected cliques in hypothesis order), 'n_cliques' (maximal cliques enumerated, or "
          "cliques offered by the branch and bound), 'search_nodes', 'search_work' (the branch and bound's "
          "work units, what max_work caps), 'search_used' (what 'auto' ran), "
          "'enumerate_work' (auto's enumeration work, against enumerate_budget times the nodes that can be "
          "in a clique) and 'cap_hit'.");
    m.def("turboreg", &turboreg, "src"_a, "tgt"_a, "max_n"_a = 7000, "tau"_a = 0.012, "num_pivot"_a = 2000,
          "radius_nms"_a = 0.15, "tau_inlier"_a = 0.1, "metric"_a = "IN", "hard"_a = true, "refine_iters"_a = 20,
          "num_threads"_a = 0, "TurboReg (ICCV 2025) on the CPU: pose, winning 3-clique, counts, stage timings (ms)");
    m.def("length_graph_edges", &length_graph_edges, "src"_a, "tgt"_a, "tau"_a, "cut"_a, "hard"_a = true,
          "num_threads"_a = 0, "TurboReg's compatibility graph C and SC^2 on it (sc2; sc2_masked: masked_square in float64): upper edges i < j");
    m.def("torch_topk_sparse", &torch_topk_sparse, "dim"_a, "k"_a, "pos"_a, "val"_a,
          "torch.topk's positions (ties included) of a sparse non-negative sequence");
    m.def("nearest_rows", &nearest_rows, "a"_a, "b"_a, "num_threads"_a = 0,
          "Index of the nearest row of b for every row of a (Euclidean, brute force in float64; ties: lowest)");
    m.def("voxel_downsample", &voxel_downsample, "points"_a, "voxel"_a, "num_threads"_a = 0,
          "Open3D's voxel_down_sample (centroids, sums in input order), keypoints ordered by voxel");
    m.def("radius_neighbours", &radius_neighbours, "points"_a, "radius"_a, "max_nn"_a, "num_threads"_a = 0,
          "Open3D's hybrid search over a cloud itself: CSR dict(ptr, idx, d2), nearest first, at most max_nn");
    m.def("fpfh_describe", &fpfh_describe, "keypoints"_a, "normal_radius"_a, "normal_max_nn"_a, "feature_radius"_a,
          "feature_max_nn"_a, "viewpoint"_a = nb::none(), "rows"_a = nb::none(), "num_threads"_a = 0,
          "normals"_a = nb::none(), "normalize"_a = false,
          "(normals (N, 3), FPFH (rows, 33)) with Open3D's definitions; given normals are used as they are; "
          "normalize: each row divided by its norm as numpy's np.linalg.norm gives it (bit for bit)");
    m.def("unit_rows", &unit_rows, "x"_a, "num_threads"_a = 0,
          "x / np.linalg.norm(x, axis=1, keepdims=True) bit for bit (rows of norm 0 unchanged), as a new array");
    m.def("nearest_other_distances", &nearest_other_distances, "points"_a, "num_threads"_a = 0,
          "Each point's distance to its nearest other point (exact, from a grid; MAC's mesh resolution is the mean)");
    m.def("count_within", &count_within, "queries"_a, "points"_a, "radius"_a, "num_threads"_a = 0,
          "For each query, how many points lie within radius (squared distance <= radius^2), from a grid");
    m.def("explained_counts", &explained_counts, "src"_a, "tgt"_a, "poses"_a, "threshold"_a, "num_threads"_a = 0,
          "For each pose (H, 4, 4), how many correspondences it maps within threshold (|R s + t - q| < threshold)");
    m.def("nearest_rows_fast", &nearest_rows_fast, "a"_a, "b"_a, "num_threads"_a = 0,
          "(nearest_rows' indices by a float32 screen and float64 where needed, runner-up squared distance "
          "in float64, rows whose winner float64 settled)");
    m.def("kabsch", &kabsch, "src"_a, "tgt"_a, "weights"_a = nb::none(),
          "4x4 pose by Kabsch with unweighted centroids (optionally weighted cross-covariance).");
    nb::class_<fastmac::PatchIndex>(m, "BufferPatchIndex",
                                    "buffer_cut_patches' grid over one cloud (buffer_patch_index)")
        .def_ro("n", &fastmac::PatchIndex::n)
        .def_ro("radius", &fastmac::PatchIndex::radius)
        .def_prop_ro("levels", [](const fastmac::PatchIndex &ix) { return ix.level_size.size(); });
    m.def("buffer_patch_index", &buffer_patch_index, "cloud"_a, "radius"_a, "k"_a,
          "The grid buffer_cut_patches searches, built once for a cloud (pass it as index=)");
    m.def("buffer_cut_patches", &buffer_cut_patches, "cloud"_a, "keypoints"_a, "radius"_a, "k"_a,
          "index"_a.none() = nb::none(),
          "BUFFER patches (M, k, 3): the first k-1 cloud points within radius of each keypoint, padded with it");
    m.def("buffer_group_cells", &buffer_group_cells, "pts"_a, "centres"_a, "r2"_a, "ptr"_a, "cells"_a, "grid"_a,
          "inv_h"_a, "samples"_a, "BUFFER's sphere_query grouping of aligned patches (M, cells * samples, 3)");
    m.def("spinnet_group_cells", &spinnet_group_cells, "pts"_a, "centres"_a, "r2"_a, "ptr"_a, "cells"_a, "grid"_a,
          "to_unit"_a, "inv_h"_a, "samples"_a, "rot"_a,
          "SpinNet's sphere_query + var_to_invar of aligned patches (M, cells * samples, 3)");
    m.def("spinnet_pool_cells", &spinnet_pool_cells, "pts"_a, "centres"_a, "r2"_a, "ptr"_a, "cells"_a, "grid"_a,
          "to_unit"_a, "inv_h"_a, "samples"_a, "rot"_a, "weights"_a,
          "spinnet_group_cells, then each cell's max over its slots of slot @ weights (3, F): (M, cells, F)");
    m.def("default_threads", []() { return fastmac::resolve_threads(0); },
          "Threads used when num_threads=0 (problems with fewer than serial_below rows run on one).");
    m.attr("serial_below") = fastmac::kSerialBelow;
    m.attr("default_enumerate_budget") = fastmac::kEnumerateBudget;
    m.attr("mac_reduced_core") = fastmac::kSingleCore;  // MAC's cores from this many nodes: float32 or bfloat16  // params.DEFAULT_ENUMERATE_BUDGET
#ifdef FASTMAC_OPENMP
    m.attr("parallel_backend") = "openmp";
#else
    m.attr("parallel_backend") = "threads";
#endif
}
