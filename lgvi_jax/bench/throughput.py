"""Benchmark of what users run: sweeps, gradients and fits, beside compiled-loop baselines.

Four parts (``lgvi-jax bench --out DIR``; writes ``bench.json`` and ``bench.md``):

1. **Throughput of the sweep's work.** For each system (the car-pendulum and the heavy top),
   method (``lgvi``, ``hamel``, ``hamel-cayley``, ``hamel-exact``, and the compositions
   ``lgvi@4``, ``lgvi@6``, ``lgvi@8``) and engine, the batched rollout that ``lgvi-jax
   sweep`` runs: :func:`lgvi_jax.sweep.batch_arguments` with ``kind="metrics"`` (the
   energy error, every momentum map's drift, the orthogonality error and the Newton
   iterations measured after every step), at h = 5e-3 over ``steps`` steps (10^4 by
   default), for one trajectory (a sweep of one: one device) and for a batch (1024 by
   default, split over every device in ``jax.devices()``: on a CPU-only machine one
   XLA host device per core, ``lgvi-jax bench --devices``), from the sweep's initial
   conditions (perturbation 0.01, seed 0). The method is built as the sweep builds it
   (:func:`lgvi_jax.sweep.sweep_method`): ``--engines scalar`` (the default) is what the
   sweep runs, the autodiff engine on scalars; ``general`` the same equations on arrays,
   for comparison. Beside each car-pendulum row, the Numba baseline of the same method
   (``lgvi_jax/bench/numba_lgvi.py``, ``numba_hamel.py``: the same discrete equations,
   hand-derived and reduced to three unknowns, scalar loops, the engine's chord-then-Newton
   iteration; compositions as the same sub-steps) **with the same per-step diagnostics**
   (``sweep_metrics``: the car-pendulum's energy, cart momentum, vertical angular momentum
   and orthogonality error written in Numba, reduced as the sweep reduces them), one
   trajectory on one core and the batch on all cores. The heavy top has no Numba baseline.
2. **Gradient.** ``jax.grad`` of a loss of the final state with respect to the inertia
   ``J``, through ``steps`` steps of one car-pendulum trajectory (``lgvi`` and ``hamel``;
   the autodiff engine on arrays and on scalars, the default), with the library's
   checkpointed rollout (``simulate(..., checkpoint_every=K)``, K near the square root of
   the steps): forward
   and gradient run times, their ratio, compile times.
3. **Fit.** ``lgvi_jax.identify.fit`` with its defaults (``lgvi``, Levenberg–Marquardt, the
   engine its rollout's length picks: ``identify.FIT_SCALAR_MIN_STEPS``) recovering the
   inertia from noise-free synthetic observations (every 0.05 s over 5 s from the
   independent reference) at h = 5e-3: wall
   time and the relative error of the recovered inertia.
4. **A sweep end to end** (``--parts sweep``, not in the default parts: it spawns fresh
   processes for a few minutes). ``lgvi-jax sweep SYSTEM --method hamel --dt 5e-3
   --t-final T --n BATCH --perturb 0.01 --seed 0`` for each system, a fresh process each:
   :data:`SWEEP_COLD_RUNS` times *cold* (each with an empty cache folder; the median is
   reported) and :data:`SWEEP_WARM_RUNS` times *warm* (the last cold run's folder:
   compiled and traced programs reused), wall clock of the whole command; beside
   it, for the car-pendulum, the Numba Hamel baseline's compiled batched run of the same
   work with the same per-step diagnostics on all cores (the issue's yardstick).
5. **Memory of long runs.** ``lgvi-jax simulate`` for 10^6 steps with ``--save-every
   1000`` (and 10^5 for comparison) in child processes: their peak resident memory.

Times are the best of at least ``repeats`` runs after compilation that took at least
:data:`MIN_TIME_S` in all (one trajectory: dozens of runs), fewer when a side's runs
already took :data:`TIME_BUDGET_S` (a batch of ``lgvi@8`` runs for minutes); the first
run counts. What a ratio compares is timed alternately, one run of each side in turn
(JAX and Numba; the forward run and the gradient), so that a slow stretch of a shared
machine weighs on both sides alike. Compile times are ahead of time
(``lower().compile()``) and cold: ``lgvi-jax bench`` leaves the command line's persistent
compilation cache off, and each throughput compile starts without JAX's in-memory caches
and the scalar programs (:func:`~lgvi_jax.newton.clear_scalar_programs`), as in a fresh
process; each program is compiled several times (:data:`SINGLE_COMPILES`,
:data:`BATCH_COMPILES`) and its compile time is the median. The benchmark reports
numbers and asserts nothing about them.

Run: ``lgvi-jax bench --out results/bench`` (or ``python lgvi_jax/bench/throughput.py``).
"""

from __future__ import annotations

import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import lgvi_jax as lj
from lgvi_jax._io import atomic_write_json, atomic_write_text
from lgvi_jax.newton import clear_scalar_programs
from lgvi_jax.studies import script_main
from lgvi_jax.sweep import batch_arguments, engine_name, initial_conditions, sweep_method

