#!/usr/bin/env bash
# Measures what docs/cluster.md's core-hour estimates rest on: per pair, the describe cost (FPFH, once per
# pair and seed thanks to the shared correspondence cache) and the registration cost of one sweep member
# (FastMAC at 20 %, and MAC = ratio 1, the slowest member), on the embedded synthetic pairs and the real
# pairs of ../shared/data. One process, one BLAS thread, empty caches of its own:
#   docs/cluster_cost.sh [OUT]        (default outputs/cluster_cost; then read OUT/cost.md)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-outputs/cluster_cost}
rm -rf "$OUT" && mkdir -p "$OUT"
export OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
common=(tracker=none progress=false "cache.dir=$OUT/cache/corr")
syn=("dataset.cache_dir=$OUT/cache/synthetic")
member() {  # member <name> <overrides...>: one run, its wall time in OUT/<name>/wall_s
  local name=$1; shift
  local t0; t0=$(date +%s.%N)
  python run.py "$@" "${common[@]}" "hydra.run.dir=$OUT/$name" >"$OUT/$name.log" 2>&1
  echo "$(date +%s.%N) - $t0" | bc >"$OUT/$name/wall_s"
}
member synthetic_fastmac20 "${syn[@]}" sampler=highpass ratio=0.2         # cold: builds scenes, describes
member synthetic_mac "${syn[@]}" sampler=none                          # warm: correspondences from the cache
if [ -f ../shared/data/pairs.json ]; then
  for cat in indoor outdoor; do
    member "real_${cat}_fastmac20" dataset=shared_real dataset.category=$cat sampler=highpass ratio=0.2
    member "real_${cat}_mac" dataset=shared_real dataset.category=$cat sampler=none
  done
fi
python - "$OUT" <<'PY'
import sys
from pathlib import Path

import pandas as pd

out = Path(sys.argv[1])
lines = ["| run | pairs | wall s | wall s / pair | median describe ms | median registration ms (t_total) |",
         "|---|---|---|---|---|---|"]
for d in sorted(p for p in out.iterdir() if (p / "results.csv").exists()):
    t = pd.read_csv(d / "results.csv")
    wall = float((d / "wall_s").read_text())
    lines.append(f"| {d.name} | {len(t)} | {wall:.1f} | {wall / len(t):.2f} | "
                 f"{t['t_describe_ms'].median():.0f} | {t['t_total_ms'].median():.1f} |")
    for fam, g in t.groupby(t["pair"].str.extract(r"^(3dm|3dlm|kitti|lidar|apollo|3dmatch)")[0].fillna("other")):
        lines.append(f"| &nbsp; {d.name} {fam} | {len(g)} | | | {g['t_describe_ms'].median():.0f} | "
                     f"{g['t_total_ms'].median():.1f} |")
(out / "cost.md").write_text("\n".join(lines) + "\n")
print("\n".join(lines))
PY
