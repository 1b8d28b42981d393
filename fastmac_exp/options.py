"""The one registry of a run's options, for the command line and the library alike: the config groups of
conf/ (what `python run.py --help` lists as GROUP=OPTION and `--cfg job` shows as keys).

The CLI composes them through Hydra; `fastmac_exp.register()` composes the same files here, so a group's
option (conf/sampler/highpass.yaml's `scores`, conf/backend/turboreg.yaml's `num_pivot`, ...) is reachable
from Python by the same name, and an option added to a config file is reachable from both at once.
"""

from __future__ import annotations

import copy
import difflib
from functools import lru_cache
from typing import Any

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import ConfigAttributeError, ConfigKeyError

from fastmac_exp.errors import InputError
from fastmac_exp.resources import config_dir

# The groups whose options a library call may set, and the run-level tables of MAC's parameters. The
# order is the order in which a bare name is looked up (a name in two of them must be qualified).
GROUPS = ("sampler", "backend", "descriptor")
TABLES = ("mac", "graph")


def choices(group: str) -> list[str]:
    """The options of a config group: its conf/<group>/*.yaml files."""
    return sorted(p.stem for p in (config_dir() / group).glob("*.yaml"))


@lru_cache(maxsize=32)
def _composed(picks: tuple[tuple[str, str], ...]) -> DictConfig:
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            return compose("config", overrides=[f"{g}={o}" for g, o in picks])
    finally:
        GlobalHydra.instance().clear()


def compose_run(picks: dict[str, str]) -> DictConfig:
    """The run config the CLI would compose for these group choices (a copy the caller may change)."""
    for group, option in picks.items():
        known = choices(group)
        if option not in known:
            close = difflib.get_close_matches(str(option), known, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise InputError(f"unknown {group} {option!r}{hint} (choose one of {', '.join(known)})")
    return copy.deepcopy(_composed(tuple(sorted(picks.items()))))


def option_names(cfg: DictConfig, groups: tuple[str, ...]) -> dict[str, list[str]]:
    """Bare name -> the full keys it may mean, over the given groups' options and MAC's tables (one level
    of nesting too: the sampler's `estimate.anchors` is `anchors`)."""
    names: dict[str, list[str]] = {}
    for part in (*groups, *TABLES):
        node = cfg.get(part)
        if not isinstance(node, DictConfig):
            continue
        for key in node:
            if str(key).startswith("_"):
                continue
            names.setdefault(str(key), []).append(f"{part}.{key}")
            if isinstance(node[key], DictConfig):
                for sub in node[key]:
                    names.setdefault(str(sub), []).append(f"{part}.{key}.{sub}")
    return names


def apply_options(cfg: DictConfig, options: dict[str, Any], groups: tuple[str, ...]) -> None:
    """Set each option on `cfg` by its bare name (`scores`) or its full key as on the command line
    (`sampler.scores`); an unknown or ambiguous name is an InputError that says what to write."""
    names = option_names(cfg, groups)
    missing = object()
    for name, value in options.items():
        if "." in name:
            if (
                name.split(".")[0] not in (*groups, *TABLES)
                or OmegaConf.select(cfg, name, default=missing) is missing
            ):
                raise InputError(f"register(): unknown option {name!r}{_did_you_mean(name, names)}")
            path = name
        else:
            paths = names.get(name, [])
            if not paths:
                raise InputError(f"register(): unknown option {name!r}{_did_you_mean(name, names)}")
            if len(paths) > 1:
                alts = " or ".join(f"**{{{p!r}: ...}}" for p in paths)
                raise InputError(f"register(): {name!r} is an option of several parts; write {alts}")
            path = paths[0]
        if isinstance(value, dict):
            value = OmegaConf.create(value)
        try:
            OmegaConf.update(cfg, path, value, merge=True)
        except (ConfigKeyError, ConfigAttributeError) as exc:  # a dict value with a key the part lacks
            raise InputError(f"register(): unknown option {exc.full_key!r} (in {name}=)") from None


def _did_you_mean(name: str, names: dict[str, list[str]]) -> str:
    known = list(names) + [p for paths in names.values() for p in paths]
    close = difflib.get_close_matches(name, known, n=1, cutoff=0.6)
    return f"; did you mean {close[0]!r}?" if close else f"; known: {', '.join(sorted(names))}"


def instantiate_part(node: DictConfig) -> Any:
    """The part a config node names; the project's own error behind Hydra's InstantiationException is
    raised as itself (what the library caller can catch and what says what is wrong)."""
    from hydra.utils import instantiate

    from fastmac_exp.errors import FastMacError

    try:
        return instantiate(node)
    except Exception as exc:
        cause: BaseException | None = exc
        for _ in range(10):
            if cause is None or isinstance(cause, FastMacError):
                break
            cause = cause.__cause__ or cause.__context__
        if isinstance(cause, FastMacError):
            raise cause from None
        raise
