"""The experiment loop: every pair of a dataset through the pipeline, with fault isolation, resume,
parallel workers and trackers. Usable without Hydra: pass a DictConfig or a plain dict."""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import signal
import sys
import traceback
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from fastmac_exp import __version__
from fastmac_exp.cpus import available_cores
from fastmac_exp.errors import InputError
from fastmac_exp.geometry.metrics import PAIR_STAGES, summarize
from fastmac_exp.geometry.trust import TRUST_LEVEL
from fastmac_exp.pipeline import PairOutcome, run_pair
from fastmac_exp.pipeline.cache import CorrespondenceCache
from fastmac_exp.pipeline.row import PairRow
from fastmac_exp.pipeline.stopwatch import Stopwatch
from fastmac_exp.resources import find_file
from fastmac_exp.run.checks import check_run_keys, run_escalates, run_ratio, run_samples
from fastmac_exp.run.escalate_pair import StepParts, escalate_pair
from fastmac_exp.run.results import ResultsLog, pose_file, pose_matrix, write_pose
from fastmac_exp.run.resume import CONFIG_NAME, RESUMED_NAME, check_is_run, check_same_experiment, is_auto
from fastmac_exp.run.runlock import RunLock
from fastmac_exp.trackers.redact import redact
from fastmac_exp.types import Pair

log = logging.getLogger(__name__)


class Components:
    """The instantiated parts of a run (built once per process)."""

    def __init__(self, cfg: DictConfig) -> None:
        ds_cfg = OmegaConf.to_container(cfg.dataset, resolve=True)
        self.limit = cfg.get("limit")
        self.dataset = instantiate(cfg.dataset)
        # progress=false silences the descriptor's per-keypoint bar too (not a key of the cache's)
        quiet = {"progress": False} if not cfg.get("progress", True) and "progress" in cfg.descriptor else {}
        self.descriptor = instantiate(cfg.descriptor, **quiet)
        front_end_for = getattr(self.dataset, "front_end_for", None)  # dataset=3dmatch|3dlomatch|kitti
        if front_end_for is not None:
            self.descriptor = front_end_for(self.descriptor)  # what the data hold picks the front end
        self.sampler = instantiate(cfg.sampler)
        self.backend = instantiate(cfg.backend)
        self.cfg = cfg
        self.step_parts: StepParts | None = None  # escalate=auto's parts, built on first use
        cache_cfg = cfg.get("cache") or {}
        self.cache = CorrespondenceCache(cache_cfg.get("dir"), bool(cache_cfg.get("correspondences", False)))
        desc_plain = OmegaConf.to_container(cfg.descriptor, resolve=True)
        self._cache_parts = {
            "dataset": ds_cfg,
            "descriptor": desc_plain,
            "files": _file_stamps(desc_plain),  # a retrained model invalidates its cached matches
            "version": __version__,
            "frame": "pair-centred",  # entries hold what run_pair describes: the pair moved to its centre
            "seed": int(cfg.seed),
        }
        if getattr(self.dataset, "chosen", None):  # the data home's folder and the front end it picked
            self._cache_parts["data"] = self.dataset.chosen
        self.labels = {  # the results rows' labels: what each part calls itself
            group: str(getattr(part, "name", group))
            for group, part in (("dataset", self.dataset), ("descriptor", self.descriptor),
                                ("sampler", self.sampler), ("backend", self.backend))
        }  # fmt: skip

    def names(self) -> list[str]:
        names = list(self.dataset.names())
        if self.limit is not None:
            if int(self.limit) < 1:
                raise InputError(f"limit must be >= 1 (null = every pair), got {self.limit}")
            names = names[: int(self.limit)]
        check_inputs = getattr(self.dataset, "check_inputs", None)  # files a config names, up front
        if check_inputs is not None:
            check_inputs()
        return names


def _file_stamps(cfg: dict[str, Any]) -> dict[str, list[float]]:
    """Size and mtime of every existing file a config names (e.g. descriptor.model, found as the
    descriptors find it: from the cwd, else from the package)."""
    stamps = {}
    for key, value in cfg.items():
        found = find_file(value) if isinstance(value, str) and value else None
        if found is not None:
            st = found.stat()
            stamps[key] = [st.st_size, st.st_mtime]
    return stamps


