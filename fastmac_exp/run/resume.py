"""What a resume may continue: exactly the experiment the run directory holds.

Every config key determines the rows except those listed in FREE (how a run is executed or watched, where
caches live) and `limit`, which may grow (a resume then adds the further pairs) but not shrink.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from fastmac_exp.errors import InputError

CONFIG_NAME = "config.yaml"
RESUMED_NAME = "config.resumed.yaml"  # the latest resume's config (its limit may have grown)
# keys (and key prefixes) that cannot change a row
FREE = ("workers", "progress", "tracker", "fail_fast", "resume", "cache", "dataset.cache_dir")
ABSENT = "<absent>"


def is_auto(resume: Any) -> bool:
    return resume is True or (isinstance(resume, str) and resume.lower() == "auto")


def _leaves(node: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(node, dict):
        out: dict[str, Any] = {}
        for k, v in node.items():
            out.update(_leaves(v, f"{prefix}{k}."))
        return out or {prefix[:-1]: {}}
    return {prefix[:-1]: node}


def _free(key: str) -> bool:
    return any(key == f or key.startswith(f + ".") for f in FREE)


def differences(saved: DictConfig, cfg: DictConfig) -> list[tuple[str, Any, Any]]:
    """(key, saved value, this run's value) for every row-determining key that differs."""
    old = _leaves(OmegaConf.to_container(saved, resolve=False))
    new = _leaves(OmegaConf.to_container(cfg, resolve=False))
    out = []
    # another option of a group (another _target_) is one difference, not one per key of the group
    swapped = [k[: -len("._target_")] for k in old if k.endswith("._target_") and old[k] != new.get(k)]
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key, ABSENT), new.get(key, ABSENT)
        if _free(key) or a == b or any(key.startswith(g + ".") and key != g + "._target_" for g in swapped):
            continue
        if key == "limit" and (b is None or (a is not None and b != ABSENT and a != ABSENT and b > a)):
            continue
        out.append((key, a, b))
    return out


def check_same_experiment(run_dir: Path, cfg: DictConfig) -> None:
    """Refuse (InputError) to resume `run_dir` with a config that would add rows of another experiment."""
    latest = run_dir / RESUMED_NAME if (run_dir / RESUMED_NAME).is_file() else run_dir / CONFIG_NAME
    diff = differences(OmegaConf.load(latest), cfg)
    if not diff:
        return
    lines = "\n".join(
        f"  {k}: {a!r} (saved) vs {b!r} (this command)"
        + (" - a resume may raise limit, not lower it" if k == "limit" else "")
        for k, a, b in diff
    )
    raise InputError(
        f"resume={run_dir}: that run is another experiment; these keys differ:\n{lines}\n"
        f"resume with the saved run's overrides (see {latest}), or drop resume= to start a "
        "new run"
    )


def check_is_run(path: Path, resume: Any) -> None:
    if not path.is_dir():
        raise InputError(f"resume={resume}: no such run directory ({path.resolve()})")
    if not (path / CONFIG_NAME).is_file():
        raise InputError(
            f"resume={resume}: {path.resolve()} is no run directory (it has no {CONFIG_NAME}); pass a "
            "directory a run wrote, e.g. outputs/runs/<run>"
        )


def latest_run(runs_dir: Path, cfg: DictConfig) -> Path | None:
    """The most recently written run under `runs_dir` whose experiment is exactly `cfg`'s."""
    found = []
    if not runs_dir.is_dir():
        return None
    for d in runs_dir.iterdir():
        conf = d / CONFIG_NAME
        if not conf.is_file():
            continue
        try:
            same = not differences(OmegaConf.load(conf), cfg)
        except Exception:  # noqa: BLE001 - an unreadable config is no candidate
            continue
        if same:
            stamp = max(p.stat().st_mtime for p in (conf, d / "results.jsonl") if p.exists())
            found.append((stamp, d.name, d))
    return max(found)[2] if found else None
