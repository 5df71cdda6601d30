"""Distributed sweeps: two real local processes (CPU) joined by jax.distributed through a
coordinator on 127.0.0.1 divide a sweep's chunks, and give the single-process results;
a killed process, a resume with 2 or 1 processes, an unreachable coordinator and
mismatched arguments."""

import csv
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

from lgvi_jax.distributed import INITIALIZATION_TIMEOUT_S, DistributedError, initialize
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


def _run_group(out, n=2, extra=(), extra_by_process=None, env_by_process=None):
    """Start ``n`` processes of one sweep; return their ``CompletedProcess``-like tuples
    ``(returncode, stdout, stderr, seconds)`` in process order."""
    port = _free_port()
    procs, start = [], time.monotonic()
    for i in range(n):
        dist = ["--coordinator", f"127.0.0.1:{port}", "--num-processes", str(n),
                "--process-id", str(i)]
        more = (extra_by_process or {}).get(i, [])
        procs.append(subprocess.Popen(
            _cmd(out, [*extra, *dist, *more]), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True, env=_env(**(env_by_process or {}).get(i, {}))))
    results = []
    try:
        for p in procs:
            stdout, stderr = p.communicate(timeout=TIMEOUT_S)
            results.append((p.returncode, stdout, stderr, time.monotonic() - start))
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


def test_killed_process_then_resume_with_two_and_with_one(tmp_path, reference):
    out = tmp_path / "killed"
    # Process 1 kills itself (SIGKILL) right after writing its first chunk; process 0
    # must not hang: JAX's heartbeats end it within the heartbeat timeout.
    (rc0, _, err0, t0), (rc1, _, _, _) = _run_group(
        out, extra=["--heartbeat-timeout", "10"],
        env_by_process={1: {KILL_HOOK_ENV: "0"}})
    assert rc1 == -signal.SIGKILL
    assert rc0 != 0
    assert "another task died" in err0 or "heartbeat" in err0, err0[-2000:]
    assert t0 < 120
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