def pair_rng(seed: int, index: int) -> np.random.Generator:
    """One independent stream per pair, so results do not depend on order or on the number of workers."""
    return np.random.default_rng([int(seed), int(index)])


def process_pair(comp: Components, index: int, name: str) -> PairOutcome:
    """Run one pair; any exception becomes a failed row with the error message (fault isolation)."""
    cfg = comp.cfg
    row = PairRow(index=index, pair=name, **comp.labels, ratio=run_ratio(cfg), seed=int(cfg.seed),
                  protocol=str(cfg.protocol))  # fmt: skip
    watch = Stopwatch()
    try:
        pair = comp.dataset.load(index)
        watch.lap("load")
        if "resolution_ms" in pair.meta:  # MAC's mesh resolution, computed inside the dataset's load
            watch.ms["resolution"] = pair.meta["resolution_ms"]
            watch.ms["load"] -= pair.meta["resolution_ms"]
        row.set(scene=pair.scene, family=pair.family)
        rng_seed = (cfg.seed, index)

        def run_step(
            p: Pair,
            descriptor: Any,
            sampler: Any,
            samples: Any,
            alike: bool,
            r: PairRow,
            w: Stopwatch | None = None,
        ) -> PairOutcome:
            return run_pair(
                p,
                descriptor,
                sampler,
                comp.backend,
                run_ratio(cfg),
                pair_rng(*rng_seed),
                protocol=str(cfg.protocol),
                graph_overrides=OmegaConf.to_container(cfg.graph) if cfg.get("graph") else None,
                mac_overrides=OmegaConf.to_container(cfg.mac) if cfg.get("mac") else None,
                row=r,
                cache=comp.cache if alike else None,
                cache_key=comp.cache.key({**comp._cache_parts, "index": index, "pair": name}),
                samples=samples,
                watch=w,
            )

        outcome = run_step(pair, comp.descriptor, comp.sampler, run_samples(cfg), True, row, watch)
        if run_escalates(cfg):
            outcome = escalate_run_pair(comp, outcome, pair, run_step, row)
        return outcome
    except Exception as exc:  # noqa: BLE001 - one bad pair must never stop the run
        if cfg.get("fail_fast", False):
            raise
        row.set(error=f"{type(exc).__name__}: {exc}", success=False)
        log.debug("pair %s failed:\n%s", name, traceback.format_exc())
        return PairOutcome(row=row.to_dict())


def escalate_run_pair(
    comp: Components, first: PairOutcome, pair: Pair, run_step: Any, row: PairRow
) -> PairOutcome:
    """escalate=auto: a pose that is not trusted runs the wider steps (run/escalate_pair.py); a step that
    fails is recorded as a failed step, never as the pair's failure."""
    if first.row.get("trusted"):
        first.row["escalation_step"] = "first"
        return first

    def step(p: Pair, descriptor: Any, sampler: Any, samples: Any, alike: bool) -> PairOutcome:
        r = dataclasses.replace(row, descriptor=str(getattr(descriptor, "name", row.descriptor)),
                                sampler=str(getattr(sampler, "name", row.sampler)), timings={})  # fmt: skip
        try:
            return run_step(p, descriptor, sampler, samples, alike, r)
        except Exception as exc:  # noqa: BLE001 - a wider step's failure is not the pair's
            r.set(error=f"{type(exc).__name__}: {exc}", success=False)
            return PairOutcome(row=r.to_dict())

    if comp.step_parts is None:
        comp.step_parts = StepParts(comp.cfg, comp.descriptor, comp.sampler)
    return escalate_pair(first, pair, comp.step_parts, step, float(comp.cfg.get("escalate_budget_s", 30.0)))


_WORKER: Components | None = None


def _init_worker(cfg_yaml: str) -> None:
    global _WORKER
    # The main process handles Ctrl-C (sent to the whole process group) and SIGTERM, and ends the workers;
    # a worker whose main process dies however it dies (SIGKILL) gets SIGTERM from the kernel.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    _die_with_parent()
    _WORKER = Components(OmegaConf.create(cfg_yaml))


def _die_with_parent() -> None:
    if sys.platform.startswith("linux"):
        import ctypes

        pr_set_pdeathsig = 1
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, int(signal.SIGTERM))


