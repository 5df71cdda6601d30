r"""The rotation group SO(3): exponential, logarithm, Cayley map and their differentials.

All functions are pure functions of ``jax.numpy`` arrays. They accept leading batch
dimensions (vectors ``(..., 3)``, matrices ``(..., 3, 3)``), work in float64 (the package
switches on ``jax_enable_x64``) and can be ``jit``-ed, ``vmap``-ed and differentiated
(``grad``, ``jacfwd``, ``jacrev``) -- including at the identity and close to rotations by
:math:`\pi`, where the textbook formulas divide by zero.

**Conventions.** The Lie algebra :math:`\mathfrak{so}(3)` is identified with
:math:`\mathbb{R}^3` by the hat map

.. math::  \hat w = \begin{pmatrix} 0 & -w_3 & w_2 \\ w_3 & 0 & -w_1 \\ -w_2 & w_1 & 0
           \end{pmatrix}, \qquad \hat a\, b = a \times b,

with inverse :func:`vee`. With :math:`\theta = |w|`:

* exponential (Rodrigues): :math:`\exp(w) = I + \frac{\sin\theta}{\theta}\hat w +
  \frac{1-\cos\theta}{\theta^2}\hat w^2`, a rotation by angle :math:`\theta` about
  :math:`w/\theta`;
* logarithm: the inverse of :math:`\exp` on :math:`|w| \le \pi` (:func:`log`);
* Cayley map: :math:`\operatorname{cay}(w) = (I - \tfrac12\hat w)^{-1}(I + \tfrac12\hat w)
  = I + \frac{4}{4+\theta^2}\bigl(\hat w + \tfrac12\hat w^2\bigr)`, a rotation by angle
  :math:`2\arctan(\theta/2)`, with inverse :math:`\operatorname{cay}^{-1}(R) =
  \frac{2}{1+\operatorname{tr}R}\,\operatorname{vee}(R - R^\top)`;
* adjoint action: :math:`R\hat w R^\top = \widehat{Rw}`, so :math:`\mathrm{Ad}_R = R`.

**Differentials (right-trivialised).** Variational integrators update
:math:`R_{k+1} = R_k\,\tau(\xi_k)` with :math:`\tau \in \{\exp, \operatorname{cay}\}`, so the
differentials are trivialised on the right (body frame): for :math:`\tau` and a direction
:math:`\delta \in \mathbb{R}^3`

.. math::  \frac{d}{d\varepsilon}\Big|_{\varepsilon=0} \tau(w + \varepsilon\delta)
           = \tau(w)\, \widehat{D_\tau(w)\,\delta},

* :func:`dexp`: :math:`D_{\exp}(w) = J_r(w) = I - \frac{1-\cos\theta}{\theta^2}\hat w +
  \frac{\theta-\sin\theta}{\theta^3}\hat w^2` (the right Jacobian of Sola et al.);
* :func:`dexp_inv`: :math:`J_r(w)^{-1} = I + \tfrac12\hat w + \Bigl(\frac{1}{\theta^2} -
  \frac{1+\cos\theta}{2\theta\sin\theta}\Bigr)\hat w^2` (valid for :math:`\theta < 2\pi`);
* :func:`dcayley`: :math:`D_{\operatorname{cay}}(w) = \frac{4}{4+\theta^2}(I - \tfrac12\hat w)`;
* :func:`dcayley_inv`: :math:`D_{\operatorname{cay}}(w)^{-1} = I + \tfrac12\hat w +
  \tfrac14 w w^\top`.

The left-trivialised versions, :math:`\frac{d}{d\varepsilon}\tau(w + \varepsilon\delta) =
\widehat{D^{l}_\tau(w)\delta}\,\tau(w)`, satisfy :math:`D^l_\tau(w) = D_\tau(-w) =
\tau(w) D_\tau(w)` (because :math:`\tau(-w) = \tau(w)^{-1}`); they are :func:`dexp_left`
(:math:`J_l`), :func:`dexp_left_inv`, :func:`dcayley_left` and :func:`dcayley_left_inv`.

**Numerical safety.** The coefficient functions of :math:`\theta` (e.g.
:math:`\sin\theta/\theta`) are evaluated by a Taylor polynomial in :math:`\theta^2` for small
:math:`\theta` and by the closed form otherwise. Both branches are computed and one is
selected with ``jnp.where``; the closed-form branch is fed a harmless substitute argument
wherever it is not selected (the "double where" trick), so that no ``inf``/``nan`` appears in
either branch and reverse-mode gradients stay finite. The logarithm has three branches (near
the identity, generic, near :math:`\theta = \pi`, where the axis is read from the symmetric
part of :math:`R`).

References: A. Iserles, H. Z. Munthe-Kaas, S. P. Nørsett, A. Zanna, "Lie-group methods",
*Acta Numerica* 9 (2000); E. Hairer, C. Lubich, G. Wanner, *Geometric Numerical
Integration*, 2nd ed., Springer 2006, §IV.8; J. Solà, J. Deray, D. Atchuthan, "A micro Lie
theory for state estimation in robotics", arXiv:1812.01537 (2018) (Jacobians); S. W.
Shepperd, "Quaternion from rotation matrix", *J. Guidance and Control* 1 (1978).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._checks import is_concrete

__all__ = [
    "adjoint",
    "cayley",
    "cayley_inv",
    "cayley_minus_identity",
    "dcayley",
    "dcayley_inv",
    "dcayley_left",
    "dcayley_left_inv",
    "dexp",
    "dexp_inv",
    "dexp_left",
    "dexp_left_inv",
    "exp",
    "exp_minus_identity",
    "hat",
    "is_rotation",
    "log",
    "orthogonality_error",
    "project_to_so3",
    "quat_to_rotation",
    "random_rotation",
    "rotation_angle",
    "rotation_to_quat",
    "vee",
]

# Below this value of theta^2 (theta < 0.1) the coefficient functions of theta are evaluated
# by their Taylor polynomials in theta^2. The polynomials below are truncated where the first
# omitted term is < 1e-17 at theta = 0.1, so they are exact to round-off on the whole branch.
# Just above the threshold the closed forms of (t - sin t)/t^3 and of the dexp_inv
# coefficient lose up to ~12 eps/theta^2 ~ 3e-13 (relative) to cancellation; that loss only
# enters multiplied by theta^2 (the coefficients multiply hat(w)^2), i.e. at round-off level
# in the matrices.
_TAYLOR_THETA_SQ = 1e-2

# log: Taylor branch when sin(theta)^2 < 1e-4 and cos(theta) > 0 (theta < ~0.01); axis from
# the symmetric part when sin(theta)^2 < 1e-2 and cos(theta) < 0 (pi - theta < ~0.1). The
# generic formula theta / (2 sin theta) * vee(R - R^T) amplifies round-off in R by the factor
# theta / (2 sin theta), which is <= pi / 0.2 ~ 16 on the generic branch (near pi it would
# grow like 1/(pi - theta), hence the separate branch there).
_LOG_SMALL_SIN_SQ = 1e-4
_LOG_PI_SIN_SQ = 1e-2


# ----------------------------------------------------------------------------- helpers


def _as_float(x: Any) -> jax.Array:
    """``x`` as a floating-point array (integers are promoted to the default float)."""
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def _eye_like(x: jax.Array) -> jax.Array:
    """The 3x3 identity with the dtype of ``x``."""
    return jnp.eye(3, dtype=x.dtype)


def _hat_sq(w: jax.Array) -> jax.Array:
    r""":math:`\hat w^2 = w w^\top - |w|^2 I`."""
    return _outer(w) - _theta_sq(w)[..., None, None] * _eye_like(w)


def _outer(w: jax.Array) -> jax.Array:
    r""":math:`w w^\top`."""
    return w[..., :, None] * w[..., None, :]


def _poly(x: jax.Array, coeffs: tuple[float, ...]) -> jax.Array:
    """Horner evaluation of ``sum_k coeffs[k] * x**k``."""
    out = jnp.full_like(x, coeffs[-1])
    for c in reversed(coeffs[:-1]):
        out = out * x + c
    return out


def _coefficients(theta_sq: jax.Array, *specs) -> tuple[jax.Array, ...]:
    """Functions of theta, each from its Taylor coefficients in theta^2 or its closed form;
    ``specs``: ``(taylor, closed)`` pairs.

    ``closed(theta)`` is only ever evaluated at ``theta >= 0.1`` (double-where trick), so it
    may divide by ``theta`` freely; gradients through the unselected branch are exactly zero.
    For one angle (a 0-d ``theta_sq``) one ``lax.cond`` for all of them: only the branch
    taken is computed (under ``vmap`` JAX selects between both, as ``where`` does), so that
    the closed forms' trigonometry, never needed at the small angles of a step, costs
    nothing there.
    """

    def series(t2):
        return tuple(_poly(t2, taylor) for taylor, _ in specs)

    def closed_form(t2):
        t = jnp.sqrt(jnp.where(t2 < _TAYLOR_THETA_SQ, 1.0, t2))
        return tuple(closed(t) for _, closed in specs)

    small = theta_sq < _TAYLOR_THETA_SQ
    if jnp.ndim(theta_sq) == 0:
        return jax.lax.cond(small, series, closed_form, theta_sq)
    return tuple(jnp.where(small, a, b)
                 for a, b in zip(series(theta_sq), closed_form(theta_sq), strict=True))


def _coefficient(theta_sq: jax.Array, taylor: tuple[float, ...], closed) -> jax.Array:
    """One function of theta (:func:`_coefficients`)."""
    return _coefficients(theta_sq, (taylor, closed))[0]


def _theta_sq(w: jax.Array) -> jax.Array:
    return jnp.sum(w * w, axis=-1)


# sin(t)/t = sum (-1)^k t^2k / (2k+1)!
_SINC = (
    (1.0, -1.0 / 6, 1.0 / 120, -1.0 / 5040, 1.0 / 362880, -1.0 / 39916800),
    lambda t: jnp.sin(t) / t,
)


def _sinc(theta_sq: jax.Array) -> jax.Array:
    return _coefficient(theta_sq, *_SINC)


# (1 - cos t)/t^2 = sum (-1)^k t^2k / (2k+2)!   (closed form 2 sin^2(t/2)/t^2: no cancellation)
_ONE_MINUS_COS = (
    (0.5, -1.0 / 24, 1.0 / 720, -1.0 / 40320, 1.0 / 3628800, -1.0 / 479001600),
    lambda t: 2.0 * jnp.sin(0.5 * t) ** 2 / (t * t),
)


def _one_minus_cos(theta_sq: jax.Array) -> jax.Array:
    return _coefficient(theta_sq, *_ONE_MINUS_COS)


# (t - sin t)/t^3 = sum (-1)^k t^2k / (2k+3)!
_T_MINUS_SIN = (
    (1.0 / 6, -1.0 / 120, 1.0 / 5040, -1.0 / 362880, 1.0 / 39916800, -1.0 / 6227020800),
    lambda t: (t - jnp.sin(t)) / (t * t * t),
)


def _t_minus_sin(theta_sq: jax.Array) -> jax.Array:
    return _coefficient(theta_sq, *_T_MINUS_SIN)


# 1/t^2 - (1 + cos t)/(2 t sin t) = 1/t^2 - cot(t/2)/(2t)
#   = 1/12 + t^2/720 + t^4/30240 + t^6/1209600 + t^8/47900160 + ...   (from the Laurent
#   series of cot). cot(t/2) is written as cos(t/2)/sin(t/2) so that t = pi is not 0/0.
_DEXP_INV = (
    (1.0 / 12, 1.0 / 720, 1.0 / 30240, 1.0 / 1209600, 1.0 / 47900160),
    lambda t: 1.0 / (t * t) - jnp.cos(0.5 * t) / (2.0 * t * jnp.sin(0.5 * t)),
)


def _dexp_inv_coeff(theta_sq: jax.Array) -> jax.Array:
    return _coefficient(theta_sq, *_DEXP_INV)


# ------------------------------------------------------------------------- hat and vee


def hat(w: Any) -> jax.Array:
    r"""Skew-symmetric matrix of a vector, ``(..., 3) -> (..., 3, 3)``.

    :math:`\hat w = \begin{pmatrix} 0 & -w_3 & w_2 \\ w_3 & 0 & -w_1 \\ -w_2 & w_1 & 0
    \end{pmatrix}`, so that :math:`\hat a\, b = a \times b`.
    """
    w = _as_float(w)
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack(
        [
            jnp.stack([o, -z, y], axis=-1),
            jnp.stack([z, o, -x], axis=-1),
            jnp.stack([-y, x, o], axis=-1),
        ],
        axis=-2,
    )


def vee(W: Any) -> jax.Array:
    r"""Vector of the skew part of a matrix, ``(..., 3, 3) -> (..., 3)``; inverse of :func:`hat`.

    Reads :math:`\tfrac12(W - W^\top)`, i.e. :math:`\operatorname{vee}(W) =
    \tfrac12(W_{32} - W_{23},\ W_{13} - W_{31},\ W_{21} - W_{12})`, which is exact on skew
    matrices and the orthogonal projection onto :math:`\mathfrak{so}(3)` otherwise.
    """
    W = _as_float(W)
    return 0.5 * jnp.stack(
        [
            W[..., 2, 1] - W[..., 1, 2],
            W[..., 0, 2] - W[..., 2, 0],
            W[..., 1, 0] - W[..., 0, 1],
        ],
        axis=-1,
    )


def adjoint(R: Any) -> jax.Array:
    r"""Adjoint representation :math:`\mathrm{Ad}_R` on :math:`\mathfrak{so}(3) \cong
    \mathbb{R}^3`, which is :math:`R` itself.

    Identity: :math:`R\,\hat w\,R^\top = \widehat{R w}` for every rotation :math:`R`.
    """
    return _as_float(R)


# ------------------------------------------------------------------- exp and log


def exp(w: Any) -> jax.Array:
    r"""Exponential map :math:`\mathfrak{so}(3) \to SO(3)` (Rodrigues), ``(..., 3) -> (..., 3, 3)``.

    :math:`\exp(w) = I + \frac{\sin\theta}{\theta}\hat w + \frac{1-\cos\theta}{\theta^2}\hat
    w^2`, :math:`\theta = |w|`: the rotation by angle :math:`\theta` about :math:`w/\theta`.
    Taylor branch for :math:`\theta < 0.1`; values and all derivatives are finite and
    accurate at and near :math:`w = 0`.
    """
    w = _as_float(w)
    t2 = _theta_sq(w)
    a, b = (c[..., None, None] for c in _coefficients(t2, _SINC, _ONE_MINUS_COS))
    return _eye_like(w) + a * hat(w) + b * _hat_sq(w)


def _rodrigues(w: jax.Array, a: jax.Array, b: jax.Array) -> jax.Array:
    r""":math:`a\hat w + b\hat w^2` for coefficients ``a``, ``b`` of shape ``w.shape[:-1]``:
    :math:`\exp(w) - I` with :math:`a = \sin\theta/\theta`, :math:`b = (1-\cos\theta)/\theta^2`."""
    return a[..., None, None] * hat(w) + b[..., None, None] * _hat_sq(w)


def exp_minus_identity(w: Any) -> jax.Array:
    r""":math:`\exp(w) - I` computed without cancellation, ``(..., 3) -> (..., 3, 3)``.

    For a small rotation the entries of :math:`\exp(w) - I` are :math:`O(|w|)`, while
    ``exp(w) - I`` evaluated in floating point carries the absolute round-off of the unit
    diagonal (:math:`\sim 10^{-16}`), i.e. a relative error :math:`\sim 10^{-16}/|w|`.
    Variational integrators divide this difference by the step ``h`` (a velocity), so they
    use this form.
    """
    return _exp_minus_identity(_as_float(w))


@jax.custom_jvp
def _exp_minus_identity(w: jax.Array) -> jax.Array:
    return _rodrigues(w, *_coefficients(_theta_sq(w), _SINC, _ONE_MINUS_COS))


@_exp_minus_identity.defjvp
def _exp_minus_identity_jvp(primals, tangents):
    r"""The differential in closed form, :math:`\exp(w)\,\widehat{J_r(w)\delta}` with
    :math:`J_r(w)\delta = \delta - b\, w\times\delta + c\, w\times(w\times\delta)`
    (:func:`dexp`), instead of the derivatives of the coefficient functions: the same
    matrix in fewer operations (the Newton matrices of the exponential-map Hamel VIs are
    built from it); differentiable again (second derivatives through ``b`` and ``c``)."""
    (w,), (dw,) = primals, tangents
    a, b, c = _coefficients(_theta_sq(w), _SINC, _ONE_MINUS_COS, _T_MINUS_SIN)
    E = _rodrigues(w, a, b)
    w_x_dw = jnp.cross(w, dw)
    v = dw - b[..., None] * w_x_dw + c[..., None] * jnp.cross(w, w_x_dw)
    V = hat(v)
    return E, V + E @ V


def log(R: Any) -> jax.Array:
    r"""Logarithm :math:`SO(3) \to \mathfrak{so}(3)`, ``(..., 3, 3) -> (..., 3)``, with
    :math:`|w| \in [0, \pi]`.

    With :math:`v = \operatorname{vee}(R - R^\top) = 2\sin\theta\, n` and
    :math:`c = \cos\theta = (\operatorname{tr}R - 1)/2`, the angle is
    :math:`\theta = \operatorname{atan2}(|v|/2, c)` (accurate everywhere, unlike
    ``arccos``) and

    * generic: :math:`w = \frac{\theta}{2\sin\theta} v`;
    * near the identity (:math:`\sin^2\theta < 10^{-4}`, :math:`c > 0`):
      :math:`w = \frac{\arcsin s}{s}\frac{v}{2}` with the Taylor series of
      :math:`\arcsin(s)/s` in :math:`s^2 = |v|^2/4`;
    * near :math:`\pi` (:math:`\sin^2\theta < 10^{-2}`, :math:`c < 0`): the axis
      :math:`\pm n` from the symmetric part :math:`\tfrac12(R + R^\top) - cI = (1-c)\,n
      n^\top` (its column with the largest diagonal entry, normalised), and :math:`w =
      \operatorname{atan2}(\pm n\cdot v/2,\ c)\,(\pm n)`: the signed sine fixes the
      orientation.

    For a rotation by exactly :math:`\pi` either of :math:`\pm\pi n` is returned. Values and
    derivatives are finite everywhere and stay bounded up to :math:`\theta = \pi` (where
    :math:`\log` jumps between :math:`\pm\pi n`, the derivative is that of the branch
    returned). Accuracy: :math:`\exp(\log R) = R` and :math:`\log(\exp w) = w` to a few
    ulps on all of :math:`|w| \le \pi`, including tiny and near-:math:`\pi` angles.
    """
    R = _as_float(R)
    eye = _eye_like(R)
    v = 2.0 * vee(R)  # = 2 sin(theta) n for a rotation
    c = 0.5 * (jnp.trace(R, axis1=-2, axis2=-1) - 1.0)
    s_sq = 0.25 * jnp.sum(v * v, axis=-1)

    small = (s_sq < _LOG_SMALL_SIN_SQ) & (c > 0)
    near_pi = (s_sq < _LOG_PI_SIN_SQ) & (c < 0)
    generic = ~(small | near_pi)

    # Generic branch: s is bounded away from 0 where selected.
    s_g = jnp.sqrt(jnp.where(generic, s_sq, 1.0))
    w_generic = (jnp.arctan2(s_g, c) / (2.0 * s_g))[..., None] * v

    # Near the identity: arcsin(s)/s = sum (2k)! / (4^k (k!)^2 (2k+1)) s^2k.
    asin_ratio = _poly(s_sq, (1.0, 1.0 / 6, 3.0 / 40, 5.0 / 112, 35.0 / 1152))
    w_small = (0.5 * asin_ratio)[..., None] * v

    # Near pi: the axis from the symmetric part, column k with the largest diagonal entry
    # (that entry is (1 - c) n_k^2 >= (1 - c)/3, so the column is far from zero). Where not
    # selected, the column is replaced by e1 (and c by -1), keeping the normalisation and
    # atan2 away from 0/0.
    sym = 0.5 * (R + jnp.swapaxes(R, -1, -2)) - c[..., None, None] * eye
    d0, d1, d2 = sym[..., 0, 0], sym[..., 1, 1], sym[..., 2, 2]
    use0 = (d0 >= d1) & (d0 >= d2)
    use1 = ~use0 & (d1 >= d2)
    col = jnp.where(
        use0[..., None], sym[..., :, 0], jnp.where(use1[..., None], sym[..., :, 1], sym[..., :, 2])
    )
    col = jnp.where(near_pi[..., None], col, eye[0])
    n = col / jnp.sqrt(jnp.sum(col * col, axis=-1, keepdims=True))  # = +-(true axis)
    # n.v / 2 = +-sin(theta): atan2 of this signed sine gives +-theta with the same sign as
    # n, so theta_pi * n = theta * (true axis) whichever sign the column had. No explicit
    # sign fix is needed (at theta = pi exactly, n.v = 0 and either orientation is valid).
    c_pi = jnp.where(near_pi, c, -1.0)
    theta_pi = jnp.arctan2(0.5 * jnp.sum(n * v, axis=-1), c_pi)
    w_pi = theta_pi[..., None] * n

    return jnp.where(small[..., None], w_small, jnp.where(near_pi[..., None], w_pi, w_generic))


def rotation_angle(R: Any) -> jax.Array:
    r"""Rotation angle :math:`\theta = |\log R| \in [0, \pi]`, ``(..., 3, 3) -> (...)``.

    :math:`\theta = \operatorname{atan2}\bigl(|\operatorname{vee}(R - R^\top)|,\
    \tfrac12(\operatorname{tr}R - 1)\bigr)`. Where the sine vanishes (:math:`\theta \in
    \{0, \pi\}`, where :math:`\theta` is not differentiable) the gradient is the zero
    subgradient rather than ``nan``.
    """
    R = _as_float(R)
    v = vee(R)  # = sin(theta) n
    s_sq = jnp.sum(v * v, axis=-1)
    pos = s_sq > 0
    s = jnp.where(pos, jnp.sqrt(jnp.where(pos, s_sq, 1.0)), 0.0)
    c = 0.5 * (jnp.trace(R, axis1=-2, axis2=-1) - 1.0)
    return jnp.arctan2(s, c)


# ------------------------------------------------------------------------- Cayley map


def cayley(w: Any) -> jax.Array:
    r"""Cayley map :math:`\mathfrak{so}(3) \to SO(3)`, ``(..., 3) -> (..., 3, 3)``.

    :math:`\operatorname{cay}(w) = (I - \tfrac12\hat w)^{-1}(I + \tfrac12\hat w) = I +
    \frac{4}{4+|w|^2}\bigl(\hat w + \tfrac12\hat w^2\bigr)`: the rotation by angle
    :math:`2\arctan(|w|/2)` about :math:`w/|w|`. Smooth everywhere, no branches.
    """
    w = _as_float(w)
    k = (4.0 / (4.0 + _theta_sq(w)))[..., None, None]
    return _eye_like(w) + k * (hat(w) + 0.5 * _hat_sq(w))


def cayley_minus_identity(w: Any) -> jax.Array:
    r""":math:`\operatorname{cay}(w) - I = \frac{4}{4+|w|^2}(\hat w + \tfrac12\hat w^2)`,
    computed without cancellation (see :func:`exp_minus_identity`)."""
    return _cayley_minus_identity(_as_float(w))


def _cayley_terms(w: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``k = 4/(4+|w|²)`` and ``cay(w) − I = k (ŵ + ½ŵ²)``."""
    k = 4.0 / (4.0 + _theta_sq(w))
    return k, k[..., None, None] * (hat(w) + 0.5 * _hat_sq(w))


