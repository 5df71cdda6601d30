"""Rollouts: saving, failure reporting, batching, differentiation, input validation."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lgvi_jax  # noqa: F401  (float64)
from lgvi_jax import (
    RESULTS,
    RK4,
    GalerkinVI,
    GaussLegendre,
    HarmonicOscillator,
    IntegrationError,
    Newton,
    PhaseState,
    final_state,
    simulate,
)


@pytest.fixture
def osc():
    return HarmonicOscillator(m=1.3, k=0.7)


def osc_state(model):
    """The oscillator tests' initial state."""
    return model.state(q0=0.4, p0=-0.9)


def test_saved_states_and_times(osc):
    s0 = osc_state(osc)
    every = simulate(osc, GaussLegendre(), s0, 0.05, 40)
    sparse = simulate(osc, GaussLegendre(), s0, 0.05, 40, save_every=8, t0=2.0)
    assert every.t.shape == (41,)
    assert sparse.t.shape == (6,)
    np.testing.assert_array_equal(np.asarray(sparse.state.q), np.asarray(every.state.q[::8]))
    np.testing.assert_array_equal(np.asarray(sparse.energy), np.asarray(every.energy[::8]))
    np.testing.assert_allclose(np.asarray(sparse.t), 2.0 + 0.4 * np.arange(6), rtol=1e-15)
    # the initial state comes first, unchanged
    assert float(every.state.q[0, 0]) == 0.4 and float(every.state.p[0, 0]) == -0.9
    # Newton statistics: 0 for the initial state, per-block sums after
    assert int(sparse.newton_steps[0]) == 0
    assert int(jnp.sum(sparse.newton_steps)) == int(jnp.sum(every.newton_steps))
    assert float(sparse.newton_mean) == pytest.approx(float(every.newton_mean))
    assert sparse.ok and every.message == "all 40 steps succeeded"


def test_final_state_matches_simulate(osc):
    s0 = osc_state(osc)
    for method in (RK4(), GalerkinVI()):
        tr = simulate(osc, method, s0, 0.1, 37)
        fs, code = final_state(osc, method, s0, 0.1, 37)
        assert int(code) == 0
        np.testing.assert_array_equal(np.asarray(fs.q), np.asarray(tr.state.q[-1]))


def test_energy_and_invariants_recorded(osc):
    tr = simulate(osc, RK4(), osc_state(osc), 0.1, 10)
    q, p = np.asarray(tr.state.q[:, 0]), np.asarray(tr.state.p[:, 0])
    np.testing.assert_allclose(np.asarray(tr.energy), p**2 / 2.6 + 0.35 * q**2, rtol=1e-14)
    np.testing.assert_array_equal(np.asarray(tr.invariants["energy"]), np.asarray(tr.energy))


def test_newton_failure_is_reported_and_poisons_nothing_silently(osc):
    # One iteration can never confirm convergence (the second confirms it): step 0 fails.
    method = GaussLegendre(newton=Newton(max_steps=1))
    tr = simulate(osc, method, osc_state(osc), 0.1, 20, save_every=5)
    assert int(tr.result) == RESULTS.max_steps_reached
    assert int(tr.failed_step) == 0
    assert float(tr.failed_residual) > 0
    assert not tr.ok
    assert np.all(np.isnan(np.asarray(tr.state.q[1:])))
    assert "step 0" in tr.message and "did not converge" in tr.message
    with pytest.raises(IntegrationError, match=r"step 0 .*did not converge.*residual"):
        simulate(osc, method, osc_state(osc), 0.1, 20, throw=True)


def test_overflow_detected_at_the_right_step():
    # RK4 at h = 3 > 2√2 amplifies the energy by |R(3i)|^2 per step until it overflows.
    model = HarmonicOscillator()
    h = 3.0
    growth = 1 - h**6 / 72 + h**8 / 576
    tr = simulate(model, RK4(), model.default_state(), h, 2000)
    assert int(tr.result) == RESULTS.nonfinite
    k = int(tr.failed_step)
    # |(q, p)| = sqrt(2E) starts at 1 and grows by sqrt(growth) per step: it passes the
    # float64 maximum after 2 log(max) / log(growth) steps.
    predicted = 2 * math.log(np.finfo(np.float64).max) / math.log(growth)
    # The stages overflow a few steps before the state itself does (k4 ~ (h w)^4 |y|).
    assert predicted - 15 < k <= predicted + 1, (k, predicted)
    assert np.all(np.isfinite(np.asarray(tr.state.q[: k + 1])))
    assert np.all(np.isnan(np.asarray(tr.state.q[k + 1 :])))
    with pytest.raises(IntegrationError, match=f"step {k} "):
        tr.raise_if_failed()


