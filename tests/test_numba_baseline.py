"""The Numba baselines of the benchmark solve the same discrete equations as our VIs, and
their per-step diagnostics compute what the sweep's metrics compute."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lgvi_jax as lj

pytest.importorskip("numba")
from conftest import SHARED_ROLLOUT_STEPS, SHARED_SAVE_EVERY

from lgvi_jax.bench import numba_lgvi as nb


def _engine(model, method, s0, dt, n):
    """The engine's first ``n`` steps of ``dt`` from ``s0``: ``(ok, states, invariants)``,
    the states after 0, 10, 20, ..., n steps and their invariants. Taken from a run of
    SHARED_ROLLOUT_STEPS steps saving every SHARED_SAVE_EVERY-th state: the compiled
    rollout that tests/test_lie.py runs for every VI method (tests/conftest.py), loaded
    rather than compiled again; ``ok``: every step of that run succeeded."""
    traj = lj.simulate(model, method, s0, dt, SHARED_ROLLOUT_STEPS,
                       save_every=SHARED_SAVE_EVERY)
    assert n % SHARED_SAVE_EVERY == 0
    states, invariants = jax.tree.map(lambda x: x[: n // SHARED_SAVE_EVERY + 1],
                                      (traj.state, traj.invariants))
    return traj.ok, states, invariants


@pytest.mark.parametrize("moving", [False, True])
def test_numba_lgvi_matches_the_engine(moving):
    R0 = np.asarray(lj.so3.exp(np.array([0.3, -0.2, 1.0])))
    model = lj.CarPendulum()
    s0 = model.state() if not moving else model.state(v0=(1.5, -0.7), omega0=(1.0, -0.5, 3.0),
                                                      R0=R0)
    params = nb.params_from_model(model)
    R, mu, q, p = (np.asarray(x) for x in (s0.R, s0.mu, s0.q, s0.p))
    R1, mu1, q1, p1, its, code = nb.rollout("lgvi", R, mu, q, p, 5e-3, 200, params)
    ok, st, _ = _engine(model, lj.LGVI(), s0, 5e-3, 200)
    assert code == 0 and ok
    # Both solve to |Δξ| <= 1e-12 (1 + |ξ|) per step, from different initial guesses, so
    # the end states agree to the accumulated solver tolerance, not to the last bit.
    for ours, theirs in zip((st.R, st.mu, st.q, st.p), (R1, mu1, q1, p1), strict=True):
        np.testing.assert_allclose(theirs, np.asarray(ours)[-1], atol=1e-11)
    # The engine's solver: chord iterations (one Jacobian per step), ~4 per step.
    assert 2.0 <= its / 200 <= 5.0
    # The batch runs the same compiled loop: the same iterates, bit for bit.
    batch = [np.stack([x, x]) for x in (R, mu, q, p)]
    *theirs, its_b, codes = nb.rollout_batch("lgvi", *batch, 5e-3, 200, params)
    assert np.all(codes == 0) and np.all(its_b == its)
    for a, b in zip((R1, mu1, q1, p1), theirs, strict=True):
        np.testing.assert_array_equal(b, np.stack([a, a]))
    # A large step (θ = h|ξ| ≈ 0.2; the engine's compiled rollout is reused: dt is not
    # static): agreement to the accumulated solver tolerance.
    ok, st, _ = _engine(model, lj.LGVI(), s0, 0.04, 200)
    *theirs, its, code = nb.rollout("lgvi", R, mu, q, p, 0.04, 200, params)
    assert ok and code == 0
    for a, b in zip((st.R, st.mu, st.q, st.p), theirs, strict=True):
        np.testing.assert_allclose(b, np.asarray(a)[-1], rtol=0, atol=2e-10)
    # Failure is reported, not hidden: a non-finite state, and a step far too large for
    # Newton.
    *_, code = nb.rollout("lgvi", R, mu * np.nan, q, p, 5e-3, 5, params)
    assert code == 2
    *_, code = nb.rollout("lgvi", R, mu * 1e4, q, p, 5e-3, 5, params)
    assert code != 0


def test_every_vi_of_the_benchmark_has_a_baseline():
    assert nb.METHODS == ("lgvi", "hamel", "hamel-cayley", "hamel-exact")
    with pytest.raises(ValueError, match="method must be one of"):
        nb.rollout("rk4", np.eye(3), np.zeros(3), np.zeros(2), np.zeros(2), 5e-3, 1,
                   nb.params_from_model(lj.CarPendulum()))


@pytest.mark.parametrize("name", ["hamel", "hamel-cayley", "hamel-exact"])
def test_numba_hamel_matches_the_engine(name):
    from lgvi_jax.systems.car_pendulum import moving_problem

    # The paper's state and a moving cart (generic attitude, cart momentum); both problems
    # share their parameters, so one batch holds both.
    moving = moving_problem()
    models = (lj.CarPendulum(), moving.model)
    states = (models[0].default_state(), moving.state0)
    params = nb.params_from_model(models[0])
    np.testing.assert_array_equal(nb.params_from_model(models[1]), params)
    starts = [tuple(np.asarray(x) for x in (s.R, s.mu, s.q, s.p)) for s in states]
    ends = []
    for model, s0, (R, mu, q, p) in zip(models, states, starts, strict=True):
        ok, st, _ = _engine(model, lj.RIGID_METHODS[name](), s0, 5e-3, 200)
        assert ok
        ours = [np.asarray(x)[-1] for x in (st.R, st.mu, st.q, st.p)]
        ends.append(ours)
        *theirs, its, code = nb.rollout(name, R, mu, q, p, 5e-3, 200, params)
        # The engine's solver: chord iterations (one Jacobian per step), ~4 per step.
        assert code == 0 and 2.0 <= its / 200 <= 5.0
        # Same equations, solved to |Δξ| <= 1e-12 (1 + |ξ|) from different initial guesses:
        # the end states agree to round-off grown over 200 steps (measured up to 1.1e-13;
        # each solve stops far inside its tolerance, the last update ~1e-20).
        for a, b in zip(ours, theirs, strict=True):
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-11)
    batch = [np.stack(x) for x in zip(*starts, strict=True)]
    *theirs, its, codes = nb.rollout_batch(name, *batch, 5e-3, 200, params)
    assert np.all(codes == 0) and np.all(its >= 400)
    for k, b in enumerate(theirs):
        np.testing.assert_allclose(b, np.stack([e[k] for e in ends]), rtol=0, atol=1e-11)
    # A large step (θ = h|ξ| ≈ 0.2): the closed-form branches of exp and dexp⁻¹ (the
    # engine's compiled rollout is reused: dt is not static). Both solvers stop at the
    # same tolerance from different iterates; a single step agrees to ~1e-15, 200 steps
    # to the accumulated tolerance.
    model, (R, mu, q, p) = models[1], starts[1]
    ok, st, _ = _engine(model, lj.RIGID_METHODS[name](), states[1], 0.04, 200)
    *theirs, its, code = nb.rollout(name, R, mu, q, p, 0.04, 200, params)
    assert ok and code == 0
    for a, b in zip((st.R, st.mu, st.q, st.p), theirs, strict=True):
        np.testing.assert_allclose(b, np.asarray(a)[-1], rtol=0, atol=5e-11)
    # Failure is reported, not hidden: a non-finite state, and (exp map: Newton cannot
    # follow a rotation of ~250 rad per step; the Cayley map has a root there) a step far
    # too large, which hits the iteration cap as in the engine.
    R, mu, q, p = starts[0]
    *_, code = nb.rollout(name, R, mu * np.nan, q, p, 5e-3, 5, params)
    assert code == 2
    if name != "hamel-cayley":
        *_, code = nb.rollout(name, R, mu * 1e4, q, p, 5e-3, 5, params)
        assert code == 1


# ---------------------------------------------------------------------------------------
# The per-step diagnostics of the benchmark's baselines (``sweep_metrics``) against the
# sweep's metrics (lgvi_jax.sweep)
# ---------------------------------------------------------------------------------------

#: Unit roundoff of float64.
U = 2.0**-53


def _magnitudes(model, states):
    """Per state: the energy's condition-free size ``T = ½(Σ|μ_i ω_i| + Σ|p_i v_i|) + m g
    Σ|r3_i ρ_i|`` (the sum of the magnitudes of its terms), the condition number of the
    3x3 Schur complement the inverse Legendre map solves, and the size of the vertical
    angular momentum's terms."""
    m, M, g = (float(x) for x in (model.m, model.M, model.g))
    rho, J = np.asarray(model.rho_c), np.asarray(model.J)
    R, mu, q, p = (np.asarray(x) for x in (states.R, states.mu, states.q, states.p))
    omega, v = (np.asarray(x) for x in jax.vmap(model.velocities)(states.R, states.mu,
                                                                  states.q, states.p))
    T = 0.5 * (np.abs(mu * omega).sum(-1) + np.abs(p * v).sum(-1)) + m * g * np.abs(
        R[:, 2] * rho).sum(-1)
    c = np.cross(rho, R[:, 2])
    schur = J - m * m / (m + M) * (rho @ rho * np.eye(3) - np.outer(rho, rho)
                                   - c[:, :, None] * c[:, None, :])
    kappa = np.linalg.cond(schur)
    L = np.abs(R[:, 2] * mu).sum(-1) + np.abs(q[:, 0] * p[:, 1]) + np.abs(q[:, 1] * p[:, 0])
    return T, kappa, L


