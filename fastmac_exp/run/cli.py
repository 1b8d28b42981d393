"""The command line: the Hydra app behind `python run.py ...`, `python -m fastmac_exp ...` and the
`fastmac-exp` console script (all three the same), plus the checks that turn Hydra's raw errors for a
missing launcher plugin or a mistyped key into a message that says what to do."""

from __future__ import annotations

import difflib
import logging
import shutil
import signal
import sys
import time
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from fastmac_exp.errors import InputError, own_error
from fastmac_exp.interrupts import interrupts_blocked
from fastmac_exp.resources import config_dir
from fastmac_exp.run.resume import is_auto, latest_run
from fastmac_exp.run.runlock import RunLocked
from fastmac_exp.samplers import ratio_used

log = logging.getLogger("fastmac_exp")

# hydra/launcher option -> the module it needs; all of them come with the cluster extra
CLUSTER_INSTALL = "pip install -e '.[cluster]' -c constraints.txt"
LAUNCHER_PLUGINS = {
    "slurm": "hydra_plugins.hydra_submitit_launcher",
    "submitit_slurm": "hydra_plugins.hydra_submitit_launcher",
    "submitit_local": "hydra_plugins.hydra_submitit_launcher",
    "ray_cluster": "ray",
}
# hydra-ray-launcher's own option: the package cannot be installed beside this project's joblib
RAY_PLUGIN_HINT = (
    "hydra/launcher=ray is hydra-ray-launcher's, which cannot be installed with this project: every release "
    "requires cloudpickle<3 and joblib 1.6 (hydra-joblib-launcher) requires cloudpickle>=3.0; use "
    f"hydra/launcher=ray_cluster (Ray itself, from {CLUSTER_INSTALL}; docs/cluster.md)"
)


def check_launcher(argv: list[str]) -> str | None:
    """The install hint for a `hydra/launcher=NAME` override whose plugin is missing, else None (Hydra's
    own message, "Could not load 'hydra/launcher/submitit_slurm'", names neither plugin nor package)."""
    import importlib.util

    for arg in argv:
        key, _, name = arg.lstrip("+~").partition("=")
        if key != "hydra/launcher":
            continue
        if name == "ray" and importlib.util.find_spec("hydra_plugins.hydra_ray_launcher") is None:
            return RAY_PLUGIN_HINT
        if name not in LAUNCHER_PLUGINS:
            continue
        module = LAUNCHER_PLUGINS[name]
        try:
            found = importlib.util.find_spec(module) is not None
        except ModuleNotFoundError:
            found = False
        if not found:
            return (f"hydra/launcher={name} needs {module.split('.')[-1]!r}, which is not installed: "
                    f"{CLUSTER_INSTALL} (docs/cluster.md)")  # fmt: skip
    return None


def run_amount(sampler: str, ratio: float, samples: int | None = None) -> str:
    """What a run directory's name says the sampler keeps: the ratio used (sampler=none keeps everything),
    or `k<samples>` for a count."""
    used = ratio_used(sampler, ratio)
    return f"k{samples}" if samples is not None and used != 1.0 else str(used)


OmegaConf.register_new_resolver("run_ratio", run_amount, replace=True)


def run_dataset(choice: str, family: str | None) -> str:
    """The dataset in a run directory's name, with its family where the name does not say it."""
    return f"{choice}-{family}" if family and family != choice else choice


OmegaConf.register_new_resolver("run_dataset", run_dataset, replace=True)


def run_descriptor(choice: str, alias: str | None, model: str | None) -> str:
    """The descriptor in a run directory's name: an alias option (descriptor=fcgf) is named by the model it
    runs, as its rows are (fcgf_lite)."""
    return Path(str(model)).stem if alias and model else choice


OmegaConf.register_new_resolver("run_descriptor", run_descriptor, replace=True)

