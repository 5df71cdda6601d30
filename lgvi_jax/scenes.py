"""Scenes: a model, its settable parameters, its methods and its output arrays, by name.

This is the table behind ``lgvi-jax simulate SYSTEM ...``. The library itself never parses
strings: the CLI turns ``--set NAME=V1,V2`` into float arrays and hands them to
:meth:`Scene.build`, which validates them and returns ``(model, state0)``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from .integrators import EUCLIDEAN_METHODS, AbstractIntegrator
from .models import HarmonicOscillator

__all__ = ["SCENES", "Parameter", "Scene", "get_scene"]


@dataclasses.dataclass(frozen=True)
class Parameter:
    """A settable quantity of a scene: ``size`` numbers, with a default and a description."""

    name: str
    size: int
    default: tuple[float, ...]
    doc: str


@dataclasses.dataclass(frozen=True)
class Scene:
    """A named system: how to build it, which methods apply, what a run saves."""

    name: str
    description: str
    parameters: tuple[Parameter, ...]
    methods: Mapping[str, Callable[[], AbstractIntegrator]]
    make: Callable[[dict[str, np.ndarray]], tuple[Any, Any]]
    arrays: Callable[[Any], dict[str, np.ndarray]]

    def parameter(self, name: str) -> Parameter:
        for p in self.parameters:
            if p.name == name:
                return p
        valid = ", ".join(p.name for p in self.parameters)
        raise ValueError(f"{self.name}: unknown parameter {name!r}; valid names: {valid}")

    def method(self, name: str) -> AbstractIntegrator:
        if name not in self.methods:
            valid = ", ".join(self.methods)
            raise ValueError(f"{self.name}: unknown method {name!r}; valid methods: {valid}")
        return self.methods[name]()

    def build(self, overrides: Mapping[str, Any] | None = None) -> tuple[Any, Any]:
        """Return ``(model, state0)`` with the defaults replaced by ``overrides``.

        Raises ``ValueError`` naming the parameter for an unknown name, a wrong number of
        values, or a non-finite value; the model's own checks (e.g. ``m > 0``) follow.
        """
        values = {p.name: np.asarray(p.default, dtype=np.float64) for p in self.parameters}
        for name, value in (overrides or {}).items():
            p = self.parameter(name)
            arr = np.atleast_1d(np.asarray(value, dtype=np.float64))
            if arr.shape != (p.size,):
                raise ValueError(
                    f"{self.name}: {name} takes {p.size} number(s), got {arr.size}"
                )
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{self.name}: {name} must be finite, got {arr.tolist()}")
            values[name] = arr
        return self.make(values)


def _oscillator_make(values):
    model = HarmonicOscillator(
        m=values["m"][0], k=values["k"][0], q0=values["q0"][0], p0=values["p0"][0]
    )
    return model, model.default_state()


def _oscillator_arrays(traj) -> dict[str, np.ndarray]:
    return {
        "t": np.asarray(traj.t),
        "q": np.asarray(traj.state.q)[:, 0],
        "p": np.asarray(traj.state.p)[:, 0],
        "energy": np.asarray(traj.energy),
    }


SCENES: dict[str, Scene] = {
    "oscillator": Scene(
        name="oscillator",
        description="1D harmonic oscillator H = p^2/(2m) + k q^2/2 (paper, section 1)",
        parameters=(
            Parameter("m", 1, (1.0,), "mass (> 0)"),
            Parameter("k", 1, (1.0,), "spring stiffness (> 0)"),
            Parameter("q0", 1, (1.0,), "initial position"),
            Parameter("p0", 1, (0.0,), "initial momentum"),
        ),
        methods={k: EUCLIDEAN_METHODS[k] for k in ("rk4", "gl4", "verlet", "galerkin4",
                                                     "gl6", "galerkin6")},
        make=_oscillator_make,
        arrays=_oscillator_arrays,
    ),
}


def get_scene(name: str) -> Scene:
    """The scene called ``name`` (``ValueError`` listing the valid names otherwise)."""
    if name not in SCENES:
        raise ValueError(f"unknown system {name!r}; valid systems: {', '.join(SCENES)}")
    return SCENES[name]
