r"""Symmetric compositions: higher-order methods from any symmetric one-step method.

Given a one-step method :math:`\Phi_h` and real numbers :math:`\gamma_1, \dots, \gamma_s`,
the composition method is

.. math::  \Psi_h = \Phi_{\gamma_s h} \circ \dots \circ \Phi_{\gamma_2 h} \circ
           \Phi_{\gamma_1 h}

(HLW §II.4, §V.3). It inherits every property that is closed under composition: a
composition of symplectic maps is symplectic; of maps on :math:`SO(3) \times \mathbb{R}^n`
stays there; of maps that conserve a momentum map conserves it exactly; and the composition
of discrete Lagrangian flows is the flow of a discrete Lagrangian (it is again a variational
integrator, of the composed step). If the base method is symmetric
(:math:`\Phi_{-h} = \Phi_h^{-1}`) and the :math:`\gamma`'s are palindromic
(:math:`\gamma_{s+1-i} = \gamma_i`), the composition is symmetric too.

**Order conditions.** A symmetric method of order :math:`q` has the formal expansion
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
given weight, and returns the coefficients of every word by weight. The composition's
declared ``order`` is computed this way from its :math:`\gamma`'s and the base order.

**Coefficient sets** (``SCHEMES``; the first of each order named by its stage count):

==================  =====  ======  ============================================================
name                order  stages  source
==================  =====  ======  ============================================================
``triple-jump``     4      3       :math:`\gamma_1 = \gamma_3 = 1/(2 - 2^{1/3})`,
                                   :math:`\gamma_2 = -2^{1/3}/(2 - 2^{1/3})`: Creutz & Gocksch
                                   (1989), Yoshida (1990), Suzuki (1990); HLW §II.4
``suzuki4``         4      5       Suzuki's fractal: :math:`\gamma_{1,2,4,5} = 1/(4 - 4^{1/3})`,
                                   :math:`\gamma_3 = -4^{1/3}/(4 - 4^{1/3})`: Suzuki (1990);
                                   HLW §II.4
``yoshida6``        6      7       Yoshida (1990), Table 1, solution A (15 digits published;
                                   refined to double precision, see below)
``kahan-li6``       6      9       Kahan & Li (1997), ``s9odr6a``; HLW §V.3.2
``yoshida8``        8      15      Yoshida (1990), Table 2, solution D (15 digits; refined)
``kahan-li8-s15``   8      15      Kahan & Li (1997), ``s15odr8``; HLW §V.3.2
``kahan-li8``       8      17      Kahan & Li (1997), ``s17odr8a``; HLW §V.3.2
==================  =====  ======  ============================================================

The Kahan–Li constants are copied with the 26 digits of the source. Yoshida published 15
significant digits, which satisfy the order conditions only to ~3e-12; his values were
refined here by Gauss–Newton on the conditions in 40-digit arithmetic (``mpmath``), from the
published digits: the refinement moves them by at most 2.4e-13 and the conditions then hold
to round-off (``tests/test_composition.py`` checks both).

**Defaults** (``lgvi@4``, ``@6``, ``@8``): the scheme with the smallest *error constant at
equal cost*, :math:`s^p\,\|E_{p+1}\|_2`, where :math:`E_{p+1}` are the coefficients of the
weight-:math:`(p+1)` words of the logarithm (the leading local error, independent of the
problem) and :math:`s^p` converts to equal work (:math:`s` base steps per step):
``suzuki4`` (47 against 430 for the triple jump), ``kahan-li6`` (2.0e4 against 1.1e5 for
Yoshida's), ``kahan-li8`` (7.9e6, against 2.9e7 for ``s15odr8`` and 3.7e10 for Yoshida's).
The car-pendulum agrees (``tests/test_composition.py`` step ranges; configuration error at
T = 1, h = 0.05): ``lgvi@kahan-li8`` 1.4e-8, ``lgvi@kahan-li8-s15`` 1.5e-7,
``lgvi@yoshida8`` 7.8e-4; ``lgvi@kahan-li6`` 1.2e-5 against ``lgvi@yoshida6`` 3.3e-4.

**Warm starts.** Each sub-step of a Lie-group VI solves for the mean body and cart velocity
:math:`(\xi, u)` over the sub-step, which approximates the velocity at its midpoint. The
base method starts Newton from the velocities of the current state, an :math:`O(\gamma_i h)`
guess. Inside a composition the previous sub-step's solution :math:`\bar v_{i-1}` (the
velocity near the midpoint of the previous sub-step) and the current velocity :math:`v`
give a linear extrapolation to the midpoint of the next one, valid for backward
(:math:`\gamma_i < 0`) sub-steps too since the midpoints are at signed offsets
:math:`-\gamma_{i-1}h/2` and :math:`\gamma_i h/2`:

.. math::  v_{\rm guess} = v + \frac{\gamma_i}{\gamma_{i-1}}\,(v - \bar v_{i-1}),

an :math:`O(h^2)` guess (``warm_start=True``, the default; the first sub-step uses
:math:`v`). The guess changes only the Newton iterates, not the solution.

References: M. Creutz, A. Gocksch, *Higher-order hybrid Monte Carlo algorithms*, Phys. Rev.
Lett. 63 (1989) 9–12; H. Yoshida, *Construction of higher order symplectic integrators*,
Phys. Lett. A 150 (1990) 262–268; M. Suzuki, *Fractal decomposition of exponential operators
with applications to many-body theories and Monte Carlo simulations*, Phys. Lett. A 146
(1990) 319–323; W. Kahan, R.-C. Li, *Composition constants for raising the orders of
unconventional schemes for ordinary differential equations*, Math. Comp. 66 (1997)
1089–1099; E. Hairer, C. Lubich, G. Wanner, *Geometric Numerical Integration*, 2nd ed.,
Springer 2006 (HLW), §II.4, §V.3; J. E. Marsden, M. West, *Discrete mechanics and
variational integrators*, Acta Numerica 10 (2001) 357–514 (composition methods as
variational integrators).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Iterator, Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from ..options import ChordMatrix
from ..trajectory import RESULTS
from .base import AbstractIntegrator, StepInfo

__all__ = [
    "DEFAULT_SCHEMES",
    "SCHEMES",
    "Composition",
    "CompositionScheme",
    "MethodTable",
    "compose",
    "order_conditions",
    "parse_method",
    "resolve_method",
]


# ---------------------------------------------------------------------------------------
# Coefficient sets
# ---------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class CompositionScheme:
    """A named coefficient set: ``gammas`` (palindromic, summing to 1), the order it gives
    to a second-order symmetric base method, and its source."""

    name: str
    order: int
    gammas: tuple[float, ...]
    source: str

    @property
    def stages(self) -> int:
        return len(self.gammas)


def _palindrome(half: tuple[float, ...], middle: float | None = None) -> tuple[float, ...]:
    """``half + (middle,) + reversed(half)``; ``middle`` defaults to ``1 - 2 sum(half)``."""
    mid = 1.0 - 2.0 * math.fsum(half) if middle is None else middle
    return (*half, mid, *reversed(half))


_C3 = 2.0 ** (1.0 / 3.0)
_C4 = 4.0 ** (1.0 / 3.0)

SCHEMES: dict[str, CompositionScheme] = {
    s.name: s
    for s in (
        CompositionScheme(
            "triple-jump", 4, (1 / (2 - _C3), -_C3 / (2 - _C3), 1 / (2 - _C3)),
            "Creutz & Gocksch 1989; Yoshida 1990; Suzuki 1990; HLW §II.4",
        ),
        CompositionScheme(
            "suzuki4", 4,
            (1 / (4 - _C4), 1 / (4 - _C4), -_C4 / (4 - _C4), 1 / (4 - _C4), 1 / (4 - _C4)),
            "Suzuki 1990 (fractal decomposition); HLW §II.4",
        ),
        CompositionScheme(
            # Yoshida's solution A, outermost first: w3, w2, w1, w0, w1, w2, w3. Published
            # (15 digits): w1 = -1.17767998417887, w2 = 0.235573213359357,
            # w3 = 0.784513610477560; refined to double precision (module docstring).
            "yoshida6", 6,
            _palindrome((0.7845136104775572638194976, 0.2355732133593581336847932,
                         -1.177679984178871006946416)),
            "Yoshida 1990, Table 1, solution A (refined to double precision)",
        ),
        CompositionScheme(
            "kahan-li6", 6,
            _palindrome((0.39216144400731413927925056, 0.33259913678935943859974864,
                         -0.70624617255763935980996482, 0.08221359629355080023149045),
                        0.79854399093482996339895035),
            "Kahan & Li 1997, s9odr6a; HLW §V.3.2",
        ),
        CompositionScheme(
            # Yoshida's solution D, outermost first: w7, ..., w1, w0, w1, ..., w7. Published
            # (15 digits): w1 = 0.102799849391985, w2 = -1.96061023297549,
            # w3 = 1.93813913762276, w4 = -0.158240635368243, w5 = -1.44485223686048,
            # w6 = 0.253693336566229, w7 = 0.914844246229740; refined (module docstring).
            "yoshida8", 8,
            _palindrome((0.9148442462297915667487935, 0.253693336566211354146146,
                         -1.444852236860605157694731, -0.1582406353680501752040668,
                         1.938139137622525986579186, -1.960610232975310807607633,
                         0.1027998493917964406981151)),
            "Yoshida 1990, Table 2, solution D (refined to double precision)",
        ),
        CompositionScheme(
            "kahan-li8-s15", 8,
            _palindrome((0.74167036435061295344822780, -0.40910082580003159399730010,
                         0.19075471029623837995387626, -0.57386247111608226665638773,
                         0.29906418130365592384446354, 0.33462491824529818378495798,
                         0.31529309239676659663205666),
                        -0.79688793935291635401978884),
            "Kahan & Li 1997, s15odr8; HLW §V.3.2",
        ),
        CompositionScheme(
            "kahan-li8", 8,
            _palindrome((0.13020248308889008087881763, 0.56116298177510838456196441,
                         -0.38947496264484728640807860, 0.15884190655515560089621075,
                         -0.39590389413323757733623154, 0.18453964097831570709183254,
                         0.25837438768632204729397911, 0.29501172360931029887096624),
                        -0.60550853383003451169892108),
            "Kahan & Li 1997, s17odr8a; HLW §V.3.2",
        ),
    )
}

#: The scheme chosen for ``METHOD@ORDER`` (smallest error constant at equal cost; module
#: docstring).
DEFAULT_SCHEMES: dict[int, str] = {4: "suzuki4", 6: "kahan-li6", 8: "kahan-li8"}


# ---------------------------------------------------------------------------------------
# Order conditions in the free associative algebra
# ---------------------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------------------
# The combinator
# ---------------------------------------------------------------------------------------


def _merge_info(acc, info):
    """Sum the iterations; keep the first failure's code and residual (else the largest
    residual)."""
    steps, code, res = acc
    first_failure = (code == RESULTS.successful) & (info.result != RESULTS.successful)
    res = jnp.where(first_failure, info.residual,
                    jnp.where(code == RESULTS.successful, jnp.maximum(res, info.residual), res))
    code = jnp.where(first_failure, info.result, code).astype(jnp.int32)
    return steps + info.newton_steps.astype(jnp.int32), code, res


class Composition(AbstractIntegrator):
    r"""The composition :math:`\Phi_{\gamma_s h}\circ\dots\circ\Phi_{\gamma_1 h}` of a
    symmetric one-step method ``base`` (module docstring).

    Args:
        base: a symmetric integrator (``base.symmetric``), e.g. ``LGVI()``.
        gammas: the sub-step fractions, summing to 1 (palindromic for a symmetric result).
        scheme: a label for :attr:`name` (``"<base>@<scheme>"``); default ``"custom"``.
        warm_start: start each Lie-group VI sub-step's Newton solve from the extrapolated
            previous solution (module docstring); no effect for other base methods.
        scalar: solve a Lie-group VI base's sub-steps with the autodiff engine on scalars
            (its Newton settings with ``scalar=True``, :mod:`lgvi_jax.scalarize`): the same
            solutions to round-off, several times faster (``lgvi@4``: ~6x, ``lgvi@8``:
            ~3.5x for one trajectory, docs/engine.md). Used where the base's settings allow
            it (the exact chord matrix; chord-then-Newton or plain Newton); ``False``: the
            base's own solver.

    ``order`` is computed from ``gammas`` and ``base.order`` (:func:`composition_order`);
    ``symmetric`` = base symmetric and palindromic ``gammas``; ``symplectic`` and
    ``implicit`` are the base's. The sub-steps run in a ``lax.scan`` over the array of
    ``gammas`` (one traced copy of the base step, whatever the number of stages).
    ``step`` reports the Newton iterations summed over the sub-steps and the first failing
    sub-step's result code and residual.
    """

    base: AbstractIntegrator
    gammas: tuple[float, ...] = eqx.field(static=True)
    scheme: str = eqx.field(static=True, default="custom")
    warm_start: bool = eqx.field(static=True, default=True)
    scalar: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        if not isinstance(self.base, AbstractIntegrator):
            raise ValueError(f"Composition: base must be an integrator, got {self.base!r}")
        if not self.base.symmetric:
            raise ValueError(
                f"Composition: base method {self.base.name} is not symmetric "
                "(Φ_{-h} ≠ Φ_h^{-1}); composition needs a symmetric base method "
                "(e.g. lgvi, hamel-cayley, hamel-exact, verlet, gl4)"
            )
        if isinstance(self.base, Composition):
            raise ValueError("Composition: base is already a composition; compose the "
                             "underlying method with a higher-order scheme instead")
        gammas = self.gammas
        if (not isinstance(gammas, tuple) or not gammas
                or not all(isinstance(g, float) and math.isfinite(g) for g in gammas)):
            raise ValueError(f"Composition: gammas must be a non-empty tuple of finite floats, "
                             f"got {gammas!r}")
        if abs(math.fsum(gammas) - 1.0) > 1e-12:
            raise ValueError(f"Composition: gammas must sum to 1 (consistency), they sum to "
                             f"{math.fsum(gammas)!r}")

    # --- traits -------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return f"{self.base.name}@{self.scheme}"

    @property
    def stages(self) -> int:
        return len(self.gammas)

    @property
    def order(self) -> int:
        return max(composition_order(self.gammas, self.base.order), self.base.order)

    @property
    def palindromic(self) -> bool:
        g = self.gammas
        return all(abs(a - b) <= 1e-15 * max(1.0, abs(a)) for a, b in zip(g, g[::-1], strict=True))

    @property
    def symmetric(self) -> bool:
        return self.base.symmetric and self.palindromic

    @property
    def symplectic(self) -> bool:
        return self.base.symplectic

    @property
    def implicit(self) -> bool:
        return self.base.implicit

    def check_model(self, model) -> None:
        self.base.check_model(model)

    def describe(self) -> str:
        return f"{super().describe()[:-1]}, {self.stages} stages of {self.base.name})"

    # --- the step -----------------------------------------------------------------------
    def _sub_step_method(self) -> AbstractIntegrator:
        """The base with its solver as :attr:`scalar` says."""
        return with_scalar_newton(self.base) if self.scalar else self.base

    def step(self, model, state, dt):
        from .lie import AbstractLieVI

        base = self._sub_step_method()
        gam = jnp.asarray(self.gammas, jnp.float64)
        dt = jnp.asarray(dt, jnp.float64)
        acc0 = (jnp.asarray(0, jnp.int32), jnp.asarray(RESULTS.successful, jnp.int32),
                jnp.zeros((), jnp.float64))

        if not (self.warm_start and isinstance(self.base, AbstractLieVI)):
            def plain(carry, g):
                s, acc = carry
                s, info = base.step(model, s, g * dt)
                return (s, _merge_info(acc, info)), None

            (state, acc), _ = jax.lax.scan(plain, (state, acc0), gam)
            return state, StepInfo(newton_steps=acc[0], result=acc[1], residual=acc[2])

        # Warm start: the previous sub-step's fraction (0 before the first sub-step, where
        # the guess is the current velocity).
        prev_gam = jnp.concatenate([jnp.zeros((1,), jnp.float64), gam[:-1]])

        def warm(carry, xs):
            s, prev_sol, acc = carry
            g, g_prev = xs
            v = model.velocities(s.R, s.mu, s.q, s.p)
            ratio = jnp.where(g_prev == 0.0, 0.0, g / jnp.where(g_prev == 0.0, 1.0, g_prev))
            guess = jax.tree.map(lambda a, b: a + ratio * (a - b), v, prev_sol)
            s, info, sol = base.solve_step(model, s, g * dt, guess)
            return (s, sol, _merge_info(acc, info)), None

        zero_sol = (jnp.zeros_like(state.mu), jnp.zeros_like(state.p))
        (state, _, acc), _ = jax.lax.scan(warm, (state, zero_sol, acc0), (gam, prev_gam))
        return state, StepInfo(newton_steps=acc[0], result=acc[1], residual=acc[2])


# ---------------------------------------------------------------------------------------
# Construction by order or scheme, and the METHOD@SPEC syntax
# ---------------------------------------------------------------------------------------


def _scheme_list() -> str:
    return ", ".join(f"{n} (order {s.order}, {s.stages} stages)" for n, s in SCHEMES.items())


def compose(base: AbstractIntegrator, order: int | None = None, *, scheme: str | None = None,
            warm_start: bool = True) -> Composition:
    """Compose ``base`` to the given ``order`` (4, 6 or 8; the default scheme of
    :data:`DEFAULT_SCHEMES`) or with a named ``scheme`` (a key of :data:`SCHEMES`).

    Raises ``ValueError`` for an unknown order or scheme, a non-symmetric base, or a base
    whose order is already at least the scheme's.
    """
    if (order is None) == (scheme is None):
        raise ValueError("compose: give exactly one of order (4, 6, 8) or scheme "
                         f"({', '.join(SCHEMES)})")
    if order is not None:
        if isinstance(order, bool) or order not in DEFAULT_SCHEMES:
            raise ValueError(f"compose: order must be one of {sorted(DEFAULT_SCHEMES)}, got "
                             f"{order!r}")
        scheme = DEFAULT_SCHEMES[order]
    if scheme not in SCHEMES:
        raise ValueError(f"compose: unknown scheme {scheme!r}; valid schemes: {_scheme_list()}")
    spec = SCHEMES[scheme]
    if not isinstance(base, AbstractIntegrator):
        raise ValueError(f"compose: base must be an integrator, got {base!r}")
    if not base.symmetric:
        raise ValueError(
            f"compose: {base.name} is not symmetric (Φ_{{-h}} ≠ Φ_h^{{-1}}); composition "
            "needs a symmetric base method (e.g. lgvi, hamel-cayley, hamel-exact, verlet, gl4)"
        )
    if base.order >= spec.order:
        raise ValueError(f"compose: {base.name} already has order {base.order}; scheme "
                         f"{scheme} (order {spec.order}) would not raise it")
    return Composition(base, spec.gammas, scheme=scheme, warm_start=warm_start)


def parse_method(name: str) -> tuple[str, str | None]:
    """Split ``"METHOD@SPEC"`` into ``("METHOD", "SPEC")``; a plain name gives
    ``(name, None)``. ``SPEC`` is an order (``4``, ``6``, ``8``) or a scheme name."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"method: expected a method name, got {name!r}")
    base, sep, spec = name.partition("@")
    if not sep:
        return name, None
    if not base or not spec or "@" in spec:
        raise ValueError(f"method {name!r}: expected METHOD or METHOD@ORDER (e.g. lgvi@6) or "
                         f"METHOD@SCHEME (e.g. lgvi@kahan-li8)")
    return base, spec


