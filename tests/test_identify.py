"""Differentiable trajectories and inertia identification (lgvi_jax.identify, the Newton
adjoints, checkpointed rollouts, ``lgvi-jax fit``).

Setting of the issue: observations every 0.05 s over 5 s from the independent reference
(hand-derived equations, DOP853 at 1e-13) for a pendulum whose inertia about the mass
centre is diag(0.03, 0.05, 0.04) kg m², everything else as in the paper. The heavy top
(the same pendulum without its cart) and the free body are fitted from their own ``lgvi``
attitudes over 1 s (short: each fit compiles and runs in seconds).
"""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("scipy", reason="the reference needs SciPy (the 'dev' extra)")

import lgvi_jax as lj
from lgvi_jax import identify, so3
from lgvi_jax.cli import main
from lgvi_jax.inertia import centroidal_inertia, inertia_from_params, is_physical, pivot_inertia
from lgvi_jax.models.rigid_bodies import PAPER_RHO_C

J_C_TRUE = np.diag([0.03, 0.05, 0.04])
J_TRUE = np.asarray(pivot_inertia(J_C_TRUE, 1.0, PAPER_RHO_C))
TIMES = np.arange(101) * 0.05  # every 0.05 s over 5 s
FIT_DT = 0.01  # 500 steps over 5 s; the step's bias in J_c is ~0.8% (measured, < 1%)
GRAD_DT, GRAD_STEPS = 0.005, 1000  # 10^3 steps over the same 5 s


@pytest.fixture(scope="module")
def clean_data():
    return identify.observe(lj.CarPendulum(J=J_TRUE), TIMES)


@pytest.fixture(scope="module")
def noisy_data():
    return identify.observe(lj.CarPendulum(J=J_TRUE), TIMES, noise=1e-3, seed=0)


def rel_error(J_c):
    return np.linalg.norm(np.asarray(J_c) - J_C_TRUE) / np.linalg.norm(J_C_TRUE)


# ---------------------------------------------------------------------------------------
# Gradients through 10^3 steps
# ---------------------------------------------------------------------------------------


def trajectory_loss(model, state0, method, R_obs, q_obs):
    traj = lj.simulate(model, method, state0, GRAD_DT, GRAD_STEPS, save_every=10)
    return jnp.mean(0.5 * jnp.sum((traj.state.R - R_obs) ** 2, axis=(-2, -1))
                    + jnp.sum((traj.state.q - q_obs) ** 2, axis=-1))


_loss = eqx.filter_jit(trajectory_loss)
_grad = eqx.filter_jit(eqx.filter_grad(
    lambda ms, method, R, q: trajectory_loss(ms[0], ms[1], method, R, q)))


def _directions():
    """Perturbation directions, each scaled to its quantity, one per parameter group and
    initial-state component; ``R`` is perturbed on SO(3), ``R0 exp(ε η̂)``."""
    rng = np.random.default_rng(0)
    sym = rng.normal(size=(3, 3))
    return {
        "J": ("model", "J", 0.01 * (sym + sym.T) / 2),
        "rho_c": ("model", "rho_c", 0.01 * rng.normal(size=3)),
        "m": ("model", "m", np.asarray(0.01)),
        "M": ("model", "M", np.asarray(0.01)),
        "g": ("model", "g", np.asarray(0.01)),
        "R0": ("state", "R", 0.01 * rng.normal(size=3)),
        "mu0": ("state", "mu", 0.01 * rng.normal(size=3)),
        "q0": ("state", "q", 0.01 * rng.normal(size=2)),
        "p0": ("state", "p", 0.01 * rng.normal(size=2)),
    }


def _shift(model, state0, where, field, d, eps):
    if where == "model":
        return eqx.tree_at(lambda x: getattr(x, field), model,
                           getattr(model, field) + eps * jnp.asarray(d)), state0
    if field == "R":
        return model, eqx.tree_at(lambda x: x.R, state0, state0.R @ so3.exp(eps * jnp.asarray(d)))
    return model, eqx.tree_at(lambda x: getattr(x, field), state0,
                              getattr(state0, field) + eps * jnp.asarray(d))


def _directional(grads, state0, where, field, d):
    g_model, g_state = grads
    if where == "model":
        return float(jnp.sum(getattr(g_model, field) * d))
    if field == "R":  # d/dε L(R0 exp(ε η̂)) = <∂L/∂R, R0 η̂>
        return float(jnp.sum(g_state.R * (state0.R @ so3.hat(jnp.asarray(d)))))
    return float(jnp.sum(getattr(g_state, field) * d))


