"""`python -m fastmac_exp ...`: the same Hydra app as `python run.py ...`."""

from fastmac_exp.cli import run

run()
