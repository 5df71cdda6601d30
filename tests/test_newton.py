"""Newton solver: convergence, result codes, errors, implicit differentiation."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lgvi_jax  # noqa: F401  (float64)
from lgvi_jax.linalg import ldl_solve, small_solve, spd_inverse, spd_solve
from lgvi_jax.newton import (
    CHORD_REFRESHES,
    ChordInverse,
    Newton,
    NewtonError,
    clear_scalar_programs,
    newton_solve,
    raise_if_failed,
)
from lgvi_jax.trajectory import RESULTS


def cubic(y, a):
    """Roots y_i = a_i^(1/3); Jacobian diag(3 y^2)."""
    return y**3 - a


def coupled(y, args):
    """A nonlinear 3x3 system with known root (1, 2, 3) when args = (1, 2, 3)."""
    x, yy, z = y
    a, b, c = args
    return jnp.stack([x**2 + yy - a**2 - b, yy * z - b * c, jnp.sin(z) + x - jnp.sin(c) - a])


@pytest.mark.parametrize("n", [1, 2, 3, 4, 6, 9, 12, 15])
def test_small_solve_matches_numpy(n):
    rng = np.random.default_rng(n)
    for _ in range(5):
        A = rng.normal(size=(n, n))
        b = rng.normal(size=n)
        x = jax.jit(small_solve)(jnp.asarray(A), jnp.asarray(b))
        np.testing.assert_allclose(A @ np.asarray(x), b, rtol=0, atol=1e-12 * np.linalg.cond(A))


def test_small_solve_needs_pivoting():
    # A zero leading entry: elimination without row exchanges would divide by zero.
    A = jnp.array([[0.0, 1.0, 2.0], [1.0, 0.0, 3.0], [4.0, -3.0, 8.0]])
    b = jnp.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(np.asarray(A @ small_solve(A, b)), np.asarray(b), atol=1e-14)


def test_small_solve_singular_is_nonfinite():
    A = jnp.array([[1.0, 2.0], [2.0, 4.0]])
    x = small_solve(A, jnp.array([1.0, 1.0]))
    assert not np.all(np.isfinite(np.asarray(x)))


def test_converges_quadratically_to_root():
    a = jnp.array([2.0, 27.0, 0.5])
    sol = newton_solve(cubic, jnp.ones(3), a)
    assert int(sol.result) == RESULTS.successful
    # Quadratic convergence leaves the last update's error far below round-off: the root to
    # a few ulps (the rounding of x³ − a over 3x²; measured 1.4e-16).
    np.testing.assert_allclose(np.asarray(sol.value), np.cbrt([2.0, 27.0, 0.5]), rtol=4e-15)
    # From 1 to 3 (root of 27) Newton needs a handful of steps; a linearly convergent method
    # would need dozens at this tolerance.
    assert int(sol.newton_steps) <= 9


def test_quadratic_convergence_rate():
    # Track errors per iteration by capping max_steps: e_{k+1} ~ C e_k^2.
    errors = []
    for k in range(1, 6):
        sol = newton_solve(cubic, jnp.array([1.0]), jnp.array([2.0]), Newton(max_steps=k))
        errors.append(abs(float(sol.value[0]) - np.cbrt(2.0)))
    errors = [e for e in errors if e > 1e-15]
    ratios = [errors[i + 1] / errors[i] ** 2 for i in range(len(errors) - 1)]
    assert len(ratios) >= 2
    # For f = y^3 - a the constant is f''/(2 f') = 1/y* ~ 0.8: bounded, not growing.
    assert max(ratios) < 2.0


def test_pytree_unknowns_and_coupled_system():
    sol = newton_solve(coupled, jnp.array([1.2, 1.7, 2.8]), jnp.array([1.0, 2.0, 3.0]))
    assert int(sol.result) == RESULTS.successful
    np.testing.assert_allclose(np.asarray(sol.value), [1.0, 2.0, 3.0], atol=1e-13)

    def fn(y, args):
        return {"u": y["u"] ** 2 - args, "v": y["v"] - y["u"]}

    sol = newton_solve(fn, {"u": jnp.array(1.0), "v": jnp.array(0.0)}, jnp.array(4.0))
    assert float(sol.value["u"]) == pytest.approx(2.0, rel=1e-15)
    assert float(sol.value["v"]) == pytest.approx(2.0, rel=1e-15)


def test_unsolvable_reports_max_steps():
    # y^2 + 1 = 0 has no real root: Newton wanders forever.
    sol = newton_solve(lambda y, a: y**2 + a, jnp.array([0.7]), jnp.array(1.0),
                       Newton(max_steps=25))
    assert int(sol.result) == RESULTS.max_steps_reached
    assert int(sol.newton_steps) == 25
    assert float(sol.residual) >= 1.0  # |y^2 + 1| >= 1 everywhere
    assert not bool(sol.ok)


def test_nonfinite_is_reported():
    # Starting at the critical point y = 0 of y^2 - 1 the Jacobian is singular.
    sol = newton_solve(lambda y, a: y**2 - a, jnp.array([0.0]), jnp.array(1.0))
    assert int(sol.result) == RESULTS.nonfinite
    # NaN input
    sol = newton_solve(cubic, jnp.array([jnp.nan]), jnp.array([1.0]))
    assert int(sol.result) == RESULTS.nonfinite
    assert int(sol.newton_steps) == 1


def test_throw_raises_with_numbers():
    with pytest.raises(NewtonError, match=r"did not converge.*iterations 5.*residual"):
        newton_solve(lambda y, a: y**2 + a, jnp.array([0.7]), jnp.array(1.0),
                     Newton(max_steps=5), throw=True)
    # A successful solve does not raise.
    newton_solve(cubic, jnp.ones(2), jnp.array([2.0, 3.0]), throw=True)


def test_throw_under_jit_raises_runtime_error():
    @eqx.filter_jit
    def solve(a):
        return newton_solve(lambda y, a: y**2 + a, jnp.array([0.7]), a, Newton(max_steps=5),
                            throw=True).value

    with pytest.raises(Exception, match="Newton solve failed"):
        jax.block_until_ready(solve(jnp.array(1.0)))


def test_raise_if_failed_passes_success_through():
    sol = newton_solve(cubic, jnp.ones(1), jnp.array([8.0]))
    assert raise_if_failed(sol) is sol


def test_chord_variant_converges_linearly():
    a = jnp.array([2.0, 3.0])
    full = newton_solve(cubic, jnp.array([1.2, 1.4]), a)
    chord = newton_solve(cubic, jnp.array([1.2, 1.4]), a, Newton(chord=True, max_steps=100))
    assert int(chord.result) == RESULTS.successful
    np.testing.assert_allclose(np.asarray(chord.value), np.asarray(full.value), rtol=1e-12)
    assert int(chord.newton_steps) > int(full.newton_steps)


def test_chord_phase_then_newton_fallback():
    """chord_steps: converges like chord when the chord contracts; otherwise falls back to
    full Newton from the initial guess and gives Newton's own answer."""
    a = jnp.array([2.0, 3.0])
    y0 = jnp.array([1.2, 1.4])
    full = newton_solve(cubic, y0, a)
    mixed = newton_solve(cubic, y0, a, Newton(chord_steps=30))
    assert int(mixed.result) == RESULTS.successful
    np.testing.assert_allclose(np.asarray(mixed.value), np.asarray(full.value), rtol=1e-12)
    # A guess far from the root: the chord iteration stalls (its Jacobian is poor there);
    # the fallback reaches the root Newton reaches.
    far = jnp.array([40.0, 0.05])
    full = newton_solve(cubic, far, a, Newton(max_steps=60))
    pure_chord = newton_solve(cubic, far, a, Newton(chord=True, max_steps=60))
    mixed = newton_solve(cubic, far, a, Newton(chord_steps=3, max_steps=60))
    assert int(full.result) == RESULTS.successful
    assert int(pure_chord.result) != RESULTS.successful
    assert int(mixed.result) == RESULTS.successful
    assert int(mixed.newton_steps) > int(full.newton_steps)  # chord iterations are counted too
    np.testing.assert_allclose(np.asarray(mixed.value), np.asarray(full.value), rtol=1e-12)


