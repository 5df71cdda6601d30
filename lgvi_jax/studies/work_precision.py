r"""Speed against accuracy: every method of ours beside the tools a user would otherwise pick.

For the car-pendulum (the paper's initial state, and a state with non-zero horizontal
momentum) and the harmonic oscillator, this experiment runs

* **ours**: every method of :data:`RIGID_METHOD_NAMES` / :data:`EUCLIDEAN_METHOD_NAMES` that
  resolves through ``lgvi_jax.scenes.get_scene(system).method(name)`` (composed names such as
  ``lgvi@6`` enter automatically once they resolve), each over a range of fixed steps;
* **diffrax** (optional, the ``bench`` extra): ``Tsit5`` and ``Dopri8``, adaptive
  (``PIDController(rtol, atol)``, ``rtol = atol`` over a range) and fixed-step
  (``ConstantStepSize``), on the library's continuous equations ``model.vector_field``
  (for the car-pendulum: R embedded as 9 numbers), jitted, ``SaveAt(ts=...)``;
* **SciPy** ``solve_ivp`` (``DOP853``, ``RK45``, ``rtol = atol`` over a range) on the
  hand-derived NumPy equations :meth:`lgvi_jax.reference.HandReference.rhs` (state
  ``(R, ω, q, v)``) for the car-pendulum and on ``(q̇, ṗ) = (p/m, −kq)`` for the
  oscillator, with ``t_eval`` at the save times: what a fair, idiomatic SciPy user writes
  (NumPy right-hand side, no JAX).

All are timed in the same process, after compilation (ahead-of-time ``lower().compile()``
for JAX; SciPy needs none), waiting for the result (``block_until_ready``), best of up to
:data:`REPEATS` runs when a run is cheap. Every run saves its state at the same 501 (or 101)
equally spaced times, and all metrics are computed from those saved states by the same code:

* ``position error`` at t = 10 s and t = 50 s: the pendulum mass centre
  ``(x, y, 0) + R ρ_c`` against :class:`~lgvi_jax.reference.HandReference` (hand-derived
  equations, DOP853 at ``rtol = atol = 1e-13``, piecewise, no interpolation); for the
  oscillator ``|q − q_exact|`` against the closed-form solution. The reference's own error is
  estimated by comparing it with the same solve at ``1e-12`` (``reference_uncertainty``);
* ``max relative energy error`` ``max |E − E₀|/|E₀|`` over the saved states;
* ``momentum-map drift``: ``max |p − p₀|`` (cart momentum) and ``max |L_z − L_z0|``;
* ``‖RᵀR − I‖_F``, max over the saved states.

Horizons: 10 s and 50 s (accuracy), and 5000 s where drift decides. At 5000 s the
position is not compared with any reference: position errors, the reference's own
included, grow with the horizon (phase error, sensitivity to the initial state), so no
reference can be trusted for the position there. Only the invariants, which need no
reference, are measured.

Regimes and winners (summary.md): *short horizon* (fastest to a position error at t = 10 s
below a target), *t = 50 s*, *long horizon* (fastest to a max relative energy error over
5000 s below a target), *invariants* (smallest momentum-map and SO(3) errors over 5000 s) and
*batch throughput* (trajectories per second for a batch of perturbed initial states, each
method at the cheapest setting that meets the short-horizon target on the single
trajectory; ours through :func:`lgvi_jax.sweep.batch_arguments`, diffrax through
``jax.vmap``, SciPy serially).

References: Hairer, Nørsett, Wanner, *Solving ODEs I* (1993), §II.10 (work-precision
diagrams); Kidger, *On Neural Differential Equations* (2021) (diffrax).

Run:  ``python -m lgvi_jax.studies.work_precision --out DIR [--quick]`` or
``lgvi-jax reproduce --full``.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import lgvi_jax
from lgvi_jax import diagnostics, rollout, so3
from lgvi_jax._io import atomic_write_text
from lgvi_jax.models import CarPendulum, HarmonicOscillator, PhaseState
from lgvi_jax.plotting import figure, method_style, positive, save
from lgvi_jax.reference import HandReference, moving_scene
from lgvi_jax.scenes import get_scene, resolve_methods
from lgvi_jax.studies import EUCLIDEAN_METHOD_NAMES, RIGID_METHOD_NAMES, script_main

try:  # optional peer (the ``bench`` extra)
    import diffrax
except ImportError:  # pragma: no cover - depends on the environment
    diffrax = None

#: Quick mode (tests, ``reproduce --quick``): a few methods, short horizons.
QUICK_RIGID = ("lgvi",)
QUICK_EUCLIDEAN = ("rk4", "verlet", "gl4")

#: Fixed steps swept, by the method's declared order (every one divides the save interval).
RIGID_STEPS = {2: (0.02, 0.01, 0.005, 0.0025, 0.001), 4: (0.05, 0.02, 0.01, 0.005, 0.0025),
               6: (0.1, 0.05, 0.025, 0.01, 0.005)}
OSC_STEPS = {2: (0.1, 0.05, 0.02, 0.01, 0.005, 0.002, 0.001),
             4: (0.1, 0.05, 0.025, 0.01, 0.005, 0.0025), 6: (0.1, 0.05, 0.025, 0.01, 0.005)}
#: The steps of the 5000 s run, by order (two per method: the long run is expensive).
LONG_STEPS = {"rigid": {2: (0.02, 0.01), 4: (0.05, 0.025), 6: (0.1, 0.05)},
              "oscillator": {2: (0.1, 0.05), 4: (0.1,), 6: (0.1,)}}
#: Per-method exceptions: gl4 on the embedded car-pendulum ODE costs ~10x an explicit step,
#: lgvi@8 ~15 lgvi steps per step.
LONG_STEPS_OVERRIDE = {"rigid": {"gl4": (0.1,), "lgvi@8": (0.1,)}, "oscillator": {}}
#: diffrax and SciPy settings: rtol = atol.
DIFFRAX_TOLS = {"tsit5": (1e-4, 1e-6, 1e-8, 1e-10, 1e-12),
                "dopri8": (1e-5, 1e-7, 1e-9, 1e-11, 1e-13)}
DIFFRAX_FIXED = {"tsit5": (0.05, 0.02, 0.01, 0.005, 0.0025),
                 "dopri8": (0.1, 0.05, 0.025, 0.01, 0.005)}
DIFFRAX_LONG_TOLS = {"tsit5": (1e-6, 1e-9), "dopri8": (1e-7, 1e-10)}
SCIPY_TOLS = {"DOP853": (1e-5, 1e-7, 1e-9, 1e-11), "RK45": (1e-4, 1e-6, 1e-8)}
SCIPY_LONG_TOLS = {"DOP853": (1e-9,)}  # oscillator only (car-pendulum: see summary)
#: Targets of the regimes.
TARGETS = {"short_tight": 1e-8, "short_moderate": 1e-4, "t50": 1e-5, "long_energy": 1e-6}
#: Saved states per run (the buffer of our rollout; run-time count up to this).
MAX_SAVES = 500
REPEATS = 3
CHECK_TIMES = (10.0, 50.0)
DIFFRAX_MAX_STEPS = 10**7

def config(quick: bool) -> dict:
    return {
        "quick": quick,
        "systems": ["car-paper", "oscillator"] if quick else
        ["car-paper", "car-moving", "oscillator"],
        "horizons": [10.0] if quick else [10.0, 50.0],
        "long_horizon": 100.0 if quick else 5000.0,
        "long_system": "car-paper" if quick else "car-moving",
        "saves": {"10": 100, "50": 500, "long": 500},
        "rigid_methods": list(QUICK_RIGID if quick else RIGID_METHOD_NAMES),
        "euclidean_methods": list(QUICK_EUCLIDEAN if quick else EUCLIDEAN_METHOD_NAMES),
        "rigid_steps": {"2": [0.01, 0.005], "4": [0.02, 0.01]} if quick else
        {str(k): list(v) for k, v in RIGID_STEPS.items()},
        "oscillator_steps": {"2": [0.1, 0.05], "4": [0.1, 0.05]} if quick else
        {str(k): list(v) for k, v in OSC_STEPS.items()},
        "diffrax_tols": {"tsit5": [1e-6, 1e-9]} if quick else
        {k: list(v) for k, v in DIFFRAX_TOLS.items()},
        "diffrax_fixed": {} if quick else {k: list(v) for k, v in DIFFRAX_FIXED.items()},
        "diffrax_long_tols": {"tsit5": [1e-8]} if quick else
        {k: list(v) for k, v in DIFFRAX_LONG_TOLS.items()},
        "diffrax_systems": ["oscillator"] if quick else ["car-paper", "car-moving",
                                                         "oscillator"],
        "scipy_tols": {"DOP853": [1e-6]} if quick else {k: list(v) for k, v in
                                                         SCIPY_TOLS.items()},
        "scipy_long_tols": {"DOP853": [1e-8]} if quick else
        {k: list(v) for k, v in SCIPY_LONG_TOLS.items()},
        "targets": dict(TARGETS),
        "batch": 8 if quick else 256,
        "batch_system": "oscillator" if quick else "car-paper",
        "batch_ours": 1 if quick else 3,  # our fastest methods (at the target) batched
        "batch_perturb": 0.01,
        "batch_horizon": 10.0,
        "batch_scipy_sample": 2 if quick else 4,
        "reference_rtol": 1e-13,
        "reference_check_rtol": None if quick else 1e-12,
        "repeats": REPEATS,
    }


def _order_key(order: int) -> str:
    return "2" if order <= 2 else "4" if order <= 5 else "6"


# --------------------------------------------------------------------------- systems


@dataclasses.dataclass
class System:
    """A test problem: the model, its initial state, how to compare with the reference."""

    key: str
    title: str
    scene: str
    model: Any
    state0: Any
    ref_rtol: float = 1e-13
    _ref: dict = dataclasses.field(default_factory=dict)

    @property
    def rigid(self) -> bool:
        return self.scene == "car-pendulum"

    def positions(self, states) -> np.ndarray:
        """Pendulum mass-centre positions (rigid) or ``q`` (oscillator), shape ``(n, d)``."""
        if self.rigid:
            return np.asarray(_centres(self.model, states))
        return np.asarray(states.q)

    def reference_position(self, t: float) -> np.ndarray:
        """The independent reference at time ``t`` (cached per time)."""
        if t not in self._ref:
            if self.rigid:
                ref = HandReference(self.model)
                times = sorted({*(c for c in CHECK_TIMES if c <= t), t})
                ys = ref.at(times, rtol=self.ref_rtol, atol=self.ref_rtol)
                for tt, y in zip(times, ys, strict=True):
                    self._ref[tt] = ref.centre(y)
            else:
                self._ref[t] = np.asarray(self.model.exact(self.state0, t).q)
        return self._ref[t]

    def invariants(self, states) -> dict[str, np.ndarray]:
        inv = {k: np.asarray(v) for k, v in _invariants(self.model, states).items()}
        if self.rigid:
            inv["orthogonality_error"] = np.asarray(so3.orthogonality_error(states.R))
        return inv

    # SciPy: the system as a NumPy right-hand side, and back to the library's state
    def scipy_problem(self) -> tuple[Callable, np.ndarray]:
        if self.rigid:
            ref = HandReference(self.model)
            return ref.rhs, ref.y0
        m, k = float(self.model.m), float(self.model.k)

        def rhs(_t, y):
            return np.array([y[1] / m, -k * y[0]])

        return rhs, np.array([float(self.state0.q[0]), float(self.state0.p[0])])

    def from_scipy(self, y: np.ndarray):
        """Library states from SciPy's rows ``y`` (``(n, 16)`` or ``(n, 2)``)."""
        y = jnp.asarray(y)
        if self.rigid:
            return _from_hand(self.model, y)
        return PhaseState(q=y[:, :1], p=y[:, 1:2])


