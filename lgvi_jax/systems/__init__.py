"""Systems by name: a model, its settable parameters, its methods and its output arrays, by name.

This is the table behind ``lgvi-jax simulate SYSTEM ...``. The library itself never parses
strings: the CLI turns ``--set NAME=V1,V2`` into float arrays and hands them to
:meth:`System.build`, which validates them and returns ``(model, state0)``. A system's
parameters mix the model's physical parameters and the initial condition (``q0``, ``p0``,
``R0``, ``omega0``, ``v0``): its ``make`` builds the model from the first and the state from
the second, with ``model.state(...)``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import numpy as np

from .. import so3
from ..integrators import EUCLIDEAN_METHODS, RIGID_METHODS, AbstractIntegrator, MethodTable
from ..models import CarPendulum, FreeRigidBody, HarmonicOscillator, HeavyTop
from ..models.rigid_bodies import PAPER_J, PAPER_OMEGA0, PAPER_R0, PAPER_RHO_C

__all__ = ["SYSTEMS", "Parameter", "System", "get_system", "resolve_methods"]


@dataclasses.dataclass(frozen=True)
class Parameter:
    """A settable quantity of a system: ``size`` numbers, with a default and a description."""

    name: str
    size: int
    default: tuple[float, ...]
    doc: str


@dataclasses.dataclass(frozen=True)
class System:
    """A named system: how to build it, which methods apply, what a run saves.

    ``methods`` is a :class:`~lgvi_jax.integrators.MethodTable`: it lists the base methods
    and also accepts their compositions, ``METHOD@ORDER`` (4, 6, 8) and
    ``METHOD@SCHEME`` (:func:`~lgvi_jax.integrators.resolve_method`)."""

    name: str
    description: str
    parameters: tuple[Parameter, ...]
    methods: Mapping[str, Callable[[], AbstractIntegrator]]
    make: Callable[[dict[str, np.ndarray]], tuple[Any, Any]]
    #: ``arrays(model, trajectory)``: what ``lgvi-jax simulate`` saves, by name.
    arrays: Callable[[Any, Any], dict[str, np.ndarray]]

    def parameter(self, name: str) -> Parameter:
        for p in self.parameters:
            if p.name == name:
                return p
        valid = ", ".join(p.name for p in self.parameters)
        raise ValueError(f"{self.name}: unknown parameter {name!r}; valid names: {valid}")

    def method(self, name: str) -> AbstractIntegrator:
        """The integrator called ``name``: a listed method, or ``METHOD@ORDER`` /
        ``METHOD@SCHEME`` (e.g. ``lgvi@6``). ``ValueError`` naming the system and the method
        otherwise (unknown name or scheme, a base method that is not symmetric)."""
        table = self.methods if isinstance(self.methods, MethodTable) else MethodTable(
            self.methods)
        try:
            return table.resolve(name)
        except ValueError as err:
            raise ValueError(f"{self.name}: {err}") from None

    def build(self, overrides: Mapping[str, Any] | None = None) -> tuple[Any, Any]:
        """Return ``(model, state0)`` with the defaults replaced by ``overrides``.

        Raises ``ValueError`` naming the parameter for an unknown name, a wrong number of
        values, or a non-finite value; the model's own checks (e.g. ``m > 0``) follow.
        """
        values = {p.name: np.asarray(p.default, dtype=np.float64) for p in self.parameters}
        for name, value in (overrides or {}).items():
            p = self.parameter(name)
            arr = np.atleast_1d(np.asarray(value, dtype=np.float64))
            if arr.shape != (p.size,):
                raise ValueError(
                    f"{self.name}: {name} takes {p.size} number(s), got {arr.size}"
                )
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{self.name}: {name} must be finite, got {arr.tolist()}")
            values[name] = arr
        return self.make(values)


def _oscillator_make(values):
    model = HarmonicOscillator(m=values["m"][0], k=values["k"][0])
    return model, model.state(q0=values["q0"][0], p0=values["p0"][0])


def _oscillator_arrays(model, traj) -> dict[str, np.ndarray]:
    return {
        "t": np.asarray(traj.t),
        "q": np.asarray(traj.state.q)[:, 0],
        "p": np.asarray(traj.state.p)[:, 0],
        "energy": np.asarray(traj.energy),
    }


def _flat(matrix) -> tuple[float, ...]:
    return tuple(float(x) for x in np.ravel(matrix))


def _rigid_arrays(model, traj) -> dict[str, np.ndarray]:
    """What a rigid-body run saves: ``t``, ``R`` (n,3,3), body angular velocity ``omega``
    and momentum ``mu`` (n,3), for a model with Euclidean part also ``q``, ``v``, ``p``
    (n,dof), every invariant by name (``energy``, ``momentum``, ``angular_momentum_z``, ...)
    and ``orthogonality_error`` ‖RᵀR − I‖_F (n,). Initial state first."""
    state = traj.state
    omega, v = jax.vmap(model.velocities)(state.R, state.mu, state.q, state.p)
    out = {
        "t": np.asarray(traj.t),
        "R": np.asarray(state.R),
        "omega": np.asarray(omega),
        "mu": np.asarray(state.mu),
    }
    if model.dof:
        out.update(q=np.asarray(state.q), v=np.asarray(v), p=np.asarray(state.p))
    out.update({k: np.asarray(val) for k, val in traj.invariants.items()})
    out["orthogonality_error"] = np.asarray(so3.orthogonality_error(state.R))
    return out


def _free_body_make(values):
    model = FreeRigidBody(J=values["J"].reshape(3, 3))
    return model, model.state(R0=values["R0"].reshape(3, 3), omega0=values["omega0"])


def _heavy_top_make(values):
    model = HeavyTop(J=values["J"].reshape(3, 3), m=values["m"][0], g=values["g"][0],
                     rho_c=values["rho_c"])
    return model, model.state(R0=values["R0"].reshape(3, 3), omega0=values["omega0"])


def _car_pendulum_make(values):
    model = CarPendulum(m=values["m"][0], M=values["M"][0], g=values["g"][0],
                        rho_c=values["rho_c"], J=values["J"].reshape(3, 3))
    return model, model.state(R0=values["R0"].reshape(3, 3), omega0=values["omega0"],
                              q0=values["q0"], v0=values["v0"])


_R0_DOC = "initial attitude, body to inertial, 9 numbers row-major (must be in SO(3))"
_J_DOC = "inertia about the pivot, 9 numbers row-major (symmetric, positive, triangle ineq.)"

SYSTEMS: dict[str, System] = {
    "oscillator": System(
        name="oscillator",
        description="1D harmonic oscillator H = p^2/(2m) + k q^2/2 (paper, section 1)",
        parameters=(
            Parameter("m", 1, (1.0,), "mass (> 0)"),
            Parameter("k", 1, (1.0,), "spring stiffness (> 0)"),
            Parameter("q0", 1, (1.0,), "initial position"),
            Parameter("p0", 1, (0.0,), "initial momentum"),
        ),
        methods=MethodTable({k: EUCLIDEAN_METHODS[k] for k in ("rk4", "gl4", "verlet",
                                                               "galerkin4", "gl6",
                                                               "galerkin6")}),
        make=_oscillator_make,
        arrays=_oscillator_arrays,
    ),
    "free-rigid-body": System(
        name="free-rigid-body",
        description="free rigid body, L = ω·Jω/2 on SO(3) (invariants: energy, R Jω)",
        parameters=(
            Parameter("J", 9, (2.0, 0, 0, 0, 3.0, 0, 0, 0, 4.0),
                      "inertia, 9 numbers row-major (symmetric, positive, triangle ineq.)"),
            Parameter("R0", 9, _flat(np.eye(3)), _R0_DOC),
            Parameter("omega0", 3, (0.1, 1.0, 0.1), "initial body angular velocity"),
        ),
        methods=MethodTable(RIGID_METHODS),
        make=_free_body_make,
        arrays=_rigid_arrays,
    ),
    "heavy-top": System(
        name="heavy-top",
        description="heavy top / 3D pendulum about a fixed pivot, e3 down (invariants: "
        "energy, vertical angular momentum)",
        parameters=(
            Parameter("J", 9, _flat(PAPER_J), _J_DOC),
            Parameter("m", 1, (1.0,), "mass (> 0)"),
            Parameter("g", 1, (9.81,), "gravity (>= 0), along e3 = down"),
            Parameter("rho_c", 3, PAPER_RHO_C, "pivot to mass centre, body frame"),
            Parameter("R0", 9, _flat(PAPER_R0), _R0_DOC),
            Parameter("omega0", 3, PAPER_OMEGA0, "initial body angular velocity"),
        ),
        methods=MethodTable(RIGID_METHODS),
        make=_heavy_top_make,
        arrays=_rigid_arrays,
    ),
    "car-pendulum": System(
        name="car-pendulum",
        description="the paper's 3D car-pendulum on SO(3) x R^2 (invariants: energy, cart "
        "momentum p, vertical angular momentum about the origin)",
        parameters=(
            Parameter("m", 1, (1.0,), "pendulum mass (> 0)"),
            Parameter("M", 1, (1.0,), "cart mass (> 0)"),
            Parameter("g", 1, (9.81,), "gravity (>= 0), along e3 = down"),
            Parameter("rho_c", 3, PAPER_RHO_C, "pivot to pendulum mass centre, body frame"),
            Parameter("J", 9, _flat(PAPER_J), _J_DOC),
            Parameter("q0", 2, (-0.125, -0.0125), "initial cart position (x, y)"),
            Parameter("v0", 2, (0.525, -0.0125), "initial cart velocity"),
            Parameter("R0", 9, _flat(PAPER_R0), _R0_DOC),
            Parameter("omega0", 3, PAPER_OMEGA0, "initial body angular velocity"),
        ),
        methods=MethodTable(RIGID_METHODS),
        make=_car_pendulum_make,
        arrays=_rigid_arrays,
    ),
}


def get_system(name: str | System) -> System:
    """The system called ``name`` (``ValueError`` listing the valid names otherwise); a
    :class:`System` is returned as it is (``TypeError`` for anything else)."""
    if isinstance(name, System):
        return name
    if not isinstance(name, str):
        raise TypeError(f"system: expected a system's name (one of {', '.join(SYSTEMS)}) or "
                        f"a System, got {type(name).__name__}")
    if name not in SYSTEMS:
        raise ValueError(f"unknown system {name!r}; valid systems: {', '.join(SYSTEMS)}")
    return SYSTEMS[name]


def resolve_methods(system: str, names: Sequence[str]
                    ) -> tuple[dict[str, AbstractIntegrator], list[str]]:
    """``({name: integrator}, skipped)``: each name resolved by
    ``get_system(system).method(name)``; names that raise ``ValueError`` (not implemented in
    this checkout, or not applicable) are skipped and listed."""
    spec = get_system(system)
    methods, skipped = {}, []
    for name in names:
        try:
            methods[name] = spec.method(name)
        except ValueError:
            skipped.append(name)
    return methods, skipped