def _chord_refresh_model(f, jac, y0, chord_steps, max_steps, refreshes, tol=1e-12):
    """The documented ``chord_steps`` policy, written out in NumPy on one unknown:
    ``(iterations, Jacobian evaluations, y)``."""
    y, k, newton, used, res0, jacs = y0, 0, False, 0, None, 0
    while True:
        k_phase, J, prev = k, jac(y), np.inf
        jacs += 1
        while True:
            F = f(y)
            res0 = abs(F) if res0 is None else res0
            res, d = abs(F), -F / J
            y, k = y + d, k + 1
            size = abs(d) / (tol + tol * abs(y))
            if size <= 1.0:
                return k, jacs, y
            if newton:
                assert k < k_phase + 1 + max_steps
                break
            if k - k_phase >= chord_steps or size > 0.5 * prev:
                break
            prev = size
        if not newton:
            if used < refreshes and res < res0:
                used += 1
            else:
                y, newton = y0, True


@pytest.mark.parametrize("scalar, mode", [(False, "auto"), (True, "forward"),
                                          (True, "reverse")])
def test_stalled_chord_phase_refreshes_its_jacobian(scalar, mode):
    """A chord phase that stalls after reducing the residual starts again from its iterate
    with the Jacobian there (CHORD_REFRESHES times) instead of restarting full Newton from
    the guess: the same root as Newton's, the iterations of the policy written out in
    NumPy, and fewer Jacobians than Newton from the guess (y³ = 2 from y = 2 and 3: the
    chord contracts by ~0.6 per iteration there). On scalars in reverse mode the first
    update after each Jacobian takes the residual from the Jacobian's program: the same
    iterations."""
    a = 2.0
    for y0 in (2.0, 3.0):
        sol = newton_solve(cubic, jnp.array([y0]), jnp.array([a]),
                           Newton(chord_steps=8, scalar=scalar, scalar_jacobian=mode))
        full = newton_solve(cubic, jnp.array([y0]), jnp.array([a]))
        k, jacs, y = _chord_refresh_model(lambda y: y**3 - a, lambda y: 3 * y**2, y0, 8, 20,
                                          CHORD_REFRESHES)
        assert int(sol.result) == RESULTS.successful
        assert int(sol.newton_steps) == k
        assert jacs < int(full.newton_steps)
        # Both stop on an update below the tolerance 1e-12: within a few ulps of the root.
        np.testing.assert_allclose(float(sol.value[0]), a ** (1 / 3), rtol=1e-14)
        np.testing.assert_allclose(float(sol.value[0]), y, rtol=1e-14)


