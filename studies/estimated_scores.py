"""8. Estimated vs exact sampler scores (issue 29): does FastMAC sample as well from the estimate?

    python -m studies.estimated_scores [--seeds 50] [--quick]   # runs it: outputs/studies/estimated_scores/
    python -m studies.estimated_scores --section                   # rewrites section 8 of docs/results.md

For every input where the exact scores run (the real outdoor, indoor and object pairs of ../shared/data at
5,000 FPFH correspondences; real 3DMatch 4->0 FPFH matches at voxel 0.015 m, nested subsets of 5,000,
10,000 and 20,000; the synthetic 3DMatch-, 3DLoMatch- and KITTI-like pairs) and for ratios 0.2, 0.05 and
0.01: the high-pass sampler's kept inlier ratio from the exact and from the estimated scores over `seeds`
seeds (the same draw stream for both), their difference with its standard error, registration recall over
the pair-seeds (MAC, C++ backend, on each kept set), the Spearman rank correlation of the two scores and
what `scores=auto` picks. Then the estimator's own error against N and against its anchor budget, on the
inliers and on the outliers separately (median relative error of the degree and of the high-pass response).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from fastmac_exp import core  # noqa: E402
from fastmac_exp.graph.estimate import EstimateParams, choose_scores, estimate_signals  # noqa: E402
from fastmac_exp.params import mac_params_for  # noqa: E402
from fastmac_exp.samplers.base import draw_proportional  # noqa: E402
from fastmac_exp.samplers.graph_filter import filter_scores  # noqa: E402
from fastmac_exp.types import Correspondences  # noqa: E402
from studies.common import replace_section  # noqa: E402

DATA = REPO.parent / "shared" / "data"
OUT = REPO / "outputs" / "studies" / "estimated_scores"
RATIOS = (0.2, 0.05, 0.01)
SECTION = "## 8. Estimated vs exact sampler scores"


# ---- inputs ------------------------------------------------------------------------------------------------
def shared_inputs(max_corr: int = 5000):
    """(group, name, family, correspondences with labels, GT, MAC params, sampler graph) of the real pairs."""
    from fastmac_exp.datasets.user_pairs import SharedRealPairs
    from fastmac_exp.descriptors.fpfh import FPFHDescriptor

    if not (DATA / "pairs.json").exists():
        print(f"[estimated_scores] no shared data at {DATA}: real pairs skipped")
        return
    describe = FPFHDescriptor(max_correspondences=max_corr)
    ds = SharedRealPairs(root=str(DATA))
    for i, name in enumerate(ds.names()):
        pair = ds.load(i)
        corr = pair.label(describe(pair, np.random.default_rng(0)))
        group = {"outdoor": "real_outdoor", "indoor": "real_indoor", "object": "real_object"}[pair.scene]
        yield group, name, pair, corr


def synthetic_inputs(per_family: int):
    from fastmac_exp.datasets.synthetic import SyntheticDataset
    from fastmac_exp.descriptors.fpfh import FPFHDescriptor

    describe = FPFHDescriptor(max_correspondences=5000)
    for fam in ("3dmatch", "3dlomatch", "kitti"):
        ds = SyntheticDataset(family=fam, num_pairs=per_family)
        for i, name in enumerate(ds.names()):
            pair = ds.load(i)
            yield fam, name, pair, pair.label(describe(pair, np.random.default_rng(0)))


def fullres_inputs(sizes=(5000, 10_000, 20_000), voxel: float = 0.015):
    """Real 3DMatch redkitchen 4->0 FPFH matches at voxel 0.015 m (one-way nearest feature), nested "
    "subsets."""
    from scipy.spatial import cKDTree

    from fastmac_exp._open3d import o3d
    from fastmac_exp.datasets.user_pairs import SharedRealPairs

    if not (DATA / "pairs.json").exists():
        return
    ds = SharedRealPairs(root=str(DATA))
    names = ds.names()
    if "3dm_redkitchen_4_to_0_teaser_fullres" not in names:
        return
    pair = ds.load(names.index("3dm_redkitchen_4_to_0_teaser_fullres"))

    def features(points: np.ndarray):
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
        f = o3d.pipelines.registration.compute_fpfh_feature(
            pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100)
        )
        return np.asarray(pcd.points), np.asarray(f.data).T

    ps, fs = features(pair.src_cloud)
    pt, ft = features(pair.tgt_cloud)
    _, nn = cKDTree(ft).query(fs)
    order = np.random.default_rng(0).permutation(len(ps))
    for n in sizes:
        if n > len(ps):
            print(f"[estimated_scores] full-resolution 4->0 has {len(ps)} matches, fewer than {n}: skipped")
            continue
        idx = order[:n]
        corr = pair.label(Correspondences(ps[idx], pt[nn[idx]]))
        yield "real_fullres", f"3dm_4_to_0_fullres_{n}", pair, corr


