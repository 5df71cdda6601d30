r"""Rigid-body models: free rigid body, heavy top, and the paper's 3D car-pendulum.

Each defines only its energies (in the matrix form of :mod:`lgvi_jax.models.rigid`), its
``state(...)`` (the initial state from an initial attitude and velocities, defaulting to the
model's default initial condition: class constants, not fields) and its invariants. The
fields are the physical parameters only. Conventions: ``R`` maps body to inertial coordinates,
``ω`` is the body angular velocity, and ``e3 = (0, 0, 1)`` points **down**, along gravity
(as in the paper), so the potential of a mass centre at body point ``ρ_c`` is
``U = −m g e3ᵀ R ρ_c``.
"""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

from .. import so3
from .._checks import (
    as_float_array,
    check_finite,
    check_nonnegative,
    check_positive,
    is_concrete,
)
from ..linalg import spd_solve
from .base import reject_removed_keywords
from .rigid import AbstractRigidBodyModel, RigidState, check_inertia

__all__ = ["CarPendulum", "FreeRigidBody", "HeavyTop", "rotational_kinetic"]

E3 = (0.0, 0.0, 1.0)

#: The paper's pendulum (section 3): inertia about the pivot = 0.04 I about the mass
#: centre plus the parallel-axis term of m = 1 at rho_c = (0.25, 0.25, 1.0).
PAPER_J = ((1.1025, -0.0625, -0.25), (-0.0625, 1.1025, -0.25), (-0.25, -0.25, 0.165))
PAPER_RHO_C = (0.25, 0.25, 1.0)
PAPER_R0 = ((1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0))
PAPER_OMEGA0 = (0.1, 0.2, 5.0)


def rotational_kinetic(J: jax.Array, Omega: jax.Array) -> jax.Array:
    r"""``½ tr(Ω J_d Ωᵀ)`` with ``J_d = ½ tr(J) I − J``: equals ``½ ωᵀJω`` for
    ``Ω = hat(ω)``, and ``tr((I − F) J_d)/h²`` for ``Ω = (F − I)/h``, ``F`` in SO(3)
    (Lee, Leok, McClamroch 2007, the general LGVI's kinetic energy)."""
    Jd = 0.5 * jnp.trace(J) * jnp.eye(3, dtype=J.dtype) - J
    return 0.5 * jnp.sum((Omega @ Jd) * Omega)


def _check_rotation(name: str, R, owner: str) -> None:
    if jnp.shape(R) != (3, 3):
        raise ValueError(f"{owner}: {name} must be a 3x3 matrix (9 numbers), got shape "
                         f"{jnp.shape(R)}")
    if not is_concrete(R):
        return
    arr = np.asarray(R)
    if not so3.is_rotation(arr, atol=1e-9):
        err = float(so3.orthogonality_error(arr)) if np.all(np.isfinite(arr)) else float("nan")
        det = float(np.linalg.det(arr)) if np.all(np.isfinite(arr)) else float("nan")
        raise ValueError(
            f"{owner}: {name} is not in SO(3): ‖RᵀR − I‖_F = {err:.3e}, det = {det:.6g} "
            "(need an orthogonal matrix with determinant +1, to 1e-9)"
        )


def _check_shape(name: str, value, shape: tuple[int, ...], owner: str) -> None:
    if jnp.shape(value) != shape:
        raise ValueError(f"{owner}: {name} must have shape {shape}, got {jnp.shape(value)}")


def _initial_state(model: AbstractRigidBodyModel, owner: str, R0, omega0, q0=(), v0=()
                   ) -> RigidState:
    """``model.state_from_velocities(R0, omega0, q0, v0)`` after validating the arguments
    (shapes always, SO(3) and finiteness on concrete values), each error naming it."""
    R0 = as_float_array("R0", R0, owner)
    _check_rotation("R0", R0, owner)
    values = {"omega0": (omega0, (3,)), "q0": (q0, (model.dof,)), "v0": (v0, (model.dof,))}
    arrays = {}
    for name, (value, shape) in values.items():
        arr = as_float_array(name, value, owner)
        _check_shape(name, arr, shape, owner)
        check_finite(name, arr, owner)
        arrays[name] = arr
    return model.state_from_velocities(R0, arrays["omega0"], arrays["q0"], arrays["v0"])


