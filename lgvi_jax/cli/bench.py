"""``lgvi-jax bench --out DIR``: time what users run (the sweep's batched rollout per
system, method and engine beside Numba baselines, gradients through a long rollout,
the inertia fit, end-to-end sweeps, the memory of long runs) with
:mod:`lgvi_jax.bench`; writes bench.json and bench.md into DIR and prints bench.md."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ._common import UsageError, _csv_list, _positive_int, configure_devices


def cmd_bench(args: argparse.Namespace) -> int:
    configure_devices(args.devices)
    from ..bench.throughput import ENGINE_CHOICES, PARTS, run
    from ..systems import SYSTEMS

    systems = tuple(_csv_list(args.systems, str, "--systems"))
    for s in systems:
        if s not in SYSTEMS or s == "oscillator":
            raise UsageError(f"--systems {s!r}: choose from "
                             f"{', '.join(k for k in SYSTEMS if k != 'oscillator')}")
    methods = tuple(_csv_list(args.methods, str, "--methods")) if args.methods else None
    for m in methods or ():
        for s in systems:
            try:
                SYSTEMS[s].method(m)
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


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``bench`` command to the subcommands ``sub``."""
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
