"""The classical fourth-order Runge–Kutta method (Kutta 1901)."""

from __future__ import annotations

from typing import ClassVar

import jax

from .base import AbstractIntegrator, StepInfo


def _axpy(a, x, y):
    return jax.tree.map(lambda xi, yi: yi + a * xi, x, y)


class RK4(AbstractIntegrator):
    r"""Classical RK4 on the model's vector field :math:`\dot y = f(y)`:

    .. math::
        k_1 = f(y_0),\ k_2 = f(y_0 + \tfrac h2 k_1),\ k_3 = f(y_0 + \tfrac h2 k_2),\
        k_4 = f(y_0 + h k_3),\quad y_1 = y_0 + \tfrac h6 (k_1 + 2k_2 + 2k_3 + k_4).

    Order 4, explicit, neither symmetric nor symplectic: on :math:`\dot y = i\omega y` it
    multiplies by :math:`R(i\omega h)`, :math:`|R(iy)|^2 = 1 - y^6/72 + y^8/576`, so the
    energy of a harmonic oscillator decays geometrically (stable for :math:`|y| \le 2\sqrt2`).
    Works on any model with ``vector_field(state)`` returning a state-shaped pytree.
    """

    name: ClassVar[str] = "rk4"
    order: ClassVar[int] = 4
    symmetric: ClassVar[bool] = False
    symplectic: ClassVar[bool] = False
    implicit: ClassVar[bool] = False

    def step(self, model, state, dt):
        f = model.vector_field
        k1 = f(state)
        k2 = f(_axpy(dt / 2, k1, state))
        k3 = f(_axpy(dt / 2, k2, state))
        k4 = f(_axpy(dt, k3, state))
        incr = jax.tree.map(lambda a, b, c, d: (a + 2 * b + 2 * c + d) / 6, k1, k2, k3, k4)
        return _axpy(dt, incr, state), StepInfo.explicit()
