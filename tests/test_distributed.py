"""Distributed sweeps: two real local processes (CPU) joined by jax.distributed through a
coordinator on 127.0.0.1 divide a sweep's chunks, and give the single-process results;
a killed process (the other ends with one line, exit 3), a killed coordinator, a resume with
2 or 1 processes, an unreachable coordinator and mismatched arguments; the watchdog's
verdicts on a fake key-value store."""

import csv
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

from lgvi_jax.distributed import (
    EXIT_PROCESS_LOST,
    INITIALIZATION_TIMEOUT_S,
    DistributedError,
    Watchdog,
    _port_is_free,
    initialize,
)
from lgvi_jax.sweep import KILL_HOOK_ENV

#: A child sweep takes ~5-15 s here; a hung child fails the test instead of blocking.
TIMEOUT_S = 240
ARGS = ["heavy-top", "--method", "lgvi", "--dt", "0.01", "--t-final", "2", "--n", "8",
        "--chunk", "2", "--devices", "1", "--json"]
N_CHUNKS = 4


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cmd(out, extra=()):
    return [sys.executable, "-m", "lgvi_jax.cli", "sweep", *ARGS, "--out", str(out), *extra]


def _env(**extra):
    return {**os.environ, "MPLBACKEND": "Agg", **extra}


