"""The command line: outputs, the JSON summary, and clear errors (exit 2, no traceback)."""

import io
import json
import os
import re
import subprocess
import sys
from importlib.metadata import entry_points

import numpy as np
import pytest

from lgvi_jax.cli import main
from lgvi_jax.diagnostics import rk4_energy_factor


def run_cli(args, capsys):
    code = main(args)
    out, err = capsys.readouterr()
    return code, out, err


def test_simulate_writes_npz(tmp_path, capsys):
    out = tmp_path / "sub" / "run.npz"
    code, stdout, _ = run_cli(
        ["simulate", "oscillator", "--method", "gl4", "--dt", "0.1", "--t-final", "10",
         "--out", str(out)], capsys)
    assert code == 0
    assert "wrote" in stdout
    data = np.load(out)
    for key in ("t", "q", "p", "energy"):
        assert data[key].shape == (101,)
    assert data["q"][0] == 1.0 and data["p"][0] == 0.0
    np.testing.assert_allclose(data["t"], 0.1 * np.arange(101), rtol=1e-14)
    np.testing.assert_allclose(data["q"], np.cos(data["t"]), atol=1e-5)
    np.testing.assert_allclose(data["energy"], 0.5, rtol=1e-13)
    assert json.loads(str(data["config_json"]))["method"] == "gl4"
    assert int(data["result"]) == 0


def test_simulate_json_summary_and_options(tmp_path, capsys):
    out = tmp_path / "rk4.npz"
    code, stdout, _ = run_cli(
        ["simulate", "oscillator", "--method", "rk4", "--dt", "0.1", "--t-final", "100",
         "--save-every", "10", "--set", "q0=2", "--set", "p0=0", "--set", "m=1",
         "--set", "k=1", "--out", str(out), "--json"], capsys)
    assert code == 0
    summary = json.loads(stdout)  # exactly one JSON object on stdout
    assert summary["n_steps"] == 1000 and summary["result"] == 0
    assert summary["steps_per_second"] > 0
    assert summary["wall_time_s"] == pytest.approx(
        summary["compile_time_s"] + summary["run_time_s"], rel=1e-12)
    # RK4's energy loss is known in closed form: the summary reports it. It only decays,
    # so the max over the run is the final value.
    exact = 1 - rk4_energy_factor(0.1, 1000)
    assert summary["energy_error_final"] == pytest.approx(exact, rel=1e-6)
    assert summary["energy_error_max"] == pytest.approx(exact, rel=1e-6)
    data = np.load(out)
    # The summary is computed from the saved states it wrote.
    energy = data["energy"]
    assert summary["energy_error_max"] == pytest.approx(
        float(np.max(np.abs(energy / energy[0] - 1))), rel=1e-12)
    assert data["q"].shape == (101,) and data["q"][0] == 2.0


def test_set_changes_the_physics(tmp_path, capsys):
    out = tmp_path / "m.npz"
    code, _, _ = run_cli(["simulate", "oscillator", "--method", "galerkin4", "--dt", "0.05",
                          "--t-final", "2", "--set", "m=4", "--set", "k=1", "--out", str(out)],
                         capsys)
    assert code == 0
    data = np.load(out)
    np.testing.assert_allclose(data["q"], np.cos(0.5 * data["t"]), atol=1e-7)  # ω = √(k/m)


BAD = [
    (["--dt", "0"], "--dt must be a finite number > 0"),
    (["--dt", "-0.1"], "--dt must be a finite number > 0"),
    (["--dt", "nan"], "--dt must be a finite number > 0"),
    (["--dt", "inf"], "--dt must be a finite number > 0"),
    (["--dt", "abc"], "expected a number"),
    (["--t-final", "1.05"], "must be a positive multiple of --dt"),
    (["--t-final", "0"], "--t-final must be a finite number > 0"),
    (["--t-final", "-1"], "--t-final must be a finite number > 0"),
    (["--method", "euler"], "--method 'euler' is not available for oscillator"),
    (["--set", "q0"], "expected NAME=V"),
    (["--set", "=1"], "expected NAME=V"),
    (["--set", "q0=one"], "values must be numbers"),
    (["--set", "q0=1,2"], "q0 takes 1 number"),
    (["--set", "q0=nan"], "values must be finite"),
    (["--set", "p0=inf"], "values must be finite"),
    (["--set", "omega=1"], "unknown parameter 'omega'"),
    (["--set", "m=0"], "m must be finite and > 0"),
    (["--set", "k=-2"], "k must be finite and > 0"),
    (["--save-every", "7"], r"--save-every \(7\) must divide the number of steps \(10\)"),
    (["--save-every", "0"], "expected a positive integer"),
]


