"""Cost of a composed step against its stages: ``lgvi@4/6/8`` (and the other schemes) on the
paper's car-pendulum, with and without Newton warm starts across sub-steps.

For each method: compile time (``simulate_timed``, ahead-of-time), steps/s after
compilation (best of ``--repeats`` runs), Newton iterations per sub-step, and

    ratio = (time of one composed step) / (stages x time of one base step at the same h)
          = (base steps/s) / (stages x composed steps/s),

i.e. 1.0 when a composed step costs exactly ``stages`` base steps (from process CPU time,
robust on a shared machine, and from wall time). Also the configuration
error at T = 1 against the hand-derived reference (``lgvi_jax.systems.car_pendulum``) at
the same h, to
compare the schemes at equal cost.

    python experiments/bench_composition.py --out results/composition [--quick]

Writes ``bench_composition.json`` and ``bench_composition.md`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import jax
import numpy as np

import lgvi_jax as L
from lgvi_jax._io import atomic_write_text
from lgvi_jax.integrators import LGVI, RKMK4, SCHEMES, compose
from lgvi_jax.systems.car_pendulum import HandReference, paper_problem

DEFAULT = ("suzuki4", "kahan-li6", "kahan-li8")


def _compile(model, method, s0, h, n):
    """Compile (timed, ahead-of-time) and run once; return the trajectory, the compile
    wall time and the process CPU time of compiling and running once."""
    cpu0 = time.process_time()
    traj, t = L.simulate_timed(model, method, s0, h, n, save_every=n)
    cpu = time.process_time() - cpu0
    assert traj.ok, traj.message
    return traj, t["compile_s"], cpu


def _time_interleaved(model, methods, s0, h, n, repeats):
    """Best wall and process-CPU time per run of each method, the methods interleaved in
    each of ``repeats`` rounds (so that a busy machine slows all of them alike; the CPU
    time is the robust one on a shared machine)."""
    best = {k: [np.inf, np.inf] for k in methods}
    for _ in range(repeats):
        for key, method in methods.items():
            wall0, cpu0 = time.perf_counter(), time.process_time()
            jax.block_until_ready(L.simulate(model, method, s0, h, n, save_every=n))
            wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
            best[key] = [min(best[key][0], wall), min(best[key][1], cpu)]
    return best


def _accuracy(model, method, s0, h, y_ref):
    state, code = L.final_state(model, method, s0, h, round(1.0 / h))
    if int(code) != 0:
        return float("nan")
    R_ref, _, q_ref, _ = HandReference.split(y_ref)
    return float(np.linalg.norm(np.asarray(state.R) - R_ref)
                 + np.linalg.norm(np.asarray(state.q) - q_ref))


def run(out: Path, *, quick: bool = False, dt: float = 0.01, steps: int | None = None,
        repeats: int = 5, log=print) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    n = steps or (1000 if quick else 5000)
    spec = paper_problem()
    model, s0 = spec.model, spec.state0
    y_ref = spec.reference().at([0.0, 1.0])[-1]
    schemes = DEFAULT if quick else tuple(SCHEMES)

    methods = {"lgvi": LGVI()}
    for name in schemes:
        for warm in (True, False):
            methods[name, warm] = compose(LGVI(), scheme=name, warm_start=warm)
    methods["rkmk4"], methods["rk4"] = RKMK4(), L.RK4()
    compiled = {}
    for key, method in methods.items():
        traj, c, c_cpu = _compile(model, method, s0, dt, n)
        compiled[key] = (traj, c, c_cpu)
        log(f"{method.name}{'' if key in ('lgvi', 'rkmk4', 'rk4') else f' (warm {key[1]})'}: "
            f"compiled in {c:.2f} s")
    best = _time_interleaved(model, methods, s0, dt, n, repeats)
    wall_base, cpu_base = best["lgvi"]
    rows = []
    for key, method in methods.items():
        traj, c, c_cpu = compiled[key]
        wall, cpu = best[key]
        stages = getattr(method, "stages", None)
        composed = stages is not None
        row = {
            "method": method.name, "stages": 1 if key == "lgvi" else stages,
            "order": method.order, "warm_start": key[1] if composed else None,
            "compile_s": c, "compile_cpu_s": max(c_cpu - cpu, 0.0),
            "steps_per_second": n / wall, "cpu_s_per_step": cpu / n,
            "newton_per_substep": float(traj.newton_mean) / (stages or 1),
            "ratio_cpu": cpu / (stages * cpu_base) if composed else (
                1.0 if key == "lgvi" else None),
            "ratio_wall": wall / (stages * wall_base) if composed else (
                1.0 if key == "lgvi" else None),
            "config_error_T1": (_accuracy(model, method, s0, dt, y_ref)
                                if not composed or key[1] else None),
        }
        rows.append(row)
        log(f"{method.name}: {row['steps_per_second']:.3g} steps/s, "
            f"{row['newton_per_substep']:.2f} its/sub-step, ratio (CPU) {row['ratio_cpu']}")
    its_base = rows[0]["newton_per_substep"]

    result = {
        "config": {"dt": dt, "n_steps": n, "repeats": repeats, "quick": quick,
                   "system": "car-pendulum (paper's state)"},
        "environment": {"jax": jax.__version__, "platform": platform.platform(),
                        "device": str(jax.devices()[0]), "date": time.strftime("%Y-%m-%d")},
        "rows": rows,
    }
    atomic_write_text(out / "bench_composition.json", json.dumps(result, indent=2))
    lines = [
        f"# Composed steps against their stages (car-pendulum, h = {dt:g}, {n} steps)",
        "",
        "ratio = time of one composed step / (stages x time of one base `lgvi` step at the "
        "same h), from process CPU time (and wall time), best of "
        f"{repeats} interleaved runs; 1.00 = exactly `stages` base steps. Newton iterations "
        f"per sub-step (base `lgvi`: {its_base:.2f} per step). Error: configuration error at "
        "T = 1 against the hand-derived reference, at this h.",
        "",
        "| method | stages | order | warm start | ratio (CPU) | ratio (wall) | "
        "Newton its/sub-step | steps/s | compile [s] (wall, CPU) | error at T = 1 |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        def fmt(x, f):
            return "–" if x is None else format(x, f)
        warm = "–" if r["warm_start"] is None else ("yes" if r["warm_start"] else "no")
        lines.append(
            f"| {r['method']} | {fmt(r['stages'], 'd')} | {r['order']} | {warm} | "
            f"{fmt(r['ratio_cpu'], '.2f')} | {fmt(r['ratio_wall'], '.2f')} | "
            f"{r['newton_per_substep']:.2f} | "
            f"{r['steps_per_second']:.3g} | {r['compile_s']:.2f}, {r['compile_cpu_s']:.2f} | "
            f"{fmt(r['config_error_T1'], '.2e')} |")
    atomic_write_text(out / "bench_composition.md", "\n".join(lines) + "\n")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--dt", type=float, default=0.01)
    parser.add_argument("--steps", type=int, default=None)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    run(args.out, quick=args.quick, dt=args.dt, steps=args.steps, repeats=args.repeats)
    print((args.out / "bench_composition.md").read_text(), end="")


if __name__ == "__main__":
    main()
