r"""Lie-group Galerkin variational integrators of order 2s on :math:`SO(3) \times
\mathbb{R}^n`, built from a model's energies by autodiff (``galerkin4``, ``galerkin6``,
``galerkin8``).

**Contract.** :class:`LieGalerkinVI` (``degree=s``) is an exactly variational one-step
method of order :math:`2s`: symplectic, symmetric, and it conserves every momentum map of a
left-invariant (or translation-invariant) Lagrangian to round-off (discrete Noether). Like
the second-order Lie-group VIs it takes only the model's ``kinetic`` and ``potential``; it
runs on the same engine (:class:`~lgvi_jax.integrators.lie.AbstractLieVI`: Newton by
autodiff warm-started from the previous steps, implicit-function derivatives), on small
arrays: :func:`~lgvi_jax.integrators.with_scalar_newton` leaves it as it is (its scalar
program, the second derivatives at :math:`s + 1` quadrature points, takes minutes to
compile).

**Discrete Lagrangian.** On one step the rotation is a curve in exponential coordinates
about the midpoint rotation :math:`R_m = R_k \exp(w/2)`, :math:`w = \log(R_k^\top R_{k+1})`:

.. math::
    R(t_k + \tau h) = R_m \exp\zeta(\tau), \qquad
    \zeta(\tau) = -\tfrac{w}{2} + h \sum_{j=1}^{s} \ell_j(\tau)\, Z_j,

with :math:`\ell_j` the Lagrange polynomials of degree :math:`s` on the Gauss–Lobatto
points :math:`0 = d_0 < \dots < d_s = 1`, :math:`Z_s = w/h` (so :math:`\zeta(1) = w/2`:
the curve ends at :math:`R_{k+1}`) and the inner :math:`Z_1, \dots, Z_{s-1}` free. The body
velocity is :math:`\Omega = J_r(\zeta)\,\dot\zeta` (:func:`~lgvi_jax.so3.dexp`,
:math:`\dot\zeta = \sum_j \ell_j'(\tau) Z_j`). The positions are the Euclidean Galerkin
curve :math:`q = q_k + h\sum_{j\ge1}\ell_j(\tau) W_j`, :math:`W_s = (q_{k+1} - q_k)/h`.
The action is evaluated with the :math:`(s+1)`-point Gauss–Legendre rule
:math:`(c_i, b_i)` and extremised over the inner nodes:

.. math::
    L_d(R_k, q_k, R_{k+1}, q_{k+1}) = \operatorname{ext}_{Z_{<s}, W_{<s}}\;
    h \sum_i b_i\, L\big(R(c_i), \Omega(c_i), q(c_i), \dot q(c_i)\big).

One step solves, for the unknowns :math:`(\xi = w/h, u = W_s, Z_{<s}, W_{<s})`, the
discrete Legendre transforms at :math:`k` (:math:`\mu_k = B^\top g_w - g_k`,
:math:`p_k = -\partial G/\partial q_k`, as in :mod:`~lgvi_jax.integrators.lie`, with the
exact variations :math:`A = J_r(w)^{-1}`, :math:`B = J_l(w)^{-1}` of ``hamel-exact``)
together with the stationarity of the inner nodes (:math:`\partial G/\partial Z_j = 0`,
:math:`\partial G/\partial W_j = 0`), by Newton's method; then
:math:`\mu_{k+1} = A^\top g_w` and :math:`p_{k+1} = \partial G/\partial q_{k+1}`
explicitly. By the envelope theorem the inner nodes, held fixed, do not change the
Legendre transforms of the extremised :math:`L_d`.

**Properties.** :math:`L_d` is a function on :math:`(SO(3)\times\mathbb{R}^n)^2`, so the
map is symplectic; :math:`L_d(QR_k, QR_{k+1}) = L_d(R_k, R_{k+1})` whenever :math:`L` is
invariant under :math:`R \mapsto QR` (the chart moves with :math:`R_m`), so the spatial
momentum maps are conserved exactly. The midpoint chart makes the method symmetric:
stepping back from :math:`R_{k+1}` with :math:`-h` gives :math:`w \to -w`, the same
:math:`R_m` and the reversed curve, :math:`L_d(R_{k+1}, R_k; -h) = -L_d(R_k, R_{k+1}; h)`
(a chart at :math:`R_k` would not be). The Galerkin curve in a smooth chart approximates the
exact one to :math:`O(h^{s+1})` and the quadrature is exact to degree :math:`2s+1`, so
:math:`L_d` approximates the exact discrete Lagrangian to :math:`O(h^{2s+1})`: order
:math:`2s` (variational error analysis).

References: J. Hall, M. Leok, *Lie group spectral variational integrators*, FoCM 17
(2017) 199–257 (the Lie-group curve in exponential coordinates); S. Ober-Blöbaum,
N. Saake, *Construction and analysis of higher order Galerkin variational integrators*,
Adv. Comput. Math. 41 (2015) 955–986 (Galerkin VIs, their order); J. E. Marsden, M. West,
*Discrete mechanics and variational integrators*, Acta Numerica 10 (2001), §2.3
(variational error analysis); the Euclidean
:class:`~lgvi_jax.integrators.galerkin.GalerkinVI`.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import so3
from ..models.rigid import RigidState
from ..newton import Newton
from ..options import ChordMatrix, JacobianMode
from ._tableaus import gauss_legendre, gauss_lobatto, lagrange_matrices
from .lie import AbstractLieVI, _vee_AtB
from .solver_settings import with_scalar_newton

__all__ = ["LieGalerkinVI"]


class LieGalerkinVI(AbstractLieVI):
    r"""The Lie-group Galerkin variational integrator with curves of degree ``degree``
    (module docstring): order ``2 * degree``, named ``galerkin{2 * degree}``.

    Its Newton unknowns are ``(ξ, u, Z, W)``: the step's mean velocities and the inner
    nodes, ``Z`` of shape ``(degree − 1, 3)``, ``W`` of shape ``(degree − 1, n)``, all
    velocity-sized (``Z_j ≈ d_j ω``, ``W_j ≈ d_j v``). The chord matrix is the exact one.
    """

    degree: int = eqx.field(static=True, default=2)
    #: On small arrays (module docstring): its scalar program takes minutes to compile.
    newton: Newton = Newton(chord_steps=8)

    symplectic: ClassVar[bool] = True
    jacobian_mode: ClassVar[JacobianMode] = JacobianMode.AUTO

    def __check_init__(self):
        if isinstance(self.degree, bool) or not isinstance(self.degree, int) or self.degree < 2:
            raise ValueError(f"LieGalerkinVI: degree must be an integer >= 2 (order 4 and up), "
                             f"got {self.degree!r}")
        if ChordMatrix.parse(self.chord_matrix, "LieGalerkinVI",
                             "chord_matrix") != ChordMatrix.EXACT:
            raise ValueError("LieGalerkinVI: chord_matrix must be 'exact' (the mass matrix "
                             "chord covers the velocity unknowns only, not the inner nodes)")

    @property
    def name(self) -> str:
        return f"galerkin{2 * self.degree}"

    @property
    def order(self) -> int:
        return 2 * self.degree

    # --- the discrete Lagrangian ----------------------------------------------------------
    def _tables(self):
        """Nodes ``d``, quadrature ``(c, b)`` and the Lagrange values ``V`` and derivatives
        ``D`` at the quadrature points of the nodes ``1..s`` (``(s+1, s)`` each)."""
        s = self.degree
        d = gauss_lobatto(s + 1)
        c, b = gauss_legendre(s + 1)
        V, D = lagrange_matrices(d, c)
        return d, b, V[:, 1:], D[:, 1:]

    def guess_from_velocities(self, velocities):
        omega, v = velocities
        d = jnp.asarray(self._tables()[0][1:-1], omega.dtype)[:, None]
        return omega, v, d * omega, d * v

    def action(self, model, h, R0, w, q0, Y, X):
        """``G = h Σ_i b_i L(R(c_i), Ω(c_i), q(c_i), q̇(c_i))`` for the rotation nodes
        ``Y = (Z_1, ..., Z_{s−1}, w/h)`` and position nodes ``X = (W_1, ..., W_s)``
        (module docstring); ``w`` enters through the chart's centre and end points."""
        _, b, V, D = self._tables()
        Y, X = jnp.stack(Y), jnp.stack(X)
        V, D, b = (jnp.asarray(a, Y.dtype) for a in (V, D, b))
        half = 0.5 * w
        Rm = R0 @ so3.exp(half)

        def lagrangian(zeta, zdot, q, v):
            Omega = so3.hat(so3.dexp(zeta) @ zdot)
            return model.kinetic(Rm @ so3.exp(zeta), Omega, q, v) - model.potential(
                Rm @ so3.exp(zeta), q)

        # One program for all quadrature points (vmap): (s + 1) copies of the Lagrangian
        # and its derivatives would multiply the traced and compiled program.
        lags = jax.vmap(lagrangian)(-half + h * (V @ Y), D @ Y, q0 + h * (V @ X), D @ X)
        return h * (b @ lags)

    def _galerkin_gradients(self, model, R0, xi, q0, u, Z, W, h):
        """``(g_k, ∂G/∂q_k, ∂G/∂q_{k+1}, g_w, ∂G/∂Z, ∂G/∂W)``: ``g_k`` the left-trivialised
        derivative in ``R_k`` and the position derivatives each with the other end point
        held fixed (as :meth:`AbstractLieVI.gradients`), the inner nodes held fixed."""
        w = h * xi

        def G(R0, w, q0, u, Z, W):
            Y = [Z[j] for j in range(Z.shape[0])] + [w / h]
            X = [W[j] for j in range(W.shape[0])] + [u]
            return self.action(model, h, R0, w, q0, Y, X)

        dR0, gw, dq0, du, dZ, dW = jax.grad(G, argnums=(0, 1, 2, 3, 4, 5))(R0, w, q0, u, Z, W)
        return _vee_AtB(R0, dR0), dq0 - du / h, du / h, gw, dZ, dW

    def _residual(self, z, args):
        model, R0, mu0, q0, p0, h = args
        xi, u, Z, W = z
        g0, gq0, _, gw, dZ, dW = self._galerkin_gradients(model, R0, xi, q0, u, Z, W, h)
        B = so3.dexp_left_inv(h * xi)
        return (B.T @ gw - g0 - mu0, -gq0 - p0, dZ / h, dW / h)

    def _finish(self, model, R0, q0, p0, h, xi, u, Z, W):
        w = h * xi
        _, gq0, gq1, gw, _, _ = self._galerkin_gradients(model, R0, xi, q0, u, Z, W, h)
        mu1 = so3.dexp_inv(w).T @ gw
        # p_{k+1} = p_k + (∂G/∂q_k + ∂G/∂q_{k+1}): exactly p_k when G depends on q only
        # through differences (AbstractLieVI._finish).
        return RigidState(R=R0 @ so3.exp(w), mu=mu1, q=q0 + h * u, p=p0 + (gq0 + gq1))


@with_scalar_newton.register(LieGalerkinVI)
def _(method: LieGalerkinVI, scalar: bool = True) -> LieGalerkinVI:
    # Solved on small arrays: the scalar program of the (s + 1) quadrature points' second
    # derivatives is too large to compile in reasonable time (CHANGELOG, 2026-12-06).
    if scalar:
        return method
    return dataclasses.replace(method, newton=dataclasses.replace(method.newton, scalar=False))
