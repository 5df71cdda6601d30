r"""Where each method fails: increase the step until the run breaks, and say why.

For every method of ours (names resolved through ``lgvi_jax.systems.get_system(...).method``,
composed names such as ``lgvi@6`` included once they resolve), on the car-pendulum (the
paper's state) and on the harmonic oscillator (``m = k = 1``, ``q0 = 1``, ``p0 = 0``), the
step ``h`` is scanned on a geometric grid and the boundary is then bisected between the
last stable and the first failing step of the scan.

**What "fails" means (precisely).** A run of a fixed horizon — :data:`OSC_STEPS` steps for
the oscillator (so that the per-step amplification of the linear theory decides), 50 s of
simulated time for the car-pendulum — *fails* if any of

1. a step's Newton solve does not converge (the rollout's result code,
   :data:`lgvi_jax.RESULTS`, as in :func:`lgvi_jax.simulate`);
2. a state becomes non-finite (result code ``nonfinite``);
3. the relative energy error ``|E − E₀|/|E₀|`` exceeds :data:`ENERGY_THRESHOLD` = 10 at any
   step.

A failure is always reported with its reason and step; it is never silent. The threshold
is 10, not 1: a stable method can have a bounded energy error close to 1 (Störmer–Verlet
near ``hω = 2`` oscillates between ``E₀`` and ``E₀/(1 − h²ω²/4)`` from some initial phases;
RK4 below its limit *loses* energy, ``|ΔE/E| → 1``), while an unstable one grows
geometrically, so the boundary moves only by ``~ log(threshold)/N`` in ``hω``.

**Theory (oscillator).** For the linear oscillator the one-step map is a 2x2 matrix
``M(hω)``, and the method is stable iff its eigenvalues lie in the closed unit disc
(semi-simple on the circle): RK4's stability function on the imaginary axis,
``|R(iy)|² = 1 − y⁶/72 + y⁸/576``, exceeds 1 for ``y > 2√2``; Störmer–Verlet's
``tr M = 2 − y²`` leaves ``[−2, 2]`` at ``y = 2``; Gauss–Legendre is A-stable with
``|R(iy)| = 1``: unconditionally stable. For the others (the Galerkin VIs, compositions)
the experiment also computes the *propagator limit*: the smallest ``y`` where the spectral
radius of the method's own one-step matrix (obtained by stepping the two unit vectors)
exceeds ``1 + 1e-9`` — the linear-theory prediction for any method, against which the
measured limit is compared.

References: Hairer, Nørsett, Wanner, *Solving ODEs I* (1993), §IV.2 (stability functions);
Hairer, Lubich, Wanner, *Geometric Numerical Integration* (2006), §I.5 and §XII
(Störmer–Verlet and symplectic methods on oscillators); Marsden & West, *Acta Numerica*
(2001) (Galerkin VIs).

Run:  ``python -m lgvi_jax.studies.stability --out DIR [--quick]`` or
``lgvi-jax reproduce --full``.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from lgvi_jax import rollout
from lgvi_jax.diagnostics import environment
from lgvi_jax.models import CarPendulum, HarmonicOscillator, PhaseState
from lgvi_jax.plotting import figure, method_style, positive, save
from lgvi_jax.studies import (
    EUCLIDEAN_METHOD_NAMES,
    RIGID_METHOD_NAMES,
    mark_complete,
    script_main,
    write_summary_lines,
)
from lgvi_jax.systems import resolve_methods
from lgvi_jax.trajectory import RESULTS

QUICK_RIGID = ("rk4",)
QUICK_EUCLIDEAN = ("rk4", "verlet", "gl4", "galerkin4")

#: Relative energy error above which a run counts as failed (module docstring).
ENERGY_THRESHOLD = 10.0
#: Oscillator horizon: a fixed number of steps.
OSC_STEPS = 10_000
#: Car-pendulum horizon: a fixed simulated time [s].
CAR_HORIZON = 50.0
#: Closed-form limits of h·ω on the oscillator (None: no limit, unconditionally stable).
THEORY = {"rk4": 2.0 * np.sqrt(2.0), "verlet": 2.0, "gl4": None, "gl6": None}
#: The spectral radius counts as > 1 above this (round-off of the 2x2 product).
PROPAGATOR_TOL = 1e-9

def config(quick: bool) -> dict:
    return {
        "quick": quick,
        "energy_threshold": ENERGY_THRESHOLD,
        "oscillator_steps": 2000 if quick else OSC_STEPS,
        "oscillator_scan": [0.25, 100.0, 14 if quick else 36],
        "oscillator_rtol": 1e-3 if quick else 1e-5,
        "car_horizon": 20.0 if quick else CAR_HORIZON,
        "car_scan": [0.02, 2.0, 8 if quick else 21],
        "car_rtol": 0.05 if quick else 0.01,
        "rigid_methods": list(QUICK_RIGID if quick else RIGID_METHOD_NAMES),
        "euclidean_methods": list(QUICK_EUCLIDEAN if quick else EUCLIDEAN_METHOD_NAMES),
        "max_bisections": 40,
    }


# ------------------------------------------------------------------------- the probe


@eqx.filter_jit
def _probe(model, method, state0, h, n_steps, threshold):
    """Up to ``n_steps`` steps of ``h`` (run-time: one compilation per method), stopping at
    the first failure (result code) or once the relative energy error exceeds
    ``threshold``. Returns ``(code, failed_step, max relative energy error over the finite
    states, steps taken)``."""
    e0 = model.energy(state0)
    scale = jnp.where(e0 != 0, jnp.abs(e0), 1.0)

    def observe(emax, c):
        rel = jnp.abs(model.energy(c.state) - e0) / scale
        return jnp.where(jnp.isfinite(rel), jnp.maximum(emax, rel), emax)

    end, emax = rollout.advance(model, method, h, rollout.start(model, method, state0, h),
                                n_steps, observe, jnp.zeros((), h.dtype), loop="while",
                                until=lambda c, emax: ~c.ok | (emax > threshold))
    return end.result, end.failed_step, emax, end.k


def probe(model, method, state0, h: float, n_steps: int,
          threshold: float = ENERGY_THRESHOLD) -> dict:
    """Run one probe and classify it: ``{"h", "n_steps", "failed", "reason", "step",
    "energy_error_max"}``; ``reason`` is ``None`` for a stable run, else the result code's
    description (Newton did not converge, non-finite values) or the energy criterion."""
    if not (np.isfinite(h) and h > 0):
        raise ValueError(f"probe: h must be finite and > 0, got {h!r}")
    if n_steps < 1:
        raise ValueError(f"probe: n_steps must be >= 1, got {n_steps!r}")
    code, failed_step, emax, k = _probe(
        model, method, state0, jnp.float64(h), jnp.int32(n_steps), jnp.float64(threshold))
    code, emax, k = int(code), float(emax), int(k)
    out = {"h": float(h), "n_steps": int(n_steps), "energy_error_max": emax}
    if code != RESULTS.successful:
        out.update(failed=True, reason=RESULTS.describe(code), code=code,
                   step=int(failed_step))
    elif emax > threshold:
        out.update(failed=True, reason=f"relative energy error above {threshold:g}",
                   code=None, step=k - 1)
    else:
        out.update(failed=False, reason=None, code=0, step=None)
    return out


def find_limit(run_at: Callable[[float], dict], grid: Sequence[float], rtol: float,
               max_bisections: int = 40) -> dict:
    """Scan ``run_at(h)`` over the increasing ``grid``, then bisect between the last stable
    step before the first failure and that failure until the bracket is below ``rtol``
    (relative). Returns the scan, the bracket, the limit (its midpoint) and the reason of
    the failure at the bracket's upper end; ``limit`` is None when nothing failed."""
    scan = [run_at(float(h)) for h in grid]
    first = next((i for i, r in enumerate(scan) if r["failed"]), None)
    out = {"scan": scan, "non_monotone": [], "bisections": []}
    if first is None:
        out.update(limit=None, bracket=[float(grid[-1]), None], failure=None)
        return out
    out["non_monotone"] = [r["h"] for r in scan[first + 1:] if not r["failed"]]
    if first == 0:
        out.update(limit=None, bracket=[None, float(grid[0])], failure=scan[0])
        return out
    lo, hi, fail = scan[first - 1]["h"], scan[first]["h"], scan[first]
    for _ in range(max_bisections):
        if (hi - lo) <= rtol * lo:
            break
        mid = float(np.sqrt(lo * hi))
        r = run_at(mid)
        out["bisections"].append(r)
        if r["failed"]:
            hi, fail = mid, r
        else:
            lo = mid
    out.update(limit=0.5 * (lo + hi), bracket=[lo, hi], failure=fail)
    return out


