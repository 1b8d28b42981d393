"""9. samples=auto (issue 41): does the keep sized from the scores register what MAC registers, and faster?

    python -m studies.keep_size [--seeds 5] [--per-family 8] [--core-inliers 200 ...] [--quick]
    python -m studies.keep_size --section        # rewrites section 9 of docs/results.md from the last run

For every real pair of ../shared/data (5,000 FPFH correspondences, as the other studies) and the synthetic
3DMatch-, 3DLoMatch- and KITTI-like pairs: MAC (every correspondence), FastMAC at ratio 0.2 and 0.05 and
FastMAC with samples=auto (one column per `core_inliers` and `scarce_ratio` asked; "auto": the
defaults), `seeds` seeds each, through the pipeline's
own run_pair (honest protocol, C++ backend): registrations, the keep's size and inlier ratio, the dense
core auto estimated, and the median time from the correspondences.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.machine import cpu_model  # noqa: E402
from fastmac_exp.samplers.keep_size import KeepParams  # noqa: E402
from studies.common import replace_section  # noqa: E402
from studies.estimated_scores import shared_inputs, synthetic_inputs  # noqa: E402

OUT = REPO / "outputs" / "studies" / "keep_size"
SECTION = "## 9. Keep size from the scores (samples=auto)"


def thinned_inputs(inputs, inliers: int = 45, n: int = 3431, seeds=(0, 1)):
    """The issue's 3DLoMatch-like case (45 inliers among 3,431, 1.3 %) built from the real indoor pairs:
    `inliers` of a pair's inliers and n - inliers of its outliers, drawn without replacement."""
    from fastmac_exp.types import Correspondences

    for group, name, pair, corr in inputs:
        lab = corr.labels.astype(bool)
        if group != "real_indoor" or lab.sum() < inliers or (~lab).sum() < n - inliers:
            continue
        for seed in seeds:
            rng = np.random.default_rng([seed, 45])
            idx = np.concatenate([rng.choice(np.flatnonzero(lab), inliers, replace=False),
                                  rng.choice(np.flatnonzero(~lab), n - inliers, replace=False)])  # fmt: skip
            idx = rng.permutation(idx)
            sub = Correspondences(corr.src[idx], corr.tgt[idx], labels=lab[idx])
            yield "thinned", f"{name}_thin{inliers}_{seed}", pair, sub


def methods(core_inliers: list[float], scarce_ratios: list[float]) -> list[tuple[str, object, object]]:
    """(label, ratio, samples) of each column: samples ("auto", KeepParams fields) for auto's."""
    out: list[tuple[str, object, object]] = [("MAC", 1.0, None), ("r0.2", 0.2, None), ("r0.05", 0.05, None)]
    for c in core_inliers:
        for r in scarce_ratios:
            d = KeepParams()
            label = "auto" if (c, r) == (d.core_inliers, d.scarce_ratio) else f"auto{int(c)}/{r:g}"
            out.append((label, 0.2, ("auto", {"core_inliers": c, "scarce_ratio": r})))
    return out


def run_input(group, name, pair, corr, seeds: int, cols) -> dict:
    from fastmac_exp.backends.cpp import CppBackend
    from fastmac_exp.descriptors.fpfh import FPFHDescriptor
    from fastmac_exp.pipeline import run_pair
    from fastmac_exp.samplers import GraphFilterSampler, NoSampler

    pair.correspondences = corr  # run_pair then skips the descriptor
    rec = {"group": group, "name": name, "family": pair.family, "n": len(corr),
           "inliers": int(corr.labels.sum()), "methods": {}}  # fmt: skip
    for label, ratio, samples in cols:
        ok, kept, kin, ms, core = [], [], [], [], []
        for seed in range(1 if label == "MAC" else seeds):
            if samples is None:
                sampler = NoSampler() if ratio == 1.0 else GraphFilterSampler()
                s_arg = None
            else:
                sampler = GraphFilterSampler(keep=samples[1])
                s_arg = "auto"
            t0 = time.perf_counter()
            try:
                out = run_pair(pair, FPFHDescriptor(), sampler, CppBackend(), ratio,
                               np.random.default_rng([seed, 41]), samples=s_arg)  # fmt: skip
                ms.append((time.perf_counter() - t0) * 1e3)
                ok.append(bool(out.row["success"]))
                kept.append(len(out.result.kept))
                kin.append(float(corr.labels[out.result.kept].sum()))
                core.append(out.sample.core)
            except Exception as exc:  # noqa: BLE001 - a failed registration is a failure, not a crash
                ok.append(False)
                print(f"    {name} {label} seed {seed}: {type(exc).__name__}: {exc}")
        if label == "MAC":
            ok, kept, kin, ms = ok * seeds, kept * seeds, kin * seeds, ms * seeds
        rec["methods"][label] = {
            "ok": int(sum(ok)), "seeds": seeds, "kept": float(np.mean(kept)) if kept else float("nan"),
            "kept_inliers": float(np.mean(kin)) if kin else float("nan"),
            "ms": statistics.median(ms) if ms else float("nan"), "core": int(np.median(core)) if core else 0,
        }  # fmt: skip
    return rec