# ---- one input ---------------------------------------------------------------------------------------------
def study_input(group, name, pair, corr, seeds: int, ep: EstimateParams) -> dict:
    from scipy.stats import spearmanr

    from fastmac_exp.backends.cpp import CppBackend
    from fastmac_exp.pipeline import evaluate

    params = mac_params_for(pair.family, "fpfh", pair.resolution)
    gp = mac_params_for(pair.family, "fpfh", pair.sampler_resolution).graph
    n = len(corr)
    t0 = time.perf_counter()
    exact = core.graph_signals(corr.src, corr.tgt, gp)
    t_exact = (time.perf_counter() - t0) * 1e3
    p_exact = filter_scores(exact, "highpass", pair.family)
    auto, _ = choose_scores(corr.src, corr.tgt, gp, ep, np.random.default_rng(0))
    backend = CppBackend()
    rec = {"group": group, "name": name, "family": pair.family, "n": n,
           "inlier_ratio": float(corr.labels.mean()),
           "auto": auto, "t_exact_ms": t_exact, "t_estimate_ms": [], "spearman": [], "anchors": [],
           "ratios": {}}  # fmt: skip
    kept = {(r, m): [] for r in RATIOS for m in ("exact", "estimate")}
    ok = {(r, m): [] for r in RATIOS for m in ("exact", "estimate")}
    for seed in range(seeds):
        t0 = time.perf_counter()
        est = estimate_signals(corr.src, corr.tgt, gp, np.random.default_rng([seed, 1]), ep)
        rec["t_estimate_ms"].append((time.perf_counter() - t0) * 1e3)
        rec["anchors"].append(est.anchors)
        p_est = filter_scores(est, "highpass", pair.family)
        rec["spearman"].append(float(spearmanr(p_est, p_exact)[0]))
        for r in RATIOS:
            k = max(3, int(np.floor(n * r + 1e-9)))
            for mode, p in (("exact", p_exact), ("estimate", p_est)):
                idx, _ = draw_proportional(p, k, np.random.default_rng([seed, 2]))
                kept[(r, mode)].append(float(corr.labels[idx].mean()))
                try:
                    res = backend.register(corr.subset(idx), params)
                    res.kept, res.clique = idx, idx[res.clique]
                    ok[(r, mode)].append(bool(evaluate(pair, res, "honest").success))
                except Exception:  # noqa: BLE001 - a failed registration is a failure, not a crash
                    ok[(r, mode)].append(False)
    for r in RATIOS:
        x, e = np.array(kept[(r, "exact")]), np.array(kept[(r, "estimate")])
        d = e - x
        rec["ratios"][str(r)] = {
            "kept_exact": float(x.mean()), "kept_estimate": float(e.mean()), "diff": float(d.mean()),
            "se": float(np.sqrt(x.var(ddof=1) / len(x) + e.var(ddof=1) / len(e)))
            if len(x) > 1 else float("nan"),
            "rr_exact": int(np.sum(ok[(r, "exact")])), "rr_estimate": int(np.sum(ok[(r, "estimate")])),
            "seeds": len(x),
        }  # fmt: skip
    return rec


