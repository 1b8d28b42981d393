"""What every study module of make_results shares: the page being written, loading and aggregating a study's
runs, the paper's numbers (studies/paper/*.csv), the prose (studies/text/*.md) and the cell formats."""

from __future__ import annotations

import json
import math
import re
import string
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from fastmac_exp.report import (  # noqa: E402
    aggregate,
    load_results,
    markdown_table,
    plots,  # noqa: E402
)

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
PAPER = HERE / "paper"
TEXT = HERE / "text"
PREVIOUS = HERE / "previous"
RATIOS = (1.0, 0.5, 0.2, 0.1, 0.05, 0.01)

# data key -> (display name, the paper's benchmark it stands in for)
DATA = {
    "3dmatch": ("synthetic indoor (3DMatch-like)", "3DMatch"),
    "3dlomatch": ("synthetic indoor, low overlap (3DLoMatch-like)", "3DLoMatch"),
    "kitti": ("synthetic outdoor (KITTI-like)", "KITTI"),
    "real_indoor": ("real indoor pairs (3DMatch/3DLoMatch fragments)", "3DMatch"),
    "real_outdoor": ("real outdoor pairs (KITTI, a Velodyne pair, an Apollo loop closure)", "KITTI"),
    "real_object": ("real object scans (the Stanford bunny and dragon)", "objects"),
}
SHORT = {
    "3dmatch": "synthetic 3DMatch-like",
    "3dlomatch": "synthetic 3DLoMatch-like",
    "kitti": "synthetic KITTI-like",
    "real_indoor": "real indoor",
    "real_outdoor": "real outdoor",
    "real_object": "real objects",
}


# ---- the paper's numbers (studies/paper/README.md) ---------------------------------------------------------
def read_data(path: Path) -> pd.DataFrame:
    """A CSV of studies/paper or studies/previous (its first line a # comment naming the source)."""
    return pd.read_csv(path, comment="#")


def _by_ratio(pct) -> float:
    return float(pct) / 100


def _paper_rr() -> dict[tuple[str, str], tuple[float, ...]]:
    """(benchmark, descriptor) -> RR (%) at RATIOS (the FastMAC README's table)."""
    t = read_data(PAPER / "fastmac_readme_rr.csv").set_index(["benchmark", "descriptor"])
    col = {_by_ratio(c): c for c in t.columns}
    return {key: tuple(float(row[col[r]]) for r in RATIOS) for key, row in t.iterrows()}


def _paper_filter() -> dict[str, dict[float, tuple[float, float, float]]]:
    """filter -> ratio -> (RR, RE, TE) (Table filter, KITTI FCGF)."""
    out: dict[str, dict[float, tuple[float, float, float]]] = {}
    for r in read_data(PAPER / "table_filter.csv").itertuples():
        out.setdefault(r.filter, {})[_by_ratio(r.ratio)] = (float(r.rr), float(r.re_deg), float(r.te_cm))
    return out


def _paper_profile() -> dict[float, tuple[float, ...]]:
    """ratio -> ms of Sampling, GC, MCS, NCS, PE, total (Table profile, 3DMatch FCGF)."""
    t = read_data(PAPER / "table_profile.csv")
    stages = ["sampling", "gc", "mcs", "ncs", "pe", "total"]
    return {_by_ratio(r["ratio"]): tuple(float(r[s]) for s in stages) for _, r in t.iterrows()}


def _paper_sota() -> dict[str, dict[str, tuple[float, float, float, float]]]:
    """benchmark -> method -> (RR, RE, TE, ms) (Tables kitti/3dmatch/3dlomatch, FPFH; RANSAC: appendix)."""
    out: dict[str, dict[str, tuple[float, float, float, float]]] = {}
    for r in read_data(PAPER / "table_sota.csv").itertuples():
        out.setdefault(r.benchmark, {})[r.method] = (
            float(r.rr),
            float(r.re_deg),
            float(r.te_cm),
            float(r.time_ms),
        )
    return out


PAPER_RR = _paper_rr()
PAPER_FILTER = _paper_filter()
PAPER_PROFILE = _paper_profile()
PAPER_SOTA = _paper_sota()