@jax.custom_jvp
def _cayley_minus_identity(w: jax.Array) -> jax.Array:
    return _cayley_terms(w)[1]


@_cayley_minus_identity.defjvp
def _cayley_minus_identity_jvp(primals, tangents):
    r"""The differential in closed form, :math:`\operatorname{cay}(w)\,\widehat{D(w)\delta}`
    with :math:`D(w)\delta = k(\delta - \tfrac12 w\times\delta)` (:func:`dcayley`), instead
    of the derivatives of ``k`` and of the squared hat map: fewer operations in the Newton
    matrix of ``lgvi`` (reverse mode); differentiable again."""
    (w,), (dw,) = primals, tangents
    k, E = _cayley_terms(w)
    V = hat(k[..., None] * (dw - 0.5 * jnp.cross(w, dw)))
    return E, V + E @ V


def cayley_inv(R: Any) -> jax.Array:
    r"""Inverse Cayley map, ``(..., 3, 3) -> (..., 3)``, for rotation angles :math:`< \pi`.

    :math:`\hat w = 2(R - I)(R + I)^{-1}`, in closed form :math:`w =
    \frac{2}{1 + \operatorname{tr}R}\operatorname{vee}(R - R^\top)`: for :math:`R =
    \operatorname{cay}(w)`, :math:`\operatorname{vee}(R - R^\top) = \frac{8w}{4+|w|^2}` and
    :math:`1 + \operatorname{tr}R = \frac{16}{4+|w|^2}`. Singular (``inf``) at angle
    :math:`\pi`, where :math:`|w| \to \infty`.
    """
    R = _as_float(R)
    tr = jnp.trace(R, axis1=-2, axis2=-1)
    return (4.0 / (1.0 + tr))[..., None] * vee(R)


