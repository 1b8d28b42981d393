"""register()'s own cost beside the stages it runs, side by side in one run (issue 50 item 5).

    python benchmarks/bench_facade.py [--reps 15] [--ids kitti00_95_to_94 ...] [--samples auto]

Each pair of ../shared/data (default: the dense LiDAR pairs) is described once with the core's FPFH (the
5,000-correspondence cap); then, interleaved, `--reps` calls after a warm-up of
- facade: `register(corr, family=..., samples="auto")` as a user calls it (escalate="auto": it stops at
  the first trusted pose), wall clock;
- facade, composed each call: the same with register()'s kept plans cleared before each call (what every
  call paid before they were kept: Hydra's compose, the copy, instantiate);
- stages: `pipeline.register_correspondences` on the same matches with parts built once, wall clock;
and, of the facade's calls, the sum of the stages its timings report (sampling + MAC, check, decoy) and the
facade's time above that sum; and MAC@100 through the facade (`register(corr, family, sampler="none",
escalate="off")`: every correspondence, the issue's reference) with its ratio to the facade's FastMAC call.
Medians (ms). Prints the CPU model and the load average.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.machine import cpu_model, load  # noqa: E402
from fastmac_exp import plans, register  # noqa: E402
from fastmac_exp.descriptors.fpfh import FPFHDescriptor  # noqa: E402
from fastmac_exp.families import FIXED_RESOLUTION  # noqa: E402
from fastmac_exp.geometry.offset import describe_moved  # noqa: E402
from fastmac_exp.options import compose_run, instantiate_part  # noqa: E402
from fastmac_exp.params import mac_params_for  # noqa: E402
from fastmac_exp.pipeline import register_correspondences  # noqa: E402

DATA = REPO.parent / "shared" / "data"
DENSE = ("kitti00_95_to_94", "kitti00_199_to_198", "lidar_smallgicp_source_to_target")


def stages_ms(timings: dict[str, float]) -> float:
    """What the stages took by their own clocks: sampling + MAC ('total'), the check (inliers and trust),
    the decoy."""
    return timings["total"] + timings.get("check", 0.0) + timings.get("decoy", 0.0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reps", type=int, default=15)
    ap.add_argument("--ids", nargs="+", default=list(DENSE))
    ap.add_argument("--samples", default="auto", help="register()'s samples (auto, or a count)")
    args = ap.parse_args(argv)
    if not (DATA / "pairs.json").is_file():
        print(f"no real pairs: {DATA / 'pairs.json'} not found (shared data beside the repository)")
        return 0
    from fastmac_exp.datasets.user_pairs import SharedRealPairs

    samples = args.samples if args.samples == "auto" else int(args.samples)
    ds = SharedRealPairs(root=DATA, ids=args.ids)
    print(f"CPU: {cpu_model()}   load average: {load()}   reps: {args.reps} (after one warm-up)")
    head = (f"{'pair':<34} {'N':>5} {'facade':>8} {'stages':>8} {'above':>7} {'direct':>8} "
            f"{'composed':>9} {'steps':>5} {'MAC@100':>8} {'ratio':>6}")  # fmt: skip
    print(head)
    print("-" * len(head))
    cfg = compose_run({"sampler": "highpass", "backend": "cpp"})
    sampler, backend = instantiate_part(cfg.sampler), instantiate_part(cfg.backend)
    for name in ds.names():
        pair = ds.load(ds.names().index(name))
        corr = describe_moved(FPFHDescriptor(), pair, np.random.default_rng(0))
        fam = pair.family
        params = mac_params_for(fam, "fpfh", FIXED_RESOLUTION)
        facade, stages, direct, composed, steps, mac_all = [], [], [], [], [], []
        for rep in range(args.reps + 1):
            t0 = time.perf_counter()
            res = register(corr, family=fam, samples=samples)
            t1 = time.perf_counter()
            register_correspondences(corr, params, sampler, backend, 0.2, fam, np.random.default_rng(0),
                                     samples=samples)  # fmt: skip
            t2 = time.perf_counter()
            plans._kept.cache_clear()
            register(corr, family=fam, samples=samples)
            t3 = time.perf_counter()
            register(corr, family=fam, sampler="none", escalate="off")
            t4 = time.perf_counter()
            if rep == 0:
                continue  # the warm-up
            facade.append((t1 - t0) * 1e3)
            stages.append(sum(stages_ms(s) for s in _step_timings(res)))
            direct.append((t2 - t1) * 1e3)
            composed.append((t3 - t2) * 1e3)
            mac_all.append((t4 - t3) * 1e3)
            steps.append(len(res.escalation))
        med = statistics.median
        above = [f - s for f, s in zip(facade, stages)]
        print(f"{name:<34} {len(corr):>5} {med(facade):>8.1f} {med(stages):>8.1f} {med(above):>7.2f} "
              f"{med(direct):>8.1f} {med(composed):>9.1f} {max(steps):>5} {med(mac_all):>8.1f} "
              f"{med(mac_all) / med(facade):>5.1f}x")  # fmt: skip
    print("\nms, medians. facade: register(corr, family, samples) wall; stages: the sum its stages report "
          "(sampling + MAC, check, decoy); above: facade - stages, per call; direct: "
          "register_correspondences with parts built once; composed: the facade with its kept plans "
          "cleared before each call (compose + instantiate every call, as before); steps: the escalation's "
          "steps run (1: the first pose was trusted); MAC@100: register(corr, family, sampler='none', "
          "escalate='off') wall, and its ratio to the facade.")  # fmt: skip
    return 0


def _step_timings(res) -> list[dict[str, float]]:
    """The stage timings of each step a call ran (only the returned step's are in the result: a call
    whose first step was trusted ran one)."""
    if len(res.escalation) != 1:
        raise SystemExit(
            f"the call escalated through {len(res.escalation)} steps: the stages' sum is of one step; "
            "pick a pair whose first pose is trusted"
        )
    return [res.timings]


if __name__ == "__main__":
    raise SystemExit(main())
