"""The work-precision harness: its error measurement on a small case (a known-order method
shows its order), the metrics against independent computations, running without diffrax,
diffrax's error. The quick run of the whole study, its files and values, are tested on
`lgvi-jax reproduce --full --quick` (tests/test_experiments.py), which runs it once."""

import json

import numpy as np
import pytest

from lgvi_jax.studies import work_precision as wp


@pytest.fixture(scope="module")
def oscillator():
    return wp.make_case("oscillator")


@pytest.mark.parametrize(("name", "order", "steps"),
                         [("rk4", 4, (0.1, 0.05, 0.025)), ("verlet", 2, (0.1, 0.05, 0.025))])
def test_harness_shows_the_order(oscillator, name, order, steps):
    slope, errors = wp.observed_error_order(oscillator, name, steps, T=10.0)
    # ±0.2: three steps of a pre-asymptotic fit (the lead's tolerance for this check).
    assert slope == pytest.approx(order, abs=0.2), errors


def test_metrics_match_independent_computation(oscillator):
    method = wp.get_system("oscillator").method("rk4")
    raw = wp.run_ours(oscillator, "rk4", method, 0.05, 10.0, 100, repeats=1)
    got = wp.measure(oscillator, raw, 10.0)
    q = np.asarray(raw["states"].q)[:, 0]
    p = np.asarray(raw["states"].p)[:, 0]
    t = raw["t"]
    assert got["position_error_t10"] == pytest.approx(abs(q[-1] - np.cos(10.0)), rel=1e-12)
    energy = 0.5 * (q**2 + p**2)
    assert got["energy_error_max"] == pytest.approx(np.max(np.abs(energy / 0.5 - 1)),
                                                    rel=1e-9)
    assert t[-1] == 10.0 and not got["failed"] and got["wall_s"] > 0


def test_unknown_methods_are_skipped():
    methods, skipped = wp.resolve_methods("oscillator", ["rk4", "no-such-method"])
    assert list(methods) == ["rk4"] and skipped == ["no-such-method"]
    with pytest.raises(ValueError, match="does not divide"):
        wp._grid(10.0, 100, 0.03)


def test_runs_without_diffrax(oscillator, monkeypatch):
    # `runners.diffrax` is what every part of the study reads (None: not installed).
    monkeypatch.setattr(wp.runners, "diffrax", None)
    cfg = {**wp.config(True), "euclidean_methods": ["rk4"], "scipy_tols": {"DOP853": [1e-8]}}
    res = wp._sweep_system(oscillator, cfg, log=lambda *_: None)
    families = {r["family"] for r in res["runs"]}
    assert families == {"ours", "scipy"}
    scipy_run = next(r for r in res["runs"] if r["family"] == "scipy")
    assert scipy_run["position_error_t10"] < 1e-6


def test_diffrax_error_is_measured(oscillator):
    pytest.importorskip("diffrax")
    r = wp.measure(oscillator, wp.run_diffrax(oscillator, "tsit5", True, 1e-10, 10.0, 100, 1),
                   10.0)
    assert not r["failed"] and r["position_error_t10"] < 1e-7 and r["n_steps"] > 0


def test_reproduce_full_runs_the_full_stages(tmp_path, monkeypatch):
    import lgvi_jax.reproduce as rp

    mine = [("work_precision", "lgvi_jax.studies.work_precision"),
            ("stability", "lgvi_jax.studies.stability")]
    assert all(stage in rp.FULL_STAGES for stage in mine)
    calls = []

    def fake_run(out, quick=False, log=print):
        calls.append(out.name)
        out.mkdir(parents=True, exist_ok=True)
        (out / "summary.md").write_text(f"{out.name} summary\n")
        (out / "results.json").write_text(json.dumps({"quick": quick}))

    # The real stages run in tests/test_experiments.py (`reproduce --full --quick`, all
    # three full stages); here only the wiring, with two of them.
    monkeypatch.setattr(rp, "STAGES", [])
    monkeypatch.setattr(rp, "FULL_STAGES", mine)
    monkeypatch.setattr(wp, "run", fake_run)
    from lgvi_jax.studies import stability

    monkeypatch.setattr(stability, "run", fake_run)
    rp.reproduce(tmp_path, quick=True, log=lambda *_: None)
    assert calls == []  # full=False: the full stages are not run
    rp.reproduce(tmp_path, quick=True, full=True, log=lambda *_: None)
    assert calls == ["work_precision", "stability"]
    logs = []
    rp.reproduce(tmp_path, quick=True, full=True, log=logs.append)  # done: skipped
    assert calls == ["work_precision", "stability"] and sum("already done" in m for m in logs) == 2
    assert "stability summary" in (tmp_path / "README.md").read_text()


def test_regimes_name_the_best_variational_method(tmp_path):
    """Per regime: the winner, our best, our best variational method (Verlet, not RK4, on
    the oscillator) and the peer's ratio over each; a regime no peer meets reads ∞."""
    from lgvi_jax.studies.work_precision import metrics, report

    def run(family, method, value, wall, err, **extra):
        return {"family": family, "method": method, "param": "h" if family == "ours"
                else "rtol", "value": value, "wall_s": wall, "failed": False, "horizon": 10.0,
                "position_error_t10": err, **extra}

    runs = [run("ours", "rk4", 0.1, 1.0, 1e-9), run("ours", "verlet", 0.01, 4.0, 1e-9),
            run("ours", "verlet", 0.1, 0.5, 1e-3), run("diffrax", "diffrax dopri8", 1e-9,
                                                       2.0, 1e-9)]
    long = [run("ours", "verlet", 0.1, 3.0, None, energy_error_max=1e-7,
                momentum_drift_max=1e-12),
            run("diffrax", "diffrax dopri8", 1e-10, 1.0, None, energy_error_max=1e-7,
                momentum_drift_max=1e-6)]
    cfg = {"targets": {"short_tight": 1e-8, "short_moderate": 1e-4, "t50": 1e-5,
                       "long_energy": 1e-6, "long_invariants": 1e-9},
           "horizons": [10.0], "long_horizon": 5000.0}
    regs = metrics.regimes({"systems": {"oscillator": {"runs": runs}},
                            "long_all": {"oscillator": long}}, cfg)
    tight = regs[0]
    assert tight["winner"]["method"] == "rk4" and tight["best_ours"]["method"] == "rk4"
    assert tight["best_variational"]["method"] == "verlet"
    assert tight["peer_over_ours"] == pytest.approx(2.0)
    assert tight["peer_over_variational"] == pytest.approx(0.5)
    every = next(g for g in regs if "all invariants" in g["regime"])
    assert every["best_variational"]["method"] == "verlet" and every["best_peer"] is None
    results = {"regimes": regs, "environment": {"cpu_count": 2, "date": "d", "jax": "j",
                                                 "diffrax": None}, "systems": {}, "files": []}
    text = report.write_summary(results, tmp_path)
    row = next(line for line in text.splitlines()
               if "all invariants" in line and line.startswith("|"))
    assert row.count("∞ (no peer meets it)") == 2
