"""Integrators: one interface (:class:`AbstractIntegrator`), one file per method."""

from collections.abc import Callable

from ..options import ChordMatrix, HamelMap, Variation
from .base import AbstractIntegrator, StepInfo
from .composition import Composition
from .galerkin import GalerkinVI
from .gauss_legendre import GaussLegendre
from .lie import LGVI, AbstractLieVI, HamelVI
from .lie_galerkin import LieGalerkinVI
from .lie_rk import RKMK4
from .rk4 import RK4
from .schemes import (
    DEFAULT_SCHEMES,
    SCHEMES,
    CompositionScheme,
    MethodTable,
    compose,
    default_scheme,
    parse_method,
    resolve_method,
)
from .solver_settings import with_chord_matrix, with_scalar_newton
from .verlet import StormerVerlet

#: Methods for models on R^n, by the name the CLI and the experiments use.
EUCLIDEAN_METHODS: dict[str, Callable[[], AbstractIntegrator]] = {
    "rk4": RK4,
    "gl4": lambda: GaussLegendre(stages=2),
    "gl6": lambda: GaussLegendre(stages=3),
    "verlet": StormerVerlet,
    "galerkin4": lambda: GalerkinVI(degree=2),
    "galerkin6": lambda: GalerkinVI(degree=3),
}

#: Methods for models on SO(3) x R^n. The first five are the paper's and the issue's;
#: ``rk4`` and ``gl4`` integrate the continuous equations with R embedded as 9 numbers;
#: ``rkmk4`` is the explicit Lie-group Runge–Kutta–Munthe-Kaas method (R on SO(3));
#: ``galerkin4/6/8`` the Lie-group Galerkin variational integrators of order 4, 6, 8.
#: Every symmetric method also exists composed to order 4, 6 or 8: ``resolve_method``
#: accepts ``METHOD@ORDER`` and ``METHOD@SCHEME`` (``lgvi@6``, ``lgvi@kahan-li8``).
RIGID_METHODS: dict[str, Callable[[], AbstractIntegrator]] = {
    "lgvi": LGVI,
    "hamel": lambda: HamelVI(map=HamelMap.EXP, variation=Variation.PAPER),
    "hamel-cayley": lambda: HamelVI(map=HamelMap.CAYLEY, variation=Variation.PAPER),
    "hamel-exact": lambda: HamelVI(map=HamelMap.EXP, variation=Variation.EXACT),
    "rk4": RK4,
    "hamel-cayley-exact": lambda: HamelVI(map=HamelMap.CAYLEY, variation=Variation.EXACT),
    "gl4": lambda: GaussLegendre(stages=2),
    "rkmk4": RKMK4,
    "galerkin4": lambda: LieGalerkinVI(degree=2),
    "galerkin6": lambda: LieGalerkinVI(degree=3),
    "galerkin8": lambda: LieGalerkinVI(degree=4),
}

__all__ = [
    "DEFAULT_SCHEMES",
    "EUCLIDEAN_METHODS",
    "LGVI",
    "RIGID_METHODS",
    "RK4",
    "RKMK4",
    "SCHEMES",
    "AbstractIntegrator",
    "AbstractLieVI",
    "ChordMatrix",
    "Composition",
    "CompositionScheme",
    "GalerkinVI",
    "GaussLegendre",
    "HamelMap",
    "HamelVI",
    "LieGalerkinVI",
    "MethodTable",
    "StepInfo",
    "StormerVerlet",
    "Variation",
    "compose",
    "default_scheme",
    "parse_method",
    "resolve_method",
    "with_chord_matrix",
    "with_scalar_newton",
]
