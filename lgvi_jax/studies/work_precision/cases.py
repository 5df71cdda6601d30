"""The test problems of the work-precision study and their references.

:class:`Case` holds a model, its initial state and how its runs are compared: the
pendulum mass centre (car-pendulum) or ``q`` (oscillator) against the independent reference
(:class:`~lgvi_jax.systems.car_pendulum.HandReference`, DOP853; the oscillator's exact
solution), the
invariants, and the problem as SciPy sees it (a NumPy right-hand side).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from lgvi_jax import so3
from lgvi_jax.models import HarmonicOscillator, PhaseState
from lgvi_jax.systems.car_pendulum import HandReference, moving_problem, paper_problem

#: The times at which positions are compared with the reference.
CHECK_TIMES = (10.0, 50.0)
#: The cases on the car-pendulum (SO(3) x R^2); the other one is the oscillator.
RIGID_CASES = ("car-paper", "car-moving")


@dataclasses.dataclass
class Case:
    """A test problem: the model, its initial state, how to compare with the reference.
    ``initial_condition``: for the car-pendulum, the ``(R0, omega0, q0, v0)`` that
    ``state0`` was built from, where the independent reference starts."""

    key: str
    title: str
    system_name: str
    model: Any
    state0: Any
    ref_rtol: float = 1e-13
    initial_condition: dict = dataclasses.field(default_factory=dict)
    _ref: dict = dataclasses.field(default_factory=dict)

    @property
    def rigid(self) -> bool:
        return self.system_name == "car-pendulum"

    def positions(self, states) -> np.ndarray:
        """Pendulum mass-centre positions (rigid) or ``q`` (oscillator), shape ``(n, d)``."""
        if self.rigid:
            return np.asarray(_centres(self.model, states))
        return np.asarray(states.q)

    def reference_position(self, t: float) -> np.ndarray:
        """The independent reference at time ``t`` (cached per time)."""
        if t not in self._ref:
            if self.rigid:
                ref = HandReference(self.model, **self.initial_condition)
                times = sorted({*(c for c in CHECK_TIMES if c <= t), t})
                ys = ref.at(times, rtol=self.ref_rtol, atol=self.ref_rtol)
                for tt, y in zip(times, ys, strict=True):
                    self._ref[tt] = ref.centre(y)
            else:
                self._ref[t] = np.asarray(self.model.exact(self.state0, t).q)
        return self._ref[t]

    def invariants(self, states) -> dict[str, np.ndarray]:
        inv = {k: np.asarray(v) for k, v in _invariants(self.model, states).items()}
        if self.rigid:
            inv["orthogonality_error"] = np.asarray(so3.orthogonality_error(states.R))
        return inv

    # SciPy: the system as a NumPy right-hand side, and back to the library's state
    def scipy_problem(self) -> tuple[Callable, np.ndarray]:
        if self.rigid:
            ref = HandReference(self.model, **self.initial_condition)
            return ref.rhs, ref.y0
        m, k = float(self.model.m), float(self.model.k)

        def rhs(_t, y):
            return np.array([y[1] / m, -k * y[0]])

        return rhs, np.array([float(self.state0.q[0]), float(self.state0.p[0])])

    def from_scipy(self, y: np.ndarray):
        """Library states from SciPy's rows ``y`` (``(n, 16)`` or ``(n, 2)``)."""
        y = jnp.asarray(y)
        if self.rigid:
            return _from_hand(self.model, y)
        return PhaseState(q=y[:, :1], p=y[:, 1:2])


@eqx.filter_jit
def _centres(model, states):
    return jax.vmap(model.pendulum_centre)(states)


@eqx.filter_jit
def _invariants(model, states):
    return jax.vmap(model.invariants)(states)


@eqx.filter_jit
def _from_hand(model, y):
    R = y[:, :9].reshape(-1, 3, 3)
    return jax.vmap(model.state_from_velocities)(R, y[:, 9:12], y[:, 12:14], y[:, 14:16])


def make_case(key: str, ref_rtol: float = 1e-13) -> Case:
    """``car-paper`` (the paper's state), ``car-moving`` (non-zero horizontal momentum,
    :func:`lgvi_jax.systems.car_pendulum.moving_problem`) or ``oscillator`` (m = k = q0 = 1,
    p0 = 0)."""
    if key in RIGID_CASES:
        problem, title = ((paper_problem(), "car-pendulum, paper state") if key == "car-paper"
                          else (moving_problem(), "car-pendulum, moving cart"))
        return Case(key, title, "car-pendulum", problem.model, problem.state0, ref_rtol,
                    problem.initial_condition)
    if key == "oscillator":
        model = HarmonicOscillator()
        return Case(key, "harmonic oscillator", "oscillator", model, model.default_state(),
                    ref_rtol)
    raise ValueError(f"make_case: unknown system {key!r}; valid: car-paper, car-moving, "
                     "oscillator")


def _scipy_y0(system: Case):
    """SciPy's problem for a (perturbed) state of the system: NumPy rhs and ``y0`` built
    from the state's velocities."""
    rhs, _ = system.scipy_problem()
    s = system.state0
    if system.rigid:
        omega, v = system.model.velocities(s.R, s.mu, s.q, s.p)
        y0 = np.concatenate([np.ravel(np.asarray(s.R)), np.asarray(omega), np.asarray(s.q),
                             np.asarray(v)])
    else:
        y0 = np.array([float(s.q[0]), float(s.p[0])])
    return rhs, y0
