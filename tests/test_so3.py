"""SO(3) maths: property tests of hat/vee, exp/log, Cayley, differentials, quaternions.

Conventions under test (see lgvi_jax/so3.py): hat(a) b = a x b; right-trivialised
differentials d/de tau(w + e d) = tau(w) hat(D(w) d); left-trivialised ones
d/de tau(w + e d) = hat(D_l(w) d) tau(w).

Most calls go through jit-compiled versions (``jso3``): on CPU, XLA compilation dominates
the runtime of these tests, and one compilation per input shape is much cheaper than eager
op-by-op dispatch (which compiles every primitive separately).
"""

from decimal import Decimal, localcontext
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lgvi_jax  # noqa: F401  (float64)
from lgvi_jax import so3

N = 200
EYE = np.eye(3)

jso3 = SimpleNamespace(
    **{name: jax.jit(getattr(so3, name)) for name in so3.__all__ if name != "is_rotation"}
)
jso3.random_rotation = jax.jit(so3.random_rotation, static_argnums=1)
# vmap-ed versions (jit-compiled once, shared by several tests).
vlog = jax.jit(jax.vmap(so3.log))


def unit_vectors(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def rotation_vectors(seed, n=N, max_angle=np.pi):
    """Random directions, angles uniform in [0, max_angle)."""
    rng = np.random.default_rng(seed)
    return unit_vectors(rng, n) * rng.uniform(0.0, max_angle, size=(n, 1))


def random_rotations(seed, n=N):
    return np.asarray(jso3.random_rotation(jax.random.key(seed), (n,)))


def hat_np(w):
    w = np.asarray(w, dtype=float)
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


E_HAT = np.stack([hat_np(e) for e in EYE])  # E_HAT[j] = hat(e_j)


def axis_angle(n, angles):
    """Rotation vectors angle * n for one unit axis n and several angles."""
    return np.asarray(angles, dtype=float)[:, None] * np.asarray(n, dtype=float)[None, :]


# Special points where the formulas switch branches or are singular in closed form:
# w = 0, tiny, both sides of the Taylor threshold theta = 0.1, close to pi and pi itself.
AXIS = np.array([2.0, -1.0, 2.0]) / 3.0
SPECIAL_ANGLES = [0.0, 1e-12, 1e-8, 1e-5, 0.05, 0.1 - 1e-9, 0.1 + 1e-9, 1.0, np.pi - 1e-6, np.pi]
SPECIAL_W = axis_angle(AXIS, SPECIAL_ANGLES)


# ----------------------------------------------------------------------------- hat / vee


def test_hat_vee_inverse_and_cross_product():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(2, N, 3))
    A = np.asarray(jso3.hat(a))
    assert A.shape == (N, 3, 3)
    np.testing.assert_array_equal(A, -np.swapaxes(A, -1, -2))
    np.testing.assert_array_equal(jso3.vee(A), a)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", A, b), np.cross(a, b), atol=1e-14)
    # vee reads the skew part: adding a symmetric matrix does not change it.
    S = rng.normal(size=(N, 3, 3))
    np.testing.assert_allclose(jso3.vee(A + S + np.swapaxes(S, -1, -2)), a, atol=1e-14)
    # Eager (op-by-op) evaluation works too, and integer input is promoted to float.
    np.testing.assert_array_equal(so3.hat(np.array([1, 2, 3])), hat_np([1, 2, 3]))


def test_adjoint_identity():
    """R hat(w) R^T = hat(R w), i.e. Ad_R = R."""
    R = random_rotations(1)
    w = rotation_vectors(2)
    lhs = R @ jso3.hat(w) @ np.swapaxes(R, -1, -2)
    rhs = jso3.hat(np.einsum("nij,nj->ni", jso3.adjoint(R), w))
    np.testing.assert_allclose(lhs, rhs, atol=1e-14)


# ----------------------------------------------------------------------------- exp


