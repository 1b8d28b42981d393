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
import re
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
from studies.common import REPO, Page, ran_line, ran_records, render_claims, text, wall_times


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
    commit = lines.get("cpp_commit", lines.get("commit", "?"))  # cpp_commit: the last that changed the C++
    return f" C++ core: the extension built from commit `{commit[:12]}` (copied once)."


# section number -> the directories below the studies directory whose sweeps it reads (each sweep's ran.json,
# written by run_studies.sh, names the core, when it ran and the load it ran under)
SECTION_RUNS = {
    1: ["sampling_strategy_*"],
    2: ["filter_ablation_*"],
    3: ["signal_ablation_*"],
    4: ["stochastic_vs_deterministic_*", "sampler_timing"],
    5: ["descriptor_robustness_*"],
    6: ["time_profile_*"],
    7: ["state_of_the_art_*"],
}
SECTION = re.compile(r"^## (\d+)\. ", re.M)
RAN = re.compile(r"_(Ran on|Not rerun on) ")


def sections_of(md: str) -> dict[int, str]:
    """The numbered sections ("## N. ...") of a page, each up to the next "## " heading."""
    out = {}
    for m in SECTION.finditer(md):
        nxt = md.find("\n## ", m.end())
        out[int(m.group(1))] = md[m.start() : nxt + 1 if nxt >= 0 else len(md)].rstrip() + "\n"
    return out


def previous_core(md: str) -> str:
    """The core the previous page names in its head ("built from commit `...`"), or "?"."""
    m = re.search(r"built from commit `([0-9a-f]+)`", md)
    return m.group(1)[:7] if m else "?"


def place_sections(lines: list[str], studies: Path, old: str) -> list[str]:
    """Sections 1-7 with the line naming their core under each heading; a section whose study did not run
    here (no ran.json) keeps the previous page's text, said so; the previous page's sections past 7 (written
    by their own scripts or by hand: 8 estimated scores, 9 keep size, 10 raw clouds to a pose) kept as
    they were, before the notes."""
    md = "\n".join(lines)
    before = sections_of(old)
    new = sections_of(md)
    for n, patterns in SECTION_RUNS.items():
        if n not in new:
            continue
        records = ran_records(studies, patterns)
        if records:
            head, _, rest = new[n].partition("\n")
            block = f"{head}\n\n{ran_line(records)}\n{rest}"
        elif n in before:
            head, _, rest = before[n].partition("\n")
            if RAN.match(rest.lstrip("\n")):  # the previous page's own line says where it ran
                block = before[n]
            else:
                core = previous_core(old)
                said = (
                    f"_Not rerun on this core: the section as the previous page had it (C++ core `{core}`)._"
                )
                block = f"{head}\n\n{said}\n{rest}"
        else:
            continue
        md = md.replace(new[n], block, 1)
    kept = "".join(block + "\n" for k, block in sorted(before.items()) if k > max(SECTION_RUNS))
    if kept:
        at = md.index("\n## Notes") + 1 if "\n## Notes" in md else len(md)
        md = md[:at] + kept + md[at:]
    return md.split("\n")


def make_results(studies: Path, docs: Path) -> str:
    """Write <docs>/results.md, <docs>/figures/ (emptied first of all but the figures other pages of <docs>
    show) and <docs>/results/; returns the page."""
    page = Page(studies=studies, docs=docs)
    old = (docs / "results.md").read_text() if (docs / "results.md").exists() else ""
    if page.fig.exists():  # the figures of the last page go; those other pages of <docs> show stay
        others = "".join(f.read_text() for f in docs.glob("*.md") if f.name != "results.md")
        for f in page.fig.iterdir():
            if f"figures/{f.name}" not in others:
                shutil.rmtree(f) if f.is_dir() else f.unlink()
    page.fig.mkdir(parents=True, exist_ok=True)
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
    lines = place_sections(lines, studies, old)
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