# ----------------------------------------------------------------------- differentials


def dexp(w: Any) -> jax.Array:
    r"""Right-trivialised differential of :func:`exp` (right Jacobian :math:`J_r`),
    ``(..., 3) -> (..., 3, 3)``.

    :math:`\frac{d}{d\varepsilon}\exp(w + \varepsilon\delta)\big|_0 = \exp(w)\,
    \widehat{J_r(w)\delta}` with :math:`J_r(w) = I - \frac{1-\cos\theta}{\theta^2}\hat w +
    \frac{\theta - \sin\theta}{\theta^3}\hat w^2`.
    """
    w = _as_float(w)
    t2 = _theta_sq(w)
    b, c = (x[..., None, None] for x in _coefficients(t2, _ONE_MINUS_COS, _T_MINUS_SIN))
    return _eye_like(w) - b * hat(w) + c * _hat_sq(w)


def dexp_inv(w: Any) -> jax.Array:
    r"""Inverse of :func:`dexp`, :math:`J_r(w)^{-1}`, ``(..., 3) -> (..., 3, 3)``.

    :math:`J_r(w)^{-1} = I + \tfrac12\hat w + \Bigl(\frac{1}{\theta^2} -
    \frac{1+\cos\theta}{2\theta\sin\theta}\Bigr)\hat w^2`, the coefficient evaluated as
    :math:`1/\theta^2 - \cot(\theta/2)/(2\theta)` (finite at :math:`\theta = \pi`; singular
    at :math:`\theta = 2\pi`), Taylor series :math:`\tfrac1{12} + \tfrac{\theta^2}{720} +
    \dots` for small :math:`\theta`.
    """
    return _dexp_inv(w, 0.5)


