"""Rigid-body models: the mechanics derived by autodiff against hand-written formulas (the
paper's eqs. 38–39, Euler's equations, the heavy-top torque), and input validation."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lgvi_jax  # noqa: F401  (float64)
from lgvi_jax import so3
from lgvi_jax.models import CarPendulum, FreeRigidBody, HeavyTop, RigidState
from lgvi_jax.models.rigid import check_inertia, left_gradient
from lgvi_jax.models.rigid_bodies import PAPER_OMEGA0, PAPER_R0, rotational_kinetic

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
    with pytest.raises(ValueError, match="CarPendulum: R0 is not in SO"):
        CarPendulum().state(R0=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ValueError, match="CarPendulum: q0 must have shape"):
        CarPendulum().state(q0=(1.0, 2.0, 3.0))
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


# ------------------------------------------------ initial states: model.state, not fields

RIGID_MODELS = {"free-rigid-body": FreeRigidBody, "heavy-top": HeavyTop,
                "car-pendulum": CarPendulum}


@pytest.mark.parametrize("name", list(RIGID_MODELS))
def test_default_state_is_the_default_initial_condition(name):
    """``state()`` and ``default_state()`` are the state of the class's default initial
    condition (the paper's for the top and the car-pendulum), built by the model's
    Legendre map from the configuration and velocities."""
    cls = RIGID_MODELS[name]
    model = cls()
    empty = np.zeros(0)
    q0 = getattr(cls, "DEFAULT_Q0", empty)
    v0 = getattr(cls, "DEFAULT_V0", empty)
    expected = model.state_from_velocities(np.asarray(cls.DEFAULT_R0), cls.DEFAULT_OMEGA0,
                                           q0, v0)
    for state in (model.state(), model.default_state()):
        for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(expected), strict=True):
            np.testing.assert_array_equal(a, b)
    # The defaults are the ones the models carried before (the paper's for the top and
    # the car-pendulum; near the intermediate axis for the free body).
    if name == "free-rigid-body":
        np.testing.assert_array_equal(cls.DEFAULT_R0, np.eye(3))
        assert cls.DEFAULT_OMEGA0 == (0.1, 1.0, 0.1)
    else:
        assert (cls.DEFAULT_R0, cls.DEFAULT_OMEGA0) == (PAPER_R0, PAPER_OMEGA0)
    if name == "car-pendulum":
        assert (cls.DEFAULT_Q0, cls.DEFAULT_V0) == ((-0.125, -0.0125), (0.525, -0.0125))
        # Written out: the paper's state, eq. 39 at (PAPER_R0, PAPER_OMEGA0, q0, v0).
        R, w = np.asarray(PAPER_R0), np.asarray(PAPER_OMEGA0)
        v = np.asarray(cls.DEFAULT_V0)
        rho, J = np.asarray(model.rho_c), np.asarray(model.J)
        np.testing.assert_allclose(model.state().mu, J @ w + np.cross(rho, R.T @ P.T @ v),
                                   rtol=1e-14, atol=1e-15)
        np.testing.assert_allclose(model.state().p, 2 * v + P @ R @ np.cross(w, rho),
                                   atol=1e-15)


def test_state_takes_each_initial_condition():
    """Each argument of ``state`` is used: the same as ``state_from_velocities`` with it."""
    model = CarPendulum()
    R0 = so3.exp(jnp.array([0.6, -0.9, 0.4]))
    kwargs = {"R0": R0, "omega0": (1.0, -0.5, 3.0), "q0": (0.7, -0.4), "v0": (0.8, -0.3)}
    state = model.state(**kwargs)
    expected = model.state_from_velocities(R0, jnp.array(kwargs["omega0"]),
                                           jnp.array(kwargs["q0"]), jnp.array(kwargs["v0"]))
    for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(expected), strict=True):
        np.testing.assert_array_equal(a, b)
    top = HeavyTop()
    s = top.state(R0=np.eye(3), omega0=(0.0, 0.0, 2.0))
    np.testing.assert_array_equal(s.R, np.eye(3))
    # The Legendre map by autodiff: a few roundings of J's entries (measured 1.7e-16).
    np.testing.assert_allclose(s.mu, np.asarray(top.J) @ np.array([0.0, 0.0, 2.0]),
                               rtol=1e-14)


@pytest.mark.parametrize("name", list(RIGID_MODELS))
def test_grad_through_state_matches_finite_differences(name):
    """``jax.grad`` of the energy with respect to ``omega0``, through ``state`` (whose
    checks are skipped under tracing), equals central differences; also under ``jit``, and
    ``vmap`` over initial velocities gives the single states."""
    model = RIGID_MODELS[name]()

    def energy(omega0):
        return model.energy(model.state(omega0=omega0))

    w = jnp.array([0.3, -0.7, 1.9])
    g = np.asarray(jax.grad(energy)(w))
    np.testing.assert_allclose(np.asarray(jax.jit(jax.grad(energy))(w)), g, rtol=1e-14,
                               atol=1e-15)
    eps = 1e-6
    fd = np.array([(energy(w.at[i].add(eps)) - energy(w.at[i].add(-eps))) / (2 * eps)
                   for i in range(3)])
    # The energy is quadratic in omega0: central differences are exact but for rounding
    # (~eps_machine |E| / 1e-6 ~ 1e-10 relative).
    np.testing.assert_allclose(g, fd, rtol=1e-7, atol=1e-9)
    # ... and g = J_eff ω0 is not trivially zero.
    assert np.linalg.norm(g) > 0.1
    batch = jnp.stack([w, 2 * w])
    states = jax.vmap(lambda x: model.state(omega0=x))(batch)
    for i in range(2):
        single = model.state(omega0=batch[i])
        for a, b in zip(jax.tree.leaves(states), jax.tree.leaves(single), strict=True):
            np.testing.assert_allclose(a[i], b, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize(("cls", "name", "value"), [
    (CarPendulum, "omega0", (1.0, 0.0, 0.0)), (CarPendulum, "R0", np.eye(3)),
    (CarPendulum, "q0", (0.0, 0.0)), (CarPendulum, "v0", (0.0, 0.0)),
    (HeavyTop, "omega0", (1.0, 0.0, 0.0)), (HeavyTop, "R0", np.eye(3)),
    (FreeRigidBody, "omega0", (1.0, 0.0, 0.0)), (FreeRigidBody, "R0", np.eye(3)),
])
def test_removed_initial_condition_keywords_say_where_they_go(cls, name, value):
    msg = (f"{cls.__name__}: {name} is an initial condition, not a parameter: pass it to "
           f"model.state({name}=...)")
    with pytest.raises(TypeError) as err:
        cls(**{name: value})
    assert str(err.value) == msg
    with pytest.raises(TypeError, match="unexpected keyword argument 'omega'"):
        cls(omega=(1.0, 0.0, 0.0))


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"R0": np.diag([1.0, 1.0, -1.0])}, "CarPendulum: R0 is not in SO\\(3\\)"),
    ({"R0": 1.01 * np.eye(3)}, "CarPendulum: R0 is not in SO\\(3\\)"),
    ({"R0": np.eye(2)}, "CarPendulum: R0 must be a 3x3 matrix"),
    ({"omega0": (1.0, 2.0)}, "CarPendulum: omega0 must have shape \\(3,\\)"),
    ({"omega0": (np.nan, 0.0, 0.0)}, "CarPendulum: omega0 must be finite"),
    ({"q0": (1.0, 2.0, 3.0)}, "CarPendulum: q0 must have shape \\(2,\\)"),
    ({"v0": (np.inf, 0.0)}, "CarPendulum: v0 must be finite"),
    ({"omega0": "fast"}, "CarPendulum: omega0 must be a number or an array"),
])
def test_state_validates_its_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        CarPendulum().state(**kwargs)


def test_free_body_and_top_states_validate_their_arguments():
    for cls in (FreeRigidBody, HeavyTop):
        with pytest.raises(ValueError, match=f"{cls.__name__}: R0 is not in SO"):
            cls().state(R0=np.diag([1.0, -1.0, -1.0]) * 2)
        with pytest.raises(ValueError, match=f"{cls.__name__}: omega0 must have shape"):
            cls().state(omega0=np.zeros(4))
        with pytest.raises(ValueError, match=f"{cls.__name__}: omega0 must be finite"):
            cls().state(omega0=(0.0, np.nan, 0.0))


@pytest.mark.parametrize("system", ["free-rigid-body", "heavy-top", "car-pendulum"])
def test_a_model_does_not_change_with_the_initial_condition(system):
    """The model is its parameters only: systems built with different initial conditions
    give equal models (the same pytree, leaves equal) and different states; no field is an
    initial condition."""
    from lgvi_jax.systems import get_system

    spec = get_system(system)
    overrides = {"omega0": np.array([1.0, -0.5, 3.0]),
                 "R0": np.ravel(np.asarray(so3.exp(jnp.array([0.6, -0.9, 0.4]))))}
    if system == "car-pendulum":
        overrides.update(q0=np.array([0.7, -0.4]), v0=np.array([0.8, -0.3]))
    model_a, state_a = spec.build()
    model_b, state_b = spec.build(overrides)
    assert bool(eqx.tree_equal(model_a, model_b))
    assert jax.tree.structure(model_a) == jax.tree.structure(RIGID_MODELS[system]())
    assert bool(eqx.tree_equal(model_a, RIGID_MODELS[system]()))
    assert not np.array_equal(np.asarray(state_a.mu), np.asarray(state_b.mu))
    fields = {f.name for f in dataclasses.fields(model_a)}
    assert not fields & {"R0", "omega0", "q0", "v0"}, fields
    # A parameter does change the model.
    model_c, _ = spec.build({"J": np.ravel(np.diag([1.0, 1.5, 2.0]))})
    assert not bool(eqx.tree_equal(model_a, model_c))
