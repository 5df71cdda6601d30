"""Benchmark: ``identify.fit``'s Levenberg–Marquardt against optimistix's least-squares
solvers on the same fits.

The problems are those of ``lgvi_jax/studies/identify_inertia.py`` (and of ``lgvi-jax bench``
part 3): the car-pendulum's inertia about the mass centre recovered from observations of
the independent reference (hand-derived equations, SciPy DOP853 at 1e-13) every 0.05 s,
starting from the paper's inertia (20% away), ``lgvi`` rollouts, the fit's horizon
continuation and stopping rule (relative loss change <= 1e-10 for 3 iterations), at most
300 iterations:

* ``clean-h0.005``: noise-free, 5 s, h = 0.005 (1000 steps);
* ``noisy-h0.01``: noise sigma = 1e-3, 5 s, h = 0.01;
* ``short-h0.01``: noise-free, 1 s, h = 0.01 (the tests' short fit).

Solvers, all driven by ``fit``'s loop (one solver step per iteration, host-side, so that
the progress bar, the callback and the stopping rule are the same):

* ``ours``: ``fit(optimizer="gauss-newton")`` (``identify._LevenbergMarquardt``: Marquardt's
  ``diag(JᵀJ)`` scaling, initial damping 1e-3, forward-mode Jacobian in one program);
* ``optx-lm``: :class:`optimistix.LevenbergMarquardt` (its trust-region damping ``λI``,
  initial ``λ = 1``; its Jacobian by :func:`jax.linearize`, its default ``jac="fwd"``);
* ``optx-lm-1e-9``: the same with the initial ``λ = 1e-9`` (the best of 1, 1e-3, 1e-6, 1e-9
  on ``short-h0.01``: chosen after the fact);
* ``optx-gn``: :class:`optimistix.GaussNewton` (full steps, no damping).

Each run is a fresh process (cold: tracing and compilation included) which then repeats the
same fit (warm: the compiled programs reused, i.e. the run time alone). Runs alternate
between solvers, repeated ``--repeats`` times, and wait for the machine's 1-minute load
average to fall below ``--max-load`` before each.

Run:  ``python experiments/compare_least_squares.py --out DIR [--cases ...] [--solvers ...]``
→ ``DIR/compare_least_squares.{jsonl,md}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from lgvi_jax._io import atomic_write_text

J_C_TRUE = np.diag([0.03, 0.05, 0.04])
#: case -> (step h, observed span in s, noise sigma)
CASES = {"clean-h0.005": (0.005, 5.0, 0.0), "noisy-h0.01": (0.01, 5.0, 1e-3),
         "short-h0.01": (0.01, 1.0, 0.0)}
SOLVERS = ("ours", "optx-lm", "optx-lm-1e-9", "optx-gn")


# ------------------------------------------------------------------ optimistix in fit()


def _install_optimistix():
    """Teach ``identify.fit`` the optimiser names ``optx-lm[-λ0]`` and ``optx-gn``: one
    optimistix solver step per ``fit`` iteration (optimistix's ``init``/``step`` interface,
    each compiled once), the loss being ``|r|²`` at the solver's accepted iterate."""
    import equinox as eqx
    import jax.numpy as jnp
    import optimistix as optx

    from lgvi_jax import identify

    solvers = {"lm": optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12),
               "gn": optx.GaussNewton(rtol=1e-12, atol=1e-12)}

    def residuals(params, problem):
        return identify._residuals(params, problem), None

    @eqx.filter_jit
    def init(solver, params, problem, step_size):
        f_struct = eqx.filter_eval_shape(identify._residuals, params, problem)
        state = solver.init(residuals, params, problem, {}, f_struct, None, frozenset())
        if hasattr(state.search_state, "step_size"):  # LM: λ = 1 / step size
            state = eqx.tree_at(lambda s: s.search_state.step_size, state, step_size)
        return state

    @eqx.filter_jit
    def step(solver, params, state, problem):
        y, state, _ = solver.step(residuals, params, problem, {}, state, frozenset())
        return y, state, jnp.sum(state.f_info.residual**2)

    class State:
        def __init__(self, inner=None):
            self.inner = inner

    @dataclasses.dataclass(frozen=True)
    class Optimistix:
        solver: Any
        damping0: float

        def init(self, params):
            return State()

        def step(self, params, state, problem):
            inner = state.inner
            if inner is None:  # (a dynamic step size: one compilation for every λ0)
                inner = init(self.solver, params, problem,
                             jnp.asarray(1.0 / self.damping0, jnp.float64))
            y, inner, value = step(self.solver, params, inner, problem)
            return y, State(inner), value

    def parse(name):
        kind, _, lam = name.removeprefix("optx-").partition("-")
        return Optimistix(solvers[kind], float(lam) if lam else 1.0)

    optimizer, loss_value = identify._optimizer, identify._loss_value

    def _optimizer(name, lr):
        return parse(name) if name.startswith("optx-") else optimizer(name, lr)

    def _loss_value(name, params, problem):
        if not name.startswith("optx-"):
            return loss_value(name, params, problem)
        opt = parse(name)  # the first step evaluates at params and stays there
        return float(opt.step(params, opt.init(params), problem)[2])

    identify._optimizer, identify._loss_value = _optimizer, _loss_value