def _dexp_inv(w: Any, half: float) -> jax.Array:
    """``I + half ŵ + d ŵ²``: :func:`dexp_inv` (``half = 1/2``) and :func:`dexp_left_inv`
    (``-1/2``; ``ŵ²`` and ``d`` are even in ``w``), computed from ``w`` itself so that the
    two share the coefficient's evaluation."""
    w = _as_float(w)
    d = _dexp_inv_coeff(_theta_sq(w))[..., None, None]
    return _eye_like(w) + half * hat(w) + d * _hat_sq(w)


def dexp_left(w: Any) -> jax.Array:
    r"""Left-trivialised differential of :func:`exp` (left Jacobian :math:`J_l`),
    ``(..., 3) -> (..., 3, 3)``.

    :math:`\frac{d}{d\varepsilon}\exp(w + \varepsilon\delta)\big|_0 =
    \widehat{J_l(w)\delta}\,\exp(w)` with :math:`J_l(w) = J_r(-w) = \exp(w) J_r(w) = I +
    \frac{1-\cos\theta}{\theta^2}\hat w + \frac{\theta - \sin\theta}{\theta^3}\hat w^2`.
    """
    return dexp(-_as_float(w))


def dexp_left_inv(w: Any) -> jax.Array:
    r"""Inverse of :func:`dexp_left`, ``(..., 3) -> (..., 3, 3)``.

    :math:`J_l(w)^{-1} = J_r(-w)^{-1} = I - \tfrac12\hat w + \Bigl(\frac{1}{\theta^2} -
    \frac{1+\cos\theta}{2\theta\sin\theta}\Bigr)\hat w^2`.
    """
    return _dexp_inv(w, -0.5)