# ---- prose (studies/text/*.md) ----------------------------------------------------------------------------
def text(name: str, **values: object) -> list[str]:
    """studies/text/<name>.md as page lines: `$name` placeholders filled from `values`, `<!-- -->` comment
    lines dropped, each paragraph (or list item, or heading) on one line, a blank line after each block."""
    raw = string.Template("\n".join(verbatim(name))).substitute(values)
    out: list[str] = []
    for block in raw.split("\n\n"):
        lines: list[str] = []
        for ln in block.splitlines():
            if not lines or ln.startswith(("- ", "#")):
                lines.append(ln)
            else:
                lines[-1] += " " + ln
        if lines:
            out += [" ".join(ln.split()) for ln in lines] + [""]
    return out


def verbatim(name: str) -> list[str]:
    """studies/text/<name>.md line by line, without its `<!-- -->` comment lines."""
    return [ln for ln in (TEXT / f"{name}.md").read_text().splitlines() if not ln.startswith("<!--")]


# ---- the page ---------------------------------------------------------------------------------------------
@dataclass
class Page:
    """docs/results.md while it is written: the sections' lines, the claims and notes the studies find, and
    where the runs are read from (`studies`) and the page, figures and CSVs go (`docs`)."""

    studies: Path
    docs: Path
    md: list[str] = field(default_factory=list)
    claims: dict[str, list[tuple[str, str]]] = field(default_factory=dict)  # claim -> [(verdict, evidence)]
    pair_counts: dict[str, str] = field(default_factory=dict)
    mac_rr: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    @property
    def fig(self) -> Path:
        return self.docs / "figures"

    @property
    def csv(self) -> Path:
        return self.docs / "results"

    def add(self, *lines: str) -> None:
        self.md.extend(lines)

    def claim(self, title: str, verdict: str, evidence: str) -> None:
        self.claims.setdefault(title, []).append((verdict, evidence))

    def load(self, study: str, data: str) -> pd.DataFrame | None:
        """Every run below <studies>/<study>_<data>/ (its report/ left out); None when there is none."""
        d = self.studies / f"{study}_{data}"
        if not d.is_dir():
            return None
        t = load_results(d, exclude=[d / "report"])
        return t if len(t) else None

    def save_csv(self, a: pd.DataFrame, name: str) -> None:
        self.csv.mkdir(parents=True, exist_ok=True)
        a.to_csv(self.csv / f"{name}.csv", index=False)

    def caps(self, study: str, data: str, t: pd.DataFrame) -> None:
        """A note for the rows whose clique search hit a cap."""
        if "cap_hit" not in t:
            return
        hit = t["cap_hit"].fillna("").astype(str).ne("")
        if hit.any():
            by = t[hit].groupby(["sampler", "ratio"]).size()
            where = ", ".join(f"{s}@{r:g}: {n}" for (s, r), n in by.items())
            self.notes.append(
                f"{study}, {data}: {int(hit.sum())} of {len(t)} rows hit a clique-search cap "
                f"({t.loc[hit, 'cap_hit'].iloc[0]}; {where}); MAC then selects among the cliques found "
                "so far "
                f"({int(t.loc[hit, 'success'].fillna(False).astype(bool).sum())} of them still registered)."
            )

    def figure(self, name: str, alt: str) -> None:
        self.add(f"![{alt}](figures/{name})", "")

    def per_data(self, study: str, label: Callable[[pd.DataFrame], pd.Series] | None = None):
        """(data, rows, aggregate) for each data set that ran `study`, its caps noted and its aggregate
        saved as docs/results/<study>_<data>.csv; the aggregate's groups are label(rows) (default: the
        sampler) x ratio."""
        for data in DATA:
            t = self.load(study, data)
            if t is None:
                continue
            self.caps(study.replace("_", " "), data, t)
            a = agg_by(t, label(t) if label else t["sampler"].astype(str))
            self.save_csv(a, f"{study}_{data}")
            yield data, t, a

    def line_figure(self, aggs: dict[str, pd.DataFrame], name: str, title: str, rename: dict | None = None):
        """plots.plot_sampling over several data sets (one row each); `sampler` holds the line label."""
        parts = []
        for data, a in aggs.items():
            a = a.drop(columns=["descriptor"]).assign(dataset=SHORT[data])
            if rename:
                a["sampler"] = a["sampler"].map(lambda s: rename.get(s, s))
            parts.append(a)
        plots.plot_sampling(pd.concat(parts, ignore_index=True), self.fig / name, title=title)
        return name


