"""Batched throughput of the sweep's rollout on an accelerator (GPU), beside the CPU.

What ``lgvi-jax sweep`` runs per batch (``sweep.batch_arguments(..., kind="metrics")``:
the step and the per-step diagnostics), for each system, method and engine, at several
batch sizes, sharded over ``jax.devices()`` as the sweep does; compile time apart, the best
of a few runs. Optional: the compiled Numba baselines (car-pendulum) on every CPU core.

    python experiments/bench_accelerator.py --out DIR [--batches 4096,131072]
        [--steps 1000] [--budget-s 300] [--numba]

Writes ``accelerator.json`` (rewritten after every row, so that a run cut short keeps what
it measured) and prints one line per row. The measured results are in docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import jax
import numpy as np

import lgvi_jax as lj
import lgvi_jax.systems  # binds lj.systems
from lgvi_jax._io import atomic_write_json
from lgvi_jax.sweep import batch_arguments, engine_name, initial_conditions, sweep_method

DT, PERTURB, SEED = 5e-3, 0.01, 0


def _bench(model, method, s0, steps: int, batch: int, repeats: int) -> dict:
    states = initial_conditions(model, s0, batch, PERTURB, SEED)
    fn, args = batch_arguments(model, method, states, DT, steps, kind="metrics")
    t0 = time.perf_counter()
    compiled = fn.lower(*args).compile()
    compile_s = time.perf_counter() - t0
    dyn = args[:1] + args[2:]
    times, res = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = jax.block_until_ready(compiled(*dyn))
        times.append(time.perf_counter() - t0)
    ok = np.asarray(res["result"]) == 0
    return {"batch": batch, "steps": steps, "compile_s": compile_s, "run_s": min(times),
            "steps_per_s": batch * steps / min(times), "failed": int(np.sum(~ok)),
            "energy_error_max": float(np.max(np.asarray(res["energy_error_max"])[ok]))
            if ok.any() else float("nan"),
            "newton_mean": float(np.mean(np.asarray(res["newton_mean"])[ok]))
            if ok.any() else float("nan")}


def _numba_rows(steps: int, batch: int, methods) -> list[dict]:
    from lgvi_jax.bench.throughput import _load_numba, _numpy_states

    nb, used = _load_numba(methods, print)  # compiled once, before the timed runs
    if nb is None:
        return []
    model, s0 = lj.systems.get_system("car-pendulum").build()
    params = nb.params_from_model(model)
    arrays = _numpy_states(initial_conditions(model, s0, batch, PERTURB, SEED))
    rows = []
    for name in methods:
        times = []
        for _ in range(2):
            t0 = time.perf_counter()
            nb.sweep_metrics(name, *arrays, DT, steps, params)
            times.append(time.perf_counter() - t0)
        rows.append({"system": "car-pendulum", "method": name, "engine": "numba",
                     "device": f"cpu x {used['threads']} threads", "batch": batch,
                     "steps": steps, "run_s": min(times),
                     "steps_per_s": batch * steps / min(times)})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--systems", default="car-pendulum,heavy-top")
    ap.add_argument("--methods", default="hamel,lgvi")
    ap.add_argument("--engines", default="scalar,general")
    ap.add_argument("--batches", default="4096,131072")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--budget-s", type=float, default=300.0,
                    help="start no new row after this many seconds")
    ap.add_argument("--numba", action="store_true", help="add the Numba CPU baselines")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    dev = jax.devices()[0]
    report = {"jax": jax.__version__, "device": str(dev), "platform": dev.platform,
              "device_kind": dev.device_kind, "cpu_count": os.cpu_count(), "rows": []}
    print(json.dumps({k: v for k, v in report.items() if k != "rows"}), flush=True)
    batches = [int(b) for b in a.batches.split(",")]
    for system in a.systems.split(","):
        model, s0 = lj.systems.get_system(system).build()
        for name in a.methods.split(","):
            for engine in a.engines.split(","):
                method = sweep_method(system, name, scalar=engine == "scalar")
                for batch in batches:
                    if time.perf_counter() - start > a.budget_s:
                        print("budget spent: row skipped", system, name, engine, batch)
                        continue
                    try:
                        row = _bench(model, method, s0, a.steps, batch, a.repeats)
                    except Exception as err:
                        row = {"batch": batch, "error": f"{type(err).__name__}: {err}"[:500]}
                    row.update(system=system, method=name, engine=engine_name(method),
                               device=f"{dev.device_kind} x {len(jax.devices())}")
                    report["rows"].append(row)
                    print(json.dumps(row), flush=True)
                    atomic_write_json(out / "accelerator.json", report)
    if a.numba and time.perf_counter() - start < a.budget_s:
        for row in _numba_rows(a.steps, max(batches[0], 1024), a.methods.split(",")):
            report["rows"].append(row)
            print(json.dumps(row), flush=True)
        atomic_write_json(out / "accelerator.json", report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