def _gravity_potential(m, g, rho_c, R):
    return -m * g * jnp.dot(jnp.asarray(E3, R.dtype), R @ rho_c)


class FreeRigidBody(AbstractRigidBodyModel):
    r"""A free rigid body: :math:`L = \tfrac12\omega^\top J\omega`, no potential.

    Invariants: energy and the spatial angular momentum :math:`R J\omega` (3 numbers,
    conserved by rotational symmetry :math:`R \mapsto QR`). Default: ``J = diag(2, 3, 4)``
    and (:meth:`state`) ``R0 = I``, ``ω0 = (0.1, 1.0, 0.1)``: close to a steady spin about
    the intermediate axis, which is unstable (the tennis-racket flips).
    """

    J: jax.Array

    dof: ClassVar[int] = 0
    #: The default initial condition: identity attitude, near the intermediate axis.
    DEFAULT_R0: ClassVar[tuple] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    DEFAULT_OMEGA0: ClassVar[tuple] = (0.1, 1.0, 0.1)

    def __init__(self, J=((2.0, 0, 0), (0, 3.0, 0), (0, 0, 4.0)), **removed):
        owner = "FreeRigidBody"
        reject_removed_keywords(owner, removed, ("R0", "omega0"))
        self.J = as_float_array("J", J, owner)

    def __check_init__(self):
        check_inertia("J", self.J, "FreeRigidBody")

    def kinetic(self, R, Omega, q, v):
        return rotational_kinetic(self.J, Omega)

    def potential(self, R, q):
        return jnp.zeros((), R.dtype)

    def state(self, R0=DEFAULT_R0, omega0=DEFAULT_OMEGA0) -> RigidState:
        """The state with attitude ``R0`` (3x3, in SO(3)) and body angular velocity
        ``omega0`` (3,); defaults :attr:`DEFAULT_R0`, :attr:`DEFAULT_OMEGA0`. ``ValueError``
        naming the argument otherwise (SO(3) and finiteness checked on concrete values only:
        ``jit``, ``vmap`` and ``grad`` trace through)."""
        return _initial_state(self, "FreeRigidBody", R0, omega0)

    def invariants(self, state: RigidState) -> dict[str, jax.Array]:
        return {
            "energy": self.energy(state),
            "angular_momentum": self.spatial_angular_momentum(state),
        }


class HeavyTop(AbstractRigidBodyModel):
    r"""A heavy top, or 3D pendulum, about a fixed pivot:
    :math:`L = \tfrac12\omega^\top J\omega + m g\, e_3^\top R\rho_c` (``e3`` down).

    ``J`` is the inertia about the pivot and ``ρ_c`` the pivot-to-mass-centre vector in the
    body frame. Invariants: energy and the vertical angular momentum :math:`e_3^\top R J
    \omega` (symmetry: rotations about the vertical through the pivot). Defaults: the
    paper's pendulum without its cart, and (:meth:`state`) its initial attitude and
    angular velocity.
    """

    J: jax.Array
    m: jax.Array
    g: jax.Array
    rho_c: jax.Array

    dof: ClassVar[int] = 0
    #: The default initial condition: the paper's.
    DEFAULT_R0: ClassVar[tuple] = PAPER_R0
    DEFAULT_OMEGA0: ClassVar[tuple] = PAPER_OMEGA0

    def __init__(self, J=PAPER_J, m=1.0, g=9.81, rho_c=PAPER_RHO_C, **removed):
        owner = "HeavyTop"
        reject_removed_keywords(owner, removed, ("R0", "omega0"))
        self.J = as_float_array("J", J, owner)
        self.m = as_float_array("m", m, owner)
        self.g = as_float_array("g", g, owner)
        self.rho_c = as_float_array("rho_c", rho_c, owner)

    def __check_init__(self):
        owner = "HeavyTop"
        check_inertia("J", self.J, owner)
        check_positive("m", self.m, owner)
        check_nonnegative("g", self.g, owner)
        _check_shape("rho_c", self.rho_c, (3,), owner)
        check_finite("rho_c", self.rho_c, owner)

    def kinetic(self, R, Omega, q, v):
        return rotational_kinetic(self.J, Omega)

    def potential(self, R, q):
        return _gravity_potential(self.m, self.g, self.rho_c, R)

    def state(self, R0=DEFAULT_R0, omega0=DEFAULT_OMEGA0) -> RigidState:
        """The state with attitude ``R0`` (3x3, in SO(3)) and body angular velocity
        ``omega0`` (3,); defaults the paper's, :attr:`DEFAULT_R0`, :attr:`DEFAULT_OMEGA0`.
        ``ValueError`` naming the argument otherwise (SO(3) and finiteness checked on
        concrete values only: ``jit``, ``vmap`` and ``grad`` trace through)."""
        return _initial_state(self, "HeavyTop", R0, omega0)

    def invariants(self, state: RigidState) -> dict[str, jax.Array]:
        return {
            "energy": self.energy(state),
            "angular_momentum_z": self.spatial_angular_momentum(state)[..., 2],
        }


