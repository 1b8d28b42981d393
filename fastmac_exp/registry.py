"""Name -> implementation for the library API (`fastmac_exp.register(..., sampler="highpass")`).

The Hydra configs in conf/sampler and conf/backend name the same classes through `_target_`;
tests/test_config.py checks that both agree.
"""

from __future__ import annotations

from typing import Any

from fastmac_exp.errors import InputError
from fastmac_exp.samplers import FPSSampler, GraphFilterSampler, NoSampler, RandomSampler, Sampler, XYZSampler

SAMPLERS: dict[str, Any] = {
    "highpass": lambda: GraphFilterSampler("highpass"),
    "lowpass": lambda: GraphFilterSampler("lowpass"),
    "allpass": lambda: GraphFilterSampler("allpass"),
    "xyz": lambda: XYZSampler("110"),
    "random": RandomSampler,
    "fps": FPSSampler,
    "none": NoSampler,
}


def make_sampler(name: str) -> Sampler:
    if name == "deterministic":
        from fastmac_exp.deterministic import DeterministicSampler

        return DeterministicSampler()
    if name not in SAMPLERS:
        raise InputError(f"unknown sampler {name!r}; choose one of {sorted([*SAMPLERS, 'deterministic'])}")
    return SAMPLERS[name]()


def make_backend(name: str = "auto"):
    """'cpp', 'python', or 'auto' (cpp when the extension is built, else python)."""
    from fastmac_exp.backends.python_mac import PythonBackend

    if name == "python":
        return PythonBackend()
    if name in ("cpp", "auto"):
        from fastmac_exp.backends import cpp

        if name == "cpp" or cpp.available():
            return cpp.CppBackend()
        return PythonBackend()
    raise InputError(f"unknown backend {name!r}; choose cpp, python or auto")