# ------------------------------------------------------------------------------ one run


def _data(case: str, folder: Path):
    from lgvi_jax import identify
    from lgvi_jax.inertia import pivot_inertia
    from lgvi_jax.models import CarPendulum
    from lgvi_jax.models.rigid_bodies import PAPER_RHO_C

    dt, span, noise = CASES[case]
    path = folder / f"data-{case}.npz"
    if not path.exists():
        true = CarPendulum(J=np.asarray(pivot_inertia(J_C_TRUE, 1.0, PAPER_RHO_C)))
        times = 0.05 * np.arange(round(span / 0.05) + 1)
        np.savez(path, **identify.observe(true, times, noise=noise, seed=0))
    return identify.check_observations(dict(np.load(path)), dt), dt


def run_one(solver: str, case: str, folder: Path) -> dict:
    from lgvi_jax import identify

    _install_optimistix()
    obs, dt = _data(case, folder)
    optimizer = "gauss-newton" if solver == "ours" else solver
    rows = {}
    for run in ("cold", "warm"):
        t0 = time.perf_counter()
        r = identify.fit(obs, dt, names=("J",), optimizer=optimizer, iterations=300)
        wall = time.perf_counter() - t0
        rows[run] = {"wall_s": wall, "compile_s": r.compile_time_s,
                     "iterations": r.iterations, "stopped": r.stopped,
                     "loss_final": r.loss_final,
                     "rel_error_J_c": float(np.linalg.norm(r.J_c - J_C_TRUE)
                                            / np.linalg.norm(J_C_TRUE))}
    return {"solver": solver, "case": case, **rows}


# ------------------------------------------------------------------------------- driver


def _wait_for_quiet(max_load: float, log) -> float:
    while (load := os.getloadavg()[0]) > max_load:
        log(f"  load {load:.2f} > {max_load}: waiting a minute")
        time.sleep(60)
    return load


def table(rows: list[dict]) -> str:
    lines = ["| case | solver | iterations | stopped | compile (s) | run (s) | final loss "
             "| error of J_c |", "|---|---|---|---|---|---|---|---|"]
    by_key: dict[tuple, list[dict]] = {}
    for r in rows:
        by_key.setdefault((r["case"], r["solver"]), []).append(r)
    for (case, solver), rs in by_key.items():
        # compile: the cold fit's wall time less the warm fit's (same iterations); run:
        # the warm fit's wall time. Each as min-max over the repeats.
        comp = [r["cold"]["wall_s"] - r["warm"]["wall_s"] for r in rs]
        run = [r["warm"]["wall_s"] for r in rs]
        w = rs[0]["warm"]

        def span(xs):
            return f"{min(xs):.2f}" if len(xs) == 1 else f"{min(xs):.2f}–{max(xs):.2f}"

        lines.append(f"| {case} | {solver} | {w['iterations']} | {w['stopped']} | "
                     f"{span(comp)} | {span(run)} | {w['loss_final']:.4e} | "
                     f"{w['rel_error_J_c']:.4e} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--cases", default=",".join(CASES))
    parser.add_argument("--solvers", default=",".join(SOLVERS))
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--max-load", type=float, default=2.5)
    parser.add_argument("--one", nargs=2, metavar=("SOLVER", "CASE"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.one:
        print(json.dumps(run_one(*args.one, out)))
        return 0
    log = print
    results = out / "compare_least_squares.jsonl"
    rows = []
    for case in args.cases.split(","):
        _data(case, out)  # written once, before the timed runs
        for rep in range(args.repeats):
            for solver in args.solvers.split(","):
                load = _wait_for_quiet(args.max_load, log)
                proc = subprocess.run([sys.executable, __file__, "--out", str(out), "--one",
                                       solver, case], capture_output=True, text=True,
                                      check=True)
                row = {**json.loads(proc.stdout.strip().splitlines()[-1]), "repeat": rep,
                       "load_before": load}
                rows.append(row)
                atomic_write_text(results, "".join(json.dumps(r) + "\n" for r in rows))
                c, w = row["cold"], row["warm"]
                log(f"{case} {solver} #{rep}: {w['iterations']} it ({w['stopped']}), cold "
                    f"{c['wall_s']:.2f} s, warm {w['wall_s']:.2f} s, loss "
                    f"{w['loss_final']:.4e}, error {w['rel_error_J_c']:.3e} (load {load:.2f})")
    atomic_write_text(out / "compare_least_squares.md", table(rows) + "\n")
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
