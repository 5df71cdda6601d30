"""Property-based tests (hypothesis) and finite gradients at special rotations.

* ``so3``: exp/log, Cayley and its inverse, quaternions round trip over the whole group,
  angles near 0 and near pi included; ``dexp``/``dexp_inv`` (and the Cayley and left
  versions) are inverse to each other.
* ``newton_solve`` finds the root of random well-conditioned small systems.
* ``--set`` parsing: random valid strings round trip, random other strings are either valid
  or refused with a ``UsageError``, never another exception.
* ``jax.grad`` and ``jax.jacfwd`` through exp, log, Cayley, its inverse and a short heavy-top
  rollout are finite and equal central finite differences at the identity, at 1e-8 and
  near pi.

Tolerances are derived, not fitted: ``EPS`` (float64 unit round-off, 2^-52 = 2.2e-16)
times the condition number of the computation times a modest factor, stated at each bound.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import lgvi_jax as lj
from lgvi_jax import so3
from lgvi_jax.cli import UsageError, parse_set
from lgvi_jax.newton import Newton, newton_solve

EPS = float(np.finfo(np.float64).eps)  # 2.2e-16
SETTINGS = settings(max_examples=80, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow])

# ---------------------------------------------------------------------------------------
# Strategies: axes and angles over the whole group, with the hard places over-sampled
# ---------------------------------------------------------------------------------------

_unit = st.tuples(*[st.floats(-1.0, 1.0) for _ in range(3)]).filter(
    lambda v: 0.1 <= math.sqrt(sum(x * x for x in v)) <= 1.0).map(
    lambda v: np.asarray(v) / np.linalg.norm(v))

_angle = st.one_of(
    st.floats(0.0, math.pi),  # anywhere
    st.floats(-300.0, -1.0).map(lambda e: 10.0**e),  # tiny: 1e-300 .. 0.1
    st.floats(-15.0, -1.0).map(lambda e: math.pi - 10.0**e),  # near pi, below it
    st.sampled_from([0.0, 1e-8, math.pi, math.pi - 1e-6, 0.1, math.pi - 0.1]),
)

rotation_vectors = st.tuples(_unit, _angle).map(lambda a: a[1] * a[0])
quaternions = st.tuples(*[st.floats(-1.0, 1.0) for _ in range(4)]).filter(
    lambda q: sum(x * x for x in q) >= 1e-2).map(np.asarray)

_exp = jax.jit(so3.exp)
_log = jax.jit(so3.log)
_cay = jax.jit(so3.cayley)
_cay_inv = jax.jit(so3.cayley_inv)
_q2r = jax.jit(so3.quat_to_rotation)
_r2q = jax.jit(so3.rotation_to_quat)


def _axis_angle_rotation(axis, angle):
    """The rotation by ``angle`` about ``axis`` from the quaternion ``(cos a/2, sin a/2 n)``:
    built independently of ``exp`` (a different formula, a different rounding)."""
    return np.asarray(_q2r(np.concatenate([[math.cos(angle / 2)],
                                           math.sin(angle / 2) * axis])))


# ---------------------------------------------------------------------------------------
# exp and log
# ---------------------------------------------------------------------------------------

# Bound for log(exp(w)) = w, relative to |w|. exp(w)'s entries are a dozen flops on O(1)
# numbers: rounding <= ~10 EPS absolute, and the off-diagonal entries (all that the small
# branch of log reads) carry it relative to |w|. log amplifies a perturbation of R by at
# most ~16 (theta/(2 sin theta) in the generic branch, which is used for sin^2 theta >=
# 1e-2; the small branch is a series of bounded coefficients; near pi the axis comes from
# the symmetric part, eigen-gap ~2). 10 EPS x 16 x sqrt(3) = 280 EPS; x4 margin.
LOG_EXP_RTOL = 1024 * EPS


@SETTINGS
@given(rotation_vectors)
def test_log_of_exp_is_the_identity(w):
    theta = np.linalg.norm(w)
    got = np.asarray(_log(_exp(w)))
    if theta > math.pi - 1e-9:
        # Within ~1e-9 of pi the rounding of exp(w) (1e-15) can move the rotation across
        # pi, where log jumps to the antipodal representative w - 2 pi w/|w| (the same
        # rotation): accept either, and in any case the rotation must come back.
        other = w - 2 * math.pi * w / theta
        err = min(np.linalg.norm(got - w), np.linalg.norm(got - other))
    else:
        err = np.linalg.norm(got - w)
    assert err <= LOG_EXP_RTOL * max(theta, 1e-300), (theta, err)
    assert np.linalg.norm(got) <= math.pi * (1 + 4 * EPS)


# exp(log(R)) = R, absolute: R's entries are O(1). Rounding of R (~10 EPS), log's
# amplification (<= 16, above) and exp's conditioning (|dexp| <= 1) give ~160 EPS x sqrt(3);
# 1024 EPS leaves a factor ~4. This holds up to and at pi, where log may pick either
# representative but both map back to R.
EXP_LOG_ATOL = 1024 * EPS


@SETTINGS
@given(_unit, _angle)
def test_exp_of_log_is_the_identity(axis, angle):
    R = _axis_angle_rotation(axis, angle)
    back = np.asarray(_exp(_log(R)))
    assert np.max(np.abs(back - R)) <= EXP_LOG_ATOL
    # The angle is recovered with an absolute error of the same order (it is an O(1)
    # function of R's entries, atan2 being well conditioned).
    assert abs(np.linalg.norm(np.asarray(_log(R))) - angle) <= EXP_LOG_ATOL * 4


@SETTINGS
@given(_unit, _angle)
def test_exp_agrees_with_the_quaternion_formula(axis, angle):
    # Two formulas for the same rotation (Rodrigues; quaternion): ~10 EPS each, absolute.
    np.testing.assert_allclose(_exp(angle * axis), _axis_angle_rotation(axis, angle),
                               rtol=0, atol=64 * EPS)


# ---------------------------------------------------------------------------------------
# Cayley and its inverse
# ---------------------------------------------------------------------------------------

_cayley_vectors = st.tuples(_unit, st.one_of(
    st.floats(-300.0, 6.0).map(lambda e: 10.0**e), st.just(0.0))).map(lambda a: a[1] * a[0])


@SETTINGS
@given(_cayley_vectors)
def test_cayley_inverse_of_cayley(w):
    # cay(w) is the rotation by 2 arctan(|w|/2); cayley_inv divides by 1 + tr R =
    # 16/(4 + |w|^2), computed from R's entries with ~10 EPS absolute error: the relative
    # condition number of the round trip is ~(1 + |w|^2/4) (the angle nears pi as |w|
    # grows). Bound: 64 EPS (1 + |w|^2/4), relative to |w|.
    theta = np.linalg.norm(w)
    got = np.asarray(_cay_inv(_cay(w)))
    cond = 1.0 + theta**2 / 4
    assert np.linalg.norm(got - w) <= 64 * EPS * cond * max(theta, 1e-300), (theta, cond)


@SETTINGS
@given(_unit, st.one_of(st.floats(0.0, math.pi - 1e-6),
                        st.floats(-300.0, -1.0).map(lambda e: 10.0**e),
                        st.floats(-6.0, -1.0).map(lambda e: math.pi - 10.0**e)))
def test_cayley_of_cayley_inverse(axis, angle):
    # cayley_inv divides by 1 + tr R = 4 cos^2(angle/2) ~ d^2 (d = pi - angle), whose
    # absolute rounding is ~EPS: |w| = 2 tan(angle/2) ~ 4/d gets a relative error ~4 EPS/d^2,
    # and cay maps it back to an angle error (4/|w|^2) |w| 4 EPS/d^2 ~ 4 EPS/d. So the
    # round trip's absolute error is ~EPS (1 + 4/d) (measured: 14 EPS at d = 1e-2, 1.9e3 EPS
    # at 1e-3, 4e5 EPS at 1e-6); bound 64 EPS (1 + 4/d).
    R = _axis_angle_rotation(axis, angle)
    d = math.pi - angle
    np.testing.assert_allclose(_cay(_cay_inv(R)), R, rtol=0, atol=64 * EPS * (1 + 4 / d))


# ---------------------------------------------------------------------------------------
# Quaternions
# ---------------------------------------------------------------------------------------


@SETTINGS
@given(quaternions)
def test_quaternion_round_trips(q):
    # Shepperd's method divides only by sqrt of its largest diagonal entry (>= 1 of 4):
    # O(1)-conditioned, so ~10 EPS absolute each way; 64 EPS bounds both.
    unit = q / np.linalg.norm(q)
    R = np.asarray(_q2r(q))
    back = np.asarray(_r2q(R))
    assert back[0] >= 0
    err = min(np.max(np.abs(back - unit)), np.max(np.abs(back + unit)))  # q ~ -q
    assert err <= 64 * EPS
    np.testing.assert_allclose(_q2r(back), R, rtol=0, atol=64 * EPS)
    np.testing.assert_allclose(R.T @ R, np.eye(3), rtol=0, atol=64 * EPS)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=64 * EPS)


# ---------------------------------------------------------------------------------------
# Differentials: dexp and dexp_inv (and their Cayley and left versions) are inverses
# ---------------------------------------------------------------------------------------

_PAIRS = {
    "dexp": (so3.dexp, so3.dexp_inv),
    "dexp_left": (so3.dexp_left, so3.dexp_left_inv),
    "dcayley": (so3.dcayley, so3.dcayley_inv),
    "dcayley_left": (so3.dcayley_left, so3.dcayley_left_inv),
}
_PAIRS_JIT = {k: (jax.jit(a), jax.jit(b)) for k, (a, b) in _PAIRS.items()}

# dexp is invertible for |w| < 2 pi; sample up to 2 pi - 1e-3 (condition ~ 1/|2 pi - |w||).
_dexp_vectors = st.tuples(_unit, st.one_of(
    _angle, st.floats(math.pi, 2 * math.pi - 1e-3),
    st.floats(-6.0, -3.0).map(lambda e: 2 * math.pi - 10.0**e))).map(lambda a: a[1] * a[0])


@pytest.mark.parametrize("name", list(_PAIRS))
@SETTINGS
@given(w=_dexp_vectors)
def test_differential_and_its_inverse(name, w):
    if name.startswith("dcayley"):
        w = w * 10.0  # the Cayley differentials are invertible for every w: go far out
    d, d_inv = (np.asarray(f(w)) for f in _PAIRS_JIT[name])
    # Each matrix is a handful of flops per entry (~10 EPS relative to its norm), so the
    # product's error is <= ~20 EPS |D| |D^-1| = 20 EPS cond(D) (2-norm condition number,
    # computed here); 64 EPS cond gives a factor ~3.
    cond = np.linalg.norm(d, 2) * np.linalg.norm(d_inv, 2)
    for prod in (d @ d_inv, d_inv @ d):
        assert np.max(np.abs(prod - np.eye(3))) <= 64 * EPS * cond, (np.linalg.norm(w), cond)


_MAP_INV_JIT = {
    "exp": (jax.jit(so3.exp), jax.jit(so3.dexp_inv)),
    "cayley": (jax.jit(so3.cayley), jax.jit(so3.dcayley_inv)),
}


@pytest.mark.parametrize("name", list(_MAP_INV_JIT))
@SETTINGS
@given(w=_dexp_vectors)
def test_inverse_differential_times_map_transposed_is_at_minus_w(name, w):
    # J_l(w) = tau(w) J_r(w) = J_r(-w), so J_r(w)^-1 tau(w)^T = J_r(-w)^-1: the exact Hamel
    # variations' B (integrators/lie.py) evaluated without the product. The product's
    # rounding is ~10 EPS |J_r^-1| (tau is orthogonal), each side's ~10 EPS |J_r^-1(+-w)|;
    # 64 EPS times the larger norm bounds the difference.
    if name == "cayley":
        w = w * 10.0
    tau, d_inv = _MAP_INV_JIT[name]
    lhs = np.asarray(d_inv(w)) @ np.asarray(tau(w)).T
    rhs = np.asarray(d_inv(-w))
    scale = max(np.linalg.norm(lhs, 2), np.linalg.norm(rhs, 2))
    assert np.max(np.abs(lhs - rhs)) <= 64 * EPS * scale, np.linalg.norm(w)


# ---------------------------------------------------------------------------------------
# Newton on random well-conditioned small systems
# ---------------------------------------------------------------------------------------


def _residual(y, args):
    # A (y - y*) + 0.3 (sin y - sin y*): Jacobian A + 0.3 diag(cos y), A = 3 I + M with
    # |M|_2 <= 1, so the Jacobian's eigenvalues lie in [1.7, 4.3] (cond <= ~2.5): a
    # well-conditioned system with the unique root y*.
    A, ystar = args
    return A @ (y - ystar) + 0.3 * (jnp.sin(y) - jnp.sin(ystar))


@jax.jit
def _solve(A, ystar, y0):
    return newton_solve(_residual, y0, (A, ystar), Newton(rtol=1e-12, atol=1e-12,
                                                          max_steps=30))


@SETTINGS
@given(n=st.integers(1, 6), seed=st.integers(0, 2**32 - 1),
       scale=st.sampled_from([1e-3, 1.0, 1e3]), start=st.floats(0.0, 1.0))
def test_newton_solves_well_conditioned_systems(n, seed, scale, start):
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((n, n))
    M /= max(np.linalg.norm(M, 2), 1.0)
    A = 3.0 * np.eye(n) + M
    ystar = scale * rng.standard_normal(n)
    y0 = ystar + start * rng.standard_normal(n)  # within ~1 of the root: Newton's basin
    sol = _solve(A, ystar, y0)
    assert bool(sol.ok), int(sol.result)
    assert int(sol.newton_steps) <= 12  # quadratic convergence from O(1) away
    # The last update met |dy_i| <= 1e-12 (1 + |y_i|), and with quadratic convergence the
    # error after it is much smaller; the round-off floor is cond (<= 2.5) x EPS x the
    # residual's scale (|A| |y| ~ 4 |y|). Bound: 10 x (the Newton tolerance + 16 EPS |y*|).
    tol = 10 * (1e-12 * (1 + np.abs(ystar)) + 16 * EPS * np.max(np.abs(ystar)))
    np.testing.assert_array_less(np.abs(np.asarray(sol.value) - ystar), tol)


# ---------------------------------------------------------------------------------------
# --set parsing
# ---------------------------------------------------------------------------------------

_names = st.text(st.sampled_from("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ_0123"
                                 "456789"), min_size=1, max_size=8)
_values = st.lists(st.floats(allow_nan=False, allow_infinity=False), min_size=1, max_size=9)
_pad = st.sampled_from(["", " ", "  "])


@SETTINGS
@given(st.dictionaries(_names, _values, min_size=1, max_size=4), _pad, _pad,
       st.sampled_from([repr, lambda x: f"{x:.17g}", lambda x: f"{x:.17e}"]))
def test_set_parsing_round_trips_valid_strings(assignments, pad1, pad2, fmt):
    items = [f"{pad1}{name}{pad2}={pad2}" + ",".join(fmt(v) for v in values)
             for name, values in assignments.items()]
    parsed = parse_set(items)
    assert list(parsed) == list(assignments)
    for name, values in assignments.items():
        assert parsed[name].dtype == np.float64
        np.testing.assert_array_equal(parsed[name], values)  # 17 digits round trip exactly


@SETTINGS
@given(st.lists(st.text(max_size=20), min_size=1, max_size=3))
def test_set_parsing_of_any_string_is_valid_or_refused(items):
    try:
        parsed = parse_set(items)
    except UsageError as err:
        message = str(err)
        assert message.startswith("--set") and "\n" not in message
        return
    # Accepted: then every item was NAME=numbers, with finite values and distinct names.
    assert len(parsed) == len(items)
    for item, (name, values) in zip(items, parsed.items(), strict=True):
        assert name == item.partition("=")[0].strip() and name
        assert values.ndim == 1 and values.size >= 1 and np.all(np.isfinite(values))


@pytest.mark.parametrize("items, message", [
    (["m"], "expected NAME=V"),
    (["=1"], "expected NAME=V"),
    (["m="], "expected NAME=V"),
    (["m= "], "expected NAME=V"),
    (["m=1,,2"], "numbers separated by commas"),
    (["m=1;2"], "numbers separated by commas"),
    (["m=0x10"], "numbers separated by commas"),
    (["m=nan"], "finite"),
    (["m=1,-inf"], "finite"),
    (["m=1e999"], "finite"),  # overflows to inf
    (["m=1", "m=2"], "m given twice"),
])
def test_set_parsing_refuses_with_a_message(items, message):
    with pytest.raises(UsageError, match=message):
        parse_set(items)


@SETTINGS
@given(_names, _values, st.sampled_from(["nan", "inf", "-inf", "x", "", "1..2", "--1"]),
       st.integers(0, 9))
def test_set_parsing_refuses_one_bad_value_anywhere(name, values, bad, where):
    tokens = [repr(v) for v in values]
    tokens.insert(where % (len(tokens) + 1), bad)
    with pytest.raises(UsageError, match=r"^--set "):
        parse_set([f"{name}=" + ",".join(tokens)])


# ---------------------------------------------------------------------------------------
# Finite gradients at special rotations
# ---------------------------------------------------------------------------------------

_C = np.random.default_rng(20).standard_normal((3, 3))  # a fixed random linear read-out
_c3 = np.random.default_rng(21).standard_normal(3)
_U = np.array([2.0, -1.0, 0.5]) / np.linalg.norm([2.0, -1.0, 0.5])  # a generic axis


def _central_difference(f, x, h):
    x = np.asarray(x, dtype=np.float64)
    g = np.zeros_like(x)
    for i in range(x.size):
        e = np.zeros_like(x)
        e.flat[i] = h
        g.flat[i] = (float(f(x + e)) - float(f(x - e))) / (2 * h)
    return g


def _check_gradient(f, x, h, rtol, compiled=None):
    """``jax.grad`` and ``jax.jacfwd`` of the scalar ``f`` at ``x``: finite, and equal to
    each other and to the central difference of step ``h`` (to ``rtol`` of the gradient's
    norm). ``compiled``: ``(f, grad f, jacfwd f)`` already jitted, to compile once."""
    x = jnp.asarray(x, dtype=jnp.float64)
    f_jit, grad, jacfwd = compiled or (jax.jit(f), jax.grad(f), jax.jacfwd(f))
    g_rev = np.asarray(grad(x))
    g_fwd = np.asarray(jacfwd(x))
    assert np.all(np.isfinite(g_rev)) and np.all(np.isfinite(g_fwd))
    scale = max(np.linalg.norm(g_rev), 1e-300)
    # Forward and reverse mode evaluate the same derivative formulas in another order.
    assert np.linalg.norm(g_rev - g_fwd) <= 1e3 * EPS * scale
    fd = _central_difference(f_jit, x, h)
    err = np.linalg.norm(g_rev - fd) / scale
    assert err <= rtol, (err, g_rev, fd)
    return err


# Central differences have error h^2/6 |f'''| + EPS |f| / h. With the scalar losses below
# (O(1) values and derivatives) and h = 1e-6, that is ~1e-13 + 2e-10: a relative tolerance
# of 1e-6 holds with a margin > 1000 even where the derivatives are a few times larger
# (near pi), and still catches any wrong derivative formula (errors of O(1)).
FD_STEP = 1e-6
FD_RTOL = 1e-6

POINTS = {
    "identity": 0.0,
    "small-1e-8": 1e-8,
    "moderate": 1.0,
    "near-pi-1e-6": math.pi - 1e-6,
}


@pytest.mark.parametrize("point", list(POINTS))
def test_gradients_through_exp(point):
    w0 = POINTS[point] * _U
    _check_gradient(lambda w: jnp.sum(_C * so3.exp(w)), w0, FD_STEP, FD_RTOL)


@pytest.mark.parametrize("point", list(POINTS))
def test_gradients_through_cayley(point):
    w0 = POINTS[point] * _U
    _check_gradient(lambda w: jnp.sum(_C * so3.cayley(w)), w0, FD_STEP, FD_RTOL)


# log is differentiable on angles < pi (at pi it jumps between +-pi n). Along the group,
# delta -> log(R0 exp(delta)) has bounded derivatives up to pi (dexp is invertible there),
# so the central difference only needs h well below the distance to pi: at pi - 1e-4 with
# h = 1e-6 the points stay 99e-6 below pi.
LOG_POINTS = {"identity": 0.0, "small-1e-8": 1e-8, "moderate": 1.0,
              "near-pi-1e-4": math.pi - 1e-4}


@pytest.mark.parametrize("point", list(LOG_POINTS))
def test_gradients_through_log_along_the_group(point):
    R0 = so3.exp(LOG_POINTS[point] * _U)
    _check_gradient(lambda d: jnp.dot(_c3, so3.log(R0 @ so3.exp(d))), np.zeros(3), FD_STEP,
                    FD_RTOL)


@pytest.mark.parametrize("point", ["identity", "small-1e-8", "moderate"])
def test_gradients_through_log_in_the_matrix_entries(point):
    # The formula of log as a function of all nine entries (the derivative autodiff uses
    # off the group, e.g. for a slightly non-orthogonal R): smooth in each branch away from
    # pi, so the central difference of the entries applies (the points stay in one branch).
    R0 = np.asarray(so3.exp(LOG_POINTS[point] * _U))
    _check_gradient(lambda R: jnp.dot(_c3, so3.log(R)), R0, FD_STEP, FD_RTOL)


# cayley_inv is finite for angles < pi, with |w| = 2 tan(angle/2) ~ 4/d -> inf at the
# distance d -> 0 to pi. Relative to the gradient (~4/d^2), the central difference has a
# truncation error ~ (h/d)^2 and a round-off error ~ (EPS 4/d^2 relative error of w) x
# |w| / (h |g|) ~ 4 EPS/(d^2 h) x d: at d = 1e-2 and h = 1e-6, 1e-8 + 1e-7, below FD_RTOL
# by 10x. (At d = 1e-3 the best step leaves ~5e-7: too close, so nearer to pi only
# finiteness and forward = reverse are checked.)
CAY_INV_POINTS = {"identity": 0.0, "small-1e-8": 1e-8, "moderate": 1.0,
                  "near-pi-1e-2": math.pi - 1e-2}


def _cayley_inv_loss(angle):
    R0 = so3.exp(angle * _U)
    return lambda d: jnp.dot(_c3, so3.cayley_inv(R0 @ so3.exp(d)))


@pytest.mark.parametrize("point", list(CAY_INV_POINTS))
def test_gradients_through_cayley_inverse(point):
    _check_gradient(_cayley_inv_loss(CAY_INV_POINTS[point]), np.zeros(3), FD_STEP, FD_RTOL)


def test_gradients_through_cayley_inverse_are_finite_next_to_pi():
    f = _cayley_inv_loss(math.pi - 1e-6)
    g_rev, g_fwd = (np.asarray(jax.grad(f)(jnp.zeros(3))),
                    np.asarray(jax.jacfwd(f)(jnp.zeros(3))))
    assert np.all(np.isfinite(g_rev)) and np.linalg.norm(g_rev) > 1e10  # ~4/d^2
    # Same formulas in another order, each rounded relative to the huge |w| ~ 4e6.
    assert np.linalg.norm(g_rev - g_fwd) <= 1e-6 * np.linalg.norm(g_rev)


# A short rollout of the heavy top from R0 = identity: every step solves the discrete
# equations (Newton, differentiated by the implicit function theorem) through exp and log
# at small angles. The Newton tolerance (1e-12 relative on the update, then one more
# quadratic step) makes the loss smooth to ~1e-16 relative, so the central difference
# with h = 1e-6 (relative to the O(1) parameters) keeps the error estimate above: ~1e-10
# relative, and 1e-6 is a safe bound.
ROLLOUT_STEPS = 5
ROLLOUT_DT = 0.01


_J0 = np.asarray(lj.HeavyTop().J)
_E = np.array([[1.0, 0.3, 0.0], [0.3, -0.5, 0.2], [0.0, 0.2, 0.7]])  # a symmetric direction


def _rollout_loss(x):
    """A scalar of the final state of a heavy top started at R0 = identity, as a function
    of ``x = (omega0, a)``: the initial body angular velocity and a change ``a |J0| E`` of
    the inertia about the pivot (a field of the model; the initial velocity is an argument
    of ``model.state``)."""
    model = lj.HeavyTop(J=_J0 + x[3] * np.linalg.norm(_J0) * _E)
    traj = lj.simulate(model, lj.LGVI(), model.state(R0=np.eye(3), omega0=x[:3]), ROLLOUT_DT,
                       ROLLOUT_STEPS)
    final = jax.tree.map(lambda y: y[-1], traj.state)
    return jnp.sum(_C * final.R) + jnp.dot(_c3, final.mu)


_ROLLOUT = (jax.jit(_rollout_loss), jax.jit(jax.grad(_rollout_loss)),
            jax.jit(jax.jacfwd(_rollout_loss)))


@pytest.mark.parametrize("omega_scale", [1.0, 1e-8, 0.0])
def test_gradients_through_a_heavy_top_rollout(omega_scale):
    """With respect to omega0 (at the default spin, at 1e-8 of it and at rest: the
    rotations of the first steps are then at or near the identity) and to the inertia."""
    x = np.concatenate([omega_scale * np.asarray(lj.HeavyTop.DEFAULT_OMEGA0), [0.0]])
    _check_gradient(_rollout_loss, x, FD_STEP, FD_RTOL, compiled=_ROLLOUT)
