"""The backend interface: MAC on a set of correspondences."""

from __future__ import annotations

from typing import Protocol

from fastmac_exp.params import MacParams
from fastmac_exp.types import Correspondences, RegistrationResult


class Backend(Protocol):
    """Runs MAC (graph, cliques, selection, pose) on correspondences that were already sampled.

    `register` returns a RegistrationResult whose `kept` is arange(N) (sampling is the pipeline's job),
    whose `clique` indexes the given correspondences, and whose `timings` hold the stages
    `graph`, `cliques`, `selection` and `pose` in milliseconds. It raises RegistrationFailed when no
    pose can be produced (too few correspondences, no second-order edge, no clique).
    """

    name: str

    def register(self, corr: Correspondences, params: MacParams) -> RegistrationResult: ...