def exit_code(argv):
    """Run the CLI in-process; argparse's own errors raise SystemExit, ours return 2."""
    try:
        return main(argv)
    except SystemExit as stop:
        return stop.code


@pytest.mark.parametrize(("extra", "message"), BAD, ids=[" ".join(b[0]) for b in BAD])
def test_bad_input_exits_2_with_message(tmp_path, capsys, extra, message):
    options = {"--method": "rk4", "--dt": "0.1", "--t-final": "1"}
    rest = []
    for flag, value in zip(extra[::2], extra[1::2], strict=True):
        if flag in options:
            options[flag] = value
        else:
            rest += [flag, value]
    out = tmp_path / "x.npz"
    argv = ["simulate", "oscillator", *[x for kv in options.items() for x in kv], *rest,
            "--out", str(out)]
    assert exit_code(argv) == 2
    err = capsys.readouterr().err
    assert "error:" in err
    assert re.search(message, err), err
    assert "Traceback" not in err
    assert not out.exists()


def test_unknown_system_and_bad_out(tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(["simulate", "pendulum9", "--method", "rk4", "--dt", "0.1", "--t-final", "1",
              "--out", str(tmp_path / "x.npz")])
    assert info.value.code == 2
    assert "invalid choice: 'pendulum9'" in capsys.readouterr().err
    code, _, err = run_cli(["simulate", "oscillator", "--method", "rk4", "--dt", "0.1",
                            "--t-final", "1", "--out", str(tmp_path / "x.txt")], capsys)
    assert code == 2 and "ending in .npz" in err
    blocker = tmp_path / "file"
    blocker.write_text("")
    code, _, err = run_cli(["simulate", "oscillator", "--method", "rk4", "--dt", "0.1",
                            "--t-final", "1", "--out", str(blocker / "x.npz")], capsys)
    assert code == 2 and "cannot create folder" in err


def test_failed_integration_exits_1_and_keeps_output(tmp_path, capsys):
    out = tmp_path / "blowup.npz"
    code, _, err = run_cli(["simulate", "oscillator", "--method", "rk4", "--dt", "3",
                            "--t-final", "6000", "--out", str(out)], capsys)
    assert code == 1
    assert "integration failed" in err and "non-finite" in err
    data = np.load(out)
    assert int(data["result"]) == 2 and np.isnan(data["q"][-1])


def test_info_lists_methods(capsys):
    code, out, _ = run_cli(["info"], capsys)
    assert code == 0
    for name in ("rk4", "gl4", "verlet", "galerkin4"):
        assert name in out
    assert "order 4, symmetric, symplectic, implicit" in out


def test_console_script_is_declared_and_runs(tmp_path, capsys):
    scripts = {ep.name: ep.value for ep in entry_points(group="console_scripts")}
    assert scripts.get("lgvi-jax") == "lgvi_jax.cli:run"
    out = tmp_path / "v.npz"
    proc = subprocess.run(
        [sys.executable, "-m", "lgvi_jax.cli", "simulate", "oscillator", "--method", "verlet",
         "--dt", "0.1", "--t-final", "1", "--out", str(out), "--json"],
        capture_output=True, text=True, check=False, timeout=300)
    # (the child ends with os._exit, skipping the interpreter's teardown: what it printed
    # and wrote must be complete all the same)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["method"] == "verlet"
    assert np.load(out)["q"].shape[0] == 11
    # A usage error: exit status 2 and one message, no traceback (the status is main's
    # return value, which the child above passes to the shell; run here, not in a second
    # child, which would cost another import of JAX).
    code, _, err = run_cli(["simulate", "oscillator", "--method", "verlet", "--dt", "-1",
                            "--t-final", "1", "--out", str(out)], capsys)
    assert code == 2
    assert "Traceback" not in err and "--dt must be" in err


def test_closed_standard_output_ends_quietly(tmp_path, monkeypatch, capsys):
    """``lgvi-jax info | head``: the reader closes the pipe; the command stops with the
    shell's SIGPIPE status and no traceback, and standard output then goes to the null
    device (so the flush at exit does not raise again)."""

    class ClosedPipe(io.TextIOBase):
        def __init__(self, fd):
            self.fd = fd

        def write(self, text):
            raise BrokenPipeError(32, "Broken pipe")

        def fileno(self):
            return self.fd

    fd = os.open(tmp_path / "stdout", os.O_WRONLY | os.O_CREAT)
    try:
        monkeypatch.setattr(sys, "stdout", ClosedPipe(fd))
        code = main(["info"])
        assert code == 141
        assert os.path.samestat(os.fstat(fd), os.stat(os.devnull))
    finally:
        os.close(fd)
    assert "Traceback" not in capsys.readouterr().err


# ------------------------------------------------------------------- rigid bodies


def test_simulate_car_pendulum_npz_and_json(tmp_path, capsys):
    """The issue's file keys and shapes, initial state first, and the JSON extras. (10^4
    steps saving every 10th state: the compiled rollout tests/test_lie.py runs for
    hamel-cayley on the car-pendulum, tests/conftest.py: SHARED_ROLLOUT_STEPS, loaded
    rather than compiled again.)"""
    out = tmp_path / "cp.npz"
    code, stdout, _ = run_cli(
        ["simulate", "car-pendulum", "--method", "hamel-cayley", "--dt", "0.005",
         "--t-final", "50", "--save-every", "10", "--set", "v0=0.8,-0.3",
         "--set", "omega0=1,-0.5,3", "--out", str(out), "--json"], capsys)
    assert code == 0
    summary = json.loads(stdout)
    data = np.load(out)
    n = 1001
    shapes = {"t": (n,), "R": (n, 3, 3), "omega": (n, 3), "q": (n, 2), "v": (n, 2),
              "energy": (n,), "momentum": (n, 2), "angular_momentum_z": (n,)}
    for key, shape in shapes.items():
        assert data[key].shape == shape, key
    np.testing.assert_array_equal(data["R"][0], [[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    # Recovered from the saved momenta by the inverse Legendre map (a solve with the mass
    # matrix): a few roundings amplified by its condition (measured up to 1.6e-15).
    np.testing.assert_allclose(data["omega"][0], [1.0, -0.5, 3.0], rtol=1e-13)
    np.testing.assert_allclose(data["v"][0], [0.8, -0.3], rtol=1e-13)
    np.testing.assert_allclose(data["q"][0], [-0.125, -0.0125], rtol=0)
    # The saved invariants are the conserved ones (hamel-cayley: exactly). Over 10^4 steps
    # (tests/test_lie.py's bounds for this length): p by an exact zero sum (measured 0);
    # L_z (|L_z| ~ 5) at most one ulp per step, linearly: 1e4 x 5 x 2.2e-16 = 1.1e-11.
    assert np.abs(data["momentum"][0]).max() > 0.1
    np.testing.assert_allclose(data["momentum"], data["momentum"][:1].repeat(n, 0), atol=1e-13)
    np.testing.assert_allclose(data["angular_momentum_z"], data["angular_momentum_z"][0],
                               atol=1e-11)
    # Every summary value is the one of the saved states (atol: the drifts are
    # round-off, ~1e-14, of which only their size matters).
    assert summary["momentum_drift_max"] == pytest.approx(
        float(np.max(np.abs(data["momentum"] - data["momentum"][0]))), rel=1e-12, abs=1e-15)
    assert summary["angular_momentum_z_drift_max"] == pytest.approx(
        float(np.max(np.abs(data["angular_momentum_z"] - data["angular_momentum_z"][0]))),
        rel=1e-12, abs=1e-15)
    energy = data["energy"]
    assert summary["energy_error_max"] == pytest.approx(
        float(np.max(np.abs(energy / energy[0] - 1))), rel=1e-12)
    assert 1e-9 < summary["energy_error_max"] < 1e-2  # an O(h^2) method at h = 5e-3
    assert summary["newton_iterations_mean"] <= summary["newton_iterations_max"] <= 20
    assert summary["wall_time_s"] >= summary["run_time_s"] > 0
    assert summary["steps_per_second"] == pytest.approx(10_000 / summary["run_time_s"],
                                                        rel=1e-9)
    assert summary["momentum_drift_max"] <= 1e-13
    # A few ulps per product as a random walk over 10^4 steps: sqrt(1e4) x 10 eps = 2e-13
    # (tests/test_lie.py's bound 1e-12, measured 3.5e-14).
    assert summary["orthogonality_error_max"] < 1e-12
    assert 1 <= summary["newton_iterations_mean"] <= 4
    assert summary["orthogonality_error_max"] == pytest.approx(
        float(np.max(data["orthogonality_error"])), rel=1e-12)


# The steps and saving strides of the rollouts tests/test_lie.py compiles for these systems
# with lgvi (the free body: 60 steps of 0.05 every state saved, the paper's equations test;
# the heavy top: 2000 steps of 5e-3 every 10th, the momentum-map test), so that the command
# line loads them instead of compiling its own. Drifts: round-off, one ulp of |L| (~3, ~1)
# per step at most, over 60 steps 4e-14, over 2000 steps 4.4e-13 (test_lie's bound).
@pytest.mark.parametrize("system, key, args, n_saved", [
    ("free-rigid-body", "angular_momentum", ["--dt", "0.05", "--t-final", "3"], 61),
    ("heavy-top", "angular_momentum_z",
     ["--dt", "0.005", "--t-final", "10", "--save-every", "10"], 201)],
    ids=["free-rigid-body-angular_momentum", "heavy-top-angular_momentum_z"])
def test_simulate_other_rigid_systems(tmp_path, capsys, system, key, args, n_saved):
    out = tmp_path / f"{system}.npz"
    code, stdout, _ = run_cli(
        ["simulate", system, "--method", "lgvi", *args, "--out", str(out), "--json"], capsys)
    assert code == 0
    data = np.load(out)
    assert data["R"].shape == (n_saved, 3, 3) and data["omega"].shape == (n_saved, 3)
    assert json.loads(stdout)[f"{key}_drift_max"] < 1e-12


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--set", "R0=1,0,0,0,1,0,0,0,1.1"], "R0 is not in SO(3)"),
        (["--set", "R0=1,0,0,0,1,0,0,0,-1"], "R0 is not in SO(3)"),  # a reflection
        (["--set", "J=1,0,0,0,1,0,0,0,3"], "J is not a physical inertia"),
        (["--set", "J=1,0.5,0,0,1,0,0,0,1"], "J must be symmetric"),
        (["--set", "J=-1,0,0,0,1,0,0,0,1"], "J is not a physical inertia"),
        (["--set", "rho_c=1,2"], "rho_c takes 3 number"),
        (["--set", "m=0"], "m must be finite and > 0"),
        (["--set", "omega=1,2,3"], "unknown parameter 'omega'"),
        (["--method", "gl6"], "not available for car-pendulum"),
    ],
)
def test_car_pendulum_bad_input(tmp_path, capsys, extra, message):
    out = tmp_path / "x.npz"
    args = ["simulate", "car-pendulum", "--method", "lgvi", "--dt", "0.01", "--t-final", "1",
            "--out", str(out), *extra]
    code, _, err = run_cli(args, capsys)
    assert code == 2
    assert message in err and "Traceback" not in err
    assert not out.exists()
