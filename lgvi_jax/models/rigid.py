r"""Models on :math:`SO(3) \times \mathbb{R}^n`: a rigid body, possibly coupled to ``n``
Euclidean coordinates (a cart, ...).

A model is an ``eqx.Module`` whose fields are its physical parameters (the initial state
belongs to the problem: ``model.state(R0=..., omega0=..., ...)`` builds it from an initial
configuration and velocities, ``model.default_state()`` is ``model.state()``). It defines only

* ``kinetic(R, Omega, q, v)``: the kinetic energy, with ``Omega`` a 3x3 **matrix** body
  velocity. Write rotational terms in matrix form, ``½ tr(Ω J_d Ωᵀ)`` with
  ``J_d = ½ tr(J) I − J``, and couplings through ``R Ω``. For a skew ``Ω = hat(ω)`` this is
  the usual ``½ ωᵀJω``; for the group difference ``Ω = (F − I)/h`` it is exactly the kinetic
  part of the general Lie group variational integrator (``lgvi``), so one formula serves
  every method;
* ``potential(R, q)``;
* ``state(...)``, the initial state from initial configuration and velocities
  (through :meth:`AbstractRigidBodyModel.state_from_velocities`), and its
  invariants (energy and momentum maps).

Everything else is derived here by autodiff. With the body angular velocity ``ω``
(``Ṙ = R hat(ω)``) and ``L(R, ω, q, v) = T(R, hat(ω), q, v) − U(R, q)``:

.. math::
    \mu = \partial L/\partial\omega, \qquad p = \partial L/\partial v, \qquad
    H = \mu\cdot\omega + p\cdot v - L,

and the equations of motion (Euler–Poincaré/Hamel with configuration dependence)

.. math::
    \dot R = R\,\hat\omega, \quad \dot\mu = \mu\times\omega + \mathrm{d}_R L, \quad
    \dot q = v, \quad \dot p = \partial L/\partial q,

where :math:`\mathrm{d}_R L\cdot\eta = \tfrac{d}{d\varepsilon} L(R e^{\varepsilon\hat\eta},
\omega, q, v)|_0` is the left-trivialised derivative. The state is
``RigidState(R, mu, q, p)``: the configuration and the (left-trivialised) momenta, the
natural variables of the discrete Legendre transforms. Kinetic energy must be quadratic in
``(ω, v)``, so the Legendre map is inverted exactly by one linear solve.

Reference: Holm, Schmah, Stoica, *Geometric Mechanics and Symmetry* (2009), ch. 7;
Lee, Leok, McClamroch, *Global Formulations of Lagrangian and Hamiltonian Dynamics on
Manifolds* (2018), ch. 6.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import so3
from .._checks import check_float64_finite, is_concrete, symmetric_3x3
from ..linalg import spd_solve

__all__ = ["AbstractRigidBodyModel", "RigidState", "check_inertia", "left_gradient"]


class RigidState(eqx.Module):
    """A point of :math:`T^*(SO(3) \\times \\mathbb{R}^n)`, left-trivialised.

    Attributes:
        R: rotation, body to inertial frame, ``(3, 3)``.
        mu: body angular momentum ``∂L/∂ω``, ``(3,)``.
        q: Euclidean coordinates, ``(n,)`` (``n = 0`` for a body alone).
        p: their momenta ``∂L/∂v``, ``(n,)``.

    Trajectories stack states along a leading axis.
    """

    R: jax.Array
    mu: jax.Array
    q: jax.Array
    p: jax.Array


def left_gradient(f, R: jax.Array) -> jax.Array:
    r"""Left-trivialised gradient of a scalar function of a rotation:
    :math:`g\cdot\eta = \tfrac{d}{d\varepsilon} f(R e^{\varepsilon\hat\eta})|_0`.

    Evaluated as the gradient of :math:`\eta \mapsto f(R(I + \hat\eta))` at 0: the curve
    :math:`R(I + \varepsilon\hat\eta)` has the same tangent :math:`R\hat\eta` as
    :math:`R e^{\varepsilon\hat\eta}`, so for ``f`` smooth on 3x3 matrices the first
    derivatives agree exactly, at the cost of one matrix product.
    """
    eye = jnp.eye(3, dtype=R.dtype)
    return jax.grad(lambda eta: f(R @ (eye + so3.hat(eta))))(jnp.zeros(3, R.dtype))


def check_inertia(name: str, J, owner: str, *, strict: bool = True) -> None:
    """Refuse a matrix that is not a physical inertia tensor: it must be 3x3, finite,
    symmetric, positive definite, and its principal moments must satisfy the triangle
    inequality ``λ_i <= λ_j + λ_k`` (equivalently ``J_d = ½tr(J)I − J`` is positive
    semi-definite: the mass distribution has non-negative second moments). Concrete values
    only (skipped under tracing)."""
    if not is_concrete(J):
        return
    arr, scale = symmetric_3x3(name, J, owner)
    lam = np.linalg.eigvalsh(arr)
    if lam[0] <= 0:
        raise ValueError(
            f"{owner}: {name} is not a physical inertia: it must be positive definite, "
            f"its principal moments are {lam.tolist()}"
        )
    if strict and lam[2] > lam[0] + lam[1] + 1e-12 * scale:
        raise ValueError(
            f"{owner}: {name} is not a physical inertia: its principal moments "
            f"{lam.tolist()} violate the triangle inequality (largest <= sum of the others)"
        )


class AbstractRigidBodyModel(eqx.Module):
    """A Lagrangian system on :math:`SO(3) \\times \\mathbb{R}^n` defined by its energies.

    Subclasses set ``dof`` (``n``) and implement :meth:`kinetic`, :meth:`potential`,
    :meth:`state` and, usually, :meth:`invariants` (extending the energy with the
    model's momentum maps). The fields are the physical parameters only: the initial
    condition is an argument of :meth:`state`, not part of the model.
    """

    dof: ClassVar[int]

    @abc.abstractmethod
    def kinetic(self, R: jax.Array, Omega: jax.Array, q: jax.Array, v: jax.Array) -> jax.Array:
        """Kinetic energy ``T(R, Ω, q, v)``, ``Ω`` a 3x3 matrix body velocity (quadratic in
        ``(Ω, v)``)."""

    @abc.abstractmethod
    def potential(self, R: jax.Array, q: jax.Array) -> jax.Array:
        """Potential energy ``U(R, q)``."""

    @abc.abstractmethod
    def state(self, *args, **kwargs) -> RigidState:
        """The initial state from the initial configuration and velocities (each defaulting
        to the model's default initial condition), validated on concrete values; usable under
        ``jit``/``vmap``/``grad``."""

    def default_state(self) -> RigidState:
        """Convenience: ``self.state()``, the model's default initial condition (the
        paper's, where there is one)."""
        return self.state()

    # --- mechanics derived by autodiff -------------------------------------------------

    def lagrangian(self, R, omega, q, v) -> jax.Array:
        """``L(R, ω, q, v) = T(R, hat(ω), q, v) − U(R, q)``."""
        return self.kinetic(R, so3.hat(omega), q, v) - self.potential(R, q)

    def momenta(self, R, omega, q, v) -> tuple[jax.Array, jax.Array]:
        """Legendre transform ``(μ, p) = (∂L/∂ω, ∂L/∂v)``."""
        return jax.grad(self.lagrangian, argnums=(1, 3))(R, omega, q, v)

    def mass_matrix(self, R, q) -> tuple[jax.Array, jax.Array]:
        """The Legendre map as an affine map of the flat velocities ``x = (ω, v)``:
        ``(μ, p) = M x + c``; returns ``(M, c)``, ``M`` the kinetic-energy Hessian (symmetric
        positive definite), by autodiff."""
        n = jnp.shape(q)[-1]

        def flat_momenta(x):
            return jnp.concatenate(self.momenta(R, x[:3], q, x[3:]))

        zero = jnp.zeros(3 + n, dtype=jnp.result_type(R))
        return jax.jacfwd(flat_momenta)(zero), flat_momenta(zero)

    def velocities(self, R, mu, q, p) -> tuple[jax.Array, jax.Array]:
        """Inverse Legendre transform ``(ω, v)`` (exact: the momenta are affine in the
        velocities, so one linear solve with the mass matrix from autodiff)."""
        mass, at_rest = self.mass_matrix(R, q)
        # Symmetric positive definite: the pivot-free elimination (no gathers).
        x = spd_solve(mass, jnp.concatenate([mu, p]) - at_rest)
        return x[:3], x[3:]

    def state_from_velocities(self, R, omega, q, v) -> RigidState:
        """The state with configuration ``(R, q)`` and velocities ``(ω, v)``."""
        R, omega, q, v = (jnp.asarray(x, jnp.float64) for x in (R, omega, q, v))
        mu, p = _momenta(self, R, omega, q, v)
        return RigidState(R=R, mu=mu, q=q, p=p)

    def energy(self, state: RigidState) -> jax.Array:
        """Hamiltonian ``H = μ·ω + p·v − L`` at the state's velocities."""
        omega, v = self.velocities(state.R, state.mu, state.q, state.p)
        return (
            jnp.dot(state.mu, omega)
            + jnp.dot(state.p, v)
            - self.lagrangian(state.R, omega, state.q, v)
        )

    def vector_field(self, state: RigidState) -> RigidState:
        """The continuous equations of motion with ``R`` embedded as 9 numbers:
        ``(Ṙ, μ̇, q̇, ṗ) = (R hat(ω), μ × ω + d_R L, v, ∂L/∂q)``. Used by RK4 and other
        Euclidean methods (which do not keep ``R`` on SO(3))."""
        R, mu, q, p = state.R, state.mu, state.q, state.p
        omega, v = self.velocities(R, mu, q, p)
        torque = left_gradient(lambda S: self.lagrangian(S, omega, q, v), R)
        force = jax.grad(self.lagrangian, argnums=2)(R, omega, q, v)
        return RigidState(
            R=R @ so3.hat(omega), mu=jnp.cross(mu, omega) + torque, q=v, p=force
        )

    def spatial_angular_momentum(self, state: RigidState) -> jax.Array:
        """``R μ``: the body's angular momentum about the body-frame origin, in the
        inertial frame (the momentum map of rotations ``R -> Q R``)."""
        # elementwise, not a matrix product or a reduction: under vmap XLA CPU makes those
        # batched library calls
        return sum(state.R[..., :, j] * state.mu[..., None, j] for j in range(3))

    def invariants(self, state: RigidState) -> dict[str, jax.Array]:
        """Quantities conserved by the exact flow, by name (at least ``energy``)."""
        return {"energy": self.energy(state)}

    def check_state(self, state: RigidState, name: str = "state0") -> None:
        """Validate a concrete state: shapes, float64, finite, and ``R`` in SO(3)."""
        owner = type(self).__name__
        if not isinstance(state, RigidState):
            raise ValueError(f"{owner}: {name} must be a RigidState, got {type(state).__name__}")
        shapes = {"R": (3, 3), "mu": (3,), "q": (self.dof,), "p": (self.dof,)}
        for field, expected in shapes.items():
            shape = jnp.shape(getattr(state, field))
            if shape != expected:
                raise ValueError(f"{owner}: {name}.{field} must have shape {expected}, got {shape}")
        check_float64_finite(name, state, owner)
        if is_concrete(state.R) and not so3.is_rotation(state.R, atol=1e-9):
            err = float(so3.orthogonality_error(state.R))
            det = float(np.linalg.det(np.asarray(state.R)))
            raise ValueError(
                f"{owner}: {name}.R is not a rotation matrix (‖RᵀR − I‖_F = {err:.3e}, "
                f"det R = {det:.6g}); use lgvi_jax.so3.project_to_so3 to project it"
            )


@eqx.filter_jit
def _momenta(model, R, omega, q, v):
    """``model.momenta`` compiled as one program: called eagerly (a system's default state),
    its autodiff would run op by op, each op compiled on its own."""
    return model.momenta(R, omega, q, v)