def test_unrolled_iterations_give_the_loop_iterates():
    a = jnp.array([2.0, 3.0])
    y0 = jnp.array([1.2, 1.4])
    loop = newton_solve(cubic, y0, a)
    for unroll in (1, 3, 50):
        sol = newton_solve(cubic, y0, a, Newton(unroll=unroll))
        np.testing.assert_array_equal(np.asarray(sol.value), np.asarray(loop.value))
        assert int(sol.newton_steps) == int(loop.newton_steps)
        assert int(sol.result) == int(loop.result)


def test_implicit_gradient_matches_analytic():
    # y*(a) = a^(1/3): dy/da = 1 / (3 y^2)
    @jax.jit
    def root(a):
        return newton_solve(cubic, jnp.ones(2), a).value

    a = jnp.array([2.0, 5.0])
    expected = np.diag(1.0 / (3.0 * np.cbrt(np.asarray(a)) ** 2))
    np.testing.assert_allclose(np.asarray(jax.jacrev(root)(a)), expected, rtol=1e-13)
    np.testing.assert_allclose(np.asarray(jax.jacfwd(root)(a)), expected, rtol=1e-13)


def test_implicit_gradient_matches_finite_differences():
    @jax.jit
    def loss(args):
        y = newton_solve(coupled, jnp.array([1.2, 1.7, 2.8]), args).value
        return jnp.sum(y**2) + y[0] * y[2]

    args = jnp.array([1.0, 2.0, 3.0])
    g = np.asarray(jax.grad(loss)(args))
    eps = 1e-6
    fd = [
        (float(loss(args.at[i].add(eps))) - float(loss(args.at[i].add(-eps)))) / (2 * eps)
        for i in range(3)
    ]
    # Central differences carry O(eps^2) truncation and O(1e-16/eps) round-off: ~1e-9.
    np.testing.assert_allclose(g, fd, rtol=1e-7)