# ---------------------------------------------------------------------- oscillator


@eqx.filter_jit
def _one_step_matrix(model, method, h):
    """The 2x2 one-step matrix of ``method`` on the (linear) oscillator, columns the images
    of the unit vectors ``(q, p) = (1, 0)`` and ``(0, 1)``."""
    def image(q, p):
        s, _ = method.step(model, PhaseState(q=jnp.array([q]), p=jnp.array([p])), h)
        return jnp.array([s.q[0], s.p[0]])

    return jnp.stack([image(1.0, 0.0), image(0.0, 1.0)], axis=1)


def spectral_radius(model, method, h: float) -> float:
    M = np.asarray(_one_step_matrix(model, method, jnp.float64(h)))
    return float(np.max(np.abs(np.linalg.eigvals(M)))) if np.all(np.isfinite(M)) else np.inf


def propagator_limit(model, method, grid: Sequence[float], rtol: float) -> float | None:
    """The smallest scanned-then-bisected ``h`` with spectral radius > 1 + PROPAGATOR_TOL."""
    def at(h):
        rho = spectral_radius(model, method, h)
        return {"h": h, "failed": not rho <= 1.0 + PROPAGATOR_TOL, "rho": rho}

    return find_limit(at, grid, rtol)["limit"]


def oscillator_study(cfg: dict, log: Callable) -> dict:
    model = HarmonicOscillator(m=1.0, k=1.0)
    s0 = model.state(q0=1.0, p0=0.0)
    omega = float(model.omega)
    lo, hi, n = cfg["oscillator_scan"]
    grid = np.geomspace(lo, hi, int(n)) / omega
    methods, skipped = resolve_methods("oscillator", cfg["euclidean_methods"])
    res = {"omega": omega, "n_steps": cfg["oscillator_steps"], "skipped_methods": skipped,
           "methods": {}}
    for name, method in methods.items():
        start = time.perf_counter()
        lim = find_limit(lambda h, m=method: probe(model, m, s0, h, cfg["oscillator_steps"],
                                                   cfg["energy_threshold"]),
                         grid, cfg["oscillator_rtol"], cfg["max_bisections"])
        prop = propagator_limit(model, method, grid, cfg["oscillator_rtol"])
        # Linear instability, or a bounded energy excursion above the threshold (eigenvalues
        # on the unit circle but nearly colliding, as Verlet's near hω = 2)?
        fail_h = (lim["failure"] or {}).get("h")
        rho = None if fail_h is None else spectral_radius(model, method, fail_h)
        base = name.split("@")[0]
        theory = THEORY.get(name, "n/a") if "@" not in name else "n/a"
        lim.update(
            measured_h_omega=None if lim["limit"] is None else lim["limit"] * omega,
            bracket_h_omega=[None if b is None else b * omega for b in lim["bracket"]],
            theory_h_omega=theory,
            propagator_h_omega=None if prop is None else prop * omega,
            spectral_radius_at_failure=rho,
            linearly_unstable_at_failure=None if rho is None else rho > 1 + PROPAGATOR_TOL,
            base=base, order=method.order, wall_s=time.perf_counter() - start)
        res["methods"][name] = lim
        log(f"    oscillator {name}: measured hω = {_fmt(lim['measured_h_omega'])}, theory "
            f"{_fmt(theory)}, propagator {_fmt(lim['propagator_h_omega'])}, reason: "
            f"{(lim['failure'] or {}).get('reason')}")
    return res