SYSTEMS = ("car-pendulum", "heavy-top")
METHODS = ("lgvi", "hamel", "hamel-cayley", "hamel-exact", "lgvi@4", "lgvi@6", "lgvi@8")
#: The engines timed: ``scalar`` (what ``lgvi-jax sweep`` runs) and, on request,
#: ``general`` (the autodiff engine on arrays, :func:`lgvi_jax.sweep.sweep_method` with
#: ``scalar=False``).
ENGINES = ("scalar",)
ENGINE_CHOICES = ("scalar", "general")
PARTS = ("throughput", "gradient", "fit", "sweep")
#: The parts run unless ``--parts`` names others (``sweep`` spawns processes for minutes).
DEFAULT_PARTS = ("throughput", "gradient", "fit")
#: Warm repetitions of the end-to-end sweep (``sweep`` part).
SWEEP_WARM_RUNS = 3
#: Cold runs of the end-to-end sweep, each with an empty cache folder; the cold time
#: reported is their median (each one in bench.json): one cold run's wall clock moved by
#: 4.7–6.4 s between runs of the same code on one host (docs/benchmarks.md, History).
SWEEP_COLD_RUNS = 3
#: ``--quick``: a smoke test of every part but the fit (whose Jacobian program is slow to
#: compile), on fewer methods, the default engines only, and the gradient on arrays only (the
#: scalar engine's gradient is the slowest program to compile).
QUICK_METHODS = ("lgvi", "hamel", "lgvi@4")
QUICK_ENGINES = ("scalar",)
QUICK_PARTS = ("throughput", "gradient")
GRAD_METHODS = ("lgvi", "hamel")
GRAD_ENGINES = ("array", "scalar")
DT = 5e-3
PERTURB, SEED = 0.01, 0
#: Stop repeating a timed run once its runs took this long in all (seconds).
TIME_BUDGET_S = 20.0
#: Repeat a timed run until its runs took at least this long in all (seconds), beyond the
#: ``repeats`` runs: one trajectory of 10^4 steps runs in milliseconds, and three such runs
#: fit inside one slow stretch of a shared machine (measured: stretches of seconds in which
#: one side ran 35 % slower).
MIN_TIME_S = 1.0
#: One trajectory's program is compiled this many times and its speed is the median: the
#: same program compiles to code of two speeds (docs/engine.md, "a lottery per
#: compilation": about one compilation in ten runs 1.3–2.2x slower), so one compilation
#: can misreport it twice over. A batch's speed has no such spread: its first compilation
#: is the one timed.
SINGLE_COMPILES = 3
#: A batch's program is compiled this many times (each cold), for its compile time: a
#: compile's wall clock varies by 20–40 % with the load of a shared host (docs/benchmarks.md),
#: so the time reported, one trajectory's too, is the median over the compilations (each one
#: in bench.json).
BATCH_COMPILES = 3
#: The fit: the inertia about the mass centre of the synthetic truth (the paper's is
#: 0.04 I, the fit's start), observations every 0.05 s over 5 s (1 s with --quick).
FIT_J_C_TRUE = ((0.03, 0.0, 0.0), (0.0, 0.05, 0.0), (0.0, 0.0, 0.04))
FIT_OBS_EVERY, FIT_T_FINAL, FIT_T_FINAL_QUICK = 0.05, 5.0, 1.0

#: What both sides compute (bench.md).
WORK = ("Both sides compute, after every step, what `lgvi-jax sweep` records per "
        "trajectory: the relative energy error |H - H0|/|H0| (running max and final), the "
        "drift of every momentum map (the car-pendulum's cart momentum and vertical angular "
        "momentum; the heavy top's vertical angular momentum), the orthogonality error "
        "‖RᵀR - I‖_F (running max) and the Newton iterations (mean and max per step). JAX: "
        "the sweep's batched rollout (`lgvi_jax.sweep.batch_arguments(..., "
        "kind=\"metrics\")`; one trajectory is a sweep of one, on one device) with the "
        "method `lgvi-jax sweep` builds (engine *scalar*; *general*: the same equations "
        "on arrays). Numba: the same discrete "
        "equations reduced by hand to three unknowns, with the same diagnostics written in "
        "Numba (`lgvi_jax/bench/numba_lgvi.py` `sweep_metrics`; car-pendulum only: n/a for "
        "the heavy top); one trajectory on one core, the batch on all cores.")


def _rss_mb() -> float:
    # ru_maxrss is in kilobytes on Linux.
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _timed(fn: Callable[[], object], repeats: int, budget_s: float = TIME_BUDGET_S,
           min_s: float = MIN_TIME_S):
    """``(best seconds, runs, first result)`` of ``fn`` (:func:`_timed_alternating`)."""
    return _timed_alternating([fn], repeats, budget_s, min_s)[0]


