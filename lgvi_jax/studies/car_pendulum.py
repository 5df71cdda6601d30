"""Paper section 3: the 3D car-pendulum with the general LGVI and the Hamel VI.

Reproduces figures 5–11 (cart and pendulum mass-centre trajectories, their components
against time, energy, energy error, orthogonality error ‖RᵀR − I‖_F) for the paper's two
methods — ``lgvi`` (the general-form LGVI) and ``hamel`` (the paper's Hamel VI) — with
``hamel-cayley``, ``hamel-exact`` and RK4 beside them, and adds:

* the momentum maps (cart momentum ``p``, vertical angular momentum ``L_z``) against time;
* a step-size sweep (h = 0.02 … 0.0025 over 5 s, from a state with non-zero cart momentum):
  state error against a reference, energy error, momentum-map errors, run time; error
  against h with fitted slopes, and error against run time (work–precision);
* a long run (10^6 steps of h = 5e-3 per VI method; 10^4 in quick mode) for the
  energy-drift claim, drawn as the maximum energy error over windows of time (a flat
  band: bounded, no drift);
* a 3D view of the motion from the saved states of the paper run (cart, rod, mass centre,
  body axes): ``motion_snapshots.png`` (2x4 snapshots) and ``motion.gif``; in a notebook,
  :func:`motion_animation`;
* ``summary.md`` with a table and a verdict on each claim of the paper, computed from the
  numbers, and ``results.json`` (written last).

Choices the paper leaves open: g = 9.81; the orthogonality error is the Frobenius norm;
Newton stops when the update is below 1e-12 (absolute + relative); the sweep's reference is
RK4 with a step 16 times smaller than the smallest swept step (its agreement with an
independent, hand-derived reference integrated by DOP853 at 1e-13 is checked in
``tests/test_reference.py``).

Run:  ``python -m lgvi_jax.studies.car_pendulum --out DIR [--quick]`` or ``lgvi-jax reproduce``.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from lgvi_jax import so3
from lgvi_jax.diagnostics import drift_ratio, environment, observed_order
from lgvi_jax.integrators import RIGID_METHODS, resolve_method
from lgvi_jax.models import CarPendulum, RigidState
from lgvi_jax.plotting import envelope, figure, positive, save, style_for
from lgvi_jax.simulate import simulate_timed
from lgvi_jax.studies import mark_complete, script_main, write_summary_lines

PAPER_METHODS = ("lgvi", "hamel")
METHODS = ("lgvi", "hamel", "hamel-cayley", "hamel-exact", "rk4")
VI_METHODS = ("lgvi", "hamel", "hamel-cayley", "hamel-exact")
#: Beyond the paper, in the 50 s table only: symmetric compositions of lgvi (orders 4, 6, 8)
#: and the explicit Lie-group RK4 (their convergence is in the work-precision stage).
EXTRA_METHODS = ("lgvi@4", "lgvi@6", "lgvi@8", "rkmk4")
LABELS = {
    "lgvi": "general LGVI (lgvi)",
    "hamel": "Hamel VI, paper (hamel)",
    "hamel-cayley": "Hamel VI, Cayley (hamel-cayley)",
    "hamel-exact": "Hamel VI, exact variations (hamel-exact)",
    "rk4": "RK4 (R as 9 numbers)",
    "reference": "reference",
}
SWEEP_STEPS = (0.02, 0.01, 0.005, 0.0025)
SWEEP_SEGMENTS = 10  # divides T/h for every swept step
#: The long run's energy error is drawn as its maximum over this many windows of time, each
#: at least LONG_RUN_MIN_WINDOW_S long (the error oscillates with the swings, ~1 s, and is
#: modulated over ~7 s: a shorter window would catch the oscillation, not its envelope).
LONG_RUN_WINDOWS = 100
LONG_RUN_MIN_WINDOW_S = 5.0


def config(quick: bool) -> dict:
    return {
        "quick": quick,
        "g": 9.81,
        "paper_dt": 5e-3,
        "paper_t_final": 50.0,
        "paper_save_every": 10,
        "sweep_steps": list(SWEEP_STEPS),
        "sweep_t_final": 5.0,
        "sweep_state": {"q0": [0.7, -0.4], "v0": [0.8, -0.3], "omega0": [1.0, -0.5, 3.0],
                        "R0_rotation_vector": [0.6, -0.9, 0.4]},
        "reference_dt": SWEEP_STEPS[-1] / 16,
        "long_dt": 5e-3,
        # Quick mode: the long run is the 50 s paper run itself (no extra compilation).
        "long_n_steps": 10**4 if quick else 10**6,
        "long_save_every": 10 if quick else 1000,
        "newton_tolerance": 1e-12,
        # Quick mode (tests): the paper's methods only, to keep compilations few.
        "extra_methods": [] if quick else list(EXTRA_METHODS),
        # The 3D view of the motion, drawn from the saved states of this method's paper run.
        "motion_method": "lgvi",
        "motion_snapshots_t": 2.0,  # 2x4 snapshots over [0, 2] s (about one swing)
        "motion_gif_t": 6.0,
        "motion_gif_fps": 10,
    }


def _max_dev(x: np.ndarray) -> float:
    x = np.asarray(x, dtype=np.float64)
    dev = np.abs(x - x[:1]).reshape(len(x), -1)
    return float(np.max(dev))


# ------------------------------------------------------------------ paper figures


def paper_runs(model, cfg, log) -> tuple[dict, dict]:
    h, T, every = cfg["paper_dt"], cfg["paper_t_final"], cfg["paper_save_every"]
    n = round(T / h)
    s0 = model.default_state()
    runs, table = {}, {}
    for name in (*METHODS, *cfg["extra_methods"]):
        method = resolve_method(name, RIGID_METHODS)
        traj, timing = simulate_timed(model, method, s0, h, n, save_every=every)
        runs[name] = (traj, timing)
        inv = {k: np.asarray(v) for k, v in traj.invariants.items()}
        E = inv["energy"]
        table[name] = {
            "result": int(traj.result),
            "message": traj.message,
            "max_energy_error": float(np.max(np.abs(E - E[0]))),
            "max_relative_energy_error": float(np.max(np.abs(E - E[0])) / abs(E[0])),
            "max_momentum_error": _max_dev(inv["momentum"]),
            "max_angular_momentum_z_error": _max_dev(inv["angular_momentum_z"]),
            "max_orthogonality_error": float(np.max(so3.orthogonality_error(traj.state.R))),
            "newton_mean": float(traj.newton_mean),
            "newton_max": int(traj.newton_max),
            "steps_per_second": timing["steps_per_second"],
            "compile_s": timing["compile_s"],
        }
        log(f"    {name}: max |ΔH| {table[name]['max_energy_error']:.3e}, "
            f"{timing['steps_per_second']:.3g} steps/s")
    return runs, table


def paper_figures(model, runs: dict, cfg, out: Path) -> None:
    h = cfg["paper_dt"]
    centres = {name: np.asarray(jax.vmap(model.pendulum_centre)(traj.state))
               for name, traj in runs.items()}
    carts = {name: np.asarray(traj.state.q) for name, traj in runs.items()}
    t = np.asarray(runs["lgvi"].t)
    title = f"h = {h:g} s"

    fig, ax = figure(width=6, height=5)
    for name in PAPER_METHODS:
        ax.plot(carts[name][:, 0], carts[name][:, 1], label=LABELS[name], **style_for(name))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"Cart mass-centre trajectory, {title} (paper fig. 5)")
    ax.legend(fontsize=8)
    save(fig, out / "fig5_cart_trajectory.png")

    fig, axes = figure(1, 2, width=11, height=5)
    for name in PAPER_METHODS:
        c = centres[name]
        axes[0].plot(c[:, 0], c[:, 1], label=LABELS[name], linewidth=0.6, **style_for(name))
        axes[1].plot(c[:, 0], c[:, 2], label=LABELS[name], linewidth=0.6, **style_for(name))
    axes[0].set_xlabel("x [m]")
    axes[0].set_ylabel("y [m]")
    axes[1].set_xlabel("x [m]")
    axes[1].set_ylabel("z [m] (down)")
    axes[1].invert_yaxis()
    fig.suptitle(f"Pendulum mass-centre trajectory, {title} (paper fig. 6)")
    axes[0].legend(fontsize=8)
    save(fig, out / "fig6_pendulum_trajectory.png")

    for fname, data, comps, fig_no, what in (
        ("fig7_cart_components.png", carts, ("x", "y"), 7, "Cart mass centre"),
        ("fig8_pendulum_components.png", centres, ("x", "y", "z"), 8, "Pendulum mass centre"),
    ):
        fig, axes = figure(len(comps), 1, width=9, height=2.2, sharex=True)
        for i, comp in enumerate(comps):
            for name in PAPER_METHODS:
                axes[i].plot(t, data[name][:, i], label=LABELS[name], linewidth=0.8,
                             **style_for(name))
            axes[i].set_ylabel(f"{comp} [m]")
        axes[0].set_title(f"{what} against time, {title} (paper fig. {fig_no})")
        axes[0].legend(fontsize=8, loc="upper right")
        axes[-1].set_xlabel("t [s]")
        save(fig, out / fname)

    fig, ax = figure(width=9, height=3.6)
    for name in PAPER_METHODS:
        ax.plot(t, np.asarray(runs[name].energy), label=LABELS[name], linewidth=0.8,
                **style_for(name))
    ax.set_xlabel("t [s]")
    ax.set_ylabel("H [J]")
    ax.set_title(f"Energy, {title} (paper fig. 9)")
    ax.legend(fontsize=8)
    save(fig, out / "fig9_energy.png")

    fig, (ax1, ax2) = figure(2, 1, width=9, height=3.0, sharex=True)
    for name in (*PAPER_METHODS, "hamel-exact", "rk4"):
        E = np.asarray(runs[name].energy)
        kw = style_for(name)
        if name in PAPER_METHODS:
            ax1.plot(t, E - E[0], label=LABELS[name], linewidth=0.7, **kw)
        ax2.semilogy(t[1:], positive(E[1:] - E[0]), label=LABELS[name], linewidth=0.6, **kw)
    ax1.set_ylabel("H − H₀ [J]")
    ax1.set_title(f"Energy error, {title} (paper fig. 10)")
    ax1.legend(fontsize=8)
    ax2.set_ylabel("|H − H₀| [J]")
    ax2.set_xlabel("t [s]")
    ax2.legend(fontsize=7, loc="lower right")
    save(fig, out / "fig10_energy_error.png")

    fig, ax = figure(width=9, height=3.8)
    for name in (*PAPER_METHODS, "rk4"):
        orth = np.asarray(so3.orthogonality_error(runs[name].state.R))
        ax.semilogy(t[1:], positive(orth[1:]), label=LABELS[name], linewidth=0.8,
                    **style_for(name))
    ax.set_xlabel("t [s]")
    ax.set_ylabel("‖RᵀR − I‖_F")
    ax.set_title(f"Orthogonality error, {title} (paper fig. 11)")
    ax.legend(fontsize=8)
    save(fig, out / "fig11_orthogonality_error.png")

    fig, (ax1, ax2) = figure(2, 1, width=9, height=3.0, sharex=True)
    for name in METHODS:
        inv = {k: np.asarray(v) for k, v in runs[name].invariants.items()}
        dp = np.max(np.abs(inv["momentum"] - inv["momentum"][0]), axis=1)
        dlz = np.abs(inv["angular_momentum_z"] - inv["angular_momentum_z"][0])
        ax1.semilogy(t[1:], positive(dp[1:]), label=LABELS[name], linewidth=0.7,
                     **style_for(name))
        ax2.semilogy(t[1:], positive(dlz[1:]), label=LABELS[name], linewidth=0.7,
                     **style_for(name))
    ax1.set_ylabel("max |p − p₀| (0 drawn at 1e-17)")
    ax1.set_title(f"Momentum maps, {title}: cart momentum and vertical angular momentum")
    ax2.set_ylabel("|L_z − L_z,0|")
    ax2.set_xlabel("t [s]")
    ax2.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 1.0))
    save(fig, out / "momentum_maps.png")


# ------------------------------------------------------------------ step-size sweep


@eqx.filter_jit
def _advance(model, method, state, h, n):
    """``n`` steps with a run-time ``n`` (one compilation per method), and the worst Newton
    result code met."""

    def body(_, carry):
        s, code = carry
        s, info = method.step(model, s, h)
        return s, jnp.maximum(code, info.result)

    return jax.lax.fori_loop(0, jnp.asarray(n, jnp.int32), body,
                             (state, jnp.asarray(0, jnp.int32)))


@eqx.filter_jit
def _invariants(model, state):
    return model.invariants(state)


def sweep_problem(cfg) -> tuple[CarPendulum, RigidState]:
    """``(model, state0)`` of the moving-cart sweep: the paper's parameters (with
    ``cfg["g"]``) from ``cfg["sweep_state"]``."""
    st = cfg["sweep_state"]
    model = CarPendulum(g=cfg["g"])
    return model, model.state(q0=st["q0"], v0=st["v0"], omega0=st["omega0"],
                              R0=so3.exp(jnp.asarray(st["R0_rotation_vector"])))


def _config_vector(model, state) -> np.ndarray:
    """Cart position and pendulum mass-centre position (5 numbers)."""
    return np.concatenate([np.asarray(state.q), np.asarray(model.pendulum_centre(state))])


def sweep(cfg, out: Path, log) -> dict:
    """The sweep from the paper's state and from a state with non-zero cart momentum."""
    paper = CarPendulum(g=cfg["g"])
    problems = {"paper state": (paper, paper.default_state()), "moving cart": sweep_problem(cfg)}
    res = {key: _sweep_one(model, s0, cfg, log) for key, (model, s0) in problems.items()}
    T = cfg["sweep_t_final"]
    fig, axes = figure(2, 3, width=15, height=4.2)
    for row, (key, rr) in enumerate(res.items()):
        for name in METHODS:
            r = rr[name]
            kw = {**style_for(name), "marker": "o", "markersize": 4}
            axes[row, 0].loglog(SWEEP_STEPS, positive(r["state_error"]), **kw,
                                label=f"{name}: slope {r['state_error_order']:.2f}")
            axes[row, 1].loglog(SWEEP_STEPS, positive(r["energy_error"]), **kw,
                                label=f"{name}: slope {r['energy_error_order']:.2f}")
            axes[row, 2].loglog(r["run_s"], positive(r["state_error"]), **kw, label=name)
        axes[row, 0].set_ylabel(f"position error at t = {T:g} s [m]")
        axes[row, 1].set_ylabel("max |H − H₀| [J]")
        axes[row, 2].set_ylabel(f"position error at t = {T:g} s [m]")
        axes[row, 0].set_title(f"{key}: accuracy against step")
        axes[row, 1].set_title(f"{key}: energy error against step")
        axes[row, 2].set_title(f"{key}: work–precision")
        for ax in axes[row, :2]:
            ax.set_xlabel("step h [s]")
        axes[row, 2].set_xlabel("run time [s] (after compilation)")
        for ax in axes[row]:
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7)
    save(fig, out / "step_sweep.png")
    return res


