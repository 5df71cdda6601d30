"""Command-line interface: ``lgvi-jax {simulate, sweep, bench, fit, reproduce, info}``.

A thin layer over the library. Bad input exits with status 2 and a one-line message (no
traceback); a run whose integration fails still writes its output (with the failure
recorded in it), prints what failed, and exits with status 1.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from . import _cache
from ._io import atomic_write_json, save_npz_atomic

PROG = "lgvi-jax"


class UsageError(Exception):
    """Bad command-line input: reported in one line, exit status 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        self.print_usage(sys.stderr)
        self.exit(2, f"{self.prog}: error: {message}\n")


# ---------------------------------------------------------------------------------------
# Parsing helpers
# ---------------------------------------------------------------------------------------


def parse_set(items: Sequence[str] | None) -> dict[str, np.ndarray]:
    """Parse repeated ``--set NAME=V1,V2,...`` options into float arrays."""
    values: dict[str, np.ndarray] = {}
    for item in items or []:
        name, sep, rhs = item.partition("=")
        name = name.strip()
        if not sep or not name or not rhs.strip():
            raise UsageError(f"--set {item!r}: expected NAME=V or NAME=V1,V2,... (e.g. m=1.5)")
        try:
            numbers = [float(v) for v in rhs.split(",")]
        except ValueError:
            raise UsageError(
                f"--set {item!r}: values must be numbers separated by commas"
            ) from None
        if not all(math.isfinite(v) for v in numbers):
            raise UsageError(f"--set {item!r}: values must be finite (no nan or inf)")
        if name in values:
            raise UsageError(f"--set: {name} given twice")
        values[name] = np.asarray(numbers, dtype=np.float64)
    return values


def steps_for(dt: float, t_final: float) -> int:
    """Number of steps of size ``dt`` in ``t_final`` (both validated, positive, finite)."""
    if not math.isfinite(dt) or dt <= 0:
        raise UsageError(f"--dt must be a finite number > 0, got {dt!r}")
    if not math.isfinite(t_final) or t_final <= 0:
        raise UsageError(f"--t-final must be a finite number > 0, got {t_final!r}")
    n = round(t_final / dt)
    if n < 1 or abs(n * dt - t_final) > 1e-9 * max(t_final, dt):
        raise UsageError(
            f"--t-final ({t_final:g}) must be a positive multiple of --dt ({dt:g}); "
            f"t_final/dt = {t_final / dt:.6g}"
        )
    return int(n)


def _float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def _check_writable_file(path: Path) -> None:
    parent = path.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UsageError(f"--out {path}: cannot create folder {parent}: {err.strerror}") from None
    if path.is_dir():
        raise UsageError(f"--out {path}: is a folder, expected a file name ending in .npz")
    if not os.access(parent, os.W_OK):
        raise UsageError(f"--out {path}: folder {parent} is not writable")


# ---------------------------------------------------------------------------------------
# Commands
# ---------------------------------------------------------------------------------------


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
    from .diagnostics import summarize
    from .integrators import with_scalar_newton
    from .scenes import get_scene
    from .simulate import simulate_timed

    scene = get_scene(args.system)
    try:
        # As in `sweep`: the Lie-group VIs solved on scalars (the same solutions to
        # round-off; one car-pendulum trajectory 7-9x faster, compiled 0.6-0.9 s longer).
        method = with_scalar_newton(scene.method(args.method))
    except ValueError as err:
        detail = str(err).removeprefix(f"{scene.name}: ")
        raise UsageError(f"--method {args.method!r} is not available for {scene.name}: "
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
        model, state0 = scene.build(overrides)
    except ValueError as err:
        raise UsageError(str(err)) from None
    _check_writable_file(out)  # last: nothing is created on disk for a rejected command
    traj, timing = simulate_timed(
        model, method, state0, args.dt, n_steps, save_every=args.save_every
    )
    summary = summarize(traj)
    config = {
        "system": scene.name,
        "method": method.name,
        "dt": args.dt,
        "t_final": args.t_final,
        "n_steps": n_steps,
        "save_every": args.save_every,
        "parameters": {k: v.tolist() for k, v in overrides.items()},
    }
    arrays = scene.arrays(model, traj)
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
            f"{scene.name} / {method.describe()}: {n_steps} steps of {args.dt:g} "
            f"in {timing['run_s']:.3g} s ({timing['steps_per_second']:.3g} steps/s, "
            f"compiled in {timing['compile_s']:.3g} s)\n"
            f"relative energy error: {energy_error_line(summary)}\n"
            f"wrote {out} ({len(arrays['t'])} saved states)"
        )
    if summary["result"] != 0:
        print(f"{PROG} simulate: integration failed: {summary['message']}", file=sys.stderr)
        return 1
    return 0


