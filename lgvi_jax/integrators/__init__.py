"""Integrators: one interface (:class:`AbstractIntegrator`), one file per method."""

from collections.abc import Callable

from .base import AbstractIntegrator, StepInfo
from .galerkin import GalerkinVI
from .gauss_legendre import GaussLegendre
from .rk4 import RK4
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

__all__ = [
    "EUCLIDEAN_METHODS",
    "RK4",
    "AbstractIntegrator",
    "GalerkinVI",
    "GaussLegendre",
    "StepInfo",
    "StormerVerlet",
]
