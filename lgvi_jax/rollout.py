"""The one rollout loop: guarded steps, folded by an observer.

Every loop of the package over a method's steps — :func:`lgvi_jax.simulate` (saved blocks),
:func:`lgvi_jax.final_state`, the sweeps' batched runs (running metrics), the stability
probe (stop at the first failure or energy blow-up), the work-precision runs — is
:func:`advance` on a :class:`Carry`:

* a **guarded step** takes one step of the method, threading its solver state (warm starts,
  chord matrices); its result code is the Newton solve's, or ``RESULTS.nonfinite`` when the
  new state is not finite. The first failure's code, step index and Newton residual are kept
  and from that step on the state is NaN, so a failed run is never mistaken for a good one;
  Newton iterations are summed (and their maximum kept) over the steps taken before it;
* an **observer** ``observe(acc, carry) -> acc`` folds what the caller keeps after each step
  (running maxima of the energy error, samples every K steps); ``until(carry, acc)`` stops a
  run early (``loop="while"``).

The loop is ``lax.scan`` for a static number of steps (reverse-mode differentiable; the
rollouts of :func:`~lgvi_jax.simulate`), ``lax.fori_loop`` for a run-time number (one
compilation for every length; forward mode only) or ``lax.while_loop`` with a stop test.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp

from . import _gc
from .trajectory import RESULTS

__all__ = ["Carry", "advance", "start"]


class Carry(eqx.Module):
    """The running state of a guarded rollout.

    Attributes:
        state: the model's state after ``k`` steps (NaN from the first failure on).
        solver_state: the method's solver state (``method.init_solver_state``).
        k: the number of steps taken (the index of the next step), ``int32``.
        result: the first failure's code, ``RESULTS.successful`` (0) while none.
        failed_step: the first failure's step index, -1 while none.
        failed_residual: the Newton residual (max-norm) the failed step reported.
        newton_steps: Newton iterations summed over the steps taken before the failure.
        newton_steps_max: the most iterations of one such step.
    """

    state: Any
    solver_state: Any
    k: jax.Array
    result: jax.Array
    failed_step: jax.Array
    failed_residual: jax.Array
    newton_steps: jax.Array
    newton_steps_max: jax.Array

    @property
    def ok(self) -> jax.Array:
        """True while no step has failed."""
        return self.result == RESULTS.successful

    def reset_counts(self) -> Carry:
        """The same carry with its Newton counters at zero (a new block of steps)."""
        zero = jnp.zeros_like(self.newton_steps)
        return eqx.tree_at(lambda c: (c.newton_steps, c.newton_steps_max), self, (zero, zero))


def start(model, method, state0, dt, k0: int | jax.Array = 0) -> Carry:
    """The carry before the first step (step index ``k0``)."""
    int0 = jnp.zeros((), jnp.int32)
    dtype = jnp.result_type(dt)
    return Carry(state=state0, solver_state=method.init_solver_state(model, state0, dt),
                 k=jnp.asarray(k0, jnp.int32), result=jnp.asarray(RESULTS.successful, jnp.int32),
                 failed_step=jnp.asarray(-1, jnp.int32), failed_residual=jnp.zeros((), dtype),
                 newton_steps=int0, newton_steps_max=int0)


def _all_finite(tree) -> jax.Array:
    leaves = jax.tree.leaves(tree)
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))


def _step(model, method, dt, c: Carry) -> Carry:
    """One guarded step (module docstring)."""
    new_state, info, solver_state = method.step_with(model, c.state, dt, c.solver_state)
    step_code = jnp.where(
        info.result != RESULTS.successful,
        info.result,
        jnp.where(_all_finite(new_state), RESULTS.successful, RESULTS.nonfinite),
    ).astype(jnp.int32)
    first_failure = c.ok & (step_code != RESULTS.successful)
    result = jnp.where(first_failure, step_code, c.result)
    failed = result != RESULTS.successful
    iters = jnp.where(c.ok, info.newton_steps, 0).astype(jnp.int32)
    return Carry(
        state=jax.tree.map(lambda x: jnp.where(failed, jnp.nan, x), new_state),
        solver_state=solver_state,
        k=c.k + 1,
        result=result,
        failed_step=jnp.where(first_failure, c.k, c.failed_step),
        failed_residual=jnp.where(first_failure, info.residual, c.failed_residual),
        newton_steps=c.newton_steps + iters,
        newton_steps_max=jnp.maximum(c.newton_steps_max, iters),
    )


@_gc.paused()  # while the loop is traced (lgvi_jax._gc)
def advance(model, method, dt, carry: Carry, n_steps: int | jax.Array,
            observe: Callable[[Any, Carry], Any] | None = None, acc: Any = None, *,
            loop: str = "fori",
            until: Callable[[Carry, Any], jax.Array] | None = None,
            batch_axes: Any = None) -> tuple[Carry, Any]:
    """``n_steps`` guarded steps of ``method`` from ``carry``, with ``acc = observe(acc,
    carry)`` after each; returns ``(carry, acc)``.

    ``loop``: ``"scan"`` (``n_steps`` a Python int; reverse-mode differentiable), ``"fori"``
    (``n_steps`` may be traced) or ``"while"`` (also stops before a step once ``until(carry,
    acc)`` is true).

    ``batch_axes``: for a batch, the axes of ``(carry, acc)`` along which their leaves hold
    its members (a ``vmap`` axes prefix; ``None`` for a leaf shared by all, such as a step
    index every member has in common). The step and ``observe`` are then written for one
    member and ``vmap``-ed inside the loop, so that the loop's body is traced once, batched;
    ``vmap`` of the whole loop traces it unbatched and batches that trace twice (JAX's
    rule for a loop: once to find its batched carries, once more to batch it). Not with
    ``loop="while"``.

    Python's garbage collector is paused while the loop is traced (:mod:`lgvi_jax._gc`).
    """
    def body(c_acc):
        c, a = c_acc
        c = _step(model, method, dt, c)
        return c, (a if observe is None else observe(a, c))

    if batch_axes is not None:
        if loop == "while":
            raise ValueError("advance: batch_axes is not supported with loop='while'")
        body = jax.vmap(body, in_axes=(batch_axes,), out_axes=batch_axes)

    if loop == "scan":
        (carry, acc), _ = jax.lax.scan(lambda ca, _: (body(ca), None), (carry, acc), None,
                                       length=n_steps)
        return carry, acc
    if loop == "fori":
        return jax.lax.fori_loop(jnp.zeros((), jnp.int32), jnp.asarray(n_steps, jnp.int32),
                                 lambda _, ca: body(ca), (carry, acc))
    if loop == "while":
        stop_at = carry.k + jnp.asarray(n_steps, jnp.int32)

        def go_on(ca):
            c, a = ca
            more = c.k < stop_at
            return more if until is None else more & ~until(c, a)

        return jax.lax.while_loop(go_on, body, (carry, acc))
    raise ValueError(f"advance: loop must be 'scan', 'fori' or 'while', got {loop!r}")
