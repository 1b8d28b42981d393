"""The C++ core (fastmac_exp._mac_core): exact against dense numpy, igraph and the Python backend."""

from __future__ import annotations

import os
import time
from dataclasses import replace
from pathlib import Path

import igraph
import numpy as np
import pytest
import scipy.sparse as sp

from fastmac_exp import core as cpp
from fastmac_exp.backends import cpp as cpp_backend
from fastmac_exp.backends import python_mac
from fastmac_exp.errors import BackendUnavailable, RegistrationFailed
from fastmac_exp.geometry.transforms import kabsch, random_rotation, rotation_error_deg
from fastmac_exp.params import GraphParams, MacParams
from fastmac_exp.types import Correspondences
from tests.conftest import make_correspondences

core = cpp.core()  # the README's install builds it: a missing core is a failure, not a skip


# ---------------------------------------------------------------------------------------------------
# helpers


def clustered(n: int, ratio: float, noise: float, seed: int, extent: float = 3.0):
    """Correspondences with a consistent inlier group and uniform outliers, plus the true pose."""
    rng = np.random.default_rng(seed)
    r = random_rotation(rng)
    t = rng.uniform(-1, 1, 3)
    src = rng.uniform(0, extent, (n, 3))
    tgt = src @ r.T + t
    k = int(round(n * ratio))
    tgt[:k] += rng.normal(0, noise, (k, 3))
    tgt[k:] = rng.uniform(0, extent, (n - k, 3)) @ r.T + t
    perm = rng.permutation(n)
    return np.ascontiguousarray(src[perm]), np.ascontiguousarray(tgt[perm]), r, t


def dense_w(src, tgt, kernel, alpha, tau, thr):
    dp = np.linalg.norm(src[:, None] - src[None], axis=2)
    dq = np.linalg.norm(tgt[:, None] - tgt[None], axis=2)
    d = np.abs(dp - dq)
    s = np.exp(-(d**2) / (2.0 * alpha**2)) if kernel == "gaussian" else 1.0 - d**2 / tau**2
    w = np.where(s >= thr, s, 0.0)
    np.fill_diagonal(w, 0.0)
    return w


def dense_signals(w, self_loops):
    a = w + np.eye(len(w)) if self_loops else w
    sog = a * (a @ a)
    s = sog.sum(axis=1)
    f = (np.diag(s) - sog) @ s
    with np.errstate(divide="ignore", invalid="ignore"):
        low = np.where(s > 0, s + (sog @ s) / np.where(s > 0, s, 1.0), 0.0)
    return s, f, low


def as_sets(cliques):
    return {tuple(int(v) for v in c) for c in cliques}


def is_canonical(cliques):
    tuples = [tuple(int(v) for v in c) for c in cliques]
    return all(list(t) == sorted(t) for t in tuples) and tuples == sorted(tuples)


# ---------------------------------------------------------------------------------------------------
# graphs


@pytest.mark.parametrize(
    "kernel,alpha,tau,thr", [("gaussian", 0.05, 0.1, 0.9), ("quadratic", 0.06, 0.1, 0.8)]
)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_graph_edges_equal_dense_numpy(kernel, alpha, tau, thr, seed):
    src, tgt, _, _ = clustered(120, 0.4, 0.01, seed)
    e = core.graph_edges(src, tgt, kernel, alpha, tau, thr)
    w = dense_w(src, tgt, kernel, alpha, tau, thr)
    g = w * (w @ w)
    i, j = np.nonzero(np.triu(w, 1))  # row-major, like the core's output
    assert len(i) > 100 and (g > 0).sum() > 50  # a non-trivial graph
    np.testing.assert_array_equal(e["i"], i)
    np.testing.assert_array_equal(e["j"], j)
    np.testing.assert_allclose(e["w"], w[i, j], rtol=0, atol=1e-9)
    np.testing.assert_allclose(e["g"], g[i, j], rtol=0, atol=1e-9)
    assert e["i"].dtype == np.int64 and e["w"].dtype == np.float64


def test_graph_edges_threads_agree_and_wrapper():
    src, tgt, _, _ = clustered(400, 0.3, 0.01, 5)
    gp = GraphParams("quadratic", 0.06, 0.1, 0.9)
    one = cpp.graph_edges(src, tgt, gp, num_threads=1)
    two = cpp.graph_edges(src, tgt, gp, num_threads=2)
    for k in "ijwg":
        np.testing.assert_array_equal(getattr(one, k), getattr(two, k))


@pytest.mark.parametrize("kernel", ["quadratic", "gaussian"])
@pytest.mark.parametrize("extent", [3.0, 80.0])
def test_pair_screens_agree(monkeypatch, extent, kernel):
    """The generic, AVX2 and AVX-512 screens and exact tests (picked at run time) give exactly the same
    edges and scores (the AVX-512 test computes the weights eight lanes at a time)."""
    src, tgt, _, _ = clustered(700, 0.2, 0.01 * extent / 3, 8, extent=extent)
    tau = 0.1 * extent / 3
    gp = (kernel, 0.02 * extent / 3, tau, 0.9)
    out, res = {}, {}
    for screen in ("generic", "avx2", "avx512"):
        monkeypatch.setenv("FASTMAC_SCREEN", screen)  # falls back where the CPU lacks the instructions
        out[screen] = core.graph_edges(src, tgt, *gp)
        res[screen] = core.mac(src, tgt, *gp, tau)  # residual screens too
    assert len(out["generic"]["i"]) > 500
    for screen in ("avx2", "avx512"):
        for k in "ijwg":
            np.testing.assert_array_equal(out[screen][k], out["generic"][k])
        for k in ("pose", "pose_unrefined", "clique"):
            np.testing.assert_array_equal(res[screen][k], res["generic"][k])
        assert res[screen]["score"] == res["generic"]["score"]


