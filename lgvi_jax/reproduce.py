"""``lgvi-jax reproduce``: run every study of the paper into one folder.

``full=True`` also runs :data:`FULL_STAGES`: the work-precision comparison against diffrax
and SciPy, the stability limits and the inertia identification (SciPy's DOP853 makes their
reference observations) (minutes on 2 cores; diffrax from the ``bench`` extra
is optional: without it the comparison runs our methods and SciPy and says so).

Each stage writes into its own sub-folder and finishes by writing ``results.json``; a
stage whose ``results.json`` exists (with the same settings) is skipped on a re-run, so an
interrupted reproduction loses at most the stage it was in. ``force=True`` recomputes.
"""

from __future__ import annotations

import importlib
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

from ._io import atomic_write_text

__all__ = ["FULL_STAGES", "STAGES", "reproduce"]

#: (name, module): each module has ``run(out_dir, quick=False, log=print) -> dict``.
STAGES: list[tuple[str, str]] = [
    ("oscillator", "lgvi_jax.studies.oscillator"),
    ("car_pendulum", "lgvi_jax.studies.car_pendulum"),
]


#: Extra stages run by ``reproduce(..., full=True)`` (``lgvi-jax reproduce --full``).
FULL_STAGES: list[tuple[str, str]] = [
    ("work_precision", "lgvi_jax.studies.work_precision"),
    ("stability", "lgvi_jax.studies.stability"),
    ("identify_inertia", "lgvi_jax.studies.identify_inertia"),
]


def _log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _done(stage_dir: Path, quick: bool) -> bool:
    marker = stage_dir / "results.json"
    if not marker.exists():
        return False
    try:
        return json.loads(marker.read_text()).get("quick") == quick
    except (OSError, json.JSONDecodeError):
        return False


def reproduce(
    out: Path | str, *, quick: bool = False, force: bool = False, full: bool = False,
    log: Callable = _log
) -> Path:
    """Run all stages into ``out`` (with ``full=True`` also :data:`FULL_STAGES`); return the
    path of the index ``out/README.md``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sections = []
    stages = STAGES + (FULL_STAGES if full else [])
    for i, (name, module) in enumerate(stages, 1):
        stage_dir = out / name
        if _done(stage_dir, quick) and not force:
            log(f"[{i}/{len(stages)}] {name}: already done in {stage_dir} (--force to redo)")
        else:
            log(f"[{i}/{len(stages)}] {name}: running{' (quick)' if quick else ''} ...")
            start = time.perf_counter()
            importlib.import_module(module).run(stage_dir, quick=quick, log=log)
            log(f"[{i}/{len(stages)}] {name}: done in {time.perf_counter() - start:.1f} s")
        summary = stage_dir / "summary.md"
        if summary.exists():
            sections.append(f"## {name}\n\nFolder: `{name}/`\n\n{summary.read_text()}")
    index = out / "README.md"
    atomic_write_text(index, "# lgvi_jax: reproduced results\n\n" + "\n\n".join(sections) + "\n")
    log(f"results in {out} (index: {index})")
    return index
