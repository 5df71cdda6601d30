r"""Fused car-pendulum steps: the engine's discrete equations for the 3D car-pendulum,
reduced by hand to three equations in the rotation increment and written in scalar
components, so that XLA fuses a Newton iteration into a handful of elementwise kernels.

**Why.** The general engine (:mod:`lgvi_jax.integrators.lie`) builds the residual by
autodiff of the discrete Lagrangian through small vector and matrix operations: ~70 XLA
kernels per step plus ~40 per Newton iteration, each costing a few nanoseconds per
trajectory in a batch and ~10 ns for a single trajectory, whatever its arithmetic (profiled,
README "Throughput"). Here every quantity is a tuple of scalars (a structure of arrays under
``vmap``: one contiguous array per component), so the whole residual is elementwise and one
iteration is ~10 kernels. Same equations, same solutions to the solver tolerance (tested
against the general engine in ``tests/test_fused.py``); several times the general engine's
throughput (``lgvi-jax bench``, README).

**Equations.** With ``F = R_kᵀR_{k+1} = I + c_1ŵ + c_2ŵ²``, ``u = (q_{k+1} − q_k)/h``,
``ρ = ρ_c``, ``e = w × ρ``, ``a_k = R_kᵀPᵀu``, ``a_{k+1} = Fᵀa_k``, ``b = R_kᵀe_3`` and
``K = μ_k + (h/2) m g ρ × b`` (derivations in ``experiments/numba_lgvi.py`` and
``experiments/numba_hamel.py``, whose Numba baselines solve the same reduced equations):

* ``lgvi`` (:class:`~lgvi_jax.integrators.lie.LGVI`, Cayley coordinates
  ``c_1 = 4/(4+θ²)``, ``c_2 = c_1/2``): the cart equation ``p_k = (m+M)u + (m/h) P R_k
  (F − I)ρ`` gives ``u`` for a given ``w``; the residual is ``c_1Jw/h + c_2 w×Jw/h +
  mρ×a_k − K`` and ``μ_{k+1} = c_1Jw/h − c_2 w×Jw/h + mρ×a_{k+1} + (h/2)mgρ×R_{k+1}ᵀe_3``.
* ``hamel``, ``hamel-cayley``, ``hamel-exact`` (:class:`~lgvi_jax.integrators.lie.HamelVI`
  with ``(exp, paper)``, ``(cayley, paper)``, ``(exp, exact)``): ``p_k = (m+M)u +
  (m/2h)PR_k(I + F)e`` gives ``u``; with ``g_w = Jw/h + (m/2)ρ×(a_k + a_{k+1})``,
  ``x = w × g_w`` and ``y = g_w + d w×x`` (``d = 0`` for the paper's variation,
  ``d = 1/θ² − cot(θ/2)/(2θ)`` for the exact one) the residual is ``y + x/2 −
  (m/2)e×a_k − K`` and ``μ_{k+1} = y − x/2 + (m/2)e×a_{k+1} + (h/2)mgρ×R_{k+1}ᵀe_3``.

In every method ``p_{k+1} = p_k`` exactly and ``q_{k+1} = q_k + hu``.

**Solver.** Newton's method on ``w`` from ``w = 0``, first as a chord iteration with the
Jacobian at ``w = 0`` (in closed form, :func:`_chord_jacobian`, once per step), inverted
by cofactors. When an update is not below a quarter of the previous one
(:data:`_CONTRACTION`) or stops being finite, a second loop continues by Broyden's method
(secant updates of an inverse Jacobian, :func:`_broyden`): for the Hamel methods restarted
from the chord's first iterate with the inverse of the Jacobian there (:func:`_restart`),
for ``lgvi`` from the last finite iterate with the chord's inverse. Under ``vmap`` it
costs nothing unless some trajectory needs it. Broyden replaced plain Newton (a fresh
Jacobian every iteration, continued from the chord's last iterate), which was no more
robust (measured on 256 trajectories perturbed by 0.3 at h = 0.02-0.2: the same failures
within 1-6 per setting) and cost a Jacobian inside a loop, ~1 s of the batched program's
compile time. Convergence: ``|Δw_i| <= tol (h + |w_i|)``, the general engine's ``|Δξ_i|
<= tol (1 + |ξ_i|)`` for ``ξ = w/h``, with ``tol = 1e-14`` (:attr:`FusedCarPendulum.tol`).
Result codes as :data:`~lgvi_jax.newton.RESULTS`; ``newton_steps`` counts residual
evaluations in the loops.

**Layouts.** One trajectory and a batch want different loops: a kernel per loop value is
cheap when each is a vector of 512 trajectories and the arithmetic vectorises, but one
trajectory pays ~20 ns per kernel whatever it computes. The step therefore chooses by
batching (``jax.custom_batching.custom_vmap``): alone, the Newton loop's state is packed in
one array (:func:`_solve_packed`); under ``vmap`` (also nested, or over the model's
parameters) each component is its own array (:func:`_solve`): batched by JAX for
``lgvi``, as an explicit batch for the Hamel methods (measured faster for each), with the
residual materialised once per iteration (:func:`_materialize`). Both solve the same
equations by the same iteration (equal to a few ulps, tested).

**Limits.** Only :class:`~lgvi_jax.models.rigid_bodies.CarPendulum`. Large steps: on
the 256 perturbed trajectories above every fused method converges at h <= 0.1, as the
general engine does; at h = 0.2 (50 steps) ``hamel``, ``hamel-cayley`` and
``hamel-exact`` converge for 245, 256 and 256 of them with the restart (25, 173 and 4
without it) and the general engine, Newton from the current velocities with the Jacobian
there, for 201, 250 and 256; ``lgvi`` for none with either engine (at h = 0.15: 69, the
general engine 71). No derivatives (``custom_vmap`` has no differentiation rule): for
gradients (inertia fitting) use the general methods, whose Newton solves have
implicit-function-theorem derivatives.
"""

