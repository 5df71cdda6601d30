"""``lgvi-jax sweep SYSTEM``: integrate ``--n`` initial conditions drawn around the
system's default state with every method and step, batched over the host devices (or
several processes, ``--coordinator``/``--distributed``); per-trajectory structure
metrics go to the folder ``--out`` chunk by chunk (resumable with ``--resume``), with
a summary and a plot. Exit status 130 when interrupted (finished chunks kept)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ._common import (
    PROG,
    UsageError,
    _csv_list,
    _float,
    _positive_int,
    configure_devices,
    parse_set,
)


def _start_distributed(args: argparse.Namespace) -> int:
    """Join the processes of a distributed sweep (before JAX computes anything); returns
    this process's index (0 without distributed options)."""
    given = [args.coordinator, args.num_processes, args.process_id]
    if args.distributed is None and all(v is None for v in given):
        return 0
    from ..distributed import DistributedError, initialize

    try:
        index, _ = initialize(args.coordinator, args.num_processes, args.process_id,
                              auto=args.distributed == "auto",
                              heartbeat_timeout=args.heartbeat_timeout,
                              prog=f"{PROG} sweep")
    except DistributedError as err:
        raise UsageError(str(err)) from None
    return index


def cmd_sweep(args: argparse.Namespace) -> int:
    distributed = args.distributed is not None or any(
        v is not None for v in (args.coordinator, args.num_processes, args.process_id))
    configure_devices(args.devices, affinity=distributed)
    index = _start_distributed(args)
    if index == 0:  # the process that draws the plot: matplotlib loads meanwhile
        from .. import _plot_worker

        _plot_worker.start()
    import jax

    from ..sweep import SweepConfig, SweepError, run_sweep
    from ..systems import get_system

    spec = get_system(args.system)
    overrides = parse_set(args.set)
    config = SweepConfig(
        system=spec.name,
        methods=tuple(_csv_list(args.method, str, "--method")),
        dts=tuple(_csv_list(args.dt, float, "--dt")),
        t_final=args.t_final, n=args.n, perturb=args.perturb, seed=args.seed,
        chunk=args.chunk, sample_every=args.sample_every,
        parameters={k: v.tolist() for k, v in overrides.items()},
        chord=args.chord,
    )
    try:
        config.validate(list(spec.methods))
        model, state0 = spec.build(overrides)
    except (SweepError, ValueError) as err:
        raise UsageError(str(err)) from None
    quiet = args.json or index != 0  # in a distributed sweep, process 0 speaks for all

    def log(msg: str) -> None:
        if not quiet:
            print(msg, file=sys.stderr)

    def warn(msg: str) -> None:  # repairs of a damaged folder: said even with --json
        print(f"{PROG} sweep: {msg}", file=sys.stderr)

    devices = jax.devices()
    where = (f" ({jax.process_count()} processes)" if jax.process_count() > 1 else "")
    log(f"{spec.name}: {config.n} initial conditions x {len(config.methods)} method(s) x "
        f"{len(config.dts)} step(s) on {len(devices)} {devices[0].platform} device(s)"
        + where)
    try:
        from ..sweep import sweep_method

        def make_method(name):
            return sweep_method(spec.name, name, config.chord)

        summary = run_sweep(config, model, state0, make_method, Path(args.out),
                            resume=args.resume, progress=not quiet, log=log, warn=warn)
    except SweepError as err:
        raise UsageError(str(err)) from None
    except KeyboardInterrupt:
        print(f"{PROG} sweep: interrupted; finished chunks are kept in {args.out}: rerun "
              "the same command with --resume to continue", file=sys.stderr)
        return 130
    if index != 0:  # process 0 reports the whole sweep
        return 0
    failed = sum(row["failed"] for row in summary["rows"])
    if args.json:
        print(json.dumps({**summary, "out": str(args.out)}))
    else:
        print((Path(args.out) / "summary.md").read_text(), end="")
        print(f"wrote {args.out}/ (manifest.json, chunks/, trajectories.csv, summary.json, "
              f"summary.md, energy_error.png); {summary['chunks_computed']} chunk(s) "
              f"computed, {summary['chunks_skipped']} resumed"
              + (f", {summary['chunks_repaired']} of them repaired"
                 if summary.get("chunks_repaired") else ""))
    if failed:
        print(f"{PROG} sweep: {failed} trajectories failed (flagged in trajectories.csv)",
              file=sys.stderr)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``sweep`` command to the subcommands ``sub``."""
    from ..systems import SYSTEMS

    sw = sub.add_parser(
        "sweep", help="batched energy-drift sweep over perturbed initial conditions",
        description="Integrate N initial conditions drawn around the system's default "
        "state with every method and step; per-trajectory structure metrics go to OUT "
        "chunk by chunk (resumable with --resume).")
    sw.add_argument("system", choices=list(SYSTEMS), help="the system to integrate")
    sw.add_argument("--method", required=True, metavar="METHOD[,METHOD...]",
                    help="integrators, comma-separated (see `lgvi-jax info`)")
    sw.add_argument("--dt", required=True, metavar="DT[,DT...]",
                    help="step sizes, comma-separated; t-final must be a multiple of each")
    sw.add_argument("--t-final", required=True, type=_float, help="final time")
    sw.add_argument("--n", required=True, type=int, help="number of initial conditions (>= 1)")
    sw.add_argument("--perturb", type=_float, default=0.01, metavar="EPS",
                    help="relative size of the velocity perturbation and angle of the "
                    "random rotation (>= 0, default 0.01)")
    sw.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sw.add_argument("--out", required=True, metavar="DIR", help="output folder")
    sw.add_argument("--resume", action="store_true",
                    help="continue an interrupted sweep in DIR, skipping finished chunks")
    sw.add_argument("--chunk", type=int, default=256, metavar="C",
                    help="trajectories per chunk written to disk (default 256)")
    sw.add_argument("--sample-every", type=int, default=1, metavar="K",
                    help="measure the invariants every K steps and at the end (default 1)")
    sw.add_argument("--devices", default="auto", metavar="auto|N",
                    help="host devices to expose on a CPU-only machine (default auto: one "
                    "per core; in a distributed sweep, per core this process may run on); the "
                    "batch is split over all devices")
    sw.add_argument("--set", action="append", metavar="NAME=V1[,V2...]",
                    help="override a parameter or the central initial value (repeatable)")
    sw.add_argument("--chord", choices=("exact", "mass"), default="exact",
                    help="chord matrix of the Lie-group VIs' Newton solves: the Jacobian "
                    "(default) or the continuous Legendre matrix (same solutions, faster "
                    "batched)")
    sw.add_argument("--json", action="store_true",
                    help="print the summary as one JSON object (no progress bar)")
    dist = sw.add_argument_group(
        "several processes or hosts (docs/distributed.md)",
        "Run the same command in every process, with the same --out on a shared file "
        "system; the chunks are divided among the processes and process 0 writes the "
        "manifest, the summary and the plot.")
    dist.add_argument("--coordinator", metavar="HOST:PORT", default=None,
                      help="address of process 0, which serves the coordinator there")
    dist.add_argument("--num-processes", type=_positive_int, metavar="N", default=None,
                      help="number of processes of the sweep")
    dist.add_argument("--process-id", type=int, metavar="I", default=None,
                      help="this process's index, 0..N-1")
    dist.add_argument("--distributed", choices=("auto",), default=None,
                      help="auto: read the coordinator, N and I from the cluster "
                      "environment (Slurm, Open MPI), as jax.distributed.initialize() does")
    dist.add_argument("--heartbeat-timeout", type=_positive_int, metavar="S", default=60,
                      help="seconds without news from a process after which the others "
                      "stop with one line and exit status 3 (default 60)")
    sw.set_defaults(func=cmd_sweep)