def test_numba_diagnostics_equal_the_sweeps_on_the_same_states():
    """The compiled diagnostics of the baselines (energy, vertical angular momentum, cart
    momentum, orthogonality error, reduced to the sweep's running maxima and final value)
    on the very states of a JAX trajectory, against the same quantities from the JAX
    model (what the sweep's metrics evaluate) reduced by the sweep's definitions: equal to
    rounding, with bounds from the standard error analysis of the two evaluations."""
    from lgvi_jax.bench import numba_hamel as nh
    from lgvi_jax.systems.car_pendulum import moving_problem

    spec = moving_problem()  # generic attitude, cart moving: every term of H is non-zero
    model = spec.model
    # 201 states: every 10th of the first 2000 steps
    ok, st, inv = _engine(model, lj.LGVI(), spec.state0, 5e-3, 2000)
    assert ok
    R, mu, q, p = (np.ascontiguousarray(np.asarray(x)) for x in (st.R, st.mu, st.q, st.p))
    params = nb.params_from_model(model)
    E_jax = np.asarray(inv["energy"])
    A, X = np.empty((3, 3)), np.empty(3)
    E_nb = np.array([nh.energy(R[k], mu[k], q[k], p[k], params, A, X) for k in range(len(R))])
    Lz_nb = np.array([nh.angular_momentum_z(R[k], mu[k], q[k], p[k]) for k in range(len(R))])
    orth_nb = np.array([nh.orthogonality_error(R[k]) for k in range(len(R))])
    # Energy, per state. Each side evaluates the same formula (the Schur complement, its
    # pivot-free Gauss-Jordan solve for ω, then v and H) with at most ~30 roundings along
    # any chain, so each is within γ_30 ≈ 30u of the exact value relative to the sum of
    # the magnitudes of its terms T, except for the solve, whose relative error in ω is
    # amplified by κ(S) (Higham, Accuracy and Stability of Numerical Algorithms, §3.1 and
    # ch. 10: elimination without pivoting is stable on symmetric positive definite
    # matrices). Two evaluations: |ΔH| <= 2 · 30 κ(S) u T <= 64 κ u T.
    T, kappa, L = _magnitudes(model, st)
    dH = 64 * kappa * U * T
    assert np.all(np.abs(E_nb - E_jax) <= dH), np.max(np.abs(E_nb - E_jax) / dH)
    # The vertical angular momentum: five products and four sums, |ΔL| <= 2 γ_5 L.
    dL = 2 * 5 * U * L / (1 - 5 * U)
    Lz_jax = np.asarray(inv["angular_momentum_z"])
    assert np.all(np.abs(Lz_nb - Lz_jax) <= dL), np.max(np.abs(Lz_nb - Lz_jax) / dL)
    # ‖RᵀR − I‖_F: each entry of RᵀR − I is three products, two sums and a subtraction of
    # numbers of size <= 1 (|R_ij| <= 1 to rounding), so within γ_4 ≈ 4u on each side;
    # over the 9 entries ‖ΔE‖_F <= 3 max|ΔE_ij| <= 3 · 2 · 4u = 24u (the square root and
    # the squares of entries of size ~1e-15 add nothing at this scale); 32u allowed.
    orth_jax = np.asarray(lj.so3.orthogonality_error(st.R))
    assert np.all(np.abs(orth_nb - orth_jax) <= 32 * U)
    # The running metrics over the trajectory, by the sweep's definitions (after each step:
    # |H - H0|/|H0| and every momentum map's |I - I0|, their maxima and final values).
    got = nb.metrics_of_states(R, mu, q, p, params)
    err = np.abs(E_jax[1:] - E_jax[0]) / abs(E_jax[0])
    # |Δ err_k| <= (ΔH_k + ΔH_0)/|H0| plus the rounding of the difference and quotient.
    d_err = (dH[1:] + dH[0]) / abs(E_jax[0]) + 4 * U * err
    assert abs(got["energy_error_max"] - err.max()) <= d_err.max()
    assert abs(got["energy_error_final"] - err[-1]) <= d_err[-1]
    Lz0 = Lz_jax[0]
    assert abs(got["angular_momentum_z_drift_max"] - np.max(np.abs(Lz_jax[1:] - Lz0))) <= (
        np.max(dL[1:] + dL[0]))
    # The cart momentum: the same numbers on both sides, subtracted: equal exactly.
    assert got["momentum_drift_max"] == np.max(np.abs(p[1:] - p[0]))
    assert abs(got["orthogonality_error_max"] - orth_jax[1:].max()) <= 32 * U
    assert err.max() > 1e-6  # an O(h²) energy error, far above the bounds (~1e-12)