def test_exp_group_properties():
    w = rotation_vectors(3, max_angle=10.0)  # exp is defined for any |w|
    # The first rows: rotations about z, exp(theta e_z) = R_z(theta).
    th = np.array([0.3, 2.0, -1.0])
    w[:3] = th[:, None] * EYE[2]
    R = np.asarray(jax.jit(jax.vmap(so3.exp))(w))
    c, s, o, i = np.cos(th), np.sin(th), np.zeros(3), np.ones(3)
    Rz = np.stack([np.stack([c, -s, o], -1), np.stack([s, c, o], -1), np.stack([o, o, i], -1)], 1)
    np.testing.assert_allclose(R[:3], Rz, atol=1e-15)
    Rt = np.swapaxes(R, -1, -2)
    np.testing.assert_allclose(Rt @ R, np.broadcast_to(EYE, R.shape), atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    Rm = np.asarray(jso3.exp(-w))
    np.testing.assert_allclose(R @ Rm, np.broadcast_to(EYE, R.shape), atol=1e-14)
    np.testing.assert_allclose(Rt, Rm, atol=1e-15)
    # Equivariance: exp(Q w) = Q exp(w) Q^T.
    Q = random_rotations(4)
    Qw = np.einsum("nij,nj->ni", Q, w)
    np.testing.assert_allclose(jso3.exp(Qw), Q @ R @ np.swapaxes(Q, -1, -2), atol=1e-13)
    # One-parameter subgroup: exp(s w) exp(t w) = exp((s + t) w).
    rng = np.random.default_rng(5)
    s, t = rng.uniform(-2.0, 2.0, size=(2, N, 1))
    np.testing.assert_allclose(jso3.exp(s * w) @ jso3.exp(t * w), jso3.exp((s + t) * w), atol=1e-13)


def _dec_sin_cos(x, prec=50):
    """sin and cos in Decimal arithmetic (Taylor series); call inside a 50-digit context."""
    s, c, term, k = Decimal(0), Decimal(0), Decimal(1), 0
    while True:
        if k % 2 == 0:
            c += term if k % 4 == 0 else -term
        else:
            s += term if k % 4 == 1 else -term
        k += 1
        term = term * x / k
        if abs(term) < Decimal(10) ** (-prec):
            return s, c


def _reference_coefficients(theta):
    """sin t/t, (1-cos t)/t^2, (t-sin t)/t^3, 1/t^2 - (1+cos t)/(2 t sin t) at 50 digits."""
    with localcontext() as ctx:
        ctx.prec = 50
        t = Decimal(float(theta))  # the float theta exactly
        s, c = _dec_sin_cos(t)
        s2, c2 = _dec_sin_cos(t / 2)
        a = s / t
        b = (1 - c) / t**2
        cc = (t - s) / t**3
        d = 1 / t**2 - c2 / (2 * t * s2)
        return float(a), float(b), float(cc), float(d)


REF_THETAS = np.array([1e-8, 1e-3, 0.05, 0.0999, 0.1001, 0.7, 2.0, 3.1])


def test_exp_and_jacobians_match_high_precision_reference():
    """Both sides of the Taylor threshold (theta = 0.1) agree with a 50-digit reference."""
    w = REF_THETAS[:, None] * AXIS
    W = np.stack([hat_np(x) for x in w])
    WW = W @ W
    a, b, c, d = (
        np.array(x)[:, None, None]
        for x in zip(*[_reference_coefficients(t) for t in REF_THETAS], strict=True)
    )
    # Round-off of assembling I + a W + b W^2 (entries of W^2 are up to theta^2): a few
    # roundings of u = 1.1e-16 in each coefficient and each term, ~2e-15 at worst (measured
    # up to 1.5e-16 (1 + theta^2)).
    atol = 2e-15 * (1 + REF_THETAS**2)[:, None, None]

    def check(actual, desired):
        assert np.all(np.abs(np.asarray(actual) - desired) <= atol)

    check(jso3.exp(w), EYE + a * W + b * WW)
    check(jso3.dexp(w), EYE - b * W + c * WW)
    check(jso3.dexp_left(w), EYE + b * W + c * WW)
    check(jso3.dexp_inv(w), EYE + 0.5 * W + d * WW)
    check(jso3.dexp_left_inv(w), EYE - 0.5 * W + d * WW)


def test_minus_identity_forms_have_small_relative_error():
    """exp(w) − I and cay(w) − I without cancellation: relative error at round-off for tiny
    angles, where ``exp(w) − I`` computed naively would keep only ~16 − |log10 θ| digits."""
    w = REF_THETAS[:, None] * AXIS
    W = np.stack([hat_np(x) for x in w])
    a, b = (np.array(x)[:, None, None]
            for x in list(zip(*[_reference_coefficients(t) for t in REF_THETAS], strict=True))[:2])
    exact = a * W + b * (W @ W)
    scale = REF_THETAS[:, None, None]  # entries of exp(w) − I are O(theta)
    # A few roundings of u = 1.1e-16 relative to theta (measured up to 1.4e-16 theta);
    # computed as exp(w) − I it would be eps / theta relative.
    assert np.all(np.abs(np.asarray(jso3.exp_minus_identity(w)) - exact) <= 2e-15 * scale)
    k = (4.0 / (4.0 + REF_THETAS**2))[:, None, None]
    exact_cay = k * (W + 0.5 * (W @ W))
    assert np.all(np.abs(np.asarray(jso3.cayley_minus_identity(w)) - exact_cay) <= 2e-15 * scale)
    np.testing.assert_allclose(jso3.exp_minus_identity(w) + EYE, jso3.exp(w), atol=2e-16)
    np.testing.assert_allclose(jso3.cayley_minus_identity(w) + EYE, jso3.cayley(w), atol=2e-16)


def test_coefficient_functions_match_high_precision_reference():
    """The scalar coefficients themselves (private helpers), on both sides of theta = 0.1.

    In the matrices a wrong high-order Taylor term is hidden below round-off (it is
    multiplied by theta^2), so the series are checked here directly.
    """
    thetas = np.array([0.0, 1e-8, 1e-3, 0.05, 0.0999, 0.1001, 0.5, 3.1])
    ref = np.array([[1.0, 0.5, 1 / 6, 1 / 12]] + [_reference_coefficients(t) for t in thetas[1:]])
    got = np.stack(
        [
            np.asarray(f(jnp.asarray(thetas**2)))
            for f in (so3._sinc, so3._one_minus_cos, so3._t_minus_sin, so3._dexp_inv_coeff)
        ],
        -1,
    )
    rel = np.abs(got - ref) / np.abs(ref)
    taylor = thetas < 0.1
    # The series: a few roundings of u = 1.1e-16 (measured up to 1.7e-16).
    assert np.all(rel[taylor] <= 2e-15)
    # Closed forms just above the switch lose digits to cancellation: (t - sin t)/t^3 about
    # eps/t^2, and 1/t^2 - cot(t/2)/(2t) about 12 eps/t^2 ~ 3e-13 relative at t = 0.1 (this
    # costs nothing in the matrices, where the coefficient is multiplied by t^2); measured
    # up to 1.3e-13.
    assert np.all(rel[~taylor] <= 3e-12)


# ----------------------------------------------------------------------------- log


def test_exp_log_roundtrip_random_rotations():
    R = random_rotations(6)
    w = vlog(R)
    assert np.all(np.linalg.norm(w, axis=-1) <= np.pi)
    np.testing.assert_allclose(jso3.exp(w), R, atol=1e-14)


def test_exp_log_roundtrip_near_pi_and_identity():
    rng = np.random.default_rng(7)
    n = unit_vectors(rng, 20)
    Rs = [jso3.exp((np.pi - delta) * n) for delta in [1e-2, 1e-4, 1e-6, 1e-8, 1e-12, 0.0]]
    # Exactly pi, built without exp: R = 2 n n^T - I (exactly symmetric).
    Rs.append(2.0 * n[:, :, None] * n[:, None, :] - EYE)
    Rs.append(np.broadcast_to(EYE, (20, 3, 3)))
    R = np.concatenate([np.asarray(r) for r in Rs])
    w = jso3.log(R)
    # |w| = θ‖n‖ with θ <= float pi and ‖n‖ = 1 to a few ulps, the norm itself rounded: at
    # most pi (1 + 8 eps) ≈ pi + 5.6e-15 (measured pi + 1 ulp, 4.4e-16).
    assert np.all(np.linalg.norm(w, axis=-1) <= np.pi + 6e-15)
    np.testing.assert_allclose(jso3.exp(w), R, atol=1e-14)
    np.testing.assert_array_equal(w[-20:], 0.0)  # log(I) = 0 exactly


def test_log_exp_roundtrip():
    # Generic angles, angles on the near-pi branch, and within 1e-6 of pi.
    rng = np.random.default_rng(8)
    n = unit_vectors(rng, N)
    w = np.concatenate(
        [
            rotation_vectors(9, max_angle=np.pi - 1e-3),
            n * rng.uniform(np.pi - 0.2, np.pi - 1e-6, size=(N, 1)),
            n * (np.pi - 1e-6),
        ]
    )
    # The near-pi branch reads the axis from the symmetric part of R, so the error stays at
    # round-off level; the textbook formula theta/(2 sin theta) vee(R - R^T) would amplify
    # round-off by 1/sin(theta) ~ 1e6 at pi - 1e-6. A few roundings of values up to pi
    # (ulp 4.4e-16) in exp and in log each; measured up to 1.1e-15 (1.6e-15 with
    # --alt-numerics).
    np.testing.assert_allclose(jso3.log(jso3.exp(w)), w, rtol=0, atol=2e-14)


def test_log_exp_roundtrip_small_angles():
    """Tiny rotations keep full relative accuracy (Taylor branch below sin(theta) = 0.01)."""
    scales = np.array([1e-300, 1e-12, 1e-9, 1e-5, 1e-3, 0.01 - 1e-9, 0.01 + 1e-9, 0.02])
    u = unit_vectors(np.random.default_rng(10), 50)
    w = scales[:, None, None] * u  # (8, 50, 3)
    out = np.asarray(jso3.log(jso3.exp(w)))
    # A few roundings of u = 1.1e-16 relative to |w| through exp and log (measured up to
    # 2.2e-16 |w|).
    assert np.all(np.abs(out - w) <= 2e-15 * scales[:, None, None])


def test_rotation_angle():
    w = rotation_vectors(11, max_angle=np.pi)
    np.testing.assert_allclose(
        jso3.rotation_angle(jso3.exp(w)), np.linalg.norm(w, axis=-1), atol=1e-14
    )
    special = np.stack([EYE, np.diag([1.0, -1.0, -1.0])])
    np.testing.assert_array_equal(jso3.rotation_angle(special), [0.0, np.pi])
    g = jax.jit(jax.vmap(jax.grad(so3.rotation_angle)))(special)
    assert np.all(np.isfinite(g))


# ----------------------------------------------------------------------------- Cayley


def test_cayley_properties():
    w = rotation_vectors(12, max_angle=20.0)  # the Cayley map is defined for every w
    R = np.asarray(jax.jit(jax.vmap(so3.cayley))(w))
    np.testing.assert_allclose(
        np.swapaxes(R, -1, -2) @ R, np.broadcast_to(EYE, R.shape), atol=1e-14
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-14)
    # Definition: (I - hat(w)/2)^{-1} (I + hat(w)/2).
    W = np.asarray(jso3.hat(w))
    np.testing.assert_allclose(R, jnp.linalg.solve(EYE - W / 2, EYE + W / 2), atol=1e-14)
    # Rotation angle 2 arctan(|w|/2).
    angle = 2 * np.arctan(np.linalg.norm(w, axis=-1) / 2)
    np.testing.assert_allclose(jso3.rotation_angle(R), angle, atol=1e-14)
    # cayley_inv o cayley = id (relative: |w| up to 20 here, where the inverse amplifies
    # the rounding of R by 1 + |w|²/4 <= 101: eps x 101 ≈ 2.2e-14 per rounding; measured
    # up to 4.6e-14).
    w_back = np.asarray(jso3.cayley_inv(R))
    np.testing.assert_allclose(w_back, w, rtol=1e-12, atol=1e-15)
    # Definition of the inverse: hat(w) = 2 (R - I)(R + I)^{-1}. The reference solves with
    # R + I, whose condition number grows like |w|^2/4 <= 100: looser tolerance.
    Rt_plus, Rt_minus = np.swapaxes(R + EYE, -1, -2), np.swapaxes(R - EYE, -1, -2)
    W_ref = 2 * np.swapaxes(np.linalg.solve(Rt_plus, Rt_minus), -1, -2)
    np.testing.assert_allclose(jso3.hat(w_back), W_ref, rtol=1e-12, atol=1e-12)


def test_cayley_of_cayley_inv():
    R = random_rotations(13)
    # cayley_inv is singular at angle pi (|w| = 2 tan(angle/2) -> inf) and the round trip
    # loses ~eps/(pi - angle)^2 there, so keep angles below 3.0 (|w| < 30).
    R = np.concatenate([R[np.asarray(jso3.rotation_angle(R)) < 3.0], EYE[None]])
    assert len(R) > 0.8 * N
    w = jso3.cayley_inv(R)
    np.testing.assert_allclose(jso3.cayley(w), R, atol=1e-13)
    np.testing.assert_array_equal(w[-1], 0.0)


# ------------------------------------------------------------------ differentials


def _trivialised(f, side):
    """jit(vmap(w -> (D, M))): D the trivialised differential of f at w recovered from
    jax.jacfwd, M the stack of the matrices f^T df/dw_j (right) or df/dw_j f^T (left),
    which must be skew for the trivialisation to exist."""

    def one(w):
        J = jax.jacfwd(f)(w)  # J[k, l, j] = d f_kl / d w_j
        R = f(w)
        if side == "right":
            M = jnp.einsum("ki,klj->jil", R, J)  # M_j = R^T dR/dw_j
        else:
            M = jnp.einsum("klj,il->jki", J, R)  # M_j = dR/dw_j R^T
        return jnp.swapaxes(so3.vee(M), -1, -2), M

    return jax.jit(jax.vmap(one))


@pytest.mark.parametrize(
    ("name", "tau", "side", "max_angle"),
    [
        ("dexp", so3.exp, "right", 2 * np.pi - 0.5),
        ("dexp_left", so3.exp, "left", 2 * np.pi - 0.5),
        ("dcayley", so3.cayley, "right", 20.0),
        ("dcayley_left", so3.cayley, "left", 20.0),
    ],
)
def test_differentials_match_autodiff(name, tau, side, max_angle):
    w = np.concatenate([rotation_vectors(14, max_angle=max_angle), SPECIAL_W])
    D_ad, M = _trivialised(tau, side)(w)
    # Autodiff's dR/dw R^T: sums of products of O(1) entries, a few ulps each (measured
    # up to 1.4e-15).
    np.testing.assert_allclose(M, -np.swapaxes(M, -1, -2), atol=1e-13)
    D = np.asarray(getattr(jso3, name)(w))
    np.testing.assert_allclose(D, D_ad, atol=1e-14)
    # The inverse: against the numerical inverse of the autodiff matrix, and D D^{-1} = I.
    # For dexp the points stay away from |w| = 2 pi, where J_r is singular: J_r^{-1} has
    # norm up to (|w|/2) / sin(|w|/2) ≈ 12 at |w| = 2 pi - 0.5, and inverting a matrix of
    # condition κ errs by ~eps κ ‖J_r^{-1}‖ ≈ 2.2e-16 x 12 x 12 ≈ 3e-14 on each side
    # (LAPACK's inverse, the closed form; measured up to 7e-14), hence 1e-12.
    D_inv = np.asarray(getattr(jso3, name + "_inv")(w))
    np.testing.assert_allclose(D_inv, np.linalg.inv(D_ad), rtol=0, atol=1e-12)
    np.testing.assert_allclose(D @ D_inv, np.broadcast_to(EYE, D.shape), atol=1e-13)


def test_dexp_inv_near_zero_and_pi():
    """dexp(w) dexp_inv(w) = I to round-off across the branch switch and up to pi."""
    w = np.concatenate([SPECIAL_W, rotation_vectors(15, max_angle=np.pi)])
    P = jso3.dexp(w) @ jso3.dexp_inv(w)
    # Three products of entries up to ‖dexp⁻¹‖ ≈ π/2 per entry, each factor a few ulps
    # off: ~10 roundings of ulp(2) = 4.4e-16.
    np.testing.assert_allclose(P, np.broadcast_to(EYE, P.shape), atol=1e-14)
    np.testing.assert_array_equal(jso3.dexp_inv(np.zeros(3)), EYE)


@pytest.mark.parametrize("tau, tau_minus_identity",
                         [(so3.exp, so3.exp_minus_identity),
                          (so3.cayley, so3.cayley_minus_identity)], ids=["exp", "cayley"])
def test_map_minus_identity_derivatives_equal_those_of_the_map(tau, tau_minus_identity):
    """exp_minus_identity and cayley_minus_identity carry their differentials in closed
    form (custom JVPs, tau(w) hat(D(w) d) with D = J_r or the Cayley map's (4/(4+|w|^2))
    (I - hat(w)/2)); exp and cayley are differentiated by autodiff through their formulas.
    tau(w) - I and tau(w) have the same derivatives: first and second, forward and reverse,
    on both sides of exp's Taylor switch, near pi and beyond."""
    w = np.concatenate([SPECIAL_W, rotation_vectors(15, max_angle=2 * np.pi - 0.5)])

    @jax.jit
    @jax.vmap
    def derivatives(w):
        return (jax.jacfwd(tau)(w), jax.jacfwd(tau_minus_identity)(w),
                jax.jacrev(tau_minus_identity)(w),
                jax.jacfwd(jax.jacfwd(tau))(w),
                jax.jacfwd(jax.jacrev(tau_minus_identity))(w))

    J, J_fwd, J_rev, H, H_new = (np.asarray(x) for x in derivatives(w))
    # Entries O(1), each a few dozen roundings (~1e-15); the coefficient functions' closed
    # forms just above theta = 0.1 lose ~eps/theta^2 to cancellation (their derivatives
    # ~eps/theta^2 more, ~1e-14 in the second derivatives): 10x margins.
    np.testing.assert_allclose(J_fwd, J, rtol=0, atol=1e-14)
    np.testing.assert_allclose(J_rev, J, rtol=0, atol=1e-14)
    np.testing.assert_allclose(H_new, H, rtol=0, atol=1e-13)


def test_differential_conventions_by_finite_differences():
    """Independent of autodiff: tau(w + h d) - tau(w - h d) ~ 2 h tau(w) hat(D(w) d)."""
    w = np.array([0.4, -1.1, 0.7])
    d = np.array([0.3, 0.2, -0.5])
    h = 1e-6
    pts = np.stack([w + h * d, w - h * d, w])
    for tau, D in [(jso3.exp, jso3.dexp), (jso3.cayley, jso3.dcayley)]:
        Rp, Rm, R = np.asarray(tau(pts))
        fd = (Rp - Rm) / (2 * h)
        # Central differences: error ~ h^2 + eps/h ~ 1e-10.
        np.testing.assert_allclose(fd, R @ hat_np(np.asarray(D(w)) @ d), atol=1e-9)


# ----------------------------------------------------------------------------- gradients


def _weights(seed, shape):
    return jnp.asarray(np.random.default_rng(seed).normal(size=shape))


M33 = _weights(20, (3, 3))
M3 = _weights(21, (3,))

SCALAR_FNS = {
    "exp": lambda w: jnp.sum(M33 * so3.exp(w)),
    "exp_minus_identity": lambda w: jnp.sum(M33 * so3.exp_minus_identity(w)),
    "cayley": lambda w: jnp.sum(M33 * so3.cayley(w)),
    "cayley_minus_identity": lambda w: jnp.sum(M33 * so3.cayley_minus_identity(w)),
    "dexp": lambda w: jnp.sum(M33 * so3.dexp(w)),
    "dexp_inv": lambda w: jnp.sum(M33 * so3.dexp_inv(w)),
    "log_exp": lambda w: jnp.sum(M3 * so3.log(so3.exp(w))),
}


def log_of_matrix(R):
    return jnp.sum(M3 * so3.log(R))


def _central_fd_points(x, h):
    """x + h e_i and x - h e_i for every coordinate i: shape (2, x.size, *x.shape)."""
    steps = h * np.eye(x.size).reshape(x.size, *x.shape)
    return np.stack([x + steps, x - steps])


def _check_gradient(f, points, fd_points, h=1e-6):
    """grad f finite at all points; equal to central differences at fd_points."""
    grads = np.asarray(jax.jit(jax.vmap(jax.grad(f)))(np.concatenate([points, fd_points])))
    assert np.all(np.isfinite(grads))
    fv = jax.jit(jax.vmap(jax.vmap(jax.vmap(f))))
    vals = np.asarray(fv(np.stack([_central_fd_points(x, h) for x in fd_points])))
    for g, (fp, fm) in zip(grads[len(points) :], vals, strict=True):
        fd = ((fp - fm) / (2 * h)).reshape(g.shape)
        # Central differences with h = 1e-6: truncation ~h^2 ~ 1e-12, round-off
        # ~eps/h ~ 1e-10; relative 1e-6 leaves a wide margin but catches any wrong term.
        assert np.linalg.norm(g - fd) <= 1e-6 * max(np.linalg.norm(g), 1.0), (g, fd)


# Finite-difference points: two generic ones, one inside the Taylor branch (|w| = 0.05) and
# one on the near-pi branch of log (|w| = 3.1).
AXIS2 = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)  # no ties between |n_i| (log's pi branch)
FD_W = np.stack([[0.4, -1.1, 0.7], [-2.0, 0.5, 1.5], 0.05 * AXIS2, 3.1 * AXIS2])


