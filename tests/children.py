"""Child processes for the signal tests, however pytest itself was started.

A background job of a non-interactive shell (`nohup python -m pytest &`, a CI script, a cluster job) starts
with SIGINT ignored, its children inherit that, and Python then installs no KeyboardInterrupt handler: every
child here gets SIGINT back at its default first. And no wait here is a sleep: a test waits until a file
holds a row, or until the child has spent some CPU time (what it has done, not how long the machine took).
"""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import psutil

REPO = Path(__file__).resolve().parents[1]
HANG_S = 600.0  # only a guard against a child that hangs: no test expects to come near it


def default_sigint() -> None:
    """preexec_fn of a child that Ctrl-C must reach: SIGINT at its default (KeyboardInterrupt in Python)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def popen(cmd: list[str], **kwargs) -> subprocess.Popen:
    return subprocess.Popen(cmd, preexec_fn=default_sigint, **kwargs)


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process, all of its threads (0 once it is gone)."""
    try:
        t = psutil.Process(pid).cpu_times()
    except psutil.Error:
        return 0.0
    return t.user + t.system


def wait_until(done: Callable[[], bool], proc: subprocess.Popen, what: str) -> None:
    """Polls `done` until it holds; fails if the child exits first (or hangs past HANG_S)."""
    end = time.monotonic() + HANG_S
    while not done():
        if proc.poll() is not None:
            if done():  # it ended between the two looks (for exits_within_cpu, the very thing waited for)
                return
            raise AssertionError(f"the child exited ({proc.returncode}) before {what}")
        if time.monotonic() > end:
            raise AssertionError(f"the child hung: still no {what} after {HANG_S:.0f} s")
        time.sleep(0.02)


def has_rows(path: Path, n: int = 1) -> Callable[[], bool]:
    return lambda: path.exists() and len(path.read_text().splitlines()) >= n


class FifoReader:
    """Tells when a process has opened a FIFO for reading (it then waits on it) by opening the write end
    without blocking, which fails while there is no reader; that end stays open (nothing written), so the
    reader waits in read() until the signal. Call close() after."""

    def __init__(self, path: Path) -> None:
        self.path, self.fd = path, None

    def __call__(self) -> bool:
        if self.fd is None:
            try:
                self.fd = os.open(self.path, os.O_WRONLY | os.O_NONBLOCK)
            except OSError as e:
                if e.errno != errno.ENXIO:  # ENXIO: no reader yet
                    raise
        return self.fd is not None

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def spent(proc: subprocess.Popen, cpu_s: float) -> Callable[[], bool]:
    """True once the child has spent `cpu_s` more CPU seconds than it had when this was called."""
    start = cpu_seconds(proc.pid)
    return lambda: cpu_seconds(proc.pid) >= start + cpu_s


def exits_within_cpu(proc: subprocess.Popen, since: float, cpu_s: float) -> None:
    """Waits for the child's exit; fails once it has spent `cpu_s` CPU seconds past `since` without
    exiting (a call that ignores a signal runs on)."""
    gone = lambda: proc.poll() is not None  # noqa: E731
    wait_until(lambda: gone() or cpu_seconds(proc.pid) > since + cpu_s, proc, "its exit")
    if not gone():
        raise AssertionError(f"the child ran on for {cpu_s:.1f} CPU s after the signal")


# what a child of interrupt_child runs around its long part; {body} is indented 4 spaces
CHILD = """
import signal, sys, time
sys.path.insert(0, {repo!r})
{setup}
print("ready", repr(one_call_cpu), flush=True)
try:
{body}
except KeyboardInterrupt:
    print("interrupted", repr(time.process_time()), flush=True)
    sys.exit(130)
print("finished", flush=True)
"""


def interrupt_child(setup: str, body: str) -> tuple[int, str, float, float]:
    """Runs a child Python that does `setup` (which sets `one_call_cpu`: the CPU seconds of one call of
    the long part, measured by a warm-up call, or 0 where the long part cannot finish), prints "ready",
    then runs `body` (calls that go on for minutes) and prints "interrupted" when a KeyboardInterrupt ends
    it. SIGINT is sent once the child has spent half a call's CPU time (at least 0.3 s) inside the body.
    Returns (exit code, the word printed after the signal, CPU seconds the child spent between the signal
    and that word, one_call_cpu): a core that polls for Ctrl-C stops within milliseconds of CPU; one that
    does not finishes its call first."""
    code = CHILD.format(repo=str(REPO), setup=setup, body=body)
    proc = popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        word, one_call = proc.stdout.readline().split()
        assert word == "ready"
        one_call = float(one_call)
        wait_until(spent(proc, max(0.5 * one_call, 0.3)), proc, "the signal (still inside the long part)")
        at_signal = cpu_seconds(proc.pid)
        proc.send_signal(signal.SIGINT)
        exits_within_cpu(proc, at_signal, max(one_call, 3.0))
        line = proc.stdout.read().split()
    finally:
        if proc.poll() is None:
            proc.kill()
    word = line[0] if line else ""
    after = float(line[1]) - at_signal if word == "interrupted" else float("inf")
    return proc.returncode, word, after, one_call
