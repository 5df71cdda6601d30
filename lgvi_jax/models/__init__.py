"""Models: each defines only its energies, default state and invariants."""

from .base import AbstractEuclideanModel, PhaseState
from .oscillator import HarmonicOscillator

__all__ = ["AbstractEuclideanModel", "HarmonicOscillator", "PhaseState"]