# ----------------------------------------------------------------------- car-pendulum


def car_study(cfg: dict, log: Callable) -> dict:
    model = CarPendulum()
    s0 = model.default_state()
    T = cfg["car_horizon"]
    lo, hi, n = cfg["car_scan"]
    grid = np.geomspace(lo, hi, int(n))
    methods, skipped = resolve_methods("car-pendulum", cfg["rigid_methods"])
    res = {"horizon": T, "skipped_methods": skipped, "methods": {}}
    for name, method in methods.items():
        start = time.perf_counter()
        lim = find_limit(lambda h, m=method: probe(model, m, s0, h, int(np.ceil(T / h - 1e-9)),
                                                   cfg["energy_threshold"]),
                         grid, cfg["car_rtol"], cfg["max_bisections"])
        lim.update(order=method.order, wall_s=time.perf_counter() - start)
        res["methods"][name] = lim
        log(f"    car-pendulum {name}: limit h = {_fmt(lim['limit'])} s, reason: "
            f"{(lim['failure'] or {}).get('reason')} ({lim['wall_s']:.1f} s)")
    return res


# --------------------------------------------------------------------------- charts


def _fmt(x, fmt=".4g") -> str:
    if x is None:
        return "none (stable)"
    if isinstance(x, str):
        return x
    return format(x, fmt)