from __future__ import annotations

import functools
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ..models.rigid import RigidState
from ..models.rigid_bodies import CarPendulum
from ..newton import RESULTS
from .base import AbstractIntegrator, StepInfo
from .lie import LGVI, HamelVI

#: fused method name -> the general method with the same discrete equations
KINDS = {
    "lgvi": LGVI,
    "hamel": lambda: HamelVI(map="exp", variation="paper"),
    "hamel-cayley": lambda: HamelVI(map="cayley", variation="paper"),
    "hamel-exact": lambda: HamelVI(map="exp", variation="exact"),
}

_TAYLOR_THETA_SQ = 1e-2  # as lgvi_jax.so3: series for θ < 0.1


# --- three-vectors as tuples of scalars -----------------------------------------------

def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _comb(*terms):
    """``Σ c_i v_i`` for pairs ``(c_i, v_i)`` of a scalar and a vector."""
    return tuple(sum(c * v[i] for c, v in terms) for i in range(3))


def _matvec(A, x):
    return tuple(_dot(row, x) for row in A)


def _coeffs(kind: str, t2):
    """``(c_1, c_2, d)`` for ``θ² = t2``: ``F = I + c_1ŵ + c_2ŵ²`` and the exact
    variation's ``d`` (0 otherwise); series branches for ``θ < 0.1`` as in
    :mod:`lgvi_jax.so3`. For the exp map a ``cond`` skips the closed forms when every angle
    (of one trajectory, or of an explicit batch ``t2``) is in the series' range, the usual
    case at small steps: XLA evaluates ``sin`` and ``cos`` element by element, and for one
    trajectory inside every kernel that needs them, which made the exp-map methods 2x slower
    batched and ~1.2x slower alone. (Long series instead of ``sin``/``cos`` were measured 5x
    slower: XLA inlines the polynomial into every kernel that uses it.)"""
    if kind in ("lgvi", "hamel-cayley"):
        c1 = 4.0 / (4.0 + t2)
        return c1, 0.5 * c1, jnp.zeros_like(t2)
    exact = kind == "hamel-exact"

    def series(t2):
        s1 = 1.0 + t2 * (-1.0 / 6 + t2 * (1.0 / 120 + t2 * (-1.0 / 5040 + t2 * (
            1.0 / 362880 + t2 * (-1.0 / 39916800)))))
        s2 = 0.5 + t2 * (-1.0 / 24 + t2 * (1.0 / 720 + t2 * (-1.0 / 40320 + t2 * (
            1.0 / 3628800 + t2 * (-1.0 / 479001600)))))
        sd = 1.0 / 12 + t2 * (1.0 / 720 + t2 * (1.0 / 30240 + t2 * (
            1.0 / 1209600 + t2 * (1.0 / 47900160)))) if exact else jnp.zeros_like(t2)
        return s1, s2, sd

    def mixed(t2):
        small = t2 < _TAYLOR_THETA_SQ
        s1, s2, sd = series(t2)
        tt = jnp.where(small, 1.0, t2)  # the closed forms only where they are accurate
        t = jnp.sqrt(tt)
        sh = jnp.sin(0.5 * t)
        c1 = jnp.where(small, s1, jnp.sin(t) / t)
        c2 = jnp.where(small, s2, 2.0 * sh * sh / tt)
        d = jnp.where(small, sd, 1.0 / tt - jnp.cos(0.5 * t) / (2.0 * t * sh)) if exact \
            else sd
        return c1, c2, d

    return jax.lax.cond(jnp.all(t2 < _TAYLOR_THETA_SQ), series, mixed, t2)


