"""The dataset interface: an indexable list of pairs."""

from __future__ import annotations

from typing import Protocol

from fastmac_exp.types import Pair


class Dataset(Protocol):
    """A finite, ordered list of registration pairs.

    `names()` is cheap (no heavy loading) and fixes the order; `load(i)` reads pair i and raises
    fastmac_exp.errors.InputError with the path and the expected layout when its files are missing
    or malformed (the experiment loop records that pair as failed and goes on).
    """

    name: str

    def names(self) -> list[str]: ...

    def load(self, index: int) -> Pair: ...

    def __len__(self) -> int: ...