@eqx.filter_jit
def _centres(model, states):
    return jax.vmap(model.pendulum_centre)(states)


@eqx.filter_jit
def _invariants(model, states):
    return jax.vmap(model.invariants)(states)


@eqx.filter_jit
def _from_hand(model, y):
    R = y[:, :9].reshape(-1, 3, 3)
    return jax.vmap(model.state_from_velocities)(R, y[:, 9:12], y[:, 12:14], y[:, 14:16])


def make_system(key: str, ref_rtol: float = 1e-13) -> System:
    """``car-paper`` (the paper's state), ``car-moving`` (non-zero horizontal momentum,
    :func:`lgvi_jax.reference.moving_scene`) or ``oscillator`` (m = k = q0 = 1, p0 = 0)."""
    if key == "car-paper":
        model = CarPendulum()
        return System(key, "car-pendulum, paper state", "car-pendulum", model,
                      model.default_state(), ref_rtol)
    if key == "car-moving":
        model = moving_scene()
        return System(key, "car-pendulum, moving cart", "car-pendulum", model,
                      model.default_state(), ref_rtol)
    if key == "oscillator":
        model = HarmonicOscillator()
        return System(key, "harmonic oscillator", "oscillator", model, model.default_state(),
                      ref_rtol)
    raise ValueError(f"make_system: unknown system {key!r}; valid: car-paper, car-moving, "
                     "oscillator")


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