def dcayley(w: Any) -> jax.Array:
    r"""Right-trivialised differential of :func:`cayley`, ``(..., 3) -> (..., 3, 3)``.

    :math:`\frac{d}{d\varepsilon}\operatorname{cay}(w + \varepsilon\delta)\big|_0 =
    \operatorname{cay}(w)\,\widehat{D(w)\delta}` with :math:`D(w) = \frac{4}{4+|w|^2}\bigl(I
    - \tfrac12\hat w\bigr)`.
    """
    w = _as_float(w)
    k = (4.0 / (4.0 + _theta_sq(w)))[..., None, None]
    return k * (_eye_like(w) - 0.5 * hat(w))


def dcayley_inv(w: Any) -> jax.Array:
    r"""Inverse of :func:`dcayley`, ``(..., 3) -> (..., 3, 3)``.

    :math:`D(w)^{-1} = I + \tfrac12\hat w + \tfrac14 w w^\top` (check:
    :math:`(I - \tfrac12\hat w)(I + \tfrac12\hat w + \tfrac14 ww^\top) = I + \tfrac14(ww^\top
    - \hat w^2) = (1 + \tfrac14|w|^2) I`).
    """
    w = _as_float(w)
    return _eye_like(w) + 0.5 * hat(w) + 0.25 * _outer(w)


