"""Rigid-body models: the mechanics derived by autodiff against hand-written formulas (the
paper's eqs. 38–39, Euler's equations, the heavy-top torque), and input validation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lgvi_jax  # noqa: F401  (float64)
from lgvi_jax import so3
from lgvi_jax.models import CarPendulum, FreeRigidBody, HeavyTop, RigidState
from lgvi_jax.models.rigid import check_inertia, left_gradient
from lgvi_jax.models.rigid_bodies import rotational_kinetic

E3 = np.array([0.0, 0.0, 1.0])
P = np.array([[1.0, 0, 0], [0, 1.0, 0]])


def random_state(seed):
    rng = np.random.default_rng(seed)
    R = np.asarray(so3.exp(rng.normal(size=3)))
    return R, rng.normal(size=3), rng.normal(size=2), rng.normal(size=2)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_car_pendulum_momenta_and_energy_match_eqs_38_39(seed):
    model = CarPendulum()
    R, w, q, v = random_state(seed)
    m, M, g = 1.0, 1.0, 9.81
    rho, J = np.asarray(model.rho_c), np.asarray(model.J)
    mu, p = model.momenta(R, w, q, v)
    # eq. 39: Π = Jω + m ρ_c × (Rᵀ Pᵀ v), p = (m + M) v + m P R (ω × ρ_c)
    np.testing.assert_allclose(mu, J @ w + m * np.cross(rho, R.T @ P.T @ v), rtol=1e-14,
                               atol=1e-14)
    np.testing.assert_allclose(p, (m + M) * v + m * P @ R @ np.cross(w, rho), rtol=1e-14,
                               atol=1e-14)
    energy = (0.5 * (m + M) * v @ v + 0.5 * w @ J @ w + m * v @ P @ R @ np.cross(w, rho)
              - m * g * E3 @ R @ rho)
    state = RigidState(R=jnp.asarray(R), mu=mu, q=jnp.asarray(q), p=p)
    assert float(model.energy(state)) == pytest.approx(energy, rel=1e-14)
    w2, v2 = model.velocities(R, mu, q, p)
    np.testing.assert_allclose(w2, w, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(v2, v, rtol=1e-13, atol=1e-14)


@pytest.mark.parametrize("seed", [3, 4])
def test_car_pendulum_closed_form_inverse_legendre_matches_autodiff(seed):
    """The closed-form velocities (3x3 Schur complement) and energy (T + U) equal the base
    class's autodiff mass matrix, 5x5 solve and μ·ω + p·v − L, also batched."""
    from lgvi_jax.models.rigid import AbstractRigidBodyModel as Base

    model = CarPendulum(m=0.7, M=1.9, rho_c=(0.1, -0.3, 0.8))
    states = [random_state(seed * 10 + k) for k in range(4)]
    for R, w, q, v in states:
        mu, p = model.momenta(R, w, q, v)
        for a, b in zip(model.velocities(R, mu, q, p), Base.velocities(model, R, mu, q, p),
                        strict=True):
            # Two different eliminations (3x3 Schur complement and 5x5): each within
            # ~n eps κ(M) ‖x‖ of the exact solution (n = 5, κ(M) <= 1e2 for these states),
            # ~1e-13 ‖x‖, shared by every component, so bounded relative to the largest:
            # 1e-12 ‖x‖_max. Worst measured 4.1e-14 at ‖x‖_max ~ 1 (--alt-numerics).
            np.testing.assert_allclose(a, b, rtol=0,
                                       atol=1e-12 * float(np.max(np.abs(np.asarray(b)))))
        state = RigidState(R=jnp.asarray(R), mu=mu, q=jnp.asarray(q), p=p)
        assert float(model.energy(state)) == pytest.approx(float(Base.energy(model, state)),
                                                           rel=1e-13)
    batch = jax.tree.map(lambda *x: jnp.stack(x), *[RigidState(
        R=jnp.asarray(R), mu=model.momenta(R, w, q, v)[0], q=jnp.asarray(q),
        p=model.momenta(R, w, q, v)[1]) for R, w, q, v in states])
    energies = jax.vmap(model.energy)(batch)
    for k in range(len(states)):
        one = jax.tree.map(lambda x, k=k: x[k], batch)
        assert float(energies[k]) == pytest.approx(float(model.energy(one)), rel=1e-14)


def test_rotational_kinetic_matrix_form():
    """½tr(Ω J_d Ωᵀ) is ½ωᵀJω for Ω = hat(ω), and tr((I − F)J_d)/h² for Ω = (F − I)/h."""
    J = jnp.array([[2.0, 0.3, -0.2], [0.3, 3.0, 0.4], [-0.2, 0.4, 3.5]])
    w = jnp.array([0.3, -1.2, 0.8])
    assert float(rotational_kinetic(J, so3.hat(w))) == pytest.approx(
        float(0.5 * w @ J @ w), rel=1e-14)
    F, h = so3.exp(0.1 * w), 0.1
    Jd = 0.5 * jnp.trace(J) * jnp.eye(3) - J
    lgvi = jnp.trace((jnp.eye(3) - F) @ Jd) / h**2
    assert float(rotational_kinetic(J, (F - jnp.eye(3)) / h)) == pytest.approx(float(lgvi),
                                                                                rel=1e-12)


