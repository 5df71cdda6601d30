r"""The 1D harmonic oscillator, :math:`H = p^2/(2m) + k q^2/2` (paper, section 1)."""

from __future__ import annotations

from typing import ClassVar

import jax
import jax.numpy as jnp

from .._checks import as_float_array, check_finite, check_positive
from .base import AbstractEuclideanModel, PhaseState, reject_removed_keywords


class HarmonicOscillator(AbstractEuclideanModel):
    r"""Mass ``m`` on a spring of stiffness ``k``: :math:`L = \tfrac12 m v^2 - \tfrac12 k q^2`.

    Exact flow, with :math:`\omega = \sqrt{k/m}`:
    :math:`q(t) = q_0 \cos\omega t + \tfrac{p_0}{m\omega}\sin\omega t`,
    :math:`p(t) = p_0 \cos\omega t - m\omega q_0 \sin\omega t`.
    The initial state is :meth:`state`'s, default ``q0 = 1, p0 = 0`` (the paper's
    figures 1–3).
    """

    m: jax.Array
    k: jax.Array

    dof: ClassVar[int] = 1
    separable: ClassVar[bool] = True
    #: The default initial condition (the paper's figures 1–3).
    DEFAULT_Q0: ClassVar[float] = 1.0
    DEFAULT_P0: ClassVar[float] = 0.0

    def __init__(self, m=1.0, k=1.0, **removed):
        owner = "HarmonicOscillator"
        reject_removed_keywords(owner, removed, ("q0", "p0"))
        self.m = as_float_array("m", m, owner)
        self.k = as_float_array("k", k, owner)

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

    def state(self, q0=DEFAULT_Q0, p0=DEFAULT_P0) -> PhaseState:
        """The state with position ``q0`` and momentum ``p0`` (numbers, or arrays of shape
        ``(1,)``; default the class constants :attr:`DEFAULT_Q0`, :attr:`DEFAULT_P0`).
        ``ValueError`` naming the argument for a wrong shape or a non-finite value (checked
        on concrete values only: ``jit``, ``vmap`` and ``grad`` trace through)."""
        owner = "HarmonicOscillator"
        q0 = as_float_array("q0", q0, owner)
        p0 = as_float_array("p0", p0, owner)
        for name, value in (("q0", q0), ("p0", p0)):
            if jnp.shape(value) not in ((), (1,)):
                raise ValueError(f"{owner}: {name} must be a number (shape () or (1,)), got "
                                 f"shape {jnp.shape(value)}")
            check_finite(name, value, owner)
        return PhaseState(q=jnp.reshape(q0, (1,)), p=jnp.reshape(p0, (1,)))

    def exact(self, state0: PhaseState, t: jax.Array) -> PhaseState:
        """The exact solution at times ``t`` (any shape) from ``state0``; q, p have shape
        ``t.shape + (1,)``."""
        t = jnp.asarray(t)[..., None]
        w = self.omega
        c, s = jnp.cos(w * t), jnp.sin(w * t)
        q = state0.q * c + state0.p / (self.m * w) * s
        p = state0.p * c - self.m * w * state0.q * s
        return PhaseState(q=q, p=p)
