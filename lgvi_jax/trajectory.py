"""What a rollout returns: :class:`Trajectory`, its result codes :class:`RESULTS` (shared
with the Newton solver, whose failures a rollout reports) and :class:`IntegrationError`.

Failure is a value: a rollout keeps its first failure — code, step and Newton residual —
and every later state is NaN; :meth:`Trajectory.raise_if_failed` turns it into an
exception naming the step, the time and the residual.
"""

from __future__ import annotations

import enum
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._checks import is_concrete

__all__ = ["RESULTS", "IntegrationError", "Trajectory"]


class RESULTS(enum.IntEnum):
    """Result codes of a solve (and of a rollout, which reports its first failure)."""

    successful = 0
    max_steps_reached = 1
    nonfinite = 2

    @property
    def message(self) -> str:
        return _MESSAGES[self]

    @classmethod
    def describe(cls, code: int) -> str:
        """Human-readable message for an integer result code."""
        try:
            return cls(int(code)).message
        except ValueError:
            return f"unknown result code {int(code)}"


_MESSAGES = {
    RESULTS.successful: "converged",
    RESULTS.max_steps_reached: "Newton's method did not converge within the iteration cap",
    RESULTS.nonfinite: "non-finite values (NaN or inf) in the state or the Newton iteration",
}


class IntegrationError(RuntimeError):
    """A rollout failed (Newton did not converge, or the state became non-finite)."""


class Trajectory(eqx.Module):
    """A saved trajectory: one row per saved state, the initial state first.

    Attributes:
        t: times, shape ``(n_saved,)``, ``t0 + i * save_every * dt``.
        state: the saved states (the model's state pytree with a leading axis ``n_saved``).
        invariants: ``dict`` name -> array with leading axis ``n_saved``; always has
            ``"energy"`` (also available as :attr:`energy`).
        newton_steps: Newton iterations summed over the steps leading to each saved state
            (0 for the initial state), ``(n_saved,)``.
        newton_steps_max: the most iterations of any single step in that block.
        result: ``int32`` code of the first failure, 0 (``RESULTS.successful``) if none.
        failed_step: index (0-based) of the first failed step, -1 if none.
        failed_residual: the Newton residual (max-norm) reported by the failed step.
        n_steps, save_every: the (static) length and saving stride.
        dt: the step.
    """

    t: jax.Array
    state: Any
    invariants: dict[str, jax.Array]
    newton_steps: jax.Array
    newton_steps_max: jax.Array
    result: jax.Array
    failed_step: jax.Array
    failed_residual: jax.Array
    dt: jax.Array
    n_steps: int = eqx.field(static=True)
    save_every: int = eqx.field(static=True)

    @property
    def energy(self) -> jax.Array:
        """The energy of each saved state, shape ``(..., n_saved)``."""
        return self.invariants["energy"]

    @property
    def ok(self) -> bool:
        """True if every step succeeded (concrete trajectories only)."""
        return bool(np.all(np.asarray(self.result) == RESULTS.successful))

    @property
    def message(self) -> str:
        """A human-readable account of the outcome (concrete, unbatched trajectories)."""
        code = int(np.max(np.asarray(self.result)))
        if code == RESULTS.successful:
            return f"all {self.n_steps} steps succeeded"
        k = int(np.asarray(self.failed_step))
        dt = float(np.asarray(self.dt))
        t_start = float(np.asarray(self.t[0])) + k * dt
        residual = float(np.asarray(self.failed_residual))
        # Explicit steps have no Newton residual (reported as 0): say nothing about it.
        detail = f"; Newton residual {residual:.3e}" if residual != 0 else ""
        return (
            f"step {k} (from t = {t_start:.6g} to t = {t_start + dt:.6g}) failed: "
            f"{RESULTS.describe(code)}{detail}. States from that step on are NaN."
        )

    @property
    def newton_mean(self) -> jax.Array:
        """Mean Newton iterations per step over the run."""
        return jnp.sum(self.newton_steps, axis=-1) / self.n_steps

    @property
    def newton_max(self) -> jax.Array:
        """Most Newton iterations taken by any single step."""
        return jnp.max(self.newton_steps_max, axis=-1)

    def raise_if_failed(self) -> Trajectory:
        """Raise :class:`IntegrationError` if any step failed; return ``self`` otherwise."""
        if not is_concrete(self.result):
            # Under jit only a fixed message is possible; attached to every output.
            return eqx.error_if(
                self, jnp.any(self.result != RESULTS.successful), "integration failed (throw=True)"
            )
        if np.ndim(self.result) != 0:
            bad = int(np.sum(np.asarray(self.result) != RESULTS.successful))
            if bad:
                raise IntegrationError(f"{bad} of {np.size(self.result)} trajectories failed")
            return self
        if not self.ok:
            raise IntegrationError(self.message)
        return self
