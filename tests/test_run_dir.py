"""One experiment per run directory, as the console and the files on disk show it: the lock that keeps a
second writer out, resume refusing another experiment, and Ctrl-C / SIGTERM ending a run cleanly."""

from __future__ import annotations

import json
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from fastmac_exp.run.results import read_rows
from fastmac_exp.run.runlock import LOCK_NAME, RunLock
from tests.children import HANG_S, FifoReader, has_rows, popen, wait_until
from tests.test_cli import REPO, _blob_pair, _default_run_dir, run


def test_a_run_directory_held_by_a_live_run_is_refused_and_a_stale_lock_is_taken_over(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "config.yaml").write_text("ratio: 0.2\n")  # the holder is still starting: no results yet
    with RunLock(run_dir):
        p = run("limit=1", "sampler=random", "ratio=0.1", tmp=tmp_path)
    out = p.stdout + p.stderr
    assert p.returncode == 2, out[-2000:]
    assert f"{run_dir} is in use by another run (pid {os.getpid()} on host {socket.gethostname()})" in out
    # nothing written there: not even Hydra's .hydra/ and log, which would overwrite the holder's
    assert [x.name for x in run_dir.iterdir()] == ["config.yaml"]
    (run_dir / "config.yaml").unlink()
    # a lock file whose process is gone (killed without releasing it) does not keep the directory
    (run_dir / LOCK_NAME).write_text(json.dumps({"host": socket.gethostname(), "pid": 2**22 + 7}))
    p = run("limit=1", tmp=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    assert len(read_rows(run_dir / "results.jsonl")) == 1 and not (run_dir / LOCK_NAME).exists()


def test_the_experiment_takes_the_lock_itself_for_runs_that_start_together(tmp_path):
    """The callback's early check cannot see a run that starts at the same instant: the experiment's own
    lock is what keeps the second one out (library use included)."""
    from fastmac_exp.run.experiment import run_experiment
    from fastmac_exp.run.runlock import RunLocked
    from tests.test_pipeline import _cfg

    (tmp_path / "run").mkdir()
    with RunLock(tmp_path / "run"):
        with pytest.raises(RunLocked, match=f"pid {os.getpid()} on host"):
            run_experiment(_cfg(tmp_path), tmp_path / "run")
        with pytest.raises(RunLocked):
            RunLock(tmp_path / "run").acquire()
    assert not (tmp_path / "run" / "results.jsonl").exists()
    _, summary = run_experiment(_cfg(tmp_path), tmp_path / "run")  # released: the next run goes ahead
    assert summary["pairs"] == 4


def test_resume_refuses_another_experiment_and_lists_what_differs(tmp_path):
    first = tmp_path / "first"
    p = run("limit=1", tmp=first)
    assert p.returncode == 0, p.stderr[-2000:]
    made = first / "run"
    before = (made / "results.jsonl").read_text()
    p = run("limit=1", f"resume={made}", "dataset.family=kitti", "ratio=0.1", tmp=tmp_path)
    out = p.stdout + p.stderr
    assert p.returncode == 2, out[-2000:]
    assert "dataset.family: '3dmatch' (saved) vs 'kitti' (this command)" in out
    assert "ratio: 0.2 (saved) vs 0.1 (this command)" in out and "drop resume= to start a new run" in out
    p = run("limit=1", f"resume={made}", "sampler=random", tmp=tmp_path)
    out = p.stdout + p.stderr
    assert p.returncode == 2 and "sampler._target_: 'fastmac_exp.samplers.GraphFilterSampler' (saved)" in out
    assert "sampler.filter" not in out  # another option of a group is one difference
    p = run(f"resume={made}", "limit=1", "seed=1", tmp=tmp_path)
    assert p.returncode == 2 and "seed: 0 (saved) vs 1 (this command)" in p.stdout + p.stderr
    assert (made / "results.jsonl").read_text() == before  # nothing appended
    assert not (tmp_path / "run").exists()  # and no directory of its own
    # what cannot change a row may differ, and limit may grow: the run goes on with the further pair
    p = run(f"resume={made}", "limit=2", "workers=2", "fail_fast=true", tmp=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    assert [r["pair"] for r in read_rows(made / "results.jsonl")] == ["3dmatch_000", "3dmatch_001"]
    p = run(f"resume={made}", "limit=1", tmp=tmp_path)
    assert p.returncode == 2 and "a resume may raise limit, not lower it" in p.stdout + p.stderr


def test_resume_of_a_directory_that_is_no_run_is_refused(tmp_path):
    other = tmp_path / "photos"
    other.mkdir()
    (other / "a.jpg").write_text("x")
    p = run("limit=1", f"resume={other}", tmp=tmp_path)
    out = p.stdout + p.stderr
    assert p.returncode == 2 and f"{other} is no run directory (it has no config.yaml)" in out
    assert [x.name for x in other.iterdir()] == ["a.jpg"]


def test_resume_auto_in_a_single_run_continues_the_latest_run_of_this_config(tmp_path):
    runs = tmp_path / "runs"
    p = run("limit=1", _default_run_dir(runs), tmp=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    (made,) = runs.iterdir()
    p = run("limit=2", "resume=auto", _default_run_dir(runs), tmp=tmp_path)
    assert p.returncode == 0, p.stderr[-2000:]
    assert list(runs.iterdir()) == [made] and len(read_rows(made / "results.jsonl")) == 2
    p = run("limit=2", "sampler=random", "resume=auto", _default_run_dir(runs), tmp=tmp_path)
    out = p.stdout + p.stderr
    assert p.returncode == 2 and "resume=auto: no earlier run of this exact config" in out
    assert list(runs.iterdir()) == [made]


def _second_pair_blocks(tmp: Path) -> list[str]:
    """dataset=pairs with two pairs: a cloud and its moved copy, then a FIFO nobody writes. The run writes
    the first pair's row and blocks reading the second: a signal then always lands mid-run, however slow
    or loaded the machine (replace the FIFO by a file to let the run go on)."""
    src, tgt, _ = _blob_pair(tmp)
    fifo = tmp / "blocks.npy"
    os.mkfifo(fifo)
    return ["dataset=pairs", f"dataset.source=[{src},{fifo}]", f"dataset.target=[{tgt},{fifo}]"]


def _blocked_after_first_row(proc: subprocess.Popen, run_dir: Path, fifo: Path) -> FifoReader:
    """Waits until the run has written the first pair's row and waits reading the second pair's FIFO."""
    reader = FifoReader(fifo)
    wait_until(has_rows(run_dir / "results.jsonl"), proc, "the first row")
    wait_until(reader, proc, "the second pair's read")
    return reader


def _signal_after_first_row(sig: int, run_dir: Path, *overrides: str) -> tuple[int, str]:
    cmd = [sys.executable, "run.py", "progress=false", f"hydra.run.dir={run_dir}", *overrides]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    reader = None
    try:
        reader = _blocked_after_first_row(proc, run_dir, run_dir.parent / "blocks.npy")
        workers = subprocess.run(
            ["pgrep", "-P", str(proc.pid)], capture_output=True, text=True
        ).stdout.split()
        proc.send_signal(sig)
        out = proc.communicate(timeout=HANG_S)[0]
    finally:
        if reader is not None:
            reader.close()
        if proc.poll() is None:
            proc.kill()
    for pid in workers:  # ended with the run: gone, or a zombie waiting for init to reap it
        stat = Path(f"/proc/{pid}/stat")
        assert not stat.exists() or stat.read_text().split(") ")[1].startswith("Z"), f"worker {pid} lives on"
    return proc.returncode, out


@pytest.mark.signals
def test_sigterm_with_workers_ends_them_writes_the_tables_and_says_how_to_resume(tmp_path):
    run_dir = tmp_path / "run"
    pairs = _second_pair_blocks(tmp_path)
    rc, out = _signal_after_first_row(signal.SIGTERM, run_dir, *pairs, "workers=2", "tracker=none")
    assert rc == 130, out[-2000:]
    assert f"resume={run_dir}" in out and "Traceback" not in out
    rows = read_rows(run_dir / "results.jsonl")
    assert len(rows) == 1
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["pairs"] == len(rows) and not summary["complete"]
    assert (run_dir / "results.csv").read_text().count("\n") == len(rows) + 1
    assert not (run_dir / LOCK_NAME).exists()


@pytest.mark.signals
def test_ctrl_c_with_the_trackers_on_prints_no_traceback(tmp_path):
    run_dir = tmp_path / "run"
    rc, out = _signal_after_first_row(signal.SIGINT, run_dir, *_second_pair_blocks(tmp_path))
    assert rc == 130, out[-2000:]
    assert "interrupted: 1 pair is saved" in out and len(read_rows(run_dir / "results.jsonl")) == 1
    assert "Traceback" not in out and "KeyboardInterrupt" not in out
    assert (run_dir / "recording.rrd").is_file() and (run_dir / "summary.json").is_file()


@pytest.mark.signals
def test_ctrl_c_before_the_first_pair_leaves_no_run_directory(tmp_path):
    """The pair's file is a FIFO nobody writes: the run blocks reading it, after its start-up wrote
    config.yaml and started the trackers, and Ctrl-C lands before any pair has finished."""
    fifo = tmp_path / "src.npy"
    os.mkfifo(fifo)
    run_dir = tmp_path / "run"
    cmd = [sys.executable, "run.py", "progress=false", f"hydra.run.dir={run_dir}", "dataset=pairs",
           f"dataset.source={fifo}", f"dataset.target={fifo}"]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    reader = FifoReader(fifo)
    try:
        wait_until(reader, proc, "the pair's read")  # past the start-up: config.yaml, the trackers
        assert (run_dir / "config.yaml").exists()
        proc.send_signal(signal.SIGINT)
        out = proc.communicate(timeout=HANG_S)[0]
    finally:
        reader.close()
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, out[-2000:]
    assert "Traceback" not in out and ("nothing to resume" in out or "nothing was written" in out)
    assert not run_dir.exists()


def test_resume_keeps_the_earlier_recording_and_wandb_run_and_the_report_reads_every_part(tmp_path):
    from fastmac_exp.trackers.wandb_tracker import find_offline_runs, read_offline_run

    run_dir = tmp_path / "run"
    cmd = [sys.executable, "run.py", "progress=false", f"hydra.run.dir={run_dir}"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    first = subprocess.run([*cmd, "limit=1"], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert first.returncode == 0, first.stderr[-2000:]
    recording = (run_dir / "recording.rrd").read_bytes()
    again = subprocess.run([*cmd, "limit=2", f"resume={run_dir}"], cwd=REPO, env=env, capture_output=True,
                           text=True, timeout=300)  # fmt: skip
    assert again.returncode == 0, again.stderr[-2000:]
    assert (run_dir / "recording.rrd").read_bytes() == recording  # the first part, untouched
    assert (run_dir / "recording.part2.rrd").is_file()
    runs = find_offline_runs(run_dir)
    assert len(runs) == 2
    parts = [read_offline_run(r) for r in runs]
    assert [[h["pair/index"] for h in p["history"] if "pair/index" in h] for p in parts] == [[0], [1]]
    assert parts[1]["run"]["name"].endswith("(part 2)")
    report = subprocess.run([sys.executable, "-m", "fastmac_exp.report", str(run_dir)], cwd=REPO, env=env,
                            capture_output=True, text=True, timeout=300)  # fmt: skip
    assert report.returncode == 0, report.stderr[-2000:]
    pngs = sorted(p.name for p in (run_dir / "report" / "pairs").glob("*.png"))
    assert pngs == ["3dmatch_000.png", "3dmatch_001.png"]


def _sigterm_while_blocked(tmp_path: Path, look=None) -> tuple[subprocess.Popen, str, list[str], dict]:
    """Runs two pairs whose second blocks (_second_pair_blocks), calls `look(proc)` once the run waits on
    it, sends one SIGTERM and returns (the ended process, its output, the pair overrides, the env)."""
    run_dir = tmp_path / "run"
    pairs = _second_pair_blocks(tmp_path)
    cmd = [sys.executable, "run.py", f"hydra.run.dir={run_dir}", *pairs, "seed=3", "tracker=none"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    reader = None
    try:
        reader = _blocked_after_first_row(proc, run_dir, tmp_path / "blocks.npy")
        if look is not None:
            look(proc)
        proc.send_signal(signal.SIGTERM)
        out = proc.communicate(timeout=HANG_S)[0]
    finally:
        if reader is not None:
            reader.close()
        if proc.poll() is None:
            proc.kill()
    return proc, out, pairs, env


@pytest.mark.signals
def test_an_interrupted_run_prints_the_command_that_continues_it_on_a_line_of_its_own(tmp_path):
    """Issue 42 item 6: the hint carries the run's overrides (a bare resume=DIR is refused as another
    experiment), stands on its own line even with the progress bar on, and counts in the right number."""
    run_dir = tmp_path / "run"
    log = run_dir / "results.jsonl"
    proc, out, pairs, env = _sigterm_while_blocked(tmp_path)
    assert proc.returncode == 130, out[-2000:]
    lines = out.split("\n")
    (said,) = [ln for ln in lines if "interrupted: " in ln]
    assert said.startswith("[") and "pair/s" not in said, said  # the log line alone, not after the bar
    assert f"interrupted: 1 pair is saved in {run_dir}" in said and len(read_rows(log)) == 1
    command = lines[lines.index(next(ln for ln in lines if ln.endswith("continue it with:"))) + 1].strip()
    assert shlex.split(command) == ["python", "run.py", *pairs, "seed=3", "tracker=none", f"resume={run_dir}"]
    fifo = tmp_path / "blocks.npy"
    fifo.unlink()
    shutil.copy(tmp_path / "src.npy", fifo)  # the second pair can be read now
    again = subprocess.run(
        [sys.executable, *shlex.split(command)[1:]], cwd=REPO, env=env, capture_output=True, text=True,
        timeout=HANG_S,
    )  # fmt: skip
    assert again.returncode == 0, again.stdout[-2000:] + again.stderr[-2000:]
    assert [r["pair"] for r in read_rows(log)] == ["src+tgt", "blocks+blocks"]


@pytest.mark.signals
def test_only_the_main_thread_of_a_run_takes_ctrl_c_or_sigterm(tmp_path):
    """A SIGTERM that a helper thread took (an OpenBLAS worker yielding after a product, tqdm's monitor
    waking) left the main thread asleep in its read of the next pair: the run never stopped (once in CI).
    While the run waits, every thread but the main one blocks SIGINT and SIGTERM; then one SIGTERM ends it."""
    masks = {}

    def read_masks(proc: subprocess.Popen) -> None:
        for task in Path(f"/proc/{proc.pid}/task").iterdir():
            lines = (task / "status").read_text().splitlines()
            status = dict(ln.split(":\t", 1) for ln in lines if ":\t" in ln)
            masks[int(task.name)] = (status["Name"], int(status["SigBlk"], 16))

    proc, out, _, _ = _sigterm_while_blocked(tmp_path, read_masks)
    bits = (1 << (signal.SIGINT - 1)) | (1 << (signal.SIGTERM - 1))
    assert masks[proc.pid][1] & bits == 0, "the main thread must take them"
    helpers = {tid: name for tid, (name, blocked) in masks.items() if tid != proc.pid}
    assert helpers, "the run has helper threads (the core's pool, OpenBLAS)"
    open_to_it = {
        tid: helpers[tid] for tid, (_, blocked) in masks.items() if tid in helpers and blocked & bits != bits
    }
    assert not open_to_it, f"threads that could take the run's SIGTERM: {open_to_it}"
    assert proc.returncode == 130, out[-2000:]


@pytest.mark.signals
def test_ending_workers_survives_a_result_cut_off_mid_message(tmp_path):
    """A worker SIGTERMed while sending its result leaves part of a message in the result pipe: ending the
    workers must not wait forever for the rest (it did, under load, about one interrupt in 40)."""
    script = tmp_path / "cut_off.py"
    script.write_text(
        textwrap.dedent(
            """
            import struct, sys, time
            from concurrent.futures import ProcessPoolExecutor
            from pathlib import Path
            from fastmac_exp.run.experiment import _end_workers

            def slow(x):
                Path(f"started_{x}").touch()
                time.sleep(120)
                return x

            def reading(size):  # a thread of this process is in the pipe's _recv(size)
                return any(
                    f.f_code.co_name == "_recv" and f.f_locals.get("size") == size
                    for f in sys._current_frames().values()
                )

            def wait_for(done):
                while not done():
                    time.sleep(0.01)

            if __name__ == "__main__":
                pool = ProcessPoolExecutor(max_workers=2)
                futures = [pool.submit(slow, i) for i in range(2)]
                wait_for(lambda: all(Path(f"started_{x}").exists() for x in range(2)))
                # what the cut-off send leaves: a header promising 100 bytes, and 10 of them
                pool._result_queue._writer._send(struct.pack("!i", 100) + b"x" * 10)
                wait_for(lambda: reading(100))  # the executor's thread read the header, waits for the rest
                _end_workers(pool)
                print("ended", all(f.done() for f in futures))
            """
        )
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(
        [sys.executable, str(script)], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        out = proc.communicate(timeout=120)[0]  # ends in a second or two; a hang never does
    except subprocess.TimeoutExpired:
        proc.kill()
        raise AssertionError("ending the workers hung on a result cut off mid-message") from None
    assert proc.returncode == 0 and "ended True" in out, out[-2000:]


def test_an_interrupt_between_a_rows_fsync_and_its_entry_keeps_the_row_in_the_tables(tmp_path, monkeypatch):
    """The window CI's background run hit: SIGTERM after the first row reached results.jsonl but before the
    log's in-memory list had it; the run then wrote no tables and no summary. The log on disk decides."""
    from fastmac_exp.run import results as results_mod
    from fastmac_exp.run.experiment import run_experiment
    from tests.test_pipeline import _cfg

    real = results_mod.ResultsLog.append
    calls = []

    def append_then_interrupt(self, row):
        calls.append(row["pair"])
        if len(calls) == 2:  # the second row is on disk, then the interrupt, before the list has it
            rows = list(self.rows)
            real(self, row)
            self.rows = rows
            raise KeyboardInterrupt
        real(self, row)

    monkeypatch.setattr(results_mod.ResultsLog, "append", append_then_interrupt)
    run_dir = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        run_experiment(_cfg(tmp_path), run_dir)
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["pairs"] == 2 and not summary["complete"]
    assert (run_dir / "results.csv").read_text().count("\n") == 3
    assert [r["pair"] for r in read_rows(run_dir / "results.jsonl")] == calls
