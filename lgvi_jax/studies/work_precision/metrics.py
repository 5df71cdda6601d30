"""The metrics of the work-precision study, computed from the saved states of a run by the
same code for every family: position errors against the reference, energy and
momentum-map drift, SO(3) orthogonality; and the regimes (winners, best of ours, best peer)
computed from the measured runs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from lgvi_jax.studies import VARIATIONAL_EUCLIDEAN, VARIATIONAL_RIGID
from lgvi_jax.systems import get_system

from .cases import CHECK_TIMES, RIGID_CASES, Case
from .runners import run_ours


def measure(system: Case, run: dict, T: float, positions: bool = True) -> dict:
    """The metrics of a raw run (the package docstring), as plain numbers; ``series`` keeps the
    invariant errors against time (for the long-run chart). ``positions=False`` (the long
    horizon): no comparison with the reference."""
    t, states = run["t"], run["states"]
    out = {k: run[k] for k in ("family", "method", "param", "value", "wall_s", "runs",
                               "compile_s", "n_steps", "result", "message")}
    out["horizon"] = T
    inv = system.invariants(states)
    finite = bool(all(np.all(np.isfinite(v)) for v in inv.values()))
    if out["result"] == 0 and not finite:
        out["result"], out["message"] = 1, "non-finite values in the saved states"
    out["failed"] = out["result"] != 0
    pos = system.positions(states)
    for tc in CHECK_TIMES if positions else ():
        if tc <= T + 1e-12:
            i = int(np.argmin(np.abs(t - tc)))
            if abs(t[i] - tc) < 1e-9:
                err = float(np.linalg.norm(pos[i] - system.reference_position(tc)))
                out[f"position_error_t{tc:g}"] = err if np.isfinite(err) else None
    E = inv["energy"]
    rel = np.abs(E - E[0]) / abs(E[0])
    series = {"t": t, "energy": rel}
    out["energy_error_max"] = float(np.max(rel)) if finite else None
    for k in ("momentum", "angular_momentum_z"):
        if k in inv:
            dev = np.abs(inv[k] - inv[k][:1]).reshape(len(t), -1).max(axis=1)
            series[k] = dev
            out[f"{k}_drift_max"] = float(np.max(dev)) if finite else None
    if "orthogonality_error" in inv:
        series["orthogonality"] = inv["orthogonality_error"]
        out["orthogonality_error_max"] = (float(np.max(inv["orthogonality_error"]))
                                          if finite else None)
    out["series"] = series
    return out


def observed_error_order(system: Case, name: str, steps: Sequence[float],
                         T: float = 10.0) -> tuple[float, list[float]]:
    """The harness's error measurement on a small case: position error at ``T`` for our
    method ``name`` at each step, and the least-squares slope of log error against log h."""
    method = get_system(system.system_name).method(name)
    errors = []
    for h in steps:
        raw = run_ours(system, name, method, h, T, 100, repeats=1)
        errors.append(measure(system, raw, T)[f"position_error_t{T:g}"])
    slope = float(np.polyfit(np.log(steps), np.log(errors), 1)[0])
    return slope, errors


# ------------------------------------------------------------------------- regimes


def _label(r: dict) -> str:
    if r["param"] == "h":
        return f"{r['method']} (h = {r['value']:g})"
    return f"{r['method']} (rtol = {r['value']:g})"


def _fastest(runs: list[dict], ok: Callable[[dict], bool]) -> dict[str, dict]:
    """Per method, the fastest run satisfying ``ok``."""
    best: dict[str, dict] = {}
    for r in runs:
        if r["failed"] or not ok(r):
            continue
        if r["method"] not in best or r["wall_s"] < best[r["method"]]["wall_s"]:
            best[r["method"]] = r
    return best


def _variational(key: str) -> frozenset[str]:
    """Our variational methods on the system of a regime key."""
    return VARIATIONAL_RIGID if key in RIGID_CASES else VARIATIONAL_EUCLIDEAN


def _regime(name: str, description: str, best: dict[str, dict], value_key: str,
            lower_is_better: bool = True, variational: frozenset[str] = frozenset()) -> dict:
    """Winner, best of ours, best peer and their ratio (peer / ours, > 1: ours better);
    the best of our ``variational`` methods and the best peer over it."""
    rows = sorted(best.values(), key=lambda r: r[value_key] if lower_is_better
                  else -r[value_key])
    out = {"regime": name, "description": description, "metric": value_key,
           "ranking": [{"label": _label(r), "method": r["method"], "family": r["family"],
                        value_key: r[value_key], "wall_s": r["wall_s"]} for r in rows]}
    if not rows:
        out["winner"] = None
        return out
    out["winner"] = out["ranking"][0]
    ours = [r for r in rows if r["family"] == "ours"]
    peers = [r for r in rows if r["family"] != "ours"]
    out["best_ours"] = out["ranking"][rows.index(ours[0])] if ours else None
    out["best_peer"] = out["ranking"][rows.index(peers[0])] if peers else None
    vi = [r for r in ours if r["method"] in variational]
    out["best_variational"] = out["ranking"][rows.index(vi[0])] if vi else None

    def ratio(a, b):
        return (b / a if lower_is_better else a / b) if a > 0 else None

    if ours and peers:
        out["peer_over_ours"] = ratio(ours[0][value_key], peers[0][value_key])
    if vi and peers:
        out["peer_over_variational"] = ratio(vi[0][value_key], peers[0][value_key])
    return out


def regimes(results: dict, cfg: dict) -> list[dict]:
    """The regimes of the summary table, computed from the measured runs."""
    tg = cfg["targets"]
    out = []
    for key, res in results["systems"].items():
        runs = res["runs"]
        for T, target in ((10.0, tg["short_tight"]), (10.0, tg.get("short_mid")),
                          (10.0, tg["short_moderate"]), (50.0, tg["t50"])):
            if target is None:
                continue
            if T not in cfg["horizons"]:
                continue
            err = f"position_error_t{T:g}"
            best = _fastest([r for r in runs if r["horizon"] == T],
                            lambda r, err=err, target=target: r.get(err) is not None
                            and r[err] <= target)
            out.append(_regime(f"{key}: {T:g} s, position error ≤ {target:g}",
                               f"fastest run of [0, {T:g}] s with position error at t = {T:g}"
                               f" s ≤ {target:g}", best, "wall_s",
                               variational=_variational(key)))
    T = cfg["long_horizon"]
    target = tg["long_energy"]
    for key, runs in results.get("long_all", {}).items():
        best = _fastest(runs, lambda r: (r["energy_error_max"] or np.inf) <= target)
        out.append(_regime(f"{key}: {T:g} s, max relative energy error ≤ {target:g}",
                           f"fastest run of [0, {T:g}] s whose max relative energy error "
                           f"≤ {target:g}", best, "wall_s", variational=_variational(key)))
        inv = []
        for r in runs:
            keys = [k for k in r if k.endswith("_drift_max") or k == "orthogonality_error_max"]
            if r["failed"] or not keys or any(r[k] is None for k in keys):
                continue
            inv.append({**r, "invariant_error": max(r[k] for k in keys)})
        bound = tg.get("long_invariants")
        if inv and bound is not None:
            best = _fastest(inv, lambda r, bound=bound, target=target:
                            r["invariant_error"] <= bound
                            and (r["energy_error_max"] or np.inf) <= target)
            out.append(_regime(
                f"{key}: {T:g} s, all invariants (energy ≤ {target:g}, momentum maps and "
                f"SO(3) ≤ {bound:g})",
                f"fastest run of [0, {T:g}] s whose max relative energy error ≤ {target:g} "
                f"and whose worst of max |Δp|, max |ΔL_z|, max ‖RᵀR − I‖_F ≤ {bound:g}",
                best, "wall_s", variational=_variational(key)))
        if inv:
            best = {}
            for r in inv:
                if r["method"] not in best or r["invariant_error"] < best[r["method"]][
                        "invariant_error"]:
                    best[r["method"]] = r
            out.append(_regime(f"{key}: {T:g} s, invariants",
                               "smallest worst of max |Δp|, max |ΔL_z|, max ‖RᵀR − I‖_F "
                               f"over [0, {T:g}] s", best, "invariant_error",
                               variational=_variational(key)))
    batch = results.get("batch")
    if batch and batch["rows"]:
        best = {r["method"]: r for r in batch["rows"]}
        out.append(_regime(
            f"{results['batch_system']}: batch of {batch['batch']}",
            f"trajectories per second, {batch['batch']} perturbed initial states over "
            f"[0, {batch['horizon']:g}] s, each method at its cheapest setting meeting "
            f"position error ≤ {batch['target']:g} at t = {batch['horizon']:g} s on the "
            "unperturbed state", best, "trajectories_per_s", lower_is_better=False,
            variational=_variational(results["batch_system"])))
    return out
