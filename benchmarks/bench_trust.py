"""Escalation against its parts and a peer, on every real pair ../shared/data can make (issue 48 item 3).

For each pair (benchmarks/trust_pairs.py) and seed, side by side in one run: `fastmac_exp.register()` as a
user calls it (escalate=auto, the default) and each configuration alone (escalate=off): FastMAC@20 (the
first step), samples=auto, MAC on every correspondence, mutual matching with MAC; and KISS-Matcher's whole
pipeline. Prints, per pair: which registered (GT) and whether the escalated pose is trusted; then the
target's check (every pair-seed that any configuration or KISS-Matcher registers is registered and trusted
by the escalation), the pairs registered per step that gave the pose, the time per step, the median time
of the pair-seeds whose first try was trusted (against the first try alone, i.e. today's register(), in
the same run) and the time of those that escalated, with the worst case.

    PYTHONPATH=. python benchmarks/bench_trust.py [--seeds 3] [--kinds given same_scene synthetic]
        [--synthetic 8] [--budget 30] [--no-kiss] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import cpu_model, load  # noqa: E402
from benchmarks.trust_pairs import all_cases  # noqa: E402
from fastmac_exp import register  # noqa: E402
from fastmac_exp.geometry.metrics import pose_errors  # noqa: E402

ALONE = {  # configuration: register() keywords (escalate="off")
    "fastmac20": {},
    "samples_auto": {"samples": "auto"},
    "mac_all": {"sampler": "none"},
    "mutual_mac": {"sampler": "none", "mutual": True},
}


def rules(pair) -> dict:
    """register()'s keywords for a pair's rules (object scans: their voxel and inlier threshold)."""
    kw = {"family": pair.family, "voxel_size": pair.voxel_size}
    if pair.scene == "object":
        kw["inlier_threshold"] = pair.inlier_threshold
    return kw


def kiss(pair) -> tuple[np.ndarray, float]:
    import kiss_matcher

    from fastmac_exp.backends.peers import kiss_matcher_pose

    src, tgt = (np.ascontiguousarray(c, dtype=np.float64) for c in (pair.src_cloud, pair.tgt_cloud))
    t0 = time.perf_counter()
    try:
        sol = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(pair.voxel_size)).estimate(src, tgt)
    except RuntimeError as exc:  # e.g. "Too small voxel size" on the object scans: no pose
        print(f"  KISS-Matcher on {pair.name}: {exc}")
        return np.full((4, 4), np.nan), (time.perf_counter() - t0) * 1e3
    ms = (time.perf_counter() - t0) * 1e3
    pose = kiss_matcher_pose(sol)
    return (np.full((4, 4), np.nan) if pose is None else pose), ms


def ok(pose, pair) -> bool:
    return bool(
        np.isfinite(pose).all() and pose_errors(pose, pair.gt, pair.re_thresh_deg, pair.te_thresh_m).success
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--kinds", nargs="+", default=["given", "same_scene", "synthetic"])
    ap.add_argument("--synthetic", type=int, default=8)
    ap.add_argument("--budget", type=float, default=30.0)
    ap.add_argument("--no-kiss", action="store_true")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    use_kiss = not args.no_kiss
    if use_kiss:
        try:
            import kiss_matcher  # noqa: F401
        except ImportError:
            print("kiss-matcher is not installed: its column is skipped")
            use_kiss = False
    print(f"CPU: {cpu_model()}; load at start: {load()}")
    cases = [
        c for c in all_cases(args.data, args.synthetic) if c.kind in args.kinds and c.pair.gt is not None
    ]
    # a warm-up call: the first call of a process pays imports (scipy.special, Hydra's config composition)
    p0 = cases[0].pair
    register(p0.src_cloud, p0.tgt_cloud, **rules(p0), escalate="off")
    rows = []
    alone = ", ".join(ALONE) + (", kiss" if use_kiss else "")
    print(f"{len(cases)} pairs x {args.seeds} seeds; columns: registered by GT (1/0) for "
          f"{alone}; then escalation: step, registered, trusted, ms")  # fmt: skip
    for case in cases:
        pair = case.pair
        for seed in range(args.seeds):
            row = {"pair": case.name, "kind": case.kind, "seed": seed}
            for name, kw in ALONE.items():
                t0 = time.perf_counter()
                res = register(pair.src_cloud, pair.tgt_cloud, **rules(pair), seed=seed, escalate="off", **kw)
                row[name] = ok(res.pose, pair)
                row[f"{name}_trusted"] = bool(res.trusted)
                row[f"{name}_ms"] = (time.perf_counter() - t0) * 1e3
            if use_kiss:
                pose, ms = kiss(pair)
                row["kiss"], row["kiss_ms"] = ok(pose, pair), ms
            t0 = time.perf_counter()
            res = register(pair.src_cloud, pair.tgt_cloud, **rules(pair), seed=seed, budget_s=args.budget)
            row["escalated_ms"] = (time.perf_counter() - t0) * 1e3
            row["escalated"], row["trusted"], row["step"] = ok(res.pose, pair), bool(res.trusted), res.step
            row["steps"] = res.escalation
            rows.append(row)
            cols = " ".join(str(int(row[n])) for n in ALONE) + (f" {int(row['kiss'])}" if use_kiss else "")
            print(f"{case.name[:48]:48s} s{seed}  {cols}   {row['step']:20s} {int(row['escalated'])} "
                  f"{int(row['trusted'])} {row['escalated_ms']:8.0f} ms", flush=True)  # fmt: skip
    report(rows, use_kiss)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1, default=str))


def report(rows: list[dict], use_kiss: bool) -> None:
    others = list(ALONE) + (["kiss"] if use_kiss else [])
    wanted = [r for r in rows if any(r[o] for o in others)]
    got = [r for r in wanted if r["escalated"] and r["trusted"]]
    print(f"\npair-seeds any configuration or peer registers: {len(wanted)}; escalation registers and trusts "
          f"{len(got)}")  # fmt: skip
    for r in wanted:
        if not (r["escalated"] and r["trusted"]):
            by = ", ".join(o for o in others if r[o])
            print(f"  missed: {r['pair']} seed {r['seed']} (registered by {by}; escalation: {r['step']}, "
                  f"registered {r['escalated']}, trusted {r['trusted']})")  # fmt: skip
    wrong_trusted = [r for r in rows if r["trusted"] and not r["escalated"]]
    print(f"escalated poses trusted and wrong: {len(wrong_trusted)}"
          + "".join(f"\n  {r['pair']} seed {r['seed']} ({r['step']})" for r in wrong_trusted))  # fmt: skip
    print("\n| | " + " | ".join(others + ["escalation"]) + " |")
    print("|---|" + "---|" * (len(others) + 1))
    n_esc = sum(r["escalated"] for r in rows)
    n_esc_trusted = sum(r["escalated"] and r["trusted"] for r in rows)
    print("| pair-seeds registered | " + " | ".join(str(sum(bool(r[o]) for r in rows)) for o in others)
          + f" | {n_esc} (of them trusted: {n_esc_trusted}) |")  # fmt: skip
    print(f"| of {len(rows)} | " + " | ".join("" for _ in others) + " | |")
    by_step = Counter(r["step"] for r in rows)
    reg_step = Counter(r["step"] for r in rows if r["escalated"] and r["trusted"])
    cost: dict[str, list[float]] = defaultdict(list)
    for r in rows:
        for s in r["steps"]:
            if s["ms"] > 0:
                cost[s["step"]].append(s["ms"])
    print(
        "\n| step | pair-seeds whose pose it gave | of them registered and trusted | tried "
        "| median ms when tried |"
    )
    print("|---|---:|---:|---:|---:|")
    for step in cost:
        print(f"| {step} | {by_step.get(step, 0)} | {reg_step.get(step, 0)} | {len(cost[step])} | "
              f"{statistics.median(cost[step]):.0f} |")  # fmt: skip
    first = [r for r in rows if r["step"] == "first" and r["trusted"]]
    if first:
        esc = statistics.median(r["escalated_ms"] for r in first)
        alone = statistics.median(r["fastmac20_ms"] for r in first)
        print(f"\ntrusted at the first try ({len(first)} pair-seeds): median {esc:.0f} ms with "
              f"escalate=auto, {alone:.0f} ms the first step alone (escalate=off) in the same run: "
              f"{esc / alone:.2f}x")  # fmt: skip
    later = [r["escalated_ms"] for r in rows if not (r["step"] == "first" and r["trusted"])]
    if later:
        print(f"escalated ({len(later)} pair-seeds): median {statistics.median(later):.0f} ms, worst "
              f"{max(later):.0f} ms")  # fmt: skip


if __name__ == "__main__":
    main()
