"""One pair through the flow: describe -> sample -> register -> evaluate (flow), the results row it fills
stage by stage (row) and the correspondence cache that can stand in for the describe stage (cache)."""

from fastmac_exp.pipeline.flow import PROTOCOLS, PairOutcome, evaluate, register_correspondences, run_pair

__all__ = ["PROTOCOLS", "PairOutcome", "evaluate", "register_correspondences", "run_pair"]