def dcayley_left(w: Any) -> jax.Array:
    r"""Left-trivialised differential of :func:`cayley`, ``(..., 3) -> (..., 3, 3)``.

    :math:`\frac{d}{d\varepsilon}\operatorname{cay}(w + \varepsilon\delta)\big|_0 =
    \widehat{D_l(w)\delta}\,\operatorname{cay}(w)` with :math:`D_l(w) = D(-w) =
    \frac{4}{4+|w|^2}\bigl(I + \tfrac12\hat w\bigr)`.
    """
    return dcayley(-_as_float(w))


def dcayley_left_inv(w: Any) -> jax.Array:
    r"""Inverse of :func:`dcayley_left`: :math:`D_l(w)^{-1} = I - \tfrac12\hat w + \tfrac14
    ww^\top`, ``(..., 3) -> (..., 3, 3)``."""
    return dcayley_inv(-_as_float(w))


# --------------------------------------------------------------- checks and projection


def orthogonality_error(R: Any) -> jax.Array:
    r"""Distance from orthogonality :math:`\|R^\top R - I\|_F`, ``(..., 3, 3) -> (...)``.

    The gradient at an exactly orthogonal :math:`R` (where the norm has a kink) is the zero
    subgradient rather than ``nan``.
    """
    R = _as_float(R)
    # RᵀR and the squared norm written out elementwise: under vmap XLA CPU makes a small
    # matmul, and a reduction over 3 or 9 entries, a batched library call (measured:
    # half of a car-pendulum sweep's per-step metrics)
    E = sum(R[..., k, :, None] * R[..., k, None, :] for k in range(3)) - _eye_like(R)
    sq = sum(E[..., i, j] * E[..., i, j] for i in range(3) for j in range(3))
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, 1.0)), 0.0)


