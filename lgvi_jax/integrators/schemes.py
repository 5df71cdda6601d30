r"""Named composition schemes: the coefficient tables, ``compose`` and ``METHOD@SPEC`` names.

**Contract.** :data:`SCHEMES` maps a name to a :class:`CompositionScheme`: palindromic
sub-step fractions :math:`\gamma_i` (summing to 1), the order they give to a second-order
symmetric base method, and their source. :func:`compose` builds the
:class:`~lgvi_jax.integrators.composition.Composition` of a symmetric method to a given order
(the scheme of :data:`DEFAULT_SCHEMES`) or with a named scheme; it refuses a base that is
not symmetric or whose order the scheme would not raise. :func:`parse_method` and
:func:`resolve_method` read the names the CLI, the systems and the studies use: ``METHOD``,
``METHOD@ORDER`` (4, 6, 8) and ``METHOD@SCHEME`` (``lgvi@6``, ``lgvi@kahan-li8``);
:class:`MethodTable` is a table of method factories that accepts those names too.

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
``triple-jump6``    6      3       the triple jump for an order-4 base: :math:`2^{1/5}` for
                                   :math:`2^{1/3}`
``suzuki6``         6      5       Suzuki's fractal for an order-4 base: :math:`4^{1/5}`
``triple-jump8``    8      3       the triple jump for an order-6 base: :math:`2^{1/7}`
``suzuki8``         8      5       Suzuki's fractal for an order-6 base: :math:`4^{1/7}`
==================  =====  ======  ============================================================

The orders are those given to a second-order symmetric base, except for the last four,
built for a base of order :math:`q = 4` or :math:`6` (``gl4``, ``galerkin4``, ``gl6``,
``galerkin6``; :attr:`CompositionScheme.base_order`): the same constructions with the
exponent :math:`1/(q+1)`, which cancel :math:`\sum\gamma_i^{q+1}`, the only condition of
weight :math:`q + 1` on such a base (HLW §II.4). A scheme built for a lower base order also
works on a higher one (its conditions include the base's); one built for a higher base
order is refused on a lower one.

Every set satisfies the order conditions of its order to round-off
(:func:`~lgvi_jax.integrators.order_conditions.order_conditions`; the conditions of the next
weight do not hold, so the order is exact). The Kahan–Li constants are the 26 digits of the
source. Yoshida published 15 significant digits, which satisfy the order conditions only to
~3e-12; the stored values are his refined by Gauss–Newton on the conditions in 40-digit
arithmetic (``mpmath``), starting from the published digits: they differ from them by at
most 2.4e-13 and satisfy the conditions to round-off (``tests/test_composition.py`` checks
both).

**Defaults** (``lgvi@4``, ``@6``, ``@8``): the scheme with the smallest *error constant at
equal cost*, :math:`s^p\,\|E_{p+1}\|_2`, where :math:`E_{p+1}` are the coefficients of the
weight-:math:`(p+1)` words of the logarithm
(:func:`~lgvi_jax.integrators.order_conditions.error_constant`: the leading local error,
independent of the problem) and :math:`s^p` converts to equal work (:math:`s` base steps
per step): ``suzuki4`` (47 against 430 for the triple jump), ``kahan-li6`` (2.0e4 against
1.1e5 for Yoshida's), ``kahan-li8`` (7.9e6, against 2.9e7 for ``s15odr8`` and 3.7e10 for
Yoshida's). The car-pendulum agrees (``tests/test_composition.py`` step ranges;
configuration error at T = 1, h = 0.05): ``lgvi@kahan-li8`` 1.4e-8, ``lgvi@kahan-li8-s15``
1.5e-7, ``lgvi@yoshida8`` 7.8e-4; ``lgvi@kahan-li6`` 1.2e-5 against ``lgvi@yoshida6`` 3.3e-4.

For a base of order 4 or 6 the same criterion, computed for that base order
(:func:`default_scheme`), picks ``suzuki6`` (``gl4@6``, ``galerkin4@6``: 52 against 1.9e4
for ``kahan-li6``) and ``suzuki8`` (``galerkin6@8``: 103 against 5.3e6 for ``kahan-li8``);
on a matrix problem with a known flow the errors at equal work differ by those ratios
(``tests/test_composition.py``).

References: M. Creutz, A. Gocksch, *Higher-order hybrid Monte Carlo algorithms*, Phys. Rev.
Lett. 63 (1989) 9–12; H. Yoshida, *Construction of higher order symplectic integrators*,
Phys. Lett. A 150 (1990) 262–268; M. Suzuki, *Fractal decomposition of exponential operators
with applications to many-body theories and Monte Carlo simulations*, Phys. Lett. A 146
(1990) 319–323; W. Kahan, R.-C. Li, *Composition constants for raising the orders of
unconventional schemes for ordinary differential equations*, Math. Comp. 66 (1997)
1089–1099; E. Hairer, C. Lubich, G. Wanner, *Geometric Numerical Integration*, 2nd ed.,
Springer 2006 (HLW), §II.4, §V.3.2.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable, Iterator, Mapping

from .base import AbstractIntegrator
from .composition import Composition
from .order_conditions import composition_order, error_constant

__all__ = [
    "DEFAULT_SCHEMES",
    "SCHEMES",
    "CompositionScheme",
    "MethodTable",
    "compose",
    "default_scheme",
    "parse_method",
    "resolve_method",
]


# ---------------------------------------------------------------------------------------
# Coefficient sets
# ---------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class CompositionScheme:
    """A named coefficient set: ``gammas`` (palindromic, summing to 1), the ``order`` it
    gives to a symmetric base method of order ``base_order``, and its source."""

    name: str
    order: int
    gammas: tuple[float, ...]
    source: str
    base_order: int = 2

    @property
    def stages(self) -> int:
        return len(self.gammas)


def _palindrome(half: tuple[float, ...], middle: float | None = None) -> tuple[float, ...]:
    """``half + (middle,) + reversed(half)``; ``middle`` defaults to ``1 - 2 sum(half)``."""
    mid = 1.0 - 2.0 * math.fsum(half) if middle is None else middle
    return (*half, mid, *reversed(half))


def _triple_jump(q: int) -> tuple[float, ...]:
    r"""Yoshida's triple jump raising a symmetric method of order ``q`` to ``q + 2``:
    :math:`\gamma_1 = \gamma_3 = 1/(2 - c)`, :math:`\gamma_2 = -c/(2 - c)`,
    :math:`c = 2^{1/(q+1)}`."""
    c = 2.0 ** (1.0 / (q + 1))
    return (1 / (2 - c), -c / (2 - c), 1 / (2 - c))


def _suzuki(q: int) -> tuple[float, ...]:
    r"""Suzuki's five-stage fractal raising order ``q`` to ``q + 2``:
    :math:`\gamma_{1,2,4,5} = 1/(4 - c)`, :math:`\gamma_3 = -c/(4 - c)`,
    :math:`c = 4^{1/(q+1)}`."""
    c = 4.0 ** (1.0 / (q + 1))
    return (1 / (4 - c), 1 / (4 - c), -c / (4 - c), 1 / (4 - c), 1 / (4 - c))

SCHEMES: dict[str, CompositionScheme] = {
    s.name: s
    for s in (
        CompositionScheme(
            "triple-jump", 4, _triple_jump(2),
            "Creutz & Gocksch 1989; Yoshida 1990; Suzuki 1990; HLW §II.4",
        ),
        CompositionScheme(
            "suzuki4", 4,
            _suzuki(2),
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
        # One level up from a higher-order symmetric base (``gl4``, ``galerkin4/6``): the
        # same constructions with the exponent 1/(q + 1) of the base order q.
        CompositionScheme("triple-jump6", 6, _triple_jump(4),
                          "Yoshida 1990; Suzuki 1990; HLW §II.4 (order-4 base)", base_order=4),
        CompositionScheme("suzuki6", 6, _suzuki(4),
                          "Suzuki 1990; HLW §II.4 (order-4 base)", base_order=4),
        CompositionScheme("triple-jump8", 8, _triple_jump(6),
                          "Yoshida 1990; Suzuki 1990; HLW §II.4 (order-6 base)", base_order=6),
        CompositionScheme("suzuki8", 8, _suzuki(6),
                          "Suzuki 1990; HLW §II.4 (order-6 base)", base_order=6),
    )
}

#: The scheme chosen for ``METHOD@ORDER`` of a second-order base (smallest error constant at
#: equal cost; module docstring); :func:`default_scheme` for any base order.
DEFAULT_SCHEMES: dict[int, str] = {4: "suzuki4", 6: "kahan-li6", 8: "kahan-li8"}


@functools.cache
def default_scheme(order: int, base_order: int = 2) -> str:
    r"""The scheme ``compose(base, order=order)`` uses for a symmetric base of order
    ``base_order``: among the stored schemes that give exactly ``order`` to such a base,
    the one with the smallest :math:`s^p\,\|E_{p+1}\|_2` (its leading error at equal work,
    computed for that base order: :func:`~lgvi_jax.integrators.order_conditions.error_constant`).
    For a second-order base this is :data:`DEFAULT_SCHEMES` (precomputed; a test checks
    it). Raises ``ValueError`` if ``order`` does not exceed ``base_order`` or no stored
    scheme gives it."""
    if order <= base_order:
        raise ValueError(f"default_scheme: order {order} does not exceed the base order "
                         f"{base_order}")
    if base_order == 2 and order in DEFAULT_SCHEMES:
        return DEFAULT_SCHEMES[order]
    cost = {n: s.stages**order * error_constant(s.gammas, base_order)
            for n, s in SCHEMES.items() if composition_order(s.gammas, base_order) == order}
    if not cost:
        raise ValueError(f"default_scheme: no stored scheme raises a base of order "
                         f"{base_order} to order {order}")
    return min(cost, key=cost.get)


# ---------------------------------------------------------------------------------------
# Construction by order or scheme, and the METHOD@SPEC syntax
# ---------------------------------------------------------------------------------------


def _scheme_list() -> str:
    return ", ".join(
        f"{n} (order {s.order}, {s.stages} stages"
        + ("" if s.base_order == 2 else f", for an order-{s.base_order} base") + ")"
        for n, s in SCHEMES.items())


def compose(base: AbstractIntegrator, order: int | None = None, *, scheme: str | None = None,
            warm_start: bool = True) -> Composition:
    """Compose ``base`` to the given ``order`` (4, 6 or 8; the scheme
    :func:`default_scheme` picks for the base's order) or with a named ``scheme`` (a key of
    :data:`SCHEMES`).

    Raises ``ValueError`` for an unknown order or scheme, a non-symmetric base, a base
    whose order is already at least the requested one, or a scheme that does not raise the
    base's order (one built for another base order).
    """
    if (order is None) == (scheme is None):
        raise ValueError("compose: give exactly one of order (4, 6, 8) or scheme "
                         f"({', '.join(SCHEMES)})")
    if order is not None and (isinstance(order, bool) or order not in DEFAULT_SCHEMES):
        raise ValueError(f"compose: order must be one of {sorted(DEFAULT_SCHEMES)}, got "
                         f"{order!r}")
    if scheme is not None and scheme not in SCHEMES:
        raise ValueError(f"compose: unknown scheme {scheme!r}; valid schemes: {_scheme_list()}")
    if not isinstance(base, AbstractIntegrator):
        raise ValueError(f"compose: base must be an integrator, got {base!r}")
    if not base.symmetric:
        raise ValueError(
            f"compose: {base.name} is not symmetric (Φ_{{-h}} ≠ Φ_h^{{-1}}); composition "
            "needs a symmetric base method (e.g. lgvi, hamel-cayley, hamel-exact, verlet, gl4)"
        )
    if order is not None:
        if base.order >= order:
            raise ValueError(f"compose: {base.name} already has order {base.order}; order "
                             f"{order} would not raise it")
        scheme = default_scheme(order, base.order)
    spec = SCHEMES[scheme]
    if base.order >= spec.order:
        raise ValueError(f"compose: {base.name} already has order {base.order}; scheme "
                         f"{scheme} (order {spec.order}) would not raise it")
    got = composition_order(spec.gammas, base.order)
    if got <= base.order:
        raise ValueError(f"compose: scheme {scheme} raises a base of order {spec.base_order} "
                         f"to order {spec.order}; {base.name} has order {base.order}, which it "
                         f"would not raise (order {got})")
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