def cmd_reproduce(args: argparse.Namespace) -> int:
    from .reproduce import reproduce

    if args.full:
        import importlib.util

        if importlib.util.find_spec("scipy") is None:
            raise UsageError("--full needs SciPy (the reference solutions and peer solvers): "
                             "pip install 'lgvi_jax[bench]'")
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UsageError(f"--out {out}: cannot create folder: {err.strerror}") from None
    if not os.access(out, os.W_OK):
        raise UsageError(f"--out {out}: folder is not writable")
    reproduce(out, quick=args.quick, force=args.force, full=args.full)
    return 0


def _csv_list(text: str, convert, option: str) -> list:
    items = [t.strip() for t in text.split(",") if t.strip()]
    try:
        return [convert(t) for t in items]
    except ValueError:
        raise UsageError(f"{option} {text!r}: expected a comma-separated list") from None


def configure_devices(spec: str | None, *, affinity: bool = False) -> None:
    """Expose host devices to XLA before JAX starts: ``auto`` = one per core (a no-op
    when JAX already runs, e.g. in tests), an integer = that many. With ``affinity``
    (a distributed sweep), ``auto`` counts the cores this process may run on (its CPU
    affinity: what Slurm or ``taskset`` grants it) instead of the machine's."""
    import jax

    if spec is None:
        return
    if spec == "auto":
        n = os.cpu_count() or 1
        if affinity and hasattr(os, "sched_getaffinity"):
            n = len(os.sched_getaffinity(0)) or n
    else:
        try:
            n = int(spec)
        except ValueError:
            raise UsageError(f"--devices must be 'auto' or an integer >= 1, got {spec!r}") from None
        if n < 1:
            raise UsageError(f"--devices must be 'auto' or an integer >= 1, got {spec!r}")
    try:
        jax.config.update("jax_num_cpu_devices", n)
    except RuntimeError:  # the backend is already initialised: keep its devices
        if spec != "auto":
            raise UsageError("--devices: JAX is already initialised in this process; set "
                             "it before the first computation") from None


def _start_distributed(args: argparse.Namespace) -> int:
    """Join the processes of a distributed sweep (before JAX computes anything); returns
    this process's index (0 without distributed options)."""
    given = [args.coordinator, args.num_processes, args.process_id]
    if args.distributed is None and all(v is None for v in given):
        return 0
    from .distributed import DistributedError, initialize

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
        from . import _plot_worker

        _plot_worker.start()
    import jax

    from .scenes import get_scene
    from .sweep import SweepConfig, SweepError, run_sweep

    scene = get_scene(args.system)
    overrides = parse_set(args.set)
    config = SweepConfig(
        system=scene.name,
        methods=tuple(_csv_list(args.method, str, "--method")),
        dts=tuple(_csv_list(args.dt, float, "--dt")),
        t_final=args.t_final, n=args.n, perturb=args.perturb, seed=args.seed,
        chunk=args.chunk, sample_every=args.sample_every,
        parameters={k: v.tolist() for k, v in overrides.items()},
        chord=args.chord,
    )
    try:
        config.validate(list(scene.methods))
        model, state0 = scene.build(overrides)
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
    log(f"{scene.name}: {config.n} initial conditions x {len(config.methods)} method(s) x "
        f"{len(config.dts)} step(s) on {len(devices)} {devices[0].platform} device(s)"
        + where)
    try:
        from .sweep import sweep_method

        def make_method(name):
            return sweep_method(scene.name, name, config.chord)

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