# the parts' own keys: an override of one changes the results, so the run's name and header carry it
PART_KEYS = ("descriptor.", "sampler.", "backend.", "graph.", "mac.")
NAMED_ELSEWHERE = ("descriptor.model", "descriptor.alias")  # run_descriptor names the model


def part_overrides(overrides) -> list[str]:
    """The command line's overrides of a part's keys (sampler.scores=exact, descriptor.impl=open3d, ...)."""
    out = []
    for o in overrides or ():
        key, sep, value = str(o).lstrip("+~").partition("=")
        if sep and key.startswith(PART_KEYS) and key not in NAMED_ELSEWHERE:
            out.append(f"{key}={value}")
    return out


def run_options(overrides) -> str:
    """The part overrides in a run directory's name: _scores=exact_impl=open3d ("" for none)."""
    return "".join("_" + o.split(".", 1)[1].replace("/", "-") for o in part_overrides(overrides))


OmegaConf.register_new_resolver("run_options", run_options, replace=True)
OmegaConf.register_new_resolver("run_backend", lambda b: "" if b == "cpp" else f"_{b}", replace=True)
# What Hydra, the experiment and its trackers write before the first pair: a directory holding nothing
# else is no run.
EMPTY_RUN = {".hydra", "run.log", "config.yaml", "config.resumed.yaml", "wandb", "recording.rrd", "rerun"}


def latest_or_refuse(cfg: DictConfig, run_dir: Path) -> Path:
    """resume=auto in a single run: the latest run of exactly this config beside this run's directory."""
    found = latest_run(run_dir.parent, cfg)
    if found is None:
        raise InputError(
            f"resume=auto: no earlier run of this exact config in {run_dir.parent.resolve()}; drop resume= "
            "to start one, or pass resume=<run dir>"
        )
    log.info("resume=auto: continuing %s", found)
    return found


def drop_if_empty(run_dir: Path, keep_log_in: Path | None = None) -> None:
    """Remove a single run's directory that holds no results (a config error, or a resume= run whose
    results went to the resumed directory; its log moves there first)."""
    if not run_dir.is_dir() or not set(p.name for p in run_dir.iterdir()) <= EMPTY_RUN:
        return
    if keep_log_in is not None and (run_dir / "run.log").exists():
        shutil.move(
            str(run_dir / "run.log"), keep_log_in / f"run.resumed-{time.strftime('%Y%m%d-%H%M%S')}.log"
        )
    shutil.rmtree(run_dir, ignore_errors=True)


@hydra.main(version_base="1.3", config_path=str(config_dir()), config_name="config")
def main(cfg: DictConfig) -> float:
    from fastmac_exp.run.experiment import format_summary, run_experiment

    hydra_cfg = HydraConfig.get()
    run_dir = Path(hydra_cfg.runtime.output_dir)
    single = hydra_cfg.mode != RunMode.MULTIRUN
    try:
        if single and is_auto(cfg.get("resume")):
            cfg.resume = str(latest_or_refuse(cfg, run_dir))
        _, summary = run_experiment(cfg, run_dir)
    except KeyboardInterrupt as exc:
        if not getattr(exc, "saved", False):
            log.warning("interrupted before the run started: nothing was written")
        elif getattr(exc, "run_dir", None):
            log.warning("continue it with:\n  %s", continue_command(exc.run_dir, single, hydra_cfg))
        if single:
            drop_if_empty(run_dir)
        sys.exit(130)
    except Exception as exc:  # noqa: BLE001 - our own errors, even wrapped by Hydra's instantiate, exit cleanly
        ours = own_error(exc)
        if ours is None:
            raise
        log.error("%s", ours)
        if single and not isinstance(ours, RunLocked):  # a locked directory is another run's
            drop_if_empty(run_dir)
        sys.exit(2)
    # One write: parallel sweep members (joblib processes) share the console, and a pipe keeps a write of
    # up to PIPE_BUF (4 KiB) bytes whole, so their summaries do not interleave.
    text = (
        format_summary({**summary, "options": part_overrides(hydra_cfg.overrides.task)})
        + f"\nresults: {summary['run_dir']}/results.parquet (and .csv, summary.json)\n"
    )
    sys.stdout.flush()
    sys.stdout.write(text)
    sys.stdout.flush()
    append_to_log(text)
    if single and Path(summary["run_dir"]).resolve() != run_dir.resolve():
        drop_if_empty(run_dir, keep_log_in=Path(summary["run_dir"]))
    if summary.get("pairs", 0) and summary.get("failed", 0) == summary["pairs"]:
        log.error("every pair failed (reasons above)")
        # A single run fails; a sweep member is a measurement (e.g. random sampling at 1 % registers
        # nothing) and the sweep goes on.
        if single:
            sys.exit(1)
    return float(summary.get("RR", 0.0))