def _timed_alternating(fns: Sequence[Callable[[], object]], repeats: int,
                       budget_s: float = TIME_BUDGET_S, min_s: float = MIN_TIME_S,
                       clock: Callable[[], float] = time.perf_counter) -> list[tuple]:
    """For each of ``fns``, ``(best seconds, runs, first result)``. Their runs alternate
    (one run of each in turn), so that a slow stretch of a shared machine falls on all of
    them alike and their ratio keeps its meaning; each is repeated until it has run
    ``repeats`` times and for ``min_s`` in all, or for ``budget_s`` in all (at least once),
    the others alternating on until they are done too."""
    times: list[list[float]] = [[] for _ in fns]
    firsts: list = [None] * len(fns)

    def done(i: int) -> bool:
        total = sum(times[i])
        return bool(times[i]) and (total >= budget_s
                                   or (len(times[i]) >= repeats and total >= min_s))

    while not all(done(i) for i in range(len(fns))):
        for i, fn in enumerate(fns):
            if done(i):
                continue
            start = clock()
            out = jax.block_until_ready(fn())
            times[i].append(clock() - start)
            if firsts[i] is None:
                firsts[i] = out
    return [(min(t), len(t), first) for t, first in zip(times, firsts, strict=True)]


def _summary(res: dict, prefix: str) -> dict:
    """Failures and the worst energy error of a batch's per-trajectory fields."""
    ok = np.asarray(res["result"]) == 0
    err = np.asarray(res["energy_error_max"])[ok]
    its = np.asarray(res["newton_mean"])[ok]
    return {f"{prefix}_failed": int(np.sum(~ok)),
            f"{prefix}_energy_error_max": float(np.max(err)) if err.size else math.nan,
            f"{prefix}_newton_mean": float(np.mean(its)) if its.size else math.nan}