def _rho(rho) -> str:
    if rho is None:
        return "—"
    return f"{rho:.12f}" if rho <= 1 + PROPAGATOR_TOL else f"{rho:.6g} (> 1)"


def _energy_chart(study: dict, scale: float, xlabel: str, title: str, threshold: float,
                  path: Path) -> None:
    fig, ax = figure(width=10, height=5)
    for name, lim in study["methods"].items():
        pts = sorted(lim["scan"] + lim["bisections"], key=lambda r: r["h"])
        style = method_style(name)
        ok = [r for r in pts if not r["failed"]]
        bad = [r for r in pts if r["failed"]]
        (line,) = ax.loglog([r["h"] * scale for r in ok],
                            positive([r["energy_error_max"] for r in ok]), marker="o",
                            markersize=3, label=name, **style)
        ax.loglog([r["h"] * scale for r in bad], [threshold * 1.5] * len(bad), "x",
                  color=line.get_color(), markersize=5)
        if lim["limit"] is not None:
            ax.axvline(lim["limit"] * scale, color=line.get_color(), linewidth=0.8,
                       linestyle="--", alpha=0.7)
    ax.axhline(threshold, color="k", linewidth=0.8)
    ax.text(ax.get_xlim()[0], threshold * 1.1, f" failure threshold |ΔE/E| = {threshold:g}; "
            "× = failed runs; dashed = measured limit", fontsize=7, va="bottom")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("max |E − E₀|/|E₀| over the horizon")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    save(fig, path)


def _limits_chart(osc: dict, path: Path, cap: float) -> None:
    names = list(osc["methods"])
    fig, ax = figure(width=9, height=4.5)
    x = np.arange(len(names))

    def val(v):
        return cap if v is None else v

    measured = [val(osc["methods"][n]["measured_h_omega"]) for n in names]
    prop = [val(osc["methods"][n]["propagator_h_omega"]) for n in names]
    ax.bar(x - 0.2, measured, 0.4, label=f"measured ({osc['n_steps']} steps, |ΔE/E| > 10 or "
           "failure)", color="tab:blue")
    ax.bar(x + 0.2, prop, 0.4, label="linear theory: spectral radius of the one-step map > 1",
           color="tab:orange", alpha=0.7)
    for i, n in enumerate(names):
        th = osc["methods"][n]["theory_h_omega"]
        if isinstance(th, float):
            ax.plot([i - 0.45, i + 0.45], [th, th], color="k", linewidth=2)
        elif th is None:
            ax.text(i, cap * 1.05, "∞ (theory)", ha="center", fontsize=7)
    ax.plot([], [], color="k", linewidth=2, label="closed form (RK4 2√2, Verlet 2)")
    ax.set_yscale("log")
    ax.set_xticks(x, names, rotation=30, fontsize=8)
    ax.set_ylabel("stability limit h·ω")
    ax.set_title(f"Oscillator: stability limits, measured against theory (bars at {cap:g} = "
                 "no failure up to the scan's end)")
    ax.legend(fontsize=7)
    save(fig, path)


