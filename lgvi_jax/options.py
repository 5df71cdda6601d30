"""The choices of algorithm of the solvers and integrators, as enums.

Each option that picks an algorithm (the Newton solver's :class:`LinearSolver`,
:class:`Adjoint`, :class:`JacobianMode` and :class:`JacobianLoop`, the Lie-group VIs'
:class:`ChordMatrix`, the Hamel VIs' :class:`HamelMap` and :class:`Variation`) is a string
enum: a member *is* its string (``ChordMatrix.MASS == "mass"``, same hash, ``str()`` and
``format()`` give ``"mass"``), so that the fields accept either and every comparison,
dictionary lookup and file key written with the string keeps working. The modules store the
member (an equinox ``converter``), so that ``LGVI(chord_matrix="mass")`` and
``LGVI(chord_matrix=ChordMatrix.MASS)`` are the same module: equal, with the same hash and
the same ``jit`` cache entry::

    import lgvi_jax as lj

    lj.LGVI(chord_matrix="mass").chord_matrix    # ChordMatrix.MASS
    lj.Newton(adjoint=lj.Adjoint.UNROLLED)

A bad value is refused with the owner, the field and the valid values named
(:meth:`_Choice.parse`).
"""

from __future__ import annotations

import enum
from typing import Any, TypeVar

__all__ = ["Adjoint", "ChordMatrix", "HamelMap", "JacobianLoop", "JacobianMode", "LinearSolver",
           "Variation"]

_C = TypeVar("_C", bound="_Choice")


class _Choice(str, enum.Enum):
    """A string enum: each member equals, hashes, prints and formats as its value."""

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)

    def __hash__(self) -> int:
        return hash(self.value)

    def __repr__(self) -> str:
        return f"{type(self).__name__}.{self.name}"

    @classmethod
    def values(cls) -> tuple[str, ...]:
        """The valid strings, in the order of the members."""
        return tuple(m.value for m in cls)

    @classmethod
    def parse(cls: type[_C], value: Any, owner: str, field: str) -> _C:
        """The member for ``value`` (a member or its string); ``ValueError`` naming
        ``owner``, ``field`` and the valid values otherwise (also for a member of another
        choice with an equal string)."""
        if isinstance(value, cls):
            return value
        # A plain string (or another str subclass), not a member of another choice: the
        # string "exact" names ChordMatrix.EXACT, Variation.EXACT does not.
        if isinstance(value, str) and not isinstance(value, _Choice):
            try:
                return cls(str.__str__(value))
            except ValueError:
                pass
        valid = ", ".join(repr(v) for v in cls.values())
        shown = repr(value if isinstance(value, _Choice) else
                     str.__str__(value) if isinstance(value, str) else value)
        raise ValueError(f"{owner}: {field} must be one of {valid}, got {shown}")

    @classmethod
    def coerce(cls, value: str) -> Any:
        """The member for ``value`` where it names one, else ``value`` unchanged: the
        fields' ``converter``, so that the owner's ``__check_init__`` refuses a bad value
        with its own name (:meth:`parse`)."""
        try:
            return cls.parse(value, cls.__name__, "value")
        except ValueError:
            return value


class LinearSolver(_Choice):
    """The Newton solver's linear solves (``Newton.linear_solver``)."""

    #: Unrolled Gaussian elimination with partial pivoting (:func:`~lgvi_jax.linalg.small_solve`).
    UNROLLED = "unrolled"
    #: ``jnp.linalg.solve`` (LAPACK).
    LU = "lu"


class Adjoint(_Choice):
    """How a Newton solve is differentiated (``Newton.adjoint``)."""

    #: The implicit function theorem at the root (:mod:`lgvi_jax.newton`).
    IMPLICIT = "implicit"
    #: Autodiff through exactly ``max_steps`` plain Newton iterations.
    UNROLLED = "unrolled"


class JacobianMode(_Choice):
    """The autodiff mode of the Jacobian program on scalars (``Newton.scalar_jacobian``,
    the Lie-group VIs' ``jacobian_mode``)."""

    #: Both traced, the one with fewer operations kept.
    AUTO = "auto"
    #: ``jax.jacfwd``: one tangent per unknown.
    FORWARD = "forward"
    #: ``jax.jacrev``: one cotangent per residual.
    REVERSE = "reverse"


class JacobianLoop(_Choice):
    """When a solve on scalars computes its chord matrix in loops at run time
    (``Newton.jacobian_loop``): for each block of unknowns (the rotational three, the rest),
    the JVP along that block run once per unknown of it, instead of the unrolled Jacobian
    (the ``scalar_jacobian`` mode's program). The car-pendulum's ``hamel``: 668 operations
    in the program instead of 1018 (a shorter compilation), 1190 run instead of 1018
    (docs/engine.md). The same matrix to the order of floating-point sums."""

    #: For a batch of solves (under ``vmap``: a sweep's batch) on a CPU; one solve, and
    #: batches on an accelerator (which would launch each column's kernels), unrolled.
    BATCHED = "batched"
    #: Always unrolled (the ``scalar_jacobian`` mode's program).
    NEVER = "never"
    #: Always in a loop.
    ALWAYS = "always"


class ChordMatrix(_Choice):
    """The matrix of the Lie-group VIs' chord iterations (``chord_matrix``)."""

    #: The Jacobian at the initial guess.
    EXACT = "exact"
    #: The continuous Legendre map's matrix, improved by Broyden's update.
    MASS = "mass"


class HamelMap(_Choice):
    """The map ``w -> R_kᵀ R_{k+1}`` of the Hamel VIs (``HamelVI.map``)."""

    EXP = "exp"
    CAYLEY = "cayley"


class Variation(_Choice):
    """The variation of the Hamel coordinate in the Hamel VIs (``HamelVI.variation``)."""

    #: The paper's formula (eq. 29), exact to first order in ``w``.
    PAPER = "paper"
    #: Through the inverse right differential of the map: exactly variational.
    EXACT = "exact"
