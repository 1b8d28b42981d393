#!/usr/bin/env bash
# Runs the paper's studies (conf/experiment presets) sequentially into outputs/studies/<study>_<data>/,
# then `python -m studies.make_results` turns them into docs/results.md and docs/figures/.
#
#   studies/run_studies.sh                      # everything (about 40 min on a shared 2-core CPU)
#   studies/run_studies.sh sampling filter      # some studies
#   DATA="3dmatch kitti" N=8 studies/run_studies.sh sampling   # fewer data sets / pairs
#   RESUME=1 DATA=kitti studies/run_studies.sh sampling    # finish an interrupted sweep (same command)
#   python -m studies.make_results              # tables + figures -> docs/results.md
# The signal and descriptor studies skip the synthetic KITTI-like family (KITTI_ALL=1 includes it): its
# RR stays at 100 % down to ratio 0.01, and its dense inlier graphs make the clique search slow.
#
# Studies: sampling filter signal stochastic descriptor profile sota timing
# Threads: one BLAS / OpenMP thread everywhere, and one C++ core thread (its pool reads OMP_NUM_THREADS),
# except the profile study, whose core uses CORE_THREADS (default 2).
# Data:    3dmatch kitti 3dlomatch (synthetic families, N pairs each), real_indoor real_outdoor
#          real_object (the real pairs of ../shared/data, dataset=shared_real by category; real_object, the
#          bunny and dragon scans, only in the descriptor study by default)
# Each sweep's directory is deleted first (RESUME=1 keeps it): a run directory that already holds results
# is refused without resume=, and with it resumed (its finished pairs skipped whatever the config).
# Each sweep writes <its directory>/ran.json (start, end, wall time, load averages, the core's commit), which
# make_results prints under the study's section and in the wall-time table.
set -euo pipefail
cd "$(dirname "$0")/.."

N=${N:-24}                                   # pairs per synthetic family
DATA=${DATA:-"3dmatch kitti 3dlomatch real_indoor real_outdoor"}
SMALL_N=${SMALL_N:-12}                       # synthetic pairs for the signal and descriptor studies
SEEDS=${SEEDS:-0,1,2}                        # stochastic samplers: seeds of the sampler (and the
                                             # descriptor's 5,000-row subsample); the data stay fixed
STUDIES=("$@")
[ ${#STUDIES[@]} -eq 0 ] && STUDIES=(sampling filter signal profile descriptor sota stochastic timing)
OUT=outputs/studies
LOG=${LOG:-$OUT/run_studies.log}                # a second, concurrent invocation: LOG=... (append it after)
mkdir -p "$OUT"
# one BLAS / OpenMP thread: the machine is shared, and OpenBLAS threads spinning on busy cores make a
# 1,000 x 1,000 eigendecomposition 30x slower
export OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
# mac.time_limit_s: a wall-clock cap on the clique search, off by default since the exact branch-and-bound
# selection (mac.search=bnb) replaced the enumeration of every maximal clique (the dense KITTI-like graphs
# that needed a 3-10 s cap finish in well under 2 s); its reproducible work budget mac.max_nodes stays on.
# TIME_LIMIT_S=3 brings the old safety net back.
COMMON=(tracker=none progress=false mac.time_limit_s=${TIME_LIMIT_S:-0})

# the C++ extension, copied once: `pip install -e .` (by anyone) rewrites the installed one in place, which
# crashes a running sweep; fastmac_exp loads this copy instead (FASTMAC_CORE_SO, fastmac_exp/core.py; delete
# $OUT/_core to refresh it). The copy's source is the installed extension, whatever FASTMAC_CORE_SO says now.
CORE=$OUT/_core/_mac_core.so
if [ ! -f "$CORE" ]; then
  mkdir -p "$OUT/_core"
  src=$(env -u FASTMAC_CORE_SO python -c "import importlib.util as u; print(u.find_spec('fastmac_exp._mac_core').origin)")
  cp "$src" "$CORE"
  { echo "copied $(date -u +%FT%TZ) from $src"; echo "sha1 $(sha1sum "$CORE" | cut -c1-40)";
    echo "commit $(git rev-parse HEAD)$(git diff --quiet HEAD -- fastmac_exp/_cpp || echo ' + uncommitted C++ changes')"
    echo "cpp_commit $(git log -1 --format=%H -- fastmac_exp/_cpp)"; } >"$OUT/_core/info.txt"
fi
export FASTMAC_CORE_SO=$PWD/$CORE

data_args() {  # the dataset overrides for one data key
  case $1 in
    3dmatch | kitti | 3dlomatch)
      echo "dataset=synthetic dataset.family=$1 dataset.num_pairs=$N dataset.seed=0" ;;
    real_indoor) echo "dataset=shared_real dataset.category=indoor" ;;
    real_outdoor) echo "dataset=shared_real dataset.category=outdoor" ;;
    real_object) echo "dataset=shared_real dataset.category=object" ;;
    *) echo "unknown data key $1" >&2; exit 2 ;;
  esac
}

