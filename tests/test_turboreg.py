"""backend=turboreg: TurboReg (ICCV 2025) in the C++ core against upstream's poses, a dense torch oracle of
upstream's algorithm, a known pose, torch.topk's tie order, and bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fastmac_exp import core
from fastmac_exp.backends.turboreg import TurboRegBackend
from fastmac_exp.errors import InputError, RegistrationFailed
from fastmac_exp.geometry.metrics import pose_errors
from fastmac_exp.params import mac_params_for
from fastmac_exp.types import Correspondences
from tests.conftest import SHARED_DATA, make_correspondences

pytestmark = pytest.mark.skipif(not core.available(), reason="C++ core not built")
REF = SHARED_DATA / "turboreg_reference"
INDOOR = dict(max_n=7000, tau=0.012, num_pivot=2000, radius_nms=0.15, tau_inlier=0.1)


def run(src, tgt, **kw):
    return core.core().turboreg(np.ascontiguousarray(src, float), np.ascontiguousarray(tgt, float), **kw)


def reference_pairs():
    if not (REF / "turboreg_reference.json").exists():
        return []
    ref = json.loads((REF / "turboreg_reference.json").read_text())
    return [(name, e, ref["params"][e["params"]]) for name, e in ref["pairs"].items()]


@pytest.mark.skipif(not reference_pairs(), reason="../shared/data/turboreg_reference absent")
@pytest.mark.parametrize("name", [p[0] for p in reference_pairs()] or ["none"])
def test_parity_with_upstream(name):
    """Upstream's pose on its fixed correspondences: RE < 0.05 deg, TE < 1 mm, the same success verdict."""
    _, e, p = next(x for x in reference_pairs() if x[0] == name)
    z = np.load(REF / e["file"], allow_pickle=True)
    r = run(z["src"], z["tgt"], max_n=p["max_N"], tau=p["tau_length_consis"], num_pivot=p["num_pivot"],
            radius_nms=p["radiu_nms"], tau_inlier=p["tau_inlier"], metric=p["metric"])  # fmt: skip
    upstream = np.asarray(e["turboreg_pose"])
    d = pose_errors(r["pose"], upstream, 0.05, 1e-3)
    assert d.re_deg < 0.05 and d.te_cm < 0.1, (name, d)
    re_t, te_t = float(z["re_thresh_deg"]), float(z["te_thresh_m"])
    ours, theirs = pose_errors(r["pose"], z["gt"], re_t, te_t), pose_errors(upstream, z["gt"], re_t, te_t)
    assert ours.success == theirs.success
    assert r["n_used"] == min(len(z["src"]), p["max_N"])


# ---------------------------------------------------------------------------------------------------
# a dense re-statement of upstream's runRegCXX in torch (float32, its operations in its order): the oracle
# for inputs without ../shared


def upstream_dense(src, tgt, max_n, tau, num_pivot, radius_nms, tau_inlier):
    torch = pytest.importorskip("torch")
    s = torch.tensor(src[:max_n], dtype=torch.float32)
    t = torch.tensor(tgt[:max_n], dtype=torch.float32)
    n = len(s)
    ds = torch.norm(s.unsqueeze(1) - s.unsqueeze(0), 2, -1)
    dt = torch.norm(t.unsqueeze(1) - t.unsqueeze(0), 2, -1)
    c = (torch.abs(ds - dt) < tau).to(torch.float32)
    c.masked_fill_((ds + dt) <= radius_nms, 0)
    sc2 = torch.matmul(c, c) * c
    up = torch.triu(sc2, 1)
    idx = torch.topk(up.flatten(), num_pivot)[1]
    piv = torch.stack([idx // n, idx % n], 1)
    r0, r1 = up.index_select(0, piv[:, 0]), up.index_select(0, piv[:, 1])
    score = (up[piv[:, 0], piv[:, 1]].unsqueeze(1) + (r0 + r1)) * ((r0 > 0) & (r1 > 0)).to(torch.float32)
    top2 = torch.topk(score, 2, dim=1)[1]
    cliques = torch.cat([torch.cat([piv, top2[:, :1]], 1), torch.cat([piv, top2[:, 1:]], 1)], 0)
    return cliques.numpy(), up.numpy(), c.numpy()


def kabsch_np(a, b, w=None):
    w = np.ones(len(a)) if w is None else w
    ca, cb = (a * w[:, None]).sum(0) / (w.sum() + 1e-6), (b * w[:, None]).sum(0) / (w.sum() + 1e-6)
    u, _, vt = np.linalg.svd((a - ca).T @ ((b - cb) * w[:, None]))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1, 1, d]) @ u.T
    return r, cb - r @ ca