def test_left_gradient_matches_exponential_curve():
    R = so3.exp(jnp.array([0.4, -0.3, 1.1]))
    A = jnp.arange(9.0).reshape(3, 3)

    def f(S):
        return jnp.sum(A * S) + jnp.sum(S @ S) ** 2

    g = left_gradient(f, R)
    h = 1e-6
    # Central differences: truncation O(h²) ~ 1e-12 (relative), round-off of the two
    # values of f divided by 2h: a few eps |f| / h (|f| ≈ 12 here: ~3e-9 absolute against
    # derivatives of 0.04-40); bound with a factor of 10.
    fd_noise = 10 * np.finfo(float).eps * abs(float(f(R))) / h
    for eta in np.eye(3):
        fd = (f(R @ so3.exp(h * eta)) - f(R @ so3.exp(-h * eta))) / (2 * h)
        assert float(g @ eta) == pytest.approx(float(fd), rel=1e-8, abs=fd_noise)


def test_free_body_vector_field_is_euler():
    J = jnp.array([[2.0, 0.3, -0.2], [0.3, 3.0, 0.4], [-0.2, 0.4, 3.5]])
    body = FreeRigidBody(J=J)
    R, w, _, _ = random_state(3)
    s = body.state_from_velocities(R, w, jnp.zeros(0), jnp.zeros(0))
    f = body.vector_field(s)
    np.testing.assert_allclose(f.R, R @ so3.hat(w), atol=1e-14)
    np.testing.assert_allclose(f.mu, np.cross(J @ w, w), atol=1e-13)  # J ω̇ = Jω × ω


def test_heavy_top_vector_field_torque():
    top = HeavyTop()
    R, w, _, _ = random_state(4)
    s = top.state_from_velocities(R, w, jnp.zeros(0), jnp.zeros(0))
    f = top.vector_field(s)
    J, rho = np.asarray(top.J), np.asarray(top.rho_c)
    torque = 9.81 * np.cross(rho, R.T @ E3)  # m g ρ_c × (Rᵀ e3), e3 down
    np.testing.assert_allclose(f.mu, np.cross(J @ w, w) + torque, atol=1e-12)
    inv = top.invariants(s)
    assert float(inv["angular_momentum_z"]) == pytest.approx(float((R @ J @ w)[2]), rel=1e-13)


def test_car_pendulum_invariants_and_centre():
    model = CarPendulum()
    s = model.default_state()
    inv = model.invariants(s)
    # The paper's initial state has zero horizontal momentum.
    np.testing.assert_allclose(inv["momentum"], 0.0, atol=1e-15)
    lz = (np.asarray(s.R) @ np.asarray(s.mu))[2] + (-0.125) * s.p[1] - (-0.0125) * s.p[0]
    assert float(inv["angular_momentum_z"]) == pytest.approx(float(lz), rel=1e-14)
    centre = model.pendulum_centre(s)
    np.testing.assert_allclose(centre, [-0.125 + 0.25, -0.0125 - 1.0, 0.25], atol=1e-15)
    # Batched over a trajectory axis.
    # Batched over a trajectory axis: each row is the unbatched value.
    batch = jax.tree.map(lambda x: jnp.stack([x, x]), s)
    np.testing.assert_array_equal(model.pendulum_centre(batch), np.stack([centre, centre]))
    single = np.asarray(model.spatial_angular_momentum(s))
    # R mu, the body's angular momentum in the inertial frame (3 products per entry).
    np.testing.assert_allclose(single, np.asarray(s.R) @ np.asarray(s.mu), rtol=1e-14,
                               atol=1e-15)
    assert np.abs(single).max() > 0.1
    np.testing.assert_allclose(model.spatial_angular_momentum(batch),
                               np.stack([single, single]), rtol=1e-15, atol=0)


@pytest.mark.parametrize(
    "J, message",
    [
        (np.diag([1.0, 1.0, 3.0]), "triangle inequality"),
        (np.diag([1.0, -1.0, 1.0]), "positive definite"),
        (np.array([[1.0, 0.1, 0], [0, 1.0, 0], [0, 0, 1.0]]), "symmetric"),
        (np.eye(2), "3x3"),
        (np.full((3, 3), np.nan), "finite"),
    ],
)
def test_check_inertia_refuses_unphysical(J, message):
    with pytest.raises(ValueError, match=message):
        check_inertia("J", J, "Test")
    check_inertia("J", np.diag([1.0, 1.0, 2.0]), "Test")  # a flat disc is physical


def test_models_validate_inputs():
    with pytest.raises(ValueError, match="R0 is not in SO"):
        CarPendulum(R0=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="q0 must have shape"):
        CarPendulum(q0=(1.0, 2.0, 3.0))
    with pytest.raises(ValueError, match="g must be finite and >= 0"):
        HeavyTop(g=-1.0)
    with pytest.raises(ValueError, match="M must be finite and > 0"):
        CarPendulum(M=0.0)
    model = CarPendulum()
    s = model.default_state()
    with pytest.raises(ValueError, match=r"state0\.R is not a rotation"):
        model.check_state(RigidState(R=s.R * 1.01, mu=s.mu, q=s.q, p=s.p))
    with pytest.raises(ValueError, match=r"state0\.q must have shape"):
        model.check_state(RigidState(R=s.R, mu=s.mu, q=jnp.zeros(3), p=s.p))
    with pytest.raises(ValueError, match="must be a RigidState"):
        model.check_state((s.R, s.mu))


def test_models_are_differentiable_and_vmappable_in_parameters():
    """Parameters are pytree leaves: grad and vmap over them work without closures."""

    def energy(m):
        model = CarPendulum(m=m)
        return model.energy(model.default_state())

    g = jax.grad(energy)(1.0)
    fd = (energy(1.0 + 1e-6) - energy(1.0 - 1e-6)) / 2e-6
    assert float(g) == pytest.approx(float(fd), rel=1e-7)
    energies = jax.vmap(energy)(jnp.array([0.5, 1.0, 2.0]))
    assert energies.shape == (3,)
    assert float(energies[1]) == pytest.approx(float(energy(1.0)), rel=1e-15)
