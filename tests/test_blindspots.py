"""Paths no other test runs (issue 20, section 5): the default ``fit`` optimiser (L-BFGS)
through the library and the CLI, fitting parameters other than ``J``, ``fit --lr/--json``;
sweeps of ``free-rigid-body`` and ``heavy-top`` with ``--set``, ``--sample-every`` and
``--devices auto``; ``lgvi-jax bench``. Each kept small (short horizons, few
trajectories), and each asserts values, not only that something ran."""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("scipy", reason="the reference needs SciPy (the 'dev' extra)")

import lgvi_jax as lj
from lgvi_jax import identify
from lgvi_jax.cli import main
from lgvi_jax.inertia import centroidal_inertia, pivot_inertia
from lgvi_jax.models.rigid_bodies import PAPER_J, PAPER_RHO_C

#: Observations every 0.05 s over 1 s from the independent reference (DOP853 at 1e-13),
#: fitted with steps of 0.01 (100 steps): short enough to compile and run in seconds.
TIMES = np.arange(21) * 0.05
FIT_DT = 0.01
#: The paper's inertia about the mass centre, held fixed when J is not fitted
#: (lgvi_jax.identify: the pivot inertia follows the fitted m and rho_c).
J_C0 = np.asarray(centroidal_inertia(np.asarray(PAPER_J), 1.0, np.asarray(PAPER_RHO_C)))


def _truth(m=1.0, rho_c=PAPER_RHO_C):
    rho_c = np.asarray(rho_c, dtype=np.float64)
    return lj.CarPendulum(m=m, rho_c=rho_c, J=np.asarray(pivot_inertia(J_C0, m, rho_c)))


# --------------------------------------------------------- fit (default, L-BFGS)


def test_library_fit_recovers_the_mass_with_the_default_optimiser():
    """``identify.fit`` with its default optimiser (Levenberg–Marquardt) and ``names=("m",)``,
    from the paper's m = 1 to data of m = 1.25: the mass recovered to the step's bias
    (the O(h^2) error of lgvi at h = 0.01 against the exact reference; 1e-2 allowed), the
    loss down to the step's floor, J_c untouched."""
    m_true = 1.25
    obs = identify.check_observations(identify.observe(_truth(m=m_true), TIMES), FIT_DT)
    result = identify.fit(obs, FIT_DT, names=("m",), iterations=60)
    assert result.optimizer == "gauss-newton" and result.names == ("m",)
    assert abs(float(result.model.m) - m_true) <= 1e-2 * m_true, float(result.model.m)
    # The loss cannot reach 0: the step's own error stays (O(h^2) in the attitude, a
    # loss of ~1e-6). The fit gets down to that floor, the loss at the true mass, from
    # ~3e-3 at the start.
    _, params, problem = identify.make_loss(obs, FIT_DT, names=("m",),
                                            model=_truth(m=m_true))
    # The loss as the fit evaluates it (identify._loss_value: the sum of squares of the
    # residuals from the Gauss-Newton program the fit compiled, the same problem's shapes),
    # not a compilation of another program for the same rollout.
    floor = identify._loss_value("gauss-newton", params, problem)
    assert result.loss_final <= 1.01 * floor < 1e-2 * result.loss_initial, (
        result.loss_initial, result.loss_final, floor)
    assert result.stopped == "converged" and result.iterations < 60
    np.testing.assert_allclose(result.J_c, J_C0, atol=1e-12)
    np.testing.assert_array_equal(result.model.rho_c, PAPER_RHO_C)


