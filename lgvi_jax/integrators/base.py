"""The one integrator interface shared by every method of the library.

An integrator is an immutable ``eqx.Module`` whose fields are its hyperparameters (for
example its Newton settings). It advances a model's state by one step ``dt``::

    new_state, info = method.step(model, state, dt)

A rollout also threads what a method carries from one step to the next (diffrax's
``solver_state``)::

    solver_state = method.init_solver_state(model, state, dt)
    new_state, info, solver_state = method.step_with(model, state, dt, solver_state)

(the implicit Lie-group VIs keep their last solutions there, to start Newton from their
extrapolation). The solution of a step does not depend on it, only the iterates do.

``dt`` may be negative (integration backwards in time, used to check time reversibility).
Each method declares its ``order`` (of the global error), and whether it is ``symmetric``
(``Φ_{-h} = Φ_h^{-1}``), ``symplectic`` and ``implicit``.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ..newton import NewtonSolution
from ..trajectory import RESULTS


class StepInfo(eqx.Module):
    """What one step reports: Newton iterations, result code, final residual (max-norm)."""

    newton_steps: jax.Array
    result: jax.Array
    residual: jax.Array

    @classmethod
    def explicit(cls) -> StepInfo:
        """Info of an explicit step: no iterations, success (finiteness is checked by the
        rollout)."""
        return cls(
            newton_steps=jnp.asarray(0, jnp.int32),
            result=jnp.asarray(RESULTS.successful, jnp.int32),
            residual=jnp.asarray(0.0),
        )

    @classmethod
    def from_solution(cls, sol: NewtonSolution) -> StepInfo:
        return cls(newton_steps=sol.newton_steps, result=sol.result, residual=sol.residual)


class AbstractIntegrator(eqx.Module):
    """Base class of all one-step methods.

    Subclasses provide ``name``, ``order``, ``symmetric``, ``symplectic``, ``implicit`` (as
    class attributes or properties) and :meth:`step`.
    """

    # Declared here, defined by each method as class attributes (or properties when they
    # depend on a hyperparameter, e.g. the number of stages).
    name: ClassVar[str]
    order: ClassVar[int]
    symmetric: ClassVar[bool]
    symplectic: ClassVar[bool]
    implicit: ClassVar[bool]

    @abc.abstractmethod
    def step(self, model: Any, state: Any, dt: jax.Array) -> tuple[Any, StepInfo]:
        """Advance ``state`` of ``model`` by one step ``dt``."""

    def init_solver_state(self, model: Any, state: Any, dt: jax.Array) -> Any:
        """What the method carries between the steps of a rollout of step ``dt`` that starts
        at ``state``; ``None`` (the default) for methods that carry nothing."""
        return None

    def step_with(self, model: Any, state: Any, dt: jax.Array,
                  solver_state: Any) -> tuple[Any, StepInfo, Any]:
        """:meth:`step` with the solver state of :meth:`init_solver_state` (or of the
        previous step); returns ``(new_state, info, new_solver_state)``."""
        new_state, info = self.step(model, state, dt)
        return new_state, info, solver_state

    def check_model(self, model: Any) -> None:
        """Raise ``ValueError`` if this method cannot integrate ``model``."""

    def describe(self) -> str:
        traits = [
            f"order {self.order}",
            "symmetric" if self.symmetric else "not symmetric",
            "symplectic" if self.symplectic else "not symplectic",
            "implicit" if self.implicit else "explicit",
        ]
        return f"{self.name} ({', '.join(traits)})"