# ---- aggregates -------------------------------------------------------------------------------------------
def agg_by(t: pd.DataFrame, label: pd.Series) -> pd.DataFrame:
    """report.aggregate with each row's `sampler` replaced by a label (groups = label x ratio)."""
    t = t.copy()
    t["sampler"] = label.to_numpy()
    return aggregate(t)


def row_of(a: pd.DataFrame, sampler: str, ratio: float) -> pd.Series | None:
    m = a[(a["sampler"] == sampler) & np.isclose(a["ratio"].astype(float), ratio)]
    return m.iloc[0] if len(m) else None


def per_seed_pairs(a: pd.DataFrame) -> str:
    seeds = int(a["seeds"].max()) if "seeds" in a else 1
    pairs = int(a["pairs"].max()) // max(seeds, 1)
    return f"{pairs} pairs" + (f" × {seeds} seeds" if seeds > 1 else "")


def one_pair(a: pd.DataFrame) -> float:
    """RR points of one pair (100 / pairs per seed): mean RRs closer than this are counted as ties."""
    seeds = int(a["seeds"].max()) if "seeds" in a else 1
    return 100.0 / max(int(a["pairs"].max()) // max(seeds, 1), 1) - 1e-9


def data_heading(data: str, a: pd.DataFrame, extra: str = "") -> str:
    return f"### {data}: {DATA[data][0]} — {per_seed_pairs(a)}{extra}"


def ran_records(studies: Path, patterns: list[str]) -> list[dict]:
    """The ran.json of every sweep below the directories `patterns` (globs in <studies>)."""
    out = []
    for pattern in patterns:
        for d in sorted(studies.glob(pattern)):
            for f in sorted([d / "ran.json", *d.glob("*/ran.json")]):
                if f.is_file():
                    out.append(json.loads(f.read_text()))
    return out


def ran_line(records: list[dict]) -> str:
    """One line: the core the sweeps ran on, when, their wall time and the load they ran under."""
    cores = sorted({r["core_commit"][:7] for r in records})
    sha = sorted({r["core_sha1"][:8] for r in records})
    t0 = min(datetime.fromisoformat(r["started"].replace("Z", "+00:00")) for r in records)
    t1 = max(datetime.fromisoformat(r["ended"].replace("Z", "+00:00")) for r in records)
    loads = [float(r[k].split()[0]) for r in records for k in ("load_start", "load_end")]
    failed = [r for r in records if r.get("status") != "done"]
    return (
        f"_Ran on the C++ core of commit `{'`, `'.join(cores)}` (extension sha1 {', '.join(sha)}), "
        f"{t0:%Y-%m-%d %H:%M}–{t1:%H:%M} UTC, {len(records)} sweep(s), "
        f"{sum(int(r['wall_s']) for r in records):,} s of wall time in all, on {records[0]['cpu']} "
        f"({records[0]['nproc']} cores), load average (1 min) {min(loads):.1f}–{max(loads):.1f} at the "
        "sweeps' starts and ends" + (f"; {len(failed)} sweep(s) failed" if failed else "") + "._"
    )


# ---- verdicts ---------------------------------------------------------------------------------------------
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


def compare(mine: float, others: list[float], spread: float = 0.0) -> str:
    """'better' / 'tie' / 'worse' of one RR against the best of the others."""
    best = max(others)
    if mine > best + 1e-9:
        return "better" if mine - best > spread else "better (within the seed spread)"
    if mine >= best - 1e-9:
        return "tie"
    return "worse" if best - mine > spread else "worse (within the seed spread)"


def tally(wins: int, losses: int) -> str:
    """The verdict of a claim from the ratios it wins and loses (ties count for neither)."""
    if losses == 0 and wins:
        return "agrees"
    if wins == losses == 0:
        return "no difference"
    return "partly" if wins > losses else "disagrees"


# ---- cell formats -----------------------------------------------------------------------------------------
def fnum(v, d: int = 1) -> str:
    return "–" if v is None or not np.isfinite(v) else f"{v:.{d}f}"


def rr_mean(r: pd.Series | None) -> float:
    if r is None:
        return math.nan
    return float(r["RR_seed_mean"]) if r.get("seeds", 1) >= 2 else float(r["RR"])


def rr_cell(r: pd.Series | None) -> str:
    if r is None:
        return "–"
    if r.get("seeds", 1) >= 2 and np.isfinite(r.get("RR_seed_std", np.nan)):
        return f"{r['RR_seed_mean']:.1f} ± {r['RR_seed_std']:.1f}"
    return fnum(r["RR"])


def ms(v) -> str:
    if v is None or not np.isfinite(v):
        return "–"
    return f"{v:.2f}" if v < 10 else f"{v:.1f}" if v < 1000 else f"{v:.0f}"


def re_te(r: pd.Series | None) -> str:
    return "–" if r is None else f"{fnum(r['RE_deg'], 2)} / {fnum(r['TE_cm'], 2)}"


def te_cell(r: pd.Series | None) -> str:
    return "–" if r is None else fnum(r["TE_cm"], 1)


def wall_times(studies: Path) -> list[str]:
    """The last successful run of each sweep in <studies>/run_studies.log, with its wall time."""
    log = studies / "run_studies.log"
    if not log.exists():
        return []
    done: dict[str, tuple[str, int]] = {}
    cmd = None
    for line in log.read_text().splitlines():
        if m := re.match(r"\[\d\d:\d\d:\d\d\] (python .*)", line):
            cmd = m.group(1)
        elif (m := re.match(r"\[\d\d:\d\d:\d\d\]\s+done in (\d+) s", line)) and cmd:
            d = re.search(r"hydra.sweep.dir=outputs/studies/(\S+)", cmd)
            key = d.group(1) if d else cmd[:60]
            done.pop(key, None)
            done[key] = (cmd, int(m.group(1)))
            cmd = None
    ran = {k: _ran(studies, k) for k in done}
    with_ran = any(ran.values())
    rows = [[f"`{k}`", str(s)] + (_ran_cells(ran[k]) if with_ran else []) for k, (_, s) in done.items()]
    total = sum(s for _, s in done.values())
    rows.append(["**total**", f"**{total} s ({total / 60:.0f} min)**"] + (["", ""] if with_ran else []))
    header = ["sweep (outputs/studies/…)", "wall time (s)"]
    header += ["started (UTC)", "load average (1 min) at start → end"] if with_ran else []
    out = [markdown_table(header, rows, ["l", "r"] + (["l", "l"] if with_ran else [])), ""]
    cmds = [c for c, _ in done.values()]
    note = (
        " (logged before `dataset.limit` became the run key `limit`: write `limit=N` today)"
        if any("dataset.limit=" in c for c in cmds)
        else ""
    )
    out += [f"Commands as logged{note}:", "", "```", *cmds, "```", ""]
    return out


def _ran(studies: Path, key: str) -> dict | None:
    """The ran.json run_studies.sh wrote for the sweep logged as `key` (None: none)."""
    import json

    d = studies / ("sampler_timing" if key.startswith("python -m studies.time_samplers") else key)
    f = d / "ran.json"
    return json.loads(f.read_text()) if f.is_file() else None


def _ran_cells(r: dict | None) -> list[str]:
    if r is None:
        return ["", ""]
    return [r["started"][11:16], f"{r['load_start'].split()[0]} → {r['load_end'].split()[0]}"]


def replace_section(page: Path, heading: str, block: str) -> None:
    """Put `block` (starting with `heading`, a "## " line) into the Markdown page: in place of the section
    with that heading, else before "## Notes", else at the end."""
    text = page.read_text()
    if heading in text:
        start = text.index(heading)
        nxt = text.find("\n## ", start + len(heading))
        text = text[:start] + block + (text[nxt + 1 :] if nxt >= 0 else "")
    elif "\n## Notes" in text:
        i = text.index("\n## Notes")
        text = text[: i + 1] + block + "\n" + text[i + 1 :]
    else:
        text = text.rstrip() + "\n\n" + block
    page.write_text(text)