def _sweep_one(model, s0, cfg, log) -> dict:
    T = cfg["sweep_t_final"]
    h_ref = cfg["reference_dt"]
    ref_state, _ = _advance(model, RIGID_METHODS["rk4"](), s0, jnp.float64(h_ref),
                            jnp.int32(round(T / h_ref)))
    ref = _config_vector(model, ref_state)
    inv0 = {k: np.asarray(v) for k, v in _invariants(model, s0).items()}
    res = {}
    for name in METHODS:
        method = RIGID_METHODS[name]()
        _advance(model, method, s0, jnp.float64(SWEEP_STEPS[0]), jnp.int32(1))  # compile
        rows = {"state_error": [], "energy_error": [], "momentum_error": [],
                "angular_momentum_z_error": [], "run_s": [], "result": []}
        for h in SWEEP_STEPS:
            n = round(T / h)
            seg, rest = divmod(n, SWEEP_SEGMENTS)
            assert rest == 0, (h, n)
            state, e_max, p_max, lz_max, run_s, code = s0, 0.0, 0.0, 0.0, 0.0, 0
            for _ in range(SWEEP_SEGMENTS):
                start = time.perf_counter()
                state, c = jax.block_until_ready(
                    _advance(model, method, state, jnp.float64(h), jnp.int32(seg)))
                run_s += time.perf_counter() - start
                code = max(code, int(c))
                inv = {k: np.asarray(v) for k, v in _invariants(model, state).items()}
                e_max = max(e_max, abs(float(inv["energy"] - inv0["energy"])))
                p_max = max(p_max, float(np.max(np.abs(inv["momentum"] - inv0["momentum"]))))
                lz_max = max(lz_max, abs(float(inv["angular_momentum_z"]
                                               - inv0["angular_momentum_z"])))
            rows["state_error"].append(float(np.linalg.norm(_config_vector(model, state) - ref)))
            rows["energy_error"].append(e_max)
            rows["momentum_error"].append(p_max)
            rows["angular_momentum_z_error"].append(lz_max)
            rows["run_s"].append(run_s)
            rows["result"].append(code)
        for key in ("state_error", "energy_error"):
            vals = np.asarray(rows[key])
            rows[f"{key}_order"] = (observed_order(SWEEP_STEPS, vals)
                                    if np.all(np.isfinite(vals) & (vals > 0)) else None)
        lz = np.asarray(rows["angular_momentum_z_error"])
        rows["angular_momentum_z_error_order"] = (
            observed_order(SWEEP_STEPS, lz) if np.all(lz > 1e-11) else None)
        res[name] = rows
        log(f"    sweep {name}: state error {rows['state_error'][-1]:.2e} at h = "
            f"{SWEEP_STEPS[-1]}, order {rows['state_error_order']:.2f}")
    return res


