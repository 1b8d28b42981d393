"""Registration backends: MAC in C++ (`cpp`) and in Python (`python`), and the peer methods (`peers`)."""

from __future__ import annotations

from fastmac_exp.errors import InputError


def make_backend(name: str = "auto"):
    """'cpp', 'python', or 'auto' (cpp when the extension is built, else python)."""
    from fastmac_exp.backends.python_mac import PythonBackend

    if name == "python":
        return PythonBackend()
    if name in ("cpp", "auto"):
        from fastmac_exp import core
        from fastmac_exp.backends.cpp import CppBackend

        if name == "cpp" or core.available():
            return CppBackend()
        return PythonBackend()
    raise InputError(f"unknown backend {name!r}; choose cpp, python or auto")