def _bench_row(model, method, s0, steps: int, batch: int, repeats: int, min_s: float,
               nb=None, name: str | None = None,
               single_compiles: int = SINGLE_COMPILES,
               batch_compiles: int = BATCH_COMPILES) -> tuple[dict, dict | None]:
    """The JAX rollout of ``method`` (one trajectory on one device, and the batch) and,
    with ``nb``, the Numba baseline of the method ``name`` (one trajectory on one core, the
    batch on all): ``(jax, numba)`` rows. Each side's runs alternate with the other's
    (:func:`_timed_alternating`); one trajectory is compiled ``single_compiles`` times and
    its speed is the median over them, the batch ``batch_compiles`` times and its first
    program timed; each compile time is the median over its compilations."""
    out: dict = {"engine": engine_name(method)}
    base: dict | None = None if nb is None else {}
    params = None if nb is None else nb.params_from_model(model)
    for label, n, devices, threads in (("single", 1, jax.devices()[:1], 1),
                                       ("batch", batch, None, None)):
        states = initial_conditions(model, s0, n, PERTURB, SEED)
        fn, args = batch_arguments(model, method, states, DT, steps, kind="metrics",
                                   devices=devices)
        dyn = args[:1] + args[2:]  # the static argument is baked into the compiled program
        fns, compile_s = [], []
        for k in range(single_compiles if label == "single" else batch_compiles):
            # Compiled again, not taken from JAX's caches, and its scalar programs built
            # again: every compile is timed as a fresh process (a cold sweep) pays it.
            jax.clear_caches()
            clear_scalar_programs()
            start = time.perf_counter()
            compiled = fn.lower(*args).compile()
            compile_s.append(time.perf_counter() - start)
            if label == "single" or not k:
                fns.append(lambda compiled=compiled, dyn=dyn: compiled(*dyn))
        out[f"{label}_compile_s"] = statistics.median(compile_s)
        out[f"{label}_compile_s_each"] = compile_s
        n_jax = len(fns)
        if nb is not None:
            arrays = _numpy_states(states)
            fns.append(lambda arrays=arrays, threads=threads: nb.sweep_metrics(
                name, *arrays, DT, steps, params, threads=threads))
        timed = _timed_alternating(fns, repeats, min_s=min_s)
        # The median over the compilations (one trajectory: a lottery per compilation,
        # SINGLE_COMPILES); each compilation's speed, slowest first, in `..._each`.
        ranked = sorted(timed[:n_jax], key=lambda t: t[0], reverse=True)
        best, runs, res = ranked[(n_jax - 1) // 2]
        out[f"{label}_steps_per_s"] = n * steps / best
        out[f"{label}_steps_per_s_each"] = [n * steps / t for t, _, _ in ranked]
        out[f"{label}_runs"] = runs
        out.update(_summary(res, label))
        if nb is not None:
            nb_best, nb_runs, (nb_res, _) = timed[n_jax]
            base[f"{label}_steps_per_s"] = n * steps / nb_best
            base[f"{label}_runs"] = nb_runs
            base.update(_summary(nb_res, label))
        if label == "batch":
            out["batch_wall_s"] = best
            try:
                mem = compiled.memory_analysis()
                out["batch_xla_memory_mb"] = (mem.argument_size_in_bytes
                                              + mem.output_size_in_bytes
                                              + mem.temp_size_in_bytes) / 2**20
            except Exception:  # memory_analysis is not available on every backend
                out["batch_xla_memory_mb"] = math.nan
    out["compile_s"] = out["single_compile_s"]  # (the names of earlier bench.json files)
    return out, base


def _numpy_states(states) -> list[np.ndarray]:
    return [np.ascontiguousarray(np.asarray(x)) for x in (states.R, states.mu, states.q,
                                                         states.p)]


def _throughput(systems, methods, engines, steps, batch, repeats, min_s, single_compiles,
                batch_compiles, nb, log) -> list[dict]:
    rows: list[dict] = []
    for system in systems:
        spec = lj.systems.get_system(system)
        model, s0 = spec.build()
        seen = set()
        for name in methods:
            for engine in engines:
                method = sweep_method(system, name, scalar=engine == "scalar")
                used = engine_name(method)
                if (name, used) in seen:
                    continue
                seen.add((name, used))
                has_base = (nb is not None and system == "car-pendulum"
                            and name.partition("@")[0] in nb.METHODS)
                jax_row, numba_row = _bench_row(model, method, s0, steps, batch, repeats,
                                                min_s, nb if has_base else None, name,
                                                single_compiles, batch_compiles)
                row = {"system": system, "method": name, "engine": used,
                       "engine_option": engine, "jax": jax_row, "numba": numba_row}
                if numba_row is not None:
                    for k in ("single", "batch"):
                        row[f"ratio_{k}"] = (row["jax"][f"{k}_steps_per_s"]
                                             / row["numba"][f"{k}_steps_per_s"])
                rows.append(row)
                j, n = row["jax"], row["numba"]
                each = j["single_steps_per_s_each"]
                msg = (f"  {system} {name} [{used}]: single {j['single_steps_per_s']:.3g} "
                       f"steps/s (compilations {each[0]:.3g}-{each[-1]:.3g}), batch "
                       f"{j['batch_steps_per_s']:.3g} steps/s "
                       f"({j['batch_failed']} failed), compile {j['single_compile_s']:.2f} + "
                       f"{j['batch_compile_s']:.2f} s")
                if n is not None:
                    msg += (f"; numba single {n['single_steps_per_s']:.3g}, batch "
                            f"{n['batch_steps_per_s']:.3g}; ratios {row['ratio_single']:.2f} "
                            f"/ {row['ratio_batch']:.2f}")
                log(msg)
    return rows


def _segment(n_steps: int) -> int:
    """The checkpoint segment: the largest divisor of ``n_steps`` at most its square root
    (memory ~ n/K + K)."""
    return max(k for k in range(1, math.isqrt(n_steps) + 1) if n_steps % k == 0)


def _gradient(methods, engines, steps: int, repeats: int, min_s: float, log) -> list[dict]:
    from lgvi_jax.integrators import with_scalar_newton

    model = lj.CarPendulum()
    s0 = model.default_state()
    K = _segment(steps)
    rows = []
    grads: dict[str, np.ndarray] = {}
    for name in methods:
        for engine in engines:
            method = with_scalar_newton(lj.RIGID_METHODS[name](), engine == "scalar")

            def loss(J, method=method):
                # A loss of the final state: how far the pendulum and the cart moved.
                traj = lj.simulate(eqx.tree_at(lambda m: m.J, model, J), method, s0, DT,
                                   steps, save_every=K, checkpoint_every=K)
                R, q = traj.state.R[-1], traj.state.q[-1]
                value = 0.5 * jnp.sum((R - s0.R) ** 2) + 0.5 * jnp.sum((q - s0.q) ** 2)
                return value, traj.result

            row: dict = {"method": name, "engine": engine, "steps": steps,
                         "checkpoint_every": K}
            labels = ("forward", "gradient")
            runs_of = []
            for label, fn in zip(labels, (loss, jax.grad(loss, has_aux=True)), strict=True):
                start = time.perf_counter()
                compiled = jax.jit(fn).lower(model.J).compile()
                row[f"{label}_compile_s"] = time.perf_counter() - start
                runs_of.append(lambda c=compiled: c(model.J))
            # Alternated, so that the ratio compares runs under the same load.
            for label, (best, runs, (value, code)) in zip(
                    labels, _timed_alternating(runs_of, repeats, min_s=min_s), strict=True):
                row[f"{label}_s"] = best
                row[f"{label}_runs"] = runs
                row[f"{label}_failed"] = int(code) != 0
                if label == "forward":
                    row["loss"] = float(value)
                else:
                    g = np.asarray(value)
                    grads[f"{name}/{engine}"] = g
                    row["gradient_norm"] = float(np.linalg.norm(g))
            row["gradient_over_forward"] = row["gradient_s"] / row["forward_s"]
            ref = grads.get(f"{name}/{engines[0]}")
            g = grads[f"{name}/{engine}"]
            row["gradient_rel_diff"] = (float(np.max(np.abs(g - ref)) / np.max(np.abs(ref)))
                                        if ref is not None else math.nan)
            rows.append(row)
            log(f"  grad {name} [{engine}], {steps} steps (checkpoint every {K}): forward "
                f"{row['forward_s'] * 1e3:.1f} ms, gradient {row['gradient_s'] * 1e3:.1f} ms "
                f"({row['gradient_over_forward']:.2f}x), compile {row['forward_compile_s']:.1f}"
                f" + {row['gradient_compile_s']:.1f} s")
    return rows


def _fit(quick: bool, log) -> dict:
    from lgvi_jax import identify
    from lgvi_jax.inertia import centroidal_inertia, pivot_inertia
    from lgvi_jax.models.rigid_bodies import PAPER_J, PAPER_RHO_C

    J_c_true = np.asarray(FIT_J_C_TRUE)
    true = lj.CarPendulum(J=np.asarray(pivot_inertia(J_c_true, 1.0, PAPER_RHO_C)))
    t_final = FIT_T_FINAL_QUICK if quick else FIT_T_FINAL
    times = FIT_OBS_EVERY * np.arange(round(t_final / FIT_OBS_EVERY) + 1)
    data = identify.observe(true, times)  # the independent reference (SciPy DOP853)
    obs = identify.check_observations(data, DT)
    result = identify.fit(obs, DT, names=("J",))  # defaults: lgvi, Gauss-Newton, 300 iterations

    def rel(a, b):
        return float(np.linalg.norm(np.asarray(a) - b) / np.linalg.norm(b))

    out = {"dt": DT, "t_final": t_final, "observations": len(times),
           "method": result.method, "optimizer": result.optimizer,
           # the engine the fit ran on (make_loss resolves the method's name as fit does)
           "engine": engine_name(identify.make_loss(obs, DT, names=("J",))[2].method),
           "wall_s": result.wall_time_s, "compile_s": result.compile_time_s,
           "iterations": result.iterations, "stopped": result.stopped,
           "start_rel_error_J_c": rel(centroidal_inertia(
               np.asarray(PAPER_J), 1.0, np.asarray(PAPER_RHO_C)), J_c_true),
           "rel_error_J_c": rel(result.J_c, J_c_true),
           "rel_error_J": rel(result.model.J, np.asarray(true.J)),
           "loss_initial": result.loss_initial, "loss_final": result.loss_final}
    log(f"  fit J ({result.optimizer}, {result.method}, h = {DT:g}, {len(times)} "
        f"observations over {t_final:g} s): relative error of J_c {out['rel_error_J_c']:.3%}, "
        f"{result.iterations} iterations ({result.stopped}), {result.wall_time_s:.1f} s")
    return out


def _sweep_end_to_end(systems, steps: int, batch: int, nb, log) -> list[dict]:
    """Wall clock of ``lgvi-jax sweep`` in fresh processes, cold and warm (module
    docstring, part 4), and the Numba Hamel batched run of the same work."""
    rows = []
    for system in systems:
        with tempfile.TemporaryDirectory() as tmp:
            # The cold runs each in an empty cache folder; the warm runs in the last one's.
            caches = [Path(tmp) / f"cache{k}" for k in range(SWEEP_COLD_RUNS)]
            caches += [caches[-1]] * SWEEP_WARM_RUNS
            walls = []
            for k, cache in enumerate(caches):
                args = [sys.executable, "-m", "lgvi_jax.cli", "sweep", system, "--method",
                        "hamel", "--dt", str(DT), "--t-final", f"{steps * DT:g}", "--n",
                        str(batch), "--perturb", str(PERTURB), "--seed", str(SEED),
                        "--out", str(Path(tmp) / f"out{k}"), "--json"]
                start = time.perf_counter()
                proc = subprocess.run(args, capture_output=True, text=True,
                                      env={**os.environ, "LGVI_JAX_CACHE_DIR": str(cache)},
                                      check=False)
                walls.append(time.perf_counter() - start)
                if proc.returncode != 0:
                    raise RuntimeError(f"sweep {system} failed: {proc.stderr[-2000:]}")
            summary = json.loads((Path(tmp) / "out0" / "summary.json").read_text())
        cold = walls[:SWEEP_COLD_RUNS]
        row = {"system": system, "method": "hamel", "n": batch, "steps": steps,
               "engine": engine_name(sweep_method(system, "hamel")),
               "cold_s": statistics.median(cold), "cold_s_each": cold,
               "warm_s": walls[SWEEP_COLD_RUNS:],
               "energy_error_max": summary["rows"][0]["energy_error_max_max"],
               "numba_run_s": None}
        if nb is not None and system == "car-pendulum":
            model, s0 = lj.systems.get_system(system).build()
            arrays = _numpy_states(initial_conditions(model, s0, batch, PERTURB, SEED))
            params = nb.params_from_model(model)
            row["numba_run_s"], _, _ = _timed(
                lambda a=arrays, p=params: nb.sweep_metrics("hamel", *a, DT, steps, p), 2)
        rows.append(row)
        log(f"  {system}: cold {row['cold_s']:.2f} s (median of "
            + ", ".join(f"{w:.2f}" for w in cold) + "), warm "
            + ", ".join(f"{w:.2f}" for w in row["warm_s"]) + " s"
            + (f"; Numba's compiled run {row['numba_run_s']:.2f} s" if row["numba_run_s"]
               else ""))
    return rows


def _long_run_memory(n_steps: int, log) -> dict:
    """Peak resident memory of ``lgvi-jax simulate`` over ``n_steps`` (child process)."""
    with tempfile.TemporaryDirectory() as tmp:
        # The child's own high-water mark: VmHWM of /proc/self/status belongs to the
        # address space the child built after exec. Its ru_maxrss would not do: Linux
        # keeps the maximum across execve, so it starts at the size of the forked
        # benchmark process, whatever the run.
        script = (
            "import resource, sys; from lgvi_jax.cli import main; "
            "code = main(sys.argv[1:]); "
            "hwm = [l.split()[1] for l in open('/proc/self/status') if l.startswith('VmHWM')] "
            "if sys.platform.startswith('linux') else []; "
            "print(int(hwm[0]) / 1024.0 if hwm else "
            "resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0); "
            "sys.exit(code)"
        )
        args = [sys.executable, "-c", script, "simulate", "car-pendulum", "--method", "lgvi",
                "--dt", str(DT), "--t-final", f"{n_steps * DT:g}", "--save-every", "1000",
                "--out", str(Path(tmp) / "run.npz"), "--json"]
        start = time.perf_counter()
        proc = subprocess.run(args, capture_output=True, text=True, check=False)
        wall = time.perf_counter() - start
        if proc.returncode != 0:
            raise RuntimeError(f"long run failed: {proc.stderr[-2000:]}")
        lines = proc.stdout.strip().splitlines()
        report = json.loads(lines[0])
        out = {"n_steps": n_steps, "save_every": 1000, "saved_states": n_steps // 1000 + 1,
               "peak_rss_mb": float(lines[-1]), "wall_s": wall,
               "steps_per_s": report["steps_per_second"],
               "energy_error_max": report["energy_error_max"]}
    log(f"  {n_steps:.0e} steps, save every 1000: peak RSS {out['peak_rss_mb']:.0f} MB, "
        f"{out['steps_per_s']:.3g} steps/s")
    return out


def _environment() -> dict:
    """What a result depends on beyond its options: versions, the CPU (the same command
    measures differently on another one), the XLA settings and the devices."""
    from lgvi_jax import _xla

    devices = jax.devices()
    return {"jax": jax.__version__, "python": platform.python_version(),
            "machine": platform.machine(), "cpu": _xla.cpu_model(), "cpu_count": os.cpu_count(),
            "avx512": _xla._wide_vectors(), "avx2": "avx2" in _xla._cpu_flags(),
            "xla_settings": list(_xla.added()),
            "devices": [str(d) for d in devices], "platform": devices[0].platform,
            "device_kind": devices[0].device_kind}


def _load_numba(methods: Sequence[str], log):
    """The Numba baselines, compiled for ``methods`` (``None`` without Numba), and what
    was used."""
    try:
        from lgvi_jax.bench import numba_lgvi as nb
    except ImportError as err:
        log(f"Numba baseline unavailable ({err}); install the bench extra: "
            "pip install 'lgvi_jax[bench]'")
        return None, None
    import numba

    bases = {m.partition("@")[0] for m in methods} & set(nb.METHODS)
    # One compiled loop for lgvi, one for every Hamel method.
    kernels = tuple(k for k in ("lgvi", "hamel")
                    if any((b == "lgvi") == (k == "lgvi") for b in bases))
    start = time.perf_counter()
    nb.warmup(kernels)
    return nb, {"version": numba.__version__, "threads": numba.get_num_threads(),
                "compile_s": time.perf_counter() - start}


def run(out_dir: Path | str, quick: bool = False, log: Callable = print, *,
        steps: int | None = None, batch: int | None = None,
        methods: Sequence[str] | None = None, systems: Sequence[str] = SYSTEMS,
        engines: Sequence[str] | None = None, parts: Sequence[str] | None = None,
        long_run: bool = True) -> dict:
    """Run the benchmark into ``out_dir`` (``bench.json``, ``bench.md``); returns the
    results. ``quick``: small sizes (1000 steps, batch 64, 2 repeats, 2 compilations of
    each program) and, unless given,
    :data:`QUICK_METHODS`, :data:`QUICK_ENGINES`, :data:`QUICK_PARTS` (module
    docstring)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    steps = steps or (1000 if quick else 10_000)
    batch = batch or (64 if quick else 1024)
    repeats = 2 if quick else 3
    min_s = 0.0 if quick else MIN_TIME_S
    single_compiles = 2 if quick else SINGLE_COMPILES
    batch_compiles = 2 if quick else BATCH_COMPILES
    methods = tuple(methods or (QUICK_METHODS if quick else METHODS))
    engines = tuple(engines or (QUICK_ENGINES if quick else ENGINES))
    parts = tuple(parts or (QUICK_PARTS if quick else DEFAULT_PARTS))
    systems = tuple(systems)
    env = _environment()
    results: dict = {"quick": quick, "dt": DT, "steps": steps, "batch": batch,
                     "perturb": PERTURB, "seed": SEED, "repeats": repeats,
                     "min_time_s": min_s, "single_compiles": single_compiles,
                     "batch_compiles": batch_compiles,
                     "time_budget_s": TIME_BUDGET_S, "systems": list(systems),
                     "methods": list(methods), "engines": list(engines),
                     "parts": list(parts), "numba": None, "environment": env}
    if "throughput" in parts:
        uses_numba = "car-pendulum" in systems
        nb, results["numba"] = _load_numba(methods, log) if uses_numba else (None, None)
        log(f"throughput: h = {DT}, {steps} steps, batch {batch}, metrics every step, on "
            f"{len(env['devices'])} {env['platform']} device(s)")
        results["throughput"] = _throughput(systems, methods, engines, steps, batch, repeats,
                                            min_s, single_compiles, batch_compiles, nb,
                                            log)
    if "gradient" in parts:
        grad_methods = tuple(m for m in GRAD_METHODS if m in methods) or GRAD_METHODS[:1]
        grad_engines = GRAD_ENGINES[:1] if quick else GRAD_ENGINES
        log(f"gradient: jax.grad through {steps} steps of one car-pendulum trajectory")
        results["gradient"] = _gradient(grad_methods, grad_engines, steps, repeats, min_s,
                                        log)
    if "fit" in parts:
        log("fit: the inertia from noise-free synthetic observations")
        results["fit"] = _fit(quick, log)
    if "sweep" in parts:
        nb, info = _load_numba(("hamel",), log) if "car-pendulum" in systems else (None, None)
        results["numba"] = results["numba"] or info
        log(f"sweep end to end: hamel, {batch} trajectories x {steps} steps, fresh processes")
        results["sweep"] = _sweep_end_to_end(systems, steps, batch, nb, log)
    results["process_peak_rss_mb"] = _rss_mb()
    if long_run:
        results["long_run"] = [_long_run_memory(n, log)
                               for n in ((10_000, 100_000) if quick else (100_000, 1_000_000))]
    atomic_write_text(out_dir / "bench.md", _markdown(results))
    atomic_write_json(out_dir / "bench.json", results)
    log(f"wrote {out_dir / 'bench.json'} and {out_dir / 'bench.md'}")
    return results


def _g(x, spec: str = ".3g") -> str:
    """``x`` formatted by ``spec``, ``n/a`` when missing or not finite."""
    return format(x, spec) if x is not None and math.isfinite(x) else "n/a"


def _markdown(r: dict) -> str:
    env = r["environment"]
    numba = r.get("numba")
    lines = [
        f"# Benchmark: h = {r['dt']}, {r['steps']} steps",
        "",
        f"{len(env['devices'])} {env['platform']} device(s) ({env['device_kind']}), "
        f"{env['cpu_count']} CPU cores ({env.get('cpu', 'unknown')}"
        + (", AVX-512" if env.get("avx512") else ", AVX2" if env.get("avx2") else "")
        + f"), jax {env['jax']}"
        + (f", Numba {numba['version']} with {numba['threads']} threads" if numba
           else ", no Numba baseline") + ". Best of at least "
        f"{r['repeats']} runs after compilation and {r.get('min_time_s', 0.0):g} s of runs "
        f"(fewer once a side's runs took {r.get('time_budget_s', TIME_BUDGET_S):g} s), the "
        "sides of a ratio alternated run by run; one trajectory: the median over "
        f"{r.get('single_compiles', 1)} compilations of its program (each compilation's "
        "speed in bench.json); compile times cold (ahead of time, no persistent cache, "
        "every program traced and built afresh as in a fresh process), each the median over "
        f"its compilations ({r.get('single_compiles', 1)} of one trajectory's program, "
        f"{r.get('batch_compiles', 1)} of the batch's; each one in bench.json).",
    ]
    if "throughput" in r:
        lines += [
            "",
            f"## Throughput of the sweep's work (metrics every step; one trajectory, and a "
            f"batch of {r['batch']})",
            "",
            WORK + " Engines: *scalar* (the autodiff engine solving on scalars, what the "
            "sweep runs), *general* (the autodiff engine on arrays). Ratio = JAX / Numba steps per "
            "second.",
            "",
            "| system | method | engine | JAX 1 traj (steps/s) | Numba 1 traj | ratio | "
            f"JAX batch of {r['batch']} (steps/s) | Numba batch (all cores) | ratio | "
            "failed (JAX, Numba) | max energy error (JAX, Numba) | compile (s) 1 traj, "
            "batch | batch program memory (MB) |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for row in r["throughput"]:
            j, n = row["jax"], row.get("numba")

            def nb_cell(key, n=n):
                return _g(n[key]) if n else "n/a"

            failed = f"{j['batch_failed'] + j['single_failed']}, " + (
                f"{n['batch_failed'] + n['single_failed']}" if n else "n/a")
            energy = f"{_g(j['batch_energy_error_max'], '.2e')}, " + (
                _g(n["batch_energy_error_max"], ".2e") if n else "n/a")
            lines.append(
                f"| {row['system']} | {row['method']} | {row['engine']} | "
                f"{_g(j['single_steps_per_s'])} | {nb_cell('single_steps_per_s')} | "
                f"{_g(row.get('ratio_single'), '.2f')} | {_g(j['batch_steps_per_s'])} | "
                f"{nb_cell('batch_steps_per_s')} | {_g(row.get('ratio_batch'), '.2f')} | "
                f"{failed} | "
                f"{energy} | {j['single_compile_s']:.2f}, {j['batch_compile_s']:.2f} | "
                f"{j['batch_xla_memory_mb']:.2f} |")
    if "gradient" in r:
        rows = r["gradient"]
        lines += [
            "",
            f"## Gradient through {rows[0]['steps'] if rows else r['steps']} steps",
            "",
            "`jax.grad` of a loss of the final state (½‖R_N − R_0‖² + ½|q_N − q_0|²) with "
            "respect to the inertia J, one car-pendulum trajectory from the paper's state, "
            "through the library's rollout with checkpoints (`simulate(..., "
            "checkpoint_every=K)`; implicit-function-theorem derivatives of every Newton "
            "solve), against the same rollout forward. Engines: *array* (the autodiff "
            "engine on small arrays, `with_scalar_newton(method, False)`) and *scalar* "
            "(on scalars, the default of the Lie-group VIs).",
            "",
            "| method | engine | K | forward (ms) | gradient (ms) | gradient / forward | "
            "compile (s) forward, gradient | gradient vs first engine (rel.) |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for row in rows:
            lines.append(
                f"| {row['method']} | {row['engine']} | {row['checkpoint_every']} | "
                f"{row['forward_s'] * 1e3:.3g} | {row['gradient_s'] * 1e3:.3g} | "
                f"{row['gradient_over_forward']:.2f} | {row['forward_compile_s']:.1f}, "
                f"{row['gradient_compile_s']:.1f} | "
                + (f"{row['gradient_rel_diff']:.1e}" if math.isfinite(
                    row["gradient_rel_diff"]) and row["engine"] != GRAD_ENGINES[0] else "–")
                + " |")
    if "fit" in r:
        f = r["fit"]
        lines += [
            "",
            "## Fit: the inertia recovered from a trajectory",
            "",
            f"`lgvi_jax.identify.fit(obs, {f['dt']:g}, names=(\"J\",))` with its defaults "
            f"(`{f['method']}` on the {f['engine']} autodiff engine, {f['optimizer']}, "
            "horizon continuation): noise-free observations of R and q every "
            f"{FIT_OBS_EVERY:g} s over {f['t_final']:g} s from the independent reference "
            "(DOP853 at 1e-13) for J_c = diag(0.03, 0.05, 0.04) about the mass centre, "
            f"from the paper's J ({f['start_rel_error_J_c']:.0%} off). The error left is the "
            "integrator's O(h²) bias, absorbed into the inertia.",
            "",
            "| wall time (s) | of which the first iteration (compile) | iterations | stopped "
            "| relative error of J_c | relative error of J (pivot) |",
            "|---|---|---|---|---|---|",
            f"| {f['wall_s']:.1f} | {f['compile_s']:.1f} | {f['iterations']} | {f['stopped']} "
            f"| {f['rel_error_J_c']:.3%} | {f['rel_error_J']:.3%} |",
        ]
    if r.get("sweep"):
        rows = r["sweep"]
        ref = next((x["numba_run_s"] for x in rows if x["numba_run_s"]), None)
        car = next((x for x in rows if x["system"] == "car-pendulum"), None)
        lines += [
            "", "## A sweep end to end", "",
            f"`lgvi-jax sweep SYSTEM --method hamel --dt {r['dt']:g} --t-final "
            f"{r['steps'] * r['dt']:g} --n {r['batch']} --perturb {PERTURB:g} --seed {SEED}`, "
            "metrics every step, a fresh process each: *cold* with an empty cache folder "
            f"(`LGVI_JAX_CACHE_DIR`; the median of {SWEEP_COLD_RUNS} runs, each in "
            "bench.json), *warm* the same command again (compiled and traced "
            "programs reused). Numba: the Hamel baseline's compiled batched run of the same "
            "work with the same per-step diagnostics, all cores (run time only, after its "
            "compilation). Ratio = Numba's run / our wall clock (≥ 1: we are faster).",
            "",
            "| system | engine | cold (s) | warm (s) | Numba's run (s) | ratio cold, best warm "
            "| vs the car-pendulum (cold, best warm) |",
            "|---|---|---|---|---|---|---|",
        ]
        for x in rows:
            best = min(x["warm_s"])
            ratio = (f"{ref / x['cold_s']:.2f}, {ref / best:.2f}" if ref else "n/a")
            rel = (f"{x['cold_s'] / car['cold_s']:.2f}, {best / min(car['warm_s']):.2f}"
                   if car else "n/a")
            lines.append(f"| {x['system']} | {x['engine']} | {x['cold_s']:.2f} | "
                         + ", ".join(f"{w:.2f}" for w in x["warm_s"])
                         + f" | {_g(ref, '.2f')} | {ratio} | {rel} |")
    if r.get("long_run"):
        lines += ["", "## Memory of long runs", "",
                  "`lgvi-jax simulate car-pendulum --method lgvi --save-every 1000`, child "
                  "process:", "",
                  "| steps | saved states | peak RSS (MB) | steps/s |", "|---|---|---|---|"]
        for lr in r["long_run"]:
            lines.append(f"| {lr['n_steps']} | {lr['saved_states']} | {lr['peak_rss_mb']:.0f} "
                         f"| {lr['steps_per_s']:.3g} |")
    lines += ["", f"Peak resident memory of the benchmark process: "
              f"{r['process_peak_rss_mb']:.0f} MB."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(script_main(run, __doc__))