def test_vmap_equals_loop():
    batch = jnp.array([[2.0, 3.0], [5.0, 7.0], [0.1, 100.0]])

    def solve(a):
        sol = newton_solve(cubic, jnp.ones(2), a)
        return sol.value, sol.newton_steps

    values, steps = jax.vmap(solve)(batch)
    for i, a in enumerate(batch):
        v, s = solve(a)
        np.testing.assert_array_equal(np.asarray(values[i]), np.asarray(v))
        assert int(steps[i]) == int(s)


def scaled_cubic(y, args):
    a, s = args
    return s * (y**3 - a) + 0.1 * jnp.sin(y[::-1])


@pytest.mark.parametrize("jacobian_loop, mode", [("batched", "auto"), ("never", "forward"),
                                                 ("never", "reverse"), ("always", "auto")])
@pytest.mark.parametrize("chord_steps", [0, 3])
def test_scalar_solve_under_vmap_equals_a_loop(chord_steps, jacobian_loop, mode):
    """The scalar solve batched (written on vectors over the batch, not batched by JAX)
    gives every member its own solve: the same values bit for bit, iterations and result
    codes as the solve alone, with members that converge at once, that leave the chord
    phase for the Newton fallback (far guess), that fail (non-finite data) and that run
    out of iterations; one argument unbatched. With the chord matrix in a loop over the
    unit vectors (``"batched"``: the batch's; ``"always"``: both) bit for bit too, here:
    the run-time one-hot tangents multiply by exact ones and zeros. In reverse mode (the
    first update after each Jacobian takes the residual from the Jacobian's program) the
    same iterations and result codes, and the roots to the solver's tolerance: XLA's
    kernels for the batch and for one solve round that program's arithmetic differently
    by an ulp (measured: 1 ulp in the first iterate of the far guess)."""
    solver = Newton(scalar=True, chord_steps=chord_steps, max_steps=8,
                    jacobian_loop=jacobian_loop, scalar_jacobian=mode)
    a = jnp.array([[2.0, 3.0], [5.0, 7.0], [1.0, 1.0], [0.1, 100.0], [jnp.nan, 1.0],
                   [1e30, 2.0]])
    y0 = jnp.array([[1.26, 1.44], [1.0, 1.0], [1.0, 1.0], [3.0, 0.2], [1.0, 1.0],
                    [1.0, 1.0]])
    s = jnp.asarray(1.5)

    def solve(y0, a):
        sol = newton_solve(scaled_cubic, y0, (a, s), solver)
        return sol.value, sol.result, sol.newton_steps, sol.residual

    batched = jax.jit(jax.vmap(solve))(y0, a)
    alone = jax.jit(solve)
    codes = set()
    exact = mode != "reverse"

    def check(got, want):
        value, result, steps, residual = (np.asarray(x) for x in got)
        assert int(result) == int(want[1]) and int(steps) == int(want[2])
        if exact:
            np.testing.assert_array_equal(value, np.asarray(want[0]))
            np.testing.assert_array_equal(residual, np.asarray(want[3]))
        elif int(result) == RESULTS.successful:
            # Both stop on an update of at most atol + rtol |y| (1e-12 each, Newton's
            # defaults) with the iteration contracting: within twice that of the root.
            np.testing.assert_allclose(value, np.asarray(want[0]), rtol=4e-12, atol=2e-12)

    for i in range(a.shape[0]):
        check([x[i] for x in batched], alone(y0[i], a[i]))
        codes.add(int(batched[1][i]))
    # the cases above reach success, non-finite data and the iteration cap
    assert {RESULTS.successful, RESULTS.nonfinite, RESULTS.max_steps_reached} <= codes
    # the guess unbatched too (broadcast to the batch)
    one_guess = jax.jit(jax.vmap(solve, in_axes=(None, 0)))(y0[0], a)
    for i in range(a.shape[0]):
        check([x[i] for x in one_guess], alone(y0[0], a[i]))


