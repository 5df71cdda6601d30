r"""An explicit Lie-group Runge–Kutta method: Runge–Kutta–Munthe-Kaas of order 4 (``rkmk4``).

The continuous equations of a model on :math:`SO(3) \times \mathbb{R}^n`
(:mod:`lgvi_jax.models.rigid`) are

.. math::  \dot R = R\,\hat\omega, \qquad \dot z = g(R, z), \quad z = (\mu, q, p),

with :math:`\omega = \omega(R, z)` from the inverse Legendre map. Write the attitude near
the step's start as :math:`R(t) = R_0\exp(u(t))`. Since :math:`\frac{d}{dt}\exp(u) =
\exp(u)\,\widehat{J_r(u)\dot u}` (:func:`~lgvi_jax.so3.dexp`),

.. math::  \dot u = J_r(u)^{-1}\,\omega\big(R_0\exp(u), z\big), \qquad u(0) = 0,

an ODE on the vector space :math:`\mathbb{R}^3 \cong \mathfrak{so}(3)`. RKMK4 applies the
classical RK4 to :math:`(u, z)` and maps back (Munthe-Kaas 1998; Iserles, Munthe-Kaas,
Nørsett, Zanna 2000, §5; HLW §IV.8.2):

.. math::
    k_1 &= \omega(Y_1), & Y_1 &= (R_0, z_0), \\
    k_2 &= J_r(\tfrac h2 k_1)^{-1}\omega(Y_2), & Y_2 &= (R_0 e^{h k_1/2},
        z_0 + \tfrac h2 g_1), \\
    k_3 &= J_r(\tfrac h2 k_2)^{-1}\omega(Y_3), & Y_3 &= (R_0 e^{h k_2/2},
        z_0 + \tfrac h2 g_2), \\
    k_4 &= J_r(h k_3)^{-1}\omega(Y_4), & Y_4 &= (R_0 e^{h k_3}, z_0 + h g_3), \\
    R_1 &= R_0\exp\big(\tfrac h6(k_1 + 2k_2 + 2k_3 + k_4)\big), &
    z_1 &= z_0 + \tfrac h6(g_1 + 2g_2 + 2g_3 + g_4),

with :math:`g_i = g(Y_i)` and the exact :math:`J_r^{-1}` (:func:`~lgvi_jax.so3.dexp_inv`).
Every stage attitude is a product of rotations, so :math:`R` stays on SO(3) to round-off
(:math:`\|R^\top R - I\|_F` grows like a random walk of ~1e-16 per step), unlike RK4 on the
embedded 9-number equations, which leaves SO(3) by :math:`O(h^4)` per unit time. Order 4,
explicit, four evaluations of the vector field per step; neither symmetric nor symplectic,
and it conserves momentum maps only to :math:`O(h^4)`: the cheap on-group contrast to the
variational integrators.

References: H. Munthe-Kaas, *Runge–Kutta methods on Lie groups*, BIT 38 (1998) 92–111;
A. Iserles, H. Z. Munthe-Kaas, S. P. Nørsett, A. Zanna, *Lie-group methods*, Acta Numerica 9
(2000) 215–365; E. Hairer, C. Lubich, G. Wanner, *Geometric Numerical Integration*, 2nd ed.
(2006), §IV.8.
"""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp

from .. import so3
from ..models.rigid import AbstractRigidBodyModel, RigidState
from .base import AbstractIntegrator, StepInfo

__all__ = ["RKMK4"]


def _field(model, R, z):
    """``(ω, ż)`` at ``(R, z)``: the body angular velocity and the field of
    ``z = (μ, q, p)``, from the model's ``vector_field`` (whose ``R``-part is ``R ω̂``)."""
    mu, q, p = z
    f = model.vector_field(RigidState(R=R, mu=mu, q=q, p=p))
    return so3.vee(R.T @ f.R), (f.mu, f.q, f.p)


def _axpy(a, x, y):
    return jax.tree.map(lambda xi, yi: yi + a * xi, x, y)


class RKMK4(AbstractIntegrator):
    """The Runge–Kutta–Munthe-Kaas method of order 4 on :math:`SO(3) \\times
    \\mathbb{R}^n` (``rkmk4``; module docstring). Order 4, explicit, not symmetric, not
    symplectic; ``R`` on SO(3) to round-off."""

    name: ClassVar[str] = "rkmk4"
    order: ClassVar[int] = 4
    symmetric: ClassVar[bool] = False
    symplectic: ClassVar[bool] = False
    implicit: ClassVar[bool] = False

    def check_model(self, model) -> None:
        if not isinstance(model, AbstractRigidBodyModel):
            raise ValueError(
                f"{self.name}: needs a model on SO(3) x R^n (AbstractRigidBodyModel), got "
                f"{type(model).__name__}; Euclidean models use rk4, gl4, verlet, galerkin4"
            )

    def step(self, model, state: RigidState, dt):
        R0 = state.R
        h = jnp.asarray(dt, R0.dtype)
        z0 = (state.mu, state.q, state.p)

        w1, g1 = _field(model, R0, z0)
        k1 = w1
        u2 = 0.5 * h * k1
        w2, g2 = _field(model, R0 @ so3.exp(u2), _axpy(0.5 * h, g1, z0))
        k2 = so3.dexp_inv(u2) @ w2
        u3 = 0.5 * h * k2
        w3, g3 = _field(model, R0 @ so3.exp(u3), _axpy(0.5 * h, g2, z0))
        k3 = so3.dexp_inv(u3) @ w3
        u4 = h * k3
        w4, g4 = _field(model, R0 @ so3.exp(u4), _axpy(h, g3, z0))
        k4 = so3.dexp_inv(u4) @ w4

        u = (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        incr = jax.tree.map(lambda a, b, c, d: (a + 2.0 * b + 2.0 * c + d) / 6.0,
                            g1, g2, g3, g4)
        mu1, q1, p1 = _axpy(h, incr, z0)
        return RigidState(R=R0 @ so3.exp(u), mu=mu1, q=q1, p=p1), StepInfo.explicit()