def _transpose_rotate(c1, c2, t2, w, a):
    """``Fᵀa = a − c_1 w×a + c_2 (w (w·a) − θ² a)``."""
    return _comb((1.0, a), (-c1, _cross(w, a)), (c2 * _dot(w, a), w), (-c2 * t2, a))


def _equations(kind, prm, h, R0, K, p, w):
    """The reduced step for the increment ``w``: ``(residual, u, μ_{k+1} without its
    gravity term, c_1, c_2)``."""
    m, M, rho, J = prm["m"], prm["M"], prm["rho"], prm["J"]
    t2 = _dot(w, w)
    c1, c2, d = _coeffs(kind, t2)
    e = _cross(w, rho)
    if kind == "lgvi":
        g, k = _comb((c1, e), (c2, _cross(w, e))), m / h  # (F − I)ρ
    else:
        g, k = _comb((2.0 - c2 * t2, e), (c1, _cross(w, e))), 0.5 * m / h  # (I + F)e
    inv_mass = 1.0 / (m + M)
    u = tuple((p[i] - k * _dot(R0[i], g)) * inv_mass for i in range(2))
    a = tuple(R0[0][j] * u[0] + R0[1][j] * u[1] for j in range(3))  # R_kᵀPᵀu
    b = _transpose_rotate(c1, c2, t2, w, a)  # a_{k+1} = Fᵀa_k
    Jw = tuple(x / h for x in _matvec(J, w))
    if kind == "lgvi":
        x = _comb((c2, _cross(w, Jw)),)
        res = _comb((c1, Jw), (1.0, x), (m, _cross(rho, a)), (-1.0, K))
        nxt = _comb((c1, Jw), (-1.0, x), (m, _cross(rho, b)))
        return res, u, nxt, c1, c2
    gw = _comb((1.0, Jw), (0.5 * m, _cross(rho, _comb((1.0, a), (1.0, b)))))
    x = _cross(w, gw)
    y = _comb((1.0, gw), (d, _cross(w, x))) if kind == "hamel-exact" else gw
    res = _comb((1.0, y), (0.5, x), (-0.5 * m, _cross(e, a)), (-1.0, K))
    nxt = _comb((1.0, y), (-0.5, x), (0.5 * m, _cross(e, b)))
    return res, u, nxt, c1, c2


#: :func:`_equations` as a traced-once function: the chord and Broyden loops, the final
#: outputs (and, with the same argument shapes, later programs in the process) reuse one
#: trace and one lowering instead of tracing the scalar arithmetic each time; XLA inlines
#: the calls, so the compiled program is the same.
_equations_once = jax.jit(_equations, static_argnums=0)


def _jacobian(f, w):
    """``∂f/∂w`` at ``w`` by forward-mode autodiff (three tangents, ``vmap``ped so that ``f``
    is traced once), row-major; ``w``'s components may be arrays of a batch (each
    trajectory's own 3x3 Jacobian): for the Broyden restart (:func:`_restart`), the generic
    solver tests and to check :func:`_chord_jacobian`."""
    shape = jnp.shape(w[0])
    eye = tuple(jnp.broadcast_to(
        jnp.asarray([float(i == j) for j in range(3)], w[i].dtype).reshape(
            (3,) + (1,) * len(shape)), (3, *shape)) for i in range(3))
    rows = jax.vmap(lambda t: jax.jvp(f, (w,), (t,))[1])(eye)  # rows[i][j] = ∂f_i/∂w_j
    return tuple(rows[i][j] for i in range(3) for j in range(3))


def _unit_cross(j, v):
    """``e_j × v``."""
    return ((0.0, -v[2], v[1]), (v[2], 0.0, -v[0]), (-v[1], v[0], 0.0))[j]