@pytest.mark.parametrize("seed", [0, 1])
def test_dense_core_products_equal_dense_numpy(monkeypatch, seed):
    """Graphs with a dense core (outdoor-like: a large consistent group) take the matrix-product path
    (masked_square.cpp); every kernel and the all-sparse path give W * (W W) and the dense numpy signals."""
    src, tgt, _, _ = clustered(900, 0.35, 0.004, seed)
    gp = ("quadratic", 0.06, 0.1, 0.8)
    w = dense_w(src, tgt, *gp)
    g = w * (w @ w)
    i, j = np.nonzero(np.triu(w, 1))
    s, f, _ = dense_signals(w, True)
    cores = {}
    modes = [
        ("sparse", {"FASTMAC_DENSE_CORE": "off"}),
        ("generic", {"FASTMAC_GEMM": "generic"}),
        ("avx2", {"FASTMAC_GEMM": "avx2"}),
        ("avx512", {"FASTMAC_GEMM": "avx512"}),
    ]
    for mode, env in modes:
        monkeypatch.delenv("FASTMAC_DENSE_CORE", raising=False)
        monkeypatch.delenv("FASTMAC_GEMM", raising=False)
        for k, v in env.items():
            monkeypatch.setenv(k, v)  # a kernel the CPU lacks falls back to one it has
        for threads in (1, 2):
            e = core.graph_edges(src, tgt, *gp, num_threads=threads)
            np.testing.assert_array_equal(e["i"], i)
            np.testing.assert_array_equal(e["j"], j)
            np.testing.assert_allclose(e["g"], g[i, j], rtol=1e-12, atol=1e-12)
            sig = core.graph_signals(src, tgt, *gp, single=False, num_threads=threads)
            np.testing.assert_allclose(sig["degree"], s, rtol=1e-12)
            np.testing.assert_allclose(sig["highpass"], f, rtol=1e-9, atol=1e-9 * np.abs(s).max() ** 2)
            # float32 products in the core (the sampler's default, as the reference's torch code)
            sig32 = core.graph_signals(src, tgt, *gp, num_threads=threads)
            np.testing.assert_allclose(sig32["degree"], s, rtol=2e-6)
            np.testing.assert_allclose(sig32["highpass"], f, rtol=0, atol=1e-5 * np.abs(f).max())
            gap = np.abs(sig32["degree"] - sig["degree"]).max() / s.max()
            assert (gap == 0) if mode == "sparse" else (1e-12 < gap < 2e-6)  # float32 ran in the core only
            cores[mode] = (e["dense_core"], sig["dense_core"], sig32["dense_core"])
    assert cores["sparse"] == (0, 0, 0)
    n_in = int(round(900 * 0.35))
    for mode in ("generic", "avx2", "avx512"):  # the product path fired, on about the inlier group
        assert 0.8 * n_in <= cores[mode][0] <= 1.3 * n_in and len(set(cores[mode])) == 1, cores


def test_mac_products_run_in_float32_in_large_cores_only(monkeypatch):
    """MAC's products (G, the clustering coefficients' sums) stay float64 in cores under
    core.mac_reduced_core (320) nodes and run in float32 in larger ones (the near-cliques FastMAC keeps
    at 50,000, where the product is MAC's whole cost; the reference computes G in float32, spec 2.3): G
    within float32's rounding of dense numpy, and MAC's pose that of the float64 products."""
    src, tgt, r, t = clustered(2400, 0.5, 0.004, 11)
    gp = ("quadratic", 0.06, 0.1, 0.8)
    w = dense_w(src, tgt, *gp)
    i, j = np.nonzero(np.triu(w, 1))
    g = (w * (w @ w))[i, j]
    out, res = {}, {}
    for mode in ("double", "single"):  # single: float32 (the default where the CPU lacks AVX512_BF16)
        monkeypatch.setenv("FASTMAC_MAC_PRECISION", mode)
        out[mode] = core.graph_edges(src, tgt, *gp)
        res[mode] = core.mac(src, tgt, *gp, 0.1)
    assert out["single"]["dense_core"] >= core.mac_reduced_core, out["single"]["dense_core"]
    np.testing.assert_allclose(out["double"]["g"], g, rtol=1e-12)
    np.testing.assert_allclose(out["single"]["g"], g, rtol=2e-6)
    pos = g > 0
    gap = np.abs(out["single"]["g"][pos] / g[pos] - 1).max()
    assert 1e-12 < gap < 2e-6, gap  # float32 ran, within its rounding
    rot = rotation_error_deg(res["single"]["pose"][:3, :3], res["double"]["pose"][:3, :3])
    assert rot < 1e-3 and np.linalg.norm(res["single"]["pose"][:3, 3] - res["double"]["pose"][:3, 3]) < 1e-4
    assert rotation_error_deg(res["single"]["pose"][:3, :3], r) < 2.0
    # a smaller core keeps float64: the same G as with the switch
    assert core.mac_reduced_core == 320
    src, tgt, _, _ = clustered(700, 0.35, 0.004, 0)
    monkeypatch.setenv("FASTMAC_MAC_PRECISION", "auto")
    small = core.graph_edges(src, tgt, *gp)
    monkeypatch.setenv("FASTMAC_MAC_PRECISION", "double")
    assert 128 <= small["dense_core"] < core.mac_reduced_core, small["dense_core"]
    np.testing.assert_array_equal(small["g"], core.graph_edges(src, tgt, *gp)["g"])
    # a core of 320-511 nodes (the ~450 of the 500 that samples=auto keeps of a dense KITTI pair) does not
    src, tgt, r, _ = clustered(1000, 0.42, 0.004, 0)
    w = dense_w(src, tgt, *gp)
    i, j = np.nonzero(np.triu(w, 1))
    g = (w * (w @ w))[i, j]
    monkeypatch.setenv("FASTMAC_MAC_PRECISION", "auto")
    mid, mid_pose = core.graph_edges(src, tgt, *gp), core.mac(src, tgt, *gp, 0.1)["pose"]
    monkeypatch.setenv("FASTMAC_MAC_PRECISION", "double")
    exact, exact_pose = core.graph_edges(src, tgt, *gp), core.mac(src, tgt, *gp, 0.1)["pose"]
    assert core.mac_reduced_core <= mid["dense_core"] < 512, mid["dense_core"]
    pos = g > 0
    gap = np.abs(mid["g"][pos] / g[pos] - 1)
    assert np.abs(exact["g"][pos] / g[pos] - 1).max() < 1e-12
    assert 1e-12 < gap.max() < 1e-3 and np.median(gap) < 1e-4, (gap.max(), np.median(gap))
    assert rotation_error_deg(mid_pose[:3, :3], exact_pose[:3, :3]) < 1e-3
    assert np.linalg.norm(mid_pose[:3, 3] - exact_pose[:3, 3]) < 1e-4
    assert rotation_error_deg(mid_pose[:3, :3], r) < 2.0


