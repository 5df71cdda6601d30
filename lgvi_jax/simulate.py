r"""Rollouts: ``simulate(model, method, state0, dt, n_steps, save_every=1)``.

A rollout is a pure, ``jit``-compiled function built from two nested ``lax.scan`` loops: the
inner one takes ``save_every`` steps, the outer one records the state, the energy and the
model's invariants after each block. Memory therefore grows with the number of *saved*
states only, and a 10^6-step run saving every 1000th state stores 1001 states.

Failure is a value. Every step reports a result code (the Newton solve's, or
:attr:`~lgvi_jax.newton.RESULTS.nonfinite` if the new state is not finite). The rollout keeps
the first failure — its code, step index and residual — and from that step on the states are
NaN, so a failed run can never be mistaken for a good one. ``throw=True`` turns a failure
into an :class:`IntegrationError` naming the step, the time and the residual.

``model``, ``method`` and ``state0`` are pytrees and ``dt`` is a traced scalar, so the
rollout can be differentiated (``jax.grad``, ``jax.jvp``) and batched (``jax.vmap``) with
respect to parameters, initial state and step without recompiling; only ``n_steps``,
``save_every`` and ``checkpoint_every`` are compile-time constants.

**Memory of reverse mode.** ``jax.grad`` of a plain rollout stores the residuals of every
step (the linearisation points of the Newton solves and of the step maps), so its memory
grows like ``n_steps``. With ``checkpoint_every=K`` the rollout is a scan over ``n_steps/K``
segments of ``K`` steps, each wrapped in ``jax.checkpoint``: the backward pass keeps only
the state at the start of each segment and recomputes one segment's steps at a time, so
memory grows like ``n_steps/K + K`` (optimal near ``K = sqrt(n_steps)``) at the price of a
second forward pass (binomial checkpointing with one level; Griewank & Walther,
*Evaluating Derivatives*, SIAM 2008, ch. 12). The values are identical. The second
forward pass need not solve the implicit steps again: their Newton solutions (named
``newton.SOLUTION_NAME`` in the solver's differentiation rule) are kept from the first
pass by a ``jax.checkpoint`` policy, a few numbers per step (``save_solutions=False``
turns it off); the backward pass then only forms each step's Jacobian at its solution.
``experiments/bench_gradients.py`` measures it.
"""

from __future__ import annotations

import functools
import time
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._checks import is_concrete
from .integrators.base import AbstractIntegrator
from .newton import SOLUTION_NAME
from .rollout import advance, start
from .trajectory import IntegrationError, Trajectory

__all__ = ["IntegrationError", "Trajectory", "final_state", "simulate", "simulate_timed"]


def _record(model, state):
    return state, model.invariants(state)


@eqx.filter_jit
def _rollout(model, method, state0, dt, t0, n_steps: int, save_every: int,
             checkpoint_every: int | None = None, save_solutions: bool = True) -> Trajectory:
    n_blocks = n_steps // save_every

    def one_block(carry, _):
        carry, _ = advance(model, method, dt, carry.reset_counts(), save_every, loop="scan")
        saved = (*_record(model, carry.state), carry.newton_steps, carry.newton_steps_max)
        return carry, saved

    init = start(model, method, state0, dt)
    if checkpoint_every is None:
        end, saved = jax.lax.scan(one_block, init, None, length=n_blocks)
    else:
        blocks_per_segment = checkpoint_every // save_every

        # The solves' outputs, named in their differentiation rules, are kept (a few
        # numbers per step) so that the backward pass recomputes the steps but not their
        # Newton iterations.
        policy = (jax.checkpoint_policies.save_only_these_names(SOLUTION_NAME)
                  if save_solutions else None)

        @functools.partial(jax.checkpoint, prevent_cse=False, policy=policy)
        def one_segment(carry, _):
            return jax.lax.scan(one_block, carry, None, length=blocks_per_segment)

        end, saved = jax.lax.scan(one_segment, init, None,
                                  length=n_steps // checkpoint_every)
        saved = jax.tree.map(lambda x: x.reshape((n_blocks, *x.shape[2:])), saved)
    int0 = jnp.zeros((), jnp.int32)
    first = (*_record(model, state0), int0, int0)

    def prepend(x0, xs):
        return jnp.concatenate([jnp.asarray(x0)[None], xs], axis=0)

    states, inv, it_sum, it_max = jax.tree.map(prepend, first, saved)
    t = t0 + dt * save_every * jnp.arange(n_blocks + 1, dtype=dt.dtype)
    return Trajectory(
        t=t,
        state=states,
        invariants=inv,
        newton_steps=it_sum,
        newton_steps_max=it_max,
        result=end.result,
        failed_step=end.failed_step,
        failed_residual=end.failed_residual,
        dt=dt,
        n_steps=n_steps,
        save_every=save_every,
    )


def _check_int(name: str, value: Any, minimum: int = 1) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"simulate: {name} must be an integer >= {minimum}, got {value!r}")


def _check_checkpoint(checkpoint_every, n_steps: int, save_every: int) -> int | None:
    if checkpoint_every is None:
        return None
    _check_int("checkpoint_every", checkpoint_every)
    if checkpoint_every % save_every or n_steps % checkpoint_every:
        raise ValueError(
            f"simulate: checkpoint_every ({checkpoint_every}) must be a multiple of "
            f"save_every ({save_every}) and divide n_steps ({n_steps})"
        )
    return int(checkpoint_every)