def run_ours(system: System, name: str, method, h: float, T: float, n_saves: int,
             repeats: int = REPEATS) -> dict:
    """One timed run of our ``method`` at step ``h`` over ``[0, T]``; returns the raw run
    (saved times and states, wall time, compile time, result)."""
    t, k = _grid(T, n_saves, h)
    args = (system.model, method, system.state0, jnp.float64(h), jnp.int32(k),
            jnp.int32(n_saves))
    key = ("ours", name, system.scene)
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


def run_diffrax(system: System, solver: str, adaptive: bool, x: float, T: float,
                n_saves: int, repeats: int = REPEATS) -> dict:
    """One timed diffrax run: ``x`` = ``rtol = atol`` (adaptive) or the fixed step."""
    t = np.linspace(0.0, T, n_saves + 1)
    args = (system.model, system.state0, jnp.asarray(t), jnp.float64(x))
    fn = _diffrax_fn(solver, adaptive)
    key = ("diffrax", solver, adaptive, system.scene, n_saves)
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


def run_scipy(system: System, solver: str, tol: float, T: float, n_saves: int,
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


# --------------------------------------------------------------------------- metrics


def measure(system: System, run: dict, T: float, positions: bool = True) -> dict:
    """The metrics of a raw run (module docstring), as plain numbers; ``series`` keeps the
    invariant errors against time (for the long-run chart). ``positions=False`` (the long
    horizon): no comparison with the reference."""
    t, states = run["t"], run["states"]
    out = {k: run[k] for k in ("family", "method", "param", "value", "wall_s", "runs",
                               "compile_s", "n_steps", "result", "message")}
    out["horizon"] = T
    inv = system.invariants(states)
    finite = bool(all(np.all(np.isfinite(v)) for v in inv.values()))
    if out["result"] == 0 and not finite:
        out["result"], out["message"] = 1, "non-finite values in the saved states"
    out["failed"] = out["result"] != 0
    pos = system.positions(states)
    for tc in CHECK_TIMES if positions else ():
        if tc <= T + 1e-12:
            i = int(np.argmin(np.abs(t - tc)))
            if abs(t[i] - tc) < 1e-9:
                err = float(np.linalg.norm(pos[i] - system.reference_position(tc)))
                out[f"position_error_t{tc:g}"] = err if np.isfinite(err) else None
    E = inv["energy"]
    rel = np.abs(E - E[0]) / abs(E[0])
    series = {"t": t, "energy": rel}
    out["energy_error_max"] = float(np.max(rel)) if finite else None
    for k in ("momentum", "angular_momentum_z"):
        if k in inv:
            dev = np.abs(inv[k] - inv[k][:1]).reshape(len(t), -1).max(axis=1)
            series[k] = dev
            out[f"{k}_drift_max"] = float(np.max(dev)) if finite else None
    if "orthogonality_error" in inv:
        series["orthogonality"] = inv["orthogonality_error"]
        out["orthogonality_error_max"] = (float(np.max(inv["orthogonality_error"]))
                                          if finite else None)
    out["series"] = series
    return out


def observed_error_order(system: System, name: str, steps: Sequence[float],
                         T: float = 10.0) -> tuple[float, list[float]]:
    """The harness's error measurement on a small case: position error at ``T`` for our
    method ``name`` at each step, and the least-squares slope of log error against log h."""
    method = get_scene(system.scene).method(name)
    errors = []
    for h in steps:
        raw = run_ours(system, name, method, h, T, 100, repeats=1)
        errors.append(measure(system, raw, T)[f"position_error_t{T:g}"])
    slope = float(np.polyfit(np.log(steps), np.log(errors), 1)[0])
    return slope, errors


# ------------------------------------------------------------------------ the study


def _sweep_system(system: System, cfg: dict, log: Callable) -> dict:
    """All runs of one system at the short horizons; returns ``{"runs": [...], ...}``."""
    rigid = system.rigid
    names = cfg["rigid_methods"] if rigid else cfg["euclidean_methods"]
    methods, skipped = resolve_methods(system.scene, names)
    steps_by_order = cfg["rigid_steps"] if rigid else cfg["oscillator_steps"]
    runs = []
    for T in cfg["horizons"]:
        n_saves = cfg["saves"][f"{T:g}"]
        for name, method in methods.items():
            steps = steps_by_order.get(_order_key(method.order), [])
            for h in steps:
                r = measure(system, run_ours(system, name, method, h, T, n_saves,
                                             cfg["repeats"]), T)
                runs.append(r)
            last = runs[-1]
            log(f"    {system.key} T={T:g} {name}: h = {steps[-1]}, wall "
                f"{last['wall_s']:.3g} s, err {last.get(f'position_error_t{T:g}')}")
        if diffrax is not None and system.key in cfg["diffrax_systems"]:
            for solver, tols in cfg["diffrax_tols"].items():
                for tol in tols:
                    runs.append(measure(system, run_diffrax(system, solver, True, tol, T,
                                                            n_saves, cfg["repeats"]), T))
                log(f"    {system.key} T={T:g} diffrax {solver}: {runs[-1]['wall_s']:.3g} s")
            for solver, steps in cfg["diffrax_fixed"].items():
                for h in steps:
                    runs.append(measure(system, run_diffrax(system, solver, False, h, T,
                                                            n_saves, cfg["repeats"]), T))
        for solver, tols in cfg["scipy_tols"].items():
            for tol in tols:
                reps = cfg["repeats"] if not rigid else 1
                runs.append(measure(system, run_scipy(system, solver, tol, T, n_saves,
                                                      reps), T))
            log(f"    {system.key} T={T:g} scipy {solver}: {runs[-1]['wall_s']:.3g} s")
    return {"runs": runs, "skipped_methods": skipped, "methods": list(methods)}


def _long_runs(system: System, cfg: dict, log: Callable) -> list[dict]:
    """The long horizon: one step per method of ours, a few tolerances per peer."""
    T = cfg["long_horizon"]
    n_saves = cfg["saves"]["long"]
    names = cfg["rigid_methods"] if system.rigid else cfg["euclidean_methods"]
    methods, _ = resolve_methods(system.scene, names)
    kind = "rigid" if system.rigid else "oscillator"
    table, override = LONG_STEPS[kind], LONG_STEPS_OVERRIDE[kind]
    if cfg["quick"]:
        table, override = {k: v[-1:] for k, v in table.items()}, {}
    runs = []
    for name, method in methods.items():
        for h in override.get(name, table[int(_order_key(method.order))]):
            runs.append(measure(system, run_ours(system, name, method, h, T, n_saves, 1), T,
                                False))
            log(f"    long {system.key} {name}: h = {h}, wall {runs[-1]['wall_s']:.3g} s, "
                f"max dE/E {runs[-1]['energy_error_max']}")
    if diffrax is not None and system.key in cfg["diffrax_systems"]:
        for solver, tols in cfg["diffrax_long_tols"].items():
            for tol in tols:
                runs.append(measure(system, run_diffrax(system, solver, True, tol, T,
                                                        n_saves, 1), T, False))
                log(f"    long {system.key} diffrax {solver} rtol {tol:g}: "
                    f"{runs[-1]['wall_s']:.3g} s")
    if not system.rigid:
        for solver, tols in cfg["scipy_long_tols"].items():
            for tol in tols:
                runs.append(measure(system, run_scipy(system, solver, tol, T, n_saves), T, False))
    return runs


def _batch(system: System, short: list[dict], cfg: dict, log: Callable) -> dict:
    """Batch throughput at matched accuracy (module docstring)."""
    from lgvi_jax.sweep import batch_arguments, initial_conditions

    target = cfg["targets"]["short_moderate"]
    T = cfg["batch_horizon"]
    B = cfg["batch"]
    key_err = f"position_error_t{T:g}"
    cands = [r for r in short if r["horizon"] == T and not r["failed"]
             and (r.get(key_err) or np.inf) <= target]
    best: dict[str, dict] = {}
    for r in cands:
        if r["method"] not in best or r["wall_s"] < best[r["method"]]["wall_s"]:
            best[r["method"]] = r
    ours = sorted((r for r in best.values() if r["family"] == "ours"),
                  key=lambda r: r["wall_s"])[: cfg["batch_ours"]]
    # The fastest configuration of each peer family (diffrax, SciPy) meeting the target.
    peers = []
    for fam in ("diffrax", "scipy"):
        rows = [r for r in best.values() if r["family"] == fam]
        if rows:
            peers.append(min(rows, key=lambda r: r["wall_s"]))
    states = initial_conditions(system.model, system.state0, B, cfg["batch_perturb"], 0)
    device = jax.devices()[:1]
    out = {"batch": B, "horizon": T, "target": target, "devices": [str(d) for d in device],
           "rows": []}
    methods, _ = resolve_methods(system.scene, [r["method"] for r in ours])
    for r in ours:
        h = r["value"]
        fn, args = batch_arguments(system.model, methods[r["method"]], states, h,
                                   round(T / h), kind="final", devices=device)
        start = time.perf_counter()
        compiled = fn.lower(*args).compile()
        compile_s = time.perf_counter() - start
        # jitted with the static half of (model, method) as a static argument: the
        # compiled function takes the others only.
        dyn = (args[0], *args[2:])
        res, wall, _ = _time_best(lambda c=compiled, a=dyn: jax.block_until_ready(c(*a)),
                                  cfg["repeats"], 2.0)
        ok = int(np.sum(np.asarray(res["result"]) == 0))
        out["rows"].append({"family": "ours", "method": r["method"], "param": "h",
                            "value": h, "wall_s": wall, "compile_s": compile_s,
                            "trajectories_per_s": B / wall, "succeeded": ok})
    for r in peers:
        if r["family"] == "diffrax":
            solver = r["method"].split()[1]
            adaptive = "fixed" not in r["method"]
            fn = _diffrax_fn(solver, adaptive, batched=True)
            args = (system.model, states, jnp.asarray([0.0, T]), jnp.float64(r["value"]))
            start = time.perf_counter()
            compiled = fn.lower(*args).compile()
            compile_s = time.perf_counter() - start
            res, wall, _ = _time_best(lambda c=compiled, a=args: jax.block_until_ready(c(*a)),
                                      cfg["repeats"], 2.0)
            out["rows"].append({"family": "diffrax", "method": r["method"],
                                "param": r["param"], "value": r["value"], "wall_s": wall,
                                "compile_s": compile_s, "trajectories_per_s": B / wall,
                                "succeeded": int(np.sum(np.asarray(res[1])))})
        elif r["family"] == "scipy":
            # Serial: a sample of the batch, timed one by one, extrapolated to B.
            k = cfg["batch_scipy_sample"]
            solver = r["method"].split()[1]
            from scipy.integrate import solve_ivp

            walls = []
            for i in range(k):
                s_i = jax.tree.map(lambda x, i=i: x[i], states)
                sys_i = dataclasses.replace(system, state0=s_i)
                rhs, y0 = _scipy_y0(sys_i)
                start = time.perf_counter()
                solve_ivp(rhs, (0.0, T), y0, method=solver, rtol=r["value"],
                          atol=r["value"])
                walls.append(time.perf_counter() - start)
            per = float(np.mean(walls))
            out["rows"].append({"family": "scipy", "method": r["method"], "param": "rtol",
                                "value": r["value"], "wall_s": per * B, "compile_s": 0.0,
                                "trajectories_per_s": 1.0 / per, "succeeded": None,
                                "note": f"serial; {k} trajectories timed, extrapolated"})
    for row in out["rows"]:
        log(f"    batch {system.key} {row['method']}: {row['trajectories_per_s']:.3g} "
            "trajectories/s")
    return out


def _scipy_y0(system: System):
    """SciPy's problem for a (perturbed) state of the system: NumPy rhs and ``y0`` built
    from the state's velocities."""
    rhs, _ = system.scipy_problem()
    s = system.state0
    if system.rigid:
        omega, v = system.model.velocities(s.R, s.mu, s.q, s.p)
        y0 = np.concatenate([np.ravel(np.asarray(s.R)), np.asarray(omega), np.asarray(s.q),
                             np.asarray(v)])
    else:
        y0 = np.array([float(s.q[0]), float(s.p[0])])
    return rhs, y0


# ------------------------------------------------------------------------- regimes


def _label(r: dict) -> str:
    if r["param"] == "h":
        return f"{r['method']} (h = {r['value']:g})"
    return f"{r['method']} (rtol = {r['value']:g})"


def _fastest(runs: list[dict], ok: Callable[[dict], bool]) -> dict[str, dict]:
    """Per method, the fastest run satisfying ``ok``."""
    best: dict[str, dict] = {}
    for r in runs:
        if r["failed"] or not ok(r):
            continue
        if r["method"] not in best or r["wall_s"] < best[r["method"]]["wall_s"]:
            best[r["method"]] = r
    return best


def _regime(name: str, description: str, best: dict[str, dict], value_key: str,
            lower_is_better: bool = True) -> dict:
    """Winner, best of ours, best peer and their ratio (peer / ours, > 1: ours better)."""
    rows = sorted(best.values(), key=lambda r: r[value_key] if lower_is_better
                  else -r[value_key])
    out = {"regime": name, "description": description, "metric": value_key,
           "ranking": [{"label": _label(r), "method": r["method"], "family": r["family"],
                        value_key: r[value_key], "wall_s": r["wall_s"]} for r in rows]}
    if not rows:
        out["winner"] = None
        return out
    out["winner"] = out["ranking"][0]
    ours = [r for r in rows if r["family"] == "ours"]
    peers = [r for r in rows if r["family"] != "ours"]
    out["best_ours"] = out["ranking"][rows.index(ours[0])] if ours else None
    out["best_peer"] = out["ranking"][rows.index(peers[0])] if peers else None
    if ours and peers:
        a, b = ours[0][value_key], peers[0][value_key]
        out["peer_over_ours"] = (b / a if lower_is_better else a / b) if a > 0 else None
    return out


def regimes(results: dict, cfg: dict) -> list[dict]:
    """The regimes of the summary table, computed from the measured runs."""
    tg = cfg["targets"]
    out = []
    for key, res in results["systems"].items():
        runs = res["runs"]
        for T, target in ((10.0, tg["short_tight"]), (10.0, tg["short_moderate"]),
                          (50.0, tg["t50"])):
            if T not in cfg["horizons"]:
                continue
            err = f"position_error_t{T:g}"
            best = _fastest([r for r in runs if r["horizon"] == T],
                            lambda r, err=err, target=target: r.get(err) is not None
                            and r[err] <= target)
            out.append(_regime(f"{key}: {T:g} s, position error ≤ {target:g}",
                               f"fastest run of [0, {T:g}] s with position error at t = {T:g}"
                               f" s ≤ {target:g}", best, "wall_s"))
    T = cfg["long_horizon"]
    target = tg["long_energy"]
    for key, runs in results.get("long_all", {}).items():
        best = _fastest(runs, lambda r: (r["energy_error_max"] or np.inf) <= target)
        out.append(_regime(f"{key}: {T:g} s, max relative energy error ≤ {target:g}",
                           f"fastest run of [0, {T:g}] s whose max relative energy error "
                           f"≤ {target:g}", best, "wall_s"))
        inv = []
        for r in runs:
            keys = [k for k in r if k.endswith("_drift_max") or k == "orthogonality_error_max"]
            if r["failed"] or not keys:
                continue
            inv.append({**r, "invariant_error": max(r[k] for k in keys)})
        if inv:
            best = {}
            for r in inv:
                if r["method"] not in best or r["invariant_error"] < best[r["method"]][
                        "invariant_error"]:
                    best[r["method"]] = r
            out.append(_regime(f"{key}: {T:g} s, invariants",
                               "smallest worst of max |Δp|, max |ΔL_z|, max ‖RᵀR − I‖_F "
                               f"over [0, {T:g}] s", best, "invariant_error"))
    batch = results.get("batch")
    if batch and batch["rows"]:
        best = {r["method"]: r for r in batch["rows"]}
        out.append(_regime(
            f"{results['batch_system']}: batch of {batch['batch']}",
            f"trajectories per second, {batch['batch']} perturbed initial states over "
            f"[0, {batch['horizon']:g}] s, each method at its cheapest setting meeting "
            f"position error ≤ {batch['target']:g} at t = {batch['horizon']:g} s on the "
            "unperturbed state", best, "trajectories_per_s", lower_is_better=False))
    return out


# --------------------------------------------------------------------------- charts


def _peer_style(method: str) -> dict:
    styles = {"diffrax tsit5": ("tab:gray", "-"), "diffrax dopri8": ("black", "-"),
              "diffrax tsit5 fixed": ("tab:gray", ":"), "diffrax dopri8 fixed": ("black", ":"),
              "scipy DOP853": ("tab:pink", "--"), "scipy RK45": ("tab:pink", ":")}
    if method in styles:
        c, ls = styles[method]
        return {"color": c, "linestyle": ls}
    return method_style(method)


_MARKERS = {"ours": "o", "diffrax": "s", "scipy": "^"}


def _wp_axis(ax, runs, ykey, title, floor=None):
    by_method: dict[str, list] = {}
    for r in runs:
        if r["failed"] or r.get(ykey) is None:
            continue
        by_method.setdefault(r["method"], []).append(r)
    for name, rs in by_method.items():
        rs = sorted(rs, key=lambda r: r["wall_s"])
        ax.loglog([r["wall_s"] for r in rs], positive([r[ykey] for r in rs]),
                  marker=_MARKERS[rs[0]["family"]], markersize=3.5, linewidth=1.0,
                  label=name, **_peer_style(name))
    if floor:
        ax.axhline(floor, color="k", linewidth=0.6, alpha=0.5)
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("wall time [s] (after compilation)")
    ax.grid(True, which="both", alpha=0.3)


def charts(results: dict, cfg: dict, out: Path) -> list[str]:
    files = []
    systems = results["systems"]
    for key, res in systems.items():
        runs = res["runs"]
        horizons = cfg["horizons"]
        fig, axes = figure(1, len(horizons) + 1, width=5.2 * (len(horizons) + 1), height=4.4)
        axes = np.atleast_1d(axes)
        for ax, T in zip(axes, horizons, strict=False):
            # the reference's estimated error (at t = 50 s) as a guide line
            _wp_axis(ax, [r for r in runs if r["horizon"] == T], f"position_error_t{T:g}",
                     f"{res['title']}: position error at t = {T:g} s",
                     res.get("reference_uncertainty") if T == 50.0 else None)
            ax.set_ylabel("position error [m]" if "car" in key else "|q − q_exact|")
        T = horizons[-1]
        _wp_axis(axes[-1], [r for r in runs if r["horizon"] == T], "energy_error_max",
                 f"{res['title']}: max |ΔE/E| over [0, {T:g}] s")
        axes[-1].set_ylabel("max relative energy error")
        axes[-1].legend(fontsize=6, loc="center left", bbox_to_anchor=(1.01, 0.5))
        name = f"work_precision_{key}.png"
        save(fig, out / name)
        files.append(name)
    long = results.get("long_all", {})
    if long:
        fig, axes = figure(1, len(long), width=6 * len(long), height=4.4)
        axes = np.atleast_1d(axes)
        for ax, (key, runs) in zip(axes, long.items(), strict=True):
            _wp_axis(ax, runs, "energy_error_max",
                     f"{systems[key]['title'] if key in systems else key}: max |ΔE/E| over "
                     f"[0, {cfg['long_horizon']:g}] s")
            ax.set_ylabel("max relative energy error")
            ax.legend(fontsize=6)
        save(fig, out / "energy_vs_time.png")
        files.append("energy_vs_time.png")
    lr = results.get("long")
    if lr:
        panels = [("energy", "|E − E₀|/|E₀|"), ("momentum", "|p − p₀| (max component)"),
                  ("angular_momentum_z", "|L_z − L_z0|"), ("orthogonality", "‖RᵀR − I‖_F")]
        panels = [p for p in panels if p[0] in lr["runs"][0]["series"]]
        fig, axes = figure(2, 2, width=13, height=4.0)
        for ax, (k, ylabel) in zip(np.ravel(axes), panels, strict=False):
            shown: set[str] = set()
            for r in sorted(lr["runs"], key=lambda r: r["value"]):
                # one run per method (its smallest step or tolerance): readable lines
                if r["failed"] or r["method"] in shown:
                    continue
                shown.add(r["method"])
                s = r["series"]
                ax.semilogy(s["t"][1:], positive(np.maximum.accumulate(s[k][1:])),
                            linewidth=1.0, label=_label(r), **_peer_style(r["method"]))
            ax.set_ylabel(f"max over [0, t] of {ylabel}", fontsize=8)
            ax.set_xlabel("t [s]")
            ax.grid(True, which="both", alpha=0.3)
        np.ravel(axes)[1].legend(fontsize=6, loc="center left", bbox_to_anchor=(1.01, 0.5))
        fig.suptitle(f"Invariant errors against time, {lr['title']}, "
                     f"{cfg['long_horizon']:g} s (saved every {cfg['long_horizon'] / 500:g} s)")
        save(fig, out / "invariants_long_run.png")
        files.append("invariants_long_run.png")
    return files


# --------------------------------------------------------------------------- summary


def _f(x, fmt=".3g") -> str:
    return "—" if x is None else format(x, fmt)


def recommendations(regs: list[dict]) -> list[str]:
    """Plain-language advice, each sentence computed from a regime's numbers."""
    lines = []
    for g in regs:
        w = g.get("winner")
        if w is None:
            lines.append(f"- **{g['regime']}**: no method met the target in the measured "
                         "range.")
            continue
        m = g["metric"]
        unit = {"wall_s": " s", "trajectories_per_s": " trajectories/s",
                "invariant_error": ""}[m]
        ours, peer = g.get("best_ours"), g.get("best_peer")
        txt = f"- **{g['regime']}**: choose **{w['label']}** ({_f(w[m])}{unit})"
        ratio = g.get("peer_over_ours")
        worse = {"wall_s": "slower", "trajectories_per_s": "lower in throughput",
                 "invariant_error": "larger in invariant error"}[m]
        if ours and peer and ratio is not None:
            if w["family"] == "ours":
                txt += f"; the best peer, {peer['label']}, is {ratio:.3g}× {worse}"
            else:
                txt += (f"; **our methods lose here**: our best, {ours['label']}, is "
                        f"{1 / ratio:.3g}× {worse}")
        elif not ours:
            txt += "; none of our methods met the target in the measured range"
        elif not peer:
            txt += "; no peer met the target in the measured range"
        lines.append(txt + ".")
    return lines


def method_table(results: dict) -> list[str]:
    """Per method: best wall time to each regime's target (the numbers behind the advice)."""
    regs = results["regimes"]
    names: list[str] = []
    for g in regs:
        for r in g["ranking"]:
            if r["method"] not in names:
                names.append(r["method"])
    head = "| method | " + " | ".join(g["regime"] for g in regs) + " |"
    lines = [head, "|---|" + "---|" * len(regs)]
    for n in names:
        cells = []
        for g in regs:
            hit = [(i, r) for i, r in enumerate(g["ranking"]) if r["method"] == n]
            if hit:
                i, r = hit[0]
                cells.append(f"{_f(r[g['metric']])} (#{i + 1})")
            else:
                cells.append("—")
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    return lines


def write_summary(results: dict, out: Path) -> str:
    regs = results["regimes"]
    env = results["environment"]
    lines = [
        "Work-precision: every method of ours against diffrax and SciPy, all timed in this "
        f"run after compilation on {env['cpu_count']} CPU cores ({env['date']}, jax "
        f"{env['jax']}, diffrax {env['diffrax'] or 'not installed'}).",
        "",
    ]
    if diffrax is None:
        lines += ["**diffrax is not installed: its runs were skipped** (install the `bench` "
                  "extra).", ""]
    lines += [
        "Ours: fixed steps. diffrax: `Tsit5`/`Dopri8` on `model.vector_field` (the library's "
        "equations, R as 9 numbers), adaptive `PIDController(rtol = atol)` or fixed step. "
        "SciPy: `solve_ivp` on the hand-derived NumPy equations "
        "(`HandReference.rhs`), `rtol = atol`, `t_eval` at the save times. Position error: "
        "pendulum mass centre against `HandReference` (DOP853, rtol = atol = 1e-13) or the "
        "exact oscillator solution. Energy and momentum-map errors: max over the saved "
        "states (every T/500; every 0.1 s at t ≤ 50 s). At the long horizon only "
        "invariants are compared: no reference can be trusted for the position there.",
        "",
    ]
    for res in results["systems"].values():
        if res.get("reference_uncertainty") is not None:
            lines.append(f"- {res['title']}: reference uncertainty at t = 50 s (1e-13 vs "
                         f"1e-12 solve) {res['reference_uncertainty']:.1e} m; errors near "
                         "it are not resolved.")
        if res["skipped_methods"]:
            lines.append(f"- {res['title']}: methods not available in this checkout: "
                         f"{', '.join(res['skipped_methods'])}.")
    osc = [r for k, res in results["systems"].items() if not k.startswith("car")
           for r in res["runs"] if not r["failed"]]
    if osc:
        lines.append(f"- oscillator: the fastest run took {min(r['wall_s'] for r in osc):.2g} s;"
                     " runs this short measure call overhead (dispatch of a compiled function,"
                     " SciPy's per-step Python) more than arithmetic.")
    if results.get("scipy_long_note"):
        lines.append(f"- {results['scipy_long_note']}")
    lines += ["", "![work-precision](work_precision_car-paper.png)", ""]
    lines += ["## Winners per regime", "",
              "| regime | winner | best of ours | best peer | peer / ours |",
              "|---|---|---|---|---|"]
    def cell(row, m):
        if not row:
            return "—"
        extra = f" in {_f(row['wall_s'])} s" if m == "invariant_error" else ""
        return f"{row['label']}: {_f(row[m])}{extra}"

    for g in regs:
        m = g["metric"]
        lines.append(f"| {g['regime']} | {cell(g.get('winner'), m)} | "
                     f"{cell(g.get('best_ours'), m)} | {cell(g.get('best_peer'), m)} | "
                     f"{_f(g.get('peer_over_ours'))} |")
    lines += ["", "Metric: wall time [s] to the target (lower is better), except *invariants* "
              "(worst invariant error) and *batch* (trajectories/s, higher is better); "
              "*peer / ours* > 1 means ours is better by that factor.", "",
              "## When to choose each method (from these measurements)", ""]
    lines += recommendations(regs)
    lines += ["", "## Every method in every regime (value, rank)", ""]
    lines += method_table(results)
    lines += ["", "Charts: " + ", ".join(f"`{f}`" for f in results["files"]), ""]
    text = "\n".join(lines) + "\n"
    atomic_write_text(out / "summary.md", text)
    return text


# ------------------------------------------------------------------------------ run


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def _strip(runs: list[dict], keep_series: bool = False) -> list[dict]:
    return [{k: v for k, v in r.items() if keep_series or k != "series"} for r in runs]


def environment() -> dict:
    return diagnostics.environment(
        diffrax=getattr(diffrax, "__version__", None) if diffrax is not None else None,
        scipy=__import__("scipy").__version__)


def run(out_dir: Path | str, *, quick: bool = False, log: Callable = print) -> dict:
    """Run the whole study into ``out_dir``; returns the results dictionary."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cfg = config(quick)
    start = time.perf_counter()
    systems, long_all = {}, {}
    results: dict[str, Any] = {"quick": quick, "config": cfg}
    if diffrax is None:
        log("  diffrax is not installed: its runs are skipped")
    for key in cfg["systems"]:
        system = make_system(key, cfg["reference_rtol"])
        log(f"  {system.title} ...")
        res = _sweep_system(system, cfg, log)
        res["title"] = system.title
        if system.rigid and cfg["reference_check_rtol"] is not None:
            coarse = make_system(key, cfg["reference_check_rtol"])
            res["reference_uncertainty"] = float(np.linalg.norm(
                coarse.reference_position(50.0) - system.reference_position(50.0)))
        systems[key] = res
        if key == cfg["long_system"] or not system.rigid:
            log(f"  {system.title}: long horizon {cfg['long_horizon']:g} s ...")
            long_all[key] = _long_runs(system, cfg, log)
            if key == cfg["long_system"]:
                results["long"] = {"system": key, "title": system.title,
                                   "runs": long_all[key]}
        if key == cfg["batch_system"]:
            log("  batch throughput ...")
            results["batch"] = _batch(system, res["runs"], cfg, log)
            results["batch_system"] = key
    results["systems"] = systems
    results["long_all"] = long_all
    rigid_scipy = [r for k, res in systems.items() if "car" in k for r in res["runs"]
                   if r["family"] == "scipy" and r["horizon"] == max(cfg["horizons"])]
    if rigid_scipy:
        cheapest = min(r["wall_s"] for r in rigid_scipy)
        factor = cfg["long_horizon"] / max(cfg["horizons"])
        results["scipy_long_note"] = (
            f"SciPy is left out of the {cfg['long_horizon']:g} s car-pendulum run: its "
            f"cheapest {max(cfg['horizons']):g} s run took {cheapest:.3g} s here, so "
            f"≥ {cheapest * factor:.3g} s per tolerance at {cfg['long_horizon']:g} s.")
    results["regimes"] = regimes(results, cfg)
    results["files"] = charts(results, cfg, out)
    results["environment"] = environment()
    results["wall_time_s"] = time.perf_counter() - start
    write_summary(results, out)
    clean = {
        **results,
        "systems": {k: {**v, "runs": _strip(v["runs"])} for k, v in systems.items()},
        "long_all": {k: _strip(v) for k, v in long_all.items()},
    }
    if "long" in results:
        clean["long"] = {**results["long"], "runs": _strip(results["long"]["runs"], True)}
    # results.json last: its presence marks the stage as complete (see lgvi_jax.reproduce).
    atomic_write_text(out / "results.json", json.dumps(_jsonable(clean), indent=1))
    return results


if __name__ == "__main__":
    sys.exit(script_main(run, __doc__, quick_help="a few methods, short horizons"))
