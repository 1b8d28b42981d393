"""The sampler graph's triangle listing (masked_square.cpp, forward_products): on large graphs the
products of every edge outside the dense core come from listing each triangle once instead of the
per-edge gathers. These tests force it on small graphs (FASTMAC_TRIANGLES=on) and hold it to the dense
numpy formula, to the gathers, and to one result for any number of threads."""

from __future__ import annotations

import os

import numpy as np
import pytest

from fastmac_exp import core as cpp
from tests.children import interrupt_child
from tests.test_cpp_core import clustered, dense_signals, dense_w

core = cpp.core()


def signals(monkeypatch, src, tgt, gp, mode, threads, single=True, self_loops=True):
    monkeypatch.setenv("FASTMAC_TRIANGLES", mode)
    return core.graph_signals(src, tgt, *gp, self_loops=self_loops, single=single, num_threads=threads)


@pytest.mark.parametrize(
    "n,ratio,gp,dense_core",
    [
        (900, 0.35, ("quadratic", 0.06, 0.1, 0.8), True),  # a dense core: its own triangles by GEMM
        (700, 0.05, ("quadratic", 0.06, 0.3, 0.8), False),  # sparse, no core
        (600, 0.4, ("gaussian", 0.02, 0.1, 0.3), True),  # another kernel, weights well below 1
    ],
)
@pytest.mark.parametrize("self_loops", [True, False])
def test_listing_equals_dense_formula_for_any_thread_count(monkeypatch, n, ratio, gp, dense_core, self_loops):
    src, tgt, _, _ = clustered(n, ratio, 0.004, 11)
    w = dense_w(src, tgt, *gp)
    s, f, low = dense_signals(w, self_loops)
    runs = [signals(monkeypatch, src, tgt, gp, "on", t, self_loops=self_loops) for t in (1, 2, 3)]
    assert (runs[0]["dense_core"] > 0) == dense_core
    for out in runs[1:]:  # fixed-point sums of the shared terms: bit-identical whatever the threads
        for k in ("degree", "highpass", "lowpass"):
            np.testing.assert_array_equal(out[k], runs[0][k])
    out = runs[0]
    # float32 weights (the sampler's graph, as the reference): a relative error of ~1e-7
    np.testing.assert_allclose(out["degree"], s, rtol=2e-6, atol=1e-9)
    np.testing.assert_allclose(out["highpass"], f, rtol=0, atol=1e-5 * max(np.abs(f).max(), 1.0))
    np.testing.assert_allclose(out["lowpass"], low, rtol=2e-6, atol=1e-9)
    gathers = signals(monkeypatch, src, tgt, gp, "off", 2, self_loops=self_loops)
    np.testing.assert_allclose(out["degree"], gathers["degree"], rtol=2e-6)
    assert not np.array_equal(out["degree"], gathers["degree"])  # it did run the listing


def test_mac_graph_never_lists_triangles(monkeypatch):
    """MAC's float64 graph keeps the per-edge sums (the Python backend's parity rests on their order)."""
    src, tgt, _, _ = clustered(600, 0.3, 0.004, 5)
    gp = ("quadratic", 0.06, 0.1, 0.8)
    on = signals(monkeypatch, src, tgt, gp, "on", 2, single=False)
    off = signals(monkeypatch, src, tgt, gp, "off", 2, single=False)
    for k in ("degree", "highpass", "lowpass"):
        np.testing.assert_array_equal(on[k], off[k])