def _chord_jacobian(kind, prm, h, R0, p):
    """``∂f/∂w`` at ``w = 0`` of :func:`_equations`' residual, row-major, in closed form.
    At ``θ = 0``: ``c_1 = 1``, ``c_2 = 1/2`` and the terms of second order in ``w`` drop,
    so with ``e' = δ×ρ``, ``u' = −(m/h) P R_k e'/(m+M)``, ``a' = R_kᵀPᵀu'`` and ``a_0`` the
    ``a_k`` at ``w = 0``: ``lgvi``: ``f' = Jδ/h + m ρ×a'``; Hamel (``b' = a' − δ×a_0``,
    ``g_0 = m ρ×a_0``, ``g' = Jδ/h + (m/2) ρ×(a' + b')``): ``f' = g' + δ×g_0/2 −
    (m/2) e'×a_0``. Equal to the forward-mode derivative to rounding (tested); it replaced
    it because differentiating (and batching the derivative of) the traced residual cost
    ~0.4 s of tracing in every program (measured)."""
    m, M, rho, J = prm["m"], prm["M"], prm["rho"], prm["J"]
    inv_mass = 1.0 / (m + M)
    a0 = tuple((R0[0][j] * p[0] + R0[1][j] * p[1]) * inv_mass for j in range(3))
    if kind != "lgvi":
        g0 = tuple(m * x for x in _cross(rho, a0))
    cols = []
    for j in range(3):
        ep = _unit_cross(j, rho)
        up = tuple(-(m / h) * inv_mass * _dot(R0[i], ep) for i in range(2))
        ap = tuple(R0[0][k] * up[0] + R0[1][k] * up[1] for k in range(3))
        Jd = tuple(J[i][j] / h for i in range(3))
        if kind == "lgvi":
            cols.append(_comb((1.0, Jd), (m, _cross(rho, ap))))
        else:
            bp = _comb((1.0, ap), (-1.0, _unit_cross(j, a0)))
            gp = _comb((1.0, Jd), (0.5 * m, _cross(rho, _comb((1.0, ap), (1.0, bp)))))
            cols.append(_comb((1.0, gp), (0.5, _unit_cross(j, g0)),
                              (-0.5 * m, _cross(ep, a0))))
    return tuple(cols[j][i] for i in range(3) for j in range(3))


def _invert3(jac, one=None):
    """The inverse of a 3x3 matrix (row-major entries) by cofactors. ``one``: a runtime
    one, to :func:`_materialize` the entries first (each is read by several cofactors)."""
    if one is not None:
        jac = _materialize(jac, one)
    (j00, j01, j02), (j10, j11, j12), (j20, j21, j22) = jac[:3], jac[3:6], jac[6:]
    k00 = j11 * j22 - j12 * j21
    k01 = j12 * j20 - j10 * j22
    k02 = j10 * j21 - j11 * j20
    idet = 1.0 / (j00 * k00 + j01 * k01 + j02 * k02)
    return (idet * k00, idet * (j02 * j21 - j01 * j22), idet * (j01 * j12 - j02 * j11),
            idet * k01, idet * (j00 * j22 - j02 * j20), idet * (j02 * j10 - j00 * j12),
            idet * k02, idet * (j01 * j20 - j00 * j21), idet * (j00 * j11 - j01 * j10))


def _materialize(xs, one):
    """``xs`` unchanged (``x / 1`` is exact), each divided by a runtime one (``h / h``),
    which XLA cannot fold. XLA's fusion pass does not duplicate a division into several
    consumers, so each ``x`` becomes one kernel's output, computed once, instead of being
    recomputed inside every kernel that reads it. Under ``vmap`` the Newton update read the
    residual in six kernels (three components of the update, three of its size), so the
    residual was evaluated six times per iteration; materialised, the batched steps are
    1.5-1.6x faster (measured). The same holds for the chord matrix: its nine entries each
    recomputed the whole Jacobian (then three forward-mode tangents of the residual), and each
    Broyden entry the products ``Hy`` and ``sᵀH``. Materialising the residual, the
    Jacobian's rows and Broyden's products cut the optimised batched program from 9290 to
    6350 HLO lines (one trajectory's: 13299 to ~8000) and, measured alternating with the
    unmaterialised version (fresh processes, 2 devices, hamel-exact): compilation 0.5-1.3 s
    faster batched and ~1 s alone (1.6 instead of 2.6-2.9 s), runs 6-15 % faster batched and
    10-15 % alone. (For one trajectory, before the whole rollout was compiled as one
    function (:mod:`lgvi_jax._xla`), materialising the residual was 2x slower: a kernel cost
    more than the arithmetic it saved.)"""
    return tuple(x / one for x in xs)


# loop status
_RUNNING, _CONVERGED, _NEWTON, _NONFINITE = 0, 1, 2, 3
#: The chord loop hands over to Broyden when an update is not below this fraction of the
#: previous one. 0.5 (halving) let slowly contracting chords run to the iteration cap at
#: h = 0.05-0.1 (1-17 of 256 perturbed trajectories failed per method); 0.25 converges all
#: of them in 12-14 iterations on average instead of 16-19, and changes nothing at
#: h = 5e-3 (contraction ~0.03).
_CONTRACTION = 0.25


def _newton_update(H, w, fw, h, tol):
    """``w − H f(w)`` and the update's size ``max_i |Δw_i| / (h + |w_i|) / tol``."""
    d = tuple(-(H[3 * i] * fw[0] + H[3 * i + 1] * fw[1] + H[3 * i + 2] * fw[2])
              for i in range(3))
    new = tuple(wi + di for wi, di in zip(w, d, strict=True))
    size = jnp.maximum(jnp.maximum(jnp.abs(d[0]) / (h + jnp.abs(new[0])),
                                   jnp.abs(d[1]) / (h + jnp.abs(new[1]))),
                       jnp.abs(d[2]) / (h + jnp.abs(new[2]))) / tol
    return new, size