@pytest.mark.parametrize("backend, unrolled", [("cpu", False), ("gpu", True)])
def test_a_batch_builds_the_loop_jacobian_on_a_cpu_only(monkeypatch, backend, unrolled):
    """``jacobian_loop="batched"`` (the default): a batch of solves on a CPU computes its
    chord matrix in loops (traced as a sweep traces a block: no unrolled Jacobian program
    built at all); on an accelerator, which would launch each loop iteration's kernels
    once per column, unrolled."""
    from lgvi_jax import newton

    built = []
    real = newton._scalar_jacobian
    monkeypatch.setattr(newton, "_scalar_jacobian",
                        lambda *a, **k: built.append(1) or real(*a, **k))
    monkeypatch.setattr(jax, "default_backend", lambda: backend)
    newton.clear_scalar_programs()
    solver = Newton(scalar=True, chord_steps=3, max_steps=8)
    a = jnp.array([[2.0, 3.0], [5.0, 7.0]])

    def solve(y0, a):
        return newton_solve(scaled_cubic, y0, (a, jnp.asarray(1.5)), solver).value

    with newton.batched_trace():  # as a sweep traces its blocks
        jax.make_jaxpr(jax.vmap(solve))(jnp.ones((2, 2)), a)
    assert bool(built) == unrolled


class _Power(eqx.Module):
    """``y**k = a`` (``k`` static): a residual given as a bound method."""

    k: int = eqx.field(static=True)

    def residual(self, y, a):
        return y**self.k - a


def test_scalar_programs_are_built_once_per_equations_across_traces(monkeypatch):
    """The scalar programs of a residual are remembered across traces (a bound method: per
    function and instance): a second ``jit`` of another function solving the same
    equations, and an equal instance, build none; an instance with other settings builds
    its own, and each solve reaches its own root; ``clear_scalar_programs`` forgets them."""
    from lgvi_jax import scalarize as sc

    built = []
    init = sc.ScalarFunction.__init__

    def counting(self, fn, *example):
        built.append(fn)
        init(self, fn, *example)

    monkeypatch.setattr(sc.ScalarFunction, "__init__", counting)
    solver = Newton(scalar=True, chord_steps=8)
    a = jnp.array([2.0, 5.0])

    def solve_with(power):
        return jax.jit(lambda y0, a: newton_solve(power.residual, y0, a, solver).value)

    root3 = solve_with(_Power(3))(jnp.ones(2), a)
    first = len(built)
    assert first >= 2  # the residual and its Jacobian
    # Another traced function, a new (equal) instance, other values: nothing rebuilt.
    again = solve_with(_Power(3))(jnp.full(2, 1.5), 2.0 * a)
    assert len(built) == first
    root4 = solve_with(_Power(4))(jnp.ones(2), a)
    assert len(built) > first
    # Forgotten (a cold compile, as lgvi-jax bench times it): built again.
    n_built = len(built)
    clear_scalar_programs()
    solve_with(_Power(3))(jnp.ones(2), a)
    assert len(built) >= n_built + 2
    # The roots in closed form. Bound from the solver's contract: the last update is at
    # most atol + rtol |y| (<= 3e-12 here) and, contracting at least 2x, bounds the error
    # left (measured: 1 ulp).
    for got, want in ((root3, a ** (1 / 3)), (again, (2.0 * a) ** (1 / 3)),
                      (root4, a ** (1 / 4))):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-11)


def test_bad_settings_rejected():
    with pytest.raises(ValueError, match="rtol"):
        Newton(rtol=-1.0)
    with pytest.raises(ValueError, match="max_steps"):
        Newton(max_steps=0)
    with pytest.raises(ValueError, match="both be 0"):
        Newton(rtol=0.0, atol=0.0)
    with pytest.raises(ValueError, match="residuals"):
        newton_solve(lambda y, a: jnp.concatenate([y, y]), jnp.ones(2), None)