def test_fit_command_lbfgs_rho_c_with_lr_and_json(tmp_path, capsys):
    """``lgvi-jax fit --fit rho_c --optimizer lbfgs --lr 0.5 --json``: the printed JSON
    and the written file carry the recovered mass-centre offset near the truth, a loss
    brought down from the start's, and the options used."""
    rho_true = np.array([0.2, 0.3, 0.9])
    data = identify.observe(_truth(rho_c=rho_true), TIMES)
    path = tmp_path / "obs.npz"
    np.savez(path, **data)
    out = tmp_path / "fit.json"
    code = main(["fit", "car-pendulum", "--data", str(path), "--method", "lgvi",
                 "--dt", str(FIT_DT), "--fit", "rho_c", "--optimizer", "lbfgs", "--lr", "0.5",
                 "--iterations", "80", "--out", str(out), "--json"])
    assert code == 0
    printed = json.loads(capsys.readouterr().out)
    written = json.loads(out.read_text())
    assert "loss_history" not in printed and "loss_history" in written
    for report in (printed, written):
        assert report["optimizer"] == "lbfgs" and report["fitted"] == ["rho_c"]
        rho = np.asarray(report["rho_c"])
        np.testing.assert_allclose(rho, report["values"]["rho_c"], rtol=0, atol=0)
        # From (0.25, 0.25, 1.0), 0.12 away: recovered to the step's bias.
        assert np.linalg.norm(rho - rho_true) <= 1e-2, rho
        # Down to the step's error floor (~1e-6, see the test above), from far above it.
        assert report["loss_final"] < 1e-2 * report["loss_initial"]
        assert report["loss_final"] < 1e-5
        assert report["values"]["m"] == 1.0
        np.testing.assert_allclose(report["values"]["J_c"], J_C0, atol=1e-12)
    assert written["loss_history"][-1] == written["loss_final"]


# ------------------------------------------------------------------ sweeps of other systems


def _rows(out):
    return list(csv.DictReader(open(out / "trajectories.csv")))


def test_free_rigid_body_sweep_with_set_and_devices_auto(tmp_path):
    """``lgvi-jax sweep free-rigid-body --set J=... --set omega0=... --devices auto`` in a
    child process (``auto`` only acts before JAX starts): one device per core, and the
    physics of the given body. lgvi conserves the free body's energy and its spatial
    angular momentum to round-off (its discrete flow is the exact flow of a modified
    system sharing both invariants); rkmk4, in the same run, does not (O(h^4) drift)."""
    out = tmp_path / "frb"
    args = [sys.executable, "-m", "lgvi_jax.cli", "sweep", "free-rigid-body",
            "--method", "lgvi,rkmk4", "--dt", "0.05", "--t-final", "5", "--n", "3",
            "--set", "J=2,0,0,0,2.5,0,0,0,4", "--set", "omega0=0.3,1.5,0.2",
            "--devices", "auto", "--out", str(out), "--json"]
    run = subprocess.run(args, capture_output=True, text=True, timeout=300, check=False)
    assert run.returncode == 0, run.stderr
    summary = json.loads(run.stdout)
    assert len(summary["devices"]) == (os.cpu_count() or 1)
    assert summary["config"]["parameters"] == {"J": [2.0, 0, 0, 0, 2.5, 0, 0, 0, 4.0],
                                               "omega0": [0.3, 1.5, 0.2]}
    rows = {row["method"]: row for row in summary["rows"]}
    assert rows["lgvi"]["failed"] == rows["rkmk4"]["failed"] == 0
    # Round-off over 100 steps: a few ulps per step of a relative energy error, at most
    # linear accumulation, 100 x 4 x 1.1e-16 ~ 4e-14 (measured 3e-15); |L| ~ 4, so 1e-12
    # absolute for the momentum (measured 8e-15). rkmk4: measured 1e-8 and 1e-7.
    assert rows["lgvi"]["energy_error_max_max"] <= 1e-12
    assert rows["lgvi"]["angular_momentum_drift_max_max"] <= 1e-12
    assert rows["rkmk4"]["energy_error_max_max"] > 1e-10
    assert rows["rkmk4"]["angular_momentum_drift_max_max"] > 1e-10
    for key in ("lgvi", "rkmk4"):
        assert rows[key]["orthogonality_error_max_max"] <= 1e-13  # 100 products of exp's
    assert len(_rows(out)) == 2 * 3


def _heavy_top(tmp_path, capsys, name, *extra):
    out = tmp_path / name
    argv = ["sweep", "heavy-top", "--method", "lgvi", "--dt", "0.01", "--t-final", "1",
            "--n", "2", "--out", str(out), "--json", *extra]
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    return summary, {int(r["index"]): r for r in _rows(out)}