def _broyden(H, s, y, one):
    """Broyden's ("good") update of an inverse Jacobian ``H`` (row-major) for the secant
    pair ``s = Δw``, ``y = Δf``: ``H + (s − Hy)(sᵀH)/(sᵀHy)`` (Sherman–Morrison form; Dennis
    & Schnabel, *Numerical Methods for Unconstrained Optimization*, §8.1). ``H`` unchanged
    where ``sᵀHy`` is 0 (``s = 0`` at the first iterate) or not finite. ``Hy``, ``sᵀH`` and
    the scale, each read by several entries, are materialised (:func:`_materialize`, with
    the runtime one ``one``)."""
    Hy = _materialize(tuple(H[3 * i] * y[0] + H[3 * i + 1] * y[1] + H[3 * i + 2] * y[2]
                            for i in range(3)), one)
    sH = _materialize(tuple(s[0] * H[j] + s[1] * H[3 + j] + s[2] * H[6 + j]
                            for j in range(3)), one)
    den = _dot(s, Hy)
    ok = (den != 0) & jnp.isfinite(den)
    inv = _materialize((jnp.where(ok, 1.0 / jnp.where(ok, den, 1.0), 0.0),), one)[0]
    return tuple(H[3 * i + j] + (s[i] - Hy[i]) * (sH[j] * inv)
                 for i in range(3) for j in range(3))


def _restart(f, Ji0, h, tol, one, shape, dtype):
    """Where Broyden's loop starts when the chord stalls: the chord's first iterate
    ``w_1 = −J_0⁻¹ f(0)`` (about ``hΩ_k``, the general engine's start) and the inverse of
    the Jacobian there (:func:`_jacobian`). Restarting there instead of continuing from the
    chord's last iterate with its matrix: at h = 0.2 on 256 trajectories perturbed by 0.3
    (50 steps), the trajectories converged went from 25 to 245 (``hamel``), 173 to 256
    (``hamel-cayley``) and 4 to 256 (``hamel-exact``); from ``w_1`` with the chord's matrix,
    184, 248 and 188 (measured)."""
    z = tuple(jnp.zeros(shape, dtype) for _ in range(3))
    w1, _ = _newton_update(Ji0, z, _materialize(f(z), one), h, tol)
    return w1, _invert3(_jacobian(f, w1), one)


def _status(size, prev, chord: bool):
    """The loop status after an update of ``size`` (the previous one ``prev``): converged;
    running; in the chord loop, stalled (not below :data:`_CONTRACTION` of the previous
    update, or not finite) -> Broyden; in the Broyden loop, not finite -> failed."""
    if chord:
        st = jnp.where(size <= 1.0, _CONVERGED,
                       jnp.where(jnp.isfinite(size) & (size <= _CONTRACTION * prev), _RUNNING,
                                 _NEWTON))
    else:
        st = jnp.where(size <= 1.0, _CONVERGED,
                       jnp.where(jnp.isfinite(size), _NEWTON, _NONFINITE))
    return st


