"""A finished sweep's outputs: the summary per method and step (:func:`summarize_sweep`),
``trajectories.csv``, ``summary.{json,md}`` and the energy-error plot."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import numpy as np

from .._io import (
    atomic_open,
    atomic_write_bytes,
    atomic_write_json,
    atomic_write_text,
)
from ..trajectory import RESULTS
from .config import FORMAT, SweepConfig


def summarize_sweep(config: SweepConfig, results) -> dict[str, Any]:
    rows = []
    for (method, dt), r in results.items():
        ok = r["result"] == RESULTS.successful
        e = r["energy_error_max"][ok]
        row = {"method": method, "dt": dt, "n": int(r["result"].size),
               "failed": int(np.sum(~ok)),
               "energy_error_max_median": float(np.median(e)) if e.size else float("nan"),
               "energy_error_max_p95": float(np.quantile(e, 0.95)) if e.size else float("nan"),
               "energy_error_max_max": float(np.max(e)) if e.size else float("nan"),
               "newton_mean": float(np.mean(r["newton_mean"][ok])) if ok.any() else float("nan")}
        for k in r:
            if k.endswith("_drift_max") or k == "orthogonality_error_max":
                row[f"{k}_max"] = float(np.max(r[k][ok])) if ok.any() else float("nan")
        rows.append(row)
    return {**FORMAT, "config": config.to_json(), "rows": rows}


def _write_outputs(out: Path, config: SweepConfig, results, summary) -> None:
    # trajectories.csv: one row per (method, dt, i)
    fields = [k for k in next(iter(results.values())) if k != "index"]
    with atomic_open(out / "trajectories.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["method", "dt", "index", *fields])
        for (method, dt), r in results.items():
            for j in range(r["index"].size):
                writer.writerow([method, repr(dt), int(r["index"][j]),
                                 *(repr(r[k][j].item()) for k in fields)])
    atomic_write_json(out / "summary.json", summary)
    lines = [f"# Sweep: {config.system}, {config.n} initial conditions, perturbation "
             f"{config.perturb:g}, seed {config.seed}, t_final = {config.t_final:g}", "",
             "Relative energy error max |H - H0|/|H0| per trajectory (over trajectories "
             "that did not fail).", "",
             "| method | dt | failed | median | p95 | max | Newton its/step |",
             "|---|---|---|---|---|---|---|"]
    def fmt(x: float, spec: str) -> str:  # n/a: every trajectory of the row failed
        return format(x, spec) if math.isfinite(x) else "n/a"

    for row in summary["rows"]:
        lines.append(f"| {row['method']} | {row['dt']:g} | {row['failed']}/{row['n']} | "
                     f"{fmt(row['energy_error_max_median'], '.3e')} | "
                     f"{fmt(row['energy_error_max_p95'], '.3e')} | "
                     f"{fmt(row['energy_error_max_max'], '.3e')} | "
                     f"{fmt(row['newton_mean'], '.2f')} |")
    atomic_write_text(out / "summary.md", "\n".join(lines) + "\n")
    _plot(out / "energy_error.png", config, results)


def _plot(path: Path, config: SweepConfig, results) -> None:
    from .. import _plot_worker
    from ..plotting import METHOD_STYLE

    data, labels, colors = [], [], []
    for (method, dt), r in results.items():
        ok = r["result"] == RESULTS.successful
        e = r["energy_error_max"][ok]
        data.append(np.log10(np.maximum(e, 1e-17)) if e.size else np.array([np.nan]))
        failed = int(np.sum(~ok))
        labels.append(f"{method}\ndt={dt:g}" + (f"\n{failed} failed" if failed else ""))
        colors.append(METHOD_STYLE.get(method, {}).get("color", "C0"))
    payload = {
        "data": data, "labels": labels, "colors": colors,
        "ylabel": r"$\log_{10}$ max $|H - H_0|/|H_0|$",
        "title": (f"{config.system}: energy error over {config.n} initial conditions\n"
                  f"(perturbation {config.perturb:g}, t = {config.t_final:g})"),
        "width": max(6.0, 1.1 * len(results) + 2), "height": 4.2,
    }
    atomic_write_bytes(path, _plot_worker.render(payload))
