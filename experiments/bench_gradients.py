"""Memory and time of gradients through long rollouts: implicit-function-theorem Newton
derivatives, with and without checkpointing, against the forward run and against
differentiating through unrolled Newton iterations.

The car-pendulum with the general LGVI (``lgvi``), the paper's state, h = 5e-3, 10^4 steps
(50 s), the state saved every 10 steps; the loss is a trajectory loss on the saved attitudes
and cart positions. For each program — the forward loss, ``jax.grad`` of it with the
default (implicit) Newton adjoint, the same with ``checkpoint_every=K``, and ``jax.grad``
through unrolled Newton iterations (``Newton(adjoint="unrolled", max_steps=6)``) — the
compiled program's memory is read from XLA (``compiled.memory_analysis()``: the temporary
buffers plus arguments and outputs, i.e. the peak the executable allocates; deterministic,
unlike a process's resident size), and the run time is measured after compilation.
Reverse mode without checkpointing stores every step's residuals (memory ~ n); with
checkpoints every K steps it stores n/K states and one segment's residuals (~ n/K + K).

Run:  ``python experiments/bench_gradients.py --out DIR [--quick]``; writes
``bench_gradients.json`` and ``bench_gradients.md``.
"""

from __future__ import annotations

import json
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp

import lgvi_jax as lj
from lgvi_jax._io import atomic_write_text


def _memory(compiled) -> dict[str, int]:
    stats = compiled.memory_analysis()
    temp = int(stats.temp_size_in_bytes)
    total = (temp + int(stats.argument_size_in_bytes) + int(stats.output_size_in_bytes)
             - int(stats.alias_size_in_bytes))
    return {"temp_bytes": temp, "peak_bytes": total}


def _measure(fn, args, repeats: int = 3) -> dict:
    start = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - start
    out = jax.block_until_ready(compiled(*args))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - start)
    return {**_memory(compiled), "compile_s": compile_s, "run_s": min(times), "value": out}


def run(out_dir, quick: bool = False, log: Callable = print) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    n_steps = 1000 if quick else 10_000
    dt, save_every = 5e-3, 10
    ks = (100,) if quick else (10, 100, 1000)
    model = lj.CarPendulum()
    state0 = model.default_state()
    # Targets: the paper model's own trajectory with a slightly different inertia.
    target_model = eqx.tree_at(lambda m: m.J, model, model.J + 0.002 * jnp.eye(3))
    target = lj.simulate(target_model, lj.LGVI(), state0, dt, n_steps, save_every=save_every)
    R_obs, q_obs = target.state.R, target.state.q

    def loss(model, method, checkpoint_every=None):
        traj = lj.simulate(model, method, state0, dt, n_steps, save_every=save_every,
                           checkpoint_every=checkpoint_every)
        return jnp.mean(0.5 * jnp.sum((traj.state.R - R_obs) ** 2, axis=(-2, -1))
                        + jnp.sum((traj.state.q - q_obs) ** 2, axis=-1))

    implicit = lj.LGVI()
    unrolled = lj.LGVI(newton=lj.Newton(adjoint="unrolled", max_steps=6))
    rows = {}
    log(f"bench_gradients: {n_steps} steps of lgvi, forward ...")
    rows["forward"] = _measure(lambda m: loss(m, implicit), (model,))
    log("  gradient (implicit Newton derivatives, no checkpoints) ...")
    rows["grad"] = _measure(jax.grad(lambda m: loss(m, implicit)), (model,))
    for k in ks:
        log(f"  gradient, checkpoint_every={k} ...")
        rows[f"grad_checkpoint_{k}"] = _measure(
            jax.grad(lambda m, k=k: loss(m, implicit, k)), (model,))
    log("  gradient through unrolled Newton iterations (6 per step) ...")
    rows["grad_unrolled"] = _measure(jax.grad(lambda m: loss(m, unrolled)), (model,))

    g_ref = rows["grad"]["value"].J
    for name, row in rows.items():
        value = row.pop("value")
        if name != "forward":
            row["max_rel_diff_J_grad_vs_implicit"] = float(
                jnp.max(jnp.abs(value.J - g_ref)) / jnp.max(jnp.abs(g_ref)))
    forward_peak = rows["forward"]["peak_bytes"]
    for row in rows.values():
        row["peak_over_forward"] = row["peak_bytes"] / forward_peak
    results = {
        "quick": quick,
        "n_steps": n_steps,
        "dt": dt,
        "save_every": save_every,
        "method": "lgvi",
        "rows": rows,
        "platform": {"python": platform.python_version(), "jax": jax.__version__,
                     "device": str(jax.devices()[0]), "machine": platform.machine()},
    }
    labels = {"forward": "forward loss", "grad": "grad, implicit Newton adjoint",
              "grad_unrolled": "grad through unrolled Newton (6 its/step)"}
    lines = [
        f"# Gradient memory: {n_steps} steps of `lgvi` on the car-pendulum (h = {dt:g}, "
        f"saved every {save_every})",
        "",
        "Peak = XLA's compiled temporary buffers + arguments + outputs "
        "(`compiled.memory_analysis()`).",
        "",
        "| program | peak memory | / forward | run time | compile | max rel. diff of ∂L/∂J "
        "vs implicit |",
        "|---|---|---|---|---|---|",
    ]
    for name, row in rows.items():
        label = labels.get(name, name.replace("grad_checkpoint_", "grad, checkpoint_every="))
        diff = row.get("max_rel_diff_J_grad_vs_implicit")
        diff_text = "—" if diff is None else f"{diff:.1e}"
        lines.append(f"| {label} | {row['peak_bytes'] / 2**20:.3f} MiB | "
                     f"{row['peak_over_forward']:.1f} | {row['run_s'] * 1e3:.0f} ms | "
                     f"{row['compile_s']:.1f} s | {diff_text} |")
    text = "\n".join(lines) + "\n"
    atomic_write_text(out_dir / "bench_gradients.md", text)
    atomic_write_text(out_dir / "bench_gradients.json", json.dumps(results, indent=1) + "\n")
    log(text)
    return results


if __name__ == "__main__":
    from lgvi_jax.studies import script_main

    sys.exit(script_main(run, __doc__, quick_help='10^3 steps, one checkpoint K'))