def _solve(f, h, tol, max_steps, dtype, jac=None, shape=None, restart=True):
    """``w`` with ``f(w) = 0`` (module docstring): ``(w, iterations, status)``, for one
    trajectory or an explicit batch (every quantity an array of the batch's shape, each
    trajectory's iteration masked once it stops, the loops running while any is active).
    ``jac``: ``∂f/∂w`` at ``w = 0`` (row-major), for the chord matrix (default: by
    :func:`_jacobian`); ``shape``: the batch's shape (default: ``f(0)``'s); ``restart``:
    Broyden from :func:`_restart`, else from the chord's last iterate with its matrix."""
    one = h / h
    zero = tuple(jnp.zeros((), dtype) for _ in range(3))
    Ji0 = _invert3(_jacobian(f, zero) if jac is None else jac, one)
    shape = jnp.shape(f(zero)[0]) if shape is None else shape

    def masked(active, new, old):
        return jax.tree.map(lambda a, b: jnp.where(active, a, b), new, old)

    def chord(carry):
        w, it, prev, status = carry
        active = (status == _RUNNING) & (it < max_steps)
        new, size = _newton_update(Ji0, w, _materialize(f(w), one), h, tol)
        new = tuple(jnp.where(jnp.isfinite(size), a, b) for a, b in zip(new, w, strict=True))
        st = _status(size, prev, chord=True).astype(jnp.int32)
        return masked(active, (new, it + 1, size, st), carry)

    def broyden(carry):
        (w, it, _, status), (wp, fp, H) = carry
        active = (status == _NEWTON) & (it < max_steps)
        fw = _materialize(f(w), one)
        H = _broyden(H, tuple(a - b for a, b in zip(w, wp, strict=True)),
                     tuple(a - b for a, b in zip(fw, fp, strict=True)), one)
        new, size = _newton_update(H, w, fw, h, tol)
        st = _status(size, None, chord=False).astype(jnp.int32)
        return masked(active, ((new, it + 1, size, st), (w, fw, H)), carry)

    def going(want):
        return lambda c: jnp.any((c[3] == want) & (c[1] < max_steps))

    init = (tuple(jnp.zeros(shape, dtype) for _ in range(3)), jnp.zeros(shape, jnp.int32),
            jnp.full(shape, jnp.inf, dtype), jnp.full(shape, _RUNNING, jnp.int32))
    carry = jax.lax.while_loop(going(_RUNNING), chord, init)

    def fallback(carry):
        # Broyden from the restart point (:func:`_restart`; s = 0 skips the first update)
        # for the trajectories whose chord stalled.
        if restart:
            w1, H = _restart(f, Ji0, h, tol, one, shape, dtype)
            w = tuple(jnp.where(carry[3] == _NEWTON, a, b) for a, b in zip(w1, carry[0],
                                                                            strict=True))
        else:
            w, H = carry[0], tuple(jnp.broadcast_to(x, shape) for x in Ji0)
        secant = (w, tuple(jnp.zeros(shape, dtype) for _ in range(3)), H)
        return jax.lax.while_loop(lambda c: going(_NEWTON)(c[0]), broyden,
                                  ((w, *carry[1:]), secant))[0]

    # Entered only when needed: setting up its state every step (an empty loop) cost 20-25 %
    # of the batched throughput (measured, hamel-exact; for one trajectory, whose packed
    # state is small, a cond measured no faster).
    w, it, _, status = jax.lax.cond(going(_NEWTON)(carry), fallback, lambda c: c, carry)
    return w, it, status


def _solve_packed(f, h, tol, max_steps, dtype, jac=None, restart=True):
    """:func:`_solve` with the loop state packed in one array ``(w, size, status,
    iterations)`` (and, in the Broyden loop, the previous iterate, its residual and the
    inverse), the chord inverse in another: for one trajectory, where XLA makes a kernel of
    every separate loop value and the kernels' count, not their arithmetic, sets the speed
    (measured 2.8x faster than :func:`_solve` for one trajectory, 4-30x slower under
    ``vmap``, whose strided columns do not vectorise)."""
    one = h / h
    zero = tuple(jnp.zeros((), dtype) for _ in range(3))
    Ji0 = _invert3(_jacobian(f, zero) if jac is None else jac, one)

    def chord(c):
        w = (c[0], c[1], c[2])
        new, size = _newton_update(Ji0, w, _materialize(f(w), one), h, tol)
        w = tuple(jnp.where(jnp.isfinite(size), a, b) for a, b in zip(new, w, strict=True))
        return jnp.stack([*w, size, _status(size, c[3], chord=True).astype(dtype), c[5] + 1])

    def broyden(c):
        w, wp, fp, H = (c[0], c[1], c[2]), (c[6], c[7], c[8]), (c[9], c[10], c[11]), c[12:]
        fw = _materialize(f(w), one)
        H = _broyden(H, tuple(a - b for a, b in zip(w, wp, strict=True)),
                     tuple(a - b for a, b in zip(fw, fp, strict=True)), one)
        new, size = _newton_update(H, w, fw, h, tol)
        return jnp.stack([*new, size, _status(size, None, chord=False).astype(dtype),
                          c[5] + 1, *w, *fw, *H])

    def going(want):
        return lambda c: (c[4] == want) & (c[5] < max_steps)

    def restart_at(c):
        w1, H = _restart(f, Ji0, h, tol, one, (), dtype)
        return jnp.concatenate([jnp.stack(w1), c[3:], jnp.stack(w1), jnp.zeros(3, dtype),
                                jnp.stack(H)])

    def done(c):
        return jnp.concatenate([c, jnp.zeros(15, dtype)])

    init = jnp.array([0.0, 0.0, 0.0, jnp.inf, _RUNNING, 0.0], dtype)
    c = jax.lax.while_loop(going(_RUNNING), chord, init)
    if restart:
        c = jax.lax.cond(c[4] == _NEWTON, restart_at, done, c)
    else:
        c = jnp.concatenate([c, c[:3], jnp.zeros(3, dtype), jnp.stack(Ji0)])
    c = jax.lax.while_loop(going(_NEWTON), broyden, c)
    return (c[0], c[1], c[2]), c[5].astype(jnp.int32), c[4].astype(jnp.int32)


