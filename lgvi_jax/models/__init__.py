"""Models: each defines only its energies (its fields are its parameters), ``state(...)``, the
initial state from an initial condition, and its invariants."""

from .base import AbstractEuclideanModel, PhaseState
from .oscillator import HarmonicOscillator
from .rigid import AbstractRigidBodyModel, RigidState
from .rigid_bodies import CarPendulum, FreeRigidBody, HeavyTop

__all__ = [
    "AbstractEuclideanModel",
    "AbstractRigidBodyModel",
    "CarPendulum",
    "FreeRigidBody",
    "HarmonicOscillator",
    "HeavyTop",
    "PhaseState",
    "RigidState",
]