@pytest.mark.parametrize("n,ratio", [(600, 0.42), (1100, 0.3), (1500, 0.27)])
def test_packed_products_at_tile_edges_and_thread_counts(monkeypatch, n, ratio):
    """Cores of sizes that are not multiples of the micro-kernels' tiles (12 x 32 floats, 12 x 16 doubles,
    6 x 16 / 6 x 8 for AVX2, 4 x 8 portable): every kernel's packed product equals dense numpy in float64,
    and 1, 2 and 3 threads give bit-identical sums (each tile of P is accumulated in one fixed order
    whatever the thread count)."""
    src, tgt, _, _ = clustered(n, ratio, 0.004, n)
    gp = ("quadratic", 0.06, 0.1, 0.8)
    w = dense_w(src, tgt, *gp)
    i, j = np.nonzero(np.triu(w, 1))
    g = (w * (w @ w))[i, j]
    monkeypatch.setenv("FASTMAC_MAC_PRECISION", "double")  # the float64 tiles (cores of 320+ would reduce)
    for kernel in ("generic", "avx2", "avx512"):
        monkeypatch.setenv("FASTMAC_GEMM", kernel)  # a kernel the CPU lacks falls back to one it has
        out = {t: core.graph_edges(src, tgt, *gp, num_threads=t) for t in (1, 2, 3)}
        m = out[1]["dense_core"]
        assert m >= 128 and m % 12 and m % 16, m
        np.testing.assert_array_equal(out[1]["i"], i)
        np.testing.assert_allclose(out[1]["g"], g, rtol=1e-12, atol=1e-12)
        sig = {t: core.graph_signals(src, tgt, *gp, num_threads=t) for t in (1, 2, 3)}
        for t in (2, 3):
            np.testing.assert_array_equal(out[t]["g"], out[1]["g"])
            for k in ("degree", "highpass", "lowpass"):
                np.testing.assert_array_equal(sig[t][k], sig[1][k])


@pytest.mark.parametrize("na,nb,dim", [(1000, 1500, 33), (13, 5, 33), (9, 1, 3), (40, 17, 7)])
def test_nearest_rows_equal_a_kd_tree(monkeypatch, na, nb, dim):
    """The brute-force feature matcher (FPFH) gives cKDTree's nearest neighbour, with the lowest index on
    exact ties, for block and padding edges (rows not a multiple of 8, fewer columns than a vector)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(na)
    a, b = rng.random((na, dim)), rng.random((nb, dim))
    b[nb // 2 :] = b[: nb - nb // 2] if nb > 1 else b[nb // 2 :]  # duplicated rows: exact ties
    dist, _ = cKDTree(b).query(a, k=1)
    for kernel in ("generic", "avx512"):
        monkeypatch.setenv("FASTMAC_NN", kernel)  # falls back where the CPU lacks AVX-512
        for threads in (1, 2):
            idx = core.nearest_rows(a, b, num_threads=threads)
            np.testing.assert_allclose(np.linalg.norm(a - b[idx], axis=1), dist, rtol=1e-12, atol=1e-12)
            d_all = np.linalg.norm(a[:, None] - b[None], axis=2)
            ties = np.isclose(d_all, dist[:, None], rtol=1e-12, atol=1e-12)
            np.testing.assert_array_equal(idx, ties.argmax(axis=1))  # the lowest index among the ties
    with pytest.raises(ValueError, match="same number of columns"):
        core.nearest_rows(a, b[:, :2].copy())
    assert len(core.nearest_rows(a[:0].copy(), b)) == 0


def test_core_keeps_freed_memory_unless_told_not_to():
    """The module sets glibc's malloc to keep freed memory mapped (page faults cost ~1.7 us each in a VM);
    FASTMAC_MALLOC_TUNE=0 leaves the allocator as it was."""
    import platform
    import subprocess
    import sys

    code = "from fastmac_exp import core; print(core.core().keeps_freed_memory)"
    env = dict(os.environ)
    on = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    env["FASTMAC_MALLOC_TUNE"] = "0"
    off = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert off.stdout.strip() == "False"
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc":
        assert on.stdout.strip() == "True"


def test_dense_core_is_used_by_mac_with_the_same_result(monkeypatch):
    src, tgt, r, t = clustered(700, 0.4, 0.004, 3)
    out = {}
    for mode in ("off", "on"):
        monkeypatch.setenv("FASTMAC_DENSE_CORE", mode)
        out[mode] = core.mac(src, tgt, "quadratic", 0.06, 0.1, 0.8, 0.1, return_selected=True)
    assert core.graph_edges(src, tgt, "quadratic", 0.06, 0.1, 0.8)["dense_core"] >= 200
    assert [list(c) for c in out["on"]["selected"]] == [list(c) for c in out["off"]["selected"]]
    np.testing.assert_allclose(out["on"]["pose"], out["off"]["pose"], atol=1e-9)
    assert rotation_error_deg(out["on"]["pose"][:3, :3], r) < 2.0


@pytest.mark.parametrize("self_loops", [True, False])
@pytest.mark.parametrize("kernel,thr", [("gaussian", 0.9), ("quadratic", 0.8)])
def test_graph_signals_equal_dense_formula(self_loops, kernel, thr):
    src, tgt, _, _ = clustered(90, 0.4, 0.01, 7)
    gp = GraphParams(kernel, 0.05, 0.1, thr)
    out = cpp.graph_signals(src, tgt, gp, self_loops=self_loops)
    w = dense_w(src, tgt, kernel, 0.05, 0.1, thr)
    s, f, low = dense_signals(w, self_loops)
    np.testing.assert_allclose(out.degree, s, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(out.highpass, f, rtol=1e-9, atol=1e-7 * np.abs(s).max() ** 2)
    np.testing.assert_allclose(out.lowpass, low, rtol=1e-12, atol=1e-9)
    assert out.n_edges == int((np.triu(w, 1) > 0).sum())


def test_second_order_mirror_in_blocks_equals_dense_formula():
    """A graph of > 2^15 edges: the second-order values are mirrored to the lower entries in parallel row
    blocks; any thread count gives the serial values, which are the dense formula's."""
    src, tgt, _, _ = clustered(700, 0.5, 0.005, 11)
    gp = GraphParams("quadratic", 0.05, 0.1, 0.01)
    w = dense_w(src, tgt, "quadratic", 0.05, 0.1, 0.01)
    assert (np.triu(w, 1) > 0).sum() > 2**15
    s, f, _ = dense_signals(w, False)
    one = cpp.graph_signals(src, tgt, gp, self_loops=False, single=False, num_threads=1)
    two = cpp.graph_signals(src, tgt, gp, self_loops=False, single=False, num_threads=2)
    np.testing.assert_array_equal(one.degree, two.degree)
    np.testing.assert_array_equal(one.highpass, two.highpass)
    np.testing.assert_allclose(one.degree, s, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(one.highpass, f, rtol=1e-9, atol=1e-7 * np.abs(s).max() ** 2)


def test_graph_signals_isolated_nodes():
    # no edges at all: with self-loops s = 1, f = 0, l = 2; without, everything is 0
    src = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3]], float)
    tgt = src * 3.0
    gp = GraphParams("quadratic", 0.05, 0.1, 0.99)
    on = cpp.graph_signals(src, tgt, gp, self_loops=True)
    off = cpp.graph_signals(src, tgt, gp, self_loops=False)
    assert on.n_edges == 0 and off.n_edges == 0
    np.testing.assert_array_equal(on.degree, np.ones(4))
    np.testing.assert_array_equal(on.highpass, np.zeros(4))
    np.testing.assert_array_equal(on.lowpass, np.full(4, 2.0))
    for k in ("degree", "highpass", "lowpass"):
        np.testing.assert_array_equal(getattr(off, k), np.zeros(4))


