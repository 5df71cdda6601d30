"""A sweep on disk: the chunk plan, atomic chunk files, the manifest, resume and damaged
chunks, the run over several processes (:func:`run_sweep`)."""

from __future__ import annotations

import json
import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from .._io import (
    atomic_write_json,
    save_npz_atomic,
)
from ..progress import Progress
from .batch import _prepare_batch, initial_conditions, run_batch
from .config import _FIELD_DOCS, FORMAT, SweepConfig, SweepError
from .report import _write_outputs, summarize_sweep

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
    """The fields a chunk of this model holds (the keys the ``finish`` of
    :func:`~lgvi_jax.sweep.batch._sweep_parts` returns)."""
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
    from .._io import read_npz

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
    from .._io import TEMP_SUFFIX

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
        from ..distributed import stop_watchdog

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
    from ..distributed import DistributedError, Group

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
