"""Property-based: random correspondence sets, rigid transforms and outlier fractions; both backends
agree and never crash (they either return the same pose or fail with the same clear error)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fastmac_exp.backends import cpp as cpp_backend
from fastmac_exp.backends.python_mac import PythonBackend
from fastmac_exp.errors import RegistrationFailed
from fastmac_exp.geometry.transforms import random_rotation
from fastmac_exp.params import mac_params_for
from fastmac_exp.types import Correspondences


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(0, 300),
    outlier_fraction=st.floats(0.0, 1.0),
    noise=st.sampled_from([0.0, 0.001, 0.01]),
    family=st.sampled_from(["3dmatch", "kitti"]),
)
def test_backends_agree_and_never_crash(seed, n, outlier_fraction, noise, family):
    rng = np.random.default_rng(seed)
    extent = 3.0 if family == "3dmatch" else 50.0
    src = rng.uniform(0, extent, (n, 3))
    r, t = random_rotation(rng), rng.uniform(-extent, extent, 3)
    tgt = src @ r.T + t + rng.normal(scale=noise, size=(n, 3))
    n_out = int(round(n * outlier_fraction))
    tgt[:n_out] = rng.uniform(0, extent, (n_out, 3))
    corr = Correspondences(src, tgt)
    params = mac_params_for(family, "fpfh")
    outcomes = []
    runs = [
        (PythonBackend(), params),
        (cpp_backend.CppBackend(), replace(params, search="enumerate")),
        (cpp_backend.CppBackend(), replace(params, search="bnb")),
        (cpp_backend.CppBackend(), params),  # the default search: auto
    ]
    for backend, p in runs:
        try:
            res = backend.register(corr, p)
            outcomes.append(("ok", res))
        except RegistrationFailed as exc:
            outcomes.append(("failed", str(exc).split("(")[0].strip()))
    (ka, a), (kb, b), (kc, c), (kd, d) = outcomes
    assert ka == kb == kc == kd, outcomes
    if ka == "failed":
        assert a == b == c == d
        return
    assert a.n_cliques == b.n_cliques
    for other in (b, c, d):
        assert other.n_selected == a.n_selected
        np.testing.assert_array_equal(np.sort(a.clique), np.sort(other.clique))
        np.testing.assert_allclose(a.pose, other.pose, atol=1e-6)
