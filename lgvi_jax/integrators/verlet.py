"""The Störmer–Verlet method (velocity Verlet), kick–drift–kick form."""

from __future__ import annotations

from typing import ClassVar

import jax

from ..models.base import PhaseState
from .base import AbstractIntegrator, StepInfo


class StormerVerlet(AbstractIntegrator):
    r"""Störmer–Verlet for separable Lagrangians :math:`L = T(v) - U(q)`:

    .. math::
        p_{1/2} = p_0 - \tfrac h2 \nabla U(q_0), \quad q_1 = q_0 + h\, v(p_{1/2}), \quad
        p_1 = p_{1/2} - \tfrac h2 \nabla U(q_1).

    It is the variational integrator of :math:`L_d(q_0, q_1) = h\,T\big((q_1-q_0)/h\big)
    - \tfrac h2 \big(U(q_0) + U(q_1)\big)`: order 2, explicit, symmetric, symplectic
    (Hairer, Lubich, Wanner, *Geometric Numerical Integration*, 2006, §I.3, §VI.6).
    Linear stability on the harmonic oscillator: :math:`h\omega < 2`.
    """

    name: ClassVar[str] = "verlet"
    order: ClassVar[int] = 2
    symmetric: ClassVar[bool] = True
    symplectic: ClassVar[bool] = True
    implicit: ClassVar[bool] = False

    def check_model(self, model):
        if not getattr(model, "separable", False):
            raise ValueError(
                f"method: verlet needs a separable model (kinetic energy independent of q); "
                f"{type(model).__name__} is not. Use gl4 or galerkin4."
            )

    def step(self, model, state, dt):
        grad_u = jax.grad(model.potential)
        p_half = state.p - 0.5 * dt * grad_u(state.q)
        q1 = state.q + dt * model.velocity(state.q, p_half)
        p1 = p_half - 0.5 * dt * grad_u(q1)
        return PhaseState(q=q1, p=p1), StepInfo.explicit()
