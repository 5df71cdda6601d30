"""What the commands of :mod:`lgvi_jax.cli` share: the program name, the one-line usage
error (:class:`UsageError`, exit status 2) and the parser that reports its own errors
that way, the argument types and checks of the options, and the host-device setup of
JAX (``--devices``)."""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

import numpy as np

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
