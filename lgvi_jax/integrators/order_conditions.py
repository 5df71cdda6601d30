r"""Order conditions of composition methods, by a Baker–Campbell–Hausdorff computation.

**Contract.** Pure Python, no JAX: functions of the sub-step fractions
:math:`\gamma_1, \dots, \gamma_s` of a composition
:math:`\Psi_h = \Phi_{\gamma_s h} \circ \dots \circ \Phi_{\gamma_1 h}` of a *symmetric*
base method :math:`\Phi_h` of order :math:`q` (``base_order``). :func:`order_conditions`
returns every coefficient of the composed logarithm up to a given weight,
:func:`composition_order` the order they give (the ``order`` of a
:class:`~lgvi_jax.integrators.composition.Composition`), :func:`error_constant` the size of
the leading error term (how :data:`~lgvi_jax.integrators.schemes.DEFAULT_SCHEMES` are
chosen). The results depend only on the :math:`\gamma`'s and :math:`q`, not on the problem.

**The maths.** A symmetric method of order :math:`q` has the formal expansion
:math:`\Phi_h = \exp(hX_1 + h^{q+1}X_{q+1} + h^{q+3}X_{q+3} + \dots)` (odd powers only,
by symmetry) with :math:`X_1` the vector field and :math:`X_k` its error fields, viewed as
free, non-commuting generators. Then by the Baker–Campbell–Hausdorff formula

.. math::  \Psi_h = \exp\Big(h\textstyle\sum_i\gamma_i X_1 + \sum_k h^k
           \sum_i\gamma_i^k X_k + h^4(\dots)[X_1, X_3] + \dots\Big),

and :math:`\Psi` has order :math:`p` iff :math:`\sum_i\gamma_i = 1` and every term of
weight :math:`2, \dots, p` vanishes. For a palindromic composition of a second-order base
these are :math:`\sum\gamma_i^3 = 0` (order 4); :math:`\sum\gamma_i^5 = 0` and one
condition on :math:`[X_1,[X_1,X_3]]` (order 6); :math:`\sum\gamma_i^7 = 0` and four more
(order 8) (HLW §V.3.2). :func:`order_conditions` evaluates them all at once, without
listing them: it computes the logarithm of :math:`\prod_i \exp(\sum_k\gamma_i^k X_k)` in the
free associative algebra on the letters :math:`X_1, X_{q+1}, X_{q+3}, \dots`, truncated at a
given weight (a word's weight is the sum of its letters' indices, its power of :math:`h`),
and returns the coefficients of every word by weight. The logarithm is a Lie element, and
its part of a given weight vanishes iff all its word coefficients do: no basis of the free
Lie algebra is needed (the norms below are over words).

:func:`composition_order` is the largest :math:`p` such that the coefficients of weights
:math:`2, \dots, p` vanish to :math:`10^{-9}` relative to :math:`\sum_i|\gamma_i|^w`
(capped at 10). :func:`error_constant` is the 2-norm :math:`\|E_{p+1}\|_2` of the
coefficients of weight :math:`p + 1`: the local error of the composition is about
:math:`\|E_{p+1}\|\,h^{p+1}` in units of the base method's error fields.

References: H. Yoshida, *Construction of higher order symplectic integrators*, Phys. Lett.
A 150 (1990) 262–268 (order conditions of symmetric compositions by the BCH formula);
M. Suzuki, *Fractal decomposition of exponential operators with applications to many-body
theories and Monte Carlo simulations*, Phys. Lett. A 146 (1990) 319–323; E. Hairer,
C. Lubich, G. Wanner, *Geometric Numerical Integration*, 2nd ed., Springer 2006 (HLW),
§II.4 (composition methods), §III.4–III.5 (the BCH formula; order conditions via BCH),
§V.3.2 (symmetric compositions of symmetric methods).
"""

from __future__ import annotations

import functools
import math
from typing import Any

__all__ = ["composition_order", "error_constant", "order_conditions"]


# Elements of the truncated free associative algebra: dicts {word: coefficient}, a word a
# tuple of letter indices (its weight their sum), the empty word the unit.


