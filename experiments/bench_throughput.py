"""Throughput benchmark: the car-pendulum VIs in JAX against a compiled-loop Numba baseline.

For every VI method, at h = 5e-3 over ``steps`` steps (10^4 by default), after compilation:

* one trajectory (``final_state``: no saved states, no batch axis),
* a batch of ``batch`` trajectories (1024 by default; ``vmap``, sharded with ``shard_map``
  over every device in ``jax.devices()``: on a CPU-only machine, one XLA host device per
  core, see ``lgvi-jax bench --devices``),
* the Numba baseline of the same method (``experiments/numba_lgvi.py`` for ``lgvi``,
  ``experiments/numba_hamel.py`` for the Hamel methods: the discrete equations,
  hand-derived and reduced to three unknowns, in plain loops with a warm-started Newton
  (``lgvi``) or the engine's chord-then-Newton iteration (Hamel); the batch runs over all
  cores, with ``prange`` or one GIL-free thread per core), in the same process and run.

Reported: steps per second (best of ``repeats`` timed runs), compile time (ahead of time,
``lower().compile()``), XLA's memory estimate of the compiled batched program (arguments,
outputs, temporaries) and the process's peak resident memory, and the ratio of our
throughput to Numba's. A second part runs ``lgvi-jax simulate`` for 10^6 steps with
``--save-every 1000`` (and 10^5 for comparison) in child processes and reports their peak
resident memory, to show that a long run's memory does not grow with its length.

Writes ``bench.json`` and ``bench.md`` into the output folder. Run:
``lgvi-jax bench --out results/bench`` (or ``python experiments/bench_throughput.py``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

import lgvi_jax as lj
from lgvi_jax._io import atomic_write_json, atomic_write_text
from lgvi_jax.sweep import batch_arguments, initial_conditions

METHODS = ("lgvi", "hamel", "hamel-cayley", "hamel-exact")
#: Each method in the general engine with its default chord matrix (the Jacobian at the
#: guess) and with the continuous Legendre matrix (``chord_matrix="mass"``), and as the
#: fused scalar step (:class:`lgvi_jax.FusedCarPendulum`, what ``sweep`` uses by default
#: for the car-pendulum): the same discrete equations and solutions.
CHORDS = ("exact", "mass", "fused")
DT = 5e-3


def _rss_mb() -> float:
    # ru_maxrss is in kilobytes on Linux.
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _best_time(fn: Callable[[], object], repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - start)
    return best


def _bench_jax(name: str, model, s0, steps: int, batch: int, repeats: int,
               chord: str = "exact") -> dict:
    if chord == "fused":
        method = lj.FusedCarPendulum(name)
    else:
        method = dataclasses.replace(lj.RIGID_METHODS[name](), chord_matrix=chord)
    out: dict = {}
    # One trajectory: lj.final_state (no saved states, no batch axis), on one device.
    params, static = eqx.partition((model, method), eqx.is_array)

    def single(params, state, dt):
        return lj.final_state(*eqx.combine(params, static), state, dt, steps)

    start = time.perf_counter()
    compiled = jax.jit(single).lower(params, s0, DT).compile()
    out["compile_s"] = time.perf_counter() - start
    _, code = compiled(params, s0, DT)
    assert int(code) == 0, f"{name}: single run failed"
    run_s = _best_time(lambda: compiled(params, s0, DT), repeats)
    out["single_steps_per_s"] = steps / run_s
    # The batch, sharded over all devices.
    states = initial_conditions(model, s0, batch, 0.01, 0)
    fn, args = batch_arguments(model, method, states, DT, steps, kind="final")
    start = time.perf_counter()
    compiled = fn.lower(*args).compile()
    out["batch_compile_s"] = time.perf_counter() - start
    dyn = args[:1] + args[2:]
    res = compiled(*dyn)
    out["batch_failed"] = int(np.sum(np.asarray(res["result"]) != 0))
    run_s = _best_time(lambda: compiled(*dyn), repeats)
    out["batch_steps_per_s"] = batch * steps / run_s
    out["batch_wall_s"] = run_s
    try:
        mem = compiled.memory_analysis()
        out["batch_xla_memory_mb"] = (mem.argument_size_in_bytes + mem.output_size_in_bytes
                                      + mem.temp_size_in_bytes) / 2**20
    except Exception:  # memory_analysis is not available on every backend
        out["batch_xla_memory_mb"] = float("nan")
    return out


def _bench_numba(nb, name: str, model, s0, steps: int, batch: int, repeats: int) -> dict:
    params = nb.params_from_model(model)
    R, mu, q, p = (np.asarray(x) for x in (s0.R, s0.mu, s0.q, s0.p))
    out: dict = {}
    nb.rollout(name, R, mu, q, p, DT, 2, params)  # compiled by warmup(); keep it hot
    run_s = _best_time(lambda: nb.rollout(name, R, mu, q, p, DT, steps, params), repeats)
    out["single_steps_per_s"] = steps / run_s
    states = initial_conditions(model, s0, batch, 0.01, 0)
    Rb, mub, qb, pb = (np.ascontiguousarray(np.asarray(x))
                       for x in (states.R, states.mu, states.q, states.p))
    nb.rollout_batch(name, Rb[:2], mub[:2], qb[:2], pb[:2], DT, 2, params)
    run_s = _best_time(
        lambda: nb.rollout_batch(name, Rb, mub, qb, pb, DT, steps, params), repeats)
    out["batch_steps_per_s"] = batch * steps / run_s
    return out


def _long_run_memory(n_steps: int, log) -> dict:
    """Peak resident memory of ``lgvi-jax simulate`` over ``n_steps`` (child process)."""
    with tempfile.TemporaryDirectory() as tmp:
        # The child's own high-water mark: VmHWM of /proc/self/status belongs to the
        # address space the child built after exec. Its ru_maxrss would not do: Linux
        # keeps the maximum across execve, so it starts at the size of the forked
        # benchmark process (a measured 1 GB whatever the run).
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
    devices = jax.devices()
    return {"jax": jax.__version__, "python": platform.python_version(),
            "machine": platform.machine(), "cpu_count": os.cpu_count(),
            "devices": [str(d) for d in devices], "platform": devices[0].platform,
            "device_kind": devices[0].device_kind}


def run(out_dir: Path | str, quick: bool = False, log: Callable = print, *,
        steps: int | None = None, batch: int | None = None,
        methods: tuple[str, ...] = METHODS, long_run: bool = True) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    steps = steps or (1000 if quick else 10_000)
    batch = batch or (64 if quick else 1024)
    repeats = 2 if quick else 3
    model = lj.CarPendulum()
    s0 = model.default_state()
    try:
        from lgvi_jax.experiments import numba_lgvi as nb

        start = time.perf_counter()
        nb.warmup()
        numba_compile_s = time.perf_counter() - start
        import numba

        numba_info = {"version": numba.__version__, "threads": numba.get_num_threads(),
                      "compile_s": numba_compile_s}
    except ImportError as err:
        log(f"Numba baseline unavailable ({err}); install the bench extra: "
            "pip install 'lgvi_jax[bench]'")
        nb = None
        numba_info = None
    env = _environment()
    log(f"car-pendulum, h = {DT}, {steps} steps, batch {batch}, on {len(env['devices'])} "
        f"{env['platform']} device(s)")
    rows, numba_rows = {}, {}
    for base, chord in ((n, c) for n in methods for c in CHORDS):
        row = {"jax": _bench_jax(base, model, s0, steps, batch, repeats, chord),
               "method": base, "chord_matrix": chord}
        name = {"exact": base, "mass": f"{base}, mass chord", "fused": f"{base}, fused"}[chord]
        if nb is not None and base in nb.METHODS:
            if base not in numba_rows:  # one baseline per method, for both chord rows
                numba_rows[base] = _bench_numba(nb, base, model, s0, steps, batch, repeats)
            row["numba"] = numba_rows[base]
            for k in ("single_steps_per_s", "batch_steps_per_s"):
                row[f"ratio_{k.split('_')[0]}"] = row["jax"][k] / row["numba"][k]
        rows[name] = row
        j = row["jax"]
        msg = (f"  {name}: single {j['single_steps_per_s']:.3g} steps/s, batch "
               f"{j['batch_steps_per_s']:.3g} steps/s, compile {j['compile_s']:.2f} s")
        if "numba" in row:
            msg += (f"; numba single {row['numba']['single_steps_per_s']:.3g}, batch "
                    f"{row['numba']['batch_steps_per_s']:.3g}; ratios "
                    f"{row['ratio_single']:.2f} / {row['ratio_batch']:.2f}")
        log(msg)
    results = {"quick": quick, "dt": DT, "steps": steps, "batch": batch, "repeats": repeats,
               "methods": rows, "numba": numba_info, "environment": env,
               "process_peak_rss_mb": _rss_mb()}
    if long_run:
        results["long_run"] = [_long_run_memory(n, log)
                               for n in ((10_000, 100_000) if quick else (100_000, 1_000_000))]
    atomic_write_text(out_dir / "bench.md", _markdown(results))
    atomic_write_json(out_dir / "bench.json", results)
    log(f"wrote {out_dir / 'bench.json'} and {out_dir / 'bench.md'}")
    return results


def _markdown(r: dict) -> str:
    env = r["environment"]
    lines = [
        f"# Throughput: car-pendulum, h = {r['dt']}, {r['steps']} steps",
        "",
        f"{len(env['devices'])} {env['platform']} device(s) ({env['device_kind']}), "
        f"{env['cpu_count']} CPU cores, jax {env['jax']}"
        + (f", Numba {r['numba']['version']} with {r['numba']['threads']} threads"
           if r["numba"] else ", no Numba baseline") + ". Best of "
        f"{r['repeats']} runs after compilation.",
        "",
        "Rows marked *mass chord* use `chord_matrix=\"mass\"` (the continuous Legendre "
        "matrix as the chord matrix, updated by Broyden's formula: more, cheaper "
        "iterations, the same solutions). Rows marked *fused* are "
        "`lgvi_jax.FusedCarPendulum`, the same discrete equations reduced to three "
        "unknowns in scalar form (what `lgvi-jax sweep` uses for the car-pendulum by "
        "default).",
        "",
        "| method | JAX 1 traj (steps/s) | Numba 1 traj | ratio | JAX batch of "
        f"{r['batch']} (steps/s) | Numba batch (all cores) | ratio | compile (s) 1 traj, "
        "batch | batch program memory (MB) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, row in r["methods"].items():
        j, n = row["jax"], row.get("numba")

        def cell(d, key):
            return f"{d[key]:.3g}" if d else "n/a"

        lines.append(
            f"| {name} | {j['single_steps_per_s']:.3g} | {cell(n, 'single_steps_per_s')} | "
            f"{row.get('ratio_single', float('nan')):.2f} | {j['batch_steps_per_s']:.3g} | "
            f"{cell(n, 'batch_steps_per_s')} | {row.get('ratio_batch', float('nan')):.2f} | "
            f"{j['compile_s']:.2f}, {j['batch_compile_s']:.2f} | "
            f"{j['batch_xla_memory_mb']:.1f} |")
    if r.get("long_run"):
        lines += ["", "Long runs (`lgvi-jax simulate car-pendulum --method lgvi --save-every "
                  "1000`, child process):", "",
                  "| steps | saved states | peak RSS (MB) | steps/s |", "|---|---|---|---|"]
        for lr in r["long_run"]:
            lines.append(f"| {lr['n_steps']} | {lr['saved_states']} | {lr['peak_rss_mb']:.0f} "
                         f"| {lr['steps_per_s']:.3g} |")
    lines += ["", f"Peak resident memory of the benchmark process: "
              f"{r['process_peak_rss_mb']:.0f} MB."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="results/bench")
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args(argv)
    run(args.out, quick=args.quick)
    return 0


if __name__ == "__main__":
    sys.exit(main())