def cmd_bench(args: argparse.Namespace) -> int:
    configure_devices(args.devices)
    from .bench.throughput import ENGINE_CHOICES, PARTS, run
    from .scenes import SCENES

    systems = tuple(_csv_list(args.systems, str, "--systems"))
    for s in systems:
        if s not in SCENES or s == "oscillator":
            raise UsageError(f"--systems {s!r}: choose from "
                             f"{', '.join(k for k in SCENES if k != 'oscillator')}")
    methods = tuple(_csv_list(args.methods, str, "--methods")) if args.methods else None
    for m in methods or ():
        for s in systems:
            try:
                SCENES[s].method(m)
            except ValueError as err:
                raise UsageError(f"--methods: {err}") from None
    engines = tuple(_csv_list(args.engines, str, "--engines")) if args.engines else None
    for e in engines or ():
        if e not in ENGINE_CHOICES:
            raise UsageError(f"--engines {e!r}: choose from {', '.join(ENGINE_CHOICES)}")
    parts = tuple(_csv_list(args.parts, str, "--parts")) if args.parts else None
    for p in parts or ():
        if p not in PARTS:
            raise UsageError(f"--parts {p!r}: choose from {', '.join(PARTS)}")
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UsageError(f"--out {out}: cannot create folder: {err.strerror}") from None
    run(out, quick=args.quick, steps=args.steps, batch=args.batch, methods=methods,
        systems=systems, engines=engines, parts=parts, long_run=not args.no_long_run,
        log=lambda m: print(m, file=sys.stderr, flush=True))
    print((out / "bench.md").read_text(), end="")
    return 0


#: ``--init`` names of ``lgvi-jax fit`` (the initial state's R0 and q0 come from the data).
FIT_INIT_NAMES = ("J", "rho_c", "m", "M", "g", "omega0", "v0")