def test_cliques_and_pose_match_a_dense_torch_oracle():
    corr, gt = make_correspondences(n=700, inlier_ratio=0.15, noise=0.003, seed=3)
    kw = dict(INDOOR, num_pivot=300)
    cliques, up, c = upstream_dense(corr.src, corr.tgt, kw["max_n"], kw["tau"], kw["num_pivot"],
                                    kw["radius_nms"], kw["tau_inlier"])  # fmt: skip
    g = core.core().length_graph_edges(corr.src, corr.tgt, kw["tau"], kw["radius_nms"])
    iu = np.nonzero(np.triu(c, 1))
    assert len(g["i"]) == len(iu[0]) and (g["i"] == iu[0]).all() and (g["j"] == iu[1]).all()
    assert (g["sc2"] == up[g["i"], g["j"]]).all()  # SC^2 exactly
    np.testing.assert_array_equal(g["sc2_masked"], g["sc2"])  # bitset counts = the core's masked square
    soft = core.core().length_graph_edges(corr.src, corr.tgt, kw["tau"], kw["radius_nms"], hard=False)
    np.testing.assert_array_equal(soft["i"], g["i"])
    assert ((soft["w"] > 0) & (soft["w"] <= 1)).all()
    # the oracle's best hypothesis (IN, first argmax) and refinement, in float64
    r = run(corr.src, corr.tgt, **kw)
    counts = []
    for cl in cliques:
        R, t = kabsch_np(corr.src[cl], corr.tgt[cl])
        counts.append((np.linalg.norm(corr.src @ R.T + t - corr.tgt, axis=1) < kw["tau_inlier"]).sum())
    best = cliques[int(np.argmax(counts))]
    assert sorted(r["clique"]) == sorted(best)
    assert r["score"] == max(counts)
    R, t = kabsch_np(corr.src[best], corr.tgt[best])
    prev = 0
    for _ in range(20):
        e = np.linalg.norm(corr.src @ R.T + t - corr.tgt, axis=1)
        m = e < kw["tau_inlier"]
        if m.sum() == prev:
            break
        prev = m.sum()
        R, t = kabsch_np(corr.src[m], corr.tgt[m], 1 / (1 + (e[m] / kw["tau_inlier"]) ** 2))
    np.testing.assert_allclose(r["pose"][:3, :3], R, atol=1e-9)
    np.testing.assert_allclose(r["pose"][:3, 3], t, atol=1e-9)
    assert pose_errors(r["pose"], gt, 1.0, 0.02).success


def test_sc2_bitset_tiles_are_exact_for_any_thread_count(monkeypatch):
    """5,000 nodes: SC^2's bitset counts run over two column chunks and three row blocks (the cache tiles of
    common_neighbours.cpp) and must equal C (C C) on C's support, whatever the thread count and kernel."""
    sparse = pytest.importorskip("scipy.sparse")
    corr, _ = make_correspondences(n=5000, inlier_ratio=0.1, noise=0.003, seed=5)
    g = {t: core.core().length_graph_edges(corr.src, corr.tgt, 0.03, 0.15, num_threads=t) for t in (1, 2, 3)}
    i, j = g[1]["i"], g[1]["j"]
    assert len(i) > 100_000 and j.max() >= 4096 and (j - i).max() > 2048  # edges across chunks and blocks
    c = sparse.coo_matrix((np.ones(len(i)), (i, j)), shape=(5000, 5000)).tocsr()
    c = c + c.T
    want = np.asarray((c @ c)[i, j]).ravel()
    np.testing.assert_array_equal(g[1]["sc2"], want)
    np.testing.assert_array_equal(g[1]["sc2_masked"], want)
    for t in (2, 3):
        np.testing.assert_array_equal(g[t]["sc2"], g[1]["sc2"])
    monkeypatch.setenv("FASTMAC_GEMM", "generic")  # the portable kernel (CPUs without AVX-512 VPOPCNTDQ)
    np.testing.assert_array_equal(core.core().length_graph_edges(corr.src, corr.tgt, 0.03, 0.15)["sc2"], want)


@pytest.mark.parametrize("extent,tau,cut", [(3.0, 0.012, 0.15), (80.0, 0.1, 0.15), (3.0, 0.05, 1.0)])
def test_length_graph_kernels_agree(monkeypatch, extent, tau, cut):
    """C by the AVX-512 kernel and by the portable one: exactly the same edges (many of them near tau and
    near the length cut) and soft weights."""
    corr, _ = make_correspondences(n=3000, inlier_ratio=0.2, noise=0.003, seed=11, extent=extent)
    for hard in (True, False):
        monkeypatch.delenv("FASTMAC_SCREEN", raising=False)
        got = core.core().length_graph_edges(corr.src, corr.tgt, tau, cut, hard=hard)
        monkeypatch.setenv("FASTMAC_SCREEN", "generic")
        want = core.core().length_graph_edges(corr.src, corr.tgt, tau, cut, hard=hard)
        assert len(want["i"]) > 5000
        for k in "ijw":  # the soft graph's weights too
            np.testing.assert_array_equal(got[k], want[k])