def test_given_chord_matrix_reaches_the_same_root():
    """``jac0``: the chord phase runs with the given matrix (an approximation of the
    Jacobian) and reaches Newton's root; a useless matrix sends the solve to the Newton
    fallback, which still converges; the derivative of the root ignores ``jac0``."""
    a = jnp.array([2.0, 3.0])
    y0 = jnp.array([1.2, 1.4])
    full = newton_solve(cubic, y0, a, Newton())
    approx = jnp.diag(3.0 * y0**2) * 1.1  # 10% off: a contracting chord
    chord = newton_solve(cubic, y0, a, Newton(chord_steps=30), jac0=approx)
    assert int(chord.result) == RESULTS.successful
    # Both stop at an update <= 1e-12 relative; the chord's last update is tightened to
    # 1e-14 of the tolerance's size, so both are at the root to round-off.
    np.testing.assert_allclose(np.asarray(chord.value), np.asarray(full.value), rtol=1e-14)
    assert int(chord.newton_steps) > int(full.newton_steps)  # linear, not quadratic
    bad = newton_solve(cubic, y0, a, Newton(chord_steps=5), jac0=-jnp.eye(2))  # diverges
    assert int(bad.result) == RESULTS.successful
    np.testing.assert_allclose(np.asarray(bad.value), np.asarray(full.value), rtol=1e-14)
    # The implicit derivative: dy/da = 1 / (3 y^2), whatever the chord matrix.
    grad = jax.grad(lambda a: newton_solve(cubic, y0, a, Newton(chord_steps=30),
                                           jac0=approx).value.sum())(a)
    np.testing.assert_allclose(np.asarray(grad), 1.0 / (3.0 * np.cbrt(np.asarray(a)) ** 2),
                               rtol=1e-12)
    with pytest.raises(ValueError, match="jac0 must have shape"):
        newton_solve(cubic, y0, a, Newton(chord_steps=3), jac0=jnp.eye(3))


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8])
def test_spd_inverse_matches_numpy(n):
    """Pivot-free Gauss–Jordan on symmetric positive definite matrices, including badly
    scaled ones (condition ~1e6): the inverse and the solve to round-off times the condition
    number."""
    rng = np.random.default_rng(n)
    for scale in (1.0, 1e3):
        Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
        eig = np.geomspace(1.0 / scale, scale, n)
        A = (Q * eig) @ Q.T
        A = 0.5 * (A + A.T)
        X = np.asarray(jax.jit(spd_inverse)(jnp.asarray(A)))
        cond = np.linalg.cond(A)
        np.testing.assert_allclose(X @ A, np.eye(n), atol=50 * cond * 1e-16)
        np.testing.assert_allclose(X, np.linalg.inv(A), rtol=0,
                                   atol=50 * cond * 1e-16 * np.abs(np.linalg.inv(A)).max())
        b = rng.normal(size=n)
        for solve in (spd_solve, ldl_solve):
            x = np.asarray(jax.jit(solve)(jnp.asarray(A), jnp.asarray(b)))
            np.testing.assert_allclose(A @ x, b, atol=50 * cond * 1e-16 * np.abs(b).max())
    with pytest.raises(ValueError, match="square"):
        spd_inverse(jnp.ones((2, 3)))
    with pytest.raises(ValueError, match="spd_solve"):
        spd_solve(jnp.eye(2), jnp.ones(3))
    with pytest.raises(ValueError, match="ldl_solve"):
        ldl_solve(jnp.eye(2), jnp.ones(3))


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 7, 10])
def test_scalar_block_solve_matches_numpy(n):
    """The scalar engine's solve by blocks (the leading 3x3 block and the Schur complement,
    recursively beyond 6 unknowns; no pivoting) on matrices like its Newton matrices: a
    symmetric positive definite matrix (condition up to ~1e4) plus a nonsymmetric O(h)
    part. Bound: backward stable without pivoting for such matrices (growth ~1), so the
    error is at most a few n eps cond |x|; 50 eps cond |x| leaves room for n <= 10. A
    singular leading block gives non-finite values, as documented."""
    from lgvi_jax import scalarize as sc
    from lgvi_jax.newton import _scalar_block_factor, _scalar_block_solve

    @jax.jit
    def solve(A, f):
        rows = [list(r) for r in sc.split(A)]
        return jnp.stack([jnp.asarray(v) for v in
                          _scalar_block_solve(_scalar_block_factor(rows), list(sc.split(f)))])

    rng = np.random.default_rng(n)
    for scale in (1.0, 1e2):
        Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
        A = (Q * np.geomspace(1.0 / scale, scale, n)) @ Q.T
        A = 0.5 * (A + A.T) + 0.01 * rng.normal(size=(n, n))
        f = rng.normal(size=n)
        x = np.linalg.solve(A, f)
        np.testing.assert_allclose(np.asarray(solve(jnp.asarray(A), jnp.asarray(f))), x,
                                   rtol=0, atol=50 * 2.2e-16 * np.linalg.cond(A) * np.abs(x).max())
    if n > 3:
        A = np.eye(n)
        A[:3, :3] = [[1.0, 2.0, 0.0], [2.0, 4.0, 0.0], [0.0, 0.0, 1.0]]
        assert not np.all(np.isfinite(np.asarray(solve(jnp.asarray(A), jnp.ones(n)))))


