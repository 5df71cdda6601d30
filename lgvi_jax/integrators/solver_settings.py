r"""How a method's Lie-group VI steps are solved: the chord matrix and the scalar engine.

**Contract.** :func:`with_chord_matrix` and :func:`with_scalar_newton` take any integrator
and return one that solves the same implicit step equations, only differently:

* a Lie-group VI (:class:`~lgvi_jax.integrators.lie.AbstractLieVI`: ``LGVI``, ``HamelVI``)
  gets the setting itself;
* a method built from one (a :class:`~lgvi_jax.integrators.composition.Composition` of a
  Lie-group VI) gets it in those steps: each such combinator registers its rule next to its
  class (both functions are :func:`functools.singledispatch` functions; the composition's
  rule is in :mod:`lgvi_jax.integrators.composition`);
* any other method is returned unchanged (it has no chord phase and no scalar engine).

``chord_matrix`` is checked for every method (``ValueError`` naming ``with_chord_matrix``
for an invalid one), whether or not it has a chord phase.

**What the settings change.** Each Lie-group VI step solves its discrete Legendre map for
the mean body and cart velocity over the step, :math:`F(\xi, u) = 0`, by chord iterations
:math:`x \leftarrow x - M^{-1}F(x)` with Newton as the fallback
(:class:`~lgvi_jax.newton.Newton`). ``chord_matrix`` picks :math:`M`: ``"exact"`` the
Jacobian of :math:`F` at the initial guess; ``"mass"`` the continuous Legendre map's matrix
:math:`\partial(\mu, p)/\partial(\omega, v)` at the current configuration (the Jacobian up
to :math:`O(h)`, at the cost of no derivative), improved by Broyden's update. The scalar
engine (``Newton(scalar=True)``, :mod:`lgvi_jax.scalarize`) runs the iteration as scalar
operations instead of small-array ones; it covers the exact chord matrix with
chord-then-Newton or plain Newton and implicit derivatives
(:attr:`~lgvi_jax.newton.Newton.scalar_compatible`), and :func:`with_scalar_newton` leaves
a Lie-group VI with other settings as it is. Both change the iterates, not the equations:
the same solutions to round-off (:class:`~lgvi_jax.integrators.lie.AbstractLieVI`,
docs/engine.md).

References: C. T. Kelley, *Iterative Methods for Linear and Nonlinear Equations*, SIAM 1995
(the chord method); C. G. Broyden, *A class of methods for solving nonlinear simultaneous
equations*, Math. Comp. 19 (1965) 577–593.
"""

from __future__ import annotations

import dataclasses
import functools

from ..options import ChordMatrix
from .base import AbstractIntegrator
from .lie import AbstractLieVI

__all__ = ["with_chord_matrix", "with_scalar_newton"]


def _parse_chord_matrix(chord_matrix: ChordMatrix | str) -> ChordMatrix:
    return ChordMatrix.parse(chord_matrix, "with_chord_matrix", "chord_matrix")


@functools.singledispatch
def with_chord_matrix(method: AbstractIntegrator,
                      chord_matrix: ChordMatrix | str) -> AbstractIntegrator:
    """``method`` with its Lie-group VI steps using ``chord_matrix`` (a
    :class:`~lgvi_jax.options.ChordMatrix` or its string, ``"exact"`` or ``"mass"``, see
    :class:`~lgvi_jax.integrators.lie.AbstractLieVI`), also inside a composition; any other
    method is returned unchanged (it has no chord phase)."""
    _parse_chord_matrix(chord_matrix)
    return method


@with_chord_matrix.register(AbstractLieVI)
def _(method: AbstractLieVI, chord_matrix: ChordMatrix | str) -> AbstractLieVI:
    return dataclasses.replace(method, chord_matrix=_parse_chord_matrix(chord_matrix))


@functools.singledispatch
def with_scalar_newton(method: AbstractIntegrator, scalar: bool = True) -> AbstractIntegrator:
    """``method`` with its Lie-group VI steps solved on scalars (``Newton(scalar=True)``,
    :mod:`lgvi_jax.scalarize`, the default of ``LGVI`` and ``HamelVI``), also inside a
    composition, where the chord matrix is the exact one and the Newton settings allow it
    (chord-then-Newton or plain Newton, implicit derivatives); with ``scalar=False`` on small
    arrays (``Newton(scalar=False)``) instead. Any other method is returned unchanged. The
    same solutions to round-off."""
    _check_scalar(scalar)
    return method


def _check_scalar(scalar) -> None:
    if not isinstance(scalar, bool):
        raise TypeError(f"with_scalar_newton: scalar must be True or False, got {scalar!r}")


@with_scalar_newton.register(AbstractLieVI)
def _(method: AbstractLieVI, scalar: bool = True) -> AbstractLieVI:
    _check_scalar(scalar)
    # Where the scalar engine does not apply the flag says so (the step runs on arrays).
    scalar = scalar and (method.chord_matrix == ChordMatrix.EXACT
                         and method.newton.scalar_compatible)
    return dataclasses.replace(method, newton=dataclasses.replace(method.newton,
                                                                  scalar=scalar))