def test_masked_square_path_gives_the_bitset_path_result(monkeypatch):
    """FASTMAC_TURBO_SC2=masked: SC^2 of the (unweighted) hard graph by masked_square instead of the bitset
    counts; the same cliques and pose."""
    corr, _ = make_correspondences(n=1500, inlier_ratio=0.1, noise=0.003, seed=7)
    want = run(corr.src, corr.tgt, **INDOOR)
    monkeypatch.setenv("FASTMAC_TURBO_SC2", "masked")
    got = run(corr.src, corr.tgt, **INDOOR)
    assert list(got["clique"]) == list(want["clique"]) and got["n_sog_edges"] == want["n_sog_edges"]
    np.testing.assert_array_equal(got["pose"], want["pose"])


def test_topk_tie_order_is_torchs():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(0)
    cases = ((200_000, 2000, 0.05), (1000, 50, 0.3), (5000, 2, 0.01), (100, 2, 0.2), (300, 30, 1.0))
    for dim, k, density in cases:
        v = np.zeros(dim, np.float32)
        pos = np.sort(rng.choice(dim, int(dim * density), replace=False))
        v[pos] = rng.integers(1, 6, len(pos))  # many ties
        want = torch.topk(torch.from_numpy(v), k)[1].numpy()
        got = core.core().torch_topk_sparse(dim, k, pos.astype(np.int64), v[pos].astype(np.float64))
        np.testing.assert_array_equal(got, want)


def test_known_pose_and_family_defaults():
    corr, gt = make_correspondences(n=2000, inlier_ratio=0.08, noise=0.003, seed=1)
    b = TurboRegBackend()
    assert b.settings("3dmatch") == INDOOR
    assert b.settings("kitti") == dict(max_n=6000, tau=0.1, num_pivot=2500, radius_nms=0.15, tau_inlier=0.4)
    res = b.register(corr, mac_params_for("3dmatch", "fpfh"))
    assert pose_errors(res.pose, gt, 1.0, 0.02).success
    assert set(res.timings) == {"graph", "pivots", "hypotheses", "pose"}
    assert len(res.clique) == 3 and corr.labels[res.clique].all()


def test_max_n_keeps_the_first_correspondences_and_null_keeps_all():
    corr, _ = make_correspondences(n=900, inlier_ratio=0.2, noise=0.003, seed=2)
    first = run(corr.src[:500], corr.tgt[:500], **dict(INDOOR, max_n=0))
    cut = run(corr.src, corr.tgt, **dict(INDOOR, max_n=500))
    np.testing.assert_array_equal(first["pose"], cut["pose"])
    assert cut["n_used"] == 500
    assert run(corr.src, corr.tgt, **dict(INDOOR, max_n=0))["n_used"] == 900
    assert TurboRegBackend(max_N=None).settings("3dmatch")["max_n"] == 0


def test_wrong_answers_are_caught_bad_input_raises():
    corr, _ = make_correspondences(n=300, seed=4)
    params = mac_params_for("3dmatch", "fpfh")
    with pytest.raises(RegistrationFailed):
        TurboRegBackend().register(Correspondences(corr.src[:2], corr.tgt[:2]), params)
    with pytest.raises(RegistrationFailed):
        run(corr.src[:2], corr.tgt[:2])
    bad = corr.src.copy()
    bad[5, 1] = np.nan
    with pytest.raises((InputError, ValueError)):
        run(bad, corr.tgt)
    with pytest.raises(InputError):
        TurboRegBackend(metric="median")
    with pytest.raises(InputError):
        TurboRegBackend(max_N="some")
    with pytest.raises(ValueError):
        run(corr.src, corr.tgt, tau=0.0)
    # no compatible triangle at all (every pair inconsistent): a failure, not an arbitrary pose
    rng = np.random.default_rng(0)
    with pytest.raises(RegistrationFailed):
        run(rng.uniform(0, 1, (3, 3)), rng.uniform(0, 100, (3, 3)))


def test_fastmac_sampler_in_front(tmp_path):
    """sampler=highpass ratio=0.2 backend=turboreg end to end: a row with TurboReg's stage timings."""
    from fastmac_exp.pipeline import register_correspondences
    from fastmac_exp.samplers import make_sampler

    corr, gt = make_correspondences(n=2000, inlier_ratio=0.1, noise=0.003, seed=5)
    res, _ = register_correspondences(corr, mac_params_for("3dmatch", "fpfh"), make_sampler("highpass"),
                                      TurboRegBackend(), ratio=0.2)  # fmt: skip
    assert len(res.kept) == 400
    assert {"sampling", "graph", "pivots", "hypotheses", "pose", "total"} <= set(res.timings)
    assert pose_errors(res.pose, gt, 2.0, 0.05).success


def test_summary_shows_turboregs_stages():
    from fastmac_exp.run.experiment import format_summary

    s = {"pairs": 1, "median_graph_ms": 1.0, "median_pivots_ms": 2.0, "median_hypotheses_ms": 3.0,
         "median_cliques_ms": float("nan"), "median_pose_ms": 0.1}  # fmt: skip
    line = next(x for x in format_summary(s).splitlines() if x.startswith("median ms:"))
    assert "pivots 2.0" in line and "hypotheses 3.0" in line and "cliques" not in line
