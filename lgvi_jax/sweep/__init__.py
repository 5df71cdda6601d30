r"""Batched, resumable energy-drift sweeps: many initial conditions x methods x steps.

A sweep draws ``n`` initial conditions around a model's default state, integrates each one
with every ``(method, dt)`` pair and records, per trajectory, how well the structure was
kept. It is built for long unattended runs:

* **Batched and split over the devices.** A chunk of trajectories is one ``jax.vmap`` of a
  jitted rollout, split over every device in ``jax.devices()``, each device's share
  independent of the others (no communication): on CPUs the one-device program run once
  per share, the shares concurrently; on accelerators ``jax.shard_map``. On a CPU-only
  machine, expose one XLA host device per core (``lgvi-jax sweep --devices N``, or
  ``jax.config.update("jax_num_cpu_devices", N)`` before JAX starts, or ``XLA_FLAGS=
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

from .batch import batch_arguments, initial_conditions, run_batch
from .config import FORMAT, SweepConfig, SweepError, engine_name, sweep_method
from .report import summarize_sweep
from .store import KILL_HOOK_ENV, load_results, prepare_out_dir, run_sweep

__all__ = [
    "FORMAT",
    "KILL_HOOK_ENV",
    "SweepConfig",
    "SweepError",
    "batch_arguments",
    "engine_name",
    "initial_conditions",
    "load_results",
    "prepare_out_dir",
    "run_batch",
    "run_sweep",
    "summarize_sweep",
    "sweep_method",
]