@pytest.mark.parametrize("name", ["lgvi", "hamel-exact"])
def test_numba_sweep_metrics_equal_the_sweeps(name):
    """``sweep_metrics`` (the benchmark's Numba baseline with per-step diagnostics) against
    ``lgvi-jax sweep``'s batched rollout (``run_batch`` with the method the sweep builds by
    default: the autodiff engine on scalars) on the sweep's initial conditions, plus a
    trajectory that fails at once. Both integrate the same discrete equations to their solvers'
    tolerances, so the trajectories agree to the accumulated tolerance δ (< 1e-11 after 200
    steps, test_numba_lgvi_matches_the_engine), and the metrics to the energy's
    sensitivity to it plus the rounding of the test above."""
    from lgvi_jax.sweep import initial_conditions, run_batch, sweep_method

    model = lj.CarPendulum()
    states = initial_conditions(model, model.default_state(), 4, 0.01, 0)
    states = eqx.tree_at(lambda s: s.mu, states, states.mu.at[3].set(jnp.nan))  # fails
    method = sweep_method("car-pendulum", name)
    assert method.newton.scalar
    ours = run_batch(model, method, states, 5e-3, 200)
    arrays = [np.asarray(x) for x in (states.R, states.mu, states.q, states.p)]
    theirs, _ = nb.sweep_metrics(name, *arrays, 5e-3, 200, nb.params_from_model(model))
    assert set(theirs) == set(ours)
    ok = slice(0, 3)
    assert np.all(ours["result"][ok] == 0) and np.all(theirs["result"][ok] == 0)
    # The energy's sensitivity to the state along these trajectories (measured on the
    # central one): |∂H/∂μ| = |ω| <= 7.2, |∂H/∂p| = |v| <= 2.9, the potential's m g |ρ| =
    # 10.4 per unit rotation of R, and the kinetic energy's dependence on R through the
    # coupling, m |ρ| |v| |ω| <= 22: |ΔH| <= 50 δ = 5e-10 with δ = 1e-11, relative to
    # |H0| >= 0.9 (0.97 to 1.14 here): 5.6e-10. (Measured: 1.6e-13.)
    bound = 50 * 1e-11 / 0.9
    for key in ("energy_error_max", "energy_error_final"):
        np.testing.assert_allclose(theirs[key][ok], ours[key][ok], rtol=0, atol=bound)
    # The momentum maps and orthogonality: both at round-off and solver-tolerance level.
    np.testing.assert_array_equal(theirs["momentum_drift_max"][ok], 0.0)
    np.testing.assert_array_equal(ours["momentum_drift_max"][ok], 0.0)
    for key, tol in (("angular_momentum_z_drift_max", 1e-12),
                     ("orthogonality_error_max", 1e-13)):
        assert np.all(theirs[key][ok] <= tol) and np.all(ours[key][ok] <= tol), key
    # Newton iterations: different solvers (the engine solves for (ξ, u) with its chord
    # matrix at the guess, the baseline for w alone): counted, not compared.
    assert np.all(theirs["newton_mean"][ok] >= 2) and np.all(ours["newton_mean"][ok] >= 2)
    assert np.all(theirs["newton_max"][ok] >= theirs["newton_mean"][ok])
    # Failure is a value on both sides, with the sweep's semantics: flagged at step 0, the
    # maxima NaN (no step succeeded), the final value NaN.
    for r in (ours, theirs):
        assert r["result"][3] != 0 and r["failed_step"][3] == 0
        assert np.isnan(r["energy_error_max"][3]) and np.isnan(r["energy_error_final"][3])
    np.testing.assert_array_equal(theirs["failed_step"][ok], -1)