@pytest.mark.parametrize("name", list(SCALAR_FNS))
def test_gradients_finite_and_match_finite_differences(name):
    """Finite at w = 0, |w| = 1e-8, near the Taylor switch, within 1e-6 of pi and at pi."""
    _check_gradient(SCALAR_FNS[name], SPECIAL_W, FD_W)


@pytest.mark.parametrize("name", ["exp", "exp_minus_identity", "cayley_minus_identity",
                                  "dexp_inv"])
def test_second_derivatives_finite(name):
    # Newton iterations of the integrators differentiate residuals built from exp/dexp_inv,
    # so their Jacobians must be differentiable too (also through the Taylor branch).
    H = jax.jit(jax.vmap(jax.hessian(SCALAR_FNS[name])))(SPECIAL_W)
    assert np.all(np.isfinite(H))


def test_log_gradient():
    """log as a function of the 9 matrix entries, on each of its three branches."""
    special = np.concatenate([jso3.exp(SPECIAL_W), (2 * np.outer(AXIS, AXIS) - EYE)[None]])
    # Near identity, generic, near pi. The FD directions leave SO(3), and log's off-manifold
    # extension depends on which column the pi branch reads, so the axis avoids ties.
    fd_R = np.asarray(jso3.exp(np.stack([0.005 * AXIS2, FD_W[0], 3.1 * AXIS2])))
    _check_gradient(log_of_matrix, special, fd_R)


