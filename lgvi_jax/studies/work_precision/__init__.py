r"""Speed against accuracy: every method of ours beside the tools a user would otherwise pick.

For the car-pendulum (the paper's initial state, and a state with non-zero horizontal
momentum) and the harmonic oscillator, this experiment runs

* **ours**: every method of :data:`RIGID_METHOD_NAMES` / :data:`EUCLIDEAN_METHOD_NAMES` that
  resolves through ``lgvi_jax.systems.get_system(system).method(name)`` (composed names such as
  ``lgvi@6`` enter automatically once they resolve), each over a range of fixed steps;
* **diffrax** (optional, the ``bench`` extra): ``Tsit5`` and ``Dopri8``, adaptive
  (``PIDController(rtol, atol)``, ``rtol = atol`` over a range) and fixed-step
  (``ConstantStepSize``), on the library's continuous equations ``model.vector_field``
  (for the car-pendulum: R embedded as 9 numbers), jitted, ``SaveAt(ts=...)``;
* **SciPy** ``solve_ivp`` (``DOP853``, ``RK45``, ``rtol = atol`` over a range) on the
  hand-derived NumPy equations :meth:`lgvi_jax.systems.car_pendulum.HandReference.rhs` (state
  ``(R, ω, q, v)``) for the car-pendulum and on ``(q̇, ṗ) = (p/m, −kq)`` for the
  oscillator, with ``t_eval`` at the save times: what a fair, idiomatic SciPy user writes
  (NumPy right-hand side, no JAX).

All are timed in the same process, after compilation (ahead-of-time ``lower().compile()``
for JAX; SciPy needs none), waiting for the result (``block_until_ready``), best of up to
:data:`REPEATS` runs when a run is cheap. Every run saves its state at the same 501 (or 101)
equally spaced times, and all metrics are computed from those saved states by the same code:

* ``position error`` at t = 10 s and t = 50 s: the pendulum mass centre
  ``(x, y, 0) + R ρ_c`` against :class:`~lgvi_jax.systems.car_pendulum.HandReference` (hand-derived
  equations, DOP853 at ``rtol = atol = 1e-13``, piecewise, no interpolation); for the
  oscillator ``|q − q_exact|`` against the closed-form solution. The reference's own error is
  estimated by comparing it with the same solve at ``1e-12`` (``reference_uncertainty``);
* ``max relative energy error`` ``max |E − E₀|/|E₀|`` over the saved states;
* ``momentum-map drift``: ``max |p − p₀|`` (cart momentum) and ``max |L_z − L_z0|``;
* ``‖RᵀR − I‖_F``, max over the saved states.

Horizons: 10 s and 50 s (accuracy), and 5000 s where drift decides. At 5000 s the
position is not compared with any reference: position errors, the reference's own
included, grow with the horizon (phase error, sensitivity to the initial state), so no
reference can be trusted for the position there. Only the invariants, which need no
reference, are measured.

Regimes and winners (summary.md): *short horizon* (fastest to a position error at t = 10 s
below a target), *t = 50 s*, *long horizon* (fastest to a max relative energy error over
5000 s below a target), *invariants* (smallest momentum-map and SO(3) errors over 5000 s) and
*batch throughput* (trajectories per second for a batch of perturbed initial states, each
method at the cheapest setting that meets the short-horizon target on the single
trajectory: our fastest methods, every diffrax solver, adaptive and fixed-step apart, and
SciPy's fastest; ours through :func:`lgvi_jax.sweep.batch_arguments`, diffrax through
``jax.vmap``, SciPy serially).

References: Hairer, Nørsett, Wanner, *Solving ODEs I* (1993), §II.10 (work-precision
diagrams); Kidger, *On Neural Differential Equations* (2021) (diffrax).

Run:  ``python -m lgvi_jax.studies.work_precision --out DIR [--quick]`` or
``lgvi-jax reproduce --full``.

Layout (each module imports only those listed after it): :mod:`.report` (charts,
``summary.md``), :mod:`.sweeps` (the plan, :func:`config`, and the sweeps of each system),
:mod:`.metrics` (errors, drift, invariants, regimes), :mod:`.runners` (ours, diffrax, SciPy;
timing; compiled functions), :mod:`.cases` (:class:`Case`, the references). This module
holds :func:`run`; ``diffrax`` is :data:`runners.diffrax` (``None`` when not installed: set
it there to run without it).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from lgvi_jax.studies import mark_complete
from lgvi_jax.systems import get_system, resolve_methods

from . import cases, metrics, report, runners, sweeps
from .cases import CHECK_TIMES, Case, make_case
from .metrics import measure, observed_error_order, regimes
from .report import (
    _jsonable,
    _strip,
    charts,
    environment,
    method_table,
    recommendations,
    write_summary,
)
from .runners import (
    DIFFRAX_MAX_STEPS,
    MAX_SAVES,
    REPEATS,
    diffrax,
    run_diffrax,
    run_ours,
    run_scipy,
)
from .runners import _grid as _grid
from .sweeps import (
    DIFFRAX_FIXED,
    DIFFRAX_LONG_TOLS,
    DIFFRAX_TOLS,
    LONG_STEPS,
    LONG_STEPS_OVERRIDE,
    OSC_STEPS,
    QUICK_EUCLIDEAN,
    QUICK_RIGID,
    RIGID_STEPS,
    SCIPY_LONG_TOLS,
    SCIPY_TOLS,
    TARGETS,
    _batch,
    _long_runs,
    _sweep_system,
    config,
)

__all__ = [
    "CHECK_TIMES",
    "DIFFRAX_FIXED",
    "DIFFRAX_LONG_TOLS",
    "DIFFRAX_MAX_STEPS",
    "DIFFRAX_TOLS",
    "LONG_STEPS",
    "LONG_STEPS_OVERRIDE",
    "MAX_SAVES",
    "OSC_STEPS",
    "QUICK_EUCLIDEAN",
    "QUICK_RIGID",
    "REPEATS",
    "RIGID_STEPS",
    "SCIPY_LONG_TOLS",
    "SCIPY_TOLS",
    "TARGETS",
    "Case",
    "cases",
    "charts",
    "config",
    "diffrax",
    "environment",
    "get_system",
    "make_case",
    "measure",
    "method_table",
    "metrics",
    "observed_error_order",
    "recommendations",
    "regimes",
    "report",
    "resolve_methods",
    "run",
    "run_diffrax",
    "run_ours",
    "run_scipy",
    "runners",
    "sweeps",
    "write_summary",
]


def run(out_dir: Path | str, *, quick: bool = False, log: Callable = print) -> dict:
    """Run the whole study into ``out_dir``; returns the results dictionary."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cfg = config(quick)
    start = time.perf_counter()
    systems, long_all = {}, {}
    results: dict[str, Any] = {"quick": quick, "config": cfg}
    if runners.diffrax is None:
        log("  diffrax is not installed: its runs are skipped")
    for key in cfg["systems"]:
        system = make_case(key, cfg["reference_rtol"])
        log(f"  {system.title} ...")
        res = _sweep_system(system, cfg, log)
        res["title"] = system.title
        if system.rigid and cfg["reference_check_rtol"] is not None:
            coarse = make_case(key, cfg["reference_check_rtol"])
            res["reference_uncertainty"] = float(np.linalg.norm(
                coarse.reference_position(50.0) - system.reference_position(50.0)))
        systems[key] = res
        if key == cfg["long_system"] or not system.rigid:
            log(f"  {system.title}: long horizon {cfg['long_horizon']:g} s ...")
            long_all[key] = _long_runs(system, cfg, log)
            if key == cfg["long_system"]:
                results["long"] = {"system": key, "title": system.title,
                                   "runs": long_all[key]}
        if key == cfg["batch_system"]:
            log("  batch throughput ...")
            results["batch"] = _batch(system, res["runs"], cfg, log)
            results["batch_system"] = key
    results["systems"] = systems
    results["long_all"] = long_all
    rigid_scipy = [r for k, res in systems.items() if "car" in k for r in res["runs"]
                   if r["family"] == "scipy" and r["horizon"] == max(cfg["horizons"])]
    if rigid_scipy:
        cheapest = min(r["wall_s"] for r in rigid_scipy)
        factor = cfg["long_horizon"] / max(cfg["horizons"])
        results["scipy_long_note"] = (
            f"SciPy is left out of the {cfg['long_horizon']:g} s car-pendulum run: its "
            f"cheapest {max(cfg['horizons']):g} s run took {cheapest:.3g} s here, so "
            f"≥ {cheapest * factor:.3g} s per tolerance at {cfg['long_horizon']:g} s.")
    results["regimes"] = regimes(results, cfg)
    results["files"] = charts(results, cfg, out)
    results["environment"] = environment()
    results["wall_time_s"] = time.perf_counter() - start
    write_summary(results, out)
    clean = {
        **results,
        "systems": {k: {**v, "runs": _strip(v["runs"])} for k, v in systems.items()},
        "long_all": {k: _strip(v) for k, v in long_all.items()},
    }
    if "long" in results:
        clean["long"] = {**results["long"], "runs": _strip(results["long"]["runs"], True)}
    mark_complete(out, _jsonable(clean), indent=1)
    return results