@pytest.fixture(scope="module")
def gradient_setup(clean_data):
    model = lj.CarPendulum()  # differentiate at the paper's parameters (not the truth)
    state0 = model.default_state()
    R_obs = jnp.asarray(clean_data["R"])
    q_obs = jnp.asarray(clean_data["q"])
    grads = {}
    for name in ("lgvi", "hamel-exact"):
        method = lj.RIGID_METHODS[name]()
        grads[name] = _grad((model, state0), method, R_obs, q_obs)
    return model, state0, R_obs, q_obs, grads


@pytest.mark.parametrize("method_name", ["lgvi", "hamel-exact"])
def test_gradient_through_1000_steps_matches_central_differences(gradient_setup, method_name):
    """Reverse mode through 10^3 implicit steps (the Newton solves by the implicit function
    theorem) against central differences, for every parameter and the initial state."""
    model, state0, R_obs, q_obs, grads = gradient_setup
    method = lj.RIGID_METHODS[method_name]()

    def f(eps, where, field, d):
        return float(_loss(*_shift(model, state0, where, field, d, eps), method, R_obs, q_obs))

    for name, (where, field, d) in _directions().items():
        exact = _directional(grads[method_name], state0, where, field, d)
        # FD step: the central difference's O(ε²) truncation is ~1e-4 relative at ε = 1e-2
        # (times the direction's 1e-2 scale), too much for 1e-6; smaller ε meets the
        # rollout's noise (Newton stops at 1e-12, which over 10^3 steps gives ~1e-13 in
        # the loss, i.e. ~1e-13/ε in the difference). Richardson extrapolation of ε and
        # ε/2 cancels the ε² term: truncation O(ε⁴) ~ 1e-8 with the noise still ~1e-10.
        eps = 1e-2
        d1 = (f(eps, where, field, d) - f(-eps, where, field, d)) / (2 * eps)
        d2 = (f(eps / 2, where, field, d) - f(-eps / 2, where, field, d)) / eps
        fd = (4 * d2 - d1) / 3
        assert fd == pytest.approx(exact, rel=1e-6), name


def test_jvp_equals_gradient_dot_direction(gradient_setup):
    """Forward mode through the same 10^3 steps: jvp(L)(v) = <grad L, v>."""
    model, state0, R_obs, q_obs, grads = gradient_setup
    method = lj.LGVI()
    dirs = _directions()
    d_model = jax.tree.map(jnp.zeros_like, model)
    d_state = jax.tree.map(jnp.zeros_like, state0)
    for where, field, d in dirs.values():
        if where == "model":
            d_model = eqx.tree_at(lambda x, f=field: getattr(x, f), d_model, jnp.asarray(d))
        elif field != "R":
            d_state = eqx.tree_at(lambda x, f=field: getattr(x, f), d_state, jnp.asarray(d))

    @eqx.filter_jit
    def jvp(model, state0, d_model, d_state):
        return jax.jvp(lambda m, s: trajectory_loss(m, s, method, R_obs, q_obs),
                       (model, state0), (d_model, d_state))[1]

    tangent = float(jvp(model, state0, d_model, d_state))
    g_model, g_state = grads["lgvi"]
    dot = sum(float(jnp.sum(a * b)) for a, b in zip(
        jax.tree.leaves((g_model, g_state)), jax.tree.leaves((d_model, d_state)), strict=True))
    # Two different linear algebra orderings of the same derivative: round-off only.
    assert tangent == pytest.approx(dot, rel=1e-10)


def test_implicit_gradient_equals_unrolled_newton_gradient(gradient_setup):
    """The implicit-function-theorem gradient equals the gradient obtained by
    differentiating through plain Newton iterations (converged to round-off: 6 iterations
    from the current velocities, where Newton needs 3)."""
    model, state0, R_obs, q_obs, grads = gradient_setup
    unrolled = lj.LGVI(newton=lj.Newton(adjoint="unrolled", max_steps=6))
    g_unrolled = _grad((model, state0), unrolled, R_obs, q_obs)
    implicit = jax.tree.leaves(grads["lgvi"])
    diffs = [float(jnp.max(jnp.abs(a - b))) / max(float(jnp.max(jnp.abs(a))), 1e-300)
             for a, b in zip(implicit, jax.tree.leaves(g_unrolled), strict=True) if jnp.any(a != 0)]
    # Round-off of 10^3 steps (two different sequences of floating-point operations),
    # amplified by the sensitivity of the motion over 5 s: measured 2e-12.
    assert max(diffs) < 1e-10
    # Not trivially equal: the unrolled solve really is a different computation (two
    # different sequences of operations over 10^3 steps never agree to the last bit).
    assert max(diffs) > 0


