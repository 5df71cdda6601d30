"""The report of the work-precision study: the charts, ``summary.md`` (winners per regime,
advice computed from them, every method in every regime) and what ``results.json`` needs
(the environment, JSON-safe values).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lgvi_jax import diagnostics
from lgvi_jax.plotting import figure, method_style, positive, save
from lgvi_jax.studies import write_summary_lines

from . import runners
from .metrics import _label

# --------------------------------------------------------------------------- charts


def _peer_style(method: str) -> dict:
    styles = {"diffrax tsit5": ("tab:gray", "-"), "diffrax dopri8": ("black", "-"),
              "diffrax tsit5 fixed": ("tab:gray", ":"), "diffrax dopri8 fixed": ("black", ":"),
              "scipy DOP853": ("tab:pink", "--"), "scipy RK45": ("tab:pink", ":")}
    if method in styles:
        c, ls = styles[method]
        return {"color": c, "linestyle": ls}
    return method_style(method)


_MARKERS = {"ours": "o", "diffrax": "s", "scipy": "^"}


def _wp_axis(ax, runs, ykey, title, floor=None):
    by_method: dict[str, list] = {}
    for r in runs:
        if r["failed"] or r.get(ykey) is None:
            continue
        by_method.setdefault(r["method"], []).append(r)
    for name, rs in by_method.items():
        rs = sorted(rs, key=lambda r: r["wall_s"])
        ax.loglog([r["wall_s"] for r in rs], positive([r[ykey] for r in rs]),
                  marker=_MARKERS[rs[0]["family"]], markersize=3.5, linewidth=1.0,
                  label=name, **_peer_style(name))
    if floor:
        ax.axhline(floor, color="k", linewidth=0.6, alpha=0.5)
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("wall time [s] (after compilation)")
    ax.grid(True, which="both", alpha=0.3)


def what_each_side_computes(cfg: dict) -> str:
    """The charts' caption: every side computes the same output, timed the same way."""
    saves = ", ".join(f"{n + 1} at T = {T} s" for T, n in cfg["saves"].items() if T != "long")
    return ("Same work on every side: the state at the same equally spaced save times "
            f"({saves}), nothing else (no per-step diagnostics).\nOurs: a fixed-step rollout "
            "saving every N steps (lgvi_jax.rollout); diffrax: SaveAt(ts) at those times; "
            "SciPy: dense output at those times. Wall time: the best of up to "
            f"{cfg['repeats']} runs after compilation, in one process.")


