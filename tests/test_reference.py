r"""The car-pendulum against an independent reference: its continuous equations of motion
derived by hand (below), in plain NumPy, integrated by SciPy's DOP853 at tolerance 1e-13.

Derivation (``e3`` down, ``P = [e1 e2]ᵀ``, ``a = RᵀPᵀv`` the cart velocity in the body
frame). From ``L = ½(m+M)|v|² + ½ωᵀJω + m vᵀPR(ω×ρ) + m g e3ᵀRρ``:

* momenta: ``Π = ∂L/∂ω = Jω + m ρ×a`` (since ``a·(ω×ρ) = ω·(ρ×a)``) and
  ``p = ∂L/∂v = (m+M)v + m PR(ω×ρ)``;
* the left-trivialised configuration derivative (``R → R(I + εη̂)``):
  ``τ = m (ω×ρ)×a + m g ρ×(Rᵀe3)``;
* equations: ``Ṙ = Rω̂``, ``Π̇ = Π×ω + τ``, ``ṗ = 0`` (``L`` does not depend on ``q``);
* with ``ȧ = −ω×a + RᵀPᵀv̇``, the accelerations solve the symmetric 5x5 system
  ``J ω̇ + m ρ̂RᵀPᵀ v̇ = Π×ω + τ + m ρ×(ω×a)``,
  ``−m PRρ̂ ω̇ + (m+M) v̇ = −m PR(ω×(ω×ρ))``.

None of this calls the library's autodiff mechanics; the library only supplies the
parameters and the integrators under test.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import lgvi_jax as L
from lgvi_jax import so3
from lgvi_jax.diagnostics import observed_order
from lgvi_jax.integrators import RIGID_METHODS
from lgvi_jax.models import CarPendulum
from lgvi_jax.simulate import simulate

E3 = np.array([0.0, 0.0, 1.0])
P = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
VI = ("lgvi", "hamel", "hamel-cayley", "hamel-exact")
STEPS = (0.02, 0.01, 0.005, 0.0025)
T_FINAL = 1.0


def hat(w):
    return np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])


class Reference:
    """Hand-derived car-pendulum equations (module docstring); state
    ``y = (R (9), ω (3), q (2), v (2))``."""

    def __init__(self, model: CarPendulum):
        self.m, self.M, self.g = float(model.m), float(model.M), float(model.g)
        self.rho, self.J = np.asarray(model.rho_c), np.asarray(model.J)

    def split(self, y):
        return y[:9].reshape(3, 3), y[9:12], y[12:14], y[14:16]

    def momenta(self, R, w, v):
        a = R.T @ P.T @ v
        Pi = self.J @ w + self.m * np.cross(self.rho, a)
        p = (self.m + self.M) * v + self.m * P @ R @ np.cross(w, self.rho)
        return Pi, p

    def energy(self, y):
        R, w, _, v = self.split(y)
        m, rho = self.m, self.rho
        return (0.5 * (m + self.M) * v @ v + 0.5 * w @ self.J @ w
                + m * v @ P @ R @ np.cross(w, rho) - m * self.g * E3 @ R @ rho)

    def angular_momentum_z(self, y):
        R, w, q, v = self.split(y)
        Pi, p = self.momenta(R, w, v)
        return (R @ Pi)[2] + q[0] * p[1] - q[1] * p[0]

    def rhs(self, _t, y):
        R, w, _, v = self.split(y)
        m, M, rho = self.m, self.M, self.rho
        a = R.T @ P.T @ v
        Pi, _ = self.momenta(R, w, v)
        tau = m * np.cross(np.cross(w, rho), a) + m * self.g * np.cross(rho, R.T @ E3)
        A = np.zeros((5, 5))
        A[:3, :3] = self.J
        A[:3, 3:] = m * hat(rho) @ R.T @ P.T
        A[3:, :3] = -m * P @ R @ hat(rho)
        A[3:, 3:] = (m + M) * np.eye(2)
        b = np.concatenate([np.cross(Pi, w) + tau + m * np.cross(rho, np.cross(w, a)),
                            -m * P @ R @ np.cross(w, np.cross(w, rho))])
        acc = np.linalg.solve(A, b)
        return np.concatenate([(R @ hat(w)).ravel(), acc[:3], v, acc[3:]])

    def solve(self, y0, t_eval):
        sol = solve_ivp(self.rhs, (0.0, t_eval[-1]), y0, method="DOP853", t_eval=t_eval,
                        rtol=1e-13, atol=1e-13)
        assert sol.success, sol.message
        return sol.y.T


def paper_model():
    return CarPendulum()


def moving_model():
    """Non-zero horizontal momentum, generic attitude, cart away from the origin."""
    return CarPendulum(q0=(0.7, -0.4), v0=(0.8, -0.3), omega0=(1.0, -0.5, 3.0),
                       R0=so3.exp(jnp.array([0.6, -0.9, 0.4])))


MODELS = {"paper": paper_model, "moving": moving_model}


@pytest.fixture(scope="module", params=list(MODELS))
def case(request):
    model = MODELS[request.param]()
    ref = Reference(model)
    y0 = np.concatenate([np.ravel(model.R0), model.omega0, model.q0, model.v0])
    t = np.linspace(0.0, 2.0, 201)
    ys = ref.solve(y0, t)
    return request.param, model, ref, t, ys


def test_reference_conserves_its_invariants(case):
    """The hand-derived reference conserves energy, cart momentum and L_z (a check of the
    derivation and of the solver's accuracy)."""
    _, _, ref, _, ys = case
    E = np.array([ref.energy(y) for y in ys])
    p = np.array([ref.momenta(*ref.split(y)[:2], ref.split(y)[3])[1] for y in ys])
    lz = np.array([ref.angular_momentum_z(y) for y in ys])
    # DOP853 at rtol = atol = 1e-13 over 2 s: the invariants hold to ~1e-12.
    assert np.max(np.abs(E - E[0])) <= 1e-11 * max(1.0, abs(E[0]))
    assert np.max(np.abs(p - p[0])) <= 1e-11
    assert np.max(np.abs(lz - lz[0])) <= 1e-11
    R_end = ref.split(ys[-1])[0]
    assert np.linalg.norm(R_end.T @ R_end - np.eye(3)) <= 1e-11


def test_library_model_agrees_with_hand_derivation_at_t0(case):
    """Energy, momenta and L_z of the library's model (by autodiff) equal the hand
    formulas, and so does the library's vector field."""
    name, model, ref, _, ys = case
    y0 = ys[0]
    R, w, _, v = ref.split(y0)
    s0 = model.default_state()
    Pi, p = ref.momenta(R, w, v)
    np.testing.assert_allclose(s0.mu, Pi, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(s0.p, p, rtol=1e-14, atol=1e-14)
    inv = model.invariants(s0)
    assert float(inv["energy"]) == pytest.approx(ref.energy(y0), rel=1e-14)
    assert float(inv["angular_momentum_z"]) == pytest.approx(ref.angular_momentum_z(y0),
                                                             rel=1e-13, abs=1e-14)
    if name == "paper":  # the paper's initial state has zero horizontal momentum
        np.testing.assert_allclose(p, 0.0, atol=1e-15)
    else:
        assert np.abs(p).max() > 0.1


def test_rk4_with_tiny_step_matches_reference(case):
    """Validates the library's autodiff equations of motion end to end."""
    _, model, ref, t, ys = case
    n = round(t[-1] / 1e-3)
    traj = simulate(model, RIGID_METHODS["rk4"](), model.default_state(), 1e-3, n,
                    save_every=n)
    R_ref, _, q_ref, _ = ref.split(ys[-1])
    # RK4 at h = 1e-3: global error ~ C h^4 ~ 1e-12 over 2 s.
    np.testing.assert_allclose(traj.state.R[-1], R_ref, atol=1e-10)
    np.testing.assert_allclose(traj.state.q[-1], q_ref, atol=1e-10)


@eqx.filter_jit
def advance(model, method, state, h, n):
    """``n`` steps (a run-time value: one compilation per method for all steps)."""
    return jax.lax.fori_loop(0, jnp.asarray(n, jnp.int32),
                             lambda _, s: method.step(model, s, h)[0], state)


@eqx.filter_jit
def energy_of(model, state):
    return model.energy(state)


@pytest.fixture(scope="module")
def orders(case):
    """Position and energy errors against the reference at T = 1 for every method."""
    _, model, ref, t, ys = case
    k = int(np.argmin(np.abs(t - T_FINAL)))
    R_ref, _, q_ref, _ = ref.split(ys[k])
    centre_ref = np.concatenate([q_ref, [0.0]]) + R_ref @ np.asarray(model.rho_c)
    E0 = ref.energy(ys[0])
    s0 = model.default_state()
    out = {}
    for name in (*VI, "rk4"):
        method = RIGID_METHODS[name]()
        pos, energy = [], []
        for h in STEPS:
            n = round(T_FINAL / h)
            state, errors = s0, []
            for _ in range(10):  # the energy error at ten times in (0, T]
                state = advance(model, method, state, jnp.float64(h), jnp.int32(n // 10))
                errors.append(abs(float(energy_of(model, state)) - E0))
            pos.append(float(np.linalg.norm(np.asarray(model.pendulum_centre(state))
                                            - centre_ref)))
            energy.append(max(errors))
        out[name] = (observed_order(STEPS, pos), observed_order(STEPS, energy), pos, energy)
    return out


@pytest.mark.parametrize("name", [*VI, "rk4"])
def test_observed_orders_against_reference(orders, name):
    """Log-log slopes over h = 0.02 … 0.0025 at T = 1: 2 ± 0.1 for the variational
    integrators, 4 ± 0.2 for RK4, in the pendulum mass-centre position and in the energy
    error (maximum over the ten saved times)."""
    pos_order, energy_order, pos, energy = orders[name]
    expected, tol = (4.0, 0.2) if name == "rk4" else (2.0, 0.1)
    assert abs(pos_order - expected) <= tol, (pos_order, pos)
    assert abs(energy_order - expected) <= tol, (energy_order, energy)


def test_library_is_importable_without_scipy_at_runtime():
    """The reference needs SciPy (a dev extra); the library itself does not."""
    assert "scipy" not in L.__dict__