def _run_group(out, n=2, extra=(), extra_by_process=None, env_by_process=None, port=None):
    """Start ``n`` processes of one sweep; return their ``CompletedProcess``-like tuples
    ``(returncode, stdout, stderr, seconds)`` in process order, ``seconds`` from the start
    to that process's end."""
    port = _free_port() if port is None else port
    procs, start = [], time.monotonic()
    for i in range(n):
        dist = ["--coordinator", f"127.0.0.1:{port}", "--num-processes", str(n),
                "--process-id", str(i)]
        more = (extra_by_process or {}).get(i, [])
        procs.append(subprocess.Popen(
            _cmd(out, [*extra, *dist, *more]), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True, env=_env(**(env_by_process or {}).get(i, {}))))
    results: list = [None] * n

    def wait(i, p):
        try:
            stdout, stderr = p.communicate(timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired:
            p.kill()
            stdout, stderr = p.communicate()
        results[i] = (p.returncode, stdout, stderr, time.monotonic() - start)

    threads = [threading.Thread(target=wait, args=(i, p), daemon=True)
               for i, p in enumerate(procs)]
    try:
        for t in threads:
            t.start()
        for t in threads:
            t.join(TIMEOUT_S + 10)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    return results


def _run_single(out, extra=()):
    return subprocess.run(_cmd(out, extra), capture_output=True, text=True,
                          timeout=TIMEOUT_S, env=_env())


def _rows(out):
    with open(out / "trajectories.csv") as fh:
        return sorted(csv.reader(fh))


@pytest.fixture(scope="module")
def unreachable():
    """A process whose coordinator never answers, started early so that its wait overlaps
    the other tests (checked by the last test): ``{"rc", "stdout", "stderr", "seconds"}``
    once it has ended."""
    port = _free_port()  # nothing listens there
    start = time.monotonic()
    proc = subprocess.Popen(
        _cmd("unused-out", ["--coordinator", f"127.0.0.1:{port}", "--num-processes", "2",
                            "--process-id", "1"]),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    result = {}

    def wait():
        try:
            result["stdout"], result["stderr"] = proc.communicate(timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            result["stdout"], result["stderr"] = proc.communicate()
        result["seconds"] = time.monotonic() - start
        result["rc"] = proc.returncode

    thread = threading.Thread(target=wait, daemon=True)
    thread.start()
    yield thread, result
    thread.join(TIMEOUT_S)


@pytest.fixture(scope="module")
def reference(tmp_path_factory, unreachable):
    """The uninterrupted single-process sweep."""
    out = tmp_path_factory.mktemp("single") / "sweep"
    done = _run_single(out)
    assert done.returncode == 0, done.stderr
    return out


def test_arguments_are_checked_before_connecting():
    with pytest.raises(DistributedError, match="missing: --coordinator"):
        initialize(None, 2, 0)
    with pytest.raises(DistributedError, match="do not also give"):
        initialize("127.0.0.1:1234", auto=True)
    with pytest.raises(DistributedError, match=r"--process-id must be an integer in 0\.\.1"):
        initialize("127.0.0.1:1234", 2, 2)
    with pytest.raises(DistributedError, match="expected HOST:PORT"):
        initialize("localhost", 2, 0)
    with socket.socket() as busy:  # process 0 would serve the coordinator on a busy port
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(DistributedError, match=f"port {port} is already in use"):
            initialize(f"127.0.0.1:{port}", 2, 0)


def test_two_processes_share_the_work_and_match_one_process(tmp_path, reference):
    out = tmp_path / "two"
    (rc0, out0, err0, _), (rc1, out1, err1, _) = _run_group(out)
    assert rc0 == 0, err0
    assert rc1 == 0, err1
    assert out1 == "" and err1 == ""  # the others are quiet; process 0 reports
    summary = json.loads(out0)
    assert summary["processes"] == 2
    shares = summary["chunks_by_process"]
    files = [f for share in shares for f in share]
    assert all(shares) and len(files) == N_CHUNKS
    assert sorted(files) == sorted(f"chunks/{p.name}" for p in (out / "chunks").glob("*.npz"))
    assert _rows(out) == _rows(reference)
    for name in ("summary.json", "summary.md", "energy_error.png", "manifest.json"):
        assert (out / name).is_file()
    # Process 0 refuses the finished folder without --resume; the others say the same.
    for rc, _, err, _ in _run_group(out):
        assert rc == 2 and "already holds a sweep" in err, err


def _slurm_job_id() -> int:
    """A job id whose port (JAX's Slurm rule: 61440 + id mod 4096) is free here."""
    for job in range(1000, 5096):
        try:
            with socket.socket() as s:
                s.bind(("127.0.0.1", job % 4096 + 61440))
            return job
        except OSError:
            continue
    pytest.skip("no free port in 61440..65535")


def test_distributed_auto_under_a_slurm_environment(tmp_path, reference):
    """``--distributed auto`` reads the coordinator, N and I from Slurm's variables, as
    ``srun`` sets them (here faked for 2 tasks on this host)."""
    out = tmp_path / "slurm"
    job = _slurm_job_id()
    slurm = {"SLURM_JOB_ID": str(job), "SLURM_STEP_NODELIST": "localhost",
             "SLURM_NTASKS": "2", "SLURM_STEP_NUM_NODES": "1"}
    procs = [subprocess.Popen(
        _cmd(out, ["--distributed", "auto"]), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True, env=_env(**slurm, SLURM_PROCID=str(i), SLURM_LOCALID=str(i)))
        for i in range(2)]
    try:
        done = [(p.communicate(timeout=TIMEOUT_S), p.returncode) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    for (_, err), rc in done:
        assert rc == 0, err
    summary = json.loads(done[0][0][0])
    assert summary["processes"] == 2 and all(summary["chunks_by_process"])
    assert _rows(out) == _rows(reference)


#: The watchdog timeout (--heartbeat-timeout) of the kill tests, and the most seconds a
#: survivor may take after the death beyond it (it takes 1-2.5 s here: a poll or two of
#: 1 s; JAX's own verdict, which these tests must not see, comes after 15-30 s).
KILL_HEARTBEAT_S = 5
KILL_MARGIN_S = 8
RERUN = "rerun the same command with --resume to finish the sweep"


def _assert_one_clean_line(err: str, expected: str) -> None:
    """``err`` is exactly the line ``expected``: no Python traceback, no JAX log or C++
    stack trace."""
    assert err.strip().splitlines() == [expected], err[-3000:]
    for junk in ("Traceback", "stack trace", "Check failure", "Terminating process"):
        assert junk not in err, err[-3000:]
    assert not re.search(r"^[IWEF]\d{4} ", err, re.MULTILINE), err[-3000:]  # JAX's log


def test_killed_process_then_resume_with_two_and_with_one(tmp_path, reference):
    out = tmp_path / "killed"
    # Process 1 kills itself (SIGKILL) right after writing its first chunk; process 0
    # must not hang: its watchdog ends it with one line and exit 3, KILL_HEARTBEAT_S after
    # process 1's last heartbeat.
    (rc0, _, err0, t0), (rc1, _, _, t1) = _run_group(
        out, extra=["--heartbeat-timeout", str(KILL_HEARTBEAT_S)],
        env_by_process={1: {KILL_HOOK_ENV: "0"}})
    assert rc1 == -signal.SIGKILL
    assert rc0 == EXIT_PROCESS_LOST, err0[-3000:]
    _assert_one_clean_line(err0, f"lgvi-jax sweep: process 1 stopped responding (no heartbeat "
                                 f"for {KILL_HEARTBEAT_S} s); {RERUN}")
    assert KILL_HEARTBEAT_S - 2 < t0 - t1 < KILL_HEARTBEAT_S + KILL_MARGIN_S, (t0, t1)
    assert not (out / "trajectories.csv").exists()
    written = sorted(p.name for p in (out / "chunks").glob("*.npz"))
    assert 1 <= len(written) < N_CHUNKS
    copy = tmp_path / "killed-copy"
    shutil.copytree(out, copy)

    # Resume with 2 processes: only the missing chunks, divided among both.
    (rc0, out0, err0, _), (rc1, _, err1, _) = _run_group(out, extra=["--resume"])
    assert rc0 == 0, err0
    assert rc1 == 0, err1
    summary = json.loads(out0)
    assert summary["chunks_skipped"] == len(written)
    assert summary["chunks_computed"] == N_CHUNKS - len(written)
    assert _rows(out) == _rows(reference)

    # Resume with 1 process (no distributed options at all).
    done = _run_single(copy, ["--resume"])
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["chunks_skipped"] == len(written)
    assert _rows(copy) == _rows(reference)


def test_killed_coordinator_ends_the_others_with_one_line(tmp_path):
    """Process 0 (the coordinator) kills itself after its first chunk: its keeper holds
    the connections open, so process 1's JAX client does not abort it at once and its
    watchdog ends it with one line; the coordinator's port is free at once for a rerun."""
    out = tmp_path / "killed0"
    port = _free_port()
    (rc0, _, _, t0), (rc1, out1, err1, t1) = _run_group(
        out, extra=["--heartbeat-timeout", str(KILL_HEARTBEAT_S)],
        env_by_process={0: {KILL_HOOK_ENV: "0"}}, port=port)
    assert rc0 == -signal.SIGKILL
    assert rc1 == EXIT_PROCESS_LOST, err1[-3000:]
    _assert_one_clean_line(err1, "lgvi-jax sweep: lost the connection to the coordinator "
                                 f"(process 0): no answer for {KILL_HEARTBEAT_S} s; {RERUN}")
    assert out1 == ""
    assert KILL_HEARTBEAT_S - 2 < t1 - t0 < KILL_HEARTBEAT_S + KILL_MARGIN_S, (t0, t1)
    assert _port_is_free(port)
    assert 1 <= len(list((out / "chunks").glob("*.npz"))) < N_CHUNKS


class _FakeStore:
    """The two key-value calls of the watchdog, in memory; ``fail`` makes them raise."""

    def __init__(self):
        self.kv, self.fail = {}, False

    def key_value_set(self, key, value, allow_overwrite=False):
        if self.fail:
            raise RuntimeError("UNAVAILABLE: Socket closed\nmore detail")
        assert allow_overwrite or key not in self.kv
        self.kv[key] = value

    def key_value_dir_get(self, prefix):
        if self.fail:
            raise RuntimeError("UNAVAILABLE: Socket closed\nmore detail")
        return [(k, v) for k, v in list(self.kv.items()) if k.startswith(prefix)]


@pytest.mark.parametrize("case", ["stale", "never", "stopped", "left", "coordinator"])
def test_watchdog_verdicts(case, capfd):
    """Process 1 of 3 watches processes 0 and 2 (fast timings): process 2 is done and
    never judged; process 0 beats for a while, then ``case`` happens to it (or to the
    store); the watchdog ends the process with one line and exit status 3 (recorded)."""
    store, exits, keep_beating = _FakeStore(), [], threading.Event()
    keep_beating.set()
    timeout = 0.6
    dog = Watchdog(store, 1, 3, timeout, grace_s=0.5, poll_s=0.05, prog="prog",
                   exit=exits.append)
    store.kv[Watchdog.PREFIX + "2"] = "done"

    def beat():
        n = 0
        while keep_beating.is_set():
            n += 1
            store.kv[Watchdog.PREFIX + "0"] = f"alive {n}"
            time.sleep(0.05)

    if case != "never":
        threading.Thread(target=beat, daemon=True).start()
    start = time.monotonic()
    dog.start()
    time.sleep({"never": 0.15, "stale": 1.0}.get(case, 0.3))  # stale: beats > timeout
    assert exits == [] or case == "never"
    assert store.kv[Watchdog.PREFIX + "1"].startswith("alive")
    keep_beating.clear()
    time.sleep(0.1)
    if case == "stopped":
        store.kv[Watchdog.PREFIX + "0"] = "stopped process 7 stopped responding"
    elif case == "left":
        store.kv[Watchdog.PREFIX + "0"] = "left"
    elif case == "coordinator":
        store.fail = True
    ended = time.monotonic()
    while not exits and time.monotonic() - ended < 10:
        time.sleep(0.02)
    waited = time.monotonic() - ended
    assert exits == [EXIT_PROCESS_LOST]
    expected = {
        "stale": f"process 0 stopped responding (no heartbeat for 0.6 s); {RERUN}",
        "never": f"process 0 stopped responding (no heartbeat for 0.6 s); {RERUN}",
        "stopped": "process 7 stopped responding",
        "left": f"process 0 ended before the sweep was complete; {RERUN}",
        "coordinator": "lost the connection to the coordinator (process 0): UNAVAILABLE: "
                       f"Socket closed; {RERUN}",
    }[case]
    assert capfd.readouterr().err == f"prog: {expected}\n"
    bound = {"left": 0.5, "stopped": 0.0, "coordinator": 0.0}.get(case, timeout)
    assert waited < bound + 2.5, waited
    if case == "never":
        assert time.monotonic() - start > timeout
    if case != "coordinator":  # the others are told why, before the exit
        assert store.kv[Watchdog.PREFIX + "1"] == f"stopped {expected}"


def test_watchdog_stop_and_leave(monkeypatch):
    """``stop("done")`` leaves ``done`` and judges nothing more; ``leave`` ends a process
    that did not complete at once, and process 0 only once the others have ended."""
    store, exits = _FakeStore(), []
    dog = Watchdog(store, 1, 2, 0.3, poll_s=0.02, exit=exits.append)
    dog.start()
    time.sleep(0.1)
    dog.stop("done")
    time.sleep(0.1)
    assert store.kv[Watchdog.PREFIX + "1"] == "done"
    time.sleep(0.4)  # process 0 never beat, but a stopped watchdog judges nothing
    dog.leave(2)  # done: nothing to do
    assert exits == []

    monkeypatch.setattr("lgvi_jax.distributed._start_keeper", lambda linger: None)
    store, exits = _FakeStore(), []
    store.kv[Watchdog.PREFIX + "1"] = "alive 1"
    dogs = [Watchdog(store, i, 2, 2.0, grace_s=1.0, poll_s=0.02, exit=exits.append)
            for i in range(2)]
    for d in dogs:
        d.start()
    time.sleep(0.1)
    leaving = threading.Thread(target=dogs[0].leave, args=(130,))
    leaving.start()  # process 0 leaves first: it waits for process 1
    time.sleep(0.3)
    assert exits == [] and store.kv[Watchdog.PREFIX + "0"] == "left"
    dogs[1].leave(2)
    assert exits == [2] and store.kv[Watchdog.PREFIX + "1"] == "left"
    leaving.join(2)
    assert exits == [2, 130]


def test_mismatched_arguments_are_refused(tmp_path):
    out = tmp_path / "mismatch"
    (rc0, _, err0, _), (rc1, _, err1, _) = _run_group(
        out, extra_by_process={1: ["--seed", "3"]})
    for rc, err in ((rc0, err0), (rc1, err1)):
        assert rc == 2, err
        assert "process 1 was started with other sweep arguments" in err
        assert "--seed" in err
    assert not (out / "manifest.json").exists()


def test_an_error_in_one_process_stops_the_others_with_its_message(tmp_path):
    out = tmp_path / "blocked"
    # A folder in the way of the second chunk (process 1's first): its write fails.
    (out / "chunks" / "lgvi__dt0__0000002-0000004.npz" / "x").mkdir(parents=True)
    (rc0, _, err0, _), (rc1, _, err1, _) = _run_group(out)
    assert rc1 == 2 and "cannot write" in err1, err1
    assert rc0 == 2 and "process 1 failed: cannot write" in err0, err0
    assert not (out / "trajectories.csv").exists()


def test_unreachable_coordinator_exits_2_within_60_s(unreachable):
    thread, result = unreachable
    thread.join(TIMEOUT_S)
    assert result["rc"] == 2, result["stderr"]
    assert INITIALIZATION_TIMEOUT_S - 1 <= result["seconds"] < 60, result["seconds"]
    lines = result["stderr"].strip().splitlines()
    assert len(lines) == 1 and "cannot reach the coordinator" in lines[0], result["stderr"]
    assert result["stdout"] == ""