class CarPendulum(AbstractRigidBodyModel):
    r"""The paper's 3D car-pendulum (section 3): a rigid pendulum hinged on a cart that
    moves freely in the horizontal plane. Configuration ``(R, q)``, ``q = (x, y)`` the cart
    position; with ``v = q̇``, ``P = [e1 e2]ᵀ`` and ``e3`` down (eq. 38):

    .. math::
        L = \tfrac12 (m+M)|v|^2 + \tfrac12\omega^\top J\omega
            + m\, v^\top P R(\omega\times\rho_c) + m g\, e_3^\top R\rho_c,

    written for the engine as ``T = ½(m+M)|v|² + ½ tr(Ω J_d Ωᵀ) + m vᵀ P R Ω ρ_c``.
    Momenta (eq. 39): ``μ = Jω + m hat(ρ_c) Rᵀ Pᵀ v``, ``p = (m+M) v + m P R (ω × ρ_c)``.

    Invariants: energy; the cart's horizontal momentum ``p`` (translations of the cart);
    the vertical angular momentum about the origin, ``e3·(R μ) + x p_y − y p_x``
    (rotations about the vertical axis through the origin move the cart and the pendulum
    together). Defaults: the paper's parameters, ``g = 9.81``, and (:meth:`state`) its
    initial state.
    """

    m: jax.Array
    M: jax.Array
    g: jax.Array
    rho_c: jax.Array
    J: jax.Array

    dof: ClassVar[int] = 2
    #: The default initial condition: the paper's (zero horizontal momentum).
    DEFAULT_R0: ClassVar[tuple] = PAPER_R0
    DEFAULT_OMEGA0: ClassVar[tuple] = PAPER_OMEGA0
    DEFAULT_Q0: ClassVar[tuple] = (-0.125, -0.0125)
    DEFAULT_V0: ClassVar[tuple] = (0.525, -0.0125)

    def __init__(self, m=1.0, M=1.0, g=9.81, rho_c=PAPER_RHO_C, J=PAPER_J, **removed):
        owner = "CarPendulum"
        reject_removed_keywords(owner, removed, ("R0", "omega0", "q0", "v0"))
        self.m = as_float_array("m", m, owner)
        self.M = as_float_array("M", M, owner)
        self.g = as_float_array("g", g, owner)
        self.rho_c = as_float_array("rho_c", rho_c, owner)
        self.J = as_float_array("J", J, owner)

    def __check_init__(self):
        owner = "CarPendulum"
        check_positive("m", self.m, owner)
        check_positive("M", self.M, owner)
        check_nonnegative("g", self.g, owner)
        check_inertia("J", self.J, owner)
        _check_shape("rho_c", self.rho_c, (3,), owner)
        check_finite("rho_c", self.rho_c, owner)

    def kinetic(self, R, Omega, q, v):
        coupling = self.m * jnp.dot(v, (R @ (Omega @ self.rho_c))[:2])
        return 0.5 * (self.m + self.M) * jnp.dot(v, v) + rotational_kinetic(self.J, Omega) + (
            coupling
        )

    def potential(self, R, q):
        return _gravity_potential(self.m, self.g, self.rho_c, R)

    def state(self, R0=DEFAULT_R0, omega0=DEFAULT_OMEGA0, q0=DEFAULT_Q0, v0=DEFAULT_V0
              ) -> RigidState:
        """The state with pendulum attitude ``R0`` (3x3, in SO(3)), body angular velocity
        ``omega0`` (3,), cart position ``q0`` (2,) and velocity ``v0`` (2,); defaults the
        paper's, :attr:`DEFAULT_R0`, :attr:`DEFAULT_OMEGA0`, :attr:`DEFAULT_Q0`,
        :attr:`DEFAULT_V0`. ``ValueError`` naming the argument otherwise (SO(3) and
        finiteness checked on concrete values only: ``jit``, ``vmap`` and ``grad`` trace
        through)."""
        return _initial_state(self, "CarPendulum", R0, omega0, q0, v0)

    def velocities(self, R, mu, q, p) -> tuple[jax.Array, jax.Array]:
        r"""The inverse Legendre map in closed form (the base class's autodiff mass matrix
        and 5x5 solve give the same, tested). Eliminating ``v`` from ``p = (m+M) v +
        m P R (ω × ρ_c)`` leaves the 3x3 Schur complement

        .. math::
            \big(J - \tfrac{m^2}{m+M}\, \hat\rho_c \Pi \hat\rho_c^\top\big)\, \omega
            = \mu - \tfrac{m}{m+M}\, \rho_c \times (R^\top P^\top p), \qquad
            \Pi = R^\top P^\top P R = I - r_3 r_3^\top,

        ``r_3 = Rᵀe_3``, symmetric positive definite (solved without pivoting), then
        ``v = (p − m P R (ω × ρ_c)) / (m+M)``. Used by every energy evaluation of a sweep:
        faster batched and quicker to compile than the autodiff form."""
        # Written out elementwise, not with matrix products or reductions: under vmap XLA
        # CPU turns small ones into batched library calls.
        m, M, rho = self.m, self.M, self.rho_c
        total = m + M
        c = jnp.cross(rho, R[2])  # ρ̂ Π ρ̂ᵀ = ρ̂ ρ̂ᵀ − c cᵀ = |ρ|² I − ρρᵀ − c cᵀ
        rr = rho[0] * rho[0] + rho[1] * rho[1] + rho[2] * rho[2]
        schur = self.J - (m * m / total) * (
            rr * jnp.eye(3, dtype=R.dtype) - rho[:, None] * rho[None, :] - c[:, None] * c[None, :])
        a_p = R[0] * p[0] + R[1] * p[1]  # RᵀPᵀp
        omega = spd_solve(schur, mu - (m / total) * jnp.cross(rho, a_p))
        e = jnp.cross(omega, rho)
        v = (p - m * (R[:2, 0] * e[0] + R[:2, 1] * e[1] + R[:2, 2] * e[2])) / total
        return omega, v

    def energy(self, state: RigidState) -> jax.Array:
        """``H = T + U`` with ``T = ½(μ·ω + p·v)`` (the kinetic energy is quadratic in the
        velocities): the base class's ``μ·ω + p·v − L`` without evaluating ``L``."""
        omega, v = self.velocities(state.R, state.mu, state.q, state.p)
        mu, p, r3, rho = state.mu, state.p, state.R[2], self.rho_c
        return 0.5 * (mu[0] * omega[0] + mu[1] * omega[1] + mu[2] * omega[2] + p[0] * v[0]
                      + p[1] * v[1]) - self.m * self.g * (
            r3[0] * rho[0] + r3[1] * rho[1] + r3[2] * rho[2])

    def invariants(self, state: RigidState) -> dict[str, jax.Array]:
        x, y = state.q[..., 0], state.q[..., 1]
        px, py = state.p[..., 0], state.p[..., 1]
        return {
            "energy": self.energy(state),
            "momentum": state.p,
            "angular_momentum_z": self.spatial_angular_momentum(state)[..., 2] + x * py - y * px,
        }

    def pendulum_centre(self, state: RigidState) -> jax.Array:
        """Inertial position of the pendulum's mass centre, ``(x, y, 0) + R ρ_c``."""
        cart = jnp.concatenate([state.q, jnp.zeros_like(state.q[..., :1])], axis=-1)
        return cart + jnp.einsum("...ij,j->...i", state.R, self.rho_c)
