r"""Batched, resumable energy-drift sweeps: many initial conditions x methods x steps.

A sweep draws ``n`` initial conditions around a model's default state, integrates each one
with every ``(method, dt)`` pair and records, per trajectory, how well the structure was
kept. It is built for long unattended runs:

* **Batched and sharded.** A chunk of trajectories is one ``jax.vmap`` of a jitted rollout,
  split over every device in ``jax.devices()`` with ``jax.shard_map`` (each device runs its
  share independently, no communication). On a CPU-only machine, expose one XLA host
  device per core (``lgvi-jax sweep --devices N``, or ``jax.config.update(
  "jax_num_cpu_devices", N)`` before JAX starts, or ``XLA_FLAGS=
  --xla_force_host_platform_device_count=N``). The step ``dt`` and the number of steps are
  run-time values, so each method compiles once per sweep.
* **Resumable.** Results go to disk chunk by chunk, each file written atomically
  (temporary file and rename). ``resume=True`` skips every chunk already on disk and gives
  a result identical, bit for bit, to an uninterrupted run: the initial condition of
  trajectory ``i`` depends only on ``(seed, i)``, and every chunk is computed with the same
  batch shape (the last one is padded).
* **Several processes and hosts.** Under :mod:`jax.distributed` (``lgvi-jax sweep
  --coordinator HOST:PORT --num-processes N --process-id I`` or ``--distributed auto``,
  :mod:`lgvi_jax.distributed`), the processes divide the chunks among themselves and write
  into one shared folder; process 0 writes the manifest and the summary
  (``docs/distributed.md``).
* **Failure is a value.** A trajectory whose Newton solve fails or whose state stops being
  finite is flagged (``result`` code, ``failed_step``) and stops contributing; it never
  stops or contaminates the rest of its batch.

Initial conditions (``perturb = ε``): for rigid bodies, ``R = R0 exp(ε u)`` with ``u`` a
uniformly random unit vector (a rotation by exactly ``ε``), and each velocity vector
``x ∈ {ω, v}`` becomes ``x + ε |x| z/√d`` with ``z`` standard normal in ``R^d`` (relative
perturbation; absolute ``ε`` if ``x = 0``). For Euclidean models the phase point
``(q, p)`` is perturbed the same way.

Recorded per trajectory (the metrics are taken every ``sample_every`` steps and at the
end, over the steps before any failure):

``energy_error_max``, ``energy_error_final``
    max and final :math:`|H - H_0| / |H_0|` (absolute if :math:`H_0 = 0`); final is NaN for
    a failed trajectory, and every max is NaN for one that fails before its first sample.
``<invariant>_drift_max``
    for every other invariant of the model (momentum maps), the max over time and
    components of :math:`|I - I_0|`.
``orthogonality_error_max``
    :math:`\max \|R^\top R - I\|_F` (models on SO(3) only).
``newton_mean``, ``newton_max``
    Newton iterations per step; ``result`` (0 = success, see :class:`~lgvi_jax.RESULTS`),
    ``failed_step`` (-1 if none).

On-disk format (``format = "lgvi-jax-sweep"``, ``version = 1``): ``manifest.json`` (the full
configuration, the list of chunks, the field descriptions), ``chunks/<method>__dt<j>__
<start>-<stop>.npz`` (one array per field over the chunk's trajectories, plus ``index``),
and, when the sweep completes, ``trajectories.csv`` (one row per trajectory, method and
step), ``summary.json``, ``summary.md`` and ``energy_error.png``.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import rollout, so3
from ._io import (
    atomic_open,
    atomic_write_bytes,
    atomic_write_json,
    atomic_write_text,
    save_npz_atomic,
)
from .progress import Progress
from .scalarize import on_scalars
from .trajectory import RESULTS

__all__ = [
    "FORMAT",
    "SweepConfig",
    "SweepError",
    "batch_arguments",
    "engine_name",
    "initial_conditions",
    "load_results",
    "run_batch",
    "run_sweep",
    "sweep_method",
]

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
    #: The Lie-group VIs' chord matrix (``"exact"`` or ``"mass"``): the same solutions to
    #: round-off, ``"mass"`` is faster batched (``lgvi-jax bench``).
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
        from .integrators import parse_method
        from .scenes import SCENES

        try:
            base, spec = parse_method(name)
        except ValueError as err:
            raise SweepError(f"--method: {err}") from None
        if spec is not None and base in valid_methods and self.system in SCENES:
            try:
                SCENES[self.system].method(name)
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
        if self.chord not in ("exact", "mass"):
            raise SweepError(f"--chord must be 'exact' or 'mass', got {self.chord!r}")
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


def sweep_method(system: str, name: str, chord: str = "exact", *,
                 scalar: bool = True) -> Any:
    """The integrator that ``lgvi-jax sweep SYSTEM --method NAME --chord CHORD`` runs: the
    scene's method (``NAME`` may be a composition, ``lgvi@6``) with the chord
    matrix ``chord``, solved on scalars (:func:`~lgvi_jax.integrators.with_scalar_newton`,
    wherever its settings allow it: ``--chord exact``). ``scalar=False``: the autodiff
    engine on arrays throughout (the same equations; for ``lgvi-jax bench``'s
    comparison). Raises ``ValueError`` for an unknown method."""
    from .integrators import Composition, with_chord_matrix, with_scalar_newton
    from .scenes import get_scene

    method = with_chord_matrix(get_scene(system).method(name), chord)
    if scalar:
        method = with_scalar_newton(method)
    elif isinstance(method, Composition):  # the array engine throughout
        method = dataclasses.replace(method, scalar=False)
    return method


def engine_name(method) -> str:
    """``"scalar"`` (the autodiff engine solving on scalars) or ``"general"`` (the autodiff
    engine on arrays): which engine runs ``method`` (also inside a composition)."""
    from .integrators import Composition

    base = method._sub_step_method() if isinstance(method, Composition) else method
    newton = getattr(base, "newton", None)
    return "scalar" if getattr(newton, "scalar", False) else "general"


# ---------------------------------------------------------------------------------------
# Initial conditions
# ---------------------------------------------------------------------------------------


def _perturb_vector(key, x, eps):
    """``x + eps |x| z/√d`` (``eps z/√d`` if ``x = 0``), ``z`` standard normal."""
    if x.size == 0:
        return x
    z = jax.random.normal(key, x.shape, x.dtype) / jnp.sqrt(x.size)
    norm = jnp.linalg.norm(x)
    return x + eps * jnp.where(norm > 0, norm, 1.0) * z


def _one_initial_condition(model, state0, eps, key):
    k_rot, k_w, k_v = jax.random.split(key, 3)
    if hasattr(state0, "R"):
        omega, v = model.velocities(state0.R, state0.mu, state0.q, state0.p)
        u = jax.random.normal(k_rot, (3,), state0.R.dtype)
        u = u / jnp.linalg.norm(u)
        R = state0.R @ so3.exp(eps * u)
        return model.state_from_velocities(
            R, _perturb_vector(k_w, omega, eps), state0.q, _perturb_vector(k_v, v, eps)
        )
    flat = jnp.concatenate([state0.q, state0.p])
    new = _perturb_vector(k_w, flat, eps)
    n = state0.q.shape[0]
    return type(state0)(q=new[:n], p=new[n:])


@eqx.filter_jit
def _initial_conditions(model, state0, eps, seed, indices):
    base = jax.random.key(seed)
    keys = jax.vmap(lambda i: jax.random.fold_in(base, i))(indices)
    # One condition at a time (lax.map), not vmap: every condition is then computed by the
    # same unbatched code whatever n is, so condition i is bit-for-bit the same in any
    # chunking (under vmap, XLA's vector and remainder loops can round differently: 1 ulp).
    return jax.lax.map(lambda key: _one_initial_condition(model, state0, eps, key), keys)


def initial_conditions(model, state0, n: int, perturb: float, seed: int,
                       start: int = 0) -> Any:
    """Initial conditions ``start, ..., start + n - 1`` of a sweep, batched (leading axis
    ``n``). Condition ``i`` depends only on ``(seed, i)`` (``jax.random.fold_in``), so any
    chunking of the index range gives the same states."""
    from . import _cache

    indices = np.arange(start, start + n, dtype=np.uint32)
    # The cached program returns the states' leaves: jax.export serialises only the
    # pytree nodes registered with it, and a state class is not (every run traced again).
    leaves = _cache.call("sweep.initial_conditions", _initial_condition_leaves, model,
                         state0, np.float64(perturb), np.uint32(seed % 2**32), indices)
    return jax.tree.unflatten(jax.tree.structure(state0), leaves)


def _initial_condition_leaves(model, state0, eps, seed, indices):
    return jax.tree.leaves(_initial_conditions(model, state0, eps, seed, indices))


# ---------------------------------------------------------------------------------------
# The batched rollout
# ---------------------------------------------------------------------------------------


def _diagnostics(model, state):
    """The model's invariants and, on SO(3) x Rⁿ, the orthogonality error ‖RᵀR − I‖_F."""
    out = dict(model.invariants(state))
    if hasattr(state, "R"):
        out["orthogonality_error"] = so3.orthogonality_error(state.R)
    return out


