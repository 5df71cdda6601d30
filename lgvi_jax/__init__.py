"""lgvi_jax: differentiable, structure-preserving integrators for rigid-body mechanics.

Importing the package switches JAX to 64-bit floats (``jax_enable_x64``): long-horizon
energy and momentum checks are meaningless in float32. It also raises XLA CPU's size limit for
compiling a ``while`` loop as one function and selects XLA's elemental emitter, unless JAX
has already started or ``LGVI_JAX_XLA_TUNING=0`` (:mod:`lgvi_jax._xla`: faster rollouts
and compiles, the same results to rounding; ``docs/process-settings.md``).

Layout: :mod:`lgvi_jax.so3` (Lie-group maths), :mod:`lgvi_jax.linalg` (tiny linear
systems), :mod:`lgvi_jax.options` (the choices of algorithm, as enums),
:mod:`lgvi_jax.newton` (Newton solver), :mod:`lgvi_jax.models` (models defined by
their energies), :mod:`lgvi_jax.integrators` (one file per method),
:mod:`lgvi_jax.trajectory` (what a rollout returns, result codes), :mod:`lgvi_jax.simulate`
(rollouts), :mod:`lgvi_jax.diagnostics`, :mod:`lgvi_jax.plotting`, :mod:`lgvi_jax.systems`,
:mod:`lgvi_jax.inertia` (physically consistent inertia parametrisation),
:mod:`lgvi_jax.identify` (parameter fitting; imported on first use, as it needs optax),
:mod:`lgvi_jax.sweep`, :mod:`lgvi_jax.studies` (what ``lgvi-jax reproduce`` runs),
:mod:`lgvi_jax.bench` (what ``lgvi-jax bench`` runs) and :mod:`lgvi_jax.cli`.
"""

import jax

from . import _xla

jax.config.update("jax_enable_x64", True)
_xla.configure()  # XLA CPU: small loops whole, elemental emitter (lgvi_jax._xla), before JAX starts

from . import diagnostics, inertia, so3  # noqa: E402
from ._version import __version__  # noqa: E402
from .integrators import (  # noqa: E402
    EUCLIDEAN_METHODS,
    LGVI,
    RIGID_METHODS,
    RK4,
    RKMK4,
    AbstractIntegrator,
    Composition,
    GalerkinVI,
    GaussLegendre,
    HamelVI,
    LieGalerkinVI,
    StepInfo,
    StormerVerlet,
    compose,
    resolve_method,
)
from .models import (  # noqa: E402
    AbstractEuclideanModel,
    AbstractRigidBodyModel,
    CarPendulum,
    FreeRigidBody,
    HarmonicOscillator,
    HeavyTop,
    PhaseState,
    RigidState,
)
from .newton import Newton, NewtonError, NewtonSolution, newton_solve  # noqa: E402
from .options import (  # noqa: E402
    Adjoint,
    ChordMatrix,
    HamelMap,
    JacobianLoop,
    JacobianMode,
    LinearSolver,
    Variation,
)
from .simulate import final_state, simulate, simulate_timed  # noqa: E402
from .trajectory import RESULTS, IntegrationError, Trajectory  # noqa: E402

__all__ = [
    "EUCLIDEAN_METHODS",
    "LGVI",
    "RESULTS",
    "RIGID_METHODS",
    "RK4",
    "RKMK4",
    "AbstractEuclideanModel",
    "AbstractIntegrator",
    "AbstractRigidBodyModel",
    "Adjoint",
    "CarPendulum",
    "ChordMatrix",
    "Composition",
    "FreeRigidBody",
    "GalerkinVI",
    "GaussLegendre",
    "HamelMap",
    "HamelVI",
    "HarmonicOscillator",
    "HeavyTop",
    "IntegrationError",
    "JacobianLoop",
    "JacobianMode",
    "LieGalerkinVI",
    "LinearSolver",
    "Newton",
    "NewtonError",
    "NewtonSolution",
    "PhaseState",
    "RigidState",
    "StepInfo",
    "StormerVerlet",
    "Trajectory",
    "Variation",
    "__version__",
    "compose",
    "diagnostics",
    "final_state",
    "identify",
    "inertia",
    "newton_solve",
    "resolve_method",
    "simulate",
    "simulate_timed",
    "so3",
]


def __getattr__(name: str):
    # lgvi_jax.identify on first use (it imports optax, which the rest does not need).
    if name == "identify":
        import importlib

        return importlib.import_module(".identify", __name__)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