def resolve_method(name: str,
                   registry: Mapping[str, Callable[[], AbstractIntegrator]]) -> AbstractIntegrator:
    """Build the method called ``name`` from ``registry`` (name -> factory).

    Syntax: ``METHOD`` (a registry key), ``METHOD@ORDER`` with ``ORDER`` in 4, 6, 8 (the
    default scheme of that order, :data:`DEFAULT_SCHEMES`), or ``METHOD@SCHEME`` with a
    scheme of :data:`SCHEMES` (e.g. ``lgvi@6``, ``verlet@8``, ``gl4@6``,
    ``lgvi@kahan-li8``, ``hamel-cayley@triple-jump``). Raises ``ValueError`` naming the
    method for an unknown name or scheme and for a base method that is not symmetric.
    """
    base_name, spec = parse_method(name)
    if base_name not in registry:
        valid = ", ".join(registry)
        where = f" (in {name!r})" if spec is not None else ""
        raise ValueError(f"unknown method {base_name!r}{where}; valid methods: {valid}, each "
                         "optionally as METHOD@ORDER (4, 6, 8) or METHOD@SCHEME")
    base = registry[base_name]()
    if spec is None:
        return base
    try:
        if spec.isdigit():
            return compose(base, order=int(spec))
        if spec not in SCHEMES:
            raise ValueError(f"unknown order or scheme {spec!r}; orders: "
                             f"{', '.join(map(str, DEFAULT_SCHEMES))}; schemes: {_scheme_list()}")
        return compose(base, scheme=spec)
    except ValueError as err:
        raise ValueError(f"method {name!r}: {str(err).removeprefix('compose: ')}") from None


