r"""The car-pendulum against an independent reference: its continuous equations of motion,
derived by hand below, written in plain NumPy and integrated by SciPy's DOP853 at
``rtol = atol = 1e-13``.

Notation: ``e3 = (0, 0, 1)`` points down (along gravity), ``P = [[1, 0, 0], [0, 1, 0]]``,
``R`` maps body to inertial coordinates, ``Ṙ = R ω̂``, ``q = (x, y)``, ``v = q̇``, ``ρ = ρ_c``,
and ``a = RᵀPᵀv`` is the cart velocity seen in the body frame. The Lagrangian is

    L = ½(m+M)|v|² + ½ωᵀJω + m vᵀPR(ω×ρ) + m g e3ᵀRρ.

Momenta. The coupling is ``m vᵀPR(ω×ρ) = m a·(ω×ρ) = m ω·(ρ×a)`` (cyclic triple product), so

    Π = ∂L/∂ω = Jω + m ρ×a = Jω + m ρ̂RᵀPᵀv,      p = ∂L/∂v = (m+M)v + m PR(ω×ρ).

Left-trivialised configuration derivative, ``τ·η = d/dε L(R e^{εη̂}, ω, q, v)|₀`` (the
tangent of ``R e^{εη̂}`` at 0 is ``Rη̂``):

* coupling: ``m vᵀPRη̂(ω×ρ) = m a·(η×(ω×ρ)) = m η·((ω×ρ)×a)``;
* gravity: ``m g e3ᵀRη̂ρ = m g (Rᵀe3)·(η×ρ) = m g η·(ρ×Rᵀe3)``;

so ``τ = m (ω×ρ)×a + m g ρ×(Rᵀe3)``. ``L`` does not depend on ``q`` (cart translations).

Equations of motion (Euler–Poincaré with configuration dependence, and Euler–Lagrange for
the cart):

    Ṙ = Rω̂,   Π̇ = Π×ω + τ,   q̇ = v,   ṗ = 0.

(For ``m = 0`` the first is Euler's ``Jω̇ = Jω×ω``: the sign of ``Π×ω`` is right.)
Accelerations: ``ȧ = (Rω̂)ᵀPᵀv + RᵀPᵀv̇ = −ω×a + RᵀPᵀv̇`` and
``d/dt PR(ω×ρ) = PR(ω×(ω×ρ)) + PR(ω̇×ρ)`` with ``ω̇×ρ = −ρ̂ω̇``. Hence ``(ω̇, v̇)`` solve the
5x5 linear system (3 rotational + 2 cart unknowns)

    J ω̇ + m ρ̂RᵀPᵀ v̇       = Π×ω + τ + m ρ×(ω×a),
    −m PRρ̂ ω̇ + (m+M) v̇   = −m PR(ω×(ω×ρ)),

whose matrix is symmetric (``ρ̂ᵀ = −ρ̂``) and positive definite (it is the kinetic-energy
Hessian). Energy: ``E = Π·ω + p·v − L = ½(m+M)|v|² + ½ωᵀJω + m vᵀPR(ω×ρ) − m g e3ᵀRρ``.
Conserved besides ``E`` and ``p``: the vertical angular momentum about the origin,
``e3·(RΠ) + x p_y − y p_x`` (rotations about the vertical through the origin).

This module is the independent reference of the tests, of the identification and
work-precision experiments. It uses only the model's parameters (as plain numbers) and the
initial configuration and velocities ``(R0, ω0, q0, v0)``; none of the library's mechanics
(autodiff momenta, velocities, vector field). The library enters only as the system under
test. :func:`paper_problem` and :func:`moving_problem` are the two test problems: a
:class:`ReferenceProblem` holds the model, its initial condition, the library's initial state
(``state0``) and the reference started from the same condition (``reference()``).

Needs SciPy (the ``dev`` and ``bench`` extras): imported when a solve is asked for.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["HandReference", "ReferenceProblem", "dop853_at", "moving_problem", "paper_problem"]

E3 = np.array([0.0, 0.0, 1.0])
P = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def hat(w):
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def dop853_at(rhs, y0, times, *, rtol: float = 1e-13, atol: float = 1e-13,
              who: str = "dop853_at") -> np.ndarray:
    """States of ``y' = rhs(t, y)``, ``y(0) = y0``, at the increasing ``times`` (the first
    may be 0), shape ``(len(times), len(y0))``: SciPy's DOP853 integrated piecewise from one
    time to the next, so every returned state is an accepted step (no dense-output
    interpolation). ``RuntimeError`` naming ``who`` if a piece fails."""
    from scipy.integrate import solve_ivp

    out = np.empty((len(times), np.size(y0)))
    y, t = np.array(y0, dtype=np.float64), 0.0
    for i, t_next in enumerate(times):
        if t_next > t:
            sol = solve_ivp(rhs, (t, t_next), y, method="DOP853", rtol=rtol, atol=atol)
            if not sol.success:
                raise RuntimeError(f"{who}: DOP853 failed: {sol.message}")
            y, t = sol.y[:, -1], t_next
        out[i] = y
    return out


class HandReference:
    """The hand-derived equations (module docstring) in NumPy; state vector
    ``y = (R (9, row-major), ω (3), q = (x, y) (2), v (2))``.

    ``model``: a :class:`~lgvi_jax.models.CarPendulum`, of which only the parameters ``m, M,
    g, rho_c, J`` are read. ``R0, omega0, q0, v0``: the initial configuration and velocities
    (the arguments of ``model.state``), each defaulting to the model's default initial
    condition (the paper's); the initial state is ``y0``."""

    def __init__(self, model, R0=None, omega0=None, q0=None, v0=None):
        self.m = float(model.m)
        self.M = float(model.M)
        self.g = float(model.g)
        self.rho = np.array(model.rho_c, dtype=np.float64)
        self.J = np.array(model.J, dtype=np.float64)
        cls = type(model)
        initial = {"R0": (R0, cls.DEFAULT_R0, (3, 3)), "omega0": (omega0, cls.DEFAULT_OMEGA0, (3,)),
                   "q0": (q0, cls.DEFAULT_Q0, (2,)), "v0": (v0, cls.DEFAULT_V0, (2,))}
        parts = []
        for name, (value, default, shape) in initial.items():
            arr = np.asarray(default if value is None else value, dtype=np.float64)
            if arr.shape != shape:
                raise ValueError(f"HandReference: {name} must have shape {shape}, got "
                                 f"{arr.shape}")
            parts.append(np.ravel(arr))
        self.y0 = np.concatenate(parts)

    @staticmethod
    def split(y):
        return y[:9].reshape(3, 3), y[9:12], y[12:14], y[14:16]

    def momenta(self, y):
        """``(Π, p)``."""
        R, w, _, v = self.split(y)
        a = R.T @ P.T @ v
        Pi = self.J @ w + self.m * np.cross(self.rho, a)
        p = (self.m + self.M) * v + self.m * P @ R @ np.cross(w, self.rho)
        return Pi, p

    def torque(self, y):
        """Left-trivialised ``∂L/∂R``: ``τ = m (ω×ρ)×a + m g ρ×(Rᵀe3)``."""
        R, w, _, v = self.split(y)
        a = R.T @ P.T @ v
        return (self.m * np.cross(np.cross(w, self.rho), a)
                + self.m * self.g * np.cross(self.rho, R.T @ E3))

    def energy(self, y):
        R, w, _, v = self.split(y)
        m, rho = self.m, self.rho
        return (0.5 * (m + self.M) * v @ v + 0.5 * w @ self.J @ w
                + m * v @ (P @ R @ np.cross(w, rho)) - m * self.g * E3 @ (R @ rho))

    def angular_momentum_z(self, y):
        R, _, q, _ = self.split(y)
        Pi, p = self.momenta(y)
        return (R @ Pi)[2] + q[0] * p[1] - q[1] * p[0]

    def mass_matrix(self, R):
        m, M, rho_hat = self.m, self.M, hat(self.rho)
        A = np.empty((5, 5))
        A[:3, :3] = self.J
        A[:3, 3:] = m * rho_hat @ R.T @ P.T
        A[3:, :3] = -m * P @ R @ rho_hat
        A[3:, 3:] = (m + M) * np.eye(2)
        return A

    def rhs(self, _t, y):
        R, w, _, v = self.split(y)
        m, rho = self.m, self.rho
        a = R.T @ P.T @ v
        Pi, _ = self.momenta(y)
        b = np.concatenate([
            np.cross(Pi, w) + self.torque(y) + m * np.cross(rho, np.cross(w, a)),
            -m * P @ R @ np.cross(w, np.cross(w, rho)),
        ])
        acc = np.linalg.solve(self.mass_matrix(R), b)
        return np.concatenate([(R @ hat(w)).ravel(), acc[:3], v, acc[3:]])

    def solve(self, t_final, *, rtol: float = 1e-13, atol: float = 1e-13):
        """The solver's own steps on ``[0, t_final]`` (times, states): no dense-output
        interpolation, whose error (~2e-12 here, measured) exceeds the step accuracy; the
        last state is an accepted step at exactly ``t_final``."""
        from scipy.integrate import solve_ivp

        sol = solve_ivp(self.rhs, (0.0, t_final), self.y0, method="DOP853",
                        rtol=rtol, atol=atol)
        if not sol.success or sol.t[-1] != t_final:
            raise RuntimeError(f"HandReference.solve: DOP853 failed: {sol.message}")
        return sol.t, sol.y.T

    def at(self, times: Sequence[float], *, rtol: float = 1e-13,
           atol: float = 1e-13) -> np.ndarray:
        """States at the given increasing times (the first may be 0), shape
        ``(len(times), 16)``. Integrated piecewise from one time to the next, so every
        returned state is an accepted step of DOP853 (no interpolation)."""
        times = np.asarray(times, dtype=np.float64)
        if times.ndim != 1 or times.size == 0 or times[0] < 0 or np.any(np.diff(times) <= 0):
            raise ValueError("HandReference.at: times must be a non-empty, increasing 1-D "
                             f"array starting at t >= 0, got {times!r}")
        return dop853_at(self.rhs, self.y0, times, rtol=rtol, atol=atol,
                         who="HandReference.at")

    def centre(self, y) -> np.ndarray:
        """Inertial position of the pendulum's mass centre, ``(x, y, 0) + R ρ_c``."""
        R, _, q, _ = self.split(np.asarray(y))
        return np.array([q[0], q[1], 0.0]) + R @ self.rho


@dataclasses.dataclass(frozen=True, eq=False)
class ReferenceProblem:
    """A car-pendulum problem: the model (its parameters) and the initial condition,
    attitude ``R0`` (3, 3), body angular velocity ``omega0`` (3,), cart position ``q0`` and
    velocity ``v0`` (2,), as float64 NumPy arrays."""

    model: Any
    R0: np.ndarray
    omega0: np.ndarray
    q0: np.ndarray
    v0: np.ndarray

    @property
    def initial_condition(self) -> dict[str, np.ndarray]:
        """``{"R0": ..., "omega0": ..., "q0": ..., "v0": ...}``: the keyword arguments of
        ``model.state`` and of :class:`HandReference`."""
        return {"R0": self.R0, "omega0": self.omega0, "q0": self.q0, "v0": self.v0}

    @functools.cached_property
    def state0(self):
        """The library's initial state, ``model.state(**initial_condition)``."""
        return self.model.state(**self.initial_condition)

    def reference(self) -> HandReference:
        """The independent reference from the same parameters and initial condition."""
        return HandReference(self.model, **self.initial_condition)


def _scene(model, **initial) -> ReferenceProblem:
    cls = type(model)
    defaults = {"R0": cls.DEFAULT_R0, "omega0": cls.DEFAULT_OMEGA0, "q0": cls.DEFAULT_Q0,
                "v0": cls.DEFAULT_V0}
    values = {k: np.asarray(initial.get(k, d), dtype=np.float64) for k, d in defaults.items()}
    return ReferenceProblem(model=model, **values)


def paper_problem() -> ReferenceProblem:
    """The paper's parameters and initial state (zero horizontal momentum)."""
    from ..models import CarPendulum

    return _scene(CarPendulum())


def moving_problem() -> ReferenceProblem:
    """The paper's parameters; non-zero horizontal momentum, a generic attitude, the cart
    away from the origin (so that ``x p_y − y p_x`` matters in the vertical angular
    momentum)."""
    import jax.numpy as jnp

    from .. import so3
    from ..models import CarPendulum

    return _scene(CarPendulum(), q0=(0.7, -0.4), v0=(0.8, -0.3), omega0=(1.0, -0.5, 3.0),
                  R0=so3.exp(jnp.array([0.6, -0.9, 0.4])))