def test_derivatives_at_zero_are_exact():
    @jax.jit
    def derivatives():
        z = jnp.zeros(3)
        return (
            jax.grad(SCALAR_FNS["exp"])(z),
            jax.hessian(SCALAR_FNS["exp"])(z),
            jax.jacfwd(so3.log)(jnp.eye(3)),
            jax.jacfwd(lambda w: so3.log(so3.exp(w)))(z),
            jax.jacfwd(so3.dexp_inv)(z),
        )

    g, H, J_log, J_log_exp, J_dexp_inv = derivatives()
    # d/dw_j exp(w)|_0 = hat(e_j)  and  d^2/dw_i dw_j exp(w)|_0 = (E_i E_j + E_j E_i)/2.
    np.testing.assert_allclose(g, np.einsum("kl,jkl->j", M33, E_HAT), atol=1e-15)
    EE = np.einsum("ikl,jlm->ijkm", E_HAT, E_HAT)
    H_exact = np.einsum("km,ijkm->ij", M33, 0.5 * (EE + np.swapaxes(EE, 0, 1)))
    np.testing.assert_allclose(H, H_exact, atol=1e-15)
    # log near the identity is vee to first order: d log_i(R)/dR_kl at I = d vee_i/dR_kl,
    # which is hat(e_i)_kl / 2 (vee reads (W - W^T)/2).
    np.testing.assert_allclose(J_log, 0.5 * E_HAT, atol=1e-15)
    # d/dw log(exp(w)) = I at w = 0; d/dw dexp_inv(w) at 0 = d/dw hat(w)/2.
    np.testing.assert_allclose(J_log_exp, EYE, atol=1e-15)
    np.testing.assert_allclose(J_dexp_inv, 0.5 * np.moveaxis(E_HAT, 0, -1), atol=1e-15)


