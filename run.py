"""`python run.py sampler=highpass ratio=0.05 dataset=synthetic`, sweeps with -m: the Hydra app of
fastmac_exp/run/cli.py (also `python -m fastmac_exp` and the `fastmac-exp` console script)."""

from fastmac_exp.run.cli import run

if __name__ == "__main__":
    run()
