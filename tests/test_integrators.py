"""Euclidean integrators: orders, energy behaviour, symplecticity, symmetry."""

from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import lgvi_jax  # noqa: F401  (float64)
from lgvi_jax.diagnostics import (
    drift_ratio,
    observed_order,
    relative_energy_error,
    rk4_energy_factor,
)
from lgvi_jax.integrators import (
    EUCLIDEAN_METHODS,
    RK4,
    GalerkinVI,
    GaussLegendre,
    StormerVerlet,
)
from lgvi_jax.models import AbstractEuclideanModel, HarmonicOscillator, PhaseState
from lgvi_jax.simulate import final_state, simulate

EPS = np.finfo(np.float64).eps
SYMPLECTIC = ("gl4", "gl6", "verlet", "galerkin4", "galerkin6")


class Pendulum(AbstractEuclideanModel):
    """Simple pendulum, L = v²/2 + cos q (nonlinear, separable)."""

    dof: ClassVar[int] = 1
    separable: ClassVar[bool] = True

    def kinetic(self, q, v):
        return 0.5 * jnp.sum(v**2)

    def potential(self, q):
        return -jnp.sum(jnp.cos(q))

    def state(self):
        return PhaseState(q=jnp.array([1.0]), p=jnp.array([0.5]))


class VariableMass(AbstractEuclideanModel):
    """Non-separable: L = ½(1 + q₁² + q₂²/2)|v|² + v₁ q₂ / 4 − ½|q|² − q₁⁴/8 (gyroscopic
    term, position-dependent mass)."""

    dof: ClassVar[int] = 2
    separable: ClassVar[bool] = False

    def kinetic(self, q, v):
        mass = 1.0 + q[0] ** 2 + 0.5 * q[1] ** 2
        return 0.5 * mass * jnp.sum(v**2) + 0.25 * v[0] * q[1]

    def potential(self, q):
        return 0.5 * jnp.sum(q**2) + q[0] ** 4 / 8

    def state(self):
        return PhaseState(q=jnp.array([0.6, -0.3]), p=jnp.array([0.2, 0.9]))


def reference(model, state0, T):
    """Independent reference: SciPy's DOP853 on Hamilton's equations, tol 1e-13."""
    n = model.dof
    field = jax.jit(lambda y: jnp.concatenate(jax.tree.leaves(
        model.vector_field(PhaseState(q=y[:n], p=y[n:])))))
    y0 = np.concatenate([state0.q, state0.p])
    sol = solve_ivp(lambda t, y: np.asarray(field(jnp.asarray(y))), (0.0, T), y0,
                    method="DOP853", rtol=1e-13, atol=1e-14)
    assert sol.success
    return sol.y[:, -1]


def endpoint_errors(model, method, steps, T, ref):
    s0 = model.default_state()
    errs = []
    for h in steps:
        state, code = final_state(model, method, s0, h, round(T / h))
        assert int(code) == 0
        errs.append(np.linalg.norm(np.concatenate([state.q, state.p]) - ref))
    return errs


# ---------------------------------------------------------------------------------------

def test_declared_traits():
    expected = {
        "rk4": (4, False, False, False),
        "gl4": (4, True, True, True),
        "gl6": (6, True, True, True),
        "verlet": (2, True, True, False),
        "galerkin4": (4, True, True, True),
        "galerkin6": (6, True, True, True),
    }
    for name, (order, symmetric, symplectic, implicit) in expected.items():
        m = EUCLIDEAN_METHODS[name]()
        assert m.name == name
        assert (m.order, m.symmetric, m.symplectic, m.implicit) == (
            order, symmetric, symplectic, implicit)


@pytest.mark.parametrize(
    ("name", "order"), [("rk4", 4), ("gl4", 4), ("galerkin4", 4), ("verlet", 2)]
)
def test_oscillator_convergence_order(name, order):
    model = HarmonicOscillator()
    s0 = model.default_state()
    ex = model.exact(s0, 10.0)
    ref = np.concatenate([ex.q, ex.p])
    steps = [0.1, 0.05, 0.025, 0.0125]
    slope = observed_order(steps, endpoint_errors(model, EUCLIDEAN_METHODS[name](), steps,
                                                  10.0, ref))
    assert abs(slope - order) <= 0.1, slope


