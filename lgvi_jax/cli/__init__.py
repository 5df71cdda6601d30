"""Command-line interface: ``lgvi-jax {simulate, sweep, bench, fit, reproduce, info}``.

A thin layer over the library. Bad input exits with status 2 and a one-line message (no
traceback); a run whose integration fails still writes its output (with the failure
recorded in it), prints what failed, and exits with status 1; a closed standard output
(``| head``) ends the command quietly with status 141.

One module per command holds its function and its options (``register``);
:mod:`lgvi_jax.cli._common` holds what the commands share.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

from .. import _cache
from . import bench, fit, info, reproduce, simulate, sweep
from ._common import PROG, UsageError, _Parser, parse_set
from .simulate import energy_error_line

__all__ = ["PROG", "UsageError", "build_parser", "energy_error_line", "main", "parse_set",
           "run"]


def build_parser() -> argparse.ArgumentParser:
    """The ``lgvi-jax`` parser: each command module adds its own subcommand."""
    parser = _Parser(
        prog=PROG,
        description="Structure-preserving integrators for rigid-body mechanics (JAX).",
    )
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for command in (simulate, reproduce, sweep, bench, fit, info):
        command.register(sub)
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
    except BrokenPipeError:
        # The reader of standard output went away (``... --json | head``): stop quietly,
        # with the shell's status for SIGPIPE, like other command-line tools; what later
        # flushes write goes nowhere instead of raising again at exit.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        code = 141
    if args.command == "sweep":  # a distributed sweep that did not complete ends here
        from ..distributed import end_process

        end_process(code)
    return code


def run() -> None:
    """The ``lgvi-jax`` console script: :func:`main`, then :func:`_exit_now`."""
    _exit_now(main())


def _exit_now(code: int) -> None:
    """End the process without the interpreter's teardown, which destroys JAX's backend
    and every compiled program (a noticeable share of a warm sweep), once the outputs
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