class MethodTable(Mapping):
    """A read-only table of method factories that also accepts ``METHOD@SPEC`` names.

    Iterating (and ``len``) lists only the base methods; ``name in table`` is true for
    every name :func:`resolve_method` accepts, and ``table[name]`` returns a factory for
    it. This keeps code that validates names with ``in`` working for compositions."""

    def __init__(self, methods: Mapping[str, Callable[[], AbstractIntegrator]]):
        self._methods = dict(methods)

    def __getitem__(self, name: str) -> Callable[[], AbstractIntegrator]:
        if name in self._methods:
            return self._methods[name]
        try:
            resolve_method(name, self._methods)
        except ValueError:
            raise KeyError(name) from None
        return functools.partial(resolve_method, name, self._methods)

    def __contains__(self, name: object) -> bool:
        if not isinstance(name, str):
            return False
        if name in self._methods:
            return True
        try:
            resolve_method(name, self._methods)
        except ValueError:
            return False
        return True

    def __iter__(self) -> Iterator[str]:
        return iter(self._methods)

    def __len__(self) -> int:
        return len(self._methods)

    def resolve(self, name: str) -> AbstractIntegrator:
        """:func:`resolve_method` on this table."""
        return resolve_method(name, self._methods)

    def composable(self) -> list[str]:
        """The base methods that can be composed (symmetric, order below 8)."""
        return [n for n, make in self._methods.items()
                if make().symmetric and make().order < max(DEFAULT_SCHEMES)]