def charts(results: dict, cfg: dict, out: Path) -> list[str]:
    files = []
    systems = results["systems"]
    for key, res in systems.items():
        runs = res["runs"]
        horizons = cfg["horizons"]
        fig, axes = figure(1, len(horizons) + 1, width=5.2 * (len(horizons) + 1), height=4.4)
        axes = np.atleast_1d(axes)
        for ax, T in zip(axes, horizons, strict=False):
            # the reference's estimated error (at t = 50 s) as a guide line
            _wp_axis(ax, [r for r in runs if r["horizon"] == T], f"position_error_t{T:g}",
                     f"{res['title']}: position error at t = {T:g} s",
                     res.get("reference_uncertainty") if T == 50.0 else None)
            ax.set_ylabel("position error [m]" if "car" in key else "|q − q_exact|")
        T = horizons[-1]
        _wp_axis(axes[-1], [r for r in runs if r["horizon"] == T], "energy_error_max",
                 f"{res['title']}: max |ΔE/E| over [0, {T:g}] s")
        axes[-1].set_ylabel("max relative energy error")
        axes[-1].legend(fontsize=6, loc="center left", bbox_to_anchor=(1.01, 0.5))
        fig.suptitle(what_each_side_computes(cfg), fontsize=7)
        name = f"work_precision_{key}.png"
        save(fig, out / name)
        files.append(name)
    long = results.get("long_all", {})
    if long:
        fig, axes = figure(1, len(long), width=6 * len(long), height=4.4)
        axes = np.atleast_1d(axes)
        for ax, (key, runs) in zip(axes, long.items(), strict=True):
            _wp_axis(ax, runs, "energy_error_max",
                     f"{systems[key]['title'] if key in systems else key}: max |ΔE/E| over "
                     f"[0, {cfg['long_horizon']:g}] s")
            ax.set_ylabel("max relative energy error")
            ax.legend(fontsize=6)
        save(fig, out / "energy_vs_time.png")
        files.append("energy_vs_time.png")
    lr = results.get("long")
    if lr:
        panels = [("energy", "|E − E₀|/|E₀|"), ("momentum", "|p − p₀| (max component)"),
                  ("angular_momentum_z", "|L_z − L_z0|"), ("orthogonality", "‖RᵀR − I‖_F")]
        panels = [p for p in panels if p[0] in lr["runs"][0]["series"]]
        fig, axes = figure(2, 2, width=13, height=4.0)
        for ax, (k, ylabel) in zip(np.ravel(axes), panels, strict=False):
            shown: set[str] = set()
            for r in sorted(lr["runs"], key=lambda r: r["value"]):
                # one run per method (its smallest step or tolerance): readable lines
                if r["failed"] or r["method"] in shown:
                    continue
                shown.add(r["method"])
                s = r["series"]
                ax.semilogy(s["t"][1:], positive(np.maximum.accumulate(s[k][1:])),
                            linewidth=1.0, label=_label(r), **_peer_style(r["method"]))
            ax.set_ylabel(f"max over [0, t] of {ylabel}", fontsize=8)
            ax.set_xlabel("t [s]")
            ax.grid(True, which="both", alpha=0.3)
        np.ravel(axes)[1].legend(fontsize=6, loc="center left", bbox_to_anchor=(1.01, 0.5))
        fig.suptitle(f"Invariant errors against time, {lr['title']}, "
                     f"{cfg['long_horizon']:g} s (saved every {cfg['long_horizon'] / 500:g} s)")
        save(fig, out / "invariants_long_run.png")
        files.append("invariants_long_run.png")
    return files


# --------------------------------------------------------------------------- summary


def _f(x, fmt=".3g") -> str:
    return "—" if x is None else format(x, fmt)


def recommendations(regs: list[dict]) -> list[str]:
    """Plain-language advice, each sentence computed from a regime's numbers."""
    lines = []
    for g in regs:
        w = g.get("winner")
        if w is None:
            lines.append(f"- **{g['regime']}**: no method met the target in the measured "
                         "range.")
            continue
        m = g["metric"]
        unit = {"wall_s": " s", "trajectories_per_s": " trajectories/s",
                "invariant_error": ""}[m]
        ours, peer = g.get("best_ours"), g.get("best_peer")
        txt = f"- **{g['regime']}**: choose **{w['label']}** ({_f(w[m])}{unit})"
        ratio = g.get("peer_over_ours")
        worse = {"wall_s": "slower", "trajectories_per_s": "lower in throughput",
                 "invariant_error": "larger in invariant error"}[m]
        if ours and peer and ratio is not None:
            if w["family"] == "ours":
                txt += f"; the best peer, {peer['label']}, is {ratio:.3g}× {worse}"
            else:
                txt += (f"; **our methods lose here**: our best, {ours['label']}, is "
                        f"{1 / ratio:.3g}× {worse}")
        elif not ours:
            txt += "; none of our methods met the target in the measured range"
        elif not peer:
            txt += "; no peer met the target in the measured range"
        lines.append(txt + ".")
    return lines


def method_table(results: dict) -> list[str]:
    """Per method: best wall time to each regime's target (the numbers behind the advice)."""
    regs = results["regimes"]
    names: list[str] = []
    for g in regs:
        for r in g["ranking"]:
            if r["method"] not in names:
                names.append(r["method"])
    head = "| method | " + " | ".join(g["regime"] for g in regs) + " |"
    lines = [head, "|---|" + "---|" * len(regs)]
    for n in names:
        cells = []
        for g in regs:
            hit = [(i, r) for i, r in enumerate(g["ranking"]) if r["method"] == n]
            if hit:
                i, r = hit[0]
                cells.append(f"{_f(r[g['metric']])} (#{i + 1})")
            else:
                cells.append("—")
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    return lines