def _weight(word: tuple[int, ...]) -> int:
    return sum(word)


def _mul(a: dict, b: dict, max_weight: int) -> dict:
    out: dict = {}
    for wa, ca in a.items():
        la = _weight(wa)
        for wb, cb in b.items():
            if la + _weight(wb) > max_weight:
                continue
            key = wa + wb
            out[key] = out.get(key, 0) + ca * cb
    return out


def _exp(x: dict, max_weight: int, one) -> dict:
    out, term = {(): one}, {(): one}
    for n in range(1, max_weight + 1):  # every letter has weight >= 1
        term = {k: v / n for k, v in _mul(term, x, max_weight).items()}
        for k, v in term.items():
            out[k] = out.get(k, 0) + v
    return out


def _log(a: dict, max_weight: int) -> dict:
    z = {k: v for k, v in a.items() if k}
    out, term = {}, {(): 1}
    for n in range(1, max_weight + 1):
        term = _mul(term, z, max_weight)
        sign = 1 if n % 2 else -1
        for k, v in term.items():
            out[k] = out.get(k, 0) + sign * v / n
    return out


def order_conditions(gammas, max_weight: int, base_order: int = 2, *,
                     one: Any = 1.0) -> dict[int, dict[tuple[int, ...], Any]]:
    r"""Coefficients of :math:`\log\prod_i\exp(\sum_k\gamma_i^kX_k)` by weight.

    The letters are :math:`X_1` and :math:`X_k` for odd :math:`k > q` = ``base_order``
    (the error fields of a symmetric method of order ``q``); a word's weight is the sum of
    its letters' indices (its power of ``h``). Returns ``{weight: {word: coefficient}}``
    for weights ``1 .. max_weight``; the composition has order ``p`` iff the weight-1
    coefficient (of :math:`X_1`) is 1 and all coefficients of weight ``2 .. p`` vanish.
    ``one`` sets the number type (e.g. ``mpmath.mpf(1)`` for extended precision).
    """
    letters = [1, *range(base_order + 1, max_weight + 1, 2)]
    prod = {(): one}
    for g in gammas:
        g = one * g
        step = _exp({(k,): g**k for k in letters}, max_weight, one)
        prod = _mul(step, prod, max_weight)  # Φ_{γ_i h} applied after the earlier ones
    by_weight: dict[int, dict] = {}
    for word, coef in _log(prod, max_weight).items():
        by_weight.setdefault(_weight(word), {})[word] = coef
    return by_weight


def _defects(gammas, max_weight, base_order):
    """The 2-norm of the coefficients of each weight ``2 .. max_weight``."""
    conds = order_conditions(gammas, max_weight, base_order)
    out = {}
    for w in range(2, max_weight + 1):
        coefs = conds.get(w, {})
        out[w] = math.sqrt(math.fsum(c * c for c in coefs.values())) if coefs else 0.0
    return out


@functools.cache
def composition_order(gammas: tuple[float, ...], base_order: int = 2) -> int:
    """The order of the composition of a symmetric method of order ``base_order`` with
    these ``gammas``: the largest ``p`` such that the order conditions of weights
    ``2 .. p`` hold (to 1e-9 relative to ``sum |γ|^w``). Capped at 10."""
    scale_w = {w: math.fsum(abs(g) ** w for g in gammas) for w in range(2, 12)}
    p = 1
    for max_weight in (9, 11):
        defects = _defects(gammas, max_weight, base_order)
        p = 1
        for w in range(2, max_weight + 1):
            if defects[w] > 1e-9 * max(1.0, scale_w[w]):
                break
            p = w
        if p < max_weight:
            break
    return min(p, 10)


def error_constant(gammas: tuple[float, ...], base_order: int = 2) -> float:
    """2-norm of the leading error coefficients (weight ``order + 1``) of the composition:
    its local error is about ``error_constant * h^(order+1)`` in units of the base method's
    (problem-dependent) error fields."""
    p = composition_order(tuple(gammas), base_order)
    return _defects(tuple(gammas), p + 1, base_order)[p + 1]
