"""``lgvi-jax reproduce --out DIR``: reproduce the paper's results (figures, tables) into
DIR, skipping stages whose results are already there unless ``--force``; ``--quick``
shortens the runs, ``--full`` adds the studies that need SciPy (the ``bench`` extra)."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from ._common import UsageError


def cmd_reproduce(args: argparse.Namespace) -> int:
    from ..reproduce import reproduce

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


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``reproduce`` command to the subcommands ``sub``."""
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