# ---------------------------------------------------------------- batching and jit


def test_vmap_matches_loop_and_batch_dims():
    R = random_rotations(22)
    batched = np.asarray(vlog(R))
    looped = np.stack([np.asarray(jso3.log(r)) for r in R[:20]])
    # Batched and unbatched kernels may round differently: a few ulps of values up to pi.
    np.testing.assert_allclose(batched[:20], looped, rtol=0, atol=1e-14)
    # Leading batch dimensions (no vmap) give the same as vmap over a flat batch.
    Rb = R[:12].reshape(3, 4, 3, 3)
    out = jso3.log(Rb)
    assert out.shape == (3, 4, 3)
    np.testing.assert_allclose(out, batched[:12].reshape(3, 4, 3), atol=1e-15)


# ------------------------------------------------------------------ quaternions


def quat_mul(p, q):
    """Hamilton product, scalar first."""
    p0, pv, q0, qv = p[..., :1], p[..., 1:], q[..., :1], q[..., 1:]
    return np.concatenate(
        [p0 * q0 - np.sum(pv * qv, -1, keepdims=True), p0 * qv + q0 * pv + np.cross(pv, qv)],
        axis=-1,
    )


def test_quaternion_conventions_and_roundtrip():
    rng = np.random.default_rng(24)
    q = rng.normal(size=(N, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    R = np.asarray(jso3.quat_to_rotation(q))
    assert so3.is_rotation(R, atol=1e-14)
    # Homomorphism: R(p q) = R(p) R(q); and q, -q, 2q give the same rotation.
    p = q[::-1]
    np.testing.assert_allclose(jso3.quat_to_rotation(quat_mul(p, q)), R[::-1] @ R, atol=1e-14)
    np.testing.assert_allclose(jso3.quat_to_rotation(-2.0 * q), R, atol=1e-15)
    # Axis-angle: q = (cos(t/2), sin(t/2) n) is exp(t n).
    w = rotation_vectors(25)
    t = np.linalg.norm(w, axis=-1, keepdims=True)
    qw = np.concatenate([np.cos(t / 2), np.sin(t / 2) * w / t], axis=-1)
    np.testing.assert_allclose(jso3.quat_to_rotation(qw), jso3.exp(w), atol=1e-14)
    # Round trips (rotation_to_quat returns the representative with q_0 >= 0).
    q_back = np.asarray(jso3.rotation_to_quat(R))
    np.testing.assert_allclose(np.linalg.norm(q_back, axis=-1), 1.0, atol=1e-15)
    assert np.all(q_back[:, 0] >= 0)
    np.testing.assert_allclose(q_back, q * np.sign(q[:, :1]), atol=1e-14)
    np.testing.assert_allclose(jso3.quat_to_rotation(q_back), R, atol=1e-14)


def test_rotation_to_quat_all_shepperd_branches():
    # Angle pi about each coordinate axis (the largest diagonal entry of K = 4 q q^T is
    # q_1^2, q_2^2, q_3^2 in turn), the identity (q_0^2), and generic / near-pi rotations.
    R = np.stack(
        [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]), EYE]
    )
    q = np.asarray(jso3.rotation_to_quat(R))
    np.testing.assert_allclose(np.abs(q), np.eye(4)[[1, 2, 3, 0]], atol=1e-15)
    Rn = jso3.exp(axis_angle(AXIS2, [np.pi - 1e-9, np.pi - 1e-3, 2.0, 1e-9]))
    np.testing.assert_allclose(jso3.quat_to_rotation(jso3.rotation_to_quat(Rn)), Rn, atol=1e-15)
    g = jax.jit(jax.jacfwd(so3.rotation_to_quat))(R)
    assert np.all(np.isfinite(g))


