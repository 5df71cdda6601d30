"""The stability experiment: failure detection (energy blow-up, non-finite values, Newton
not converging) on small cases and the bracketing of the limit. The quick run of the whole
study, its files and limits, is tested on `lgvi-jax reproduce --full --quick`
(tests/test_experiments.py), which runs it once."""

import numpy as np
import pytest

import lgvi_jax as lj
from lgvi_jax.studies import stability as st
from lgvi_jax.trajectory import RESULTS


@pytest.fixture(scope="module")
def oscillator():
    model = lj.HarmonicOscillator(m=1.0, k=1.0)
    return model, model.state(q0=1.0, p0=0.0)


@pytest.mark.parametrize(("method", "unstable", "stable"),
                         [(lj.RK4, 3.0, 2.5), (lj.StormerVerlet, 2.1, 1.9)])
def test_unstable_step_fails_and_stable_one_does_not(oscillator, method, unstable, stable):
    model, s0 = oscillator
    omega = float(model.omega)
    bad = st.probe(model, method(), s0, unstable / omega, st.OSC_STEPS)
    good = st.probe(model, method(), s0, stable / omega, st.OSC_STEPS)
    assert bad["failed"] and "energy" in bad["reason"] and bad["step"] >= 0
    assert bad["energy_error_max"] > st.ENERGY_THRESHOLD
    assert not good["failed"] and good["reason"] is None
    assert good["energy_error_max"] <= st.ENERGY_THRESHOLD


def test_nonfinite_state_is_reported(oscillator):
    model, s0 = oscillator
    # Without the energy criterion RK4 at h·ω = 100 overflows within a few dozen steps.
    r = st.probe(model, lj.RK4(), s0, 100.0, 10_000, threshold=np.inf)
    assert r["failed"] and r["code"] == RESULTS.nonfinite
    assert "non-finite" in r["reason"] and 0 <= r["step"] < 10_000


def test_newton_failure_is_reported(oscillator):
    model, s0 = oscillator
    # One Newton iteration cannot confirm convergence (the update test needs a second).
    method = lj.GaussLegendre(stages=2, newton=lj.Newton(max_steps=1))
    r = st.probe(model, method, s0, 0.1, 100)
    assert r["failed"] and r["code"] == RESULTS.max_steps_reached
    assert "Newton" in r["reason"] and r["step"] == 0


def test_find_limit_brackets_a_known_boundary():
    def at(h):  # fails above 1.2345, and again stable at 7 (a non-monotone island)
        return {"h": h, "failed": h > 1.2345 and h != 7.0, "reason": "synthetic"}

    grid = [0.5, 1.0, 2.0, 4.0, 7.0, 8.0]
    lim = st.find_limit(at, grid, rtol=1e-6)
    lo, hi = lim["bracket"]
    assert lo <= 1.2345 < hi and (hi - lo) <= 1e-6 * lo
    assert lim["limit"] == pytest.approx(1.2345, rel=1e-6)
    assert lim["non_monotone"] == [7.0]
    never = st.find_limit(lambda h: {"h": h, "failed": False}, grid, rtol=1e-3)
    assert never["limit"] is None and never["bracket"] == [8.0, None]