def _end_workers(pool: ProcessPoolExecutor) -> None:
    """Stop the workers now (an interrupt or an error): running pairs are abandoned, not waited for."""
    procs = list((getattr(pool, "_processes", None) or {}).values())  # terminate_workers() in 3.14
    for proc in procs:
        proc.terminate()
    for proc in procs:
        proc.join(10)
        if proc.is_alive():
            proc.kill()
            proc.join()
    # A worker ended half way through sending its result leaves part of a message in the result pipe, and
    # the executor's manager thread would wait for the rest forever (shutdown, and the interpreter's exit,
    # join it). With every worker gone, closing this process's own write end turns that wait into an EOF,
    # which the executor takes for a broken pool.
    writer = getattr(getattr(pool, "_result_queue", None), "_writer", None)
    if writer is not None:
        writer.close()
    pool.shutdown(wait=True)  # the executor's thread finds the workers gone and fails what is left


def _work(args: tuple[int, str]) -> PairOutcome:
    assert _WORKER is not None
    out = process_pair(_WORKER, *args)
    if out.pair is not None:  # clouds are large: send back the GT and thresholds, not the clouds
        out.pair = dataclasses.replace(out.pair, src_cloud=None, tgt_cloud=None, correspondences=None)
    return out


def _progress(total: int, enabled: bool):
    from tqdm import tqdm

    tqdm.monitor_interval = 0  # no monitor thread: a timer thread could take the run's Ctrl-C (interrupts.py)

    # disable=None: no bar where stderr is not a terminal (a log would get a carriage-return line a pair)
    return tqdm(total=total, disable=None if enabled else True, unit="pair", dynamic_ncols=True)