def _per_member(tree):
    """``tree`` itself; under ``vmap``, with every leaf batched (unbatched ones broadcast).
    For a loop's initial carry: JAX batches a loop by searching for the carries that become
    batched, retracing the body (with every Newton solve in it) at each search step; a carry
    batched from the start settles at once."""

    @jax.custom_batching.custom_vmap
    def ident(tree):
        return tree

    @ident.def_vmap
    def _rule(axis_size, in_batched, tree):
        (batched,) = in_batched
        out = jax.tree.map(
            lambda x, b: x if b else jnp.broadcast_to(x, (axis_size, *jnp.shape(x))),
            tree, batched)
        return out, jax.tree.map(lambda _: True, out)

    return ident(tree)


def _start(model, method, state0, dt) -> rollout.Carry:
    """The rollout's initial carry, every leaf per member except the step index, which
    stays shared: the metrics' ``cond`` on it then stays a branch under ``vmap`` (metrics
    every K steps cost 1/K), where a per-member index would turn it into a selection."""
    carry = rollout.start(model, method, state0, dt)
    return eqx.tree_at(lambda c: c.k, _per_member(carry), carry.k)


def _sweep_one(model, method, state0, dt, n_steps, sample_every):
    """One trajectory of ``n_steps`` (a run-time value) with running metrics."""
    # On scalars (scalarize.on_scalars): the invariants of a model derived by autodiff (the
    # inverse Legendre map through the kinetic-energy Hessian) are dozens of small array
    # operations that in a loop cost more than the step (heavy top hamel, metrics every
    # step, one trajectory: 2.2e5 steps/s on arrays, 2.15e6 on scalars).
    on_scalars_ = on_scalars(_diagnostics, model, state0)

    def diagnostics(state):
        return on_scalars_(model, state)

    inv0 = diagnostics(state0)
    e0 = inv0["energy"]
    scale = jnp.where(e0 != 0, jnp.abs(e0), 1.0)
    names = [k for k in inv0 if k not in ("energy", "orthogonality_error")]
    on_group = hasattr(state0, "R")
    ftype = e0.dtype

    def measure(state):
        inv = diagnostics(state)
        out = {"energy_error": jnp.abs(inv["energy"] - e0) / scale}
        for k in names:
            out[f"{k}_drift"] = jnp.max(jnp.abs(inv[k] - inv0[k]))
        if on_group:
            out["orthogonality_error"] = inv["orthogonality_error"]
        return out

    zero_metrics = jax.tree.map(jnp.zeros_like, measure(state0))
    # The maxima start at NaN (fmax ignores it): a trajectory that fails before its first
    # sample records NaN, not a misleading 0.
    nan_metrics = jax.tree.map(lambda x: jnp.full_like(x, jnp.nan), zero_metrics)

    def observe(acc, c):
        sample = (c.k % sample_every == 0) | (c.k == n_steps)

        def update(args):
            maxima, last = args
            m = measure(c.state)
            maxima = jax.tree.map(lambda a, b: jnp.where(c.ok, jnp.fmax(a, b), a), maxima, m)
            last = jax.tree.map(lambda b: jnp.where(c.ok, b, jnp.nan), m)
            return maxima, last

        return jax.lax.cond(sample, update, lambda a: a, acc)

    carry, acc = _start(model, method, state0, dt), _per_member((nan_metrics, zero_metrics))
    end, (maxima, last) = rollout.advance(model, method, dt, carry, n_steps, observe, acc)
    steps_done = jnp.where(end.failed_step >= 0, end.failed_step + 1, n_steps)
    out = {
        "energy_error_max": maxima["energy_error"],
        "energy_error_final": last["energy_error"],
    }
    for k in names:
        out[f"{k}_drift_max"] = maxima[f"{k}_drift"]
    if on_group:
        out["orthogonality_error_max"] = maxima["orthogonality_error"]
    out["newton_mean"] = end.newton_steps / jnp.maximum(steps_done, 1).astype(ftype)
    out["newton_max"] = end.newton_steps_max
    out["result"] = end.result
    out["failed_step"] = end.failed_step
    return out


