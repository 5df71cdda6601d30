"""Processed (effective-order) compositions of ``lgvi`` against ``lgvi@6`` / ``lgvi@8``.

A processed composition is a kernel :math:`K_h` and a processor :math:`\\pi_h`, both
compositions of a symmetric base, such that :math:`\\pi_h K_h \\pi_h^{-1}` has order
:math:`p` while :math:`K_h` alone needs fewer stages than a composition of order :math:`p`;
:math:`n` steps are :math:`\\pi_h K_h^n \\pi_h^{-1}`, so the processor runs only at the
outputs. The processed composition is itself a composition of the base (the processor's
inverse is the processor's fractions negated in reverse order, the base being symmetric),
so its effective order is checked here with the same BCH computation as every scheme
(:func:`lgvi_jax.integrators.order_conditions.composition_order`).

Coefficients (kernel half, processor fractions applied in order after the kernel):
S. Blanes, *High order numerical integrators for differential equations using composition
and processing of low order methods*, Appl. Numer. Math. 37 (2001) 289–306 (effective order
6, 7-stage kernel, 10-stage processor); S. Blanes, F. Casas, A. Murua, *Composition methods
for differential equations with processing*, SIAM J. Sci. Comput. 27 (2006) 1817–1843
(effective order 8, 13-stage kernel, 20-stage processor).

Case: the moving cart of the work-precision study at t = 10 s, pendulum mass-centre error
against the independent DOP853 reference; each method one compiled program (processor,
kernel steps, processor), best of ``--repeats`` interleaved runs; the times are then
interpolated to equal error (log-log).

    python experiments/bench_processed.py --out results/processed [--repeats 8]

Writes ``bench_processed.json`` and ``bench_processed.md`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import lgvi_jax as L
from lgvi_jax import rollout
from lgvi_jax._io import atomic_write_text
from lgvi_jax.integrators import RIGID_METHODS, Composition, resolve_method
from lgvi_jax.integrators.order_conditions import composition_order
from lgvi_jax.integrators.solver_settings import with_scalar_newton
from lgvi_jax.studies.work_precision.cases import make_case

STEPS = (0.1, 0.08, 0.0625, 0.05, 0.04, 0.03125, 0.025)
TARGETS = (1e-6, 1e-8, 1e-10)


def _antisymmetric(tail):
    """``(g1, ..., gm, -g1, ..., -gm)`` with ``g1 = -(g2 + ... + gm)``."""
    g = [-sum(tail), *tail]
    return [*g, *(-x for x in g)]


def processed_schemes() -> dict[str, tuple[list[float], list[float], int]]:
    """name -> (kernel fractions, processor fractions, effective order)."""
    a1, a2, a3 = 0.513910778424374, 0.364193022833858, -0.867423280969274
    bla = [a1, a2, a3, 1 - 2 * (a1 + a2 + a3), a3, a2, a1]
    bla_p = _antisymmetric([-0.461165940466494, -0.074332422810238, 0.384998538774070,
                            0.375012038697862])
    b1, b3, b4, b5, b6 = (0.168, 0.585550530805562, -0.460090457516872, 0.172863148729731,
                          0.179664539695039)
    mid = 1 - 2 * (2 * b1 + b3 + b4 + b5 + b6)
    bcm = [b1, b1, b3, b4, b5, b6, mid, b6, b5, b4, b3, b1, b1]
    bcm_p = _antisymmetric([-0.008488123494574411, -0.337188967354338, 0.333987768164597,
                            0.588351189003849, 0.162324207599241, -0.511744926116413,
                            0.236885952363384, 0.598212975943381, -0.543415765371656])
    # The published processors are the negated fractions, applied last to first.
    return {"blanes2001-eff6": (bla, [-x for x in bla_p][::-1], 6),
            "bcm2006-eff8": (bcm, [-x for x in bcm_p][::-1], 8)}


@eqx.filter_jit
def _processed(model, kernel, base, s, h, n, pre, post):
    def fractions(s, gammas):
        def body(s, g):
            return base.step(model, s, g * h)[0], None
        return jax.lax.scan(body, s, gammas)[0]

    c, _ = rollout.advance(model, kernel, h, rollout.start(model, kernel, fractions(s, pre), h), n)
    return fractions(c.state, post), c.newton_steps


@eqx.filter_jit
def _plain(model, method, s, h, n):
    c, _ = rollout.advance(model, method, h, rollout.start(model, method, s, h), n)
    return c.state, c.newton_steps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--repeats", type=int, default=8)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    case = make_case("car-moving")
    T = 10.0
    ref = case.reference_position(T)
    model, s0 = case.model, case.state0
    base = with_scalar_newton(L.LGVI())

    runs = {}
    for name, (kernel, post, order) in processed_schemes().items():
        pre = [-x for x in post[::-1]]
        effective = composition_order(tuple(pre + kernel + post))
        assert effective == order, (name, effective)
        comp = Composition(L.LGVI(), tuple(kernel), scheme=name)
        fracs = (jnp.asarray(pre), jnp.asarray(post))
        runs[name] = (lambda h, n, c=comp, ab=fracs:
                      _processed(model, c, base, s0, jnp.float64(h), jnp.int32(n), *ab),
                      len(kernel))
    for name in ("lgvi@6", "lgvi@8"):
        m = resolve_method(name, RIGID_METHODS)
        runs[name] = (lambda h, n, m=m: _plain(model, m, s0, jnp.float64(h), jnp.int32(n)),
                      m.stages)

    rows = {k: [] for k in runs}
    for h in STEPS:
        n = round(T / h)
        times = {k: [] for k in runs}
        for _ in range(args.repeats + 1):  # the first round compiles
            for k, (f, _) in runs.items():
                start = time.perf_counter()
                jax.block_until_ready(f(h, n))
                times[k].append(time.perf_counter() - start)
        for k, (f, stages) in runs.items():
            state, iters = f(h, n)
            err = float(np.linalg.norm(np.asarray(model.pendulum_centre(state)) - ref))
            rows[k].append({"h": h, "error": err, "time_s": min(times[k][1:]),
                            "newton_per_step": int(iters) / n, "stages": stages})
            print(f"{k:16s} h={h:<8g} error {err:.2e} m  {min(times[k][1:]) * 1e3:.2f} ms",
                  flush=True)

    def at(k, target):
        pts = sorted((r["error"], r["time_s"]) for r in rows[k])
        le, lt = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
        x = np.log(target)
        return float(np.exp(np.interp(x, le, lt))) if le[0] <= x <= le[-1] else None

    equal = {f"{t:g}": {k: at(k, t) for k in runs} for t in TARGETS}
    atomic_write_text(args.out / "bench_processed.json",
                      json.dumps({"rows": rows, "time_at_error": equal}, indent=2))
    lines = ["# Processed compositions against lgvi@6 / lgvi@8 (moving cart, t = 10 s)", "",
             "| error [m] | " + " | ".join(runs) + " |", "|---|" + "---|" * len(runs)]
    for t, row in equal.items():
        cells = [f"{v * 1e3:.2f} ms" if v else "–" for v in row.values()]
        lines.append(f"| {t} | " + " | ".join(cells) + " |")
    atomic_write_text(args.out / "bench_processed.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
