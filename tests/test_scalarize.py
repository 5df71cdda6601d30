"""The scalarising transform and the Newton iteration on scalars.

Oracles: the original JAX functions (scalarised programs compute the same arithmetic, only
the order of the additions inside a sum of products may differ), the array form of the
Newton iteration, central finite differences.

Tolerances: a sum of ``n`` products computed in another order differs by at most
``n * eps * sum |terms|`` (Higham, *Accuracy and Stability of Numerical Algorithms*, ch. 4);
the functions below have ``n <= 27`` terms of size <= 1e2, so 1e-11 absolute is a bound with
margin (the measured differences are 0 to 4e-16 on values of order 1).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lgvi_jax as lj
from lgvi_jax import so3
from lgvi_jax.integrators import with_scalar_newton
from lgvi_jax.integrators.lie import LGVI, HamelVI
from lgvi_jax.models.rigid import AbstractRigidBodyModel
from lgvi_jax.models.rigid_bodies import rotational_kinetic
from lgvi_jax.newton import Newton, newton_solve
from lgvi_jax.scalarize import ScalarFunction, join, program_for, scalarize, split
from lgvi_jax.trajectory import RESULTS

ROUNDING = 1e-11  # module docstring


def _rand(key, shape):
    return jax.random.normal(jax.random.PRNGKey(key), shape, dtype=jnp.float64)


FUNCTIONS = {
    "matmul_transpose": lambda A, B, v: (A @ B.T) @ v,
    "einsum_batch": lambda A, B, v: jnp.einsum("ij,jk->ik", A, B) + jnp.outer(v, v),
    "reductions": lambda A, B, v: (jnp.sum(A, axis=0), jnp.max(B, axis=1), jnp.min(v),
                                   jnp.trace(A @ B)),
    "slices_concat": lambda A, B, v: jnp.concatenate([A[1:, :2].reshape(-1), v[::2],
                                                      B[2]]),
    "stack_split": lambda A, B, v: jnp.stack(jnp.split(A @ v, [1])[1]) * v[0],
    "where_trig": lambda A, B, v: jnp.where(v > 0, jnp.sin(v) * jnp.sqrt(jnp.abs(v)),
                                            jnp.cos(A[0]) ** 2),
    "cross_hat_eye": lambda A, B, v: so3.hat(v) @ (A[0] + jnp.eye(3)[1]) + jnp.cross(v, B[1]),
    "so3_maps": lambda A, B, v: (so3.exp(v), so3.cayley(v), so3.dexp_inv(0.3 * v)),
    "grad_of_energy": lambda A, B, v: jax.grad(
        lambda w: rotational_kinetic(A @ A.T + 3 * jnp.eye(3), so3.hat(w)) + jnp.sum(B @ w))(v),
    "jacfwd": lambda A, B, v: jax.jacfwd(lambda w: jnp.tanh(A @ w) * jnp.exp(-w))(v),
    "cond": lambda A, B, v: jax.lax.cond(v[0] > 0, lambda x: x @ A, lambda x: -x, v),
}


@pytest.mark.parametrize("name", sorted(FUNCTIONS))
def test_scalarized_functions_equal_the_originals(name):
    fn = FUNCTIONS[name]
    args = (_rand(0, (3, 3)), _rand(1, (3, 3)), _rand(2, (3,)))
    expected = jax.jit(fn)(*args)
    got = jax.jit(scalarize(fn))(*args)
    for e, g in zip(jax.tree.leaves(expected), jax.tree.leaves(got), strict=True):
        assert g.shape == e.shape and g.dtype == e.dtype
        np.testing.assert_allclose(g, e, rtol=0, atol=ROUNDING)


def test_scalarize_commutes_with_vmap_and_traced_closures():
    A = _rand(3, (5, 3, 3))
    v = _rand(4, (5, 3))

    def f(A, v, c):
        return jnp.sin(A @ v) * c

    c = jnp.asarray(1.7)
    expected = jax.vmap(f, in_axes=(0, 0, None))(A, v, c)
    got = jax.jit(jax.vmap(scalarize(f), in_axes=(0, 0, None)))(A, v, c)
    np.testing.assert_allclose(got, expected, rtol=0, atol=ROUNDING)

    # a function that closes over a traced value (its jaxpr has a traced constant)
    @jax.jit
    def outer(A, v, c):
        return scalarize(lambda A, v: f(A, v, c))(A, v)

    np.testing.assert_allclose(jax.vmap(outer, in_axes=(0, 0, None))(A, v, c), expected,
                               rtol=0, atol=ROUNDING)


def test_structural_zeros_are_folded_away():
    # hat(w) @ v is the cross product: 6 products and 3 differences once the zeros of the
    # hat map are folded (the matrix product alone would emit 27 products and 18 sums).
    w = v = jnp.zeros(3)
    sf = ScalarFunction(lambda w, v: so3.hat(w) @ v, w, v)
    assert sf.size <= 9 + 3  # and at most one negation per component
    # gradients of a quadratic form keep only the Hessian's structure
    J = jnp.diag(jnp.array([1.0, 2.0, 3.0]))
    sf = ScalarFunction(lambda w: jax.grad(lambda x: 0.5 * x @ (J @ x))(w), w)
    out = sf(split(jnp.array([1.0, 1.0, 1.0])))
    np.testing.assert_allclose([float(x) for x in out], [1.0, 2.0, 3.0])


def test_common_subexpressions_are_merged_and_dead_code_removed():
    # x*y and y*x are one product, the sine is never read: one product, one sum remain,
    # and the value is that of the original function.
    def f(x, y):
        unused = jnp.sin(x)  # noqa: F841
        return x * y + y * x

    sf = ScalarFunction(f, 1.0, 2.0)
    assert sf.size == 2
    assert float(sf(split(jnp.asarray(3.0)), split(jnp.asarray(5.0)))[()]) == 30.0


def _primitives(jaxpr):
    """The primitives of ``jaxpr``, also those of the branches of a cond."""
    out = set()
    for e in jaxpr.eqns:
        out.add(e.primitive.name)
        for p in e.params.values():
            for sub in p if isinstance(p, tuple | list) else (p,):
                if hasattr(sub, "eqns") or hasattr(sub, "jaxpr"):
                    out |= _primitives(getattr(sub, "jaxpr", sub))
    return out


def test_a_cond_stays_a_branch_on_one_member_and_selects_on_a_batch():
    """A scalar program keeps a ``cond`` of a traced predicate as a branch (one member:
    only the branch taken runs; the so3 maps' closed forms behind their Taylor series) and
    the same conds on the same operands once (``dexp_inv`` and ``dexp_left_inv`` share
    their coefficient). Replayed on a batch's vectors (the Newton solve's layout) with
    members on both sides of the predicate, and with all on one side, it equals ``vmap``
    of the function (same operations per member: bound ROUNDING)."""
    def f(w):
        return so3.dexp_inv(w), so3.dexp_left_inv(w), so3.exp_minus_identity(w)

    sf = ScalarFunction(f, jnp.zeros(3))
    conds = [e for e in sf.program.jaxpr.eqns if e.primitive.name == "cond"]
    assert len(conds) == 2  # one per angle and function of it: exp's pair, dexp_inv's
    single = jax.make_jaxpr(lambda w: join(sf(split(w))[0]))(jnp.ones(3))
    assert "cond" in _primitives(single.jaxpr)

    rng = np.random.default_rng(5)
    mixed = rng.normal(size=(16, 3)) * np.where(np.arange(16) % 2, 0.01, 1.0)[:, None]
    for w in (mixed, 0.01 * rng.normal(size=(16, 3)), rng.normal(size=(16, 3))):
        w = jnp.asarray(w)
        lanes = np.empty(3, dtype=object)
        for i in range(3):
            lanes[i] = w[:, i]
        got = sf(lanes, batched=True)
        expected = jax.vmap(f)(w)
        for g, e in zip(got, expected, strict=True):
            g = np.stack([np.broadcast_to(np.asarray(x), (16,)) for x in g.reshape(-1)], -1)
            np.testing.assert_allclose(g, np.asarray(e).reshape(16, -1), rtol=0,
                                       atol=ROUNDING)
        # one member: the branch taken
        one = sf(split(w[0]))
        for g, e in zip(one, f(w[0]), strict=True):
            np.testing.assert_allclose(np.asarray(join(g)), e, rtol=0, atol=ROUNDING)


def _car_pendulum_residual(method):
    """``method``'s Newton residual for the car-pendulum as a function of the flat unknowns
    ``(ξ, u)``, a point ``y`` and the arguments (the paper's state, h = 5e-3)."""
    model = lj.CarPendulum()
    s0 = model.default_state()
    args = (model, s0.R, s0.mu, s0.q, s0.p, jnp.asarray(5e-3))

    def flat(y, a):
        return jnp.concatenate(method._residual((y[:3], y[3:]), a))

    return flat, jnp.array([0.3, -0.2, 1.1, 0.05, -0.4]), args


@pytest.mark.parametrize("method", [LGVI(), HamelVI()], ids=["lgvi", "hamel"])
def test_newton_jacobian_program_is_the_smaller_mode_and_equals_jacfwd(method):
    """The scalar engine's Jacobian program is forward or reverse mode, whichever has fewer
    operations (the car-pendulum's lgvi: reverse, hamel: forward), and equals jax.jacfwd of
    the residual. Bound: each entry sums at most ~100 products of terms <= 1e3 here (masses,
    inertias, 1/h), in another order: 100 * eps * 1e3 = 2e-11, taken as 1e-10."""
    from lgvi_jax.newton import _scalar_jacobian

    flat, y, args = _car_pendulum_residual(method)
    chosen = _scalar_jacobian(flat, y, args)  # "auto"
    sizes = {mode: ScalarFunction(jac(flat), y, args).size
             for mode, jac in (("forward", jax.jacfwd), ("reverse", jax.jacrev))}
    assert chosen.size == min(sizes.values())
    assert sizes["reverse" if isinstance(method, LGVI) else "forward"] == chosen.size
    assert _scalar_jacobian(flat, y, args, method.jacobian_mode).size == chosen.size
    @jax.jit
    def evaluate(y, a):
        return join(np.asarray(chosen(split(y), jax.tree.map(split, a)), dtype=object))

    np.testing.assert_allclose(evaluate(y, args), jax.jit(jax.jacfwd(flat))(y, args),
                               rtol=0, atol=1e-10)


def test_on_unit_vectors_runs_each_direction_block_on_its_unit_vectors():
    """``ScalarFunction.on_unit_vectors`` of ``(x, d1, d2) -> (A(x) d1, B(x) d2)``: ``A(x)``
    and ``B(x)`` column by column (index j of each output: the unit vector e_j), the
    operations that read no direction outside the loops; a program with an operation that
    reads two direction blocks, or an output that reads another output's block, is refused
    by name."""
    def f(x, d1, d2):
        a = jnp.array([[x[0], 2.0 * x[1], jnp.sin(x[0])], [x[0] * x[1], 0.0, 1.0]])
        b = jnp.array([[jnp.exp(x[1]), x[0] ** 2], [3.0, x[0] - x[1]]])
        return a @ d1, b @ d2

    x = jnp.array([0.7, -0.3])
    sf = ScalarFunction(f, x, jnp.zeros(3), jnp.zeros(2))
    _, _, fixed, (first, second) = sf._split_by_directions(2)
    assert fixed and first and second  # sin, exp and the products of x: before the loops

    @jax.jit
    def columns(x):
        return sf.on_unit_vectors(split(x))

    (a_rows, b_rows) = columns(x)
    a = np.array([[0.7, -0.6, np.sin(0.7)], [0.7 * -0.3, 0.0, 1.0]])
    b = np.array([[np.exp(-0.3), 0.49], [3.0, 1.0]])
    # each output entry r holds [A(x) e_j]_r = A[r, j] at index j; bound: a few roundings
    np.testing.assert_allclose(np.stack(a_rows), a, rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(np.stack(b_rows), b, rtol=1e-15, atol=1e-15)

    def mixed(x, d1, d2):
        return x[0] * d1 + jnp.sum(d2), d2

    with pytest.raises(ValueError, match="reads two directions"):
        ScalarFunction(mixed, x, jnp.zeros(2), jnp.zeros(2)).on_unit_vectors(split(x))

    def swapped(x, d1, d2):
        return x[0] * d2, x[1] * d1

    with pytest.raises(ValueError, match="output 0 reads direction 1"):
        ScalarFunction(swapped, x, jnp.zeros(2), jnp.zeros(2)).on_unit_vectors(split(x))


@pytest.mark.parametrize("method", [LGVI(), HamelVI(variation="exact")],
                         ids=["lgvi", "hamel-exact"])
def test_jacobian_in_a_loop_over_unit_vectors_equals_jacfwd(method):
    """The chord matrix of a batch (``Newton(jacobian_loop=...)``): the residual's JVPs
    along the blocks of unknowns on their unit vectors (``ScalarFunction.on_unit_vectors``,
    a run-time loop per block) are ``jax.jacfwd`` of the residual, for one point, under
    ``vmap`` and on vectors over a batch (as a batched solve calls it). The operations run
    per column (those that read the block's direction) are fewer than half the unrolled
    Jacobian's, which is what shortens a batch's compilation, and run once per column they
    cost less than 1.5x the unrolled Jacobian (measured 1.17-1.28x). Bound: as for the
    unrolled program (1e-10)."""
    from lgvi_jax.newton import _scalar_jacobian, _scalar_tangent

    flat, y, args = _car_pendulum_residual(method)
    tangent = _scalar_tangent(flat, y, args)
    # Blocks of columns: the rotational three and the shape's two.
    _, _, _, (rotational, shape) = tangent._split_by_directions(2)
    unrolled = _scalar_jacobian(flat, y, args, method.jacobian_mode).size
    assert 3 * len(rotational) + 2 * len(shape) < 1.5 * unrolled
    assert len(rotational) + len(shape) < unrolled / 2

    def columns(y, a):  # [r, j]: entry r of the Jacobian's column j
        blocks = tangent.on_unit_vectors(split(y), jax.tree.map(split, a))
        return jnp.concatenate([jnp.stack(rows) for rows in blocks], axis=1)

    jacobian = jax.jit(jax.jacfwd(flat))
    np.testing.assert_allclose(jax.jit(columns)(y, args), jacobian(y, args), rtol=0,
                               atol=1e-10)
    ys = y + jnp.linspace(-0.2, 0.2, 4)[:, None]
    want = jax.vmap(jacobian, in_axes=(0, None))(ys, args)
    np.testing.assert_allclose(jax.jit(jax.vmap(columns, in_axes=(0, None)))(ys, args), want,
                               rtol=0, atol=1e-10)

    @jax.jit
    def on_lanes(ys, a):  # every scalar a vector over the batch (newton's lanes)
        y_s = np.empty((y.size,), dtype=object)
        for i in range(y.size):
            y_s[i] = ys[:, i]
        blocks = tangent.on_unit_vectors(y_s, jax.tree.map(split, a), batched=True)
        return jnp.concatenate([jnp.stack(rows) for rows in blocks], axis=1)

    np.testing.assert_allclose(jnp.moveaxis(on_lanes(ys, args), -1, 0), want, rtol=0,
                               atol=1e-10)


@pytest.mark.parametrize("model_fn", [lj.FreeRigidBody, lj.HeavyTop, lj.CarPendulum],
                         ids=["free-body", "heavy-top", "car-pendulum"])
def test_each_lie_vi_names_its_smaller_jacobian_mode(model_fn):
    """``jacobian_mode`` (what the scalar solve traces instead of both modes) is the mode
    with fewer operations for every model and variant: a change of the equations that
    turned it would show here, not as a silently slower step."""
    from lgvi_jax.newton import _scalar_jacobian

    model = model_fn()
    s0 = model.default_state()
    n = 3 + s0.q.shape[0]
    args = (model, s0.R, s0.mu, s0.q, s0.p, jnp.asarray(5e-3))
    y = jnp.linspace(-0.4, 0.6, n)
    for method in (LGVI(), HamelVI(), HamelVI(map="cayley"), HamelVI(variation="exact"),
                   HamelVI(map="cayley", variation="exact")):
        def flat(y, a, method=method):
            return jnp.concatenate(method._residual((y[:3], y[3:]), a))

        sizes = {mode: _scalar_jacobian(flat, y, args, mode).size
                 for mode in ("forward", "reverse")}
        assert sizes[method.jacobian_mode] == min(sizes.values()), (method.name, sizes)


def test_sin_cos_by_arithmetic():
    """``scalarize.sin_cos`` against long-double sine and cosine for |t| <= 100 and at
    special points. Bound: four roundings of ~2 eps in the polynomials and the reduction,
    each at most doubled by the two doublings, ~36 eps = 8e-15 absolute (10x the measured
    worst, 7e-16); relative 5e-15 where |t| < 1 (sin t ~ t; measured 5e-16)."""
    from lgvi_jax.scalarize import sin_cos

    t = np.concatenate([np.linspace(-100.0, 100.0, 200_001),
                        [np.pi, -np.pi, 2 * np.pi, 0.0, 1e-300, 5e-9, 0.1, 0.785]])
    s, c = (np.asarray(x) for x in jax.jit(jax.vmap(sin_cos))(jnp.asarray(t)))
    ref_s, ref_c = np.sin(t.astype(np.longdouble)), np.cos(t.astype(np.longdouble))
    assert float(np.max(np.abs(s - ref_s))) <= 8e-15
    assert float(np.max(np.abs(c - ref_c))) <= 8e-15
    small = (np.abs(t) < 1) & (t != 0)
    assert float(np.max(np.abs(s[small] / ref_s[small] - 1))) <= 5e-15
    assert s[t == 0][0] == 0.0 and c[t == 0][0] == 1.0
    bad = jax.vmap(sin_cos)(jnp.asarray([np.inf, -np.inf, np.nan]))
    assert not np.any(np.isfinite(np.asarray(bad)))  # failure as a value, not a number


def test_batched_replay_emits_sine_and_cosine_by_arithmetic():
    """Replayed under ``vmap`` a scalar program's float64 ``sin`` and ``cos`` become
    arithmetic (no sine left in the batched program), one trajectory keeps them; both
    equal the function (bounds: test_sin_cos_by_arithmetic, through one product)."""
    def f(w):
        return so3.exp(w)  # sin and cos in its closed branch (|w| >= 0.1)

    w = jnp.asarray(np.random.default_rng(3).normal(size=(64, 3)))
    sf = ScalarFunction(f, w[0])

    def replayed(x):
        return join(sf(split(x)))

    batched = jax.vmap(replayed)
    prims = _primitives(jax.make_jaxpr(batched)(w).jaxpr)
    assert "sin" not in prims and "cos" not in prims
    assert "sin" in _primitives(jax.make_jaxpr(replayed)(w[0]).jaxpr)  # in a branch
    np.testing.assert_allclose(batched(w), jax.vmap(f)(w), rtol=0, atol=2e-14)
    # exp's entries are sums of terms up to |w|²/2 ≈ 8 (|w| <= ~4 here): a few roundings
    # of ulp(8) = 1.8e-15 each.
    np.testing.assert_allclose(replayed(w[0]), f(w[0]), rtol=0, atol=1e-14)


def test_batched_replay_computes_an_angles_sine_and_cosine_once():
    """A batched replay evaluates ``sin t`` and ``cos t`` of the same ``t`` by one
    ``sin_cos`` (one range reduction, a ``round``, per angle), and a second angle gets its
    own; the values are those of ``sin_cos``, bit for bit."""
    from lgvi_jax.scalarize import sin_cos

    def f(t, u):
        return jnp.sin(t) * jnp.cos(t) + jnp.cos(t) ** 2 - jnp.sin(u)

    t, u = jnp.linspace(-3.0, 3.0, 16), jnp.linspace(0.5, 7.0, 16)
    sf = ScalarFunction(f, t[0], u[0])

    def replayed(t, u):
        return join(sf(split(t), split(u)))

    prims = [e.primitive.name for e in jax.make_jaxpr(jax.vmap(replayed))(t, u).jaxpr.eqns]
    assert prims.count("round") == 2

    def want(t, u):
        (s, c), (su, _) = sin_cos(t), sin_cos(u)
        return s * c + c ** 2 - su

    np.testing.assert_array_equal(jax.vmap(replayed)(t, u), jax.vmap(want)(t, u))


def test_on_scalars_equals_the_function_or_returns_it():
    """``on_scalars``: small arguments give the scalar program (same values to round-off,
    bound of the module docstring), large ones or an unsupported primitive the function
    itself."""
    from lgvi_jax.scalarize import ON_SCALARS_MAX_ENTRIES, on_scalars

    def f(A, v):
        return {"quad": v @ A @ v, "cross": jnp.cross(v, A[0])}

    A, v = _rand(1, (3, 3)), _rand(2, (3,))
    g = on_scalars(f, A, v)
    assert g is not f
    for k, want in f(A, v).items():
        np.testing.assert_allclose(jax.jit(g)(A, v)[k], want, rtol=0, atol=ROUNDING)
    n = ON_SCALARS_MAX_ENTRIES
    def norm2(x):
        return x @ x

    assert on_scalars(norm2, jnp.ones(n + 1)) is norm2
    assert on_scalars(norm2, jnp.ones(n)) is not norm2
    sort = on_scalars(jnp.sort, v)
    assert sort is jnp.sort


def test_only_floating_values_are_materialised():
    """A shared predicate as costly as a materialised value is left to XLA: dividing it by
    the runtime one would turn it into a float (``select`` then rejects it)."""
    from lgvi_jax import scalarize as sc

    def f(x):
        s, p = x, x > 0.5
        for i in range(sc.MATERIALIZE_COST):
            s = s * 1.5 + x
            p = (p | (x > 0.1 * i)) if i % 2 else (p & (x < 1.0 - 0.02 * i))
        return jnp.where(p, x, -x) + s, jnp.where(p, 2 * x, s)

    x = _rand(3, (8,))
    program = sc.ScalarFunction(f, x[0])
    assert program.keep  # s is materialised, p (as costly, read twice) is not
    assert all(jnp.issubdtype(v.aval.dtype, jnp.floating) for v in program.keep)
    g = jax.jit(jax.vmap(sc.on_scalars(f, x[0])))
    for got, want in zip(g(x), jax.vmap(f)(x), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-13, atol=0)  # the same operations


def test_unsupported_primitive_is_named():
    with pytest.raises(NotImplementedError, match="argmax"):
        scalarize(lambda x: jnp.argmax(x))(jnp.arange(3.0))


# --- Newton on scalars -----------------------------------------------------------------


def _system(y, a):
    # a well-conditioned nonlinear system with a dense Jacobian (diagonally dominant)
    M, b = a
    return M @ y + 0.1 * jnp.sin(y) * jnp.sum(y) - b


@pytest.mark.parametrize("chord_steps", [0, 8])
def test_scalar_newton_equals_the_array_iteration(chord_steps):
    n = 5
    M = 4.0 * jnp.eye(n) + 0.5 * _rand(5, (n, n))
    b = _rand(6, (n,))
    y0 = jnp.zeros(n)
    ref = newton_solve(_system, y0, (M, b), Newton(chord_steps=chord_steps))
    got = jax.jit(lambda y0, a: newton_solve(_system, y0, a,
                                             Newton(chord_steps=chord_steps, scalar=True)))(
        y0, (M, b))
    assert int(got.result) == RESULTS.successful
    assert int(got.newton_steps) == int(ref.newton_steps)
    # both stop at |Δy| <= 1e-12 (1 + |y|): the roots agree to that
    np.testing.assert_allclose(got.value, ref.value, rtol=0, atol=1e-11)
    np.testing.assert_allclose(_system(got.value, (M, b)), 0.0, atol=1e-12)


def test_scalar_newton_reports_failure_as_a_value():
    def no_root(y, a):
        return y * y + a  # no real root for a > 0

    y0 = jnp.array([0.7, 1.3])  # Newton's iterates for y² + 1 wander on the real line
    sol = newton_solve(no_root, y0, 1.0, Newton(scalar=True, max_steps=15))
    ref = newton_solve(no_root, y0, 1.0, Newton(max_steps=15))
    assert int(sol.result) == int(ref.result) == RESULTS.max_steps_reached
    sol = newton_solve(lambda y, a: jnp.log(y) - a, -jnp.ones(1), 0.0, Newton(scalar=True))
    assert int(sol.result) == RESULTS.nonfinite


def test_scalar_newton_gradients_equal_finite_differences():
    n = 4
    M = 4.0 * jnp.eye(n) + 0.5 * _rand(7, (n, n))
    b = _rand(8, (n,))

    def loss(M, b, scalar):
        return jnp.sum(newton_solve(_system, jnp.zeros(n), (M, b),
                                    Newton(chord_steps=8, scalar=scalar)).value ** 2)

    g_scalar = jax.grad(loss, argnums=(0, 1))(M, b, True)
    g_array = jax.grad(loss, argnums=(0, 1))(M, b, False)
    for s, a in zip(g_scalar, g_array, strict=True):
        np.testing.assert_allclose(s, a, rtol=1e-10, atol=1e-12)
    # central differences in b: truncation h^2 |f'''| ~ 1e-12, rounding eps |f| / h ~ 1e-10
    eps = 1e-6
    fd = np.array([(loss(M, b.at[i].add(eps), False) - loss(M, b.at[i].add(-eps), False))
                   / (2 * eps) for i in range(n)])
    np.testing.assert_allclose(g_scalar[1], fd, rtol=1e-7, atol=1e-9)


def test_a_differentiated_solve_builds_its_programs_once(monkeypatch):
    """The solve inside the JVP rule and the Jacobian at its solution share the
    residual's scalar programs (``newton._memo``): the Jacobian's two modes are traced
    once instead of twice (three times with checkpoints, whose first pass solves too), and
    the lowered gradient is the same program, text for text, as with every program built
    afresh."""
    import lgvi_jax.newton as newton_module

    n = 4
    M = 4.0 * jnp.eye(n) + 0.5 * _rand(7, (n, n))
    b = _rand(8, (n,))

    def loss(M, b):
        return jnp.sum(newton_solve(_system, jnp.zeros(n), (M, b),
                                    Newton(chord_steps=8, scalar=True)).value ** 2)

    built = []
    original = ScalarFunction.__init__

    def counting(self, fn, *example):
        original(self, fn, *example)
        built.append(self.size)

    monkeypatch.setattr(ScalarFunction, "__init__", counting)
    shared = jax.jit(jax.grad(loss)).lower(M, b).as_text()
    n_shared = len(built)
    monkeypatch.setattr(newton_module, "_memo", lambda kind, fn, y0, args, build: build())
    fresh = jax.jit(jax.grad(loss)).lower(M, b).as_text()
    n_fresh = len(built) - n_shared
    # the residual, both Jacobian modes, the reverse one with the residual (this system's
    # smaller mode) and the tangent's program; afresh, both modes once more for the
    # Jacobian at the solution
    assert (n_shared, n_fresh) == (5, 7)
    assert shared == fresh


# --- the Lie-group engine on scalars ----------------------------------------------------


class SpringTop(AbstractRigidBodyModel):
    """A model defined here, not in the package: a heavy top whose pivot slides on a
    vertical spring (one Euclidean coordinate), coupled through the pivot's motion."""

    J: jax.Array
    m: jax.Array
    k: jax.Array
    rho: jax.Array

    dof = 1

    def kinetic(self, R, Omega, q, v):
        Rw = R @ (Omega @ self.rho)
        return (rotational_kinetic(self.J, Omega) + 0.5 * self.m * v[0] ** 2
                + self.m * v[0] * Rw[2])

    def potential(self, R, q):
        return 0.5 * self.k * q[0] ** 2 - 9.81 * self.m * (q[0] + (R @ self.rho)[2])

    def state(self):
        R0 = so3.exp(jnp.array([0.3, -0.2, 0.1]))
        return self.state_from_velocities(R0, jnp.array([0.5, -1.0, 4.0]), jnp.array([0.1]),
                                          jnp.array([0.0]))


def _spring_top():
    return SpringTop(J=jnp.diag(jnp.array([1.2, 1.0, 0.4])), m=jnp.asarray(1.0),
                     k=jnp.asarray(30.0), rho=jnp.array([0.05, 0.0, 0.5]))


def _scalar(method):
    return eqx.tree_at(lambda m: m.newton, method,
                       dataclasses.replace(method.newton, scalar=True))


def _arrays(method):
    """The array engine, the reference of the scalar engine (the Lie-group VIs' default)."""
    return with_scalar_newton(method, False)


METHODS = {
    "lgvi": _arrays(LGVI()),
    "hamel": _arrays(HamelVI()),
    "hamel-cayley": _arrays(HamelVI(map="cayley")),
    "hamel-exact": _arrays(HamelVI(map="exp", variation="exact")),
}


def _max_state_diff(a, b):
    return max(float(jnp.max(jnp.abs(x - y), initial=0.0)) for x, y in
               zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


# hamel-cayley (Cayley, G with w, the paper's variations) here; lgvi (Cayley, G without w)
# in the composition test below, whose sub-steps are lgvi's steps on scalars (lgvi@4:
# 0.41 h four times, -0.66 h once) on the same model, against the array engine to the same
# bound; hamel-exact (exp map, exact variations) on every model below, hamel at large steps.
@pytest.mark.parametrize("name", ["hamel-cayley"])
def test_scalar_engine_equals_array_engine_on_the_car_pendulum(name):
    model = lj.CarPendulum()
    s0 = model.default_state()
    method = METHODS[name]
    ref, code_ref = lj.final_state(model, method, s0, 5e-3, 40)
    got, code = lj.final_state(model, _scalar(method), s0, 5e-3, 40)
    assert int(code) == int(code_ref) == 0
    # Both engines stop Newton at |Δξ| <= 1e-12 (1 + |ξ|) with |ξ| ~ 5: the increments
    # agree to ~1e-11 h per step; 40 steps of a system with Lyapunov time >> 0.2 s keep
    # the states within 40 * 1e-11 * h * |ξ| + rounding ~ 1e-12; bound 1e-10 (the
    # measured gap is 3e-15).
    assert _max_state_diff(got, ref) < 1e-10


@pytest.mark.parametrize("model_fn", [lj.FreeRigidBody, lj.HeavyTop, _spring_top],
                         ids=["free-rigid-body", "heavy-top", "spring-top"])
def test_scalar_engine_serves_every_model(model_fn):
    """Including a model defined in this test file (only energies and a state)."""
    model = model_fn()
    s0 = model.default_state()
    method = _arrays(HamelVI(map="exp", variation="exact"))
    ref, _ = lj.final_state(model, method, s0, 1e-2, 30)
    got, code = lj.final_state(model, _scalar(method), s0, 1e-2, 30)
    assert int(code) == 0
    assert _max_state_diff(got, ref) < 1e-10  # as above
    # and it conserves the model's momentum map like the array engine (free body: R μ)
    if isinstance(model, lj.FreeRigidBody):
        L0 = model.spatial_angular_momentum(s0)
        np.testing.assert_allclose(model.spatial_angular_momentum(got), L0, rtol=0,
                                   atol=64 * 30 * np.finfo(float).eps * float(
                                       jnp.linalg.norm(L0)))


def test_scalar_engine_batches_over_states_and_parameters():
    model = lj.HeavyTop()
    s0 = model.default_state()
    method = _scalar(LGVI())
    scales = jnp.array([0.9, 1.0, 1.1])

    def run(scale):
        m = eqx.tree_at(lambda m: m.J, model, model.J * scale)
        return lj.final_state(m, method, s0, 1e-2, 20)[0]

    batched = jax.vmap(run)(scales)
    for i, scale in enumerate(scales):
        one = run(scale)
        assert _max_state_diff(jax.tree.map(lambda x, i=i: x[i], batched), one) < 1e-12


def test_scalar_engine_gradients_equal_the_array_engine():
    model = lj.FreeRigidBody()  # the smallest program: the gradient compiles fastest
    s0 = model.default_state()

    def loss(J, method):
        m = eqx.tree_at(lambda m: m.J, model, J)
        traj = lj.simulate(m, method, s0, 2e-2, 10)
        return traj.state.mu[-1, 0] + traj.state.R[-1, 0, 2]

    g_array = jax.grad(loss)(model.J, _arrays(LGVI()))
    g_scalar = jax.grad(loss)(model.J, _scalar(LGVI()))
    # both are the implicit-function-theorem derivatives of the same solutions
    np.testing.assert_allclose(g_scalar, g_array, rtol=1e-8, atol=1e-10)


def test_large_steps_converge_as_with_the_pivoted_array_solve():
    """The block inverse does not pivot: at large steps (h = 0.2, perturbations of 30 %,
    where the paper's hamel loses about a fifth of the trajectories) exactly the same
    trajectories converge as with the array engine's pivoted elimination."""
    from lgvi_jax.sweep import initial_conditions, run_batch

    model = lj.CarPendulum()
    states = initial_conditions(model, model.default_state(), 64, 0.3, 1)
    method = _arrays(HamelVI())
    ok = [run_batch(model, m, states, 0.2, 30)["result"] == 0
          for m in (method, with_scalar_newton(method))]
    assert 0 < int(np.sum(ok[0])) < 64  # a regime where some fail
    np.testing.assert_array_equal(ok[1], ok[0])


def test_with_scalar_newton_selects_the_scalar_solve():
    # The Lie-group VIs solve on scalars by default; with_scalar_newton(m, False) on arrays.
    assert LGVI().newton.scalar and HamelVI().newton.scalar
    arrays = with_scalar_newton(LGVI(), False)
    assert not arrays.newton.scalar and arrays.newton.chord_steps == LGVI().newton.chord_steps
    assert with_scalar_newton(arrays) == LGVI()
    composed = with_scalar_newton(lj.compose(HamelVI(), order=4), False)
    assert not composed.base.newton.scalar and not composed._sub_step_method().newton.scalar
    assert with_scalar_newton(composed).base.newton.scalar
    # settings the scalar engine does not take: on arrays, and the flag says so
    assert not with_scalar_newton(LGVI(chord_matrix="mass")).newton.scalar
    assert not with_scalar_newton(lj.compose(LGVI(chord_matrix="mass"), order=4)).base.newton.scalar
    assert not lj.LieGalerkinVI().newton.scalar  # its scalar program compiles for minutes
    assert with_scalar_newton(lj.RKMK4()) == lj.RKMK4()
    with pytest.raises(TypeError, match="scalar must be True or False, got 'no'"):
        with_scalar_newton(LGVI(), "no")


def test_compositions_solve_on_scalars_and_equal_the_array_engine():
    """A composition's Lie-group sub-steps use the scalar engine by default (where the
    base's Newton settings allow it); the trajectory is the array engine's (bound as in the
    car-pendulum test above: 3 sub-steps per step, |γ| <= 1.36)."""
    model = lj.CarPendulum()
    s0 = model.default_state()
    fast = lj.compose(LGVI(), order=4)
    slow = dataclasses.replace(fast, scalar=False)
    assert fast._sub_step_method().newton.scalar
    assert not slow._sub_step_method().newton.scalar
    # settings the scalar engine does not take keep the base's own solver
    mass = lj.compose(LGVI(chord_matrix="mass"), order=4)
    assert not mass._sub_step_method().newton.scalar
    ref, code_ref = lj.final_state(model, slow, s0, 1e-2, 20)
    got, code = lj.final_state(model, fast, s0, 1e-2, 20)
    assert int(code) == int(code_ref) == 0
    assert _max_state_diff(got, ref) < 1e-10
    # (gradients through a scalar composition: tests/test_lie.py, lgvi@4 against finite
    # differences)


def test_the_sweep_equals_the_array_engine(tmp_path, capsys):
    """``lgvi-jax sweep`` (the autodiff engine on scalars) gives the metrics of the array
    engine's batched rollout on the same initial conditions, to round-off. (On the
    car-pendulum's ``hamel`` with 64 trajectories in one chunk: both run the batched
    programs of the large-step test above, whose step and step count are run-time values,
    so nothing is compiled again.)"""
    import csv

    from lgvi_jax.cli import main
    from lgvi_jax.sweep import initial_conditions, run_batch

    out = tmp_path / "sweep"
    assert main(["sweep", "car-pendulum", "--method", "hamel", "--dt", "0.01", "--t-final",
                 "1", "--n", "64", "--chunk", "64", "--perturb", "0.01", "--seed", "0",
                 "--out", str(out), "--json"]) == 0
    capsys.readouterr()
    with open(out / "trajectories.csv") as f:
        rows = sorted(csv.DictReader(f), key=lambda r: int(r["index"]))
    model = lj.CarPendulum()
    states = initial_conditions(model, model.default_state(), 64, 0.01, 0)
    ref = run_batch(model, _arrays(HamelVI()), states, 0.01, 100)
    assert len(rows) == 64
    for i, row in enumerate(rows):
        assert row["result"] == "0" and ref["result"][i] == 0
        # relative energy errors ~1e-2 (hamel at h = 0.01) computed from states that agree
        # to the Newton tolerance (both engines stop at updates <= 1e-12 (1 + |ξ|)):
        # measured 9e-12 relative, bound 1e-6
        assert float(row["energy_error_max"]) == pytest.approx(
            float(ref["energy_error_max"][i]), rel=1e-6, abs=1e-13)


def test_programs_are_built_once_per_function_and_shapes():
    """program_for: one scalar program per function (per instance for a bound method) and
    argument shapes; a different shape or instance gets its own; a function that closes
    over a traced value is not remembered (its program takes that value as an input)."""

    class Scaled:
        def __init__(self, k):
            self.k = k

        def __hash__(self):
            return hash(self.k)

        def __eq__(self, other):
            return isinstance(other, Scaled) and other.k == self.k

        def f(self, x):
            return self.k * jnp.cross(x, x[::-1])

    a, b = Scaled(2.0), Scaled(3.0)
    x3, x6 = jnp.ones(3), jnp.ones((2, 3))
    assert program_for(a.f, x3) is program_for(a.f, x3)
    assert program_for(a.f, x3) is not program_for(b.f, x3)
    assert program_for(a.f, x3) is not program_for(a.f, x6)
    x = jnp.array([0.3, -1.2, 0.7])
    # Values up to ~4: a few ulps of ulp(4) = 8.9e-16 if the operations are reordered.
    np.testing.assert_allclose(scalarize(b.f)(x), b.f(x), rtol=0, atol=1e-14)

    built = []

    @jax.jit
    def outer(c, x):
        g = lambda y: c * y  # noqa: E731  (closes over the traced c)
        built.append(program_for(g, x))
        return scalarize(g)(x)

    np.testing.assert_allclose(outer(2.0, x), 2.0 * x)
    assert built[0].traced_consts
