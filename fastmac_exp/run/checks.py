"""The run's own keys, checked before anything is created: a bad value is one InputError naming the key,
not a coercion, a traceback or a failure of every pair."""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, OmegaConf

from fastmac_exp.errors import InputError
from fastmac_exp.params import mac_params_for
from fastmac_exp.pipeline import PROTOCOLS
from fastmac_exp.samplers.keep_size import is_auto


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def check_run_keys(cfg: DictConfig) -> None:
    if cfg.get("protocol") not in PROTOCOLS:
        raise InputError(f"protocol must be one of {PROTOCOLS}, got {cfg.get('protocol')!r}")
    ratio = cfg.get("ratio")
    if not is_auto(ratio) and (
        isinstance(ratio, bool) or not isinstance(ratio, int | float) or not 0.0 < float(ratio) <= 1.0
    ):
        raise InputError(f"ratio must be a number in (0, 1] or auto, got {ratio!r} (config key: ratio)")
    samples = cfg.get("samples")
    if samples is not None and not is_auto(samples) and (not _is_int(samples) or samples < 3):
        raise InputError(
            f"samples must be null, auto or an integer >= 3, got {samples!r} (config key: samples)"
        )
    seed = cfg.get("seed")
    if not _is_int(seed) or seed < 0:
        raise InputError(f"seed must be a whole number >= 0, got {seed!r} (config key: seed)")
    limit = cfg.get("limit")
    if limit is not None and (not _is_int(limit) or limit < 1):
        raise InputError(f"limit must be >= 1 (null = every pair), got {limit!r} (config key: limit)")
    workers = cfg.get("workers", 1)
    if not _is_int(workers) or workers < 1:
        raise InputError(f"workers must be a whole number >= 1, got {workers!r} (config key: workers)")
    run_escalates(cfg)  # auto or off
    budget = cfg.get("escalate_budget_s", 30)
    if isinstance(budget, bool) or not isinstance(budget, int | float) or not budget >= 0:
        raise InputError(f"escalate_budget_s must be a number of seconds >= 0, got {budget!r}")
    check_devices(cfg)
    graph = OmegaConf.to_container(cfg.graph) if cfg.get("graph") else None
    mac = OmegaConf.to_container(cfg.mac) if cfg.get("mac") else None
    try:  # the overrides' own rules; the family's rules are checked again per pair
        mac_params_for("3dmatch", "fpfh", graph_overrides=graph, mac_overrides=mac)
    except TypeError as exc:
        raise InputError(f"graph/mac override of the wrong type: {exc}") from None


def run_samples(cfg: DictConfig) -> int | str | None:
    """The run's sample count: "auto" (samples=auto or ratio=auto: the keep sized from the scores), an
    integer, or None (ratio's fraction)."""
    samples = cfg.get("samples")
    if is_auto(samples) or (samples is None and is_auto(cfg.get("ratio"))):
        return "auto"
    return None if samples is None else int(samples)


def run_escalates(cfg: DictConfig) -> bool:
    """escalate=auto (a pose that is not trusted tries the wider steps) or off (YAML may read off as
    false)."""
    value = cfg.get("escalate", "off")
    if value is False or value is None or str(value) == "off":
        return False
    if str(value) == "auto":
        return True
    raise InputError(f"escalate must be auto or off, got {value!r} (config key: escalate)")


def run_ratio(cfg: DictConfig) -> float:
    """The run's ratio as a number (NaN for ratio=auto: each pair's row says what its keep was)."""
    return float("nan") if is_auto(cfg.get("ratio")) else float(cfg.ratio)


def check_devices(cfg: DictConfig) -> None:
    """sampler.device and the descriptor's execution_providers name something this machine has: a GPU that
    is not there is one InputError before anything is created, not a silent CPU run or a failure per pair."""
    device = OmegaConf.select(cfg, "sampler.device", default=None)
    if device is not None and str(device) != "cpu":
        device = str(device)
        if not (device == "cuda" or (device.startswith("cuda:") and device[5:].isdigit())):
            raise InputError(
                f"sampler.device must be cpu or cuda (cuda:N for the N-th GPU), got {device!r} "
                "(config key: sampler.device)"
            )
        import torch

        if not torch.cuda.is_available():
            raise InputError(
                f"sampler.device={device}, but torch {torch.__version__} sees no CUDA device on this "
                "machine; use sampler.device=cpu"
            )
        impl = OmegaConf.select(cfg, "sampler.impl", default="auto")
        if impl != "torch":  # auto picks the C++ core wherever it is built, on the CPU
            raise InputError(
                f"sampler.device={device} is the torch engine's: add sampler.impl=torch (got {impl!r})"
            )
    providers = OmegaConf.select(cfg, "descriptor.execution_providers", default=None)
    if providers is not None and providers != "auto":
        check_providers(providers)


def check_providers(providers: Any) -> None:
    """Every name of descriptor.execution_providers is an alias (cpu, cuda, tensorrt) or one of onnxruntime's
    provider names (one this onnxruntime lacks is dropped at run time with a notice: the CPU fallback)."""
    import onnxruntime as ort

    from fastmac_exp.descriptors.onnx_descriptor import PROVIDER_ALIASES

    names = [providers] if isinstance(providers, str) else list(providers)
    known = set(ort.get_all_providers())
    for name in names:
        if str(name).lower() not in PROVIDER_ALIASES and str(name) not in known:
            raise InputError(
                f"descriptor.execution_providers: unknown provider {name!r}; use auto, or a list of "
                f"{', '.join(PROVIDER_ALIASES)} or onnxruntime's names (CUDAExecutionProvider, ...)"
            )
