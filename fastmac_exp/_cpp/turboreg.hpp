// TurboReg (Yan et al., "TurboReg: TurboClique for Robust and Efficient Point Cloud Registration",
// ICCV 2025) on the CPU, written from the paper and the behaviour of its public code (Laka-3DV/TurboReg
// @827025f, turboreg/src/turboreg.cpp, core_turboreg_gpu.cpp, model_selection.cpp). See docs/turboreg.md.
#pragma once

#include <cstdint>

#include "mac_core.hpp"

namespace fastmac {

struct TurboParams {
    int64_t max_n = 7000;       // keep the first max_n correspondences (upstream's max_N); <= 0: all of them
    double tau = 0.012;         // tau_length_consis: the compatibility's length tolerance (m)
    int64_t num_pivot = 2000;   // K1: pivot edges, the top entries of SC^2's upper triangle
    double radius_nms = 0.15;   // radiu_nms: pairs with |p_i - p_j| + |q_i - q_j| <= this are no edge
    double tau_inlier = 0.1;    // the hypothesis metric's and the refinement's inlier threshold (m)
    Metric metric = Metric::Inliers;
    bool hard = true;           // C = [d < tau] (upstream's default, `hard = true`) or relu(1 - (d / tau)^2)
    int refine_iters = 20;
};

struct TurboResult {
    Pose pose, pose_unrefined;
    int64_t clique[3] = {0, 0, 0};  // the winning TurboClique
    double score = 0.0;             // its metric
    int64_t n_used = 0, n_edges = 0, n_sog_edges = 0, n_pivots = 0, n_hypotheses = 0, n_unique = 0;
    int refine_iters_run = 0;
    // Wall-clock ms. graph: C and SC^2. pivots: the top-K1 edges and the 3-cliques grown from them.
    // hypotheses: Kabsch on every clique and the metric. pose: the post-refinement.
    double t_graph = 0, t_pivots = 0, t_hypotheses = 0, t_pose = 0;
};

Metric parse_metric(const std::string &name);  // "IN" | "MAE" | "MSE"; throws std::invalid_argument

// src, tgt: row-major (n, 3). Throws RegistrationFailed when n < 3 or SC^2 has no positive entry.
TurboResult turboreg(const double *src, const double *tgt, int64_t n, const TurboParams &p, int nthreads);

// torch.topk(values, k) on the CPU (largest, sorted), tie order included: the positions of the k largest of
// a length-dim sequence that is zero except at the positions pos (ascending, values val > 0). Exposed for
// tests.
std::vector<int64_t> torch_topk_sparse(int64_t dim, int64_t k, const std::vector<int64_t> &pos,
                                       const std::vector<double> &val);

}  // namespace fastmac