@pytest.mark.parametrize("name", ["gl6", "galerkin6"])
def test_oscillator_sixth_order(name):
    # Larger steps: at h <= 0.05 the error of a 6th-order method is at round-off (~1e-13).
    model = HarmonicOscillator()
    s0 = model.default_state()
    ex = model.exact(s0, 10.0)
    steps = [0.4, 0.2, 0.1]
    errs = endpoint_errors(model, EUCLIDEAN_METHODS[name](), steps, 10.0,
                           np.concatenate([ex.q, ex.p]))
    assert abs(observed_order(steps, errs) - 6) <= 0.3


@pytest.mark.parametrize(
    ("model", "name", "order"),
    [
        (Pendulum(), "rk4", 4),
        (Pendulum(), "gl4", 4),
        (Pendulum(), "galerkin4", 4),
        (Pendulum(), "verlet", 2),
        (VariableMass(), "gl4", 4),
        (VariableMass(), "galerkin4", 4),
        (VariableMass(), "rk4", 4),
    ],
    ids=lambda x: type(x).__name__ if isinstance(x, AbstractEuclideanModel) else str(x),
)
def test_nonlinear_convergence_against_scipy(model, name, order):
    T = 5.0
    ref = reference(model, model.default_state(), T)
    steps = [0.1, 0.05, 0.025, 0.0125]
    errs = endpoint_errors(model, EUCLIDEAN_METHODS[name](), steps, T, ref)
    # Nonlinear problems carry higher-order error terms at the largest step: 0.15, not 0.1.
    assert abs(observed_order(steps, errs) - order) <= 0.15, (errs, observed_order(steps, errs))


def test_galerkin_degree_one_is_second_order():
    model = Pendulum()
    ref = reference(model, model.default_state(), 5.0)
    steps = [0.1, 0.05, 0.025, 0.0125]
    errs = endpoint_errors(model, GalerkinVI(degree=1), steps, 5.0, ref)
    assert abs(observed_order(steps, errs) - 2) <= 0.1


# --- energy over 10^5 steps ------------------------------------------------------------

N_LONG = 100_000


@pytest.fixture(scope="module")
def long_runs():
    model = HarmonicOscillator(m=1.0, k=1.0)
    return {
        name: relative_energy_error(
            simulate(model, EUCLIDEAN_METHODS[name](), model.state(q0=1.0, p0=0.0), 0.1, N_LONG,
                     save_every=10).energy
        )
        for name in ("rk4", "gl4", "galerkin4")
    }


def test_rk4_energy_matches_stability_polynomial(long_runs):
    predicted = 1.0 - rk4_energy_factor(0.1, N_LONG)
    measured = long_runs["rk4"][-1]
    assert predicted == pytest.approx(1.386e-3, rel=1e-3)  # |R(0.1i)|^(2e5) = 1 − 1.386e-3
    # The issue asks for 1%; the map is linear, so the agreement is at round-off (~1e-8).
    assert measured == pytest.approx(predicted, rel=1e-6)
    assert drift_ratio(long_runs["rk4"]) > 9.0  # linear drift: last tenth ~10x the first


def test_gauss_legendre_conserves_energy_to_roundoff(long_runs):
    # GL4 preserves quadratic invariants exactly; only round-off is left. Bound: N·eps.
    assert np.max(long_runs["gl4"]) <= N_LONG * EPS


def test_galerkin_energy_bounded_without_drift(long_runs):
    err = long_runs["galerkin4"]
    assert 1e-9 < np.max(err) < 1e-6  # an O(h^4) oscillation, not round-off, not drift
    assert drift_ratio(err) == pytest.approx(1.0, abs=0.02)


def test_galerkin_roundoff_does_not_drift():
    """At h = 0.05 the 6th-order Galerkin VI's energy oscillation (~2e-13) is below the
    round-off bias of the naive momentum sum (~2e-15 per step, 2e-10 over 10^5 steps):
    the rearranged sum keeps the error at the oscillation level."""
    model = HarmonicOscillator()
    tr = simulate(model, GalerkinVI(degree=3), model.default_state(), 0.05, N_LONG,
                  save_every=100)
    err = relative_energy_error(tr.energy)
    # Measured 1.9e-13 (2.9e-13 with --alt-numerics): 2e-11 keeps 10x below the naive
    # sum's 2e-10.
    assert np.max(err) < 2e-11


