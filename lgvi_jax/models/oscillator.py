r"""The 1D harmonic oscillator, :math:`H = p^2/(2m) + k q^2/2` (paper, section 1)."""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp

from .._checks import as_float_array, check_positive
from .base import AbstractEuclideanModel, PhaseState


class HarmonicOscillator(AbstractEuclideanModel):
    r"""Mass ``m`` on a spring of stiffness ``k``: :math:`L = \tfrac12 m v^2 - \tfrac12 k q^2`.

    Exact flow, with :math:`\omega = \sqrt{k/m}`:
    :math:`q(t) = q_0 \cos\omega t + \tfrac{p_0}{m\omega}\sin\omega t`,
    :math:`p(t) = p_0 \cos\omega t - m\omega q_0 \sin\omega t`.
    Default state ``q0 = 1, p0 = 0`` (the paper's figures 1–3).
    """

    m: jax.Array
    k: jax.Array
    q0: jax.Array
    p0: jax.Array

    dof: ClassVar[int] = 1
    separable: ClassVar[bool] = True

    def __init__(self, m=1.0, k=1.0, q0=1.0, p0=0.0):
        owner = "HarmonicOscillator"
        self.m = as_float_array("m", m, owner)
        self.k = as_float_array("k", k, owner)
        self.q0 = as_float_array("q0", q0, owner)
        self.p0 = as_float_array("p0", p0, owner)

    def __check_init__(self):
        check_positive("m", self.m, "HarmonicOscillator")
        check_positive("k", self.k, "HarmonicOscillator")

    @property
    def omega(self) -> jax.Array:
        """Angular frequency :math:`\\sqrt{k/m}`."""
        return jnp.sqrt(self.k / self.m)

    def kinetic(self, q, v):
        return 0.5 * self.m * jnp.sum(v**2)

    def potential(self, q):
        return 0.5 * self.k * jnp.sum(q**2)

    def default_state(self) -> PhaseState:
        return PhaseState(q=jnp.reshape(self.q0, (1,)), p=jnp.reshape(self.p0, (1,)))

    def exact(self, state0: PhaseState, t: jax.Array) -> PhaseState:
        """The exact solution at times ``t`` (any shape) from ``state0``; q, p have shape
        ``t.shape + (1,)``."""
        t = jnp.asarray(t)[..., None]
        w = self.omega
        c, s = jnp.cos(w * t), jnp.sin(w * t)
        q = state0.q * c + state0.p / (self.m * w) * s
        p = state0.p * c - self.m * w * state0.q * s
        return PhaseState(q=q, p=p)