# ---- the estimator's error ---------------------------------------------------------------------------------
def error_study(sizes=(5000, 10_000, 20_000, 50_000), budgets=(32, 64, 128, 256, 512), inliers: float = 0.05):
    """Median relative error of the degree and of |high-pass| on inliers and outliers, against N (default
    budget) and against a fixed anchor count (N = 10,000), on bench_core's outdoor-like scene."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    from bench_core import synthetic

    gp = mac_params_for("kitti", "fpfh").graph
    rows = []

    def errors(corr, exact, ep, seeds=5):
        out = {k: [] for k in ("deg_in", "deg_out", "hp_in", "hp_out", "anchors")}
        lab = corr.labels
        for s in range(seeds):
            e = estimate_signals(corr.src, corr.tgt, gp, np.random.default_rng(s), ep)
            for key, a, b in (
                ("deg", e.degree, exact.degree),
                ("hp", np.abs(e.highpass), np.abs(exact.highpass)),
            ):
                rel = np.abs(a - b) / np.maximum(np.abs(b), 1e-12)
                out[f"{key}_in"].append(float(np.median(rel[lab])))
                out[f"{key}_out"].append(float(np.median(rel[~lab])))
            out["anchors"].append(e.anchors)
        return {k: float(np.mean(v)) for k, v in out.items()}

    for n in sizes:
        corr, _ = synthetic(n, inlier_ratio=inliers, noise=0.1, seed=1, room=(60.0, 60.0, 4.0))
        exact = core.graph_signals(corr.src, corr.tgt, gp)
        rows.append({"vary": "N", "n": n, **errors(corr, exact, EstimateParams())})
        print(f"[error] N={n}: {rows[-1]}", flush=True)
    corr, _ = synthetic(10_000, inlier_ratio=inliers, noise=0.1, seed=1, room=(60.0, 60.0, 4.0))
    exact = core.graph_signals(corr.src, corr.tgt, gp)
    for m in budgets:
        ep = EstimateParams(anchors=m, min_anchors=m)
        rows.append({"vary": "anchors", "n": 10_000, **errors(corr, exact, ep)})
        print(f"[error] anchors={m}: {rows[-1]}", flush=True)
    return rows


# ---- the section -------------------------------------------------------------------------------------------
def render(results: dict) -> list[str]:
    inputs, errs = results["inputs"], results["errors"]
    seeds = max((r["ratios"]["0.2"]["seeds"] for r in inputs), default=0)
    md = [SECTION, ""]
    md.append(
        f"`python -m studies.estimated_scores` (`{results['command']}`, core {results['core']}, "
        f"{results['date']}): the high-pass sampler's kept inlier ratio from the exact and from the "
        f"estimated "
        f"scores (`sampler.scores=exact|estimate`, docs/estimated_scores.md), over {seeds} seeds per input "
        "(the draw from both scores uses the same stream), the difference estimate - exact with its standard "
        "error, registration recall over the pair-seeds (MAC on each kept set), the Spearman correlation of "
        "the two scores, and what `scores=auto` picks. Contract: kept inlier ratio within two standard "
        "errors of the exact one or higher, RR within one pair-seed."
    )
    md.append("")
    md.append("| input | N | inliers | auto | ρ | ratio | kept exact | kept estimate | diff ± SE | "
        "RR exact | "
              "RR estimate | holds |")  # fmt: skip
    md.append("|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---|")
    fails = []
    for r in inputs:
        for ratio, v in r["ratios"].items():
            kept_ok = v["diff"] >= -2 * v["se"] if np.isfinite(v["se"]) else v["diff"] >= 0
            rr_ok = v["rr_estimate"] >= v["rr_exact"] - 1
            holds = (
                "yes" if kept_ok and rr_ok else ("kept" if not kept_ok else "") + (" RR" if not rr_ok else "")
            )
            if holds != "yes":
                fails.append(f"{r['name']} @{ratio}")
            md.append(
                f"| {r['group']}: {r['name']} | {r['n']} | {r['inlier_ratio']:.3f} | {r['auto']} | "
                f"{np.mean(r['spearman']):.2f} | {ratio} | {v['kept_exact']:.3f} | "
                f"{v['kept_estimate']:.3f} | "
                f"{v['diff']:+.3f} ± {v['se']:.3f} | {v['rr_exact']}/{v['seeds']} | "
                f"{v['rr_estimate']}/{v['seeds']} "
                f"| {holds.strip()} |"
            )
    md.append("")
    n_rows = sum(len(r["ratios"]) for r in inputs)
    md.append(
        f"The contract holds on {n_rows - len(fails)} of {n_rows} input-ratio rows"
        + (f"; it fails on: {', '.join(fails)}." if fails else ".")
    )
    auto_est = [r for r in inputs if r["auto"] == "estimate"]
    auto_fails = [f for f in fails if any(f.startswith(r["name"] + " ") for r in auto_est)]
    n_auto = sum(len(r["ratios"]) for r in auto_est)
    md.append(
        f"Under `scores=auto` (the default), which uses the estimate only where it predicts it cheaper, the "
        f"estimated rows hold on {n_auto - len(auto_fails)} of {n_auto}"
        + (f" (fails: {', '.join(auto_fails)})" if auto_fails else "")
        + "; every other row is the exact sample itself."
    )
    md.append(
        f"`scores=auto` estimates on {len(auto_est)} of {len(inputs)} inputs "
        f"({', '.join(r['name'] for r in auto_est) or 'none'}); on the others it keeps the exact scores and "
        "draws the exact sample."
    )
    t_e = {r["name"]: np.median(r["t_estimate_ms"]) for r in inputs}
    md.append("")
    md.append("Score time per input (one process, the study's own runs; benchmarks/bench_core.py times them "
              "side by side): " + "; ".join(f"{r['name']} exact {r['t_exact_ms']:.0f} ms, estimate "
                                          f"{t_e[r['name']]:.0f} ms" for r in inputs) + ".")  # fmt: skip
    md.append("")
    md.append("The estimator's error (median relative error over nodes, mean of 5 seeds; "
        "bench_core's outdoor-like "
              "scene, 5 % inliers): against N at the default budget, and against a fixed anchor count at N = "
              "10,000.")  # fmt: skip
    md.append("")
    md.append("| varied | N | anchors | degree, inliers | degree, outliers | \\|high-pass\\|, inliers | "
              "\\|high-pass\\|, outliers |")  # fmt: skip
    md.append("|---|---:|---:|---:|---:|---:|---:|")
    for e in errs:
        md.append(f"| {e['vary']} | {e['n']} | {e['anchors']:.0f} | {e['deg_in']:.3f} | {e['deg_out']:.3f} | "
                  f"{e['hp_in']:.3f} | {e['hp_out']:.3f} |")  # fmt: skip
    md.append("")
    return md


def write_section(results: dict, page: Path = REPO / "docs" / "results.md") -> None:
    """Replace (or add before ## Notes) section 8 of docs/results.md."""
    block = "\n".join(render(results)) + "\n"
    replace_section(page, SECTION, block)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m studies.estimated_scores", description=__doc__.split("\n")[0]
    )
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--synthetic", type=int, default=4, help="synthetic pairs per family")
    ap.add_argument("--quick", action="store_true", help="5 seeds, 1 synthetic pair a family, no full-res")
    ap.add_argument("--section", action="store_true", help="only rewrite section 8 from the saved results")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    path = args.out / "results.json"
    if args.section:
        write_section(json.loads(path.read_text()))
        print(f"rewrote section 8 of docs/results.md from {path}")
        return 0
    seeds, per = (5, 1) if args.quick else (args.seeds, args.synthetic)
    args.out.mkdir(parents=True, exist_ok=True)
    import subprocess

    commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()  # fmt: skip
    results = {"command": " ".join(["python -m studies.estimated_scores", *(argv or sys.argv[1:])]),
               "core": commit, "date": time.strftime("%Y-%m-%d"), "inputs": [], "errors": []}  # fmt: skip
    sources = [shared_inputs(), synthetic_inputs(per)] + ([] if args.quick else [fullres_inputs()])
    ep = EstimateParams()
    for src in sources:
        for group, name, pair, corr in src:
            if corr.labels is None or corr.labels.sum() < 3:
                print(f"[estimated_scores] {name}: fewer than 3 inliers, skipped", flush=True)
                continue
            t0 = time.perf_counter()
            rec = study_input(group, name, pair, corr, seeds, ep)
            results["inputs"].append(rec)
            path.write_text(json.dumps(results, indent=1))
            r5 = rec["ratios"]["0.05"]
            print(f"[estimated_scores] {group}:{name} N={rec['n']} auto={rec['auto']} @0.05 kept "
                  f"{r5['kept_exact']:.3f} -> {r5['kept_estimate']:.3f} RR {r5['rr_exact']} -> "
                  f"{r5['rr_estimate']} "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)  # fmt: skip
    results["errors"] = error_study(sizes=(5000, 10_000) if args.quick else (5000, 10_000, 20_000, 50_000))
    path.write_text(json.dumps(results, indent=1))
    write_section(results)
    print(f"wrote {path} and section 8 of docs/results.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