def with_chord_matrix(method: AbstractIntegrator,
                      chord_matrix: ChordMatrix | str) -> AbstractIntegrator:
    """``method`` with its Lie-group VI steps using ``chord_matrix`` (a
    :class:`~lgvi_jax.options.ChordMatrix` or its string, ``"exact"`` or ``"mass"``, see
    :class:`~lgvi_jax.integrators.lie.AbstractLieVI`), also inside a composition; any other
    method is returned unchanged (it has no chord phase)."""
    import dataclasses

    from .lie import AbstractLieVI

    chord_matrix = ChordMatrix.parse(chord_matrix, "with_chord_matrix", "chord_matrix")
    if isinstance(method, AbstractLieVI):
        return dataclasses.replace(method, chord_matrix=chord_matrix)
    if isinstance(method, Composition) and isinstance(method.base, AbstractLieVI):
        return dataclasses.replace(
            method, base=dataclasses.replace(method.base, chord_matrix=chord_matrix))
    return method


def with_scalar_newton(method: AbstractIntegrator) -> AbstractIntegrator:
    """``method`` with its Lie-group VI steps solved on scalars (``Newton(scalar=True)``,
    :mod:`lgvi_jax.scalarize`), also inside a composition, where the chord matrix is the
    exact one and the Newton settings allow it (chord-then-Newton or plain Newton, implicit
    derivatives); any other method is returned unchanged. The same solutions to round-off."""
    import dataclasses

    from .lie import AbstractLieVI

    def scalar(vi):
        if vi.chord_matrix != ChordMatrix.EXACT or not vi.newton.scalar_compatible:
            return vi
        return dataclasses.replace(vi, newton=dataclasses.replace(vi.newton, scalar=True))

    if isinstance(method, AbstractLieVI):
        return scalar(method)
    if isinstance(method, Composition) and isinstance(method.base, AbstractLieVI):
        return dataclasses.replace(method, base=scalar(method.base))
    return method
