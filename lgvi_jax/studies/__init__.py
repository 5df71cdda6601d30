"""The studies that ``lgvi-jax reproduce`` runs: one module per part of the paper
(``oscillator``, ``car_pendulum``) and per study beyond it (``work_precision``,
``stability``, ``identify_inertia``).

Each module has ``run(out_dir, quick=False, log=print) -> dict``: it writes its figures,
``summary.md`` and, last, ``results.json`` into ``out_dir``. One runs alone as
``python -m lgvi_jax.studies.NAME --out DIR [--quick]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .._io import atomic_write_text

#: The methods the work-precision and stability studies run on SO(3) x R^n (the
#: car-pendulum) and on R^n (the oscillator), by system name; names that do not resolve are
#: skipped and listed in the studies' summaries.
RIGID_METHOD_NAMES: tuple[str, ...] = (
    "lgvi", "hamel", "hamel-cayley", "hamel-exact", "hamel-cayley-exact", "rk4", "gl4",
    "rkmk4", "lgvi@4", "lgvi@6", "lgvi@8", "galerkin4", "galerkin6",
)
EUCLIDEAN_METHOD_NAMES: tuple[str, ...] = (
    "rk4", "gl4", "gl6", "verlet", "galerkin4", "galerkin6", "verlet@4", "verlet@6",
    "verlet@8",
)
#: Of those, the variational integrators (discrete Lagrangians on SO(3) x R^n, the paper's
#: Hamel VIs among them; on R^n Verlet, Gauss–Legendre and the Galerkin VIs, compositions of
#: them): the work-precision summary names the best of them per regime beside our best.
VARIATIONAL_RIGID: frozenset[str] = frozenset({
    "lgvi", "hamel", "hamel-cayley", "hamel-exact", "hamel-cayley-exact", "lgvi@4", "lgvi@6",
    "lgvi@8", "galerkin4", "galerkin6", "galerkin8",
})
VARIATIONAL_EUCLIDEAN: frozenset[str] = frozenset({
    "gl4", "gl6", "verlet", "galerkin4", "galerkin6", "verlet@4", "verlet@6", "verlet@8",
})


def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def script_main(run: Callable, description: str | None, argv: list[str] | None = None, *,
                quick_help: str | None = "a shorter run (smoke test)") -> int:
    """The command line of a study or benchmark script: ``--out DIR`` and, when
    ``quick_help`` is given, ``--quick``; runs ``run(out, [quick=...,] log=...)`` and
    reports the wall time on stderr."""
    parser = argparse.ArgumentParser(description=(description or "").strip().splitlines()[0])
    parser.add_argument("--out", required=True, help="output folder")
    if quick_help:
        parser.add_argument("--quick", action="store_true", help=quick_help)
    args = parser.parse_args(argv)
    options = {"quick": args.quick} if quick_help else {}
    start = time.perf_counter()
    run(args.out, log=_stderr, **options)
    print(f"done in {time.perf_counter() - start:.1f} s", file=sys.stderr)
    return 0


def write_summary_lines(out: Path, lines: list[str]) -> str:
    """Write ``lines`` as the stage's ``out/summary.md`` (one per line); return the text."""
    text = "\n".join(lines) + "\n"
    atomic_write_text(Path(out) / "summary.md", text)
    return text


def mark_complete(out: Path, results: Any, indent: int = 2) -> None:
    """Write ``out/results.json`` — last, after every figure and ``summary.md``: its presence
    marks the stage as complete (:mod:`lgvi_jax.reproduce` skips a completed stage)."""
    atomic_write_text(Path(out) / "results.json", json.dumps(results, indent=indent))