def is_rotation(R: Any, atol: float = 1e-10) -> bool:
    r"""Whether ``R`` is a (batch of) rotation matrices: a Python ``bool``.

    True when the shape is ``(..., 3, 3)``, all entries are finite, and every matrix has
    :math:`\|R^\top R - I\|_F \le` ``atol`` and :math:`|\det R - 1| \le` ``atol``. Needs a
    concrete array (not a tracer inside ``jit``/``vmap``/``grad``); use
    :func:`orthogonality_error` there.
    """
    if not is_concrete(R):
        raise TypeError(
            "is_rotation returns a Python bool and needs a concrete array, not a tracer; "
            "use orthogonality_error inside jit/vmap/grad"
        )
    R = np.asarray(R)
    if R.ndim < 2 or R.shape[-2:] != (3, 3) or not np.issubdtype(R.dtype, np.number):
        return False
    R = R.astype(np.float64)
    if not np.all(np.isfinite(R)):
        return False
    E = np.swapaxes(R, -1, -2) @ R - np.eye(3)
    err = np.sqrt(np.sum(E * E, axis=(-2, -1)))
    det = np.linalg.det(R)
    return bool(np.all(err <= atol) and np.all(np.abs(det - 1.0) <= atol))


def _svd_projection(M: jax.Array):
    """SVD M = U diag(s) V^T with the det fix folded in: Q = U' V^T, M = U' diag(s') V^T."""
    U, s, Vt = jnp.linalg.svd(M)
    d = jnp.where(jnp.linalg.det(U) * jnp.linalg.det(Vt) < 0, -1.0, 1.0).astype(M.dtype)
    flip = jnp.stack([jnp.ones_like(d), jnp.ones_like(d), d], axis=-1)
    U = U * flip[..., None, :]
    s = s * flip
    return U @ Vt, U, s, Vt


@jax.custom_jvp
def _project(M: jax.Array) -> jax.Array:
    return _svd_projection(M)[0]


@_project.defjvp
def _project_jvp(primals, tangents):
    # Q maximises tr(Q^T M) over SO(3), so H = Q^T M = V diag(s') V^T is symmetric.
    # Differentiating, with dQ = Q V Omega V^T (Omega skew) and P = U'^T dM V:
    #   Omega diag(s') + diag(s') Omega = P - P^T  =>  Omega_ij = (P - P^T)_ij / (s'_i + s'_j),
    # and dQ = U' Omega V^T. Unlike differentiating through the SVD factors (which involves
    # 1/(s_i^2 - s_j^2) and is nan at a rotation, where all s_i = 1), this is finite unless
    # s'_i + s'_j = 0 (a reflection-like M with two equal singular values: genuinely
    # non-differentiable).
    (M,) = primals
    (dM,) = tangents
    Q, U, s, Vt = _svd_projection(M)
    P = jnp.swapaxes(U, -1, -2) @ dM @ jnp.swapaxes(Vt, -1, -2)
    A = P - jnp.swapaxes(P, -1, -2)
    denom = s[..., :, None] + s[..., None, :]
    Omega = A / denom
    return Q, U @ Omega @ Vt