def run_experiment(
    cfg: DictConfig | dict[str, Any], run_dir: str | Path
) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Run every (remaining) pair, write results.{jsonl,csv,parquet}, summary.json and config.yaml."""
    cfg = cfg if isinstance(cfg, DictConfig) else OmegaConf.create(cfg)
    check_run_keys(cfg)
    resume = cfg.get("resume")
    # resume=auto: continue this run's own directory if it holds results (sweep members, whose directories
    # Hydra names; `resume` is left out of their names), else start it
    auto = is_auto(resume)
    run_dir = Path(run_dir) if auto or not resume else Path(resume)
    if resume and not auto:
        check_is_run(run_dir, resume)
    comp = Components(cfg)  # every group's options, before anything is written
    names = comp.names()
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        lock = RunLock(run_dir).acquire()
    except OSError as exc:
        raise InputError(f"cannot write in {run_dir}: {exc.strerror}: {exc.filename}") from None
    try:
        return _run_locked(cfg, run_dir, comp, names)
    finally:
        lock.release()


def _run_locked(
    cfg: DictConfig, run_dir: Path, comp: Components, names: list[str]
) -> tuple[pd.DataFrame, dict[str, Any]]:
    resume = cfg.get("resume")
    if not resume and (run_dir / "results.jsonl").exists():
        raise InputError(
            f"{run_dir} already holds results; pass resume={run_dir} (resume=auto in a sweep) to continue "
            "that run, or choose a new run directory"
        )
    if resume and (run_dir / CONFIG_NAME).is_file():
        check_same_experiment(run_dir, cfg)
    try:
        _save_config(cfg, run_dir)
        results = ResultsLog(run_dir)
        results.check_writable()
    except OSError as exc:  # a read-only directory, an unwritable results.jsonl: before any pair runs
        raise InputError(f"cannot write in {run_dir}: {exc.strerror}: {exc.filename}") from None
    done = results.done()
    todo = [(i, n) for i, n in enumerate(names) if n not in done]
    if done:
        log.info("resuming %s: %d of %d pairs already done", run_dir, len(names) - len(todo), len(names))
    if todo and getattr(comp.descriptor, "cost_note", None):
        log.warning("descriptor=%s: %s", comp.labels["descriptor"], comp.descriptor.cost_note)

    trackers = _make_trackers(cfg)
    plain_cfg = redact(OmegaConf.to_container(cfg, resolve=True))  # no tracker URI's password in any log
    for t in trackers:
        t.start(plain_cfg, run_dir, names)

    asked = workers = int(cfg.get("workers", 1))
    if workers > 1 and len(todo) < workers:
        log.info("workers=%d: %d pair(s) to run, so %d worker(s)", workers, len(todo), max(len(todo), 1))
        workers = max(len(todo), 1)
    cores = available_cores()
    if workers > cores:
        log.warning(
            "workers=%d is more than the %d core(s) this run may use: capped at %d (more processes than "
            "cores inflate every stage's time)", asked, cores, cores,
        )  # fmt: skip
        workers = cores
    members = concurrent_members(cores)
    oversubscribed = workers * members > cores
    if oversubscribed:
        log.warning(
            "%d sweep members run at once with %d worker(s) each on %d core(s): their rows' timings are "
            "taken oversubscribed (marked in the rows' `oversubscribed`)", members, workers, cores,
        )  # fmt: skip
    bar = _progress(len(todo), bool(cfg.get("progress", True)))
    n_ok = n_done = 0
    t_sum = 0.0
    interrupted = False

    def consume(out: PairOutcome) -> None:
        nonlocal n_ok, n_done, t_sum
        out.row.update(workers=workers, oversubscribed=oversubscribed)
        results.append(out.row)
        if out.row.get("trusted") is False and not out.row.get("error"):
            with bar.external_write_mode():  # a line of its own, not glued to the progress bar
                log.warning("%s", untrusted_line(out.row))
        if out.row.get("success") is None and not out.row.get("error") and out.row.get("pose"):
            write_pose(run_dir, out.row)  # no GT: the estimate is the result
        for t in trackers:
            try:
                t.log_pair(out)
            except Exception as exc:  # noqa: BLE001 - a tracker problem must not lose results
                log.warning("tracker %s failed on pair %s: %s", t.name, out.row.get("pair"), exc)
        n_done += 1
        n_ok += bool(out.row.get("success"))
        t_sum += float(out.row.get("t_total_ms") or 0.0)
        bar.set_postfix(RR=f"{n_ok / n_done:.2f}", ms_per_pair=f"{t_sum / n_done:.0f}")
        bar.update(1)

    try:
        if workers <= 1 or len(todo) <= 1:
            for i, n in todo:
                consume(process_pair(comp, i, n))
        else:
            cfg_yaml = OmegaConf.to_yaml(cfg, resolve=True)
            pool = ProcessPoolExecutor(max_workers=workers, initializer=_init_worker, initargs=(cfg_yaml,))
            try:
                # submitted one by one, not through pool.map: on an interrupt map cancels the futures still
                # queued, and the executor (3.11) then fails setting BrokenProcessPool on them once the
                # workers are ended, with a traceback from its thread
                futures = [pool.submit(_work, item) for item in todo]
                for future in futures:
                    consume(future.result())
            except BaseException:
                _end_workers(pool)
                raise
            pool.shutdown()
    except KeyboardInterrupt:
        interrupted = True
    finally:
        bar.close()
        if interrupted:  # after the bar is closed: a line of its own
            results.reload()
            n = len(results.rows)
            if n:
                saved = "1 pair is" if n == 1 else f"{n} pairs are"
                log.warning("interrupted: %s saved in %s", saved, run_dir)
            else:
                log.warning("interrupted before the first pair finished: nothing to resume")
        keep = bool(results.rows) or not interrupted  # an interrupted start-up leaves no tables of nothing
        table = results.write_tables() if keep else results.table()
        summary = summarize(table)
        summary["failures"] = failure_reasons(table)
        summary["unscored_pairs"] = unscored_pairs(table, run_dir)
        summary["untrusted_pairs"] = untrusted_pairs(table)
        summary.update(
            run_dir=str(run_dir),
            dataset=comp.labels["dataset"],
            families=sorted(table["family"].dropna().astype(str).unique()) or _config_family(cfg),
            descriptor=comp.labels["descriptor"],
            sampler=comp.labels["sampler"],
            backend=comp.labels["backend"],
            ratio=float(table["ratio"].dropna().iloc[0])
            if table["ratio"].dropna().nunique() == 1
            else run_ratio(cfg),
            samples=cfg.get("samples"),
            seed=int(cfg.seed),
            protocol=str(cfg.protocol),
            complete=len(table) == len(names) and not interrupted,
        )
        if keep:
            (run_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
        for t in trackers:
            try:
                t.finish(table, summary)
            except Exception as exc:  # noqa: BLE001
                log.warning("tracker %s failed to finish: %s", t.name, exc)
    if interrupted:
        exc = KeyboardInterrupt("run interrupted; its finished pairs are saved")
        exc.saved = True  # type: ignore[attr-defined] - the console has said what was saved
        exc.run_dir = str(run_dir)  # type: ignore[attr-defined] - where a resume continues it
        raise exc
    return table, summary


def concurrent_members(cores: int) -> int:
    """How many sweep members run at once beside this one (the joblib launcher's n_jobs; 1 otherwise)."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
            return 1
        n_jobs = OmegaConf.select(HydraConfig.get(), "launcher.n_jobs", default=None)
    except Exception:  # noqa: BLE001 - no Hydra context: a library call
        return 1
    if not isinstance(n_jobs, int) or n_jobs == 0:
        return 1
    return max(cores + 1 + n_jobs, 1) if n_jobs < 0 else n_jobs


def _save_config(cfg: DictConfig, run_dir: Path) -> None:
    path = run_dir / CONFIG_NAME
    if cfg.get("resume") and path.exists():
        path = run_dir / RESUMED_NAME
    OmegaConf.save(OmegaConf.create(redact(OmegaConf.to_container(cfg, resolve=False))), path)


def _make_trackers(cfg: DictConfig) -> list:
    node = cfg.get("tracker")
    if not node:
        return []
    trackers = []
    for key, sub in node.items():
        if not isinstance(sub, DictConfig) or "_target_" not in sub or not sub.get("enabled", True):
            continue
        kwargs = OmegaConf.to_container(sub, resolve=True)
        kwargs.pop("enabled", None)
        try:
            trackers.append(instantiate(kwargs))
        except Exception as exc:  # noqa: BLE001 - e.g. an optional package missing
            if isinstance(exc.__cause__ or exc, InputError):  # chosen explicitly and unusable: say so, stop
                raise
            log.warning("tracker %s disabled: %s", key, exc)
    return trackers


def failure_reasons(table: pd.DataFrame) -> dict[str, dict[str, Any]]:
    """The failed pairs grouped by their error message: {message: {count, pairs}}, most frequent first."""
    if "error" not in table or not len(table):
        return {}
    errors = table["error"].fillna("").astype(str)
    groups: dict[str, list[str]] = {}
    for pair, err in zip(table["pair"].astype(str), errors):
        if err:
            groups.setdefault(err.splitlines()[0][:300], []).append(pair)
    return {
        msg: {"count": len(p), "pairs": p} for msg, p in sorted(groups.items(), key=lambda kv: -len(kv[1]))
    }


def unscored_pairs(table: pd.DataFrame, run_dir: Path, most: int = 100) -> list[dict[str, Any]]:
    """The pairs registered without GT: their pose, its file and what a user can trust it by."""
    rows = table[table["success"].isna() & table["error"].eq("") & table["pose"].notna()]
    return [
        {"pair": str(r["pair"]), "pose": pose_matrix(r["pose"]).tolist(),
         "pose_file": str(pose_file(run_dir, str(r["pair"]))), "clique_size": _int(r.get("clique_size")),
         "pose_inliers": _int(r.get("pose_inliers")), "n_in": _int(r.get("n_in")),
         "trusted": None if pd.isna(r.get("trusted", np.nan)) else bool(r.get("trusted")),
         "confidence": None if pd.isna(r.get("confidence", np.nan)) else float(r.get("confidence"))}
        for _, r in rows.head(most).iterrows()
    ]  # fmt: skip


def untrusted_line(row: dict[str, Any]) -> str:
    return (
        f"UNTRUSTED POSE for {row.get('pair')}: it explains {row.get('pose_inliers')} of {row.get('n_in')} "
        f"correspondences, not clearly more than a wrong pose would (chance, the search's own pick, "
        f"structure or a rival pose; confidence {float(row.get('confidence') or 0):.3f} < "
        f"{TRUST_LEVEL}; docs/trust.md): do not use it"
    )


def untrusted_pairs(table: pd.DataFrame) -> list[str]:
    """The pairs whose pose the GT-free check does not trust (geometry.trust), failed pairs aside."""
    if "trusted" not in table or not len(table):
        return []
    errors = table["error"].fillna("").astype(str).ne("") if "error" in table else False
    untrusted = table["trusted"].astype("boolean").eq(False).fillna(False) & ~errors
    return [str(p) for p in table.loc[untrusted, "pair"]]


def _config_family(cfg: DictConfig) -> list[str]:
    family = OmegaConf.select(cfg, "dataset.family", default=None)
    return [str(family)] if family else []


def _int(v: Any) -> int | None:
    return None if v is None or pd.isna(v) else int(v)


def _stage_label(stage: str, summary: dict[str, Any]) -> str:
    cached = int(summary.get("describe_cached") or 0)
    if stage != "describe" or not cached:
        return stage
    n = summary.get("pairs", 0)
    return f"describe ({'all' if cached == n else f'{cached} of {n}'} from the cache: original times)"


def _finite(v: Any) -> bool:
    return isinstance(v, int | float) and math.isfinite(v)


def format_summary(summary: dict[str, Any]) -> str:
    """A short human-readable summary table."""
    s = summary
    nan = float("nan")
    stages = [st for st in PAIR_STAGES if _finite(s.get(f"median_{st}_ms"))]  # those the pairs went through
    scored, unscored = s.get("scored", s.get("pairs")), s.get("unscored", 0)
    if scored:
        rr = f"RR: {100 * s.get('RR', nan):.1f}%" + (f" (of the {scored} pairs with GT)" if unscored else "")
    else:
        rr = "RR: no ground truth: not scored"
    lines = [
        f"dataset={s.get('dataset')}"
        + (f" family={','.join(s['families'])}" if s.get("families") else "")
        + f" descriptor={s.get('descriptor')} sampler={s.get('sampler')} "
        + (f"samples={s['samples']} (ratio {s['ratio']})" if s.get("samples") else f"ratio={s.get('ratio')}")
        + f" backend={s.get('backend')} protocol={s.get('protocol')}"
        + "".join(f" {o}" for o in s.get("options") or ()),
        "  ".join(
            [f"pairs: {s.get('pairs')}"]
            + ([f"registered: {s.get('registered', 0)} of {scored}"] if scored else [])
            + ([f"no ground truth (not scored): {unscored}"] if unscored else [])
            + [f"failed with an error: {s.get('failed', 0)}"]
            + ([f"UNTRUSTED poses: {len(s['untrusted_pairs'])}"] if s.get("untrusted_pairs") else [])
        ),
        f"{rr}   RE: {s.get('RE_deg', nan):.2f} deg   TE: {s.get('TE_cm', nan):.2f} cm   "
        f"inlier ratio in/kept: {s.get('inlier_ratio_in', nan):.3f}/{s.get('inlier_ratio_kept', nan):.3f}",
        "median ms: "
        + "  ".join(f"{_stage_label(st, s)} {s.get(f'median_{st}_ms', nan):.1f}" for st in stages),
        "           "
        + (
            f"end to end {s['median_end_to_end_ms']:.1f} (every stage)  "
            if _finite(s.get("median_end_to_end_ms"))
            else ""
        )
        + f"sampling + MAC {s.get('median_total_ms', nan):.1f} (the papers' total)",
    ]
    for u in (s.get("unscored_pairs") or [])[:3]:
        untrusted = (
            f"UNTRUSTED POSE (confidence {u['confidence']:.3f}: no more correspondences than chance; "
            "do not use it); "
            if u.get("trusted") is False
            else ""
        )
        lines.append(
            f"{u['pair']}: no ground truth: not scored; {untrusted}clique of {u['clique_size']}, "
            f"{u['pose_inliers']} of "
            f"{u['n_in']} correspondences within the inlier threshold; estimated pose (source -> target, "
            f"{u['pose_file']}):"
        )
        lines += ["  " + " ".join(f"{v:12.6f}" for v in row) for row in u["pose"]]
    bad = s.get("untrusted_pairs") or []
    if bad:
        lines.append(
            f"WARNING: {len(bad)} UNTRUSTED pose(s), not clearly more correspondences than a wrong pose "
            f"would explain (docs/trust.md): {', '.join(bad[:5])}{' ...' if len(bad) > 5 else ''}"
        )
    for reason, info in (s.get("failures") or {}).items():
        pairs = ", ".join(info["pairs"][:3]) + (" ..." if info["count"] > 3 else "")
        lines.append(f"failed x{info['count']}: {reason} ({pairs})")
    return "\n".join(lines)