def _prepare(model, method, state0, dt, n_steps, save_every, t0):
    """Validate the arguments of :func:`simulate`; return the rollout's arguments."""
    if not isinstance(method, AbstractIntegrator):
        raise ValueError(
            f"simulate: method must be an integrator (AbstractIntegrator), got {method!r}"
        )
    _check_int("n_steps", n_steps)
    _check_int("save_every", save_every)
    if n_steps % save_every:
        raise ValueError(f"simulate: save_every ({save_every}) must divide n_steps ({n_steps})")
    if jnp.ndim(dt) != 0:
        raise ValueError(f"simulate: dt must be a scalar, got shape {jnp.shape(dt)}")
    if is_concrete(dt):
        dt_value = float(np.asarray(dt))
        if not np.isfinite(dt_value) or dt_value == 0.0:
            raise ValueError(f"simulate: dt must be finite and non-zero, got {dt_value!r}")
    if hasattr(model, "check_state"):
        model.check_state(state0)
    method.check_model(model)
    dt = jnp.asarray(dt, dtype=jnp.float64)
    t0 = jnp.asarray(t0, dtype=jnp.float64)
    return model, method, state0, dt, t0, int(n_steps), int(save_every)


def simulate(
    model: Any,
    method: AbstractIntegrator,
    state0: Any,
    dt: float | jax.Array,
    n_steps: int,
    *,
    save_every: int = 1,
    t0: float | jax.Array = 0.0,
    throw: bool = False,
    checkpoint_every: int | None = None,
    save_solutions: bool = True,
) -> Trajectory:
    """Integrate ``model`` with ``method`` for ``n_steps`` steps of size ``dt``.

    Args:
        model: the system (e.g. :class:`~lgvi_jax.models.HarmonicOscillator`); its fields are
            the parameters, differentiable and batchable.
        method: a one-step method (:class:`~lgvi_jax.integrators.AbstractIntegrator`).
        state0: the initial state, float64 (e.g. ``model.state(...)``, or
            ``model.default_state()``).
        dt: the step; non-zero and finite. A negative step integrates backwards in time.
        n_steps: number of steps (static: one compilation per value).
        save_every: keep every ``save_every``-th state; must divide ``n_steps``.
        t0: the initial time.
        throw: raise :class:`IntegrationError` (naming the step and residual) on failure,
            instead of only reporting it in ``Trajectory.result``.
        checkpoint_every: if set, reverse-mode differentiation stores the state only every
            ``checkpoint_every`` steps and recomputes in between (module docstring): memory
            ``~ n_steps/K + K`` instead of ``~ n_steps``. A multiple of ``save_every`` that
            divides ``n_steps``. No effect on the values or on forward mode.
        save_solutions: with ``checkpoint_every``, also keep every step's Newton solution
            and result code (the implicit methods' unknowns: 5 numbers per step for the
            car-pendulum, against 16 for its state), so that the backward pass recomputes
            the steps without solving them again (module docstring). ``False``: memory
            ``~ n_steps/K + K`` states exactly.

    Returns:
        A :class:`Trajectory` with ``n_steps // save_every + 1`` saved states.

    Raises:
        ValueError: naming the argument, for invalid input.
        IntegrationError: with ``throw=True``, if a step fails.
    """
    args = _prepare(model, method, state0, dt, n_steps, save_every, t0)
    checkpoint_every = _check_checkpoint(checkpoint_every, args[5], args[6])
    traj = _rollout(*args, checkpoint_every=checkpoint_every,
                    save_solutions=bool(save_solutions))
    if throw:
        traj = traj.raise_if_failed()
    return traj


def simulate_timed(
    model: Any,
    method: AbstractIntegrator,
    state0: Any,
    dt: float | jax.Array,
    n_steps: int,
    *,
    save_every: int = 1,
    t0: float | jax.Array = 0.0,
) -> tuple[Trajectory, dict[str, float]]:
    """:func:`simulate`, with compilation and execution timed separately.

    Returns the trajectory and ``{"compile_s", "run_s", "steps_per_second"}``, where the run
    time excludes compilation (ahead-of-time ``lower().compile()``) and waits for the result.
    """
    args = _prepare(model, method, state0, dt, n_steps, save_every, t0)
    start = time.perf_counter()
    compiled = _rollout.lower(*args).compile()
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    traj = jax.block_until_ready(compiled(*args))
    run_s = time.perf_counter() - start
    return traj, {
        "compile_s": compile_s,
        "run_s": run_s,
        "steps_per_second": n_steps / run_s if run_s > 0 else float("inf"),
    }


@eqx.filter_jit
def _final_state(model, method, state0, dt, n_steps):
    end, _ = advance(model, method, dt, start(model, method, state0, dt), n_steps)
    return end.state, end.result


def final_state(
    model: Any, method: AbstractIntegrator, state0: Any, dt: float | jax.Array, n_steps: int
) -> tuple[Any, jax.Array]:
    """The state after ``n_steps`` steps of ``dt``, and the result code.

    Unlike :func:`simulate`, ``n_steps`` is a run-time value here (a ``while`` loop), so a
    convergence study over many step sizes compiles once per method. The price: no saved
    states, no statistics, and no reverse-mode differentiation (``while`` loops only support
    forward mode); use :func:`simulate` for those. A failed step gives a NaN state and a
    non-zero code, as in :func:`simulate`.
    """
    model, method, state0, dt, _, n, _ = _prepare(model, method, state0, dt, n_steps, 1, 0.0)
    return _final_state(model, method, state0, dt, jnp.asarray(n, jnp.int32))