def test_heavy_top_sweep_set_and_sample_every(tmp_path, capsys):
    """``sweep heavy-top`` with ``--set`` and ``--sample-every``. With ``--set g=0`` the
    top is a free body: lgvi's energy error falls from O(h^2) to round-off (so the value
    reaches the physics). ``--sample-every K`` only thins the samples the maxima are taken
    over: the trajectory, hence the final error, is the same bit for bit; the max over
    every 7th step is at most the max over every step; with K beyond the run's 100 steps
    only the final state is sampled, so max = final."""
    _, every = _heavy_top(tmp_path, capsys, "k1", "--sample-every", "1")
    _, seventh = _heavy_top(tmp_path, capsys, "k7", "--sample-every", "7")
    _, last = _heavy_top(tmp_path, capsys, "k1000", "--sample-every", "1000")
    for i in (0, 1):
        final = every[i]["energy_error_final"]
        assert seventh[i]["energy_error_final"] == final == last[i]["energy_error_final"]
        assert float(seventh[i]["energy_error_max"]) <= float(every[i]["energy_error_max"])
        assert last[i]["energy_error_max"] == final
        assert float(every[i]["energy_error_max"]) > float(final)  # an oscillating error
        # The vertical angular momentum of the top: round-off over 100 steps either way.
        assert float(every[i]["angular_momentum_z_drift_max"]) <= 1e-12
    summary, free = _heavy_top(tmp_path, capsys, "g0", "--set", "g=0", "--set", "m=2")
    assert summary["config"]["parameters"] == {"g": [0.0], "m": [2.0]}
    for i in (0, 1):
        assert float(every[i]["energy_error_max"]) > 1e-6  # O(h^2) with gravity
        assert float(free[i]["energy_error_max"]) <= 1e-12  # round-off without (as above)


# ---------------------------------------------------------------------------------- bench


def test_bench_markdown_reports_the_measured_values(tmp_path):
    """The writer of ``bench.md`` (lgvi_jax/bench/throughput.py) on a small synthetic
    result: every row's numbers appear, the ratio is JAX over Numba, a missing baseline is
    "n/a", the gradient, fit and long-run tables list each row."""
    from lgvi_jax.bench.throughput import _markdown

    jax_row = {"single_steps_per_s": 12345.0, "batch_steps_per_s": 67890.0,
               "single_compile_s": 1.5, "batch_compile_s": 2.25, "batch_xla_memory_mb": 0.5,
               "single_failed": 0, "batch_failed": 1, "batch_energy_error_max": 1.25e-5}
    numba_row = {"single_steps_per_s": 24690.0, "batch_steps_per_s": 13578.0,
                 "single_failed": 0, "batch_failed": 0, "batch_energy_error_max": 1.5e-5}
    result = {
        "dt": 5e-3, "steps": 50, "batch": 4, "repeats": 2, "time_budget_s": 20.0,
        "environment": {"devices": ["cpu:0", "cpu:1"], "platform": "cpu",
                        "device_kind": "cpu", "cpu_count": 2, "jax": "0.0"},
        "numba": {"version": "0.0", "threads": 2},
        "throughput": [
            {"system": "car-pendulum", "method": "lgvi", "engine": "scalar", "jax": jax_row,
             "numba": numba_row, "ratio_single": 0.5, "ratio_batch": 5.0},
            {"system": "heavy-top", "method": "lgvi@4", "engine": "scalar", "jax": jax_row,
             "numba": None},
        ],
        "gradient": [
            {"method": "lgvi", "engine": "array", "steps": 50, "checkpoint_every": 5,
             "forward_s": 0.002, "gradient_s": 0.005, "gradient_over_forward": 2.5,
             "forward_compile_s": 3.0, "gradient_compile_s": 9.0, "gradient_rel_diff": 0.0},
            {"method": "lgvi", "engine": "scalar", "steps": 50, "checkpoint_every": 5,
             "forward_s": 0.001, "gradient_s": 0.004, "gradient_over_forward": 4.0,
             "forward_compile_s": 5.0, "gradient_compile_s": 20.0,
             "gradient_rel_diff": 2.5e-12},
        ],
        "fit": {"dt": 5e-3, "t_final": 5.0, "method": "lgvi", "engine": "general",
                "optimizer": "lbfgs", "wall_s": 42.5, "compile_s": 30.25, "iterations": 250,
                "stopped": "converged", "start_rel_error_J_c": 0.2,
                "rel_error_J_c": 0.0019, "rel_error_J": 0.0001},
        "long_run": [{"n_steps": 10_000, "saved_states": 11, "peak_rss_mb": 321.0,
                      "steps_per_s": 4.5e4}],
        "process_peak_rss_mb": 512.0,
    }
    text = _markdown(result)
    assert "h = 0.005, 50 steps" in text and "batch of 4" in text
    assert ("| car-pendulum | lgvi | scalar | 1.23e+04 | 2.47e+04 | 0.50 | 6.79e+04 | 1.36e+04 "
            "| 5.00 | 1, 0 | 1.25e-05, 1.50e-05 | 1.50, 2.25 | 0.50 |") in text
    assert ("| heavy-top | lgvi@4 | scalar | 1.23e+04 | n/a | n/a | 6.79e+04 | n/a | n/a | "
            "1, n/a | 1.25e-05, n/a | 1.50, 2.25 | 0.50 |") in text
    assert "metrics every step" in text and "Both sides compute, after every step" in text
    assert "| lgvi | array | 5 | 2 | 5 | 2.50 | 3.0, 9.0 | – |" in text
    assert "| lgvi | scalar | 5 | 1 | 4 | 4.00 | 5.0, 20.0 | 2.5e-12 |" in text
    assert "| 42.5 | 30.2 | 250 | converged | 0.190% | 0.010% |" in text
    assert "(20% off)" in text
    assert "| 10000 | 11 | 321 | 4.5e+04 |" in text
    assert "2 cpu device(s)" in text and "Numba 0.0 with 2 threads" in text
    assert text.endswith("benchmark process: 512 MB.\n")