# ---------------------------------------------------------------- random / projection


def test_random_rotation_uniform():
    n = 20000
    R = random_rotations(26, n)
    assert R.shape == (n, 3, 3)
    assert so3.is_rotation(R, atol=1e-13)
    # Under the Haar measure E[R] = 0 and each entry has variance 1/3, so the sample mean of
    # an entry has standard deviation sqrt(1/(3n)) ~ 0.004: allow 6 sigma.
    assert np.abs(R.mean(axis=0)).max() < 6 * np.sqrt(1 / (3 * n))
    # The angle has CDF (t - sin t)/pi. Dvoretzky-Kiefer-Wolfowitz: P(sup|F_n - F| > eps)
    # <= 2 exp(-2 n eps^2) = 1e-6 for eps = sqrt(log(2e6)/(2n)) ~ 0.019.
    t = np.sort(np.asarray(jso3.rotation_angle(R)))
    F = (t - np.sin(t)) / np.pi
    ecdf = np.arange(1, n + 1) / n
    assert np.max(np.abs(ecdf - F)) < np.sqrt(np.log(2e6) / (2 * n))


def test_project_to_so3():
    rng = np.random.default_rng(27)
    R = random_rotations(28)
    M = R + 0.1 * rng.normal(size=R.shape)
    P = np.asarray(jso3.project_to_so3(M))
    assert so3.is_rotation(P, atol=1e-14)
    np.testing.assert_allclose(jso3.project_to_so3(P), P, atol=1e-15)  # idempotent
    np.testing.assert_allclose(jso3.project_to_so3(R), R, atol=1e-15)  # identity on SO(3)
    # Optimality (orthogonal Procrustes): P^T M is symmetric, and P is no farther from M than
    # the rotation that M was built from.
    PtM = np.swapaxes(P, -1, -2) @ M
    np.testing.assert_allclose(PtM, np.swapaxes(PtM, -1, -2), atol=1e-14)
    assert np.all(np.linalg.norm(P - M, axis=(-2, -1)) <= np.linalg.norm(R - M, axis=(-2, -1)))
    # Determinant fix: a reflected matrix is still projected onto a rotation.
    assert so3.is_rotation(jso3.project_to_so3(-M), atol=1e-14)