def test_vmap_over_initial_states_equals_loop(osc):
    q0 = jnp.linspace(-1.0, 1.0, 5)[:, None]
    p0 = jnp.linspace(0.5, -0.5, 5)[:, None]
    method = GaussLegendre()

    def run(q, p):
        return simulate(osc, method, PhaseState(q=q, p=p), 0.1, 30, save_every=10)

    batch = jax.vmap(run)(q0, p0)
    assert batch.state.q.shape == (5, 4, 1)
    for i in range(5):
        single = run(q0[i], p0[i])
        # The same equations, but vmap may compile to other vector code (SIMD body against
        # remainder loop, FMA contraction) that rounds differently (equal on one machine,
        # 1 ulp apart elsewhere). Each implicit step stops Newton once the update is below
        # 1e-12 relative (Newton()'s tolerance), so two roundings of one solve differ by at
        # most that, and can stop one iteration apart: over 30 steps of a norm-preserving
        # linear map (the oscillator, |q| <= 1.2) that is <= 30 x 1e-12 x 1.2 = 3.6e-11;
        # bound 1e-10 (the motion itself moves q by O(1), a wrong step by >= 1e-3).
        np.testing.assert_allclose(np.asarray(batch.state.q[i]), np.asarray(single.state.q),
                                   rtol=0, atol=1e-10)
        np.testing.assert_allclose(np.asarray(batch.newton_steps[i]),
                                   np.asarray(single.newton_steps), rtol=0, atol=1)


def test_vmap_over_parameters():
    ks = jnp.array([0.5, 1.0, 2.0])

    def final_q(k):
        model = HarmonicOscillator(k=k)
        return simulate(model, GalerkinVI(), model.default_state(), 0.05, 40).state.q[-1, 0]

    got = jax.vmap(final_q)(ks)
    expected = [final_q(k) for k in ks]
    # As above: batched and single rounding may differ (vector code), each of the 40
    # implicit steps by at most the Newton tolerance (1e-12 relative, |q| <= 1):
    # <= 4e-11 over the run; bound 1e-10, far below the O(1) effect of k checked next.
    np.testing.assert_allclose(np.asarray(got), np.asarray(expected), rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(got), np.cos(np.sqrt(np.asarray(ks)) * 2.0),
                               atol=1e-6)


@pytest.mark.parametrize("method", [RK4(), GaussLegendre(), GalerkinVI()],
                         ids=["rk4", "gl4", "galerkin4"])
def test_gradient_through_rollout_matches_finite_differences(method):
    @jax.jit
    def loss(params):
        k, q0, dt = params
        model = HarmonicOscillator(k=k)
        tr = simulate(model, method, model.state(q0=q0, p0=0.2), dt, 200, save_every=20)
        return jnp.sum(tr.state.q[:, 0] ** 2) + tr.energy[-1]

    x = jnp.array([1.3, 0.8, 0.05])
    g = np.asarray(jax.grad(loss)(x))
    eps = 1e-6
    fd = np.array([
        (float(loss(x.at[i].add(eps))) - float(loss(x.at[i].add(-eps)))) / (2 * eps)
        for i in range(3)
    ])
    # Central differences: O(eps^2) truncation, O(1e-16/eps) round-off, so ~1e-9 relative.
    np.testing.assert_allclose(g, fd, rtol=1e-6)
    # forward mode agrees with reverse mode
    _, tangent = jax.jvp(loss, (x,), (jnp.array([1.0, 0.0, 0.0]),))
    assert float(tangent) == pytest.approx(g[0], rel=1e-12)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"dt": 0.0}, "dt must be finite and non-zero"),
        ({"dt": float("nan")}, "dt must be finite"),
        ({"dt": float("inf")}, "dt must be finite"),
        ({"dt": jnp.ones(2)}, "dt must be a scalar"),
        ({"n_steps": 0}, "n_steps must be an integer >= 1"),
        ({"n_steps": 2.5}, "n_steps must be an integer"),
        ({"n_steps": True}, "n_steps must be an integer"),
        ({"save_every": 0}, "save_every must be an integer >= 1"),
        ({"n_steps": 10, "save_every": 3}, r"save_every \(3\) must divide n_steps \(10\)"),
        ({"state0": PhaseState(q=jnp.ones(1, jnp.float32), p=jnp.ones(1, jnp.float32))},
         "must be float64"),
        ({"state0": PhaseState(q=jnp.ones(2), p=jnp.ones(2))}, r"state0.q must have shape"),
        ({"state0": PhaseState(q=jnp.array([jnp.nan]), p=jnp.ones(1))}, "non-finite"),
        ({"state0": (jnp.ones(1), jnp.ones(1))}, "state0 must be a PhaseState"),
        ({"method": "rk4"}, "method must be an integrator"),
    ],
)
def test_bad_input_names_the_argument(osc, kwargs, match):
    args = {"model": osc, "method": RK4(), "state0": osc_state(osc), "dt": 0.1,
            "n_steps": 10}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        simulate(args.pop("model"), args.pop("method"), args.pop("state0"), args.pop("dt"),
                 args.pop("n_steps"), **args)


def test_negative_step_runs_backwards(osc):
    s0 = osc_state(osc)
    tr = simulate(osc, GaussLegendre(), s0, -0.1, 10)
    assert float(tr.t[-1]) == pytest.approx(-1.0)
    ex = osc.exact(s0, -1.0)
    assert float(jnp.abs(tr.state.q[-1, 0] - ex.q[0])) < 1e-6