def _step_arrays(kind, tol, max_steps, layout, R, mu, q, p, m, M, g, rho_c, J, h):
    """One step on the state's arrays: ``(R1, mu1, q1, iterations, status, residual)``.
    ``layout``: ``"packed"`` (one trajectory, :func:`_solve_packed`), ``"soa"`` (one
    trajectory to be ``vmap``ped, :func:`_solve`) or ``"batch"`` (an explicit batch on the
    leading axis, :func:`_solve`; the ``cond`` of :func:`_coeffs` is then batch-wide)."""
    dtype = R.dtype
    hg = 0.5 * h * m * g

    def unpack():
        R0 = tuple(tuple(R[..., i, j] for j in range(3)) for i in range(3))
        mu0 = tuple(mu[..., i] for i in range(3))
        prm = {"m": m, "M": M, "rho": tuple(rho_c[..., i] for i in range(3)),
               "J": tuple(tuple(J[..., i, j] for j in range(3)) for i in range(3))}
        K = _comb((1.0, mu0), (hg, _cross(prm["rho"], R0[2])))
        return prm, R0, K, tuple(p[..., i] for i in range(2))

    prm, R0, K, p0 = unpack()
    if layout == "packed":
        # The state's components are sliced inside the Newton loop: sliced outside, every
        # scalar is a separate loop operand, materialised by its own kernel (20 kernels a
        # step; measured 12 % faster for lgvi inside).
        def residual(w):
            prm_, R0_, K_, p0_ = unpack()
            return _equations_once(kind, prm_, h, R0_, K_, p0_, w)[0]
    else:
        def residual(w):
            return _equations_once(kind, prm, h, R0, K, p0, w)[0]

    jac = _chord_jacobian(kind, prm, h, R0, p0)
    # The Broyden restart (:func:`_restart`) for the Hamel methods; for ``lgvi`` it converged
    # no more trajectories (h = 0.12: 241 against 240 of 256, h = 0.15: 69 against 70) and
    # under JAX's batching of its loops (lgvi's batched layout) a batched ``cond`` runs both
    # branches: 28 % slower at h = 5e-3 (measured).
    restart = kind != "lgvi"
    if layout == "packed":
        w, its, status = _solve_packed(residual, h, tol, max_steps, dtype, jac, restart)
    else:
        shape = jnp.broadcast_shapes(R.shape[:-2], mu.shape[:-1], q.shape[:-1], p.shape[:-1],
                                     *(jnp.shape(x) for x in (m, M, g, h)),
                                     rho_c.shape[:-1], J.shape[:-2])
        w, its, status = _solve(residual, h, tol, max_steps, dtype, jac, shape, restart)
    res, u, nxt, c1, c2 = _equations_once(kind, prm, h, R0, K, p0, w)
    # R_{k+1} = R_k F,  F = I + c_1 ŵ + c_2 (w wᵀ − θ² I)
    dg = 1.0 - c2 * _dot(w, w)
    W = ((0.0, -w[2], w[1]), (w[2], 0.0, -w[0]), (-w[1], w[0], 0.0))
    F = tuple(tuple((dg if i == j else 0.0) + c2 * w[i] * w[j] + c1 * W[i][j]
                    for j in range(3)) for i in range(3))
    R1 = tuple(tuple(_dot(R0[i], tuple(F[k][j] for k in range(3))) for j in range(3))
               for i in range(3))
    mu1 = _comb((1.0, nxt), (hg, _cross(prm["rho"], R1[2])))
    residual_norm = jnp.maximum(jnp.maximum(jnp.abs(res[0]), jnp.abs(res[1])),
                                jnp.abs(res[2]))
    return (jnp.stack([jnp.stack(row, -1) for row in R1], -2), jnp.stack(mu1, -1),
            q + h * jnp.stack(u, -1), its, status, residual_norm)


@functools.cache
def _stepper(kind: str, tol: float, max_steps: int):
    """:func:`_step_arrays` with the loop layout chosen by batching (``custom_vmap``): the
    packed loop for one trajectory, the structure-of-arrays loop under ``vmap``."""
    one = functools.partial(_step_arrays, kind, tol, max_steps, "packed")
    # lgvi: JAX's batching of the per-trajectory loop (measured 20-25 % faster than the
    # explicit batch); the Hamel methods: the explicit batch (hamel-cayley 15 % faster; for
    # the exp maps its cond skips sin and cos: 1.6x faster).
    explicit = kind != "lgvi"
    many = jax.jit(functools.partial(_step_arrays, kind, tol, max_steps,
                                     "batch" if explicit else "soa"))
    fn = jax.custom_batching.custom_vmap(one)

    @fn.def_vmap
    def _batched(axis_size, in_batched, *args):
        # Batched arguments carry the batch on axis 0; the step is elementwise in the
        # trajectories, so it runs on the whole batch at once (NumPy broadcasting), and
        # every output is broadcast to the batch.
        if explicit:
            out = many(*args)
        else:
            out = jax.vmap(many, in_axes=tuple(0 if b else None for b in in_batched))(*args)
        shapes = ((3, 3), (3,), (2,), (), (), ())
        return (tuple(jnp.broadcast_to(o, (axis_size, *sh)) for o, sh in
                      zip(out, shapes, strict=True)), (True,) * len(out))

    return fn