def test_unrolled_adjoint_reports_failure_and_keeps_the_default_unchanged():
    assert lj.Newton().adjoint == "implicit"
    with pytest.raises(ValueError, match="adjoint"):
        lj.Newton(adjoint="nope")
    # y^2 + 1 = 0 has no real root: the unrolled solve says so.
    sol = lj.newton_solve(lambda y, a: y**2 + a, jnp.array([0.7]), jnp.array(1.0),
                          lj.Newton(adjoint="unrolled", max_steps=8))
    assert int(sol.result) == lj.RESULTS.max_steps_reached
    sol = lj.newton_solve(lambda y, a: y**3 - a, jnp.array([1.0]), jnp.array(2.0),
                          lj.Newton(adjoint="unrolled", max_steps=10))
    assert int(sol.result) == lj.RESULTS.successful
    assert float(sol.value[0]) == pytest.approx(2 ** (1 / 3), rel=1e-14)
    g = jax.grad(lambda a: lj.newton_solve(lambda y, a: y**3 - a, jnp.array([1.0]), a,
                                           lj.Newton(adjoint="unrolled",
                                                     max_steps=10)).value[0])(2.0)
    assert float(g) == pytest.approx(2 ** (1 / 3) / 6, rel=1e-12)  # d a^(1/3)/da