# ---------------------------------------------------------------------- long run


def long_run(model, cfg, out: Path, log, paper: dict) -> dict:
    """``paper``: the 50 s runs with their timings, reused when the long run is the same."""
    h, n, every = cfg["long_dt"], cfg["long_n_steps"], cfg["long_save_every"]
    same = (h == cfg["paper_dt"] and every == cfg["paper_save_every"]
            and n == round(cfg["paper_t_final"] / cfg["paper_dt"]))
    s0 = model.default_state()
    res, levels = {}, []
    fig, ax = figure(width=9, height=4)
    for name in VI_METHODS:
        log(f"    long run {name}: {n} steps ...")
        if same:
            traj, timing = paper[name]
        else:
            traj, timing = simulate_timed(model, RIGID_METHODS[name](), s0, h, n,
                                          save_every=every)
        inv = {k: np.asarray(v) for k, v in traj.invariants.items()}
        err = np.abs(inv["energy"] - inv["energy"][0])
        k = max(1, round(0.1 * len(err)))
        res[name] = {
            "result": int(traj.result),
            "max_energy_error": float(np.max(err)),
            "max_energy_error_first_10pct": float(np.max(err[1 : k + 1])),
            "max_energy_error_last_10pct": float(np.max(err[-k:])),
            "drift_ratio": drift_ratio(err, 0.1),
            "max_momentum_error": _max_dev(inv["momentum"]),
            "max_angular_momentum_z_error": _max_dev(inv["angular_momentum_z"]),
            "orthogonality_error_final": float(so3.orthogonality_error(traj.state.R[-1])),
            "steps_per_second": timing["steps_per_second"],
            "newton_mean": float(traj.newton_mean),
        }
        t = np.asarray(traj.t)
        tw, top = envelope(t, err / abs(inv["energy"][0]), LONG_RUN_WINDOWS,
                           min_span=LONG_RUN_MIN_WINDOW_S)
        levels.append(positive(top))
        ax.semilogy(tw, positive(top), linewidth=1.2, drawstyle="steps-mid", **style_for(name),
                    label=f"{LABELS[name]}; last/first 10%: {res[name]['drift_ratio']:.2f}")
        log(f"    long run {name}: drift ratio {res[name]['drift_ratio']:.2f}, "
            f"{timing['steps_per_second']:.3g} steps/s")
    span = (t[-1] - t[0]) / len(tw)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("max |H − H₀|/|H₀| per window")
    ax.set_title(f"Energy error over {n:.0e} steps of h = {h:g} s: its maximum over windows "
                 f"of {span:.3g} s ({round(span / h)} steps;\nof the states saved every {every} "
                 "steps). Flat: bounded, no drift; a drift would rise to the right", fontsize=10)
    ax.set_xlim(t[0], t[-1])
    levels = np.concatenate(levels)
    levels = levels[np.isfinite(levels)]
    if levels.size:  # a decade either side: a drift would leave the band; room for the legend
        ax.set_ylim(levels.min() / 10, levels.max() * 30)
    ax.legend(fontsize=7, loc="upper right", ncol=2)
    save(fig, out / "long_run_energy.png")
    return res


