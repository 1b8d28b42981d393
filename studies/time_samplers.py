"""Sampling time against the sample count: stochastic high-pass (FastMAC) vs greedy deterministic
(E-optimal) sampling, the left panel of the paper's Fig. stochastic, plus its right panel's split into
preparation (graph, signal / eigendecomposition) and the selection itself.

    python -m studies.time_samplers [--out outputs/studies/sampler_timing] [--budget-s 240]

Correspondences: FPFH on synthetic KITTI-like pair 0 (seed 0), subsets of N rows. The deterministic
sampler's cost grows as O(N^3 + N k^3 K); counts whose predicted time would exceed the budget left are
skipped and recorded as such. Writes timing.csv (one row per sampler x N x k, median of `repeats`).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from fastmac_exp.datasets.synthetic import SyntheticDataset  # noqa: E402
from fastmac_exp.descriptors.fpfh import FPFHDescriptor  # noqa: E402
from fastmac_exp.graph import first_order  # noqa: E402
from fastmac_exp.params import mac_params_for  # noqa: E402
from fastmac_exp.samplers import (  # noqa: E402
    GraphFilterSampler,
    draw_proportional,
)
from fastmac_exp.samplers.deterministic import graph_shift_eigenvectors, greedy_e_optimal  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DET = "deterministic (greedy E-optimal)"


def _ms(fn, repeats: int = 1):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times)), out


def sample_stats(corr, idx: np.ndarray, gp) -> dict:
    """GT inlier ratio of the sample and the number of first-order graph edges among it (what MAC gets)."""
    sub = corr.subset(np.asarray(idx))
    return dict(
        kept_inlier_ratio=float(sub.labels.mean()), kept_edges=int(first_order(sub.src, sub.tgt, gp).nnz // 2)
    )


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=str(REPO / "outputs/studies/sampler_timing"))
    ap.add_argument("--budget-s", type=float, default=240.0, help="time budget for the deterministic runs")
    ap.add_argument("--repeats", type=int, default=3, help="repeats of the stochastic timings (median)")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    pair = SyntheticDataset("kitti", num_pairs=1, seed=0, cache_dir=str(REPO / ".cache/synthetic")).load(0)
    corr = FPFHDescriptor(max_correspondences=5000)(pair, np.random.default_rng(0))
    if corr.labels is None:
        pair.label(corr)
    gp = mac_params_for(pair.family, "fpfh", pair.resolution).graph
    rows = []
    rng = np.random.default_rng(0)

    # stochastic: preparation = graph + SOG + high-pass signal; sampling = the proportional draw
    hp = GraphFilterSampler("highpass")
    for n in (1000, len(corr)):
        sub = corr.subset(np.sort(rng.choice(len(corr), n, replace=False))) if n < len(corr) else corr
        prep_ms, scores = _ms(lambda s=sub: hp.scores(s, gp, pair.family, rng), args.repeats)
        for k in (10, 20, 50, 100, 250, 500, 1000, 2500):
            if k > n // 2:
                continue
            draw_ms, (idx, _) = _ms(lambda s=scores, k=k: draw_proportional(s, k, rng), args.repeats)
            rows.append(dict(sampler="stochastic (high-pass)", n=n, k=k, prep_ms=prep_ms, select_ms=draw_ms,
                             **sample_stats(sub, idx, gp)))  # fmt: skip
            print(rows[-1], flush=True)

    # deterministic: preparation = dense SOG + eigendecomposition; sampling = the greedy loop
    t_start = time.perf_counter()
    for n in (500, 1000, 2000):
        sub = corr.subset(np.sort(rng.choice(len(corr), n, replace=False)))

        def prep(s=sub, n=n):
            w = first_order(s.src, s.tgt, gp).toarray() + np.eye(n)
            return graph_shift_eigenvectors(w * (w @ w))

        prep_ms, vecs = _ms(prep)
        last = None  # (k, select_ms) of the previous count, to predict the next (~ k^4)
        for k in (10, 20, 50, 100, 250):
            left = args.budget_s - (time.perf_counter() - t_start)
            predicted = (last[1] / 1e3) * (k / last[0]) ** 4 if last else 0.0
            if predicted > left:
                skip = f"predicted {predicted:.0f} s > budget left"
                rows.append(dict(sampler=DET, n=n, k=k, prep_ms=prep_ms, select_ms=np.nan, skipped=skip))
                print(rows[-1], flush=True)
                continue
            sel_ms, idx = _ms(lambda v=vecs, k=k: greedy_e_optimal(v[:, :k], k))
            last = (k, sel_ms)
            rows.append(
                dict(sampler=DET, n=n, k=k, prep_ms=prep_ms, select_ms=sel_ms, **sample_stats(sub, idx, gp))
            )
            print(rows[-1], flush=True)

    table = pd.DataFrame(rows)
    table["total_ms"] = table["prep_ms"] + table["select_ms"]
    table.to_csv(out / "timing.csv", index=False)
    meta = dict(pair=pair.name, family=pair.family, n_total=len(corr), inlier_ratio=float(corr.inlier_ratio),
                machine=f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores (shared)",
                blas_threads=os.environ.get("OPENBLAS_NUM_THREADS"))  # fmt: skip
    (out / "meta.json").write_text(json.dumps(meta, indent=2))
    print(table.to_string(index=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
