"""`python -m fastmac_exp ...`: the same Hydra app as `python run.py ...`."""

from fastmac_exp.run.cli import run

run()