def _final_one(model, method, state0, dt, n_steps, sample_every):
    """One trajectory, no metrics: the final state and the result code (benchmarks)."""
    del sample_every
    end, _ = rollout.advance(model, method, dt, _start(model, method, state0, dt), n_steps)
    return {"state": end.state, "result": end.result, "failed_step": end.failed_step}


_ONE = {"metrics": _sweep_one, "final": _final_one}
_RUNNERS: dict[Any, Callable] = {}

#: The most trajectories one device integrates as one vectorised batch; a larger share runs
#: as a sequence of equal blocks (``lax.map`` over ``vmap``), whose working set stays in
#: cache. Measured on one core (lgvi, mass chord, 2000 steps): 1.23e6 steps/s for 512 at
#: once, 8.9e5 for 1024 or 2048 at once, 1.22e6 for 2048 in blocks of 512.
BLOCK = 512
#: The block size for the steps emitted on scalars (the scalar engine): their hundreds of
#: live values are each a vector over the block, so the working set grows with it. Of 16,
#: 32, 64, 128 (and earlier 256, 512), 16 and 32 ran fastest across models and methods,
#: with the same compile time (CHANGELOG, 2026-12-05; measured on an AVX-512 CPU only);
#: the array engine has no such preference.
SCALAR_BLOCK = 32


