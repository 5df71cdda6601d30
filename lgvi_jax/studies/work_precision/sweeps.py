"""The plan of the work-precision study and its sweeps: which methods, steps and tolerances
each system gets (:func:`config`, full or quick), every run measured; the long horizon; the
batch throughput at matched accuracy.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from lgvi_jax.studies import EUCLIDEAN_METHOD_NAMES, RIGID_METHOD_NAMES
from lgvi_jax.systems import resolve_methods

from . import runners
from .cases import Case, _scipy_y0
from .metrics import measure
from .runners import _diffrax_fn, _time_best, run_diffrax, run_ours, run_scipy

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
#: lgvi@8 ~15 lgvi steps per step (its largest step that keeps the energy within 1e-6 over
#: 5000 s is about 0.125; 0.2 gives 8e-5), a Lie-group Galerkin step ~100 (solved on small
#: arrays).
LONG_STEPS_OVERRIDE = {"rigid": {"gl4": (0.1,), "lgvi@8": (0.125, 0.1), "galerkin4": (0.05,),
                                 "galerkin6": (0.1,)}, "oscillator": {}}
#: diffrax and SciPy settings: rtol = atol.
DIFFRAX_TOLS = {"tsit5": (1e-4, 1e-6, 1e-8, 1e-10, 1e-12),
                "dopri8": (1e-5, 1e-7, 1e-9, 1e-11, 1e-13)}
DIFFRAX_FIXED = {"tsit5": (0.05, 0.02, 0.01, 0.005, 0.0025),
                 "dopri8": (0.1, 0.05, 0.025, 0.01, 0.005)}
#: Long runs: Dopri8 down to 1e-13, so that the all-invariants regime asks the peer's
#: tightest tolerance too.
DIFFRAX_LONG_TOLS = {"tsit5": (1e-6, 1e-9), "dopri8": (1e-7, 1e-10, 1e-13)}
SCIPY_TOLS = {"DOP853": (1e-5, 1e-7, 1e-9, 1e-11), "RK45": (1e-4, 1e-6, 1e-8)}
SCIPY_LONG_TOLS = {"DOP853": (1e-9,)}  # oscillator only (car-pendulum: see summary)
#: Targets of the regimes.
TARGETS = {"short_tight": 1e-8, "short_mid": 1e-5, "short_moderate": 1e-4, "t50": 1e-5,
           "long_energy": 1e-6, "long_invariants": 1e-9}


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
        "repeats": runners.REPEATS,
    }


def _order_key(order: int) -> str:
    return "2" if order <= 2 else "4" if order <= 5 else "6"


def _sweep_system(system: Case, cfg: dict, log: Callable) -> dict:
    """All runs of one system at the short horizons; returns ``{"runs": [...], ...}``."""
    rigid = system.rigid
    names = cfg["rigid_methods"] if rigid else cfg["euclidean_methods"]
    methods, skipped = resolve_methods(system.system_name, names)
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
        if runners.diffrax is not None and system.key in cfg["diffrax_systems"]:
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


def _long_runs(system: Case, cfg: dict, log: Callable) -> list[dict]:
    """The long horizon: one step per method of ours, a few tolerances per peer."""
    T = cfg["long_horizon"]
    n_saves = cfg["saves"]["long"]
    names = cfg["rigid_methods"] if system.rigid else cfg["euclidean_methods"]
    methods, _ = resolve_methods(system.system_name, names)
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
    if runners.diffrax is not None and system.key in cfg["diffrax_systems"]:
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


def _batch(system: Case, short: list[dict], cfg: dict, log: Callable) -> dict:
    """Batch throughput at matched accuracy (the package docstring)."""
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
    # Each diffrax solver (adaptive and fixed-step apart) at its cheapest setting meeting the
    # target: the fastest on one trajectory need not be the fastest batched (an adaptive
    # step size under vmap follows the slowest member). SciPy runs serially: its fastest.
    peers = [r for r in best.values() if r["family"] == "diffrax"]
    scipy_rows = [r for r in best.values() if r["family"] == "scipy"]
    if scipy_rows:
        peers.append(min(scipy_rows, key=lambda r: r["wall_s"]))
    states = initial_conditions(system.model, system.state0, B, cfg["batch_perturb"], 0)
    device = jax.devices()[:1]
    out = {"batch": B, "horizon": T, "target": target, "devices": [str(d) for d in device],
           "rows": []}
    methods, _ = resolve_methods(system.system_name, [r["method"] for r in ours])
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
