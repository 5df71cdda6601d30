"""The physically consistent inertia parametrisation (lgvi_jax.inertia): map, inverse,
physicality of every unconstrained vector, derivatives."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lgvi_jax import so3
from lgvi_jax.inertia import (
    centroidal_inertia,
    inertia_from_params,
    is_physical,
    parallel_axis,
    params_from_inertia,
    pivot_inertia,
    pseudo_inertia,
    second_moment,
)
from lgvi_jax.models.rigid import check_inertia
from lgvi_jax.models.rigid_bodies import PAPER_J, PAPER_RHO_C


def random_physical_inertia(rng):
    """A random strictly physical inertia: principal moments from positive second moments,
    in random principal axes (independent of the parametrisation under test)."""
    sigma = rng.uniform(0.01, 2.0, 3)
    moments = np.array([sigma[1] + sigma[2], sigma[0] + sigma[2], sigma[0] + sigma[1]])
    Q = np.asarray(so3.exp(jnp.asarray(rng.normal(size=3))))
    return Q @ np.diag(moments) @ Q.T


def test_every_unconstrained_vector_is_physical():
    rng = np.random.default_rng(0)
    # Wide range: log-diagonals in [-6, 6] (moments over ~10 decades), off-diagonals O(10).
    thetas = np.concatenate([rng.uniform(-6, 6, (500, 3)), rng.normal(0, 10, (500, 3))], 1)
    J = np.asarray(inertia_from_params(jnp.asarray(thetas)))  # batched
    for Jk in J:
        check_inertia("J", Jk, "test")  # raises if not symmetric, PD, triangle
        assert is_physical(Jk)
        lam = np.linalg.eigvalsh(Jk)
        # Mathematically strict (λ_j + λ_k − λ_i = 2σ_i > 0); in floating point, to the
        # round-off of the largest moment when σ_i is ~1e-10 of it.
        assert lam[0] > 0 and lam[2] <= lam[0] + lam[1] + 1e-13 * lam[2]


def test_round_trip_inertia_to_params_and_back():
    rng = np.random.default_rng(1)
    for _ in range(50):
        J = random_physical_inertia(rng)
        theta = params_from_inertia(J)
        assert theta.shape == (6,)
        np.testing.assert_allclose(inertia_from_params(theta), J, rtol=0, atol=1e-13 * 4)


def test_round_trip_params_to_inertia_and_back():
    # The Cholesky factor with positive diagonal is unique: theta -> J -> theta is identity.
    rng = np.random.default_rng(2)
    for _ in range(50):
        theta = np.concatenate([rng.uniform(-2, 2, 3), rng.normal(0, 1, 3)])
        back = params_from_inertia(inertia_from_params(jnp.asarray(theta)))
        np.testing.assert_allclose(back, theta, rtol=1e-9, atol=1e-9)


def test_second_moments_give_the_principal_moments():
    # J_c = tr(Σ)I − Σ: the moments of a diagonal Σ are the sums of the other two.
    theta = jnp.array([np.log(0.1), np.log(0.2), np.log(0.3), 0.0, 0.0, 0.0])
    np.testing.assert_allclose(second_moment(theta), np.diag([0.01, 0.04, 0.09]), atol=1e-15)
    np.testing.assert_allclose(inertia_from_params(theta), np.diag([0.13, 0.10, 0.05]),
                               atol=1e-15)


@pytest.mark.parametrize("bad, match", [
    (np.diag([1.0, 1.0, 2.0]), "strictly physical"),     # on the boundary: flat body
    (np.diag([1.0, 1.0, 3.0]), "strictly physical"),     # violates the triangle inequality
    (np.diag([1.0, -1.0, 1.0]), "strictly physical"),    # not positive definite
    (np.array([[1.0, 0.1, 0], [0, 1, 0], [0, 0, 1]]), "symmetric"),
    (np.eye(2), "3x3"),
    (np.diag([1.0, np.nan, 1.0]), "finite"),
])
def test_inverse_refuses_unphysical_inertia(bad, match):
    with pytest.raises(ValueError, match=match):
        params_from_inertia(bad)
    assert not is_physical(bad) or match == "strictly physical"


def test_parallel_axis_and_paper_inertia():
    # PAPER_J is 0.04 I about the mass centre plus the parallel-axis term of m = 1 at rho_c.
    np.testing.assert_allclose(centroidal_inertia(PAPER_J, 1.0, PAPER_RHO_C),
                               0.04 * np.eye(3), atol=1e-15)
    rng = np.random.default_rng(3)
    J_c, m, rho = random_physical_inertia(rng), 2.5, rng.normal(size=3)
    J = np.asarray(pivot_inertia(J_c, m, rho))
    np.testing.assert_allclose(centroidal_inertia(J, m, rho), J_c, atol=1e-13)
    # Steiner: the term is m times the inertia of a point at rho: m (|rho|^2 - (rho.n)^2).
    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    assert n @ np.asarray(parallel_axis(m, rho)) @ n == pytest.approx(
        m * (rho @ rho - (rho @ n) ** 2), rel=1e-12)


def test_pseudo_inertia_is_positive_definite_for_any_parameters():
    rng = np.random.default_rng(4)
    for _ in range(100):
        theta = np.concatenate([rng.uniform(-3, 3, 3), rng.normal(0, 2, 3)])
        m, rho = np.exp(rng.uniform(-3, 3)), rng.normal(0, 3, 3)
        P = np.asarray(pseudo_inertia(inertia_from_params(jnp.asarray(theta)), m, rho))
        np.testing.assert_array_equal(P, P.T)
        assert np.linalg.eigvalsh(P)[0] > 0
        # and the inertia about the pivot it describes is physical too
        assert is_physical(np.asarray(pivot_inertia(inertia_from_params(theta), m, rho)))
    # A mass centre inconsistent with a flat centroidal inertia breaks it (not PD).
    P = np.asarray(pseudo_inertia(np.diag([1.0, 1.0, 2.0]), 1.0, np.zeros(3)))
    assert np.linalg.eigvalsh(P)[0] <= 1e-15


def test_derivative_of_the_map_matches_central_differences():
    rng = np.random.default_rng(5)
    theta = jnp.asarray(np.concatenate([rng.uniform(-1, 1, 3), rng.normal(0, 1, 3)]))
    v = jnp.asarray(rng.normal(size=6))
    _, jvp = jax.jvp(inertia_from_params, (theta,), (v,))
    eps = 1e-5  # truncation O(eps^2) ~ 1e-10, cancellation ~ 1e-16/eps ~ 1e-11
    fd = (inertia_from_params(theta + eps * v) - inertia_from_params(theta - eps * v)) / (2 * eps)
    np.testing.assert_allclose(jvp, fd, rtol=1e-8, atol=1e-9)