synthetic() { case $1 in 3dmatch | kitti | 3dlomatch) return 0 ;; *) return 1 ;; esac; }

cpu_model=$(sed -n 's/^model name[[:space:]]*: //p' /proc/cpuinfo | head -1)
record() {  # record <dir> <started> <load at start> <seconds> <status>: <dir>/ran.json, which make_results
  # prints under the study's section (the core, when, and the load it ran under)
  mkdir -p "$1"
  local core_commit core_sha1
  core_commit=$(sed -n 's/^cpp_commit //p' "$OUT/_core/info.txt")  # the last commit that changed the C++
  [ -n "$core_commit" ] || core_commit=$(sed -n 's/^commit //p' "$OUT/_core/info.txt")
  core_sha1=$(sed -n 's/^sha1 //p' "$OUT/_core/info.txt")
  printf '{"started": "%s", "ended": "%s", "wall_s": %d, "status": "%s", "load_start": "%s", "load_end": "%s", "core_commit": "%s", "core_sha1": "%s", "code_commit": "%s", "cpu": "%s", "nproc": %d}\n' \
    "$2" "$(date -u +%FT%TZ)" "$4" "$5" "$3" "$(cut -d' ' -f1-3 /proc/loadavg)" "$core_commit" "$core_sha1" \
    "$(git rev-parse HEAD)" "$cpu_model" "$(getconf _NPROCESSORS_ONLN)" >"$1/ran.json"
}

sweep() {  # sweep <dir> <overrides...>: one multirun into a fresh directory, timed into the log
  local dir=$1; shift
  [ "${RESUME:-0}" = 1 ] || rm -rf "$dir"  # RESUME=1: finish an interrupted sweep instead
  local t0=$SECONDS attempt started load0
  started=$(date -u +%FT%TZ) load0=$(cut -d' ' -f1-3 /proc/loadavg)
  echo "[$(date +%T)] python run.py -m $* ${COMMON[*]} hydra.sweep.dir=$dir" | tee -a "$LOG"
  echo "  code: $(git rev-parse --short HEAD)$(git diff --quiet HEAD -- fastmac_exp || echo ' + uncommitted changes under fastmac_exp/'); C++ core: $CORE" >>"$LOG"
  # a crash (e.g. the C++ extension rebuilt under a running sweep) is retried into the same directory with
  # resume=auto, which resumes every member run, skipping its finished pairs (without resume= the experiment
  # refuses a directory that already holds results)
  local again=()
  [ "${RESUME:-0}" = 1 ] && again=(resume=auto)
  for attempt in 1 2 3; do
    if python run.py -m "$@" "${COMMON[@]}" ${again[@]+"${again[@]}"} hydra.sweep.dir="$dir" >>"$LOG" 2>&1; then
      echo "[$(date +%T)]   done in $((SECONDS - t0)) s" | tee -a "$LOG"
      record "$dir" "$started" "$load0" $((SECONDS - t0)) done
      return 0
    fi
    echo "[$(date +%T)]   attempt $attempt failed; resuming" | tee -a "$LOG"
    again=(resume=auto)  # the finished members and pairs are kept
  done
  echo "[$(date +%T)]   FAILED after 3 attempts" | tee -a "$LOG"
  record "$dir" "$started" "$load0" $((SECONDS - t0)) failed
  return 1
}