def test_ldl_solve_reads_the_lower_triangle_and_is_smaller_on_scalars():
    """``ldl_solve`` uses only the lower triangle (the upper one may hold anything) and,
    emitted on scalars, has fewer operations than the Gauss–Jordan sweep: it is the
    factorisation, not a different answer."""
    from lgvi_jax.scalarize import ScalarFunction

    A = jnp.array([[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]])
    b = jnp.array([1.0, -2.0, 0.5])
    junk = jnp.tril(A) + jnp.triu(jnp.full((3, 3), 7.0), 1)
    # eps x cond (~3) x n: 1e-14 with margin
    np.testing.assert_allclose(ldl_solve(junk, b), np.linalg.solve(A, b), atol=1e-14)
    for n in (3, 5):
        A, b = jnp.eye(n), jnp.ones(n)
        assert ScalarFunction(ldl_solve, A, b).size < ScalarFunction(spd_solve, A, b).size


def test_broyden_chord_is_superlinear_and_reaches_the_root():
    """``Newton(broyden=True)``: the chord matrix's inverse updated by Broyden's formula
    reaches Newton's root in fewer iterations than the fixed chord from the same matrix
    (superlinear against linear convergence); passing the inverse (``ChordInverse``) is the
    same solve; the implicit derivative does not depend on the iteration."""
    args = jnp.array([1.0, 2.0, 3.0])
    y0 = jnp.array([1.1, 1.8, 3.15])
    full = newton_solve(coupled, y0, args, Newton())
    J0 = jax.jacfwd(lambda y: coupled(y, args))(y0) * 1.15  # 15% off
    fixed = newton_solve(coupled, y0, args, Newton(chord_steps=40), jac0=J0)
    broyden = newton_solve(coupled, y0, args, Newton(chord_steps=40, broyden=True), jac0=J0)
    for sol in (fixed, broyden):
        assert int(sol.result) == RESULTS.successful
        np.testing.assert_allclose(np.asarray(sol.value), [1.0, 2.0, 3.0], rtol=1e-13)
    assert int(broyden.newton_steps) < int(fixed.newton_steps)
    given_inverse = newton_solve(coupled, y0, args, Newton(chord_steps=40, broyden=True),
                                 jac0=ChordInverse(jnp.linalg.inv(J0)))
    assert int(given_inverse.newton_steps) == int(broyden.newton_steps)
    np.testing.assert_allclose(np.asarray(given_inverse.value), np.asarray(broyden.value),
                               rtol=1e-14)
    jac = jax.jacrev(lambda a: newton_solve(coupled, y0, a, Newton(chord_steps=40,
                                                                   broyden=True),
                                            jac0=J0).value)(args)
    jac_newton = jax.jacrev(lambda a: newton_solve(coupled, y0, a, Newton()).value)(args)
    # Entries that vanish exactly are round-off (~1e-16) in either: an absolute floor.
    np.testing.assert_allclose(np.asarray(jac), np.asarray(jac_newton), rtol=1e-12,
                               atol=1e-14)
    # A useless matrix: the Broyden phase stalls and the Newton fallback still converges.
    bad = newton_solve(coupled, y0, args, Newton(chord_steps=5, broyden=True),
                       jac0=-jnp.eye(3))
    assert int(bad.result) == RESULTS.successful
    np.testing.assert_allclose(np.asarray(bad.value), np.asarray(full.value), rtol=1e-13)
