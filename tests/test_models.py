"""Models: mechanics derived by autodiff, exact solutions, parameter validation."""

from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lgvi_jax  # noqa: F401  (float64)
from lgvi_jax.models import AbstractEuclideanModel, HarmonicOscillator, PhaseState


class Gyroscopic(AbstractEuclideanModel):
    """T = ½ vᵀ M(q) v + vᵀ A q with a position-dependent SPD mass matrix."""

    dof: ClassVar[int] = 3
    separable: ClassVar[bool] = False

    def mass(self, q):
        B = jnp.array([[2.0, 0.3, 0.1], [0.3, 1.5, -0.2], [0.1, -0.2, 1.0]])
        return B + jnp.diag(q**2)

    def kinetic(self, q, v):
        A = jnp.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.5], [0.0, -0.5, 0.0]])
        return 0.5 * v @ self.mass(q) @ v + v @ (A @ q)

    def potential(self, q):
        return 0.5 * jnp.sum(q**2)

    def state(self):
        return PhaseState(q=jnp.array([0.3, -0.2, 0.5]), p=jnp.array([0.1, 0.4, -0.3]))


def test_legendre_transform_round_trip():
    model = Gyroscopic()
    q = jnp.array([0.4, -0.1, 0.2])
    v = jnp.array([1.0, -2.0, 0.5])
    p = model.momentum(q, v)
    np.testing.assert_allclose(np.asarray(model.velocity(q, p)), np.asarray(v), rtol=1e-14)
    # p = M v + A q, written out by hand
    A = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.5], [0.0, -0.5, 0.0]])
    np.testing.assert_allclose(np.asarray(p), np.asarray(model.mass(q)) @ v + A @ q, rtol=1e-14)


def test_energy_is_the_hamiltonian():
    model = HarmonicOscillator(m=2.0, k=3.0)
    state = PhaseState(q=jnp.array([0.7]), p=jnp.array([-1.1]))
    assert float(model.energy(state)) == pytest.approx(1.1**2 / 4 + 1.5 * 0.49, rel=1e-15)
    # Gyroscopic terms do no work: H = ½ vᵀMv + U, whatever A is
    g = Gyroscopic()
    s = g.default_state()
    v = g.velocity(s.q, s.p)
    expected = 0.5 * v @ g.mass(s.q) @ v + g.potential(s.q)
    assert float(g.energy(s)) == pytest.approx(float(expected), rel=1e-14)


def test_vector_field_is_hamiltons_equations():
    g = Gyroscopic()
    s = g.default_state()

    def H(q, p):
        return g.energy(PhaseState(q=q, p=p))

    dHdq, dHdp = jax.grad(H, argnums=(0, 1))(s.q, s.p)
    f = g.vector_field(s)
    np.testing.assert_allclose(np.asarray(f.q), np.asarray(dHdp), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(f.p), -np.asarray(dHdq), rtol=1e-13)


def test_oscillator_exact_solution_solves_the_ode():
    model = HarmonicOscillator(m=1.5, k=0.6)
    s0 = PhaseState(q=jnp.array([0.3]), p=jnp.array([1.2]))
    t = 2.7
    state, rate = jax.jvp(lambda t: model.exact(s0, t), (jnp.asarray(t),), (jnp.asarray(1.0),))
    f = model.vector_field(PhaseState(q=state.q, p=state.p))
    np.testing.assert_allclose(np.asarray(rate.q), np.asarray(f.q), rtol=1e-14)
    np.testing.assert_allclose(np.asarray(rate.p), np.asarray(f.p), rtol=1e-14)
    e0 = model.energy(s0)
    assert float(model.energy(state)) == pytest.approx(float(e0), rel=1e-14)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"m": 0.0}, "m must be finite and > 0"), ({"m": -1.0}, "m must be"),
     ({"k": float("nan")}, "k must be finite"), ({"k": float("inf")}, "k must be finite"),
     ({"m": "heavy"}, "m must be a number")],
)
def test_oscillator_rejects_bad_parameters(kwargs, match):
    with pytest.raises(ValueError, match=match):
        HarmonicOscillator(**kwargs)


def test_parameters_are_traceable():
    # Under vmap/grad the parameter values are unknown: no check may fire, and the fields are
    # differentiable leaves.
    ks = jnp.array([0.5, 2.0])
    energies = jax.vmap(lambda k: HarmonicOscillator(k=k).energy(
        PhaseState(q=jnp.ones(1), p=jnp.zeros(1))))(ks)
    np.testing.assert_allclose(np.asarray(energies), [0.25, 1.0])
    grad_m = jax.grad(lambda m: HarmonicOscillator(m=m).energy(
        PhaseState(q=jnp.zeros(1), p=jnp.ones(1))))(2.0)
    assert float(grad_m) == pytest.approx(-1 / 8)


# ------------------------------------------------ initial states: model.state, not fields