# -------------------------------------------------------------------------- summary


def write_summary(results: dict, out: Path) -> str:
    cfg, osc, car = results["config"], results["oscillator"], results["car_pendulum"]
    thr = cfg["energy_threshold"]
    lines = [
        f"Stability: the step is increased until the run fails. **Fails** = a Newton solve "
        f"does not converge, a state is not finite, or |E − E₀|/|E₀| > {thr:g} at any step, "
        f"over a fixed horizon: {osc['n_steps']} steps (oscillator, m = k = 1, q0 = 1, "
        f"p0 = 0) or {car['horizon']:g} s (car-pendulum, paper state). Geometric scan, then "
        f"bisection between the last stable and first failing step (relative bracket "
        f"{cfg['oscillator_rtol']:g} / {cfg['car_rtol']:g}). Every failure is reported with "
        "its reason.",
        "",
        "![oscillator](stability_oscillator.png) ![limits](stability_limits_oscillator.png)",
        "![car-pendulum](stability_car_pendulum.png)",
        "",
        "## Oscillator: measured limits against theory",
        "",
        "| method | order | measured h·ω (bracket) | closed-form theory | linear propagator "
        "| measured / limit (closed form, else propagator) | reason at the limit "
        "| spectral radius there "
        "| stable again above? |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in osc["methods"].items():
        th = r["theory_h_omega"]
        ref = th if isinstance(th, float) else r["propagator_h_omega"]
        m = r["measured_h_omega"]
        ratio = f"{m / ref:.5f}" if (m is not None and isinstance(ref, float)) else "—"
        br = r["bracket_h_omega"]
        bracket = "—" if br[1] is None else f"[{br[0]:.6g}, {br[1]:.6g}]"
        th_txt = "∞ (A-stable)" if th is None else _fmt(th, ".6g")
        lines.append(
            f"| {name} | {r['order']} | {_fmt(m, '.6g')} {bracket} | {th_txt} | "
            f"{_fmt(r['propagator_h_omega'], '.6g')} | {ratio} | "
            f"{(r['failure'] or {}).get('reason') or '—'} | "
            f"{_rho(r['spectral_radius_at_failure'])} | "
            f"{', '.join(format(h * osc['omega'], '.3g') for h in r['non_monotone']) or 'no'} |")
    lines += ["", f"## Car-pendulum: largest stable step over {car['horizon']:g} s", "",
              "| method | order | limit h [s] (bracket) | reason at the limit | step of failure "
              "| max \\|ΔE/E\\| just below | stable again above? |",
              "|---|---|---|---|---|---|---|"]
    for name, r in car["methods"].items():
        below = [p for p in r["scan"] + r["bisections"] if not p["failed"]
                 and (r["limit"] is None or p["h"] <= r["bracket"][0])]
        emax = max(below, key=lambda p: p["h"])["energy_error_max"] if below else None
        br = r["bracket"]
        bracket = "—" if br[1] is None or br[0] is None else f"[{br[0]:.4g}, {br[1]:.4g}]"
        fail = r["failure"] or {}
        lines.append(
            f"| {name} | {r['order']} | {_fmt(r['limit'])} {bracket} | "
            f"{fail.get('reason') or 'no failure up to h = ' + _fmt(br[0])} | "
            f"{fail.get('step') if fail else '—'} | {_fmt(emax, '.2e') if emax else '—'} | "
            f"{', '.join(f'{h:.3g}' for h in r['non_monotone']) or 'no'} |")
    for label, study in (("oscillator", osc), ("car-pendulum", car)):
        if study["skipped_methods"]:
            lines.append(f"\nNot available in this checkout ({label}): "
                         f"{', '.join(study['skipped_methods'])}.")
    lines += ["", "**Reading the numbers:**", ""]
    lines += verdicts(results)
    return write_summary_lines(out, lines)


def verdicts(results: dict) -> list[str]:
    """Sentences computed from the measured limits."""
    osc, car = results["oscillator"], results["car_pendulum"]
    out = []
    for name, th in THEORY.items():
        r = osc["methods"].get(name)
        if r is None:
            continue
        m = r["measured_h_omega"]
        if th is None:
            out.append(f"- {name}: theory says unconditionally stable; measured: "
                       + ("no failure up to h·ω = " + _fmt(r["bracket_h_omega"][0])
                          if m is None else f"fails at h·ω ≈ {m:.4g} "
                          f"({r['failure']['reason']})") + ".")
        else:
            out.append(f"- {name}: measured limit h·ω = {_fmt(m)} against {th:.6g} in theory"
                       + (f" (ratio {m / th:.6f}; bisection bracket "
                          f"[{r['bracket_h_omega'][0]:.7g}, {r['bracket_h_omega'][1]:.7g}]; "
                          "just past the limit the energy needs many of the "
                          f"{osc['n_steps']} steps to grow tenfold, so the failing end of the "
                          "bracket lies past the theoretical limit)" if m else "") + ".")
    for name, r in osc["methods"].items():
        if name in THEORY:
            continue
        m, p = r["measured_h_omega"], r["propagator_h_omega"]
        unstable = r["linearly_unstable_at_failure"]
        why = ("" if unstable is None else
               " — there the one-step map is linearly unstable" if unstable else
               " — there the one-step map is still stable (spectral radius 1): the run fails "
               "on a bounded energy excursion above the threshold, the eigenvalues being "
               "close to colliding")
        again = ", ".join(format(h * osc["omega"], ".3g") for h in r["non_monotone"])
        band = (f"; stable again at h·ω = {again} (instability bands, not a single boundary)"
                if again else "")
        out.append(f"- {name}: measured h·ω = {_fmt(m)}, the one-step map's spectral radius "
                   f"first exceeds 1 at h·ω = {_fmt(p)}"
                   + (f" (ratio {m / p:.4f})" if m and p else "") + why + band + ".")
    if car["methods"]:
        ranked = sorted(car["methods"].items(),
                        key=lambda kv: -(kv[1]["limit"] or np.inf))
        out.append("- car-pendulum, largest stable step: " + ", ".join(
            f"{n} {_fmt(r['limit'], '.3g')} s" for n, r in ranked) + ".")
    return out


# ------------------------------------------------------------------------------ run


def run(out_dir: Path | str, *, quick: bool = False, log: Callable = print) -> dict:
    """Run the study into ``out_dir``; returns the results dictionary."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cfg = config(quick)
    start = time.perf_counter()
    log("  oscillator ...")
    osc = oscillator_study(cfg, log)
    log("  car-pendulum ...")
    car = car_study(cfg, log)
    thr = cfg["energy_threshold"]
    _energy_chart(osc, osc["omega"], "h·ω", f"Oscillator: energy error against step "
                  f"({osc['n_steps']} steps)", thr, out / "stability_oscillator.png")
    _limits_chart(osc, out / "stability_limits_oscillator.png", cfg["oscillator_scan"][1])
    _energy_chart(car, 1.0, "h [s]", f"Car-pendulum (paper state): energy error against step "
                  f"({car['horizon']:g} s)", thr, out / "stability_car_pendulum.png")
    results = {
        "quick": quick, "config": cfg, "oscillator": osc, "car_pendulum": car,
        "wall_time_s": time.perf_counter() - start,
        "environment": environment(),
    }
    write_summary(results, out)
    mark_complete(out, _jsonable(results), indent=1)
    return results


def _jsonable(obj):
    """Plain JSON: non-finite floats (an infinite spectral radius) become None."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, np.integer)):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


if __name__ == "__main__":
    sys.exit(script_main(run, __doc__, quick_help="fewer methods, coarser scan"))
