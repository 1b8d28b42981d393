"""The suite passes however pytest is started: here the signal tests run again in a pytest started as a
background job of a non-interactive shell starts it (`nohup python -m pytest &`, a CI script, a cluster
job): with SIGINT ignored, which its children inherit."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys

import pytest

from tests.children import REPO

SIGNAL_TESTS = ["tests/test_estimated_scores.py", "tests/test_heaviest.py", "tests/test_reliability.py",
                "tests/test_run_dir.py", "tests/test_triangle_listing.py"]  # fmt: skip


def _ignore_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.skipif(os.name != "posix", reason="signals")
def test_the_signal_tests_pass_in_a_background_pytest():
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "signals", *SIGNAL_TESTS]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    p = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=1200,
                       preexec_fn=_ignore_sigint)  # fmt: skip
    assert p.returncode == 0, p.stdout[-4000:] + p.stderr[-2000:]
    tally = p.stdout.strip().splitlines()[-1]
    assert re.search(r"\b\d+ passed", tally) and "skipped" not in tally, tally  # every one ran