def render(results: dict) -> list[str]:
    recs = results["inputs"]
    labels = list(recs[0]["methods"]) if recs else []
    lines = [SECTION, "",
             f"`python -m studies.keep_size` ({results['seeds']} seeds; {results['cpu']}; load average "
             "at the "
             f"start {results['load']}). Per input: registrations out of {results['seeds']} (MAC is "
             "deterministic: its one run counted for every seed), the keep's size and inliers (means), "
             "auto's estimated dense core, median ms from the correspondences (sampling + MAC).", "",
             "| input | N | inliers | "
             + " | ".join(f"{lb} ok / kept (inl) / ms" for lb in labels) + " | core |",
             "|---|---:|---:|" + "---:|" * len(labels) + "---:|"]  # fmt: skip
    for r in recs:
        cells = []
        for lb in labels:
            m = r["methods"][lb]
            cells.append(f"{m['ok']} / {m['kept']:.0f} ({m['kept_inliers']:.0f}) / {m['ms']:.0f}")
        core = max(m["core"] for m in r["methods"].values())
        lines.append(f"| {r['group']}: {r['name']} | {r['n']} | {r['inliers']} | " + " | ".join(cells)
                     + f" | {core} |")  # fmt: skip
    lines += ["", "Totals (pair-seeds registered; median of the inputs' median ms):", ""]
    for lb in labels:
        tot = sum(r["methods"][lb]["ok"] for r in recs)
        med = statistics.median(r["methods"][lb]["ms"] for r in recs) if recs else float("nan")
        lines.append(f"- {lb}: {tot} of {sum(r['methods'][lb]['seeds'] for r in recs)}, median {med:.0f} ms")
    lost = []
    for r in recs:
        mac_ok = r["methods"]["MAC"]["ok"] == r["methods"]["MAC"]["seeds"]
        for lb in labels:
            m = r["methods"][lb]
            if lb.startswith("auto") and mac_ok and m["ok"] < m["seeds"]:
                lost.append(f"{r['name']} {lb} {m['ok']}/{m['seeds']}")
    lines += [
        "",
        "Pairs MAC registers that auto loses on some seed: " + (", ".join(lost) or "none") + ".",
        "",
    ]
    return lines


def write_section(
    results: dict, page: Path = REPO / "docs" / "results.md", thinned: dict | None = None
) -> None:
    """Replace (or add before ## Notes) section 9 of docs/results.md (and the thinned inputs' table)."""
    lines = render(results)
    if thinned:
        lines += [
            "### The issue's 3DLoMatch-like case: real indoor pairs thinned to 45 inliers among 3,431",
            "",
        ]
        cmd = "`python -m studies.keep_size --thinned`"
        lines += [ln.replace("`python -m studies.keep_size`", cmd) for ln in render(thinned)[2:]]
    block = "\n".join(lines) + "\n"
    replace_section(page, SECTION, block)


def main(argv: list[str] | None = None) -> int:
    import os

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--per-family", type=int, default=8)
    ap.add_argument("--core-inliers", type=float, nargs="*", default=[200.0])
    ap.add_argument("--scarce-ratio", type=float, nargs="*", default=[KeepParams().scarce_ratio])
    ap.add_argument("--only", default=None, help="a substring of the inputs' names")
    ap.add_argument("--no-synthetic", action="store_true")
    ap.add_argument(
        "--thinned",
        action="store_true",
        help="only the real indoor pairs thinned to 45 inliers among 3,431 (the issue's 3DLoMatch-like case)",
    )
    ap.add_argument("--section", action="store_true", help="rewrite docs/results.md from the last run")
    args = ap.parse_args(argv)
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / ("thinned.json" if args.thinned else "results.json")
    if args.section:
        thin = OUT / "thinned.json"
        write_section(json.loads((OUT / "results.json").read_text()),
                      thinned=json.loads(thin.read_text()) if thin.exists() else None)  # fmt: skip
        return 0
    cols = methods(args.core_inliers, args.scarce_ratio)
    results = {"seeds": args.seeds, "cpu": cpu_model(), "load": " ".join(f"{x:.1f}" for x in os.getloadavg()),
               "inputs": []}  # fmt: skip
    sources = [shared_inputs()]
    if args.thinned:
        sources = [thinned_inputs(list(shared_inputs()))]
    if not args.no_synthetic and not args.thinned:
        sources.append(synthetic_inputs(args.per_family))
    for src in sources:
        for group, name, pair, corr in src:
            if args.only and args.only not in name:
                continue
            rec = run_input(group, name, pair, corr, args.seeds, cols)
            results["inputs"].append(rec)
            print(f"{group:12s} {name[:40]:40s} N {rec['n']:5d} inl {rec['inliers']:5d} " + "  ".join(
                f"{lb} {m['ok']}/{m['seeds']} k{m['kept']:.0f}({m['kept_inliers']:.0f}) "
                f"{m['ms']:.0f}ms c{m['core']}"
                for lb, m in rec["methods"].items()))  # fmt: skip
            sys.stdout.flush()
            path.write_text(json.dumps(results, indent=1))
    print("\n".join(render(results)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