# --- geometric properties of the one-step map ------------------------------------------


def step_map(model, method, h):
    n = model.dof

    def phi(y):
        state, _ = method.step(model, PhaseState(q=y[:n], p=y[n:]), h)
        return jnp.concatenate([state.q, state.p])

    return phi


SYMPLECTIC_CASES = [(Pendulum(), name) for name in (*SYMPLECTIC, "rk4")] + [
    (VariableMass(), name) for name in (*SYMPLECTIC, "rk4") if name != "verlet"  # separable only
]


@pytest.mark.parametrize(("model", "name"), SYMPLECTIC_CASES,
                         ids=[f"{type(m).__name__}-{n}" for m, n in SYMPLECTIC_CASES])
def test_symplecticity_of_step_jacobian(model, name):
    method = EUCLIDEAN_METHODS[name]()
    n = model.dof
    y0 = jnp.concatenate([model.default_state().q, model.default_state().p])
    Jphi = np.asarray(jax.jit(jax.jacfwd(step_map(model, method, 0.2)))(y0))
    omega = np.block([[np.zeros((n, n)), np.eye(n)], [-np.eye(n), np.zeros((n, n))]])
    defect = np.max(np.abs(Jphi.T @ omega @ Jphi - omega))
    if method.symplectic:
        assert defect < 1e-13
    else:
        assert defect > 1e-7  # RK4 is not symplectic: the test can tell


@pytest.mark.parametrize("name", list(EUCLIDEAN_METHODS))
def test_symmetry_of_step(name):
    model = Pendulum()
    method = EUCLIDEAN_METHODS[name]()
    y0 = jnp.concatenate([model.default_state().q, model.default_state().p])
    back = jax.jit(lambda y: step_map(model, method, -0.2)(step_map(model, method, 0.2)(y)))(y0)
    gap = float(jnp.max(jnp.abs(back - y0)))
    if method.symmetric:
        assert gap < 1e-14
    else:
        assert gap > 1e-8


@pytest.mark.parametrize("name", ["gl4", "galerkin4", "verlet"])
def test_time_reversal_over_many_steps(name):
    model = VariableMass() if name != "verlet" else Pendulum()
    method = EUCLIDEAN_METHODS[name]()
    s0 = model.default_state()
    fwd = simulate(model, method, s0, 0.05, 400)
    mid = jax.tree.map(lambda x: x[-1], fwd.state)
    back = simulate(model, method, mid, -0.05, 400)
    end = jax.tree.map(lambda x: x[-1], back.state)
    assert float(jnp.max(jnp.abs(end.q - s0.q))) < 1e-11
    assert float(jnp.max(jnp.abs(end.p - s0.p))) < 1e-11


def test_verlet_refuses_nonseparable_model():
    with pytest.raises(ValueError, match="verlet needs a separable model"):
        simulate(VariableMass(), StormerVerlet(), VariableMass().default_state(), 0.1, 10)


def test_bad_hyperparameters():
    with pytest.raises(ValueError, match="stages"):
        GaussLegendre(stages=0)
    with pytest.raises(ValueError, match="degree"):
        GalerkinVI(degree=0)


def test_newton_iterations_are_few():
    # Smooth problem, small step: two Newton iterations (the second confirms convergence).
    model = VariableMass()
    for method in (GaussLegendre(), GalerkinVI()):
        tr = simulate(model, method, model.default_state(), 0.01, 200)
        assert float(tr.newton_mean) <= 3.0
        assert int(tr.result) == 0


def test_rk4_stability_boundary_on_oscillator():
    # RK4 is stable on the imaginary axis for |y| <= 2√2 and unstable beyond.
    model = HarmonicOscillator()
    s0 = model.default_state()
    for h, grows in ((2.8, False), (2.9, True)):
        tr = simulate(model, RK4(), s0, h, 200)
        ratio = float(tr.energy[-1] / tr.energy[0])
        assert (ratio > 1.0) == grows
        assert ratio == pytest.approx(rk4_energy_factor(h, 200), rel=1e-9)
