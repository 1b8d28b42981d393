"""A sweep's members, each checked before the first one starts: a bad value in one member is one line and
exit 2 before anything runs, not a failure after the members before it ran (Hydra composes each member only
when it launches it)."""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from fastmac_exp.errors import own_error
from fastmac_exp.resources import config_dir

LOCAL_LAUNCHERS = ("basic", "local", "joblib")


def sweep_members(argv: list[str]) -> list[list[str]]:
    """Each member's overrides, as Hydra's basic sweeper expands them: the config's hydra.sweeper.params
    (a +experiment= preset's sweep) and then the command line's, as a product."""
    from hydra import compose, initialize_config_dir
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser

    overrides = [a for a in argv if not a.startswith("-")]
    parser = OverridesParser.create()
    parsed = parser.parse_overrides(overrides)
    fixed = [o.input_line for o in parsed if not o.is_sweep_override()]
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            base = compose("config", overrides=fixed, return_hydra_config=True)
    finally:
        GlobalHydra.instance().clear()
    params = [f"{k}={v}" for k, v in (base.hydra.sweeper.get("params") or {}).items()]
    batches = BasicSweeper.split_arguments(parser.parse_overrides(params + overrides), None)
    return [job for batch in batches for job in batch]


def check_members(argv: list[str]) -> str | None:
    """The first member whose config a run would refuse, as one line naming the member; None if all pass
    (or the sweep does not compose: Hydra's own checks and check_keys report that)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from fastmac_exp.run.checks import check_run_keys
    from fastmac_exp.run.experiment import Components

    try:
        members = sweep_members(argv)
    except Exception:  # noqa: BLE001 - a sweep that does not parse or compose is Hydra's to report
        return None
    if len(members) < 2:
        return None
    # a cluster launcher's members read their files where they run: here only the run keys are checked
    launcher = next((a.split("=", 1)[1] for a in argv if a.startswith("hydra/launcher=")), "basic")
    local = launcher in LOCAL_LAUNCHERS
    checked: set[str] = set()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            for num, job in enumerate(members):
                own = [o for o in job if not o.lstrip("+~").startswith("hydra")]
                try:
                    cfg = compose("config", overrides=own)
                    check_run_keys(cfg)
                    key = _parts_key(cfg)
                    if local and key not in checked:  # each distinct set of parts is built once
                        Components(cfg).names()
                        checked.add(key)
                except Exception as exc:  # noqa: BLE001 - only our own errors are a member's mistake
                    ours = own_error(exc)
                    if ours is None:
                        return None
                    shown = ",".join(o for o in own if o in _swept(members))
                    return f"sweep member {num} ({shown or ' '.join(own)}): {ours}; no member was started"
    finally:
        GlobalHydra.instance().clear()
    return None


def _swept(members: list[list[str]]) -> set[str]:
    """The overrides that differ between members (what names a member)."""
    every = set(members[0]).intersection(*map(set, members[1:]))
    return {o for job in members for o in job if o not in every}


def _parts_key(cfg: DictConfig) -> str:
    parts = {k: cfg.get(k) for k in ("dataset", "descriptor", "sampler", "backend", "limit", "cache")}
    return OmegaConf.to_yaml(OmegaConf.create(parts))