def write_summary(results: dict, out: Path) -> str:
    regs = results["regimes"]
    env = results["environment"]
    lines = [
        "Work-precision: every method of ours against diffrax and SciPy, all timed in this "
        f"run after compilation on {env['cpu_count']} CPU cores ({env['date']}, jax "
        f"{env['jax']}, diffrax {env['diffrax'] or 'not installed'}).",
        "",
    ]
    if runners.diffrax is None:
        lines += ["**diffrax is not installed: its runs were skipped** (install the `bench` "
                  "extra).", ""]
    lines += [
        "Ours: fixed steps. diffrax: `Tsit5`/`Dopri8` on `model.vector_field` (the library's "
        "equations, R as 9 numbers), adaptive `PIDController(rtol = atol)` or fixed step. "
        "SciPy: `solve_ivp` on the hand-derived NumPy equations "
        "(`HandReference.rhs`), `rtol = atol`, `t_eval` at the save times. Position error: "
        "pendulum mass centre against `HandReference` (DOP853, rtol = atol = 1e-13) or the "
        "exact oscillator solution. Energy and momentum-map errors: max over the saved "
        "states (every T/500; every 0.1 s at t ≤ 50 s). At the long horizon only "
        "invariants are compared: no reference can be trusted for the position there.",
        "",
    ]
    for res in results["systems"].values():
        if res.get("reference_uncertainty") is not None:
            lines.append(f"- {res['title']}: reference uncertainty at t = 50 s (1e-13 vs "
                         f"1e-12 solve) {res['reference_uncertainty']:.1e} m; errors near "
                         "it are not resolved.")
        if res["skipped_methods"]:
            lines.append(f"- {res['title']}: methods not available in this checkout: "
                         f"{', '.join(res['skipped_methods'])}.")
    osc = [r for k, res in results["systems"].items() if not k.startswith("car")
           for r in res["runs"] if not r["failed"]]
    if osc:
        lines.append(f"- oscillator: the fastest run took {min(r['wall_s'] for r in osc):.2g} s;"
                     " runs this short measure call overhead (dispatch of a compiled function,"
                     " SciPy's per-step Python) more than arithmetic.")
    if results.get("scipy_long_note"):
        lines.append(f"- {results['scipy_long_note']}")
    lines += ["", "![work-precision](work_precision_car-paper.png)", ""]
    lines += ["## Winners per regime", "",
              "| regime | winner | best of ours | best peer | peer / ours "
              "| best variational of ours | peer / variational |",
              "|---|---|---|---|---|---|---|"]
    def cell(row, m, missing="—"):
        if not row:
            return missing
        extra = f" in {_f(row['wall_s'])} s" if m == "invariant_error" else ""
        return f"{row['label']}: {_f(row[m])}{extra}"

    def ratio_cell(g, ours="best_ours", key="peer_over_ours"):
        if g.get(ours) and not g.get("best_peer"):
            return "∞ (no peer meets it)"
        return _f(g.get(key))

    for g in regs:
        m = g["metric"]
        lines.append(f"| {g['regime']} | {cell(g.get('winner'), m)} | "
                     f"{cell(g.get('best_ours'), m)} | "
                     f"{cell(g.get('best_peer'), m, 'none meets the target')} | "
                     f"{ratio_cell(g)} | {cell(g.get('best_variational'), m)} | "
                     f"{ratio_cell(g, 'best_variational', 'peer_over_variational')} |")
    lines += ["", "Metric: wall time [s] to the target (lower is better), except *invariants* "
              "(worst invariant error) and *batch* (trajectories/s, higher is better); "
              "*peer / ours* > 1 means ours is better by that factor.", "",
              "## When to choose each method (from these measurements)", ""]
    lines += recommendations(regs)
    lines += ["", "## Every method in every regime (value, rank)", ""]
    lines += method_table(results)
    lines += ["", "Charts: " + ", ".join(f"`{f}`" for f in results["files"]), ""]
    return write_summary_lines(out, lines)


# ---------------------------------------------------------------------- results.json


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def _strip(runs: list[dict], keep_series: bool = False) -> list[dict]:
    return [{k: v for k, v in r.items() if keep_series or k != "series"} for r in runs]


def environment() -> dict:
    diffrax = runners.diffrax
    return diagnostics.environment(
        diffrax=getattr(diffrax, "__version__", None) if diffrax is not None else None,
        scipy=__import__("scipy").__version__)