for study in "${STUDIES[@]}"; do
  case $study in
    sampling)  # Figs. down1-3; ratio 1 (= MAC, identical for every sampler) is run once per seed
      for d in $DATA; do
        # shellcheck disable=SC2046
        sweep "$OUT/sampling_strategy_$d/sweep" +experiment=sampling_strategy $(data_args "$d") \
          ratio=0.5,0.2,0.1,0.05,0.01 seed="$SEEDS"
        # shellcheck disable=SC2046
        sweep "$OUT/sampling_strategy_$d/mac" $(data_args "$d") sampler=none seed="$SEEDS"
      done ;;
    filter)  # Table filter
      for d in $DATA; do
        # shellcheck disable=SC2046
        sweep "$OUT/filter_ablation_$d" +experiment=filter_ablation $(data_args "$d") seed="$SEEDS"
      done ;;
    signal)  # Fig. ablation (xyz signal on a dense Gaussian graph, as FastMAC's code: ~1 s per pair), seed 0,
      # the first $SMALL_N synthetic pairs
      for d in $DATA; do
        [ "$d" = kitti ] && [ "${KITTI_ALL:-0}" != 1 ] && continue  # RR saturated there; slow cliques
        lim=""; synthetic "$d" && lim="limit=$SMALL_N"
        # shellcheck disable=SC2046
        sweep "$OUT/signal_ablation_$d" +experiment=signal_ablation $(data_args "$d") $lim
      done ;;
    profile)  # Table profile / Fig. 1: stage times against the ratio (ratio 1 with sampler=none = MAC); the
      # C++ core on CORE_THREADS threads (default 2, this machine's cores: the speed targets are for 2
      # cores; the core's pool reads OMP_NUM_THREADS), BLAS still on one
      export OMP_NUM_THREADS=${CORE_THREADS:-2}
      for d in $DATA; do
        # shellcheck disable=SC2046
        sweep "$OUT/time_profile_$d/fastmac" +experiment=time_profile $(data_args "$d") \
          ratio=0.5,0.2,0.1,0.05,0.01
        # shellcheck disable=SC2046
        sweep "$OUT/time_profile_$d/mac" $(data_args "$d") sampler=none
      done
      export OMP_NUM_THREADS=1 ;;
    descriptor)  # Fig. desc: every descriptor (fpfh, fcgf_lite, buffer, spinnet) on KITTI (the KITTI-like family and
      # the 7 real outdoor pairs), indoors (the 3DMatch-like family and the 4 real indoor pairs) and on the 2 real
      # object scan pairs (so every real pair of ../shared/data), the first
      # $DESC_N synthetic pairs, seeds $DESC_SEEDS. SpinNet (~1 min a cloud on this CPU) and BUFFER describe each
      # cloud once a sweep whatever the seeds (the process keeps the described clouds, descriptor.cache_clouds),
      # and the correspondence cache (a private one, emptied first) serves every ratio: 3 seeds, 5 data sets: 34 min
      # of sweeps on 2 shared cores (2026-12-07).
      [ "${DESC_KEEP_CACHE:-0}" = 1 ] || rm -rf "$OUT/_cache_descriptor"  # 1: a concurrent second invocation
      for d in ${DESC_DATA:-real_outdoor kitti real_indoor 3dmatch real_object}; do
        lim=""; synthetic "$d" && lim="limit=${DESC_N:-6}"
        # shellcheck disable=SC2046
        sweep "$OUT/descriptor_robustness_$d" +experiment=descriptor_robustness $(data_args "$d") $lim \
          descriptor="${DESCS:-fpfh,fcgf_lite,buffer,spinnet}" seed="${DESC_SEEDS:-0}" \
          cache.dir="$OUT/_cache_descriptor"
      done ;;
    sota)  # Tables kitti/3dmatch/3dlomatch: MAC, FastMAC@50/20 and peers on the same correspondences
      # Open3D's RANSAC on correspondences takes ~1 s per 1k iterations here (one thread, 5,000 rows), so
      # RANSAC 10k (10 s per pair) runs on the 3dmatch family and the real pairs only
      for d in $DATA; do
        methods=""
        case $d in kitti | 3dlomatch) methods="+method=mac,fastmac50,fastmac20,ransac1k,fgr,kiss_matcher,turboreg,fastmac20_turboreg" ;; esac
        # SOTA_METHODS=mac,turboreg,fastmac20_turboreg: only these members (into state_of_the_art_<d> all the same)
        [ -n "${SOTA_METHODS:-}" ] && methods="+method=$SOTA_METHODS"
        # shellcheck disable=SC2046
        sweep "$OUT/state_of_the_art_$d" +experiment=state_of_the_art $(data_args "$d") $methods
      done ;;
    stochastic)  # Fig. stochastic: RR of greedy deterministic vs stochastic sampling (outdoor, 4 pairs,
      # 10-50 samples of 1,000; 100 samples cost ~1 min per pair and are timed by the timing study)
      # shellcheck disable=SC2046
      sweep "$OUT/stochastic_vs_deterministic_kitti" +experiment=stochastic_vs_deterministic \
        $(data_args kitti) limit=4 ratio=0.05,0.02,0.01 ;;
    timing)  # Fig. stochastic, left: sampling time against the sample count, both samplers
      echo "[$(date +%T)] python -m studies.time_samplers" | tee -a "$LOG"
      t0=$SECONDS started=$(date -u +%FT%TZ) load0=$(cut -d' ' -f1-3 /proc/loadavg)
      python -m studies.time_samplers --out "$OUT/sampler_timing" --budget-s 150 >>"$LOG" 2>&1
      echo "[$(date +%T)]   done in $((SECONDS - t0)) s" | tee -a "$LOG"
      record "$OUT/sampler_timing" "$started" "$load0" $((SECONDS - t0)) done ;;
    *) echo "unknown study $study" >&2; exit 2 ;;
  esac
done
