"""Calibrate `result.trusted` (geometry/trust.py) out of sample: choose on one half of the pairs, report on
the other.

The pairs are every real pair ../shared/data can make (benchmarks/trust_pairs.py: the given 13, their
reversals, every other pair of one scene's scans with GT, unrelated pairs of other places) and the synthetic
families' pairs, split in two halves by a fixed hash of the scans they are made of. Each pair runs FPFH
(and FPFH with mutual matching) under FastMAC@20, samples=auto and MAC on every correspondence (C++),
seeds 0..S-1, with the decoy on, so every row holds all the evidence (count k, clique, chance lambda, the
best distinct rival's count and chance, the decoy's excess). The test is then replayed offline from
that evidence: the rival margin is chosen on the calibration half (no false accept there, then the fewest
false rejects) and false accepts / rejects are reported per inlier-ratio band on the held-out half, for
the previous test (the 1 % structure allowance), the rival alone, the decoy alone and both.

    PYTHONPATH=. python benchmarks/calibrate_trust.py [--data ../shared/data] [--seeds 2] [--synthetic 8]
        [--descriptors fpfh fpfh_mutual buffer] [--json evidence.json] [--replay evidence.json]

`--descriptors buffer` runs BUFFER as run.py and register() build it (conf/descriptor/buffer.yaml: INT8,
mutual matches of capped keypoint sets); the tables are printed per descriptor.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.trust_pairs import all_cases  # noqa: E402
from fastmac_exp.backends.cpp import CppBackend  # noqa: E402
from fastmac_exp.descriptors.fpfh import FPFHDescriptor  # noqa: E402
from fastmac_exp.geometry.trust import RIVAL_MARGIN, STRUCTURE_RATE, TRUST_LEVEL, decide  # noqa: E402
from fastmac_exp.pipeline import run_pair  # noqa: E402
from fastmac_exp.samplers import GraphFilterSampler, NoSampler  # noqa: E402

CONFIGS = {  # name: (sampler, ratio, samples)
    "fastmac20": (GraphFilterSampler, 0.2, None),
    "auto": (GraphFilterSampler, 0.2, "auto"),
    "mac": (NoSampler, 1.0, None),
}
BANDS = ("< 1 %", "1-3 %", "> 3 %")
MARGINS = (0.5, 1.0, 1.5, 2.0, 3.0)
TESTS = ("previous", "no_rival", "final")
RATES = (0.005, 0.0075, 0.01, 0.0125, 0.015, 0.02)


def band(ratio) -> str:
    r = 0.0 if ratio is None or not np.isfinite(ratio) else float(ratio)
    return BANDS[0] if r < 0.01 else BANDS[1] if r <= 0.03 else BANDS[2]


def configured(name: str):
    """A descriptor as run.py and register() build it: conf/descriptor/<name>.yaml, no progress bar."""
    from fastmac_exp.options import compose_run, instantiate_part

    node = compose_run({"descriptor": name}).descriptor
    node.progress = False
    return instantiate_part(node)


DESCRIPTORS = {  # name: factory (each built once a run)
    "fpfh": FPFHDescriptor,
    "fpfh_mutual": lambda: FPFHDescriptor(mutual=True),
    "buffer": lambda: configured("buffer"),
}


def gather(data: str, seeds: int, synthetic: int, descriptors=("fpfh", "fpfh_mutual")) -> list[dict]:
    rows = []
    cases = all_cases(data, synthetic)
    kinds = ("given", "same_scene", "unrelated", "synthetic")
    print(f"{len(cases)} pairs: " + ", ".join(f"{k} {sum(c.kind == k for c in cases)}" for k in kinds))
    built = {name: DESCRIPTORS[name]() for name in descriptors}
    for ci, case in enumerate(cases):
        for desc_name, desc in built.items():
            pair = case.pair
            corr = desc(pair, np.random.default_rng(0))
            if pair.gt is not None:
                pair.label(corr)
            fixed = type(pair)(**{**pair.__dict__, "correspondences": corr})
            for cfg, (smp, ratio, samples) in CONFIGS.items():
                for seed in range(seeds):
                    t0 = time.perf_counter()
                    try:
                        out = run_pair(fixed, desc, smp(), CppBackend(), ratio, np.random.default_rng(seed),
                                       samples=samples, decoy="on")  # fmt: skip
                    except Exception as exc:  # a pair the search fails outright: no pose to trust
                        rows.append({"pair": case.name, "kind": case.kind, "half": case.half,
                                     "descriptor": desc_name, "config": cfg, "seed": seed,
                                     "error": str(exc)})  # fmt: skip
                        continue
                    r, res = out.row, out.result
                    rows.append({
                        "pair": case.name, "kind": case.kind, "group": case.group, "half": case.half,
                        "descriptor": desc_name, "config": cfg, "seed": seed, "n": r["n_in"],
                        "inlier_ratio": r.get("inlier_ratio_in"), "k": r["pose_inliers"],
                        "clique": r["clique_size"], "lam": res.chance_inliers, "rival_k": res.rival_inliers,
                        "rival_lam": res.rival_chance, "decoy": res.decoy_count,
                        "success": r.get("success"), "re_deg": r.get("re_deg"), "te_cm": r.get("te_cm"),
                        "ms": (time.perf_counter() - t0) * 1e3, "t_decoy_ms": res.timings.get("decoy"),
                        "t_total_ms": res.timings.get("total"), "t_check_ms": res.timings.get("check"),
                    })  # fmt: skip
        last = rows[-1]
        print(f"[{ci + 1}/{len(cases)}] {case.kind:10s} {case.name[:60]:60s} {last.get('half', '')[:5]} "
              f"ratio {last.get('inlier_ratio') or 0:.3f} ok {last.get('success')}", flush=True)  # fmt: skip
    return rows


def verdict(row: dict, test: str, rate: float, margin: float) -> bool:
    """The test replayed from a row's evidence. previous: the test before issue 48 (Poisson(max(c, 3) +
    lambda + 1 % of N)); no_rival: today's test without the rival; final: as register() runs it
    (decoy=auto: the pose's own clique first, the decoy's count where that leaves it untrusted)."""
    n, k, c, lam = row["n"], row["k"], row["clique"], row["lam"]
    if test == "previous":
        from scipy.special import gammainc

        return 1.0 - float(gammainc(max(int(k), 1), max(c, 3) + lam + 0.01 * n)) >= TRUST_LEVEL
    rival = row["rival_k"] - row["rival_lam"] if test == "final" else None
    if decide(k, c, lam, n, rival, None, margin, rate)[0] >= TRUST_LEVEL:
        return True
    return decide(k, c, lam, n, rival, row["decoy"], margin, rate)[0] >= TRUST_LEVEL


def counts(rows: list[dict], test: str, rate: float, margin: float) -> dict:
    out = {b: {"pairs": 0, "right": 0, "fa": 0, "fr": 0} for b in BANDS}
    for r in rows:
        if "error" in r:
            continue
        b = out[band(r["inlier_ratio"])]
        b["pairs"] += 1
        ok = bool(r["success"])
        b["right"] += ok
        t = verdict(r, test, rate, margin)
        b["fa"] += t and not ok
        b["fr"] += ok and not t
    return out


def table(rows: list[dict], title: str, rate: float, margin: float) -> None:
    print(f"\n{title} ({len(rows)} runs; false accepts / false rejects of the right poses, per band)")
    print(f"| test | {' | '.join(f'{b}: runs, right, FA, FR' for b in BANDS)} |")
    print("|---|" + "---|" * len(BANDS))
    for test in TESTS:
        c = counts(rows, test, rate, margin)
        cells = " | ".join(f"{c[b]['pairs']}, {c[b]['right']}, **{c[b]['fa']}**, {c[b]['fr']}" for b in BANDS)
        print(f"| {test} | {cells} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--synthetic", type=int, default=8)
    ap.add_argument("--descriptors", nargs="+", choices=list(DESCRIPTORS), default=["fpfh", "fpfh_mutual"])
    ap.add_argument("--json", default=None, help="write the evidence rows here")
    ap.add_argument("--replay", default=None, help="read evidence rows instead of running the pairs")
    args = ap.parse_args()
    if args.replay:
        rows = json.loads(Path(args.replay).read_text())
    else:
        if not (Path(args.data) / "pairs.json").is_file():
            sys.exit(f"calibrate_trust: {args.data}/pairs.json not found (pass --data)")
        rows = gather(args.data, args.seeds, args.synthetic, args.descriptors)
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1, default=float))
    cal = [r for r in rows if r["half"] == "calibration"]
    held = [r for r in rows if r["half"] == "held_out"]
    print(f"\ncalibration half: {len({r['pair'] for r in cal})} pairs, held-out half: "
          f"{len({r['pair'] for r in held})} pairs")  # fmt: skip
    print("\nthe constants on the calibration half (final test): rate, margin, false accepts, false rejects")
    grid = []
    for rate in RATES:
        for m in MARGINS:
            c = counts(cal, "final", rate, m)
            fa, fr = sum(v["fa"] for v in c.values()), sum(v["fr"] for v in c.values())
            h = counts(held, "final", rate, m)
            h_fa, h_fr = sum(v["fa"] for v in h.values()), sum(v["fr"] for v in h.values())
            print(f"  {rate:6.4f} {m:4.1f}  FA {fa:3d}  FR {fr:3d}   (held out: FA {h_fa:3d}  FR {h_fr:3d})")
            grid.append((fa, fr, -rate, -m))
    fa, fr, rate, m = min(grid)
    print(f"chosen on the calibration half (no false accept, then the fewest false rejects, then the larger "
          f"constants): STRUCTURE_RATE {-rate}, RIVAL_MARGIN {-m} (geometry/trust.py: {STRUCTURE_RATE}, "
          f"{RIVAL_MARGIN})")  # fmt: skip
    for name in sorted({r["descriptor"] for r in rows}):
        for part, title in ((cal, "calibration half (in sample)"), (held, "held-out half (out of sample)")):
            mine = [r for r in part if r["descriptor"] == name]
            table(mine, f"{name}: {title}", STRUCTURE_RATE, RIVAL_MARGIN)
    for half_rows, label in ((cal, "calibration"), (held, "held-out")):
        for r in half_rows:
            if "error" in r:
                continue
            t = verdict(r, "final", STRUCTURE_RATE, RIVAL_MARGIN)
            if t != bool(r["success"]) and (t or band(r["inlier_ratio"]) != BANDS[0]):
                print(f"  {label} {'false accept' if t else 'false reject'}: {r['pair']} {r['descriptor']} "
                      f"{r['config']} seed {r['seed']}: k {r['k']} of {r['n']}, clique {r['clique']}, lambda "
                      f"{r['lam']:.1f}, rival {r['rival_k']}, decoy {r['decoy']:.1f}")  # fmt: skip
    cost = [r["t_decoy_ms"] / max(r["t_total_ms"], 1e-9) for r in rows if r.get("t_decoy_ms")]
    if cost:
        print(f"\ndecoy cost / sampling+MAC: median {np.median(cost):.2f}, max {np.max(cost):.2f}")


if __name__ == "__main__":
    main()