def outdoor_like(n: int, inliers: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n correspondences in a 60 x 60 x 4 m scene, 10 cm noise on the inliers (bench_core's large case)."""
    rng = np.random.default_rng(seed)
    room = np.array([60.0, 60.0, 4.0])
    src = rng.uniform(0, 1, (n, 3)) * room
    tgt = src.copy()
    k = int(n * inliers)
    tgt[:k] += rng.normal(0, 0.1, (k, 3))
    tgt[k:] = rng.uniform(0, 1, (n - k, 3)) * room
    return src, tgt


def test_large_graph_takes_the_listing_by_default(monkeypatch):
    """Past 2^21 entries outside the core the default is the listing; small graphs keep the gathers."""
    gp = ("quadratic", 0.06, 0.6, 0.9)  # the KITTI / FPFH kernel
    src, tgt = outdoor_like(20000, 0.05, 0)
    on = signals(monkeypatch, src, tgt, gp, "on", 2)
    off = signals(monkeypatch, src, tgt, gp, "off", 2)
    monkeypatch.delenv("FASTMAC_TRIANGLES")
    auto = core.graph_signals(src, tgt, *gp, num_threads=2)
    assert on["n_edges"] > 1_500_000
    np.testing.assert_array_equal(auto["degree"], on["degree"])
    np.testing.assert_allclose(on["degree"], off["degree"], rtol=2e-6)
    np.testing.assert_allclose(
        on["highpass"], off["highpass"], rtol=0, atol=1e-5 * np.abs(off["highpass"]).max()
    )
    small_src, small_tgt = outdoor_like(3000, 0.05, 1)
    small_auto = core.graph_signals(small_src, small_tgt, *gp, num_threads=2)
    small_off = signals(monkeypatch, small_src, small_tgt, gp, "off", 2)
    np.testing.assert_array_equal(small_auto["degree"], small_off["degree"])


@pytest.mark.parametrize("scale", [3.0, 1.0])  # no edge at all; a complete graph K4
def test_listing_on_tiny_graphs(monkeypatch, scale):
    src = np.array([[0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3]], float)
    gp = ("quadratic", 0.05, 0.1, 0.99)
    w = dense_w(src, src * scale, *gp)
    s, f, low = dense_signals(w, True)
    out = signals(monkeypatch, src, src * scale, gp, "on", 2)
    np.testing.assert_allclose(out["degree"], s, rtol=1e-7)
    np.testing.assert_allclose(out["highpass"], f, atol=1e-6)
    np.testing.assert_allclose(out["lowpass"], low, rtol=1e-7)


# 50,000 outdoor-like correspondences: the sampler's graph (the listing) or MAC's (float64 gathers) takes
# seconds of CPU a call here; the child repeats the call so that the signal lands inside the core.
LARGE_GRAPH_SETUP = """
import numpy as np
from fastmac_exp import core as cpp
rng = np.random.default_rng(0)
room = np.array([60.0, 60.0, 4.0])
src = rng.uniform(0, 1, (50000, 3)) * room
tgt = src.copy()
tgt[:1000] += rng.normal(0, 0.1, (1000, 3))
tgt[1000:] = rng.uniform(0, 1, (49000, 3)) * room
t0 = time.process_time()
cpp.core().{call}(src, tgt, "quadratic", 0.06, 0.6, 0.9)
one_call_cpu = time.process_time() - t0
"""
LARGE_GRAPH_LOOP = """
    for _ in range(30):
        cpp.core().{call}(src, tgt, "quadratic", 0.06, 0.6, 0.9)
"""


@pytest.mark.signals
@pytest.mark.skipif(os.name != "posix", reason="sends SIGINT")
@pytest.mark.parametrize("call", ["graph_signals", "graph_edges"])
def test_ctrl_c_stops_a_large_second_order_graph(call):
    """Ctrl-C inside the second-order products (the sampler's listing, MAC's gathers) of a 50,000-node
    graph: the core polls for it and gives control back at once, not at the end of the call."""
    rc, word, after_cpu, one_call = interrupt_child(
        LARGE_GRAPH_SETUP.format(call=call), LARGE_GRAPH_LOOP.format(call=call)
    )
    assert rc == 130 and word == "interrupted"
    # half a call's CPU time in: a core that ignored the signal would spend the other half first
    assert after_cpu < one_call / 4, f"{after_cpu:.2f} CPU s to stop, one call {one_call:.2f} s"
