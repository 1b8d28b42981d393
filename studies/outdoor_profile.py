"""The outdoor rows of the time-profile study, recomputed with the default clique search (mac.search=auto).

    DATA="kitti real_outdoor" TIME_LIMIT_S=0 studies/run_studies.sh profile
    python -m studies.outdoor_profile         # -> docs/outdoor_profile.md
    python -m studies.outdoor_profile --studies /elsewhere/outputs/studies --out FILE

Reads <studies>/time_profile_{kitti,real_outdoor}/{mac,fastmac} (one run of every pair at each ratio) and
writes the per-ratio medians of every stage, RR, the search nodes, how many rows the branch and bound
searched (the rest were enumerated) and any cap hit, beside the values
docs/results.md recorded with the enumeration of every maximal clique and a 3 s cap
(studies/previous/outdoor_profile_before.csv).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from studies.common import PREVIOUS, REPO, read_data, text

STAGES = ("sampling", "graph", "cliques", "selection", "pose", "total")
DATA = {
    "kitti": "synthetic KITTI-like, 24 pairs",
    "real_outdoor": "real outdoor pairs of ../shared/data (KITTI, LiDAR, Apollo)",
}


def before() -> dict[str, str]:
    """data -> docs/results.md's MAC -> FastMAC@20 total ms before the branch-and-bound search."""
    t = read_data(PREVIOUS / "outdoor_profile_before.csv")
    return {r.data: f"MAC {r.mac_ms:g} ms -> FastMAC@20 {r.fastmac20_ms:g} ms" for r in t.itertuples()}


def load(studies: Path, data: str) -> pd.DataFrame | None:
    files = sorted((studies / f"time_profile_{data}").rglob("results.parquet"))
    if not files:
        return None
    return pd.concat([pd.read_parquet(f) for f in files], ignore_index=True)


def table(t: pd.DataFrame) -> list[str]:
    t = t.copy()
    t["ratio"] = t["ratio"].astype(float)
    head = (
        "| ratio | pairs | kept | RR | "
        + " | ".join(f"{s} ms" for s in STAGES)
        + " | search nodes | by bnb | caps |"
    )
    lines = [head, "|" + "---:|" * (len(STAGES) + 7)]
    for ratio, g in sorted(t.groupby("ratio"), key=lambda kv: -kv[0]):
        ok = g["success"].fillna(False).astype(bool)
        cells = [f"{g[f't_{s}_ms'].median():.1f}" if f"t_{s}_ms" in g else "-" for s in STAGES]
        nodes = int(g["search_nodes"].median()) if "search_nodes" in g else 0
        caps = int(g["cap_hit"].fillna("").astype(str).ne("").sum())
        # rows the branch and bound searched ("bnb", or "auto:bnb" when auto gave the enumeration up)
        by_bnb = int(g["search"].fillna("").astype(str).str.endswith("bnb").sum()) if "search" in g else 0
        label = "1 (MAC)" if ratio >= 1 else f"{ratio:g}"
        lines.append(
            f"| {label} | {len(g)} | {int(g['n_kept'].median())} | {100 * ok.mean():.1f} % | "
            + " | ".join(cells)
            + f" | {nodes} | {by_bnb} | {caps} |"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m studies.outdoor_profile", description=__doc__.split("\n\n")[0]
    )
    ap.add_argument("--studies", type=Path, default=REPO / "outputs" / "studies", help="the studies' runs")
    ap.add_argument(
        "--out", type=Path, default=REPO / "docs" / "outdoor_profile.md", help="the page to write"
    )
    args = ap.parse_args(argv)
    md = text("outdoor_profile")
    prev = before()
    found = False
    for data, title in DATA.items():
        t = load(args.studies, data)
        if t is None:
            md += [f"## {data}: no runs in {args.studies}", ""]
            continue
        found = True
        md += [
            f"## {data}: {title}",
            "",
            f"Before (docs/results.md, enumeration + 3 s cap): {prev[data]}.",
            "",
        ]
        md += table(t) + [""]
    args.out.write_text("\n".join(md).rstrip() + "\n")
    print(args.out.read_text())
    return 0 if found else 1


if __name__ == "__main__":
    sys.exit(main())
