"""Benchmark: the cost of one Newton solve for the small systems of implicit steps.

Times, after compilation, 10^4 consecutive solves of a nonlinear n x n system
``F(y) = A y + 0.1 sin(y) − b`` (n = 3, 6, 12, the sizes of the Lie-group steps to come)
inside one ``lax.scan``, so that Python dispatch is excluded, and whole implicit steps on the
harmonic oscillator (Gauss–Legendre: 4 unknowns, Galerkin: 2 unknowns). Each is run with the
default unrolled elimination and, as the baseline in the same run, with LAPACK's LU
(``jnp.linalg.solve``), and with the chord (frozen-Jacobian) variant.

Run:  ``python experiments/bench_newton.py --out DIR``  → ``DIR/bench_newton.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import lgvi_jax
from lgvi_jax._io import atomic_write_text
from lgvi_jax.integrators import GalerkinVI, GaussLegendre
from lgvi_jax.models import HarmonicOscillator
from lgvi_jax.newton import Newton, newton_solve
from lgvi_jax.simulate import simulate_timed

VARIANTS = {
    "unrolled": Newton(),
    "lu (baseline)": Newton(linear_solver="lu"),
    "chord + unrolled": Newton(chord=True, max_steps=50),
}
N_SOLVES = 10_000


def _residual(y, args):
    A, b = args
    return A @ y + 0.1 * jnp.sin(y) - b


def time_solves(n: int, solver: Newton, repeats: int = 3) -> dict:
    rng = np.random.default_rng(n)
    A = jnp.asarray(np.eye(n) * 3 + rng.normal(size=(n, n)) / np.sqrt(n))
    bs = jnp.asarray(rng.normal(size=(N_SOLVES, n)))

    @jax.jit
    def run(bs):
        def body(y, b):
            sol = newton_solve(_residual, y, (A, b), solver)
            return sol.value, sol.newton_steps

        return jax.lax.scan(body, jnp.zeros(n), bs)

    jax.block_until_ready(run(bs))  # compile
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        _, steps = jax.block_until_ready(run(bs))
        best = min(best, time.perf_counter() - start)
    return {"us_per_solve": best / N_SOLVES * 1e6, "iterations_mean": float(np.mean(steps))}


def time_steps(method_factory, solver: Newton, n_steps: int = 100_000) -> dict:
    model = HarmonicOscillator()
    best = np.inf
    for _ in range(3):
        traj, timing = simulate_timed(model, method_factory(solver), model.default_state(), 0.1,
                                      n_steps, save_every=100)
        best = min(best, timing["run_s"])
    return {"us_per_step": best / n_steps * 1e6, "iterations_mean": float(traj.newton_mean)}


def run(out_dir: Path | str) -> dict:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    results: dict = {"systems": {}, "steps": {}}
    for n in (3, 6, 12):
        results["systems"][str(n)] = {name: time_solves(n, s) for name, s in VARIANTS.items()}
        print(f"n = {n}: " + ", ".join(
            f"{k} {v['us_per_solve']:.2f} us" for k, v in results["systems"][str(n)].items()),
            file=sys.stderr)
    methods = {"gl4 (4 unknowns)": lambda s: GaussLegendre(stages=2, newton=s),
               "galerkin4 (2 unknowns)": lambda s: GalerkinVI(degree=2, newton=s)}
    for label, make in methods.items():
        results["steps"][label] = {name: time_steps(make, s) for name, s in VARIANTS.items()}
    results["environment"] = {
        "jax": jax.__version__, "lgvi_jax": lgvi_jax.__version__,
        "machine": platform.machine(), "devices": [str(d) for d in jax.devices()],
    }
    lines = ["| system | " + " | ".join(VARIANTS) + " |", "|---" * (len(VARIANTS) + 1) + "|"]
    for n, row in results["systems"].items():
        base = row["lu (baseline)"]["us_per_solve"]
        cells = [f"{v['us_per_solve']:.2f} µs ({v['iterations_mean']:.1f} it, "
                 f"{base / v['us_per_solve']:.2f}x)" for v in row.values()]
        lines.append(f"| Newton solve, n = {n} | " + " | ".join(cells) + " |")
    for label, row in results["steps"].items():
        base = row["lu (baseline)"]["us_per_step"]
        cells = [f"{v['us_per_step']:.2f} µs ({v['iterations_mean']:.1f} it, "
                 f"{base / v['us_per_step']:.2f}x)" for v in row.values()]
        lines.append(f"| oscillator step, {label} | " + " | ".join(cells) + " |")
    table = "\n".join(lines) + "\n\n(speed-up over the LU baseline in parentheses)\n"
    atomic_write_text(out / "bench_newton.md", table)
    atomic_write_text(out / "bench_newton.json", json.dumps(results, indent=2))
    print(table)
    return results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="output folder")
    run(parser.parse_args(argv).out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
