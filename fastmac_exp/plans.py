"""register()'s configurations, composed, checked and built once per set of options.

A call's configuration is its group choices (sampler, backend, descriptor), its options and its seed.
Composing it (Hydra's compose, a deep copy, the options applied) and building its parts (Hydra's instantiate)
cost ~15 ms on 2 cores, as much as FastMAC and MAC on 5,000 correspondences, so a caller who registers in a
loop pays it once: a plan is kept for each set of options, its config read-only. The key is taken from the
options as given (a dict value by its items), and the config from a copy of them, so a later change to the
caller's dict, or another call's options, never reaches a kept plan. The parts are those a run builds once
for all its pairs: their state is their constructor's arguments.
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

from omegaconf import DictConfig, OmegaConf

from fastmac_exp.options import apply_options, compose_run, instantiate_part
from fastmac_exp.params import MacParams, mac_params_for
from fastmac_exp.run.checks import check_devices

PLANS_KEPT = 64  # sets of options a process keeps (an escalation uses up to 7 a call)


@dataclass
class Plan:
    cfg: DictConfig  # read-only
    graph_overrides: dict[str, Any]
    mac_overrides: dict[str, Any]
    _parts: dict[str, Any] = field(default_factory=dict)
    _params: dict[tuple, MacParams] = field(default_factory=dict)

    def part(self, group: str) -> Any:
        """The config's sampler, backend or descriptor, built on first use."""
        if group not in self._parts:
            self._parts[group] = instantiate_part(self.cfg[group])
        return self._parts[group]

    def params(self, family: str, graph_key: str, resolution: float) -> MacParams:
        key = (family, graph_key, float(resolution))
        if key not in self._params:
            self._params[key] = mac_params_for(family, graph_key, resolution, self.graph_overrides,
                                               self.mac_overrides)  # fmt: skip
        return self._params[key]


def plan_for(picks: dict[str, str], options: dict[str, Any], seed: int) -> Plan:
    """The plan of these group choices, options and seed: kept where the options have a key (values of
    plain types, dicts and sequences of them), else composed for this call alone."""
    try:
        key = options_key(options)
    except TypeError:  # a value that has no key (an object): not kept
        return _compose(tuple(picks.items()), options, int(seed))
    return _kept(tuple(picks.items()), key, int(seed))


def options_key(value: Any) -> Hashable:
    """A hashable key of an options value that tells apart what a config tells apart (1, 1.0 and True;
    a dict and a list); TypeError for a value that has none."""
    if isinstance(value, dict) or OmegaConf.is_dict(value):
        return ("dict", tuple(sorted((str(k), options_key(v)) for k, v in value.items())))
    if isinstance(value, (list, tuple)) or OmegaConf.is_list(value):
        return ("list", tuple(options_key(v) for v in value))
    if value is None or isinstance(value, (bool, int, float, str)):
        return (type(value).__name__, value)
    raise TypeError(f"no key for {type(value).__name__}")


@lru_cache(maxsize=PLANS_KEPT)
def _kept(picks: tuple[tuple[str, str], ...], key: Hashable, seed: int) -> Plan:
    return _compose(picks, _options_of(key), seed)


def _options_of(key: Hashable) -> Any:
    """The options back from their key (a fresh copy: nothing of the caller's is kept)."""
    kind, value = key
    if kind == "dict":
        return {k: _options_of(v) for k, v in value}
    if kind == "list":
        return [_options_of(v) for v in value]
    return value


def _compose(picks: tuple[tuple[str, str], ...], options: dict[str, Any], seed: int) -> Plan:
    cfg = compose_run(dict(picks))
    cfg.seed = seed
    apply_options(cfg, options, tuple(g for g, _ in picks))
    check_devices(cfg)
    OmegaConf.set_readonly(cfg, True)
    graph = OmegaConf.to_container(cfg.graph, resolve=True)
    mac = OmegaConf.to_container(cfg.mac, resolve=True)
    return Plan(cfg, graph, mac)