# ------------------------------------------------------------------- 3D view of the motion

#: The cart's rectangle, drawn in the plane z = 0 centred on the cart, as fractions of
#: ``|ρ_c|`` (length along x, width along y). The model's cart is a point mass that
#: translates without turning: the rectangle's size is for the eye only.
CART_SIZE = (0.6, 0.4)
#: Length of the body axes drawn at the bob, as a fraction of ``|ρ_c|``.
BODY_AXIS_LENGTH = 0.25
_AXIS_COLOURS = ("tab:red", "tab:green", "tab:blue")


def motion_geometry(model: CarPendulum, R, q) -> dict[str, np.ndarray]:
    """Inertial coordinates (``e3`` down, as in the model) of what the 3D view draws, for
    attitudes ``R`` of shape ``(..., 3, 3)`` (body to inertial) and cart positions ``q`` of
    shape ``(..., 2)``:

    * ``pivot`` ``(..., 3)``: the hinge on the cart, ``(x, y, 0)``;
    * ``bob`` ``(..., 3)``: the pendulum's mass centre, ``pivot + R ρ_c`` (the rod is drawn
      from ``pivot`` to ``bob``, along the body vector ``ρ_c``; the same point as
      :meth:`CarPendulum.pendulum_centre`);
    * ``cart`` ``(..., 4, 3)``: the corners of the cart's rectangle in the plane ``z = 0``
      (:data:`CART_SIZE`; axis-aligned, since the cart only translates);
    * ``body_axes`` ``(..., 3, 3)``: row ``i`` is the tip ``bob + s R e_i`` of the body
      axis ``e_i`` drawn at the bob (``s`` = :data:`BODY_AXIS_LENGTH` ``|ρ_c|``), which
      shows the spin about the rod.
    """
    R = np.asarray(R, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    rho = np.asarray(model.rho_c, dtype=np.float64)
    size = float(np.linalg.norm(rho))
    pivot = np.concatenate([q, np.zeros_like(q[..., :1])], axis=-1)
    bob = pivot + np.einsum("...ij,j->...i", R, rho)
    half = 0.5 * size * np.asarray(CART_SIZE)
    corners = np.array([[-half[0], -half[1], 0.0], [half[0], -half[1], 0.0],
                        [half[0], half[1], 0.0], [-half[0], half[1], 0.0]])
    body_axes = bob[..., None, :] + BODY_AXIS_LENGTH * size * np.swapaxes(R, -1, -2)
    return {"pivot": pivot, "bob": bob, "cart": pivot[..., None, :] + corners,
            "body_axes": body_axes}


def _figure_3d(nrows: int, ncols: int, width: float, height: float, *, agg: bool = False):
    """A figure of 3D axes without pyplot (so that a notebook's inline backend is left
    alone, and nothing is displayed but what the caller shows). ``agg``: on an Agg canvas,
    whose pixels can be read (otherwise the base canvas, which draws only when saved: an
    animation's frames are then drawn once each, not twice)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height))
    if agg:
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        FigureCanvasAgg(fig)
    axes = [fig.add_subplot(nrows, ncols, i + 1, projection="3d")
            for i in range(nrows * ncols)]
    return fig, axes


class MotionView:
    """The car-pendulum in 3D on one mplot3d ``Axes3D``: the cart's rectangle in the plane
    ``z = 0``, the rod from the hinge to the mass centre (the bob), the body axes at the bob,
    the bob's path over the last ``trail`` seconds, its shadow on the plane ``z = 0`` (a
    dotted vertical line, for depth) and the cart's path so far. ``e3`` points
    down, as in the model: the z axis is drawn inverted, so the pendulum hangs below the
    cart's plane. The limits are fixed over all saved states (equal scales), so that frames
    compare. :meth:`draw` shows saved state ``i`` (the update function of an animation)."""

    def __init__(self, ax, model: CarPendulum, traj, *, trail: float = 0.5,
                 geometry: dict | None = None, title: bool = True):
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection

        self.ax, self.title = ax, title
        self.t = np.asarray(traj.t)
        self.geom = geometry if geometry is not None else motion_geometry(
            model, traj.state.R, traj.state.q)
        dt = float(self.t[1] - self.t[0]) if len(self.t) > 1 else 1.0
        self.trail = max(1, round(trail / dt))
        points = np.concatenate([self.geom["cart"].reshape(-1, 3), self.geom["bob"],
                                 self.geom["body_axes"].reshape(-1, 3)])
        lo, hi = points.min(axis=0), points.max(axis=0)
        centre, half = 0.5 * (lo + hi), 0.55 * float(np.max(hi - lo))
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] + half, centre[2] - half)  # e3 down: larger z drawn lower
        ax.set_box_aspect((1.0, 1.0, 1.0))
        ax.set_xlabel("x [m]", fontsize=7, labelpad=-8)
        ax.set_ylabel("y [m]", fontsize=7, labelpad=-8)
        ax.set_zlabel("z [m] (down)", fontsize=7, labelpad=-8)
        ax.tick_params(labelsize=5, pad=-3)
        ax.locator_params(nbins=4)
        self.cart = Poly3DCollection([self.geom["cart"][0]], facecolor="tab:gray",
                                     edgecolor="black", alpha=0.6)
        ax.add_collection3d(self.cart)
        (self.cart_path,) = ax.plot([], [], [], color="tab:gray", linewidth=0.8)
        (self.path,) = ax.plot([], [], [], color="tab:orange", linewidth=0.8, alpha=0.8)
        (self.rod,) = ax.plot([], [], [], color="black", linewidth=2.0)
        (self.bob,) = ax.plot([], [], [], "o", color="tab:purple", markersize=7)
        (self.shadow,) = ax.plot([], [], [], ":o", color="tab:purple", markersize=2,
                                 linewidth=0.8, alpha=0.6, markevery=[1])
        (self.pivot,) = ax.plot([], [], [], "o", color="black", markersize=3)
        self.axes = [ax.plot([], [], [], color=c, linewidth=1.2)[0] for c in _AXIS_COLOURS]

    def artists(self) -> list:
        return [self.cart, self.cart_path, self.path, self.rod, self.bob, self.shadow,
                self.pivot, *self.axes]

    def draw(self, i: int) -> list:
        g = self.geom
        pivot, bob = g["pivot"][i], g["bob"][i]
        self.cart.set_verts([g["cart"][i]])
        self.cart_path.set_data_3d(*g["pivot"][: i + 1].T)
        self.path.set_data_3d(*g["bob"][max(0, i - self.trail) : i + 1].T)
        self.rod.set_data_3d(*np.stack([pivot, bob]).T)
        self.bob.set_data_3d([bob[0]], [bob[1]], [bob[2]])
        self.shadow.set_data_3d([bob[0], bob[0]], [bob[1], bob[1]], [bob[2], 0.0])
        self.pivot.set_data_3d([pivot[0]], [pivot[1]], [pivot[2]])
        for line, tip in zip(self.axes, g["body_axes"][i], strict=True):
            line.set_data_3d(*np.stack([bob, tip]).T)
        if self.title:
            self.ax.set_title(f"t = {self.t[i]:.2f} s", fontsize=8)
        return self.artists()


def motion_frames(traj, t_final: float, frames: int) -> np.ndarray:
    """Indices of ``frames`` saved states at equally spaced times over ``[0, t_final]``
    (the nearest saved times; ``t_final`` is clipped to the run's end)."""
    t = np.asarray(traj.t)
    wanted = np.linspace(float(t[0]), min(float(t_final), float(t[-1])), frames)
    return np.abs(t[None, :] - wanted[:, None]).argmin(axis=1)


def motion_snapshots(model: CarPendulum, traj, *, t_final: float = 2.0, rows: int = 2,
                     cols: int = 4, trail: float = 0.5, label: str = ""):
    """A still sequence of the motion: ``rows × cols`` 3D views at equally spaced times
    over ``[0, t_final]``, with the same limits in every panel. Returns the figure."""
    fig, axes = _figure_3d(rows, cols, width=3.2 * cols, height=3.2 * rows)
    geom = motion_geometry(model, traj.state.R, traj.state.q)
    for ax, i in zip(axes, motion_frames(traj, t_final, rows * cols), strict=True):
        MotionView(ax, model, traj, trail=trail, geometry=geom).draw(int(i))
    fig.suptitle(f"Car-pendulum{label}: the cart (grey) in the plane z = 0, the rod (black) "
                 f"from the hinge to the mass centre (purple), the body axes e1, e2, e3 (red, "
                 f"green, blue),\nthe mass centre's path over the last {trail:g} s (orange) "
                 "and its shadow on the plane (dotted), the cart's path (grey)", fontsize=9)
    return fig


def motion_animation(model: CarPendulum, traj, *, t_final: float = 3.0, frames: int = 30,
                     trail: float = 0.5, size: float = 4.5, dpi: int = 72,
                     interval: float | None = None):
    """A :class:`matplotlib.animation.FuncAnimation` of the motion over ``[0, t_final]``
    (``frames`` saved states, equally spaced; by default played in real time). In Jupyter:
    ``IPython.display.HTML(motion_animation(model, traj).to_jshtml())``."""
    from matplotlib.animation import FuncAnimation

    fig, (ax,) = _figure_3d(1, 1, width=size, height=size)
    fig.set_dpi(dpi)
    fig.subplots_adjust(left=0.0, right=0.93, bottom=0.03, top=0.93)  # 3D axes pad enough
    view = MotionView(ax, model, traj, trail=trail)
    index = motion_frames(traj, t_final, frames)
    if interval is None:
        t = np.asarray(traj.t)
        interval = 1000.0 * float(t[index[-1]] - t[index[0]]) / max(1, frames - 1)
    return FuncAnimation(fig, lambda k: view.draw(int(index[k])), frames=len(index),
                         interval=interval, blit=False)


def write_motion_gif(model: CarPendulum, traj, path: Path, *, t_final: float = 6.0,
                     fps: int = 10, trail: float = 0.5, size: float = 5.0,
                     dpi: int = 80) -> bool:
    """The motion over ``[0, t_final]`` in real time as an animated GIF (Pillow, which
    matplotlib depends on), written atomically; ``False`` (nothing written) without Pillow."""
    try:
        from PIL import Image
    except ImportError:  # pragma: no cover - Pillow is a dependency of matplotlib
        return False
    from lgvi_jax._io import atomic_write

    fig, (ax,) = _figure_3d(1, 1, width=size, height=size, agg=True)
    fig.set_dpi(dpi)
    fig.subplots_adjust(left=0.0, right=0.93, bottom=0.03, top=0.93)
    view = MotionView(ax, model, traj, trail=trail)
    images = []
    for i in motion_frames(traj, t_final, round(t_final * fps) + 1):
        view.draw(int(i))
        fig.canvas.draw()
        images.append(Image.fromarray(np.asarray(fig.canvas.buffer_rgba())[..., :3]))
    atomic_write(path, lambda fh: images[0].save(
        fh, format="GIF", save_all=True, append_images=images[1:],
        duration=round(1000 / fps), loop=0))
    return True


def motion_figures(model: CarPendulum, traj, cfg, out: Path) -> list[str]:
    """The 3D view of the paper run (``traj``: the saved states of one method): the still
    sequence ``motion_snapshots.png`` and the animation ``motion.gif``; the names written."""
    label = f" ({cfg['motion_method']}, h = {cfg['paper_dt']:g} s)"
    save(motion_snapshots(model, traj, t_final=cfg["motion_snapshots_t"], label=label),
         out / "motion_snapshots.png")
    names = ["motion_snapshots.png"]
    if write_motion_gif(model, traj, out / "motion.gif", t_final=cfg["motion_gif_t"],
                        fps=cfg["motion_gif_fps"]):
        names.append("motion.gif")
    return names


# ------------------------------------------------------------------------ verdicts


def _compare(a: list, b: list) -> str:
    """'all', 'none' or 'some': at how many steps is a < b."""
    wins = sum(x < y for x, y in zip(a, b, strict=True))
    return "all" if wins == len(a) else "none" if wins == 0 else "some"


def verdicts(table: dict, sweep_res: dict, long: dict) -> dict:
    out = {}
    ratios = {m: long[m]["drift_ratio"] for m in PAPER_METHODS}
    bounded = all(r < 1.5 for r in ratios.values())
    out["energy_bounded"] = {
        "claim": "both methods keep the energy bounded (no drift)",
        "verdict": "confirmed" if bounded else "refuted",
        "evidence": "max energy error over the last 10% of the long run / over the first "
        "10%: " + ", ".join(f"{m} {r:.2f}" for m, r in ratios.items())
        + " (a linear drift gives ~10)",
    }
    orth = {m: table[m]["max_orthogonality_error"] for m in PAPER_METHODS}
    out["stays_on_so3"] = {
        "claim": "both methods keep R on SO(3)",
        "verdict": "confirmed" if all(v < 1e-12 for v in orth.values()) else "refuted",
        "evidence": "max ‖RᵀR − I‖_F over 50 s: "
        + ", ".join(f"{m} {v:.1e}" for m, v in orth.items())
        + f" (RK4: {table['rk4']['max_orthogonality_error']:.1e})",
    }
    word = {"all": "confirmed", "none": "refuted", "some": "partly"}

    def versus(key):
        """hamel against lgvi at every step from both sweep states."""
        hamel = [e for rr in sweep_res.values() for e in rr["hamel"][key]]
        lgvi = [e for rr in sweep_res.values() for e in rr["lgvi"][key]]
        detail = "; ".join(
            f"{state}: " + ", ".join(f"h = {h:g}: {a:.2e} / {b:.2e}" for h, a, b in zip(
                SWEEP_STEPS, rr["hamel"][key], rr["lgvi"][key], strict=True))
            for state, rr in sweep_res.items())
        return _compare(hamel, lgvi), detail

    acc, detail = versus("state_error")
    out["hamel_more_accurate"] = {
        "claim": "the Hamel VI is more accurate than the general LGVI",
        "verdict": word[acc],
        "evidence": "position error at t = 5 s, hamel / lgvi: " + detail,
    }
    en, detail = versus("energy_error")
    paper = table["hamel"]["max_energy_error"] < table["lgvi"]["max_energy_error"]
    en_all = [en == "all" and paper, en == "none" and not paper]
    out["hamel_keeps_energy_better"] = {
        "claim": "the Hamel VI keeps the energy better than the general LGVI",
        "verdict": "confirmed" if en_all[0] else "refuted" if en_all[1] else "partly",
        "evidence": "max |H − H₀| over 5 s, hamel / lgvi: " + detail
        + f"; paper state (50 s, h = 5e-3): hamel {table['hamel']['max_energy_error']:.2e}, "
        f"lgvi {table['lgvi']['max_energy_error']:.2e} ({'hamel' if paper else 'lgvi'} "
        "smaller). Which is smaller depends on the state: both errors are O(h²) with "
        "different constants",
    }
    lz = sweep_res["moving cart"]["hamel"]
    noether = max(max(rr[m]["angular_momentum_z_error"]) for rr in sweep_res.values()
                  for m in ("lgvi", "hamel-cayley", "hamel-exact"))
    order = lz["angular_momentum_z_error_order"]
    out["momentum_maps"] = {
        "claim": "(not a claim of the paper) the methods conserve the momentum maps",
        "verdict": "lgvi, hamel-cayley, hamel-exact: yes; hamel: no",
        "evidence": f"max |ΔL_z| over the sweep: lgvi/hamel-cayley/hamel-exact <= "
        f"{noether:.1e}; the paper's hamel (moving cart) "
        + ", ".join(f"{e:.1e}" for e in lz["angular_momentum_z_error"])
        + f" at h = {', '.join(f'{h:g}' for h in SWEEP_STEPS)}"
        + (f" (slope {order:.2f}: O(h²))" if order is not None else ""),
    }
    return out


def write_summary(results: dict, out: Path) -> str:
    cfg, table, long = results["config"], results["table"], results["long_run"]
    lines = [
        "3D car-pendulum (paper §3, figures 5–11): the paper's parameters and initial state, "
        f"g = {cfg['g']}, h = {cfg['paper_dt']}, t ∈ [0, {cfg['paper_t_final']:g}]. "
        f"Step sweep: h = {', '.join(map(str, cfg['sweep_steps']))} over "
        f"{cfg['sweep_t_final']:g} s from the paper's state and from a state with non-zero cart "
        "momentum (moving cart), against RK4 at "
        f"h = {cfg['reference_dt']:g}. Long run: {cfg['long_n_steps']} steps of "
        f"h = {cfg['long_dt']}.",
        "",
        "![fig5](fig5_cart_trajectory.png) ![fig6](fig6_pendulum_trajectory.png)",
        "![fig7](fig7_cart_components.png) ![fig8](fig8_pendulum_components.png)",
        "![fig9](fig9_energy.png) ![fig10](fig10_energy_error.png)",
        "![fig11](fig11_orthogonality_error.png) ![momentum](momentum_maps.png)",
        "![sweep](step_sweep.png) ![long run](long_run_energy.png)",
        "",
        f"The motion in 3D ({cfg['motion_method']}; z points down): snapshots over the "
        f"first {cfg['motion_snapshots_t']:g} s"
        + (f", an animation of the first {cfg['motion_gif_t']:g} s in real time"
           if "motion.gif" in results["motion_figures"] else "") + ".",
        "",
        " ".join(f"![{name.split('.')[0]}]({name})" for name in results["motion_figures"]),
        "",
        "Paper state, 50 s at h = 5e-3:",
        "",
        "| method | max \\|ΔH\\| [J] | max \\|ΔH/H\\| | max \\|Δp\\| | max \\|ΔL_z\\| "
        "| max ‖RᵀR − I‖_F | Newton its/step (mean, max) | steps/s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name in (*METHODS, *cfg["extra_methods"]):
        r = table[name]
        lines.append(
            f"| {name} | {r['max_energy_error']:.3e} | {r['max_relative_energy_error']:.2e} | "
            f"{r['max_momentum_error']:.1e} | {r['max_angular_momentum_z_error']:.1e} | "
            f"{r['max_orthogonality_error']:.1e} | {r['newton_mean']:.2f}, {r['newton_max']} | "
            f"{r['steps_per_second']:.3g} |")
    lines += ["", "Step sweep (position error at the end, max energy error; slopes):", "",
              "| method | " + " | ".join(f"h = {h:g}" for h in SWEEP_STEPS)
              + " | slope (position) | slope (energy) |",
              "|---|" + "---|" * (len(SWEEP_STEPS) + 2)]
    for state, rr in results["sweep"].items():
        for name in METHODS:
            r = rr[name]
            cells = [f"{a:.2e}, {b:.2e}" for a, b in zip(r["state_error"], r["energy_error"],
                                                          strict=True)]
            lines.append(f"| {name} ({state}) | " + " | ".join(cells)
                         + f" | {r['state_error_order']:.2f} | "
                         f"{r['energy_error_order']:.2f} |")
    lines += ["", f"Long run ({cfg['long_n_steps']} steps):", "",
              "| method | max \\|ΔH\\| first 10% | last 10% | ratio | max \\|ΔL_z\\| "
              "| ‖RᵀR − I‖_F at the end | steps/s |", "|---|---|---|---|---|---|---|"]
    for name in VI_METHODS:
        r = long[name]
        lines.append(
            f"| {name} | {r['max_energy_error_first_10pct']:.3e} | "
            f"{r['max_energy_error_last_10pct']:.3e} | {r['drift_ratio']:.2f} | "
            f"{r['max_angular_momentum_z_error']:.1e} | {r['orthogonality_error_final']:.1e} | "
            f"{r['steps_per_second']:.3g} |")
    lines += ["", "**The paper's claims, measured:**", ""]
    for i, v in enumerate(results["verdicts"].values(), 1):
        lines.append(f"{i}. *{v['claim']}* — **{v['verdict']}**: {v['evidence']}.")
    return write_summary_lines(out, lines)


def run(out_dir: Path | str, *, quick: bool = False, log: Callable = print) -> dict:
    """Run the whole study into ``out_dir``; returns the results dictionary."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cfg = config(quick)
    model = CarPendulum(g=cfg["g"])
    log("  paper state, figures 5-11 ...")
    runs, table = paper_runs(model, cfg, log)
    paper_figures(model, {k: traj for k, (traj, _) in runs.items()}, cfg, out)
    log("  3D view of the motion ...")
    motion = motion_figures(model, runs[cfg["motion_method"]][0], cfg, out)
    log("  step-size sweep ...")
    sweep_res = sweep(cfg, out, log)
    log(f"  long run ({cfg['long_n_steps']} steps per VI method) ...")
    long = long_run(model, cfg, out, log, runs)
    results = {
        "quick": quick,
        "config": cfg,
        "table": table,
        "sweep": sweep_res,
        "long_run": long,
        "verdicts": verdicts(table, sweep_res, long),
        "motion_figures": motion,
        "environment": environment(),
    }
    write_summary(results, out)
    mark_complete(out, results)
    return results


if __name__ == "__main__":
    sys.exit(script_main(run, __doc__, quick_help="shorter long run"))
