r"""Diagnostics: energy errors, observed orders, drift, and closed-form predictions.

All functions take arrays (NumPy or JAX) and are usable on trajectories and in tests.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .trajectory import RESULTS

__all__ = [
    "drift_ratio",
    "observed_order",
    "relative_energy_error",
    "rk4_energy_factor",
    "summarize",
]


def relative_energy_error(energy: Any) -> np.ndarray:
    r"""``|E_n − E_0| / |E_0|`` along the last axis (absolute error when ``E_0 = 0``)."""
    energy = np.asarray(energy, dtype=np.float64)
    e0 = energy[..., :1]
    scale = np.where(e0 == 0.0, 1.0, np.abs(e0))
    return np.abs(energy - e0) / scale


def observed_order(steps: Any, errors: Any) -> float:
    r"""Least-squares slope of :math:`\log(\text{error})` against :math:`\log(h)`."""
    h = np.asarray(steps, dtype=np.float64)
    e = np.asarray(errors, dtype=np.float64)
    if h.shape != e.shape or h.size < 2:
        raise ValueError("observed_order: need at least two (step, error) pairs of equal length")
    if np.any(h <= 0) or np.any(~np.isfinite(e)) or np.any(e <= 0):
        raise ValueError("observed_order: steps and errors must be positive and finite")
    slope, _ = np.polyfit(np.log(h), np.log(e), 1)
    return float(slope)


def drift_ratio(error: Any, fraction: float = 0.1) -> float:
    """Max of ``error`` over the last ``fraction`` of the run divided by its max over the
    first ``fraction``: about 1 for a bounded oscillating error, about ``1/fraction`` for a
    linear drift."""
    err = np.abs(np.asarray(error, dtype=np.float64))
    n = max(1, round(fraction * err.shape[-1]))
    first = np.max(err[..., 1 : n + 1], axis=-1)  # skip the initial state (error 0)
    last = np.max(err[..., -n:], axis=-1)
    return float(last / first) if np.ndim(last) == 0 else last / first


def rk4_energy_factor(y: float, n_steps: int) -> float:
    r"""Exact energy ratio :math:`E_n/E_0 = |R(iy)|^{2n}` of RK4 on a harmonic oscillator,
    :math:`y = \omega h`, with :math:`|R(iy)|^2 = 1 - y^6/72 + y^8/576` (the stability
    polynomial :math:`R(z) = 1 + z + z^2/2 + z^3/6 + z^4/24` on the imaginary axis).
    """
    r2 = 1.0 - y**6 / 72.0 + y**8 / 576.0
    return float(np.exp(n_steps * np.log(r2)))


def summarize(traj: Any) -> dict[str, Any]:
    """Plain-Python summary of a (concrete, unbatched) :class:`~lgvi_jax.Trajectory`."""
    err = relative_energy_error(traj.energy)
    # The maxima are taken over the saved states after the initial one (whose error and
    # drifts are 0 by definition) that are finite: a run that fails at its first step has
    # none, and reports NaN, never a misleading 0.
    finite = np.isfinite(err[1:])
    code = int(np.asarray(traj.result))
    try:
        result_name = RESULTS(code).name
    except ValueError:
        result_name = f"unknown ({code})"
    out = {
        "n_steps": int(traj.n_steps),
        "dt": float(np.asarray(traj.dt)),
        "saved": int(np.shape(traj.t)[0]),
        "energy_error_max": float(np.max(err[1:][finite])) if finite.any() else float("nan"),
        "energy_error_final": float(err[-1]),
        "result": code,
        "result_name": result_name,
        "message": traj.message,
        "newton_iterations_mean": float(np.asarray(traj.newton_mean)),
        "newton_iterations_max": int(np.asarray(traj.newton_max)),
    }
    # Momentum maps and other invariants: the largest deviation from the initial value
    # (max over components), e.g. "momentum_drift_max", "angular_momentum_z_drift_max".
    for name, values in traj.invariants.items():
        if name == "energy":
            continue
        values = np.asarray(values, dtype=np.float64)
        dev = np.abs(values - values[:1]).reshape(len(values), -1)[1:]
        ok = np.all(np.isfinite(dev), axis=1)
        out[f"{name}_drift_max"] = float(np.max(dev[ok])) if ok.any() else float("nan")
    R = getattr(traj.state, "R", None)
    if R is not None:
        E = np.swapaxes(np.asarray(R), -1, -2) @ np.asarray(R) - np.eye(3)
        orth = np.sqrt(np.sum(E * E, axis=(-2, -1)))
        finite = np.isfinite(orth)
        out["orthogonality_error_max"] = float(np.max(orth[finite])) if finite.any() else (
            float("nan"))
    if code != RESULTS.successful:
        out["failed_step"] = int(np.asarray(traj.failed_step))
        out["failed_residual"] = float(np.asarray(traj.failed_residual))
    return out


def environment(**extra) -> dict:
    """Where a result was measured: package versions, the machine, the JAX devices and the
    date (UTC), plus ``extra`` entries; every experiment stores it in its ``results.json``."""
    import datetime
    import os
    import platform

    import jax

    from ._version import __version__

    return {
        "lgvi_jax": __version__,
        "jax": jax.__version__,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "devices": [str(d) for d in jax.devices()],
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        **extra,
    }