def test_numba_compositions_match_the_engine():
    """``lgvi@4`` in the baseline (Suzuki's five sub-steps, one of them backwards) solves
    the same equations as the engine's composition: end states to the accumulated solver
    tolerance; five solves a step."""
    model = lj.CarPendulum()
    s0 = model.default_state()
    # The engine's state after 100 steps: saved state 1 of the 10^4-step rollout (every
    # 100th state saved) that tests/test_composition.py compiles for lgvi@4 on this model.
    traj = lj.simulate(model, lj.compose(lj.LGVI(), order=4), s0, 5e-3, 10_000,
                       save_every=100)
    R, mu, q, p = (np.asarray(x) for x in (s0.R, s0.mu, s0.q, s0.p))
    *theirs, its, code = nb.rollout("lgvi@4", R, mu, q, p, 5e-3, 100,
                                    nb.params_from_model(model))
    assert traj.ok and code == 0 and its >= 5 * 2 * 100
    for a, b in zip((traj.state.R, traj.state.mu, traj.state.q, traj.state.p), theirs,
                    strict=True):
        np.testing.assert_allclose(b, np.asarray(a)[1], rtol=0, atol=1e-11)
    with pytest.raises(ValueError, match="method must be one of"):
        nb.rollout("rk4@4", R, mu, q, p, 5e-3, 1, nb.params_from_model(model))
