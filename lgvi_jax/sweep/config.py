"""What determines a sweep: :class:`SweepConfig` (stored in ``manifest.json``), the
on-disk format's name and fields, and the methods a sweep runs by name
(:func:`sweep_method`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

from ..options import ChordMatrix

FORMAT = {"format": "lgvi-jax-sweep", "version": 1}

_FIELD_DOCS = {
    "index": "trajectory index i (initial condition drawn from (seed, i))",
    "energy_error_max": "max over sampled steps of |H - H0|/|H0| (absolute if H0 = 0)",
    "energy_error_final": "|H - H0|/|H0| at t_final (NaN if the trajectory failed)",
    "orthogonality_error_max": "max over sampled steps of ||R^T R - I||_F",
    "newton_mean": "mean Newton iterations per step (0 for explicit methods)",
    "newton_max": "most Newton iterations in one step",
    "result": "0 success, 1 Newton did not converge, 2 non-finite values",
    "failed_step": "index of the first failed step, -1 if none",
}


class SweepError(ValueError):
    """Bad sweep configuration or output folder (the message names the argument)."""


@dataclasses.dataclass(frozen=True)
class SweepConfig:
    """Everything that determines a sweep's results (stored in ``manifest.json``)."""

    system: str
    methods: tuple[str, ...]
    dts: tuple[float, ...]
    t_final: float
    n: int
    perturb: float
    seed: int
    chunk: int = 256
    sample_every: int = 1
    parameters: dict[str, list[float]] = dataclasses.field(default_factory=dict)
    #: The Lie-group VIs' chord matrix (``"exact"`` or ``"mass"``, a
    #: :class:`~lgvi_jax.options.ChordMatrix`): the same solutions to round-off, ``"mass"``
    #: is faster batched (``lgvi-jax bench``). ``chord``: the manifest's key and the CLI's
    #: ``--chord``.
    chord: str = "exact"

    def to_json(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["methods"] = list(self.methods)
        d["dts"] = list(self.dts)
        if d["chord"] == "exact":  # the default: manifests of earlier sweeps stay resumable
            del d["chord"]
        return d

    def n_steps(self, dt: float) -> int:
        return round(self.t_final / dt)

    def _check_composed(self, name: str, valid_methods: Sequence[str]) -> None:
        """Accept ``METHOD@ORDER`` / ``METHOD@SCHEME`` for a listed ``METHOD`` (resolved
        by the system's method table); raise :class:`SweepError` otherwise."""
        from ..integrators import parse_method
        from ..systems import SYSTEMS

        try:
            base, spec = parse_method(name)
        except ValueError as err:
            raise SweepError(f"--method: {err}") from None
        if spec is not None and base in valid_methods and self.system in SYSTEMS:
            try:
                SYSTEMS[self.system].method(name)
            except ValueError as err:
                raise SweepError(f"--method: {err}") from None
            return
        raise SweepError(f"--method {name!r} is not available for {self.system}; "
                         f"choose from: {', '.join(valid_methods)} (each also as "
                         "METHOD@ORDER or METHOD@SCHEME when symmetric, e.g. lgvi@6)")

    def validate(self, valid_methods: Sequence[str] | None = None) -> None:
        """Raise :class:`SweepError` naming the first bad argument."""
        if not self.methods:
            raise SweepError("--method: give at least one method (e.g. lgvi,hamel)")
        if self.chord not in ChordMatrix.values():
            raise SweepError(f"--chord must be one of "
                             f"{', '.join(repr(v) for v in ChordMatrix.values())}, "
                             f"got {self.chord!r}")
        if len(set(self.methods)) != len(self.methods):
            raise SweepError(f"--method: a method is listed twice: {','.join(self.methods)}")
        if valid_methods is not None:
            for m in self.methods:
                if m not in valid_methods:
                    self._check_composed(m, valid_methods)
        if not self.dts:
            raise SweepError("--dt: give at least one step (e.g. 0.01,0.005)")
        if not (math.isfinite(self.t_final) and self.t_final > 0):
            raise SweepError(f"--t-final must be a finite number > 0, got {self.t_final!r}")
        for dt in self.dts:
            if not (math.isfinite(dt) and dt > 0):
                raise SweepError(f"--dt must contain finite numbers > 0, got {dt!r}")
            n = round(self.t_final / dt)
            if n < 1 or abs(n * dt - self.t_final) > 1e-9 * max(self.t_final, dt):
                raise SweepError(f"--t-final ({self.t_final:g}) must be a positive multiple "
                                 f"of every --dt; t_final/dt = {self.t_final / dt:.6g} for "
                                 f"dt = {dt:g}")
        if isinstance(self.n, bool) or not isinstance(self.n, int) or self.n < 1:
            raise SweepError(f"--n must be an integer >= 1, got {self.n!r}")
        if not (math.isfinite(self.perturb) and self.perturb >= 0):
            raise SweepError(f"--perturb must be a finite number >= 0, got {self.perturb!r}")
        if isinstance(self.chunk, bool) or not isinstance(self.chunk, int) or self.chunk < 1:
            raise SweepError(f"--chunk must be an integer >= 1, got {self.chunk!r}")
        if not isinstance(self.sample_every, int) or self.sample_every < 1:
            raise SweepError(f"--sample-every must be an integer >= 1, got {self.sample_every!r}")
        if not isinstance(self.seed, int) or isinstance(self.seed, bool):
            raise SweepError(f"--seed must be an integer, got {self.seed!r}")


def sweep_method(system: str, name: str,
                 chord_matrix: ChordMatrix | str = ChordMatrix.EXACT, *,
                 scalar: bool = True) -> Any:
    """The integrator that ``lgvi-jax sweep SYSTEM --method NAME --chord CHORD`` runs: the
    system's method (``NAME`` may be a composition, ``lgvi@6``) with the chord matrix
    ``chord_matrix`` (``CHORD``), solved on scalars
    (:func:`~lgvi_jax.integrators.with_scalar_newton`, wherever its settings allow it:
    ``--chord exact``). ``scalar=False``: the autodiff engine on arrays throughout (the
    same equations; for ``lgvi-jax bench``'s comparison). Raises ``ValueError`` for an
    unknown method."""
    from ..integrators import with_chord_matrix, with_scalar_newton
    from ..systems import get_system

    method = with_chord_matrix(get_system(system).method(name), chord_matrix)
    return with_scalar_newton(method, scalar)


def engine_name(method) -> str:
    """``"scalar"`` (the autodiff engine solving on scalars) or ``"general"`` (the autodiff
    engine on arrays): which engine runs ``method`` (also inside a composition)."""
    from ..integrators import Composition

    base = method._sub_step_method() if isinstance(method, Composition) else method
    return "scalar" if getattr(base, "on_scalars", False) else "general"


