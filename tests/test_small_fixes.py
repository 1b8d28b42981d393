"""Issue 42 item 10: the small things a new user meets, each seen from the console or the disk."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(REPO)}


def test_a_count_of_samples_is_what_the_header_says_and_the_descriptor_names_its_run(tmp_path):
    """samples=K is shown as such (not only as the ratio it came to); the descriptor names its run
    directory as its rows name it."""
    cmd = [sys.executable, str(REPO / "run.py"), "samples=2500", "descriptor=fcgf_lite", "limit=1",
           "tracker=none", "progress=false"]  # fmt: skip
    p = subprocess.run(cmd, cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    header = next(ln for ln in p.stdout.splitlines() if ln.startswith("dataset="))
    assert " descriptor=fcgf_lite sampler=highpass samples=2500 (ratio 0.5) backend=cpp" in header, header
    (run_dir,) = (tmp_path / "outputs" / "runs").iterdir()
    assert run_dir.name.endswith("_synthetic-3dmatch_fcgf_lite_highpass_k2500"), run_dir.name


def test_benchmarks_and_evaluation_end_in_one_line_not_a_traceback(tmp_path):
    """A missing --old build, missing real data: one line and exit 2 (evaluate.py --real used to skip the
    real pairs and exit 0, having evaluated nothing)."""
    cases = [
        (["benchmarks/compare_cores.py", "--old", str(tmp_path / "nosuch.so")],
         f"compare_cores: --old {tmp_path / 'nosuch.so'}: no such file"),
        (["benchmarks/fpfh_orientation.py", "--data", str(tmp_path)],
         f"fpfh_orientation: shared_real: {tmp_path / 'pairs.json'} not found"),
        (["descriptors/evaluate.py", "--real", "--real-root", str(tmp_path)],
         f"evaluate: --real: {tmp_path / 'pairs.json'} not found"),
    ]  # fmt: skip
    for args, message in cases:
        cmd = [sys.executable, *args]
        p = subprocess.run(cmd, cwd=REPO, env=ENV, capture_output=True, text=True, timeout=120)
        out = (p.stdout + p.stderr).strip()
        assert p.returncode == 2, (args, out[-2000:])
        assert out.startswith(message) and "Traceback" not in out and len(out.splitlines()) == 1, (args, out)