def _vmap_in_blocks(f, states, block: int):
    """``vmap(f)(states)`` over the leading axis, as a sequence of at most ``block``-sized
    vectorised blocks: ``ceil(B / block)`` blocks of equal size, the last padded with copies
    of the first state (computed and dropped), so that the step is compiled once."""
    batch = jax.tree.leaves(states)[0].shape[0]
    if batch == 1:  # one trajectory: the unbatched program (compiles in 5-6 s instead of
        # 7.5-8.5 s on scalars, car-pendulum; runs as fast)
        out = f(jax.tree.map(lambda x: x[0], states))
        return jax.tree.map(lambda y: y[None], out)
    if batch <= block:
        return jax.vmap(f)(states)
    n_blocks = -(-batch // block)
    size = -(-batch // n_blocks)
    pad = n_blocks * size - batch

    def blocks(x):
        x = jnp.concatenate([x, jnp.broadcast_to(x[:1], (pad, *x.shape[1:]))]) if pad else x
        return x.reshape(n_blocks, size, *x.shape[1:])

    out = jax.lax.map(jax.vmap(f), jax.tree.map(blocks, states))
    return jax.tree.map(lambda y: y.reshape(n_blocks * size, *y.shape[2:])[:batch], out)


def _runner(devices: tuple, kind: str = "metrics", block: int = BLOCK) -> Callable:
    """A jitted batched rollout (``kind`` = ``"metrics"`` or ``"final"``), sharded over
    ``devices`` with ``shard_map``, each device's share in blocks of at most ``block``
    (cached per device set, kind and block size)."""
    key = (devices, kind, block)
    if key in _RUNNERS:
        return _RUNNERS[key]
    one = _ONE[kind]

    def batched(params, static, states, dt, n_steps, sample_every):
        model, method = eqx.combine(params, static)
        return _vmap_in_blocks(lambda s: one(model, method, s, dt, n_steps, sample_every),
                               states, block)

    if len(devices) == 1:
        fn = jax.jit(batched, static_argnums=1)
    else:
        from jax.sharding import PartitionSpec as P

        mesh = jax.sharding.Mesh(np.array(devices), ("batch",))

        def sharded(params, static, states, dt, n_steps, sample_every):
            inner = jax.shard_map(
                lambda p, s, d, n, e: batched(p, static, s, d, n, e),
                mesh=mesh,
                in_specs=(P(), P("batch"), P(), P(), P()),
                out_specs=P("batch"),
                check_vma=False,
            )
            return inner(params, states, dt, n_steps, sample_every)

        fn = jax.jit(sharded, static_argnums=1)
    _RUNNERS[key] = fn
    return fn


def _sharding(devices, batch: bool):
    if len(devices) == 1:
        return jax.sharding.SingleDeviceSharding(devices[0])
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    mesh = jax.sharding.Mesh(np.array(devices), ("batch",))
    return NamedSharding(mesh, P("batch") if batch else P())


def _place(tree, devices, batch: bool):
    """``tree`` on ``devices``; a :class:`jax.ShapeDtypeStruct` leaf (an input not computed
    yet, :func:`_prepare_batch`) gets the sharding the array will have."""
    sharding = _sharding(devices, batch)

    def put(x):
        if isinstance(x, jax.ShapeDtypeStruct):
            return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding)
        return jax.device_put(x, devices[0] if len(devices) == 1 else sharding)

    return jax.tree.map(put, tree)


def _prepare_batch(model, method, state0, batch: int, dt, n_steps, sample_every,
                   devices) -> None:
    """Load and compile the batched rollout that :func:`run_batch` will run on ``batch``
    states shaped like ``state0`` (``_cache.prepare``; for a thread beside the initial
    conditions)."""
    from . import _cache

    try:
        states = jax.tree.map(lambda x: jax.ShapeDtypeStruct((batch, *jnp.shape(x)),
                                                             jnp.result_type(x)), state0)
        fn, args = batch_arguments(model, method, states, dt, n_steps,
                                   sample_every=sample_every, devices=devices)
        _cache.prepare("sweep.run_batch", fn, *args)
    except Exception:  # only a head start: run_batch reports any error itself
        pass


def batch_arguments(model, method, states, dt, n_steps, *, sample_every=1, devices=None,
                    kind="metrics"):
    """``(runner, args)`` of a batched rollout, the arguments placed on ``devices``: call
    ``runner(*args)``, or ``runner.lower(*args).compile()`` to time compilation apart.
    ``states`` may be :class:`jax.ShapeDtypeStruct` leaves (given their sharding here)."""
    method.check_model(model)
    batch = jax.tree.leaves(states)[0].shape[0]
    devices = tuple(jax.devices() if devices is None else devices)
    if batch % len(devices):
        devices = devices[:1]
    params, static = eqx.partition((model, method), eqx.is_array)
    args = (_place(params, devices, False), static, _place(states, devices, True),
            jnp.float64(dt), jnp.int32(n_steps), jnp.int32(sample_every))
    block = _block(method, devices, batch)
    return _runner(devices, kind, block), args


def _block(method, devices, batch: int) -> int:
    """The vectorised block of one device's share: :data:`BLOCK` or :data:`SCALAR_BLOCK`
    on CPUs (whose caches the working set must fit), the whole share on accelerators
    (whose throughput needs every trajectory at once; a sequence of blocks would
    serialise them)."""
    if devices[0].platform != "cpu":
        return max(1, -(-batch // len(devices)))
    return BLOCK if engine_name(method) == "general" else min(BLOCK, SCALAR_BLOCK)


def run_batch(model, method, states, dt: float, n_steps: int, *, sample_every: int = 1,
              devices: Sequence | None = None) -> dict[str, np.ndarray]:
    """Integrate a batch of initial states (leading axis ``B``) for ``n_steps`` steps of
    ``dt`` and return the per-trajectory metrics as NumPy arrays of shape ``(B,)``.

    The batch is split over ``devices`` (default: all of ``jax.devices()`` that divide
    ``B``, else one). ``dt``, ``n_steps`` and ``sample_every`` are run-time values.
    """
    from . import _cache

    fn, args = batch_arguments(model, method, states, dt, n_steps, sample_every=sample_every,
                               devices=devices)
    out = _cache.call("sweep.run_batch", fn, *args)  # traced once per cache (CLI)
    return {k: np.asarray(v) for k, v in out.items()}


# ---------------------------------------------------------------------------------------
# The sweep driver: chunks on disk, manifest, resume
# ---------------------------------------------------------------------------------------


#: Test hook (never set in normal use): ``LGVI_JAX_TEST_KILL_AFTER_CHUNK=k`` makes the
#: process kill itself with SIGKILL right after writing the k-th chunk (0-based) of this
#: run, so that a test interrupts a sweep at a known point instead of racing it.
KILL_HOOK_ENV = "LGVI_JAX_TEST_KILL_AFTER_CHUNK"


def _test_kill_hook(written: int) -> None:
    value = os.environ.get(KILL_HOOK_ENV)
    if value is not None and value.strip() == str(written):
        import signal

        if hasattr(signal, "SIGKILL"):
            os.kill(os.getpid(), signal.SIGKILL)
        os._exit(137)  # no SIGKILL (Windows): exit at once, no clean-up either


def _chunk_plan(config: SweepConfig) -> list[dict[str, Any]]:
    plan = []
    for method in config.methods:
        for j, dt in enumerate(config.dts):
            for start in range(0, config.n, config.chunk):
                stop = min(start + config.chunk, config.n)
                plan.append({"file": f"chunks/{method}__dt{j}__{start:07d}-{stop:07d}.npz",
                             "method": method, "dt": dt, "dt_index": j,
                             "start": start, "stop": stop})
    return plan


#: Fields of every chunk, whatever the model (plus ``<invariant>_drift_max`` and, on
#: SO(3), ``orthogonality_error_max``).
_CORE_FIELDS = ("index", "energy_error_max", "energy_error_final", "newton_mean",
                "newton_max", "result", "failed_step")


def _expected_fields(model, state0) -> set[str]:
    """The fields a chunk of this model holds (the keys :func:`_sweep_one` returns)."""
    names = {f"{k}_drift_max" for k in model.invariants(state0) if k != "energy"}
    if hasattr(state0, "R"):
        names.add("orthogonality_error_max")
    return set(_CORE_FIELDS) | names


def _read_chunk(path: Path, spec: dict[str, Any],
                fields: set[str] | None = None) -> tuple[dict[str, np.ndarray] | None, str]:
    """``(arrays, "")`` for a sound chunk file, ``(None, reason)`` for a missing or damaged
    one: unreadable, truncated or not an .npz, missing or unexpected fields (``fields``:
    the exact set expected; else at least :data:`_CORE_FIELDS`), an array that is not one
    number per trajectory, or trajectories other than ``spec``'s range."""
    from ._io import read_npz

    if not path.is_file():
        return None, "missing" if not path.exists() else "not a file"
    try:
        arrays = read_npz(path)
    except OSError as err:
        return None, f"unreadable: {err.strerror or err}"
    except ValueError as err:
        return None, str(err).removeprefix("is ")
    count = spec["stop"] - spec["start"]
    missing = sorted((fields or set(_CORE_FIELDS)) - set(arrays))
    if missing:
        return None, f"missing field(s) {', '.join(missing)}"
    if fields is not None and set(arrays) - fields:
        return None, f"unexpected field(s) {', '.join(sorted(set(arrays) - fields))}"
    for k, v in arrays.items():
        if v.shape != (count,) or v.dtype.kind not in "biuf":
            return None, (f"field {k} is {v.dtype} of shape {v.shape}, expected {count} "
                          "numbers")
    if not np.array_equal(arrays["index"], np.arange(spec["start"], spec["stop"])):
        return None, f"holds other trajectories than {spec['start']}..{spec['stop'] - 1}"
    return arrays, ""


def _read_manifest(path: Path) -> tuple[dict[str, Any] | None, str]:
    """``(manifest, "")``, or ``(None, reason)`` if ``path`` is unreadable, not JSON, or
    not a sweep manifest."""
    try:
        old = json.loads(path.read_text())
    except OSError as err:
        return None, f"unreadable: {err.strerror or err}"
    except (UnicodeDecodeError, ValueError) as err:
        return None, f"not valid JSON: {err}"
    if not isinstance(old, dict) or old.get("format") != FORMAT["format"]:
        return None, "not an lgvi-jax sweep manifest"
    if not isinstance(old.get("config"), dict) or not isinstance(old.get("chunks"), list):
        return None, "it has no configuration or chunk list"
    return old, ""


def _stray_temporaries(out: Path) -> list[Path]:
    """Temporary files of interrupted atomic writes (``.<name>.<random>.tmp``)."""
    from ._io import TEMP_SUFFIX

    found = []
    for folder in (out, out / "chunks"):
        if folder.is_dir():
            found += sorted(p for p in folder.glob(f".*{TEMP_SUFFIX}") if p.is_file())
    return found


def prepare_out_dir(out: Path, config: SweepConfig, resume: bool,
                    warn: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Create or check the output folder; return the manifest. Raises :class:`SweepError`
    (one line naming the file and what to do) for an unwritable folder, a folder holding
    another sweep, a ``resume`` whose configuration differs from the one on disk, and a
    damaged manifest or chunks without a manifest (the chunks cannot then be matched to a
    configuration). On ``resume``, stray temporary files of interrupted writes are removed
    (each reported through ``warn``)."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        (out / "chunks").mkdir(exist_ok=True)
    except OSError as err:
        raise SweepError(f"--out {out}: cannot create folder: {err.strerror}") from None
    if not os.access(out, os.W_OK) or not os.access(out / "chunks", os.W_OK):
        raise SweepError(f"--out {out}: folder is not writable")
    manifest_path = out / "manifest.json"
    manifest = {**FORMAT, "config": config.to_json(), "fields": _FIELD_DOCS,
                "chunks": _chunk_plan(config)}
    start_over = (f"delete {manifest_path} and {out / 'chunks'} to start over, or choose "
                  "another folder")
    if manifest_path.exists():
        old, reason = _read_manifest(manifest_path)
        if old is None:
            raise SweepError(f"{manifest_path} is damaged ({reason}), so the chunks beside "
                             f"it cannot be matched to a configuration: {start_over}")
        if not resume:
            raise SweepError(f"--out {out}: already holds a sweep (manifest.json); pass "
                             "--resume to continue it, or choose another folder")
        # ``engine`` (sweeps before the fused steps were retired) chose between engines
        # that solve the same equations: not part of the configuration any more.
        old_cfg = {k: v for k, v in old["config"].items() if k != "engine"}
        if old_cfg != manifest["config"]:
            diffs = [k for k in manifest["config"] if old_cfg.get(k) != manifest["config"][k]]
            raise SweepError(f"--resume: the sweep in {out} was started with a different "
                             f"configuration (differs in: {', '.join(diffs) or 'format'}); "
                             "use the same arguments or another folder")
    elif resume:
        chunks = sorted((out / "chunks").glob("*.npz"))
        if chunks:
            raise SweepError(f"--resume: {manifest_path} is missing but {out / 'chunks'} "
                             f"holds {len(chunks)} chunk file(s) that cannot be matched to a "
                             f"configuration: {start_over}")
    if resume:
        for tmp in _stray_temporaries(out):
            try:
                tmp.unlink()
            except OSError as err:
                raise SweepError(f"--resume: cannot remove the stray temporary file {tmp} "
                                 f"({err.strerror}); remove it by hand") from None
            if warn:
                warn(f"removed {tmp.relative_to(out)}: a temporary file left by an "
                     "interrupted write")
    try:
        atomic_write_json(manifest_path, manifest)
    except OSError as err:
        raise SweepError(f"--out {out}: cannot write {manifest_path.name}: "
                         f"{err.strerror or err}") from None
    return manifest


def _find_todo(out: Path, plan: list[dict[str, Any]], model, state0, resume: bool,
               warn: Callable[[str], None]) -> tuple[list[int], int]:
    """Positions in ``plan`` of the chunks to compute (all of them, or on ``resume`` the
    missing and damaged ones, each damaged one reported through ``warn``), and how many
    were damaged."""
    if not resume:
        return list(range(len(plan))), 0
    fields = _expected_fields(model, state0)
    todo, repaired = [], 0
    for k, c in enumerate(plan):
        arrays, reason = _read_chunk(out / c["file"], c, fields)
        if arrays is None:
            todo.append(k)
            if reason != "missing":
                repaired += 1
                warn(f"chunk {c['file']} is damaged ({reason}): recomputing it")
    return todo, repaired


def _compute_chunks(chunks, config, model, state0, make_method, out: Path, devices,
                    after_chunk: Callable[[int], None]) -> dict[str, float]:
    """Compute and write ``chunks`` (each atomically); ``after_chunk(count)`` after each.
    Returns the rollout wall time per ``method|dt_index``."""
    n_dev = len(devices)
    batch = math.ceil(config.chunk / n_dev) * n_dev  # padded chunk shape, fixed
    batch = min(batch, math.ceil(config.n / n_dev) * n_dev)
    timings: dict[str, float] = {}
    methods = {}
    prepared = None
    if chunks:  # the first rollout loads (or compiles) while the initial conditions do
        c = chunks[0]
        methods[c["method"]] = make_method(c["method"])
        prepared = threading.Thread(target=_prepare_batch, daemon=True, args=(
            model, methods[c["method"]], state0, batch, c["dt"], config.n_steps(c["dt"]),
            config.sample_every, devices))
        prepared.start()
    for i, c in enumerate(chunks):
        name = c["method"]
        if name not in methods:
            methods[name] = make_method(name)
        count = c["stop"] - c["start"]
        states = initial_conditions(model, state0, batch, config.perturb, config.seed,
                                    start=c["start"])
        if prepared is not None:
            prepared.join()
            prepared = None
        start = time.perf_counter()
        res = run_batch(model, methods[name], states, c["dt"], config.n_steps(c["dt"]),
                        sample_every=config.sample_every, devices=devices)
        key = f"{name}|{c['dt_index']}"
        timings[key] = timings.get(key, 0.0) + time.perf_counter() - start
        arrays = {k: v[:count] for k, v in res.items()}
        arrays["index"] = np.arange(c["start"], c["stop"], dtype=np.int64)
        try:
            save_npz_atomic(out / c["file"], arrays)
        except OSError as err:
            raise SweepError(f"cannot write {out / c['file']}: {err.strerror or err}; fix "
                             "that (free disk space, remove what is in the way), then "
                             "rerun with --resume"
                             ) from None
        _test_kill_hook(i)
        after_chunk(count)
    return timings


def run_sweep(config: SweepConfig, model, state0, make_method: Callable[[str], Any],
              out: Path | str, *, resume: bool = False, progress: bool = True,
              devices: Sequence | None = None,
              log: Callable[[str], None] | None = None,
              warn: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run (or resume) a sweep into the folder ``out``; return the summary.

    ``make_method(name)`` builds an integrator. Finished chunks are skipped when
    ``resume`` is true; damaged ones (truncated, corrupt, wrong fields or trajectories) are
    recomputed, and stray temporary files removed, each reported in one line through
    ``warn`` (default: ``log``, else :func:`warnings.warn`). A damaged manifest or chunks
    without one raise :class:`SweepError`. ``progress`` draws a bar on a terminal. Returns
    the summary dict also written to ``summary.json`` (per method and step: energy-error
    quantiles, failures, Newton iterations, throughput) plus ``"chunks_computed"``,
    ``"chunks_skipped"`` and ``"chunks_repaired"``.

    **Several processes.** When JAX runs as several processes (``jax.process_count() >
    1``, after :func:`lgvi_jax.distributed.initialize`), every process calls
    ``run_sweep`` with the same arguments and the same ``out`` on a shared file system.
    Process 0 checks the folder and writes the manifest; the chunks to compute are then
    divided among the processes (process ``i`` takes those at positions ``i`` modulo
    ``N`` of the list, each on its own ``jax.local_devices()``, or ``devices``); when all
    are written, process 0 writes the summary, CSV and plot, and every process returns
    the summary (with ``"processes"`` and ``"chunks_by_process"``). Arguments that differ
    between processes raise :class:`SweepError` in every process, naming the difference.
    Only process 0 draws progress (of the whole sweep) and logs. The watchdog started by
    :func:`lgvi_jax.distributed.initialize` (a process that stops responding ends the
    others with one line and exit status 3) stops when this returns or raises.
    """
    if warn is None:
        if log is not None:
            warn = log
        else:
            import warnings

            def warn(msg: str) -> None:
                warnings.warn(msg, stacklevel=3)

    out = Path(out)
    config.validate()
    if jax.process_count() > 1:
        from .distributed import stop_watchdog

        complete = False
        try:
            summary = _run_sweep_distributed(config, model, state0, make_method, out,
                                             resume=resume, progress=progress,
                                             devices=devices, log=log, warn=warn)
            complete = True
            return summary
        finally:  # the others no longer watch this process (see Watchdog)
            stop_watchdog("done" if complete else "left")
    manifest = prepare_out_dir(out, config, resume, warn=warn)
    devices = tuple(jax.devices() if devices is None else devices)
    plan = manifest["chunks"]
    todo_pos, repaired = _find_todo(out, plan, model, state0, resume, warn)
    todo = [plan[k] for k in todo_pos]
    skipped = len(plan) - len(todo)
    n_traj = sum(c["stop"] - c["start"] for c in plan)
    bar = Progress(n_traj, label=f"sweep {config.system}", unit="traj", enabled=progress)
    bar.advance(n_traj - sum(c["stop"] - c["start"] for c in todo), computed=False)
    if log and skipped:
        log(f"resuming: {skipped} of {len(plan)} chunks already done")
    try:
        timings = _compute_chunks(todo, config, model, state0, make_method, out, devices,
                                  bar.advance)
    finally:
        bar.close()
    results = load_results(out)
    summary = summarize_sweep(config, results)
    summary["chunks_computed"] = len(todo)
    summary["chunks_skipped"] = skipped
    summary["chunks_repaired"] = repaired
    summary["devices"] = [str(d) for d in devices]
    summary["wall_time_s_by_method_dt"] = timings
    _write_outputs(out, config, results, summary)
    return summary


def _differences(a: dict[str, Any], b: dict[str, Any]) -> list[str]:
    return [k for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]


def _why(err: BaseException) -> str:
    """How a process of a distributed sweep ended, for the others: ``process I {this}``."""
    if isinstance(err, KeyboardInterrupt):
        return "was interrupted"
    if isinstance(err, SweepError):
        return f"failed: {err}"
    return f"failed: {type(err).__name__}: {err}"


def _run_sweep_distributed(config, model, state0, make_method, out: Path, *, resume,
                           progress, devices, log, warn) -> dict[str, Any]:
    """:func:`run_sweep` as one of ``jax.process_count()`` processes (see there)."""
    from .distributed import DistributedError, Group

    group = Group("sweep")
    me, n_proc = group.index, group.count
    lead = me == 0
    devices = tuple(jax.local_devices() if devices is None else devices)

    # 1. Every process was started with the same sweep arguments.
    args = {**config.to_json(), "resume": bool(resume)}
    group.publish(f"args/{me}", args)
    group.barrier("args", timeout_s=600)
    ref = group.read("args/0", timeout_s=60)
    for j in range(1, n_proc):
        diffs = _differences(ref, group.read(f"args/{j}", timeout_s=60))
        if diffs:
            names = ", ".join(f"--{k.replace('_', '-')}" if k != "methods" else "--method"
                              for k in diffs)
            raise SweepError(f"process {j} was started with other sweep arguments than "
                             f"process 0 (differs in: {names}); start every process with "
                             "the same arguments")

    # 2. Process 0 checks the folder, writes the manifest and lists the chunks to do.
    if lead:
        try:
            manifest = prepare_out_dir(out, config, resume, warn=warn)
            todo_pos, repaired = _find_todo(out, manifest["chunks"], model, state0, resume,
                                            warn)
        except BaseException as err:
            group.publish("prepared", {"error": str(err) if isinstance(err, SweepError)
                                       else f"process 0 {_why(err)}"})
            raise
        group.publish("prepared", {"todo": todo_pos, "repaired": repaired})
    else:
        prepared = group.read("prepared")
        if "error" in prepared:
            raise SweepError(prepared["error"])
        todo_pos, repaired = prepared["todo"], prepared["repaired"]
        manifest = {"chunks": _chunk_plan(config)}
    plan = manifest["chunks"]
    todo = [plan[k] for k in todo_pos]
    mine = [c for pos, c in enumerate(todo) if pos % n_proc == me]
    total = sum(c["stop"] - c["start"] for c in todo)
    n_traj = sum(c["stop"] - c["start"] for c in plan)
    skipped = len(plan) - len(todo)

    # 3. Each process computes its share; process 0 shows the progress of all.
    bar = Progress(n_traj, label=f"sweep {config.system}", unit="traj",
                   enabled=progress and lead)
    bar.advance(n_traj - total, computed=False)
    shown = [0]

    def show(done: int) -> None:
        if done > shown[0]:
            bar.advance(done - shown[0])
            shown[0] = done

    if lead and log:
        log(f"{n_proc} processes, {len(todo)} chunk(s) to compute"
            + (f" ({skipped} of {len(plan)} already done)" if skipped else ""))
    try:
        try:
            if not lead and not (out / "manifest.json").is_file():
                raise SweepError(f"--out {out}: process {me} does not see the manifest.json "
                                 "that process 0 wrote; every process must write into the "
                                 "same folder on a shared file system")
            def after_chunk(count: int) -> None:
                done = group.add("done", count)
                if lead:
                    show(done)
                failed = group.try_read("failed")  # another process failed: stop too
                if failed is not None:
                    raise SweepError(failed)

            timings = _compute_chunks(mine, config, model, state0, make_method, out,
                                      devices, after_chunk)
        except BaseException as err:  # the others stop too, after their chunk
            try:
                group.client.key_value_set(group._key("failed"), json.dumps(
                    f"process {me} {_why(err)}"))
            except Exception:  # (another process reported first)
                pass
            raise
        group.publish(f"computed/{me}", {"files": [c["file"] for c in mine],
                                         "timings": timings,
                                         "devices": [str(d) for d in devices]})
        try:
            group.wait_for_total("done", total, on_progress=show if lead else None,
                                 failed_key="failed")
        except DistributedError as err:
            raise SweepError(str(err)) from None
        group.barrier("computed", timeout_s=600)
    finally:
        bar.close()

    # 4. Process 0 writes the summary, CSV and plot; the others wait for it.
    if not lead:
        done = group.read("summary")
        if "error" in done:
            raise SweepError(done["error"])
        return json.loads((out / "summary.json").read_text())
    try:
        shares = [group.read(f"computed/{j}", timeout_s=60) for j in range(n_proc)]
        results = load_results(out)
        summary = summarize_sweep(config, results)
        summary["chunks_computed"] = len(todo)
        summary["chunks_skipped"] = skipped
        summary["chunks_repaired"] = repaired
        summary["devices"] = [d for s in shares for d in s["devices"]]
        timings = {}
        for s in shares:
            for k, v in s["timings"].items():
                timings[k] = timings.get(k, 0.0) + v
        summary["wall_time_s_by_method_dt"] = timings
        summary["processes"] = n_proc
        summary["chunks_by_process"] = [s["files"] for s in shares]
        _write_outputs(out, config, results, summary)
    except SweepError as err:
        group.publish("summary", {"error": str(err)})
        raise
    except BaseException as err:
        why = ("was interrupted" if isinstance(err, KeyboardInterrupt) else
               f"failed writing the summary: {err}")
        group.publish("summary", {"error": f"process 0 {why}"})
        raise
    group.publish("summary", {"ok": True})
    return summary


def load_results(out: Path | str) -> dict[tuple[str, float], dict[str, np.ndarray]]:
    """Read every chunk of a sweep folder: ``{(method, dt): {field: array over i}}``,
    rows in trajectory order. Raises :class:`SweepError` (one line naming the file) if the
    manifest is missing or damaged, or a chunk is missing or damaged."""
    out = Path(out)
    manifest_path = out / "manifest.json"
    if not manifest_path.is_file():
        raise SweepError(f"{out}: no manifest.json; not a sweep folder")
    manifest, reason = _read_manifest(manifest_path)
    if manifest is None:
        raise SweepError(f"{manifest_path} is damaged ({reason}); rerun the sweep into "
                         "another folder")
    grouped: dict[tuple[str, float], list[dict[str, np.ndarray]]] = {}
    fields: set[str] | None = None
    for c in manifest["chunks"]:
        try:
            arrays, reason = _read_chunk(out / c["file"], c, fields)
        except (KeyError, TypeError):
            raise SweepError(f"{manifest_path} is damaged (a chunk entry is malformed); "
                             "rerun the sweep into another folder") from None
        if arrays is None:
            raise SweepError(f"{out}: chunk {c['file']} is {reason} (run the same sweep "
                             "command with --resume to recompute it)" if reason == "missing"
                             else f"{out}: chunk {c['file']} is damaged ({reason}); run the "
                             "same sweep command with --resume to recompute it")
        fields = set(arrays)  # every chunk holds the same fields as the first
        grouped.setdefault((c["method"], c["dt"]), []).append(arrays)
    return {key: {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
            for key, parts in grouped.items()}


def summarize_sweep(config: SweepConfig, results) -> dict[str, Any]:
    rows = []
    for (method, dt), r in results.items():
        ok = r["result"] == RESULTS.successful
        e = r["energy_error_max"][ok]
        row = {"method": method, "dt": dt, "n": int(r["result"].size),
               "failed": int(np.sum(~ok)),
               "energy_error_max_median": float(np.median(e)) if e.size else float("nan"),
               "energy_error_max_p95": float(np.quantile(e, 0.95)) if e.size else float("nan"),
               "energy_error_max_max": float(np.max(e)) if e.size else float("nan"),
               "newton_mean": float(np.mean(r["newton_mean"][ok])) if ok.any() else float("nan")}
        for k in r:
            if k.endswith("_drift_max") or k == "orthogonality_error_max":
                row[f"{k}_max"] = float(np.max(r[k][ok])) if ok.any() else float("nan")
        rows.append(row)
    return {**FORMAT, "config": config.to_json(), "rows": rows}


def _write_outputs(out: Path, config: SweepConfig, results, summary) -> None:
    # trajectories.csv: one row per (method, dt, i)
    fields = [k for k in next(iter(results.values())) if k != "index"]
    with atomic_open(out / "trajectories.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["method", "dt", "index", *fields])
        for (method, dt), r in results.items():
            for j in range(r["index"].size):
                writer.writerow([method, repr(dt), int(r["index"][j]),
                                 *(repr(r[k][j].item()) for k in fields)])
    atomic_write_json(out / "summary.json", summary)
    lines = [f"# Sweep: {config.system}, {config.n} initial conditions, perturbation "
             f"{config.perturb:g}, seed {config.seed}, t_final = {config.t_final:g}", "",
             "Relative energy error max |H - H0|/|H0| per trajectory (over trajectories "
             "that did not fail).", "",
             "| method | dt | failed | median | p95 | max | Newton its/step |",
             "|---|---|---|---|---|---|---|"]
    def fmt(x: float, spec: str) -> str:  # n/a: every trajectory of the row failed
        return format(x, spec) if math.isfinite(x) else "n/a"

    for row in summary["rows"]:
        lines.append(f"| {row['method']} | {row['dt']:g} | {row['failed']}/{row['n']} | "
                     f"{fmt(row['energy_error_max_median'], '.3e')} | "
                     f"{fmt(row['energy_error_max_p95'], '.3e')} | "
                     f"{fmt(row['energy_error_max_max'], '.3e')} | "
                     f"{fmt(row['newton_mean'], '.2f')} |")
    atomic_write_text(out / "summary.md", "\n".join(lines) + "\n")
    _plot(out / "energy_error.png", config, results)


def _plot(path: Path, config: SweepConfig, results) -> None:
    from . import _plot_worker
    from .plotting import METHOD_STYLE

    data, labels, colors = [], [], []
    for (method, dt), r in results.items():
        ok = r["result"] == RESULTS.successful
        e = r["energy_error_max"][ok]
        data.append(np.log10(np.maximum(e, 1e-17)) if e.size else np.array([np.nan]))
        failed = int(np.sum(~ok))
        labels.append(f"{method}\ndt={dt:g}" + (f"\n{failed} failed" if failed else ""))
        colors.append(METHOD_STYLE.get(method, {}).get("color", "C0"))
    payload = {
        "data": data, "labels": labels, "colors": colors,
        "ylabel": r"$\log_{10}$ max $|H - H_0|/|H_0|$",
        "title": (f"{config.system}: energy error over {config.n} initial conditions\n"
                  f"(perturbation {config.perturb:g}, t = {config.t_final:g})"),
        "width": max(6.0, 1.1 * len(results) + 2), "height": 4.2,
    }
    atomic_write_bytes(path, _plot_worker.render(payload))
