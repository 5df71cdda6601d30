r"""Models on a Euclidean configuration space :math:`\mathbb{R}^n`.

A model is an ``eqx.Module`` whose fields are its physical parameters, and only those: the
initial state belongs to the problem, built by the model's ``state(...)`` from initial
positions and momenta or velocities (``default_state()`` is ``state()`` with the model's
default initial condition). A model defines only its energies, ``kinetic(q, v)`` and
``potential(q)``, ``state`` and (optionally) extra invariants; the mechanics the integrators
need is derived here by autodiff:

.. math::
    L(q, v) = T(q, v) - U(q), \qquad p = \partial L / \partial v, \qquad
    H(q, p) = p^\top v - L(q, v), \qquad \dot q = v(q, p), \quad \dot p = \partial L/\partial q.

The kinetic energy must be a quadratic polynomial in the velocity (true of every mechanical
system, including gyroscopic couplings linear in ``v``): then the Legendre map is inverted
exactly by one Newton step from ``v = 0``, ``v = M(q)^{-1}(p - \partial L/\partial v(q, 0))``
with ``M = \partial^2 L/\partial v^2``.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from .._checks import check_float64_finite
from ..linalg import small_solve


def reject_removed_keywords(owner: str, kwargs: dict, initial_conditions: tuple[str, ...]
                            ) -> None:
    """Refuse keywords a model's constructor no longer takes: an initial condition (now an
    argument of ``model.state``) with a ``TypeError`` that says where it goes, anything else
    with Python's usual message."""
    for name in kwargs:
        if name in initial_conditions:
            raise TypeError(
                f"{owner}: {name} is an initial condition, not a parameter: pass it to "
                f"model.state({name}=...)"
            )
    if kwargs:
        raise TypeError(
            f"{owner}.__init__() got an unexpected keyword argument {next(iter(kwargs))!r}"
        )


class PhaseState(eqx.Module):
    """A point of phase space: generalised positions ``q`` and canonical momenta ``p``,
    each of shape ``(n,)`` (with leading batch/time axes in trajectories)."""

    q: jax.Array
    p: jax.Array


class AbstractEuclideanModel(eqx.Module):
    """A Lagrangian system on :math:`\\mathbb{R}^n` defined by its energies.

    Subclasses set ``dof`` and ``separable`` (kinetic energy independent of ``q``, which
    explicit splitting methods such as Störmer–Verlet require) and implement
    :meth:`kinetic`, :meth:`potential` and :meth:`state`. The fields are the physical
    parameters only: the initial condition is an argument of :meth:`state`, not part of
    the model.
    """

    dof: ClassVar[int]
    separable: ClassVar[bool]

    @abc.abstractmethod
    def kinetic(self, q: jax.Array, v: jax.Array) -> jax.Array:
        """Kinetic energy ``T(q, v)`` (quadratic in ``v``)."""

    @abc.abstractmethod
    def potential(self, q: jax.Array) -> jax.Array:
        """Potential energy ``U(q)``."""

    @abc.abstractmethod
    def state(self, *args, **kwargs) -> PhaseState:
        """The initial state built from the model's initial-condition arguments (each
        defaulting to the model's default initial condition), validated on concrete values;
        usable under ``jit``/``vmap``/``grad``."""

    def default_state(self) -> PhaseState:
        """Convenience: ``self.state()``, the model's default initial condition (the
        paper's, where there is one)."""
        return self.state()

    # --- mechanics derived by autodiff -------------------------------------------------

    def lagrangian(self, q: jax.Array, v: jax.Array) -> jax.Array:
        """``L(q, v) = T(q, v) − U(q)``."""
        return self.kinetic(q, v) - self.potential(q)

    def momentum(self, q: jax.Array, v: jax.Array) -> jax.Array:
        """Legendre transform ``p = ∂L/∂v(q, v)``."""
        return jax.grad(self.lagrangian, argnums=1)(q, v)

    def velocity(self, q: jax.Array, p: jax.Array) -> jax.Array:
        """Inverse Legendre transform ``v(q, p)`` (exact for T quadratic in v)."""
        zero = jnp.zeros_like(q)
        p_at_rest = self.momentum(q, zero)
        mass = jax.jacfwd(self.momentum, argnums=1)(q, zero)
        return small_solve(mass, p - p_at_rest)

    def force(self, q: jax.Array, v: jax.Array) -> jax.Array:
        """``∂L/∂q(q, v)``: the time derivative of ``p`` along solutions."""
        return jax.grad(self.lagrangian, argnums=0)(q, v)

    def energy(self, state: PhaseState) -> jax.Array:
        """Hamiltonian ``H(q, p) = pᵀv − L(q, v)`` with ``v = v(q, p)``."""
        v = self.velocity(state.q, state.p)
        return jnp.dot(state.p, v) - self.lagrangian(state.q, v)

    def vector_field(self, state: PhaseState) -> PhaseState:
        """Hamilton's equations ``(q̇, ṗ) = (v(q, p), ∂L/∂q(q, v(q, p)))``."""
        v = self.velocity(state.q, state.p)
        return PhaseState(q=v, p=self.force(state.q, v))

    def invariants(self, state: PhaseState) -> dict[str, jax.Array]:
        """Quantities conserved by the exact flow, by name (at least ``energy``)."""
        return {"energy": self.energy(state)}

    def check_state(self, state: PhaseState, name: str = "state0") -> None:
        """Validate a concrete state: shapes ``(dof,)``, float64, finite."""
        owner = type(self).__name__
        if not isinstance(state, PhaseState):
            raise ValueError(f"{owner}: {name} must be a PhaseState, got {type(state).__name__}")
        for field in ("q", "p"):
            shape = jnp.shape(getattr(state, field))
            if shape != (self.dof,):
                raise ValueError(
                    f"{owner}: {name}.{field} must have shape ({self.dof},), got {shape}"
                )
        check_float64_finite(name, state, owner)
