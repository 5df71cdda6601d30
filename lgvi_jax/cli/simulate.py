"""``lgvi-jax simulate SYSTEM``: integrate one system with one method (``--method``, also
``METHOD@ORDER``) for ``--t-final`` in steps of ``--dt``; writes the saved states, the
per-step result and Newton counts and the run's configuration to ``--out`` (.npz) and
prints the timing and energy error (``--json``: one object). Exit status 1 when the
integration fails (the file is still written), 2 on bad input."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from .._io import save_npz_atomic
from ._common import (
    PROG,
    UsageError,
    _check_writable_file,
    _float,
    _positive_int,
    parse_set,
    steps_for,
)


def energy_error_line(summary: dict[str, Any]) -> str:
    """``max X, final Y`` of a run's relative energy error; for a failed run the max is
    over the steps before the failure, and what was not measured reads ``n/a``."""
    failed = summary["result"] != 0
    where = f"failed at step {summary.get('failed_step', '?')}"

    def fmt(value: float) -> str:
        return f"{value:.3e}" if math.isfinite(value) else f"n/a ({where})"

    emax = summary["energy_error_max"]
    text = f"max {fmt(emax)}"
    if failed and math.isfinite(emax):
        text += f" before the failure ({where})"
    final = summary["energy_error_final"]
    if failed or not math.isfinite(final):
        return text + ", final n/a"
    return text + f", final {fmt(final)}"


def cmd_simulate(args: argparse.Namespace) -> int:
    from ..diagnostics import summarize
    from ..integrators import with_scalar_newton
    from ..simulate import simulate_timed
    from ..systems import get_system

    spec = get_system(args.system)
    try:
        # As in `sweep`: the Lie-group VIs solved on scalars (the same solutions to
        # round-off; one trajectory several times faster for a longer compile, docs/cli.md).
        method = with_scalar_newton(spec.method(args.method))
    except ValueError as err:
        detail = str(err).removeprefix(f"{spec.name}: ")
        raise UsageError(f"--method {args.method!r} is not available for {spec.name}: "
                         f"{detail}") from None
    n_steps = steps_for(args.dt, args.t_final)
    if n_steps % args.save_every:
        raise UsageError(
            f"--save-every ({args.save_every}) must divide the number of steps ({n_steps})"
        )
    out = Path(args.out)
    if out.suffix != ".npz":
        raise UsageError(f"--out {out}: expected a file name ending in .npz")
    overrides = parse_set(args.set)
    try:
        model, state0 = spec.build(overrides)
    except ValueError as err:
        raise UsageError(str(err)) from None
    _check_writable_file(out)  # last: nothing is created on disk for a rejected command
    traj, timing = simulate_timed(
        model, method, state0, args.dt, n_steps, save_every=args.save_every
    )
    summary = summarize(traj)
    config = {
        "system": spec.name,
        "method": method.name,
        "dt": args.dt,
        "t_final": args.t_final,
        "n_steps": n_steps,
        "save_every": args.save_every,
        "parameters": {k: v.tolist() for k, v in overrides.items()},
    }
    arrays = spec.arrays(model, traj)
    arrays["result"] = np.asarray(traj.result)
    arrays["newton_iterations"] = np.asarray(traj.newton_steps)
    arrays["config_json"] = np.asarray(json.dumps(config))
    save_npz_atomic(out, arrays)
    report = {
        **config,
        **summary,
        "wall_time_s": timing["compile_s"] + timing["run_s"],
        "compile_time_s": timing["compile_s"],
        "run_time_s": timing["run_s"],
        "steps_per_second": timing["steps_per_second"],
        "out": str(out),
    }
    if args.json:
        print(json.dumps(report))
    else:
        print(
            f"{spec.name} / {method.describe()}: {n_steps} steps of {args.dt:g} "
            f"in {timing['run_s']:.3g} s ({timing['steps_per_second']:.3g} steps/s, "
            f"compiled in {timing['compile_s']:.3g} s)\n"
            f"relative energy error: {energy_error_line(summary)}\n"
            f"wrote {out} ({len(arrays['t'])} saved states)"
        )
    if summary["result"] != 0:
        print(f"{PROG} simulate: integration failed: {summary['message']}", file=sys.stderr)
        return 1
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``simulate`` command to the subcommands ``sub``."""
    from ..systems import SYSTEMS

    sim = sub.add_parser("simulate", help="integrate one system with one method")
    sim.add_argument("system", choices=list(SYSTEMS), help="the system to integrate")
    sim.add_argument("--method", required=True,
                     help="integrator, or METHOD@ORDER for a composition, e.g. lgvi@6 "
                     "(see `lgvi-jax info`)")
    sim.add_argument("--dt", required=True, type=_float, help="step size (> 0)")
    sim.add_argument("--t-final", required=True, type=_float, help="final time, a multiple of dt")
    sim.add_argument("--save-every", type=_positive_int, default=1, metavar="K",
                     help="keep every K-th state (K must divide the number of steps)")
    sim.add_argument("--set", action="append", metavar="NAME=V1[,V2...]",
                     help="override a parameter or initial value (repeatable)")
    sim.add_argument("--out", required=True, help="output file (.npz)")
    sim.add_argument("--json", action="store_true", help="print a one-object JSON summary")
    sim.set_defaults(func=cmd_simulate)