def append_to_log(text: str) -> None:
    """The console's summary into run.log as well: Hydra's file handler gets the log records only."""
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):
            handler.flush()
            with open(handler.baseFilename, "a", encoding="utf-8") as f:
                f.write(text)


def program() -> str:
    """How this app was started, as a user would type it again."""
    argv0 = sys.argv[0]
    if Path(argv0).name == "run.py":
        return f"python {argv0}"
    if Path(argv0).name == "__main__.py" and Path(argv0).parent.name == "fastmac_exp":
        return "python -m fastmac_exp"
    return Path(argv0).name


def continue_command(run_dir: str, single: bool, hydra_cfg) -> str:
    """The command that continues an interrupted run (its own overrides and resume=DIR) or sweep (its
    command line with resume=auto into the same sweep directory)."""
    import shlex

    def not_resume(o: str) -> bool:
        return o.lstrip("+~").split("=", 1)[0] != "resume"

    if single:
        args = [o for o in hydra_cfg.overrides.task if not_resume(o)] + [f"resume={run_dir}"]
    else:
        args = [o for o in sys.argv[1:] if not_resume(o)] + ["resume=auto"]
        if not any(o.startswith("hydra.sweep.dir=") for o in args):
            args.append(f"hydra.sweep.dir={hydra_cfg.sweep.dir}")
    return " ".join([program(), *(shlex.quote(a) for a in args)])


def key_value(overrides: list[str], key: str) -> str:
    return next((o.split("=", 1)[1] for o in overrides if o.split("=", 1)[0] == key), "N")


def check_keys(argv: list[str]) -> str | None:
    """Our message for an override of a key that does not exist (Hydra's suggests adding it with `+`, which
    is never what a typo needs), or a `+key=` that adds a key no part reads (`+` is for the groups, as in
    +experiment=...), with the closest existing key; None when the overrides compose."""
    overrides = [a for a in argv if not a.startswith(("-", "hydra.", "hydra/"))]  # Hydra's own: its checks
    assigned = [a for a in overrides if "=" in a and not a.startswith(("++", "~"))]
    added = [a.split("=")[0][1:] for a in assigned if a.startswith("+")]
    added = [k for k in added if not (config_dir() / k.replace(".", "/")).is_dir()]  # +group=option
    if not assigned:
        return None
    import re

    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    conf = str(config_dir())

    def composed(ovr: list[str]) -> DictConfig:
        GlobalHydra.instance().clear()
        try:
            with initialize_config_dir(config_dir=conf, version_base="1.3"):
                return compose("config", overrides=ovr)
        finally:
            GlobalHydra.instance().clear()

    def base(o: str) -> str:
        return o.split("=")[0].lstrip("+")

    key = None
    try:
        composed(overrides)
    except Exception as exc:  # noqa: BLE001 - anything but a missing key or option is left to Hydra's report
        missing_option = re.search(r"Could not find '([^'/]+)/([^']+)'", str(exc))
        if missing_option:
            return unknown_option(*missing_option.groups())
        m = re.search(r"Could not override '([^']+)'", str(exc))
        if not m:
            return None
        key = m.group(1)
    group_value = next((o for o in overrides if base(o) == key and not o.startswith("+")), None)
    if key and group_value and (config_dir() / key).is_dir():  # a group outside the defaults list
        return (
            f"{key} is a config group that the defaults do not include: add it with a +, "
            f"+{group_value} (python run.py --help lists the groups)"
        )
    if key == "dataset.limit":
        n = key_value(overrides, key)
        return f"dataset.limit is a run key: write limit={n} (the first N pairs of any dataset)"
    try:
        cfg = composed([o for o in overrides if base(o) != key and base(o) not in added])
    except Exception:  # noqa: BLE001
        return None
    if key is None:
        missing = object()
        key = next((k for k in added if OmegaConf.select(cfg, k, default=missing) is missing), None)
        if key is None:
            return None
    known = []

    def walk(node, prefix: str) -> None:
        for k in node:
            path = f"{prefix}{k}"
            known.append(path)
            if OmegaConf.is_dict(node[k]):
                walk(node[k], path + ".")

    walk(cfg, "")
    close = difflib.get_close_matches(key, known, n=1, cutoff=0.6)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    return f"unknown config key {key!r}{hint} (python run.py --cfg job shows every key)"