def cmd_fit(args: argparse.Namespace) -> int:
    from .identify import FITTABLE, fit, load_observations
    from .scenes import get_scene

    scene = get_scene(args.system)
    if args.method not in scene.methods:
        raise UsageError(f"--method {args.method!r} is not available for {scene.name}; "
                         f"choose from: {', '.join(scene.methods)}")
    if not math.isfinite(args.dt) or args.dt <= 0:
        raise UsageError(f"--dt must be a finite number > 0, got {args.dt!r}")
    names = _csv_list(args.fit, str, "--fit")
    if not names:
        raise UsageError(f"--fit {args.fit!r}: name at least one of {', '.join(FITTABLE)}")
    for name in names:
        if name not in FITTABLE:
            raise UsageError(f"--fit {name!r}: choose from {', '.join(FITTABLE)}")
    if len(set(names)) != len(names):
        raise UsageError(f"--fit {args.fit!r}: a name is given twice")
    if args.lr is not None and not (math.isfinite(args.lr) and args.lr > 0):
        raise UsageError(f"--lr must be a finite number > 0, got {args.lr!r}")
    out = Path(args.out)
    if out.suffix != ".json":
        raise UsageError(f"--out {out}: expected a file name ending in .json")
    init = {}
    for name, value in parse_set(args.init).items():
        if name not in FIT_INIT_NAMES:
            raise UsageError(f"--init {name}: choose from {', '.join(FIT_INIT_NAMES)} (the "
                             "initial attitude and cart position come from --data)")
        init[name] = value
    data = Path(args.data)
    if not data.is_file():
        raise UsageError(f"--data {data}: no such file")
    try:
        obs = load_observations(data, args.dt)
    except ValueError as err:
        raise UsageError(f"--data {err}") from None
    try:
        overrides = {k: v for k, v in init.items()}
        overrides.update(R0=np.ravel(np.asarray(obs.R0)), q0=np.asarray(obs.q0))
        for key in ("omega0", "v0"):
            overrides.setdefault(key, np.asarray(getattr(obs, key)))
        model, _ = scene.build(overrides)
    except ValueError as err:
        raise UsageError(f"--init: {err}") from None
    if "omega0" in init and "omega0" not in names:
        raise UsageError("--init omega0 is only allowed with --fit omega0 (otherwise the "
                         "observed initial velocity is used)")
    if "v0" in init and "v0" not in names:
        raise UsageError("--init v0 is only allowed with --fit v0 (otherwise the observed "
                         "initial velocity is used)")
    _check_writable_file(out)
    # fit() replaces the model's initial state by the observations'; a given --init
    # omega0/v0 is the starting value of the fitted velocity instead.
    from .identify import Observations

    obs = Observations(t=obs.t, R=obs.R, q=obs.q, R0=obs.R0, omega0=model.omega0,
                       q0=obs.q0, v0=model.v0)
    try:
        result = fit(obs, args.dt, names=names, model=model, method=args.method,
                     optimizer=args.optimizer, iterations=args.iterations, lr=args.lr,
                     progress=not args.json)
    except ValueError as err:
        raise UsageError(str(err)) from None
    report = {
        "system": scene.name,
        "data": str(data),
        **result.to_json(),
        "observations": int(np.size(obs.t)),
        "init": {k: v.tolist() for k, v in init.items()},
    }
    atomic_write_json(out, report)
    if args.json:
        print(json.dumps({k: v for k, v in report.items() if k != "loss_history"}))
    else:
        J = np.asarray(report["values"]["J"])
        rows = "\n".join("  " + "  ".join(f"{x:12.6g}" for x in row) for row in J)
        fitted = ", ".join(f"{k} = {np.round(report['values'][k], 6).tolist()}"
                           for k in names if k != "J")
        print(f"{scene.name} / {result.method}: fitted {', '.join(names)} to "
              f"{report['observations']} observations with {args.optimizer}, "
              f"{result.iterations} iterations ({result.stopped}) in "
              f"{result.wall_time_s:.3g} s\n"
              f"loss {result.loss_initial:.4e} -> {result.loss_final:.4e}")
        if "J" in names:
            print(f"J about the pivot:\n{rows}")
        if fitted:
            print(fitted)
        print(f"wrote {out}")
    if result.stopped == "non-finite":
        print(f"{PROG} fit: stopped: a rollout failed (non-finite values); wrote the last "
              "good iterate", file=sys.stderr)
        return 1
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    from .integrators import SCHEMES
    from .scenes import SCENES

    for scene in SCENES.values():
        print(f"{scene.name}: {scene.description}")
        print("  methods:")
        for name, make in scene.methods.items():
            print(f"    {name:<11} {make().describe()}")
        composable = [n for n, make in scene.methods.items() if make().symmetric]
        print(f"    METHOD@ORDER (4, 6, 8) or METHOD@SCHEME ({', '.join(SCHEMES)}): a "
              f"symmetric composition of {', '.join(composable)}")
        print("  --set parameters:")
        for p in scene.parameters:
            default = ",".join(f"{v:g}" for v in p.default)
            print(f"    {p.name:<11} {p.size} number(s), default {default}: {p.doc}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from .scenes import SCENES

    parser = _Parser(
        prog=PROG,
        description="Structure-preserving integrators for rigid-body mechanics (JAX).",
    )
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    sim = sub.add_parser("simulate", help="integrate one system with one method")
    sim.add_argument("system", choices=list(SCENES), help="the system to integrate")
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

    rep = sub.add_parser("reproduce", help="reproduce the paper's results into a folder")
    rep.add_argument("--out", required=True, help="output folder")
    rep.add_argument("--quick", action="store_true",
                     help="shorter runs (for smoke tests); the figures keep their layout")
    rep.add_argument("--force", action="store_true",
                     help="recompute stages whose results already exist in the folder")
    rep.add_argument("--full", action="store_true",
                     help="also the work-precision, stability and inertia-identification "
                     "studies (about 8 min on 2 cores; needs the `bench` extra: SciPy, diffrax)")
    rep.set_defaults(func=cmd_reproduce)

    sw = sub.add_parser(
        "sweep", help="batched energy-drift sweep over perturbed initial conditions",
        description="Integrate N initial conditions drawn around the system's default "
        "state with every method and step; per-trajectory structure metrics go to OUT "
        "chunk by chunk (resumable with --resume).")
    sw.add_argument("system", choices=list(SCENES), help="the system to integrate")
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
                    "batch is sharded over all devices")
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

    be = sub.add_parser("bench", help="benchmark sweeps, gradients and fits, against Numba",
                        description="Time what users run: the sweep's batched rollout with "
                        "metrics every step (one trajectory and a batch) for each system, "
                        "method and engine, beside compiled-loop Numba baselines with the "
                        "same per-step diagnostics (car-pendulum); jax.grad through a long "
                        "rollout; the inertia fit; the memory of long runs. Writes "
                        "bench.json and bench.md into OUT.")
    be.add_argument("--out", required=True, metavar="DIR", help="output folder")
    be.add_argument("--quick", action="store_true",
                    help="small sizes (smoke test): 1000 steps, batch 64, methods "
                    "lgvi,hamel,lgvi@4, engine scalar, parts throughput,gradient")
    be.add_argument("--steps", type=_positive_int, default=None, help="steps (default 10^4)")
    be.add_argument("--batch", type=_positive_int, default=None,
                    help="batch size (default 1024)")
    be.add_argument("--methods", default=None, metavar="M[,M...]",
                    help="methods, also METHOD@ORDER (default lgvi,hamel,hamel-cayley,"
                    "hamel-exact,lgvi@4,lgvi@6,lgvi@8)")
    be.add_argument("--systems", default="car-pendulum,heavy-top", metavar="S[,S...]",
                    help="systems of the throughput part (default car-pendulum,heavy-top)")
    be.add_argument("--engines", default=None, metavar="E[,E...]",
                    help="engines to time: scalar (the autodiff engine on scalars, what "
                    "`sweep` runs; default) and general (the same equations on arrays, "
                    "for comparison)")
    be.add_argument("--parts", default=None, metavar="P[,P...]",
                    help="throughput, gradient, fit, sweep (default the first three; "
                    "sweep: a hamel sweep end to end in fresh processes, cold "
                    "and warm cache, beside Numba's compiled run)")
    be.add_argument("--no-long-run", action="store_true",
                    help="skip the 10^6-step bounded-memory run")
    be.add_argument("--devices", default="auto", metavar="auto|N",
                    help="host devices on a CPU-only machine (default: one per core)")
    be.set_defaults(func=cmd_bench)

    fi = sub.add_parser(
        "fit", help="fit parameters (inertia, ...) to an observed trajectory",
        description="Fit the car-pendulum's parameters to observed attitudes and cart "
        "positions (OBS.npz: t (n,), R (n,3,3), q (n,2), R0, omega0, q0, v0) by "
        "differentiating a variational integrator's rollout; writes FIT.json.")
    fi.add_argument("system", choices=["car-pendulum"], help="the system")
    fi.add_argument("--data", required=True, metavar="OBS.npz", help="observations (.npz)")
    fi.add_argument("--method", required=True, help="integrator (see `lgvi-jax info`)")
    fi.add_argument("--dt", required=True, type=_float,
                    help="step size; every observation time must be a multiple of it")
    fi.add_argument("--fit", required=True, metavar="NAME[,NAME...]",
                    help="quantities to fit: J, rho_c, m, M, g, omega0, v0")
    fi.add_argument("--init", action="append", metavar="NAME=V1[,V2...]",
                    help="starting value of a fitted quantity, or value of a fixed one "
                    "(repeatable; J: 9 numbers row-major, about the pivot; default: the "
                    "paper's values)")
    fi.add_argument("--iterations", type=_positive_int, default=300, metavar="N",
                    help="most optimiser iterations (default 300)")
    fi.add_argument("--lr", type=_float, default=None,
                    help="initial damping (gauss-newton, default 1e-3), learning rate "
                    "(adam, default 1e-2), or first-step scale (lbfgs, default 1)")
    fi.add_argument("--optimizer", choices=["lbfgs", "adam", "gauss-newton"],
                    default="gauss-newton", help="Levenberg-Marquardt with forward-mode "
                    "Jacobians (default), L-BFGS, or optax Adam")
    fi.add_argument("--out", required=True, metavar="FIT.json", help="output file (.json)")
    fi.add_argument("--json", action="store_true",
                    help="print a one-object JSON summary (no progress bar)")
    fi.set_defaults(func=cmd_fit)

    info = sub.add_parser("info", help="list systems, methods and parameters")
    info.set_defaults(func=cmd_info)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command not in ("info", "bench"):  # bench: compile times measured cold
        _cache.enable()  # compiled programs reused across runs (lgvi_jax._cache)
    try:
        code = args.func(args)
    except UsageError as err:
        print(f"{PROG} {args.command}: error: {err}", file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        print(f"{PROG} {args.command}: interrupted", file=sys.stderr)
        code = 130
    if args.command == "sweep":  # a distributed sweep that did not complete ends here
        from .distributed import end_process

        end_process(code)
    return code


def run() -> None:
    """The ``lgvi-jax`` console script: :func:`main`, then :func:`_exit_now`."""
    _exit_now(main())


def _exit_now(code: int) -> None:
    """End the process without the interpreter's teardown, which destroys JAX's backend
    and every compiled program (~0.5 s of a 5 s warm sweep, measured), once the outputs
    are flushed; a distributed run (JAX's client initialised: its shutdown barrier and
    the watchdog run at exit) and any doubt take the usual exit."""
    import logging

    try:
        dist = sys.modules.get("jax._src.distributed")
        if dist is not None and getattr(dist.global_state, "client", None) is not None:
            sys.exit(code)
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
    except Exception:  # (a closed stream, another JAX): the usual exit
        sys.exit(code)
    os._exit(code)


if __name__ == "__main__":  # pragma: no cover
    run()
