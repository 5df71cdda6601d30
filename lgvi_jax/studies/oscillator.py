"""Paper section 1: the 1D harmonic oscillator with RK4, Gauss–Legendre and a Galerkin VI.

Reproduces figures 1–3 (position, momentum, energy error of RK4, the 2-stage Gauss–Legendre
method and the 4th-order Galerkin variational integrator), and adds a convergence-order plot
and a 10^5-step energy-error plot, a markdown summary with a verdict on each claim of the
paper, and ``results.json`` with every number.

The paper gives neither step nor horizon: figures 1–3 use ``h = 0.1`` on ``[0, 100]`` with
``H = p²/2 + q²/2``, ``q0 = 1``, ``p0 = 0``.

Run:  ``python -m lgvi_jax.studies.oscillator --out DIR [--quick]`` or ``lgvi-jax reproduce``.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
from matplotlib.ticker import NullFormatter

from lgvi_jax.diagnostics import (
    drift_ratio,
    environment,
    observed_order,
    relative_energy_error,
    rk4_energy_factor,
)
from lgvi_jax.integrators import EUCLIDEAN_METHODS
from lgvi_jax.models import HarmonicOscillator
from lgvi_jax.plotting import envelope, figure, positive, save, style_for
from lgvi_jax.simulate import final_state, simulate, simulate_timed
from lgvi_jax.studies import mark_complete, script_main, write_summary_lines

PAPER_METHODS = ("rk4", "gl4", "galerkin4")
ALL_METHODS = ("rk4", "gl4", "galerkin4", "verlet", "gl6", "galerkin6")
LABELS = {
    "rk4": "RK4",
    "gl4": "Gauss–Legendre (2 stages)",
    "gl6": "Gauss–Legendre (3 stages)",
    "galerkin4": "Galerkin VI (degree 2)",
    "galerkin6": "Galerkin VI (degree 3)",
    "verlet": "Störmer–Verlet",
    "exact": "exact",
}

#: Steps for the convergence study; the order is fitted on FIT_STEPS (down to 0.0125).
CONV_STEPS = (0.4, 0.2, 0.1, 0.05, 0.025, 0.0125)
FIT_STEPS = (0.1, 0.05, 0.025, 0.0125)
#: Errors below this are round-off dominated and left out of the fit (6th-order methods).
ROUNDOFF_FLOOR = 1e-11
#: The long run's energy error is drawn as its maximum over this many windows of time, each
#: at least LONG_RUN_MIN_PERIODS periods of the oscillator long (the error of a VI
#: oscillates twice per period: a shorter window would catch the oscillation, not its
#: envelope).
LONG_RUN_WINDOWS = 200
LONG_RUN_MIN_PERIODS = 4


def config(quick: bool) -> dict:
    return {
        "quick": quick,
        "model": {"m": 1.0, "k": 1.0, "q0": 1.0, "p0": 0.0},
        "figures_dt": 0.1,
        "figures_t_final": 100.0,
        "convergence_t": 10.0,
        "convergence_steps": list(CONV_STEPS),
        "fit_steps": list(FIT_STEPS),
        "long_dt": 0.1,
        "long_n_steps": 10**4 if quick else 10**5,
        "long_save_every": 10,
        "crossover_steps": [0.2, 0.1, 0.05],
        "crossover_t_final": 100.0 if quick else 400.0,
    }


def _state_error(model, state, t):
    exact = model.exact(model.default_state(), t)
    return float(np.hypot(state.q[0] - exact.q[0], state.p[0] - exact.p[0]))


def figures_1_to_3(model, cfg, out: Path) -> dict:
    h, T = cfg["figures_dt"], cfg["figures_t_final"]
    n = round(T / h)
    s0 = model.default_state()
    runs = {name: simulate(model, EUCLIDEAN_METHODS[name](), s0, h, n) for name in PAPER_METHODS}
    t = np.asarray(runs["rk4"].t)
    exact = model.exact(s0, t)
    stats = {}
    for key, fname, ylabel in (("q", "fig1_position.png", "position q"),
                               ("p", "fig2_momentum.png", "momentum p")):
        fig, (ax, axe) = figure(2, 1, width=8, height=3.0, sharex=True)
        ref = np.asarray(getattr(exact, key))[:, 0]
        ax.plot(t, ref, label="exact", **style_for("exact"))
        for name, tr in runs.items():
            values = np.asarray(getattr(tr.state, key))[:, 0]
            ax.plot(t, values, label=LABELS[name], **style_for(name), linewidth=0.9)
            axe.semilogy(t[1:], positive(values - ref)[1:], label=LABELS[name],
                         **style_for(name), linewidth=0.9)  # t = 0: exact, error 0
        ax.set_ylabel(ylabel)
        ax.set_title(f"Harmonic oscillator, h = {h:g}: {ylabel} (paper fig. {fname[3]})")
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.04), ncol=4, fontsize=8,
                  frameon=False)
        axe.set_ylabel(f"|{key} − {key}_exact|")
        axe.set_xlabel("t")
        save(fig, out / fname)
    fig, (ax1, ax2) = figure(2, 1, width=8, height=3.0)
    for name, tr in runs.items():
        energy = np.asarray(tr.energy)
        signed = (energy - energy[0]) / energy[0]
        ax1.plot(t, signed, label=LABELS[name], **style_for(name))
        ax2.semilogy(t, positive(signed), label=LABELS[name], **style_for(name), linewidth=0.8)
        stats[name] = {
            "max_position_error": float(np.max(np.abs(tr.state.q[:, 0] - exact.q[:, 0]))),
            "max_momentum_error": float(np.max(np.abs(tr.state.p[:, 0] - exact.p[:, 0]))),
            "max_energy_error": float(np.max(np.abs(signed))),
        }
    ax1.set_ylabel("(H − H₀)/H₀")
    ax1.set_title(f"Energy error, h = {h:g} (paper fig. 3)")
    ax1.legend(fontsize=8)
    ax2.set_ylabel("|H − H₀|/H₀")
    ax2.set_xlabel("t")
    save(fig, out / "fig3_energy_error.png")
    return stats


def convergence(model, cfg, out: Path) -> dict:
    s0 = model.default_state()
    T = cfg["convergence_t"]
    res = {}
    fig, ax = figure(width=6.5, height=4.8)
    for name in ALL_METHODS:
        method = EUCLIDEAN_METHODS[name]()
        errors = []
        for h in CONV_STEPS:
            state, code = final_state(model, method, s0, h, round(T / h))
            errors.append(_state_error(model, state, T) if int(code) == 0 else float("nan"))
        errors = np.asarray(errors)
        fit = [(h, e) for h, e in zip(CONV_STEPS, errors, strict=True)
               if h in FIT_STEPS and e > ROUNDOFF_FLOOR]
        if len(fit) < 2:  # very high order: fit the larger steps still above round-off
            fit = [(h, e) for h, e in zip(CONV_STEPS, errors, strict=True) if e > ROUNDOFF_FLOOR]
        order = observed_order(*zip(*fit, strict=True))
        res[name] = {
            "declared_order": method.order,
            "observed_order": order,
            "steps": list(CONV_STEPS),
            "errors": errors.tolist(),
            "fit_steps": [h for h, _ in fit],
        }
        ax.loglog(CONV_STEPS, positive(errors), marker="o", markersize=4,
                  label=f"{LABELS[name]}: slope {order:.2f}", **style_for(name))
    ax.set_xlabel("step h")
    ax.set_xticks(CONV_STEPS, [f"{h:g}" for h in CONV_STEPS])
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_ylabel(f"phase-space error at t = {T:g}")
    ax.set_title("Convergence on the harmonic oscillator")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    save(fig, out / "convergence.png")
    return res


def long_run(model, cfg, out: Path, log: Callable) -> dict:
    h, n, every = cfg["long_dt"], cfg["long_n_steps"], cfg["long_save_every"]
    s0 = model.default_state()
    res = {}
    fig, ax = figure(width=9, height=4.2)
    for name in ALL_METHODS:
        traj, timing = simulate_timed(model, EUCLIDEAN_METHODS[name](), s0, h, n, save_every=every)
        t = np.asarray(traj.t)
        err = relative_energy_error(traj.energy)
        res[name] = {
            "max_energy_error": float(np.max(err)),
            "final_energy_error": float(err[-1]),
            "drift_ratio_last_over_first_tenth": drift_ratio(err, 0.1),
            "steps_per_second": timing["steps_per_second"],
            "compile_s": timing["compile_s"],
            "run_s": timing["run_s"],
            "newton_iterations_mean": float(traj.newton_mean),
            "result": int(traj.result),
        }
        tw, top = envelope(t, err, LONG_RUN_WINDOWS,
                           min_span=LONG_RUN_MIN_PERIODS * 2 * np.pi / float(model.omega))
        ax.semilogy(tw, positive(top), label=LABELS[name], drawstyle="steps-mid",
                    **style_for(name))
        log(f"    long run {name}: max |dE/E| {res[name]['max_energy_error']:.3e}, "
            f"{timing['steps_per_second']:.3g} steps/s")
    omega_h = float(model.omega) * h
    predicted = 1.0 - rk4_energy_factor(omega_h, n)
    res["rk4"]["predicted_final_energy_error"] = predicted
    res["rk4"]["measured_over_predicted"] = res["rk4"]["final_energy_error"] / predicted
    steps = np.arange(0, n + 1, every)
    ax.semilogy(steps * h, positive([1.0 - rk4_energy_factor(omega_h, int(k)) for k in steps]),
                color="black", linestyle="--", linewidth=1.5, zorder=0,
                label="RK4 secular drift, predicted:\n1 − |R(iωh)|^(2n)")
    span = (t[-1] - t[0]) / len(tw)
    ax.set_xlabel("t")
    ax.set_ylabel("max |H − H₀|/H₀ per window")
    ax.set_title(f"Energy error over {n:.0e} steps, h = {h:g}: its maximum over windows of "
                 f"t = {span:.3g} ({round(span / h)} steps).\nFlat: bounded, no drift; "
                 "rising: drift", fontsize=10)
    ax.set_xlim(t[0], t[-1])
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    save(fig, out / "long_run_energy.png")
    return res


def crossover(model, cfg) -> dict:
    """When does RK4's drifting energy error overtake the Galerkin VI's bounded one?"""
    s0 = model.default_state()
    T = cfg["crossover_t_final"]
    res = {}
    for h in cfg["crossover_steps"]:
        n = round(T / h)
        e_rk = relative_energy_error(simulate(model, EUCLIDEAN_METHODS["rk4"](), s0, h, n).energy)
        tr = simulate(model, EUCLIDEAN_METHODS["galerkin4"](), s0, h, n)
        e_gal = relative_energy_error(tr.energy)
        amplitude = float(np.max(e_gal))
        over = np.nonzero(e_rk > amplitude)[0]
        res[str(h)] = {
            "galerkin_amplitude": amplitude,
            "rk4_error_at_end": float(e_rk[-1]),
            "crossover_time": float(over[0] * h) if over.size else None,
        }
    return res


def _fmt(x: float) -> str:
    return f"{x:.2e}"


def write_summary(results: dict, out: Path) -> str:
    figs, conv, long = results["figures"], results["convergence"], results["long_run"]
    cfg = results["config"]
    lines = [
        "Harmonic oscillator `H = p²/2 + q²/2`, `q0 = 1, p0 = 0` (paper §1, figures 1–3). "
        f"Figures 1–3: h = {cfg['figures_dt']}, t ∈ [0, {cfg['figures_t_final']:g}]. "
        f"Long run: h = {cfg['long_dt']}, {cfg['long_n_steps']} steps. "
        f"Orders: phase-space error at t = {cfg['convergence_t']:g}, least-squares slope over "
        f"h = {', '.join(map(str, cfg['fit_steps']))} (6th-order methods: the steps whose "
        f"error is above {ROUNDOFF_FLOOR:g}, since below it round-off dominates).",
        "",
        "![position](fig1_position.png) ![momentum](fig2_momentum.png)",
        "![energy error](fig3_energy_error.png)",
        "![convergence](convergence.png) ![long run](long_run_energy.png)",
        "",
        "| method | order (declared) | order (observed) | max \\|ΔH/H\\| long run "
        "| final \\|ΔH/H\\| | drift ratio (last/first tenth) | steps/s | Newton its/step |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name in ALL_METHODS:
        c, r = conv[name], long[name]
        lines.append(
            f"| {name} | {c['declared_order']} | {c['observed_order']:.3f} | "
            f"{_fmt(r['max_energy_error'])} | {_fmt(r['final_energy_error'])} | "
            f"{r['drift_ratio_last_over_first_tenth']:.2f} | {r['steps_per_second']:.3g} | "
            f"{r['newton_iterations_mean']:.2f} |"
        )
    rk = long["rk4"]
    agree = max(figs[m]["max_position_error"] for m in PAPER_METHODS)
    bounded_ok = (long["galerkin4"]["drift_ratio_last_over_first_tenth"] < 1.5
                  and long["gl4"]["max_energy_error"] < 1e-10)
    cross = results["crossover"]
    cross_txt = "; ".join(
        f"h = {h}: Galerkin amplitude {_fmt(v['galerkin_amplitude'])}, RK4 passes it at "
        + (f"t ≈ {v['crossover_time']:.3g}" if v["crossover_time"] is not None
           else f"no time ≤ {cfg['crossover_t_final']:g}")
        for h, v in cross.items()
    )
    lines += [
        "",
        "**The paper's claims, measured:**",
        "",
        f"1. *RK4, Gauss–Legendre and the Galerkin VI agree in position and momentum* — "
        f"**confirmed**: on [0, {cfg['figures_t_final']:g}] the largest position error against "
        f"the exact solution is {_fmt(agree)} "
        f"(rk4 {_fmt(figs['rk4']['max_position_error'])}, "
        f"gl4 {_fmt(figs['gl4']['max_position_error'])}, "
        f"galerkin4 {_fmt(figs['galerkin4']['max_position_error'])}).",
        f"2. *The symplectic RK and the Galerkin VI keep the energy error bounded while RK4's "
        f"drifts* — **{'confirmed' if bounded_ok else 'NOT confirmed'}**: over "
        f"{cfg['long_n_steps']} steps Gauss–Legendre conserves H to "
        f"{_fmt(long['gl4']['max_energy_error'])} (round-off: it preserves quadratic "
        f"invariants exactly), the Galerkin VI's error stays below "
        f"{_fmt(long['galerkin4']['max_energy_error'])} (drift ratio "
        f"{long['galerkin4']['drift_ratio_last_over_first_tenth']:.2f}), while RK4 loses "
        f"{_fmt(rk['final_energy_error'])} of the energy — exactly its stability polynomial's "
        f"prediction 1 − |R(iωh)|^(2n) = {_fmt(rk['predicted_final_energy_error'])} "
        f"(ratio {rk['measured_over_predicted']:.9f}).",
        f"3. *The Galerkin VI's energy fluctuates less than RK4's* — **true only past a "
        f"crossover time that grows as h shrinks**: the Galerkin VI's error oscillates with a "
        f"fixed O(h⁴) amplitude while RK4's grows like t·h⁵/72, so for short runs RK4 is "
        f"closer in energy. {cross_txt}.",
    ]
    return write_summary_lines(out, lines)


def run(out_dir: Path | str, *, quick: bool = False, log: Callable = print) -> dict:
    """Run the whole study into ``out_dir``; returns the results dictionary."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cfg = config(quick)
    model = HarmonicOscillator(m=1.0, k=1.0)  # its default state: q0 = 1, p0 = 0
    log("  figures 1-3 ...")
    figs = figures_1_to_3(model, cfg, out)
    log("  convergence orders ...")
    conv = convergence(model, cfg, out)
    log(f"  long run ({cfg['long_n_steps']} steps per method) ...")
    long = long_run(model, cfg, out, log)
    log("  RK4 / Galerkin energy crossover ...")
    cross = crossover(model, cfg)
    results = {
        "quick": quick,
        "config": cfg,
        "figures": figs,
        "convergence": conv,
        "long_run": long,
        "crossover": cross,
        "environment": environment(),
    }
    write_summary(results, out)
    mark_complete(out, results)
    return results


if __name__ == "__main__":
    sys.exit(script_main(run, __doc__, quick_help="shorter long run"))