def project_to_so3(M: Any) -> jax.Array:
    r"""Nearest rotation in the Frobenius norm, ``(..., 3, 3) -> (..., 3, 3)``.

    With the SVD :math:`M = U\,\mathrm{diag}(s)\,V^\top`: :math:`\Pi(M) = U\,\mathrm{diag}(1,
    1, \det(UV^\top))\,V^\top` (the determinant fix makes it a proper rotation; Kabsch /
    orthogonal Procrustes). Idempotent, and the identity on rotations. Its derivative is
    given analytically (``custom_jvp``, see the source), finite at rotations, where the
    tangent map is :math:`dM \mapsto R\,\mathrm{skew}(R^\top dM)`.
    """
    return _project(_as_float(M))


# ------------------------------------------------------------------------- quaternions


def quat_to_rotation(q: Any) -> jax.Array:
    r"""Rotation matrix of a scalar-first quaternion :math:`q = (q_0, \mathbf{q})`,
    ``(..., 4) -> (..., 3, 3)``.

    :math:`R(q) = I + \frac{2}{|q|^2}\bigl(q_0\hat{\mathbf q} + \hat{\mathbf q}^2\bigr)`,
    which for a unit quaternion is the usual :math:`(q_0^2 - |\mathbf q|^2)I + 2\mathbf
    q\mathbf q^\top + 2q_0\hat{\mathbf q}`; dividing by :math:`|q|^2` makes it a rotation
    for any nonzero :math:`q` (so ``q`` and ``-q`` and ``2q`` give the same :math:`R`). The
    rotation about the unit axis :math:`n` by :math:`\theta` is :math:`q = (\cos\frac\theta2,
    \sin\frac\theta2 n)`.
    """
    q = _as_float(q)
    q0 = q[..., 0][..., None, None]
    qv = q[..., 1:]
    k = (2.0 / jnp.sum(q * q, axis=-1))[..., None, None]
    return _eye_like(q) + k * (q0 * hat(qv) + _hat_sq(qv))


def rotation_to_quat(R: Any) -> jax.Array:
    r"""Unit quaternion (scalar first, scalar part :math:`\ge 0`) of a rotation,
    ``(..., 3, 3) -> (..., 4)``; inverse of :func:`quat_to_rotation` up to the sign of
    :math:`q`.

    Shepperd's method: the symmetric matrix :math:`K = 4qq^\top` has the entries
    :math:`K_{00} = 1 + \operatorname{tr}R`, :math:`K_{ii} = 1 + 2R_{ii} -
    \operatorname{tr}R`, :math:`K_{0i} = (R - R^\top)_{kj}` (cyclic :math:`ijk`),
    :math:`K_{ij} = R_{ij} + R_{ji}`; its column with the largest diagonal entry
    (:math:`\ge 1` since :math:`\operatorname{tr}K = 4`) is :math:`4q_k q`, which is
    normalised. No division by small numbers anywhere. At angle exactly :math:`\pi`
    (:math:`q_0 = 0`) either of :math:`\pm q` may be returned.
    """
    R = _as_float(R)
    tr = jnp.trace(R, axis1=-2, axis2=-1)
    r00, r11, r22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    k01 = R[..., 2, 1] - R[..., 1, 2]
    k02 = R[..., 0, 2] - R[..., 2, 0]
    k03 = R[..., 1, 0] - R[..., 0, 1]
    k12 = R[..., 0, 1] + R[..., 1, 0]
    k13 = R[..., 0, 2] + R[..., 2, 0]
    k23 = R[..., 1, 2] + R[..., 2, 1]
    k00 = 1.0 + tr
    k11 = 1.0 + 2.0 * r00 - tr
    k22 = 1.0 + 2.0 * r11 - tr
    k33 = 1.0 + 2.0 * r22 - tr
    K = jnp.stack(
        [
            jnp.stack([k00, k01, k02, k03], axis=-1),
            jnp.stack([k01, k11, k12, k13], axis=-1),
            jnp.stack([k02, k12, k22, k23], axis=-1),
            jnp.stack([k03, k13, k23, k33], axis=-1),
        ],
        axis=-2,
    )
    use0 = (k00 >= k11) & (k00 >= k22) & (k00 >= k33)
    use1 = ~use0 & (k11 >= k22) & (k11 >= k33)
    use2 = ~(use0 | use1) & (k22 >= k33)
    col = jnp.where(
        use0[..., None],
        K[..., :, 0],
        jnp.where(
            use1[..., None], K[..., :, 1], jnp.where(use2[..., None], K[..., :, 2], K[..., :, 3])
        ),
    )
    q = col / jnp.sqrt(jnp.sum(col * col, axis=-1, keepdims=True))
    return jnp.where(q[..., :1] < 0, -q, q)


def random_rotation(key: jax.Array, shape: int | tuple[int, ...] = ()) -> jax.Array:
    r"""Rotations drawn uniformly (Haar measure) from SO(3), array of shape ``(*shape, 3, 3)``.

    A standard Gaussian vector in :math:`\mathbb{R}^4` normalised to unit length is uniform on
    :math:`S^3`, and the double cover :math:`S^3 \to SO(3)` (:func:`quat_to_rotation`) maps the
    uniform measure to the Haar measure. (The rotation angle then has density
    :math:`(1 - \cos\theta)/\pi` on :math:`[0, \pi]`.)
    """
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    q = jax.random.normal(key, (*shape, 4))
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return quat_to_rotation(q)