def unknown_option(group: str, option: str) -> str:
    """One line for GROUP=OPTION with no conf/GROUP/OPTION.yaml (Hydra's lists every option on its own
    line, below its search path)."""
    from fastmac_exp.options import choices

    known = choices(group)
    close = [k for k in known if k.startswith(option)] or difflib.get_close_matches(option, known, n=1)
    hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
    return f"unknown {group} {option!r}{hint} (choose one of {', '.join(known)})"


def check_output_dir(argv: list[str]) -> str | None:
    """Our message where the run (or sweep) directory cannot be made (Hydra's is a raw traceback): its
    nearest existing ancestor is a file, or not writable."""
    import os

    key = "hydra.sweep.dir" if {"-m", "--multirun"} & set(argv) else "hydra.run.dir"
    given = next((a.split("=", 1)[1] for a in argv if a.split("=", 1)[0] == key), None)
    target = Path(given.strip("'\"") if given and "${" not in given else "outputs")
    probe = target
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if probe.is_dir() and os.access(probe, os.W_OK):
        return None
    why = "is a file" if probe.exists() and not probe.is_dir() else "is not writable"
    return f"cannot write the run directory {target}: {probe.resolve()} {why} (set {key}=<a writable path>)"


def run() -> None:
    """The entry point: `data ...` (fastmac_exp.data.cli), else our checks first (they exit 2 with a
    message), then the Hydra app."""
    if sys.argv[1:2] == ["data"]:
        from fastmac_exp.data.cli import main as data_main

        sys.exit(data_main(sys.argv[2:]))
    if "--version" in sys.argv[1:]:  # Hydra's own flag would print Hydra's version
        from fastmac_exp import __version__

        print(f"fastmac-exp {__version__} (Hydra {hydra.__version__})")
        sys.exit(0)
    hint = check_launcher(sys.argv[1:]) or check_output_dir(sys.argv[1:]) or check_keys(sys.argv[1:])
    if not hint and {"-m", "--multirun"} & set(sys.argv[1:]):
        from fastmac_exp.run.sweep_check import check_members

        hint = check_members(sys.argv[1:])
    if hint:
        log.addHandler(logging.StreamHandler())
        log.error(hint)
        sys.exit(2)
    signal.signal(signal.SIGTERM, _interrupt)  # a SIGTERM ends a run as Ctrl-C does
    with interrupts_blocked():  # scipy's OpenBLAS starts its threads as it loads (fastmac_exp.interrupts)
        import scipy.special  # noqa: F401  (every registration's trust check uses it)
    try:
        main()
    except KeyboardInterrupt:  # inside Hydra's own start-up, before main's handler
        sys.exit(130)


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


if __name__ == "__main__":
    run()