def test_checkpointed_rollout_gives_the_same_values_and_gradient():
    """checkpoint_every changes what reverse mode stores, not what is computed (the memory
    it saves is measured in experiments/bench_gradients.py)."""
    model = lj.HarmonicOscillator(k=1.7)
    state0 = model.default_state()
    method = lj.StormerVerlet()

    @eqx.filter_jit
    def run(model, ck):
        def loss(model):
            traj = lj.simulate(model, method, state0, 0.1, 120, save_every=4,
                               checkpoint_every=ck)
            return jnp.sum(traj.state.q ** 3), traj
        return eqx.filter_value_and_grad(loss, has_aux=True)(model)

    (v0, t0), g0 = run(model, None)
    (v1, t1), g1 = run(model, 24)
    # The same steps in two compiled programs: XLA may contract or fuse them differently
    # (an ulp per operation), so equal to eps x 120 steps x a modest growth, not bitwise:
    # bound 1e-12 on values of order 1 (measured 0).
    np.testing.assert_allclose(t1.state.q, t0.state.q, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(t1.t, t0.t)
    assert float(v1) == pytest.approx(float(v0), rel=1e-12)
    assert float(g1.k) == pytest.approx(float(g0.k), rel=1e-12)  # round-off of reordering
    with pytest.raises(ValueError, match="checkpoint_every"):
        lj.simulate(model, method, state0, 0.1, 120, save_every=4, checkpoint_every=6)


@pytest.mark.parametrize("scalar", [False, True], ids=["arrays", "scalars"])
def test_checkpointed_gradient_reuses_the_newton_solutions(scalar):
    """With checkpoints, the backward pass recomputes each segment's steps but takes their
    Newton solutions from the forward pass (``save_solutions``, a ``jax.checkpoint``
    policy on the names the solver's rule gives them): the same gradient as without
    checkpoints and as recomputing the solves, and a compiled gradient with fewer loops
    (the recomputed solves' ``while`` loops are gone)."""
    from lgvi_jax.integrators import with_scalar_newton

    model = lj.HeavyTop()
    state0 = model.default_state()
    method = with_scalar_newton(lj.LGVI(), scalar)

    def grad_fn(**kw):
        def loss(J):
            traj = lj.simulate(eqx.tree_at(lambda m: m.J, model, J), method, state0, 0.01,
                               10, **kw)
            return (jnp.sum(traj.state.R[-1] @ jnp.arange(9.0).reshape(3, 3))
                    + jnp.sum(traj.state.mu[-1]))
        return jax.jit(jax.grad(loss)).lower(model.J).compile()

    # (checkpointed against plain gradients: test_checkpointed_rollout_gives_the_same_...)
    saved = grad_fn(checkpoint_every=5)
    solved = grad_fn(checkpoint_every=5, save_solutions=False)
    g = [np.asarray(f(model.J)) for f in (saved, solved)]
    # The same arithmetic on the same values, except that a recomputed solve or a step in
    # another compiled loop may round differently, and a chord solve's iterates carry such
    # differences into its root: the worst case over the default compilation (1.4e-15,
    # |g| ~ 190) and --alt-numerics (4.5e-14 relative, with the factored Newton solve) x a
    # margin of 10 -> 5e-13.
    assert np.max(np.abs(g[0])) > 1.0  # a loss that really depends on J
    np.testing.assert_allclose(g[0], g[1], rtol=5e-13, atol=0)

    def loops(compiled):
        return compiled.as_text().count(" while(")

    assert loops(saved) < loops(solved)


# ---------------------------------------------------------------------------------------
# Recovery of the inertia
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("noisy, tolerance", [(False, 0.01), (True, 0.05)])
def test_inertia_recovered_from_the_papers_start(clean_data, noisy_data, noisy, tolerance):
    obs = identify.check_observations(noisy_data if noisy else clean_data, FIT_DT)
    result = identify.fit(obs, FIT_DT, names=("J",), method="lgvi",
                          optimizer="gauss-newton", iterations=300)
    start_error = rel_error(centroidal_inertia(lj.CarPendulum().J, 1.0, PAPER_RHO_C))
    assert start_error > 0.15  # the start is far from the truth (20%)
    assert rel_error(result.J_c) <= tolerance
    # Converged well before the cap: one loss per iteration (and the end), over horizons
    # that grow stage by stage to the whole observation span (t = 5 s); the loss over the
    # whole span brought down by orders of magnitude from the 20%-wrong start.
    assert result.stopped == "converged"
    assert 1 <= result.iterations < 300
    assert len(result.loss_history) == result.iterations + 1
    assert result.stage_starts[0] == 0 and np.all(np.diff(result.stage_starts) > 0)
    assert result.horizons[-1] == pytest.approx(float(obs.t[-1]), rel=1e-12)
    assert result.loss_history[-1] == result.loss_final < 1e-2 * result.loss_initial
    # The loss (mean squared error per observed coordinate) reaches the noise floor σ²
    # (plus the step's own error, ~5e-8 at this step): nothing systematic is left.
    floor = 1e-6 if noisy else 0.0
    assert result.loss_history[-1] < 1.2 * floor + 2e-7
    assert is_physical(result.model.J) and is_physical(result.J_c)
    # The rest of the model is untouched.
    assert float(result.model.m) == 1.0
    np.testing.assert_array_equal(result.model.rho_c, PAPER_RHO_C)


def test_fitted_inertia_is_physical_from_any_start(clean_data):
    """Whatever the start (inertias whose second moments span 3 decades, in random axes),
    and however far the optimiser throws the iterates (optax Adam with a reckless learning
    rate), every iterate is a physical inertia: the parametrisation maps every
    unconstrained vector into the physical set. (lgvi as the integrator: physicality does
    not depend on it, and Adam's compiled step through lgvi compiles faster than through
    RK4, whose explicit step differentiates the continuous equations: measured 11.0 s
    against 14.1 s for this test's fits.)"""
    obs = identify.check_observations(clean_data, FIT_DT)
    rng = np.random.default_rng(7)
    for _ in range(3):
        sigma = np.exp(rng.uniform(-6, 0, 3))
        Q = np.asarray(so3.exp(jnp.asarray(rng.normal(size=3))))
        J_c = Q @ (sigma.sum() * np.eye(3) - np.diag(sigma)) @ Q.T
        start = lj.CarPendulum(J=np.asarray(pivot_inertia(J_c, 1.0, PAPER_RHO_C)))
        seen = []
        result = identify.fit(obs, FIT_DT, names=("J",), model=start, method="lgvi",
                              optimizer="adam", lr=3.0, iterations=3, horizons=(1.0,),
                              callback=lambda i, v, seen=seen: seen.append(v))
        assert is_physical(result.J_c) and is_physical(result.model.J)
        assert len(result.loss_history) == result.iterations + 1
        assert result.iterations == len(seen) - (result.stopped == "non-finite")


# ---------------------------------------------------------------------------------------
# Any rigid body: the heavy top and the free body
# ---------------------------------------------------------------------------------------

#: Attitudes every 0.05 s over 1 s, rollouts of h = 0.01 (100 steps).
BODY_TIMES = np.arange(21) * 0.05
BODY_DT = 0.01
#: A free body with products of inertia, and a generic initial spin.
FREE_J_TRUE = np.array([[2.0, 0.1, 0.0], [0.1, 3.0, -0.1], [0.0, -0.1, 4.0]])
FREE_OMEGA0 = (0.3, 1.0, 0.6)
#: The heavy top's start: the truth's principal moments changed and its axes turned (12%).
HEAVY_TOP_START_J_C = (np.diag([0.035, 0.045, 0.042]), [0.2, -0.1, 0.15])


def _rotated(J, angles):
    Q = np.asarray(so3.exp(jnp.asarray(angles, dtype=jnp.float64)))
    return Q @ np.asarray(J) @ Q.T


@pytest.fixture(scope="module")
def heavy_top_data():
    """The heavy top's attitudes from its own lgvi rollout at the fit's step: the truth is
    an exact zero of the fit's loss (up to round-off), so what is left after a fit is the
    solver's, not the integrator's, error."""
    true = lj.HeavyTop(J=J_TRUE)
    return true, identify.observe(true, BODY_TIMES, method="lgvi", dt=BODY_DT)


def _recovery_bound(result, problem, truth, quantity, null_dims=0):
    """A first-order bound on ``|quantity(θ̂) − quantity(θ*)|_F`` at the fit's end.

    The stopping rule (the loss changed by at most tol = 1e-10 relative for 3 successive
    iterations) cannot fire while Gauss–Newton still makes progress on a zero-residual
    problem (it squares the relative error of θ each iteration, so the loss falls by
    orders of magnitude per iteration); it fires when the loss has reached the round-off
    floor of the residuals. There, with ``r(θ) = A (θ − θ*) + r(θ*)`` to first order (``A``
    the residuals' Jacobian, ``r(θ*)`` the round-off left at the truth),
    ``|A(θ̂ − θ*)| <= |r(θ̂)| + |r(θ*)|``, so the component of ``θ̂ − θ*`` off the loss's
    ``null_dims`` flat directions is at most ``(|r(θ̂)| + |r(θ*)|) / σ`` with ``σ`` the
    smallest non-zero singular value of ``A``; a ``quantity`` constant along the flat
    directions moves by at most its Jacobian's norm times that."""
    r_hat, A = (np.asarray(a) for a in identify._jacobian(result.params, problem))
    r_true = np.asarray(identify._jacobian(truth, problem)[0])
    sigma = np.linalg.svd(A, compute_uv=False)[-1 - null_dims]
    D = np.asarray(jax.jacfwd(quantity)(result.params["J"])).reshape(9, -1)
    return np.linalg.norm(D, 2) * (np.linalg.norm(r_hat) + np.linalg.norm(r_true)) / sigma


def test_heavy_top_inertia_recovered_from_its_own_attitudes(heavy_top_data):
    """The heavy top's inertia from its attitudes alone (no cart, dof = 0), from a start
    12% away (the truth's principal moments changed and its axes turned): recovered to
    the round-off the stopping rule leaves (``_recovery_bound``), every iterate physical."""
    true, data = heavy_top_data
    obs = identify.check_observations(data, BODY_DT, dof=0)
    assert obs.dof == 0 and obs.q.shape == (len(BODY_TIMES), 0)
    J_c0 = _rotated(*HEAVY_TOP_START_J_C)
    start = lj.HeavyTop(J=np.asarray(pivot_inertia(J_c0, 1.0, PAPER_RHO_C)))
    assert rel_error(J_c0) > 0.1
    result = identify.fit(obs, BODY_DT, names=("J",), model=start)
    assert result.stopped == "converged" and result.iterations < 300
    assert isinstance(result.model, lj.HeavyTop) and result.values().keys() == {
        "J", "rho_c", "m", "g", "omega0", "J_c"}
    _, _, problem = identify.make_loss(obs, BODY_DT, names=("J",), model=start)
    bound = _recovery_bound(
        result, problem, identify.to_unconstrained(("J",), true),
        lambda th: pivot_inertia(inertia_from_params(th), 1.0, PAPER_RHO_C))
    # A bound at round-off (so the check means something: measured 3.0e-13), met with the
    # factor 10 left for the linearisation (measured error 2.0e-14).
    assert bound < 1e-11 * np.linalg.norm(J_TRUE)
    np.testing.assert_allclose(result.model.J, J_TRUE, rtol=0, atol=10 * bound)
    np.testing.assert_allclose(result.J_c, J_C_TRUE, rtol=0, atol=10 * bound)
    assert float(result.model.m) == 1.0  # the rest of the model untouched
    np.testing.assert_array_equal(result.model.rho_c, PAPER_RHO_C)


def test_free_body_inertia_recovered_up_to_its_scale():
    """A free body's attitudes fix its inertia only up to a positive factor (Euler's
    equation ``Jω̇ = Jω × ω`` is unchanged by ``J -> cJ``): the residuals' Jacobian has
    exactly one null direction, the scaling, and the fit recovers ``J / tr J`` (fitted as
    the log-Cholesky coordinates of ``J`` itself: the free body has no mass-centre offset)
    to the round-off the stopping rule leaves."""
    true = lj.FreeRigidBody(J=FREE_J_TRUE)
    data = identify.observe(true, BODY_TIMES, state=true.state(omega0=FREE_OMEGA0),
                            method="lgvi", dt=BODY_DT)
    obs = identify.check_observations(data, BODY_DT, dof=0)
    np.testing.assert_allclose(obs.omega0, FREE_OMEGA0, rtol=1e-14)
    start = lj.FreeRigidBody(J=_rotated(np.diag([2.2, 2.8, 4.3]), [0.05, 0.1, -0.05]))
    result = identify.fit(obs, BODY_DT, names=("J",), model=start)
    assert result.stopped == "converged"
    assert is_physical(result.model.J)
    np.testing.assert_array_equal(result.J_c, result.model.J)  # about its mass centre

    def normalised(J):
        return J / jnp.trace(J)

    _, _, problem = identify.make_loss(obs, BODY_DT, names=("J",), model=start)
    truth = identify.to_unconstrained(("J",), true)
    # The scaling J -> e^{2s} J is θ -> (θ_0..2 + s, e^s θ_3..5) in log-Cholesky
    # coordinates: its tangent (1, 1, 1, θ_3..5) is the Jacobian's null direction.
    _, A = identify._jacobian(truth, problem)
    scaling = np.concatenate([np.ones(3), np.asarray(truth["J"])[3:]])
    sigma = np.linalg.svd(np.asarray(A), compute_uv=False)
    assert np.linalg.norm(np.asarray(A) @ scaling) <= 1e-12 * sigma[0] * np.linalg.norm(scaling)
    assert sigma[-2] > 1e-6 * sigma[0]  # and only that one: the ratios are identifiable
    bound = _recovery_bound(result, problem, truth,
                            lambda th: normalised(inertia_from_params(th)), null_dims=1)
    # At round-off: the residuals' floor over the smallest identifiable singular value
    # (measured 6.3e-12; the floor's realisation differs from one CPU to another), far
    # below the start's 10 % error, so the check means something.
    assert bound < 1e-10
    np.testing.assert_allclose(normalised(np.asarray(result.model.J)),
                               normalised(FREE_J_TRUE), rtol=0, atol=10 * bound)


def test_heavy_top_loss_gradient_matches_central_differences(heavy_top_data):
    """The loss's gradient with respect to every unconstrained parameter of the heavy top
    (log-Cholesky J, rho_c, log m, g, and the initial velocity omega0), by reverse mode
    (as L-BFGS uses it) and as ``2 Aᵀr`` from the forward-mode Jacobian of the residuals
    (as Levenberg–Marquardt does), against central differences along a random direction
    per parameter."""
    _, data = heavy_top_data
    obs = identify.check_observations(data, BODY_DT, dof=0)
    names = identify.fittable(lj.HeavyTop())
    assert names == ("J", "rho_c", "m", "g", "omega0")
    # At the paper's parameters, away from the truth (a non-zero gradient).
    loss, params, problem = identify.make_loss(obs, BODY_DT, names=names,
                                               model=lj.HeavyTop())
    flat, unravel = jax.flatten_util.ravel_pytree(params)
    value, grad = eqx.filter_jit(jax.value_and_grad(loss))(params, problem)
    grad = np.asarray(jax.flatten_util.ravel_pytree(grad)[0])
    r, A = (np.asarray(a) for a in identify._jacobian(params, problem))
    f = eqx.filter_jit(loss)
    rng = np.random.default_rng(3)
    for name in names:
        d = np.asarray(jax.flatten_util.ravel_pytree(
            {k: (rng.normal(size=np.shape(v)) if k == name else np.zeros(np.shape(v)))
             for k, v in params.items()})[0])

        def g(eps, d=d):
            return float(f(unravel(flat + eps * d), problem))

        # Richardson's extrapolation of the central differences at ε and ε/2: truncation
        # O(ε⁴), ~1e-11 relative at ε = 1e-3 (measured ~1e-7 at ε = 1e-2); rounding: the
        # loss carries the Newton solves' tolerance, 1e-12 relative, so the difference
        # is off by ~1e-12·L/ε. Bound: ten times that, plus 1e-9 of the derivative.
        eps = 1e-3
        d1 = (g(eps) - g(-eps)) / (2 * eps)
        d2 = (g(eps / 2) - g(-eps / 2)) / eps
        fd = (4 * d2 - d1) / 3
        tol = 10 * 1e-12 * float(value) / eps + 1e-9 * abs(fd)
        assert abs(grad @ d - fd) <= tol, (name, grad @ d, fd)
        assert abs(2 * (A.T @ r) @ d - fd) <= tol, (name, 2 * (A.T @ r) @ d, fd)


def test_observations_of_a_body_without_a_cart(heavy_top_data, tmp_path):
    """A dof = 0 model is observed by its attitudes alone: its file has no q, q0, v0 (an
    extra one is named), and a missing key is named with the keys it needs."""
    _, data = heavy_top_data
    with pytest.raises(ValueError, match=r"unexpected key\(s\) q, q0"):
        identify.check_observations({**data, "q": np.zeros((21, 2)), "q0": np.zeros(2)},
                                    BODY_DT, dof=0)
    with pytest.raises(ValueError, match=r"missing key\(s\) omega0; need t \(n,\), "
                       r"R \(n,3,3\), R0 \(3,3\), omega0 \(3,\)$"):
        identify.check_observations({k: v for k, v in data.items() if k != "omega0"},
                                    BODY_DT, dof=0)
    with pytest.raises(ValueError, match="observations have 0 Euclidean"):
        identify.fit(identify.check_observations(data, BODY_DT, dof=0), BODY_DT)
    # `lgvi-jax simulate heavy-top` output: the initial state is its first row.
    from_simulate = {"t": data["t"], "R": data["R"],
                     "omega": np.tile(data["omega0"], (21, 1)), "mu": np.zeros((21, 3))}
    obs = identify.check_observations(from_simulate, BODY_DT, dof=0)
    np.testing.assert_array_equal(obs.omega0, data["omega0"])


def test_fit_command_heavy_top(heavy_top_data, tmp_path, capsys):
    """``lgvi-jax fit heavy-top``: its file has attitudes only; the inertia recovered (as in
    the library test above, whose compiled programs it reuses), the output keys of the
    car-pendulum's less the cart's; a system without a rigid body is refused, naming the
    valid ones."""
    _, data = heavy_top_data
    path = _write(tmp_path / "obs.npz", data)
    out = tmp_path / "fit.json"
    J0 = np.ravel(pivot_inertia(_rotated(*HEAVY_TOP_START_J_C), 1.0, PAPER_RHO_C))
    code = main(["fit", "heavy-top", "--data", path, "--method", "lgvi", "--dt",
                 str(BODY_DT), "--fit", "J", "--init", f"J={','.join(map(str, J0))}",
                 "--out", str(out), "--json"])
    assert code == 0, capsys.readouterr().err
    fit = json.loads(out.read_text())
    assert fit["system"] == "heavy-top" and fit["fitted"] == ["J"]
    assert fit["stopped"] == "converged"
    assert set(fit["values"]) == {"J", "rho_c", "m", "g", "omega0", "J_c"}
    np.testing.assert_allclose(fit["J"], J_TRUE, rtol=0, atol=1e-11)
    for argv, message in (
            (["heavy-top", "--fit", "M"], "--fit 'M': choose from J, rho_c, m, g, omega0"),
            (["heavy-top", "--fit", "J", "--init", "v0=1,2"], "--init v0"),
            (["oscillator", "--fit", "J"], "valid systems: free-rigid-body, heavy-top, "
                                           "car-pendulum"),
            (["car-pendulum", "--fit", "J"], "missing key(s) q")):
        assert main(["fit", argv[0], "--data", path, "--method", "lgvi", "--dt", "0.01",
                     *argv[1:], "--out", str(out)]) == 2
        assert message in capsys.readouterr().err


# ---------------------------------------------------------------------------------------
# Data checks and the command line
# ---------------------------------------------------------------------------------------


def _write(path, data, **changes):
    arrays = {**data, **changes}
    np.savez(path, **{k: v for k, v in arrays.items() if v is not None})
    return str(path)


@pytest.mark.parametrize("change, message", [
    ({"R": np.zeros((101, 3))}, "R must have shape (101, 3, 3)"),
    ({"q": np.zeros((100, 2))}, "q must have shape (101, 2)"),
    ({"omega0": np.array([np.nan, 0, 0])}, "omega0 has 1 non-finite"),
    ({"t": TIMES + 0.001}, "not a multiple of dt"),
    ({"t": TIMES[::-1].copy()}, "increasing"),
    ({"R0": None}, "missing key(s) R0"),
    ("R_scaled", "R[3] is not in SO(3)"),
    ("R_reflected", "R[3] is not in SO(3)"),
])
def test_fit_refuses_bad_data(clean_data, tmp_path, capsys, change, message):
    if change == "R_scaled":
        R = clean_data["R"].copy()
        R[3] *= 1.01
        change = {"R": R}
    elif change == "R_reflected":
        R = clean_data["R"].copy()
        R[3] = -R[3]
        change = {"R": R}
    data = _write(tmp_path / "obs.npz", clean_data, **change)
    out = tmp_path / "fit.json"
    code = main(["fit", "car-pendulum", "--data", data, "--method", "lgvi", "--dt", "0.01",
                 "--fit", "J", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert "lgvi-jax fit: error: --data" in err and message in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()


@pytest.mark.parametrize("args, message", [
    (["--fit", "J,inertia"], "--fit 'inertia'"),
    (["--fit", "J", "--init", "J=1,0,0,0,1,0,0,0,3"], "--init"),  # unphysical
    (["--fit", "J", "--init", "R0=1,0,0,0,1,0,0,0,1"], "--init R0"),
    (["--fit", "J", "--method", "verlet"], "--method 'verlet'"),
    (["--fit", "J", "--dt", "0.03"], "not a multiple of dt"),
    (["--fit", "J", "--dt", "-1"], "--dt"),
])
def test_fit_refuses_bad_arguments(clean_data, tmp_path, capsys, args, message):
    data = _write(tmp_path / "obs.npz", clean_data)
    base = {"--method": "lgvi", "--dt": "0.01"}
    for i, a in enumerate(args):
        if a in base:
            base[a] = args[i + 1]
    rest = [a for i, a in enumerate(args)
            if a not in base and (i == 0 or args[i - 1] not in base)]
    argv = ["fit", "car-pendulum", "--data", data, "--method", base["--method"], "--dt",
            base["--dt"], *rest, "--out", str(tmp_path / "fit.json")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err


def test_observations_from_simulate_output_derive_the_initial_state(clean_data):
    # `lgvi-jax simulate car-pendulum` writes t, R, q, omega, v (no R0, omega0, q0, v0).
    data = {"t": clean_data["t"], "R": clean_data["R"], "q": clean_data["q"],
            "omega": np.tile(clean_data["omega0"], (101, 1)),
            "v": np.tile(clean_data["v0"], (101, 1))}
    obs = identify.check_observations(data, FIT_DT)
    np.testing.assert_allclose(obs.R0, clean_data["R"][0], atol=1e-15)
    np.testing.assert_array_equal(obs.omega0, clean_data["omega0"])
    np.testing.assert_array_equal(obs.q0, clean_data["q"][0])


def test_fit_command_writes_the_fit(clean_data, tmp_path, capsys):
    data = _write(tmp_path / "obs.npz", clean_data)
    out = tmp_path / "fit.json"
    code = main(["fit", "car-pendulum", "--data", data, "--method", "lgvi", "--dt", "0.01",
                 "--fit", "J", "--init", "m=1", "--optimizer", "gauss-newton",
                 "--iterations", "300", "--out", str(out)])
    assert code == 0
    text = capsys.readouterr().out
    assert "J about the pivot" in text and f"wrote {out}" in text
    fit = json.loads(out.read_text())
    J = np.asarray(fit["values"]["J"])
    assert J.shape == (3, 3) and is_physical(J)
    assert rel_error(centroidal_inertia(J, 1.0, PAPER_RHO_C)) <= 0.01
    assert rel_error(fit["values"]["J_c"]) <= 0.01
    assert 1 <= fit["iterations"] < 300 and fit["stopped"] == "converged"
    assert fit["iterations"] == len(fit["loss_history"]) - 1
    assert fit["loss_history"][-1] == fit["loss_final"]  # the last entry: the whole span
    assert fit["stage_starts"][0] == 0 and fit["horizons_s"][-1] == pytest.approx(5.0)
    assert fit["method"] == "lgvi" and fit["optimizer"] == "gauss-newton" and fit["dt"] == 0.01
    assert fit["wall_time_s"] > 0 and fit["fitted"] == ["J"] and fit["init"] == {"m": [1.0]}
    assert fit["loss_final"] < 1e-2 * fit["loss_initial"]


def test_a_method_named_for_a_short_fit_solves_on_arrays_and_for_a_long_one_on_scalars():
    """make_loss (and so fit) resolves a method's name to the engine that fits faster for
    the rollout's length (identify.FIT_SCALAR_MIN_STEPS); an integrator object is kept."""
    from lgvi_jax.identify import FIT_SCALAR_MIN_STEPS, check_observations, make_loss

    dt = 0.01
    for n_steps, scalar in ((FIT_SCALAR_MIN_STEPS - 1, False), (FIT_SCALAR_MIN_STEPS, True)):
        t = dt * np.arange(n_steps + 1)
        data = {"t": t, "R": np.broadcast_to(np.eye(3), (t.size, 3, 3)), "R0": np.eye(3),
                "omega0": np.zeros(3), "q": np.zeros((t.size, 2)), "q0": np.zeros(2),
                "v0": np.zeros(2)}
        obs = check_observations(data, dt)
        _, _, problem = make_loss(obs, dt, method="lgvi")
        assert problem.method.newton.scalar is scalar, n_steps
        _, _, given = make_loss(obs, dt, method=lj.LGVI())
        assert given.method == lj.LGVI()