class FusedCarPendulum(AbstractIntegrator):
    """A car-pendulum VI step in fused scalar form (module docstring): ``method`` is
    ``"lgvi"``, ``"hamel"``, ``"hamel-cayley"`` or ``"hamel-exact"``, the discrete
    equations of the general method of that name (:meth:`general`)."""

    method: str = eqx.field(static=True, default="lgvi")
    #: Stop when ``|Δw_i| <= tol (h + |w_i|)``. Tighter than the general engine's 1e-12
    #: because the chord iteration converges linearly, so the error left after the last
    #: update is comparable to it: with 1e-12 the vertical angular momentum drifted 2e-12
    #: to 9e-12 over 5000-10000 steps, with 1e-14 7.7e-14 to 2.2e-13 (the general engine:
    #: 4e-14 to 6e-14), for one iteration more (9 at h = 5e-3).
    tol: float = eqx.field(static=True, default=1e-14)
    max_steps: int = eqx.field(static=True, default=40)

    order: ClassVar[int] = 2
    symmetric: ClassVar[bool] = True
    implicit: ClassVar[bool] = True

    def __check_init__(self):
        if self.method not in KINDS:
            raise ValueError(f"FusedCarPendulum: method must be one of {tuple(KINDS)}, got "
                             f"{self.method!r}")
        if not self.tol > 0:
            raise ValueError(f"FusedCarPendulum: tol must be > 0, got {self.tol!r}")
        if not (isinstance(self.max_steps, int) and self.max_steps >= 1):
            raise ValueError(f"FusedCarPendulum: max_steps must be an int >= 1, got "
                             f"{self.max_steps!r}")

    def general(self) -> AbstractIntegrator:
        """The general-engine method with the same discrete equations."""
        return KINDS[self.method]()

    @property
    def name(self) -> str:
        return self.method

    @property
    def symplectic(self) -> bool:
        return self.general().symplectic

    def describe(self) -> str:
        return super().describe() + ", fused car-pendulum step"

    def check_model(self, model) -> None:
        if not isinstance(model, CarPendulum):
            raise ValueError(f"FusedCarPendulum: model must be a CarPendulum, got "
                             f"{type(model).__name__}; use the general methods "
                             "(lgvi_jax.RIGID_METHODS) for other models")

    def step(self, model, state: RigidState, dt):
        dtype = state.R.dtype
        R1, mu1, q1, its, status, residual_norm = _stepper(
            self.method, self.tol, self.max_steps)(
            state.R, state.mu, state.q, state.p, *(jnp.asarray(x, dtype) for x in (
                model.m, model.M, model.g, model.rho_c, model.J, dt)))
        new_state = RigidState(R=R1, mu=mu1, q=q1, p=state.p)
        result = jnp.where(status == _CONVERGED, RESULTS.successful,
                           jnp.where(status == _NONFINITE, RESULTS.nonfinite,
                                     RESULTS.max_steps_reached)).astype(jnp.int32)
        return new_state, StepInfo(newton_steps=its, result=result, residual=residual_norm)


ENGINES = ("auto", "general", "fused", "scalar")


def fused_method(name: str, model, engine: str = "auto",
                 chord: str = "exact") -> FusedCarPendulum | None:
    """The fused step for method ``name`` on ``model`` under the engine choice ``engine``
    (``"auto"``: fused where one exists, ``"general"``/``"scalar"``: never, ``"fused"``:
    required), or
    ``None`` for the general engine. ``chord`` is the general engine's chord matrix: asking
    for ``"mass"`` explicitly selects the general engine under ``"auto"``. Raises
    ``ValueError`` (naming the option) when ``engine="fused"`` cannot be honoured."""
    if engine not in ENGINES:
        raise ValueError(f"--engine must be one of {', '.join(ENGINES)}, got {engine!r}")
    available = name in KINDS and isinstance(model, CarPendulum)
    if engine == "fused":
        if not available:
            raise ValueError(f"--engine fused: only the car-pendulum's {', '.join(KINDS)} "
                             f"have a fused step, not {name!r} on {type(model).__name__}; "
                             "use --engine auto or general")
        if chord != "exact":
            raise ValueError("--engine fused: --chord applies to the general engine only; "
                             "drop --chord or use --engine general")
        return FusedCarPendulum(name)
    if engine in ("general", "scalar") or not available or chord != "exact":
        return None
    return FusedCarPendulum(name)


__all__ = ["ENGINES", "KINDS", "FusedCarPendulum", "fused_method"]
