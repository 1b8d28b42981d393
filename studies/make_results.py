"""docs/results.md, docs/figures/*.png and docs/results/*.csv from the study directories that
studies/run_studies.sh writes.

    studies/run_studies.sh                 # runs the studies into outputs/studies/ (sequential sweeps)
    python -m studies.make_results         # this: tables, figures, the paper's numbers beside ours, verdicts
    python -m studies.make_results --studies /elsewhere/outputs/studies [--docs DIR]

Every number in results.md comes from the results tables below the studies directory (aggregated with
fastmac_exp.report) or from studies/time_samplers.py's timing.csv; the paper's numbers from
studies/paper/*.csv, the prose from studies/text/*.md. One module per study writes its section, in this
order: sampling_strategy, filter_ablation, signal_ablation, stochastic + sampler_timing,
descriptor_robustness, time_profile, state_of_the_art.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import subprocess
from pathlib import Path

from studies import (
    descriptor_robustness,
    filter_ablation,
    sampler_timing,
    sampling_strategy,
    signal_ablation,
    state_of_the_art,
    stochastic,
    time_profile,
)
from studies.common import REPO, Page, text, wall_times


def machine() -> str:
    """This machine's CPU, cores, GPU and Python (read at run time)."""
    cpu = platform.machine()
    try:
        cpu = next(
            line.split(":", 1)[1].strip()
            for line in Path("/proc/cpuinfo").read_text().splitlines()
            if line.startswith("model name")
        )
    except (OSError, StopIteration):
        pass
    try:
        gpu = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        gpu = ""
    return f"{cpu}, {os.cpu_count()} cores; GPU: {gpu or 'none'}; Python {platform.python_version()}"


def core_info(studies: Path) -> str:
    """Which C++ core the sweeps ran on (<studies>/_core/info.txt, written by run_studies.sh)."""
    info = studies / "_core" / "info.txt"
    if not info.exists():
        return ""
    lines = dict(line.split(" ", 1) for line in info.read_text().splitlines() if " " in line)
    return f" C++ core: the extension built from commit `{lines.get('commit', '?')[:12]}` (copied once)."


def render_claims(claims: dict[str, list[tuple[str, str]]], sizes: dict[str, str]) -> list[str]:
    """Each claim with its verdicts counted apart for the synthetic families and the real pairs, and each
    evidence line with the number of pairs it rests on."""
    out = []
    for title, items in claims.items():
        parts = []
        for label, real in (("synthetic", False), ("real", True)):
            group = [w for w, ev in items if ev.split(":")[0].startswith("real_") == real]
            if group:
                counts = {v: group.count(v) for v in dict.fromkeys(group)}
                parts.append(f"{label}: " + ", ".join(f"{v} {n}" for v, n in counts.items()))
        out.append(f"- **{title}** — " + "; ".join(parts) + f" (of {len(items)} data sets)")
        for v, ev in items:
            key, _, rest = ev.partition(":")
            size = f" ({sizes[key]})" if key in sizes else ""
            out.append(f"  - {key}{size}:{rest} → {v}")
    return out


def make_results(studies: Path, docs: Path) -> str:
    """Write <docs>/results.md, <docs>/figures/ (emptied first) and <docs>/results/; returns the page."""
    page = Page(studies=studies, docs=docs)
    if page.fig.exists():
        shutil.rmtree(page.fig)
    page.fig.mkdir(parents=True)
    sampling_strategy.render(page)
    filter_ablation.render(page)
    signal_ablation.render(page)
    sampler_timing.render(page, stochastic.render(page))
    descriptor_robustness.render(page)
    time_profile.render(page)
    state_of_the_art.render(page)
    head = text(
        "header",
        machine=machine(),
        core=core_info(studies),
        counts="; ".join(f"{k}: {v}" for k, v in page.pair_counts.items()),
        mac_rr="; ".join(f"{k} {v}" for k, v in page.mac_rr.items()),
    )
    verdict = text("claims") + (render_claims(page.claims, page.pair_counts) or ["(no studies found)"]) + [""]
    notes = ["## Notes", ""] + [f"- {n}" for n in page.notes] + [""]
    lines = head + text("summary") + verdict + page.md + notes + text("what_ran") + wall_times(studies)
    md = "\n".join(lines).rstrip() + "\n"
    (docs / "results.md").write_text(md)
    return md


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m studies.make_results", description=__doc__.split("\n\n")[0])
    ap.add_argument("--studies", type=Path, default=REPO / "outputs" / "studies", help="the studies' runs")
    ap.add_argument(
        "--docs", type=Path, default=REPO / "docs", help="where results.md, figures/ and results/ go"
    )
    args = ap.parse_args(argv)
    args.docs.mkdir(parents=True, exist_ok=True)
    make_results(args.studies, args.docs)
    print(f"wrote {args.docs / 'results.md'} and {len(list((args.docs / 'figures').glob('*.png')))} figures")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
