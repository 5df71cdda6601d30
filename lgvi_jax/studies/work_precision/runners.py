"""The timed runs of the work-precision study: ours (through :mod:`lgvi_jax.rollout`),
diffrax (optional) and SciPy's ``solve_ivp``, each saving its state at the same equally
spaced times; the timing (best of a few runs, after compilation) and the cache of compiled
functions. A run returns the raw saved states: :mod:`.metrics` measures them.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import lgvi_jax
from lgvi_jax import rollout

from .cases import Case

try:  # optional peer (the ``bench`` extra)
    import diffrax
except ImportError:  # pragma: no cover - depends on the environment
    diffrax = None

#: Saved states per run (the buffer of our rollout; run-time count up to this).
MAX_SAVES = 500
#: Timed runs of a cheap configuration (the best is kept; see :func:`_time_best`).
REPEATS = 3
DIFFRAX_MAX_STEPS = 10**7


# ----------------------------------------------------------------------- our rollout


@eqx.filter_jit
def _rollout(model, method, state0, h, steps_per_save, n_saves):
    """``n_saves * steps_per_save`` steps of ``h`` (both run-time: one compilation per
    method and model structure), the state saved after every ``steps_per_save`` steps into a
    buffer of ``MAX_SAVES + 1`` rows (row 0: the initial state; unused rows NaN). Failure
    bookkeeping is :mod:`lgvi_jax.rollout`'s: first failure's code and step,
    NaN states from there on."""
    buf = jax.tree.map(
        lambda x: jnp.full((MAX_SAVES + 1, *jnp.shape(x)), jnp.nan, x.dtype).at[0].set(x),
        state0)

    def block(i, carry_buf):
        carry, buf = carry_buf
        carry, _ = rollout.advance(model, method, h, carry, steps_per_save)
        return carry, jax.tree.map(lambda b, x: b.at[i + 1].set(x), buf, carry.state)

    end, buf = jax.lax.fori_loop(0, n_saves, block,
                                 (rollout.start(model, method, state0, h), buf))
    return buf, end.result, end.failed_step


_COMPILED: dict[Any, Any] = {}


def _time_best(call: Callable, repeats: int, budget_s: float = 1.0):
    """Run ``call`` (which blocks until its result is ready) up to ``repeats`` times while
    the total stays under ``budget_s``; return ``(result, best wall time, runs)``."""
    times, out = [], None
    for _ in range(max(1, repeats)):
        start = time.perf_counter()
        out = call()
        times.append(time.perf_counter() - start)
        if sum(times) > budget_s:
            break
    return out, min(times), len(times)


def _grid(T: float, n_saves: int, h: float | None = None) -> tuple[np.ndarray, int]:
    """Save times and, for a fixed step ``h``, the steps per save (which must be whole)."""
    interval = T / n_saves
    t = np.linspace(0.0, T, n_saves + 1)
    if h is None:
        return t, 0
    k = round(interval / h)
    if k < 1 or abs(k * h - interval) > 1e-9 * interval:
        raise ValueError(f"step h = {h} does not divide the save interval {interval} "
                         f"(horizon {T}, {n_saves} saves)")
    return t, k


def run_ours(system: Case, name: str, method, h: float, T: float, n_saves: int,
             repeats: int = REPEATS) -> dict:
    """One timed run of our ``method`` at step ``h`` over ``[0, T]``; returns the raw run
    (saved times and states, wall time, compile time, result)."""
    t, k = _grid(T, n_saves, h)
    args = (system.model, method, system.state0, jnp.float64(h), jnp.int32(k),
            jnp.int32(n_saves))
    key = ("ours", name, system.system_name)
    compile_s = 0.0
    if key not in _COMPILED:
        start = time.perf_counter()
        _COMPILED[key] = _rollout.lower(*args).compile()
        compile_s = time.perf_counter() - start
    fn = _COMPILED[key]
    (buf, code, failed_step), wall, runs = _time_best(
        lambda: jax.block_until_ready(fn(*args)), repeats)
    states = jax.tree.map(lambda x: x[: n_saves + 1], buf)
    code = int(code)
    message = "ok" if code == 0 else (
        f"failed at step {int(failed_step)}: {lgvi_jax.RESULTS.describe(code)}")
    return {"family": "ours", "method": name, "param": "h", "value": h, "t": t,
            "states": states, "wall_s": wall, "runs": runs, "compile_s": compile_s,
            "n_steps": k * n_saves, "result": code, "message": message}


# --------------------------------------------------------------------------- diffrax


def _diffrax_solver(name: str):
    return {"tsit5": diffrax.Tsit5, "dopri8": diffrax.Dopri8}[name]()


@functools.cache
def _diffrax_fn(solver: str, adaptive: bool, batched: bool = False):
    """A jitted ``solve(model, y0, ts, x)``: ``x`` is ``rtol = atol`` (adaptive) or the
    fixed step. Returns the states at ``ts``, success flag and accepted steps."""
    term = diffrax.ODETerm(lambda t, y, model: model.vector_field(y))

    def solve(model, y0, ts, x):
        if adaptive:
            controller, dt0 = diffrax.PIDController(rtol=x, atol=x), None
        else:
            controller, dt0 = diffrax.ConstantStepSize(), x
        sol = diffrax.diffeqsolve(
            term, _diffrax_solver(solver), ts[0], ts[-1], dt0, y0, model,
            saveat=diffrax.SaveAt(ts=ts), stepsize_controller=controller,
            max_steps=DIFFRAX_MAX_STEPS, throw=False)
        return sol.ys, sol.result == diffrax.RESULTS.successful, sol.stats["num_steps"]

    if batched:
        return jax.jit(jax.vmap(solve, in_axes=(None, 0, None, None)))
    return jax.jit(solve)


def run_diffrax(system: Case, solver: str, adaptive: bool, x: float, T: float,
                n_saves: int, repeats: int = REPEATS) -> dict:
    """One timed diffrax run: ``x`` = ``rtol = atol`` (adaptive) or the fixed step."""
    t = np.linspace(0.0, T, n_saves + 1)
    args = (system.model, system.state0, jnp.asarray(t), jnp.float64(x))
    fn = _diffrax_fn(solver, adaptive)
    key = ("diffrax", solver, adaptive, system.system_name, n_saves)
    compile_s = 0.0
    if key not in _COMPILED:
        start = time.perf_counter()
        _COMPILED[key] = fn.lower(*args).compile()
        compile_s = time.perf_counter() - start
    (ys, ok, nsteps), wall, runs = _time_best(
        lambda: jax.block_until_ready(_COMPILED[key](*args)), repeats)
    ok = bool(ok)
    label = f"diffrax {solver}" + ("" if adaptive else " fixed")
    return {"family": "diffrax", "method": label, "param": "rtol" if adaptive else "h",
            "value": x, "t": t, "states": ys, "wall_s": wall, "runs": runs,
            "compile_s": compile_s, "n_steps": int(nsteps), "result": 0 if ok else 1,
            "message": "ok" if ok else "diffrax did not succeed (max_steps or step failure)"}


# ----------------------------------------------------------------------------- SciPy


def run_scipy(system: Case, solver: str, tol: float, T: float, n_saves: int,
              repeats: int = 1) -> dict:
    """One timed ``solve_ivp`` run (NumPy right-hand side, ``t_eval`` at the save times)."""
    from scipy.integrate import solve_ivp

    rhs, y0 = system.scipy_problem()
    t = np.linspace(0.0, T, n_saves + 1)

    def call():
        return solve_ivp(rhs, (0.0, T), y0, method=solver, rtol=tol, atol=tol, t_eval=t)

    sol, wall, runs = _time_best(call, repeats)
    ok = bool(sol.success) and sol.y.shape[1] == t.size
    y = sol.y.T if ok else np.full((t.size, y0.size), np.nan)
    return {"family": "scipy", "method": f"scipy {solver}", "param": "rtol", "value": tol,
            "t": t, "states": system.from_scipy(y), "wall_s": wall, "runs": runs,
            "compile_s": 0.0, "n_steps": int(sol.nfev), "result": 0 if ok else 1,
            "message": "ok" if ok else f"solve_ivp failed: {sol.message}"}