def test_accelerator_bench_reports_the_sweeps_work(tmp_path, capsys):
    """experiments/bench_accelerator.py (the GPU measurement; here on the CPU, tiny): one
    row per system, method, engine and batch, written as it goes, each with the same
    worst energy error and Newton iterations as the sweep's own batched run of those
    states, and a positive throughput."""
    path = Path(__file__).resolve().parent.parent / "experiments" / "bench_accelerator.py"
    spec = importlib.util.spec_from_file_location("bench_accelerator", path)
    bench_accelerator = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench_accelerator)
    from lgvi_jax.sweep import initial_conditions, run_batch, sweep_method
    from lgvi_jax.systems import get_system

    out = tmp_path / "acc"
    code = bench_accelerator.main(["--out", str(out), "--systems", "free-rigid-body",
                                   "--methods", "lgvi", "--engines", "scalar",
                                   "--batches", "2", "--steps", "20", "--repeats", "1"])
    assert code == 0
    report = json.loads((out / "accelerator.json").read_text())
    assert report["platform"] == "cpu" and len(report["rows"]) == 1
    row = report["rows"][0]
    assert (row["system"], row["method"], row["engine"], row["batch"], row["steps"]) == (
        "free-rigid-body", "lgvi", "scalar", 2, 20)
    assert row["failed"] == 0 and row["steps_per_s"] > 0 and row["compile_s"] > 0
    model, s0 = get_system("free-rigid-body").build()
    states = initial_conditions(model, s0, 2, bench_accelerator.PERTURB, bench_accelerator.SEED)
    ref = run_batch(model, sweep_method("free-rigid-body", "lgvi"), states,
                    bench_accelerator.DT, 20)
    assert row["energy_error_max"] == float(np.max(ref["energy_error_max"]))
    assert row["newton_mean"] == float(np.mean(ref["newton_mean"]))
    assert json.loads(capsys.readouterr().out.splitlines()[-1]) == row


def test_bench_timer_alternates_the_sides_of_a_ratio():
    """``_timed_alternating`` on a fake clock: the sides run in turn (a, b, a, b, ...), a
    side stops once it ran ``repeats`` times and ``min_s`` in all or ran ``budget_s`` in
    all (then the other goes on alone), and each reports its fastest run, its run count
    and its first result."""
    from lgvi_jax.bench.throughput import _timed_alternating

    now = [0.0]
    calls: list[str] = []

    def side(name, durations):
        it = iter(durations)

        def run():
            calls.append(name)
            now[0] += next(it)
            return f"{name}{len(calls)}"
        return run

    # a needs 3 runs and 1 s in all: 7 runs (1.025 s); b has 1.35 s after its 3 runs.
    a = side("a", [0.1, 0.3] + [0.125] * 20)
    b = side("b", [0.5, 0.4, 0.45] + [0.4] * 20)
    (best_a, runs_a, first_a), (best_b, runs_b, first_b) = _timed_alternating(
        [a, b], repeats=3, budget_s=20.0, min_s=1.0, clock=lambda: now[0])
    assert calls[:6] == ["a", "b"] * 3 and set(calls[6:]) == {"a"}
    assert (runs_a, runs_b) == (7, 3) and len(calls) == 10
    assert best_a == pytest.approx(0.1) and best_b == pytest.approx(0.4)
    assert (first_a, first_b) == ("a1", "b2")
    # The budget ends a slow side after one run; with no minimum time, `repeats` runs.
    calls.clear()
    slow, fast = side("s", [30.0] * 3), side("f", [0.01] * 10)
    (_, runs_s, _), (_, runs_f, _) = _timed_alternating(
        [slow, fast], repeats=3, budget_s=20.0, min_s=0.0, clock=lambda: now[0])
    assert (runs_s, runs_f) == (1, 3) and calls == ["s", "f", "f", "f"]