def test_project_to_so3_derivative():
    R = random_rotations(29)[:3]
    dM = np.random.default_rng(30).normal(size=(3, 3, 3))
    # At a rotation (all singular values 1, where differentiating the SVD factors gives nan)
    # the tangent map is dM -> R skew(R^T dM).
    _, t = jax.jit(lambda x, dx: jax.jvp(so3.project_to_so3, (x,), (dx,)))(R, dM)
    RtdM = np.swapaxes(R, -1, -2) @ dM
    np.testing.assert_allclose(t, R @ (0.5 * (RtdM - np.swapaxes(RtdM, -1, -2))), atol=1e-14)
    # Reverse mode at rotations and at generic matrices, against central differences.
    f = lambda X: jnp.sum(M33 * so3.project_to_so3(X))  # noqa: E731
    _check_gradient(f, R, R + 0.3 * dM)


def test_is_rotation_and_orthogonality_error():
    R = np.asarray(jso3.random_rotation(jax.random.key(31), 5))  # shape given as an int
    assert R.shape == (5, 3, 3)
    assert so3.is_rotation(R) is True
    assert so3.is_rotation(R[0]) is True
    assert so3.is_rotation(-R[0]) is False  # reflection: det -1
    assert so3.is_rotation(2 * R[0]) is False
    assert so3.is_rotation(R[0] + 1e-8) is False
    assert so3.is_rotation(R[0] + 1e-8, atol=1e-6) is True
    assert so3.is_rotation(np.eye(2)) is False
    assert so3.is_rotation(np.full((3, 3), np.nan)) is False
    with pytest.raises(TypeError, match="concrete"):
        jax.jit(so3.is_rotation)(R[0])
    err = np.asarray(jso3.orthogonality_error(np.concatenate([R, 2 * EYE[None]])))
    # Frobenius norm of 9 entries of RᵀR − I, each a sum of 3 products (3 roundings of
    # ~1, plus R's own departure from orthogonality, a few ulps): ≲ 3 x 1.3e-15 ≈ 4e-15
    # at worst (measured up to 1.4e-15).
    np.testing.assert_allclose(err[:-1], 0.0, atol=4e-14)
    np.testing.assert_allclose(err[-1], 3 * np.sqrt(3), rtol=1e-15)  # |4I - I|_F
    assert np.all(np.isfinite(jax.jit(jax.grad(so3.orthogonality_error))(EYE)))