def test_four_node_hand_example():
    """Worked on paper.

    Points on a line, p = (x, 0, 0), q = (y, 0, 0), so d_ij = | |x_i - x_j| - |y_i - y_j| |:
      x = 0, 1, 2, 3 and y = 0, 1, 2.2, 3.5
      d01 = 0, d02 = d12 = 0.2, d23 = |1 - 1.3| = 0.3, d03 = d13 = 0.5.
    Quadratic kernel, tau = 1: s = 1 - d^2, so W01 = 1, W02 = W12 = 0.96, W23 = 0.91, and
    W03 = W13 = 0.75 fall below the threshold 0.8.

    MAC's G_ij = W_ij * sum_{k != i,j} W_ik W_kj:
      G01 = 1 * (W02 W21) = 0.9216, G02 = 0.96 * (W01 W12) = 0.9216, G12 = 0.9216,
      G23 = 0.91 * (W20 W03 + W21 W13) = 0   (3 shares no neighbour with 2).
    Without self-loops: s = (1.8432, 1.8432, 1.8432, 0), f = 0 (the triangle is regular),
      l_i = s_i + (sum_j G_ij s_j) / s_i = 1.8432 + 2 * 0.9216 = 3.6864, and l_3 = 0.
    With self-loops: off the diagonal SOG_ij = 2 W_ij^2 + G_ij:
      SOG01 = 2 + 0.9216 = 2.9216, SOG02 = SOG12 = 2 * 0.9216 + 0.9216 = 2.7648, SOG23 = 2 * 0.8281 = 1.6562;
      on it SOG_ii = 1 + sum_k W_ik^2: 2.9216, 2.9216, 1 + 0.9216 + 0.9216 + 0.8281 = 3.6713, 1.8281.
      s0 = s1 = 2.9216 + 2.9216 + 2.7648 = 8.608, s2 = 3.6713 + 2 * 2.7648 + 1.6562 = 10.8571,
      s3 = 1.8281 + 1.6562 = 3.4843.
      f0 = f1 = 2.7648 * (8.608 - 10.8571) = -6.21831168,
      f2 = 2 * 2.7648 * 2.2491 + 1.6562 * (10.8571 - 3.4843) = 12.43662336 + 12.21083136 = 24.64745472,
      f3 = 1.6562 * (3.4843 - 10.8571) = -12.21083136   (sum f = 0, as a Laplacian's must).
      l0 = 8.608 + (2.9216 * 8.608 * 2 + 2.7648 * 10.8571) / 8.608
         = 8.608 + 80.31597568 / 8.608 = 17.93838751,
      l2 = 10.8571 + (2 * 2.7648 * 8.608 + 3.6713 * 10.8571 + 1.6562 * 3.4843) / 10.8571 = 19.44403074,
      l3 = 3.4843 + (1.6562 * 10.8571 + 1.8281 * 3.4843) / 3.4843 = 10.47312928.
    """
    x = np.array([0.0, 1.0, 2.0, 3.0])
    y = np.array([0.0, 1.0, 2.2, 3.5])
    src = np.column_stack([x, np.zeros(4), np.zeros(4)])
    tgt = np.column_stack([y, np.zeros(4), np.zeros(4)])
    gp = GraphParams("quadratic", alpha=1.0, tau=1.0, threshold=0.8)

    e = cpp.graph_edges(src, tgt, gp)
    np.testing.assert_array_equal(e.i, [0, 0, 1, 2])
    np.testing.assert_array_equal(e.j, [1, 2, 2, 3])
    np.testing.assert_allclose(e.w, [1.0, 0.96, 0.96, 0.91], atol=1e-12)
    np.testing.assert_allclose(e.g, [0.9216, 0.9216, 0.9216, 0.0], atol=1e-12)

    off = cpp.graph_signals(src, tgt, gp, self_loops=False)
    assert off.n_edges == 4
    np.testing.assert_allclose(off.degree, [1.8432, 1.8432, 1.8432, 0.0], atol=1e-12)
    np.testing.assert_allclose(off.highpass, [0.0, 0.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(off.lowpass, [3.6864, 3.6864, 3.6864, 0.0], atol=1e-12)

    on = cpp.graph_signals(src, tgt, gp, self_loops=True)
    np.testing.assert_allclose(on.degree, [8.608, 8.608, 10.8571, 3.4843], atol=1e-12)
    np.testing.assert_allclose(on.highpass, [-6.21831168, -6.21831168, 24.64745472, -12.21083136], atol=1e-10)
    np.testing.assert_allclose(on.lowpass, [17.93838751, 17.93838751, 19.44403074, 10.47312928], atol=1e-8)


def test_graph_input_validation():
    src = np.zeros((5, 3))
    with pytest.raises(ValueError, match="kernel"):
        core.graph_edges(src, src, "cubic", 0.1, 0.1, 0.9)
    with pytest.raises(ValueError, match="shape"):
        core.graph_edges(np.zeros((5, 4)), np.zeros((5, 4)), "gaussian", 0.1, 0.1, 0.9)
    with pytest.raises(ValueError, match="same number of rows"):
        core.graph_edges(src, np.zeros((4, 3)), "gaussian", 0.1, 0.1, 0.9)
    with pytest.raises(ValueError, match="threshold"):
        core.graph_signals(src, src, "gaussian", 0.1, 0.1, 1.5)
    # non-contiguous and float32 input is converted
    a = np.random.default_rng(0).uniform(0, 1, (50, 6)).astype(np.float32)
    e1 = core.graph_edges(a[:, :3], a[:, 3:], "gaussian", 0.1, 0.1, 0.5)
    e2 = core.graph_edges(
        a[:, :3].astype(np.float64).copy(), a[:, 3:].astype(np.float64).copy(), "gaussian", 0.1, 0.1, 0.5
    )
    np.testing.assert_array_equal(e1["w"], e2["w"])


# ---------------------------------------------------------------------------------------------------
# maximal cliques


def igraph_cliques(n, i, j, k):
    g = igraph.Graph(n=n, edges=list(zip(i.tolist(), j.tolist())))
    g.simplify()
    return {tuple(sorted(c)) for c in g.maximal_cliques(min=k)}


def er_edges(n, p, seed):
    rng = np.random.default_rng(seed)
    i, j = np.triu_indices(n, 1)
    keep = rng.random(len(i)) < p
    return i[keep], j[keep]


@pytest.mark.parametrize(
    "n,p", [(20, 0.3), (20, 0.7), (60, 0.1), (60, 0.4), (150, 0.05), (150, 0.2), (300, 0.02), (300, 0.08)]
)
@pytest.mark.parametrize("k", [3, 4])
def test_maximal_cliques_equal_igraph_on_random_graphs(n, p, k):
    i, j = er_edges(n, p, seed=n + int(100 * p))
    got, cap = core.maximal_cliques(n, i, j, min_size=k)
    assert cap == ""
    assert is_canonical(got)
    assert as_sets(got) == igraph_cliques(n, i, j, k)
    assert len(got) == len(as_sets(got))


def test_maximal_cliques_on_a_registration_graph():
    # the support of G on correspondences: a dense inlier block plus sparse outlier structure
    src, tgt, _, _ = clustered(400, 0.15, 0.01, 11)
    e = core.graph_edges(src, tgt, "quadratic", 0.06, 0.1, 0.9)
    keep = e["g"] > 0
    i, j = e["i"][keep], e["j"][keep]
    got, cap = core.maximal_cliques(400, i, j, 3)
    want = igraph_cliques(400, i, j, 3)
    assert len(want) > 20
    assert as_sets(got) == want and is_canonical(got) and cap == ""
    # thread counts and the Python wrapper agree exactly (canonical order)
    one, _ = cpp.maximal_cliques(400, i, j, 3, num_threads=1)
    two, _ = cpp.maximal_cliques(400, i.astype(np.int32), j.astype(np.int32), 3, num_threads=2)
    assert [c.tolist() for c in one] == [c.tolist() for c in got] == [c.tolist() for c in two]


def test_maximal_cliques_edge_list_is_sanitised():
    # duplicates, both directions and self-loops are ignored; a triangle plus a pendant edge
    i = np.array([0, 1, 2, 1, 0, 3, 3, 2])
    j = np.array([1, 0, 0, 2, 2, 3, 2, 1])
    got, _ = core.maximal_cliques(4, i, j, 2)
    assert [c.tolist() for c in got] == [[0, 1, 2], [2, 3]]
    with pytest.raises(ValueError, match="out of range"):
        core.maximal_cliques(3, np.array([0]), np.array([3]), 3)
    assert core.maximal_cliques(0, np.zeros(0, np.int64), np.zeros(0, np.int64), 3) == ([], "")


def test_clique_caps_are_recorded():
    i, j = er_edges(120, 0.5, seed=3)  # a great many maximal cliques
    got, cap = core.maximal_cliques(120, i, j, 3, max_cliques=25)
    assert cap == "max_cliques=25" and len(got) == 25 and is_canonical(got)
    full = igraph_cliques(120, i, j, 3)
    assert as_sets(got) <= full
    # a cap the graph does not reach is not reported
    small_i, small_j = er_edges(30, 0.2, seed=4)
    _, cap = core.maximal_cliques(30, small_i, small_j, 3, max_cliques=10**6)
    assert cap == ""

    i, j = er_edges(400, 0.5, seed=5)  # would take far longer than the limit
    t0 = time.process_time()  # CPU time: what the search did, however loaded the machine
    got, cap = core.maximal_cliques(400, i, j, 3, time_limit_s=0.05)
    assert time.process_time() - t0 < 2.0
    assert cap == "time_limit=0.05s"
    assert is_canonical(got)

    corr, _ = make_correspondences(n=600, inlier_ratio=0.05, noise=0.002, seed=3)
    res = cpp_backend.CppBackend().register(corr, MacParams(search="enumerate", max_cliques=2))
    assert res.cap_hit == "max_cliques=2" and res.n_cliques == 2
    res = cpp_backend.CppBackend().register(corr, MacParams(search="bnb", max_nodes=2))
    assert res.cap_hit == "max_nodes=2" and res.search == "bnb"


@pytest.mark.parametrize("bad", [np.inf, np.nan, 0.0, -1.0])
def test_selection_refuses_non_finite_or_non_positive_weights(bad):
    """An infinite weight would make the branch and bound's dominance rule disagree with the enumeration."""
    i, j = er_edges(30, 0.3, 0)
    w = np.ones(len(i))
    w[3] = bad
    for search in ("enumerate", "bnb"):
        with pytest.raises(ValueError, match=r"finite and positive \(edge 3\)"):
            core.select_cliques(30, i, j, w, 3, search=search)


@pytest.mark.parametrize("seed", range(12))
def test_node_guided_selection_equals_reference_with_ties(seed):
    """Integer weights make many cliques exactly as heavy: ties go to the canonically earliest clique."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(20, 120))
    i, j = er_edges(n, float(rng.uniform(0.05, 0.4)), seed)
    w = rng.integers(1, 4, len(i)).astype(float)
    g = sp.coo_matrix((np.r_[w, w], (np.r_[i, j], np.r_[j, i])), shape=(n, n)).tocsr()
    cliques = python_mac.canonical_cliques(
        igraph.Graph(n=n, edges=list(zip(i.tolist(), j.tolist()))).maximal_cliques(min=3)
    )
    want = [tuple(c) for c in python_mac.select_cliques(cliques, g, n)]
    for threads in (1, 2):
        enum = core.select_cliques(n, i, j, w, 3, search="enumerate", num_threads=threads)
        assert enum["n_cliques"] == len(cliques)
        assert [tuple(c.tolist()) for c in enum["cliques"]] == want
        bnb = core.select_cliques(n, i, j, w, 3, search="bnb", num_threads=threads)
        assert [tuple(c.tolist()) for c in bnb["cliques"]] == want
        assert bnb["cap_hit"] == ""


# ---------------------------------------------------------------------------------------------------
# poses and MAC


def test_kabsch_matches_numpy():
    rng = np.random.default_rng(1)
    for m in (3, 4, 10, 100):
        p = rng.normal(size=(m, 3))
        q = p @ random_rotation(rng).T + rng.normal(size=3) + rng.normal(0, 0.05, (m, 3))
        np.testing.assert_allclose(core.kabsch(p, q), kabsch(p, q), atol=1e-9)
        w = rng.uniform(0.1, 1.0, m)
        np.testing.assert_allclose(core.kabsch(p, q, w), kabsch(p, q, w), atol=1e-9)
    # a mirrored target: the reflection is fixed, both give the same proper rotation
    p = rng.normal(size=(12, 3))
    q = p * [1, 1, -1]
    t = core.kabsch(p, q)
    np.testing.assert_allclose(t, kabsch(p, q), atol=1e-9)
    assert np.linalg.det(t[:3, :3]) == pytest.approx(1.0)


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("kernel,alpha,thr", [("quadratic", 0.06, 0.99), ("gaussian", 0.02, 0.5)])
def test_known_pose_recovered_with_95_percent_outliers(seed, kernel, alpha, thr):
    src, tgt, r, t = clustered(200, 0.05, 0.01, seed)  # 10 inliers with 1 cm noise
    res = cpp_backend.CppBackend().register(
        Correspondences(src, tgt), MacParams(graph=GraphParams(kernel, alpha, 0.1, thr), inlier_threshold=0.1)
    )
    assert rotation_error_deg(res.pose[:3, :3], r) < 2.0
    assert np.linalg.norm(res.pose[:3, 3] - t) < 0.03
    inliers = np.linalg.norm(src @ r.T + t - tgt, axis=1) < 0.1
    assert inliers[res.clique].all()
    assert set(res.timings) == {"graph", "cliques", "selection", "pose"}
    np.testing.assert_array_equal(res.kept, np.arange(200))
    assert res.score > 0 and res.n_selected >= 1 and res.n_cliques >= res.n_selected


def test_mac_errors_are_registration_failed():
    b = cpp_backend.CppBackend()
    with pytest.raises(RegistrationFailed, match="need at least 3 correspondences, got 2"):
        b.register(Correspondences(np.zeros((2, 3)), np.zeros((2, 3))), MacParams())
    rng = np.random.default_rng(0)
    far = Correspondences(rng.uniform(0, 1, (20, 3)), rng.uniform(0, 100, (20, 3)))
    with pytest.raises(RegistrationFailed, match="graph has no second-order edge"):
        b.register(far, MacParams())
    src, tgt, _, _ = clustered(200, 0.05, 0.002, 1)
    with pytest.raises(RegistrationFailed, match="no maximal clique of size >= 30"):
        b.register(Correspondences(src, tgt), MacParams(min_clique_size=30))
    with pytest.raises(RegistrationFailed):  # also from the module itself
        core.mac(far.src, far.tgt, "gaussian", 0.06, 0.1, 0.995, 0.1)


def test_backend_unavailable_explains_how_to_build(monkeypatch):
    monkeypatch.setattr(cpp, "_core", None)
    monkeypatch.setattr(cpp, "_IMPORT_ERROR", "No module named 'fastmac_exp._mac_core'")
    assert not cpp.available()
    with pytest.raises(BackendUnavailable, match="pip install") as err:
        cpp_backend.CppBackend()
    assert "CMake" in str(err.value) and "backend=python" in str(err.value)


def test_threads_give_identical_results():
    src, tgt, _, _ = clustered(800, 0.1, 0.01, 21)
    args = (src, tgt, "quadratic", 0.06, 0.1, 0.95, 0.1)
    a = core.mac(*args, num_threads=1, return_selected=True)
    b = core.mac(*args, num_threads=2, return_selected=True)
    for k in ("pose", "pose_unrefined", "clique"):
        np.testing.assert_array_equal(a[k], b[k])
    assert a["score"] == b["score"] and a["n_cliques"] == b["n_cliques"]
    assert [c.tolist() for c in a["selected"]] == [c.tolist() for c in b["selected"]]


def _mac_score_in_child(args, queue):
    queue.put(core.mac(*args, num_threads=2)["score"])


def test_concurrent_calls_and_fork():
    """The worker pool serves concurrent callers and is rebuilt in a forked child (no deadlock)."""
    import multiprocessing
    import threading

    src, tgt, _, _ = clustered(1600, 0.1, 0.01, 4)
    args = (src, tgt, "quadratic", 0.06, 0.1, 0.95, 0.1)
    want = core.mac(*args, num_threads=2)["score"]  # the parent's pool now exists
    got = []
    threads = [
        threading.Thread(target=lambda: got.append(core.mac(*args, num_threads=2)["score"])) for _ in range(3)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert got == [want] * 3
    if "fork" not in multiprocessing.get_all_start_methods():
        return
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_mac_score_in_child, args=(args, queue))
    child.start()
    assert queue.get(timeout=60) == want
    child.join(timeout=60)


# ---------------------------------------------------------------------------------------------------
# parity with the Python backend


PARITY_CASES = [
    # n, inlier ratio, noise, kernel, alpha, threshold, min clique size, extent
    (300, 0.1, 0.01, "quadratic", 0.06, 0.9, 3, 3.0),
    (400, 0.05, 0.005, "gaussian", 0.03, 0.6, 3, 3.0),
    (500, 0.2, 0.02, "gaussian", 0.06, 0.9, 3, 3.0),
    (300, 0.3, 0.01, "quadratic", 0.06, 0.95, 4, 3.0),
    (300, 0.5, 0.001, "quadratic", 0.06, 0.9, 3, 3.0),  # dense: the reduction of spec 2.5 fires
    (400, 0.1, 0.05, "quadratic", 0.06, 0.9, 3, 60.0),  # KITTI-like scale (tau = 0.6 below)
]


@pytest.mark.parametrize("case", PARITY_CASES)
def test_parity_with_python_backend(case):
    n, ratio, noise, kernel, alpha, thr, k, extent = case
    src, tgt, _, _ = clustered(n, ratio, noise, seed=n + k, extent=extent)
    tau = 0.6 if extent > 10 else 0.1
    params = MacParams(graph=GraphParams(kernel, alpha, tau, thr), inlier_threshold=tau, min_clique_size=k)
    corr = Correspondences(src, tgt)
    a = python_mac.PythonBackend().register(corr, params)
    enum = cpp_backend.CppBackend().register(corr, replace(params, search="enumerate"))
    assert (a.n_cliques, a.n_selected, a.n_edges, a.reduced) == (
        enum.n_cliques,
        enum.n_selected,
        enum.n_edges,
        enum.reduced,
    )
    if extent < 10 and ratio == 0.5:
        assert a.reduced, "the dense case must exercise the reduction of spec 2.5"
    b = cpp_backend.CppBackend().register(corr, replace(params, search="bnb"))
    assert b.search == "bnb" and b.cap_hit == ""
    auto = cpp_backend.CppBackend().register(corr, params)  # the default search
    assert auto.search in ("auto:enumerate", "auto:bnb")
    assert auto.n_cliques == (enum.n_cliques if auto.search == "auto:enumerate" else b.n_cliques)
    for c in (enum, b, auto):
        assert (c.n_selected, c.n_edges, c.reduced) == (a.n_selected, a.n_edges, a.reduced)
        np.testing.assert_array_equal(a.clique, c.clique)
        np.testing.assert_allclose(c.pose_unrefined, a.pose_unrefined, atol=1e-6)
        np.testing.assert_allclose(c.pose, a.pose, atol=1e-6)
        assert c.score == pytest.approx(a.score, rel=1e-9)

    # the selected cliques themselves, in order
    full = core.mac(src, tgt, kernel, alpha, tau, thr, tau, min_clique_size=k, return_selected=True)
    full_enum = core.mac(
        src, tgt, kernel, alpha, tau, thr, tau, min_clique_size=k, search="enumerate", return_selected=True
    )
    w = python_mac.first_order(src, tgt, params.graph)
    g = python_mac.second_order(w)
    gc, _ = python_mac.reduce_graph(g)
    upper = sp.triu(gc, k=1).tocoo()
    cliques = python_mac.canonical_cliques(
        igraph.Graph(n=n, edges=list(zip(upper.row.tolist(), upper.col.tolist()))).maximal_cliques(min=k)
    )
    selected = python_mac.select_cliques(cliques, g, n)
    assert [tuple(c.tolist()) for c in full["selected"]] == [tuple(c) for c in selected]
    assert [tuple(c.tolist()) for c in full_enum["selected"]] == [tuple(c) for c in selected]
    assert full["n_sog_edges"] == sp.triu(g, k=1).nnz


def test_core_so_env_loads_a_pinned_copy(tmp_path):
    """FASTMAC_CORE_SO=<file> loads the extension from that file (the studies pin one copy for a whole
    run); a path that is no extension leaves the core unavailable with a message naming the variable."""
    import shutil
    import subprocess
    import sys

    copy = tmp_path / "pinned" / Path(core.__file__).name
    copy.parent.mkdir()
    shutil.copy(core.__file__, copy)
    probe = "from fastmac_exp import core; print(core.available(), core.core().__file__)"
    run = lambda so: subprocess.run(  # noqa: E731
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=120,
        env={**os.environ, "FASTMAC_CORE_SO": str(so)},
    )  # fmt: skip
    ok = run(copy)
    assert ok.returncode == 0 and ok.stdout.split() == ["True", str(copy)], ok.stderr
    bad = run(tmp_path / "nothing.so")
    assert bad.returncode != 0 and "FASTMAC_CORE_SO" in bad.stderr and "nothing.so" in bad.stderr


def test_the_cores_default_budgets_are_the_configs():
    """The C++ default of mac.enumerate_budget (used by direct callers of the binding) is params.py's."""
    from fastmac_exp.params import DEFAULT_ENUMERATE_BUDGET

    assert core.default_enumerate_budget == DEFAULT_ENUMERATE_BUDGET == MacParams().enumerate_budget


def test_mac_products_run_in_bfloat16_in_the_largest_cores(monkeypatch):
    """Cores of >= core.mac_reduced_core nodes (the 1,000 FastMAC@20 keeps of a dense KITTI pair, the
    near-cliques samples=5000 keeps of 200,000 correspondences) run MAC's products from bfloat16 operands
    with float32 sums where the CPU has AVX512_BF16: G within bfloat16's rounding of dense numpy (each
    term's two factors rounded stochastically to 8 significant bits, so that the errors average out over
    the ~1,000 terms of a sum), and MAC's pose that of the float64 products."""
    src, tgt, r, t = clustered(2400, 0.5, 0.004, 5)
    gp = ("quadratic", 0.06, 0.1, 0.8)
    w = dense_w(src, tgt, *gp)
    i, j = np.nonzero(np.triu(w, 1))
    g = (w * (w @ w))[i, j]
    out, res = {}, {}
    for mode in ("double", "single", "auto"):
        monkeypatch.setenv("FASTMAC_MAC_PRECISION", mode)
        out[mode] = core.graph_edges(src, tgt, *gp)
        res[mode] = core.mac(src, tgt, *gp, 0.1)
    assert out["auto"]["dense_core"] >= core.mac_reduced_core, out["auto"]["dense_core"]
    pos = g > 0
    gap = {m: np.abs(out[m]["g"][pos] / g[pos] - 1) for m in out}
    assert gap["double"].max() < 1e-12 and 1e-12 < gap["single"].max() < 2e-6
    if core.bf16_cores():
        signed = out["auto"]["g"][pos] / g[pos] - 1
        # measured at 4,400 nodes: max 2.8e-4, median 2.5e-5, mean 2.7e-7 (rounding to nearest: median
        # 3.9e-4, all of one sign, the weights crowding below 1; hence the stochastic rounding)
        assert 2e-6 < gap["auto"].max() < 1e-3 and np.median(gap["auto"]) < 1e-4, (
            gap["auto"].max(),
            np.median(gap["auto"]),
        )
        assert abs(signed.mean()) < 1e-5, signed.mean()
    else:  # float32 where the CPU lacks bfloat16 dot products
        np.testing.assert_array_equal(out["auto"]["g"], out["single"]["g"])
    for m in ("single", "auto"):
        rot = rotation_error_deg(res[m]["pose"][:3, :3], res["double"]["pose"][:3, :3])
        assert rot < 1e-3 and np.linalg.norm(res[m]["pose"][:3, 3] - res["double"]["pose"][:3, 3]) < 1e-4
    assert rotation_error_deg(res["auto"]["pose"][:3, :3], r) < 2.0
    # FASTMAC_GEMM=avx2 (no bfloat16 tile) runs float32
    monkeypatch.setenv("FASTMAC_MAC_PRECISION", "auto")
    monkeypatch.setenv("FASTMAC_GEMM", "avx2")
    np.testing.assert_allclose(core.graph_edges(src, tgt, *gp)["g"][pos], g[pos], rtol=2e-6)


@pytest.mark.parametrize("n,ratio", [(1100, 0.42), (2400, 0.5)])
def test_the_amx_tile_sums_the_same_bfloat16_products(monkeypatch, n, ratio):
    """Where the CPU has AMX (and Linux grants it), MAC's bfloat16 cores run on it: the same rounded operands
    as the AVX512_BF16 tile, only summed in the hardware's order, so G agrees with that tile's to float32's
    rounding of the sums (a misplaced pair or column in the AMX packing would be off by the products
    themselves), the core sizes are not multiples of its 32 x 32 tile or of its 16 pairs a group, and 1, 2
    and 3 threads give the same bits."""
    monkeypatch.setenv("FASTMAC_GEMM", "amx")
    if core.bf16_kernel() != "amx":
        pytest.skip("no AMX-BF16 here (CPU or kernel)")
    monkeypatch.setenv("FASTMAC_GEMM", "avx512")
    assert core.bf16_kernel() == "avx512_bf16"
    src, tgt, _, _ = clustered(n, ratio, 0.004, n)
    gp = ("quadratic", 0.06, 0.1, 0.8)
    w = dense_w(src, tgt, *gp)
    i, j = np.nonzero(np.triu(w, 1))
    g = (w * (w @ w))[i, j]
    ref = core.graph_edges(src, tgt, *gp)
    monkeypatch.setenv("FASTMAC_GEMM", "amx")
    out = {t: core.graph_edges(src, tgt, *gp, num_threads=t) for t in (1, 2, 3)}
    m = out[1]["dense_core"]
    assert m >= core.mac_reduced_core and m % 32, m
    np.testing.assert_array_equal(out[1]["i"], i)
    pos = g > 0
    np.testing.assert_allclose(out[1]["g"][pos], ref["g"][pos], rtol=5e-5)
    assert np.abs(out[1]["g"][pos] / g[pos] - 1).max() < 1e-3  # bfloat16's rounding, as the other tile
    for t in (2, 3):
        np.testing.assert_array_equal(out[t]["g"], out[1]["g"])


def test_a_small_graph_dense_all_over_is_one_core(monkeypatch):
    """Where a small graph is dense all over (FastMAC@20's 1,000 keeps of a dense outdoor pair: half of all
    pairs linked, outliers included), the cost model runs the product over every node (no gathers, no
    nodes outside the product, no mirror): G as dense numpy's within the arithmetic's rounding, as with the
    degree rule's core (FASTMAC_DENSE_CORE=core), and MAC's pose that of the float64 products."""
    src, tgt, _, _ = clustered(900, 0.6, 0.004, 1, extent=0.4)
    gp = ("quadratic", 0.06, 0.1, 0.8)
    w = dense_w(src, tgt, *gp)
    i, j = np.nonzero(np.triu(w, 1))
    g = (w * (w @ w))[i, j]
    pos = g > 0
    monkeypatch.setenv("FASTMAC_MAC_PRECISION", "double")
    ref = core.mac(src, tgt, *gp, 0.1)
    # auto: bfloat16 where the CPU has it (fewer terms a sum than at 2,400 nodes: a larger worst case)
    for mode, tol, median_tol in (("single", 2e-6, 2e-7), ("auto", 5e-3, 1e-4)):
        monkeypatch.setenv("FASTMAC_MAC_PRECISION", mode)
        monkeypatch.delenv("FASTMAC_DENSE_CORE", raising=False)
        whole, res = core.graph_edges(src, tgt, *gp), core.mac(src, tgt, *gp, 0.1)
        monkeypatch.setenv("FASTMAC_DENSE_CORE", "core")
        rule = core.graph_edges(src, tgt, *gp)
        assert whole["dense_core"] == 900 and 128 <= rule["dense_core"] < 900, (
            whole["dense_core"],
            rule["dense_core"],
        )
        for out in (whole, rule):
            gap = np.abs(out["g"][pos] / g[pos] - 1)
            assert gap.max() < tol and np.median(gap) < median_tol, (mode, gap.max(), np.median(gap))
        assert np.all(whole["g"][~pos] == 0)
        rot = rotation_error_deg(res["pose"][:3, :3], ref["pose"][:3, :3])
        assert rot < 1e-3 and np.linalg.norm(res["pose"][:3, 3] - ref["pose"][:3, 3]) < 1e-4, (mode, rot)