def test_bench_command_quick_run(tmp_path, capsys):
    """``lgvi-jax bench --quick`` end to end on one method and one system, few steps and a
    small batch, its throughput part (Numba's compilation included): on the car-pendulum
    the scalar engine's step beside the Numba baseline. bench.json holds positive throughputs, no
    failed trajectory, the same worst energy error on both sides (the same equations and
    diagnostics: to the solvers' tolerance) and ratios that are JAX over Numba; bench.md
    is what was printed. (``--systems car-pendulum --parts throughput``: the heavy top's
    row, without a baseline, and the gradient part, timings of a
    jax.grad whose values are checked elsewhere (tests/test_identify.py: checkpointed
    gradients equal plain ones; tests/test_lie.py: gradients against central
    differences), compiled four programs, ~15 s, for no other check; their rows in
    bench.md: test_bench_markdown_reports_the_measured_values above.)"""
    out = tmp_path / "bench"
    code = main(["bench", "--out", str(out), "--quick", "--steps", "20", "--batch", "2",
                 "--methods", "lgvi", "--systems", "car-pendulum", "--parts", "throughput",
                 "--no-long-run"])
    assert code == 0
    printed = capsys.readouterr().out
    result = json.loads((out / "bench.json").read_text())
    assert printed == (out / "bench.md").read_text()
    assert result["quick"] is True and result["steps"] == 20 and result["batch"] == 2
    assert "long_run" not in result and "fit" not in result and "gradient" not in result
    rows = {(r["system"], r["method"], r["engine"]): r for r in result["throughput"]}
    assert set(rows) == {("car-pendulum", "lgvi", "scalar")}
    assert result["single_compiles"] == 2 and result["batch_compiles"] == 2
    for row in rows.values():
        j = row["jax"]
        # One trajectory compiled twice: the speed reported is one of the two (the median,
        # here the slower), each listed in increasing order.
        each = j["single_steps_per_s_each"]
        assert len(each) == 2 and each[0] <= each[1] and j["single_steps_per_s"] == each[0]
        # Compile times: the median over the compilations (of two: their mean), each
        # one listed.
        for label in ("single", "batch"):
            each_s = j[f"{label}_compile_s_each"]
            assert len(each_s) == 2 and min(each_s) > 0
            assert j[f"{label}_compile_s"] == pytest.approx(sum(each_s) / 2, rel=1e-12)
        assert j["single_failed"] == 0 and j["batch_failed"] == 0
        assert j["single_steps_per_s"] > 0 and j["batch_steps_per_s"] > 0
        assert 0 < j["batch_energy_error_max"] < 1e-3 and j["batch_newton_mean"] >= 1
    car = rows["car-pendulum", "lgvi", "scalar"]
    n = car["numba"]
    assert n["single_failed"] == 0 and n["batch_failed"] == 0
    assert n["single_steps_per_s"] > 0 and n["batch_steps_per_s"] > 0
    assert n["batch_energy_error_max"] == pytest.approx(car["jax"]["batch_energy_error_max"],
                                                        rel=1e-6)
    for k in ("single", "batch"):
        assert car[f"ratio_{k}"] == pytest.approx(
            car["jax"][f"{k}_steps_per_s"] / n[f"{k}_steps_per_s"], rel=1e-12)
    assert "| car-pendulum | lgvi | scalar |" in printed
    # Every result names the CPU it was measured on (the same command measures differently
    # on another one), in bench.json and in the header of bench.md.
    cpu = result["environment"]["cpu"]
    assert cpu and f"CPU cores ({cpu}" in printed.splitlines()[2]