def test_oscillator_state_defaults_and_arguments():
    """``state()``/``default_state()``: ``q0 = 1, p0 = 0`` (the paper's figures 1–3, the
    class constants); numbers or shape-(1,) arrays are taken."""
    model = HarmonicOscillator(m=2.0, k=3.0)
    expected = PhaseState(q=jnp.array([HarmonicOscillator.DEFAULT_Q0]),
                          p=jnp.array([HarmonicOscillator.DEFAULT_P0]))
    assert (HarmonicOscillator.DEFAULT_Q0, HarmonicOscillator.DEFAULT_P0) == (1.0, 0.0)
    for state in (model.state(), model.default_state()):
        for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(expected), strict=True):
            np.testing.assert_array_equal(a, b)
            assert a.dtype == jnp.float64 and a.shape == (1,)
    s = model.state(q0=np.array([0.4]), p0=-0.9)
    np.testing.assert_array_equal(s.q, [0.4])
    np.testing.assert_array_equal(s.p, [-0.9])
    model.check_state(s)


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"q0": (1.0, 2.0)}, r"HarmonicOscillator: q0 must be a number \(shape \(\) or \(1,\)\)"),
    ({"p0": float("nan")}, "HarmonicOscillator: p0 must be finite"),
    ({"q0": float("inf")}, "HarmonicOscillator: q0 must be finite"),
    ({"p0": "still"}, "HarmonicOscillator: p0 must be a number or an array"),
])
def test_oscillator_state_validates_its_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        HarmonicOscillator().state(**kwargs)


def test_grad_and_vmap_through_the_oscillator_state():
    """Derivatives with respect to the initial condition go through ``state``: the energy
    ``p0²/(2m) + k q0²/2`` has gradient ``(k q0, p0/m)``; ``vmap`` over ``q0`` works."""
    model = HarmonicOscillator(m=2.0, k=3.0)

    def energy(x):
        return model.energy(model.state(q0=x[0], p0=x[1]))

    g = jax.grad(energy)(jnp.array([0.7, -1.1]))
    np.testing.assert_allclose(np.asarray(g), [3.0 * 0.7, -1.1 / 2.0], rtol=1e-14)
    qs = jax.vmap(lambda q: model.state(q0=q).q)(jnp.array([0.5, 2.0]))
    np.testing.assert_array_equal(np.asarray(qs), [[0.5], [2.0]])


@pytest.mark.parametrize("name", ["q0", "p0"])
def test_oscillator_removed_keywords_say_where_they_go(name):
    with pytest.raises(TypeError) as err:
        HarmonicOscillator(m=1.0, **{name: 0.5})
    assert str(err.value) == (f"HarmonicOscillator: {name} is an initial condition, not a "
                              f"parameter: pass it to model.state({name}=...)")


def test_oscillator_model_does_not_change_with_the_initial_condition():
    import equinox as eqx

    from lgvi_jax.systems import get_system

    spec = get_system("oscillator")
    model_a, state_a = spec.build()
    model_b, state_b = spec.build({"q0": 0.3, "p0": -2.0})
    assert bool(eqx.tree_equal(model_a, model_b))
    assert bool(eqx.tree_equal(model_a, HarmonicOscillator()))
    np.testing.assert_array_equal(state_b.q, [0.3])
    np.testing.assert_array_equal(state_b.p, [-2.0])
    assert float(state_a.q[0]) == 1.0


def test_get_system_takes_a_name_or_a_system_and_names_what_it_got():
    from lgvi_jax.sweep import sweep_method
    from lgvi_jax.systems import get_system

    spec = get_system("heavy-top")
    assert get_system(spec) is spec
    # A System where a name is expected works too (sweep_method resolves it the same way).
    assert sweep_method(spec, "lgvi") == sweep_method("heavy-top", "lgvi")
    with pytest.raises(TypeError, match=r"expected a system's name \(one of .*heavy-top.*\) "
                                        r"or a System, got int"):
        get_system(3)
    with pytest.raises(ValueError, match="unknown system 'top'"):
        get_system("top")


# ------------------------------------------------ parameters converted on the host


_COMPILES: list[str] | None = None  # backend compiles while a test counts them


def _count_compiles(event: str, duration: float, **kwargs) -> None:
    if _COMPILES is not None and "backend_compile" in event:
        _COMPILES.append(event)


jax.monitoring.register_event_duration_secs_listener(_count_compiles)


def test_building_a_model_compiles_nothing():
    """Every model built with its default parameters, and with parameters given as Python
    numbers, NumPy values and nested lists: no XLA program is compiled (a conversion with
    ``jnp.asarray`` compiles one per shape and dtype, which every command would pay on its
    way to its first trace), and the parameters are the float64 values given."""
    global _COMPILES
    from lgvi_jax.models import CarPendulum, FreeRigidBody, HeavyTop

    J = [[0.3, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 0.7]]
    _COMPILES = []
    try:
        models = [CarPendulum(), HeavyTop(), FreeRigidBody(), HarmonicOscillator(),
                  CarPendulum(J=np.array(J, dtype=np.float32), m=2, M=np.float32(3.5),
                              g=9.81, rho_c=(0, 0, 1)),
                  HeavyTop(J=J, m=np.int64(2), g=np.float64(1.5)),
                  HarmonicOscillator(m=2, k=np.float16(0.5))]
        compiled = list(_COMPILES)
    finally:
        _COMPILES = None
    assert compiled == []
    car, top, osc = models[4], models[5], models[6]
    np.testing.assert_array_equal(np.asarray(car.J), np.asarray(J, dtype=np.float32))
    for value, expected in ((car.m, 2.0), (car.M, 3.5), (car.g, 9.81), (top.m, 2.0),
                            (top.g, 1.5), (osc.m, 2.0), (osc.k, 0.5)):
        assert isinstance(value, jax.Array) and value.dtype == jnp.float64
        assert float(value) == expected
    np.testing.assert_array_equal(np.asarray(car.rho_c), [0.0, 0.0, 1.0])
    assert car.J.dtype == jnp.float64 and car.rho_c.dtype == jnp.float64
