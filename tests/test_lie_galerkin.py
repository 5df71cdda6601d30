"""The Lie-group Galerkin variational integrators ``galerkin4`` / ``galerkin6`` /
``galerkin8`` (:class:`~lgvi_jax.integrators.lie_galerkin.LieGalerkinVI`): orders 4 and 6
against the independent car-pendulum reference, order 8 on the heavy top against
``lgvi@8``, the momentum maps to round-off, symplecticity of the one-step map,
reversibility. (Their derivatives are those of the generic Newton solve, tested in
tests/test_newton.py and tests/test_lie.py.)

Every run of a method goes through one compiled ``final_state`` (step and step count are
run-time values) per model structure: compiling the Galerkin step is most of these tests'
time."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lgvi_jax as L
from lgvi_jax import so3
from lgvi_jax.diagnostics import observed_order
from lgvi_jax.integrators import RIGID_METHODS, LieGalerkinVI, resolve_method
from lgvi_jax.models import HeavyTop, RigidState
from lgvi_jax.systems.car_pendulum import HandReference, moving_problem

T_ORDER = 1.0
#: Steps per order: the errors stay above round-off and in the asymptotic range (the
#: order-6 errors at h = 0.025 are ~2e-9, far above the reference's 1e-13).
STEPS = {4: (0.1, 0.05, 0.025), 6: (0.1, 0.05, 0.025)}
NAMES = {4: "galerkin4", 6: "galerkin6"}


def _run(model, method, state0, h, n):
    state, code = L.final_state(model, method, state0, h, n)
    assert int(code) == 0, f"{method.name} failed with code {int(code)} at h = {h}"
    return state


def _lz_and_p(model, s):
    inv = model.invariants(s)
    return float(inv["angular_momentum_z"]), np.asarray(s.p)


@pytest.fixture(scope="module")
def moving():
    spec = moving_problem()
    return spec.model, spec.state0, spec.reference()


def test_names_orders_and_traits():
    for order, name in NAMES.items():
        m = RIGID_METHODS[name]()
        assert m.name == name and m.order == order
        assert m.symmetric and m.symplectic and m.implicit
    assert resolve_method("galerkin8", RIGID_METHODS).order == 8
    for bad in (1, 0, 2.0, True):
        with pytest.raises(ValueError, match="degree"):
            LieGalerkinVI(degree=bad)
    with pytest.raises(ValueError, match="chord_matrix"):
        LieGalerkinVI(chord_matrix="mass")


@pytest.mark.parametrize("order", [4, 6])
def test_order_and_momentum_maps_against_the_reference(moving, order):
    """Log-log slope of the configuration error ``‖R − R_ref‖_F + ‖q − q_ref‖`` at T = 1
    against the hand-derived DOP853 reference: ``order ± 0.5`` (measured 3.97 and 5.9; from
    h = 0.2 the order-6 errors are pre-asymptotic).
    Along every run the cart momentum ``p`` and the vertical angular momentum ``L_z``
    (translation and rotation invariance) are conserved to round-off, whatever the step."""
    model, s0, ref = moving
    R_ref, _, q_ref, _ = HandReference.split(ref.at([T_ORDER])[-1])
    method = RIGID_METHODS[NAMES[order]]()
    lz0, p0 = _lz_and_p(model, s0)
    errors = []
    for h in STEPS[order]:
        s = _run(model, method, s0, h, round(T_ORDER / h))
        errors.append(float(np.linalg.norm(np.asarray(s.R) - R_ref)
                            + np.linalg.norm(np.asarray(s.q) - q_ref)))
        lz, p = _lz_and_p(model, s)
        # Newton's tolerance (~1e-12 relative on the step's momenta) and one ulp of |L_z|
        # ~ 5 per step, linearly over <= 20 steps: ~1e-11; measured <= 4e-14 (both orders).
        assert abs(lz - lz0) <= 1e-10 * max(1.0, abs(lz0)), (h, lz, lz0)
        np.testing.assert_allclose(p, p0, rtol=0, atol=1e-12)
        assert float(so3.orthogonality_error(s.R)) <= 1e-12
    assert min(errors) > 1e-11, errors  # above the reference's round-off
    slope = observed_order(STEPS[order], errors)
    assert abs(slope - order) <= 0.5, (slope, errors)


def test_reversibility(moving):
    """N steps with h, then N with −h, return to the start: the midpoint chart makes the
    discrete Lagrangian symmetric (module docstring)."""
    model, s0, _ = moving
    method = RIGID_METHODS["galerkin4"]()
    end = _run(model, method, s0, 0.05, 40)
    back = _run(model, method, end, -0.05, 40)
    for a, b in zip(jax.tree.leaves(back), jax.tree.leaves(s0), strict=True):
        # 80 solves exact to ~1e-12 relative (the Newton tolerance) on O(1)-O(10) values:
        # <= 1e-9 linearly; measured 2.8e-13.
        np.testing.assert_allclose(a, b, atol=1e-9, rtol=0)


def test_symplecticity_of_the_one_step_map():
    """The one-step map of the heavy top (``galerkin8``, h = 0.1, a generic state) in
    canonical coordinates ``(θ = log(R_refᵀR), p_θ = dexp(θ)ᵀμ)`` has a Jacobian ``M`` with
    ``Mᵀ Ω M = Ω``. ``M`` by central differences of the compiled rollout (one step; the
    program the other heavy-top tests use): truncation ~eps² times third derivatives ~1e-9
    and the Newton tolerance ~1e-12 / eps ~ 1e-7 per entry of an O(1) matrix, so a defect
    ≤ 1e-5; measured 1.7e-10 (``galerkin4`` 4.4e-11, ``lgvi`` 7.5e-11), while the paper's
    non-symplectic ``hamel`` gives 4e-2 with the same differences."""
    model = HeavyTop()
    s0 = model.state(R0=so3.exp(jnp.array([0.5, -0.3, 0.2])), omega0=(0.9, -0.6, 2.5))
    method = RIGID_METHODS["galerkin8"]()

    def to_x(s):
        th = so3.log(s0.R.T @ s.R)
        return np.concatenate([np.asarray(th), np.asarray(so3.dexp(th).T @ s.mu)])

    def to_state(x):
        th = jnp.asarray(x[:3])
        mu = jnp.linalg.solve(so3.dexp(th).T, jnp.asarray(x[3:]))
        return RigidState(R=s0.R @ so3.exp(th), mu=mu, q=s0.q, p=s0.p)

    def one_step(x):
        return to_x(_run(model, method, to_state(x), 0.1, 1))

    x0, eps = to_x(s0), 1e-5
    M = np.stack([(one_step(x0 + eps * e) - one_step(x0 - eps * e)) / (2 * eps)
                  for e in np.eye(6)], axis=1)
    Om = np.block([[np.zeros((3, 3)), np.eye(3)], [-np.eye(3), np.zeros((3, 3))]])
    assert np.max(np.abs(M - np.eye(6))) > 1e-2  # the step really moves the state
    assert np.max(np.abs(M.T @ Om @ M - Om)) <= 1e-5


def test_free_body_and_heavy_top_momentum_maps():
    """Free body (the top with g = 0): the spatial angular momentum ``Rμ``; heavy top: its
    vertical component. Conserved to round-off over 400 steps (discrete Noether theorem:
    the chart moves with the midpoint rotation, so ``L_d`` is left-invariant). With
    ``galerkin8``, whose compiled heavy-top rollout the order-8 test shares (``galerkin4``
    keeps the car-pendulum's momentum maps in the order test)."""
    method = RIGID_METHODS["galerkin8"]()
    J = np.array([[2.0, 0.3, -0.2], [0.3, 3.0, 0.4], [-0.2, 0.4, 3.5]])
    body = HeavyTop(J=J, g=0.0)
    s0 = body.state(R0=so3.exp(jnp.array([0.4, 0.1, -0.8])), omega0=(0.7, -1.1, 2.0))
    s = _run(body, method, s0, 0.05, 400)
    pi0, pi = (np.asarray(x.R @ x.mu) for x in (s0, s))
    # one ulp per step of |π| ~ 7, linearly over 400 steps, plus the Newton tolerance:
    # ~1e-12; measured 1e-13.
    assert np.max(np.abs(pi - pi0)) <= 1e-11 * np.linalg.norm(pi0)
    top = HeavyTop()
    t0 = top.default_state()
    t1 = _run(top, method, t0, 0.02, 400)
    lz0, lz1 = (float(top.invariants(x)["angular_momentum_z"]) for x in (t0, t1))
    assert abs(lz1 - lz0) <= 1e-11
    assert abs(float(t1.R[2, 2]) - float(t0.R[2, 2])) > 1e-3  # the top really moves


def test_order_eight_on_the_heavy_top():
    """``galerkin8`` (degree 4) on the heavy top over 2 s: log-log slope of the error in
    ``(R, μ)`` against ``lgvi@8`` at h = 2.5e-3 (an independent construction: composed
    second-order steps; its own error below 4e-14, its distance to h = 5e-3) is 8 ± 0.7
    (measured 8.2 over h = 0.2, 0.1, 0.05; the errors 4e-6 … 4e-11 stay far above the
    reference's), and the vertical angular momentum is kept to round-off."""
    top = HeavyTop()
    t0 = top.default_state()
    T = 2.0
    ref = _run(top, resolve_method("lgvi@8", RIGID_METHODS), t0, T / 800, 800)
    method = RIGID_METHODS["galerkin8"]()
    assert method.order == 8 and method.name == "galerkin8"
    lz0 = float(top.invariants(t0)["angular_momentum_z"])
    steps, errors = (0.2, 0.1, 0.05), []
    for h in steps:
        s = _run(top, method, t0, h, round(T / h))
        errors.append(float(np.max(np.abs(np.asarray(s.R - ref.R)))
                            + np.max(np.abs(np.asarray(s.mu - ref.mu)))))
        # as test_free_body_and_heavy_top_momentum_maps: <= 40 steps, ~1e-12
        assert abs(float(top.invariants(s)["angular_momentum_z"]) - lz0) <= 1e-11
    assert min(errors) > 1e-12, errors
    slope = observed_order(steps, errors)
    assert abs(slope - 8) <= 0.7, (slope, errors)
