"""What a user sees while a learned descriptor describes (issue 50 item 4): progress=false prints no
per-keypoint bar, even on a terminal, and where the output is not a terminal (a log, CI) no bar writes its
updates as carriage-return lines."""

from __future__ import annotations

import fcntl
import os
import pty
import struct
import subprocess
import sys
import termios
from pathlib import Path

import pytest

pytest.importorskip("onnxruntime")

REPO = Path(__file__).resolve().parents[1]
# one small synthetic pair, BUFFER in batches of 4: a cloud's keypoints are many batches, so its bar is due
SMALL = ["descriptor=buffer", "limit=1", "tracker=none", "descriptor.batch_size=4",
         "descriptor.voxel_size=0.2", "dataset.points_per_scan=8000", "dataset.num_pairs=1",
         "cache.correspondences=false"]  # fmt: skip


def _cmd(tmp: Path, progress: str) -> list[str]:
    return [sys.executable, "run.py", *SMALL, f"progress={progress}", f"hydra.run.dir={tmp / progress}"]


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO), "TERM": "xterm"}


def _piped(tmp: Path, progress: str) -> str:
    """The run's stdout and stderr, both into one file."""
    log = tmp / f"{progress}.log"
    with open(log, "wb") as f:
        p = subprocess.run(_cmd(tmp, progress), cwd=REPO, env=_env(), stdout=f, stderr=subprocess.STDOUT,
                           timeout=300)  # fmt: skip
    out = log.read_bytes().decode()
    assert p.returncode == 0, out[-2000:]
    return out


def _on_a_terminal(tmp: Path, progress: str) -> str:
    """The run's stdout and stderr on a pseudo-terminal, as a user at a console sees them."""
    master, slave = pty.openpty()
    # a window size: on a terminal of 0 columns tqdm draws nothing
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    p = subprocess.Popen(_cmd(tmp, progress), cwd=REPO, env=_env(), stdout=slave, stderr=slave,
                         stdin=subprocess.DEVNULL)  # fmt: skip
    os.close(slave)
    chunks = []
    try:
        while True:
            try:
                data = os.read(master, 65536)
            except OSError:  # EIO: the child closed the terminal
                break
            if not data:
                break
            chunks.append(data)
    finally:
        os.close(master)
        rc = p.wait(timeout=300)
    out = b"".join(chunks).decode(errors="replace")
    assert rc == 0, out[-2000:]
    return out


def test_progress_false_prints_no_bar_even_on_a_terminal(tmp_path):
    shown = _on_a_terminal(tmp_path, "true")
    assert "source cloud:" in shown and "kp/s" in shown and "pair/s" in shown  # the bars this test looks for
    quiet = _on_a_terminal(tmp_path, "false")
    assert "kp/s" not in quiet and "pair/s" not in quiet, quiet
    assert "\r" not in quiet.replace("\r\n", "\n"), quiet  # no bar's line redrawn in place


@pytest.mark.parametrize("progress", ["false", "true"])
def test_a_log_gets_no_bar_updates(tmp_path, progress):
    out = _piped(tmp_path, progress)
    assert "\r" not in out, out
    lines = out.splitlines()
    assert not [ln for ln in lines if "kp/s" in ln or "pair/s" in ln or "it/s" in ln], out
    # the cost note, the run's line, pairs, RR, stage times, where the results are: nothing a batch
    assert len(lines) <= 8, out


def test_the_bar_is_off_when_asked_short_or_not_on_a_terminal(capsys):
    from fastmac_exp.descriptors.progress import keypoint_bar

    assert keypoint_bar(1000, "x", False, 8).disable  # progress=false
    assert keypoint_bar(31, "x", True, 8).disable  # under four batches
    assert keypoint_bar(1000, "x", True, 8).disable  # pytest's captured stderr is not a terminal


def test_register_describes_its_learned_step_without_a_bar():
    """register()'s escalation runs BUFFER as a step of a call, not as a run the user watches."""
    from fastmac_exp.escalation import STEPS

    (learned,) = [s for s in STEPS if s.name == "learned"]
    assert learned.changes["progress"] is False
