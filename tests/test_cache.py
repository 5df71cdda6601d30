"""The command line's persistent compilation cache (lgvi_jax._cache): where it lives, that a
repeated run reuses it with identical results, that concurrent runs share it safely, and
that it can be switched off."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lgvi_jax import _cache

ARGS = ["simulate", "oscillator", "--method", "gl4", "--dt", "0.01", "--t-final", "2"]


def _env(cache) -> dict:
    env = dict(os.environ)
    env[_cache.ENV] = str(cache)
    return env


def _simulate(out: Path, cache) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "lgvi_jax.cli", *ARGS, "--out", str(out)],
                            env=_env(cache), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


def _finish(proc: subprocess.Popen) -> None:
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err


def _entries(cache: Path) -> set[str]:
    return {p.name for p in cache.glob("*-cache")}


@pytest.mark.parametrize("value", ["off", "0", "", "OFF"])
def test_cache_can_be_switched_off(monkeypatch, value):
    monkeypatch.setenv(_cache.ENV, value)
    assert _cache.cache_dir() is None
    assert _cache.enable() is None


def test_cache_folder_defaults_to_the_user_cache(monkeypatch, tmp_path):
    monkeypatch.delenv(_cache.ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert _cache.cache_dir() == tmp_path / "lgvi_jax" / "xla"
    monkeypatch.setenv(_cache.ENV, str(tmp_path / "mine"))
    assert _cache.cache_dir() == tmp_path / "mine"


def test_unwritable_cache_folder_leaves_the_cache_off(monkeypatch, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv(_cache.ENV, str(blocker / "cache"))
    assert _cache.enable() is None


def test_repeated_and_concurrent_runs_share_the_cache(tmp_path):
    cache = tmp_path / "cache"
    first = _simulate(tmp_path / "a.npz", cache)
    _finish(first)
    stored = _entries(cache)
    assert stored, "the first run stored no compiled program"
    # Two runs at once on the warm cache (reads and writes under JAX's file lock), then a
    # run with the cache off: every result is the same to the last bit.
    procs = [_simulate(tmp_path / f"{name}.npz", cache) for name in ("b", "c")]
    for proc in procs:
        _finish(proc)
    # Every program the first run stored was a hit (still there, the same entry); a later
    # run may add a program the first compiled faster than _cache.MIN_COMPILE_S (not
    # stored then) and, on a busier machine, slower: the set can grow, never change.
    assert stored <= _entries(cache)
    _finish(_simulate(tmp_path / "d.npz", "off"))
    ref = np.load(tmp_path / "a.npz")
    for name in ("b", "c", "d"):
        data = np.load(tmp_path / f"{name}.npz")
        for key in ("q", "p", "energy"):
            np.testing.assert_array_equal(data[key], ref[key])


# ---------------------------------------------------------------------------------------
# The traced-program cache (lgvi_jax._cache.call: jax.export serialisations)
# ---------------------------------------------------------------------------------------


@pytest.fixture
def traces(tmp_path, monkeypatch):
    folder = tmp_path / "traces"
    monkeypatch.setattr(_cache, "_traces", folder)
    monkeypatch.setattr(_cache, "_loaded", {})
    return folder


def _batch(method_name="hamel"):
    from lgvi_jax import sweep
    from lgvi_jax.systems import get_system

    model, state0 = get_system("free-rigid-body").build({})
    method = sweep.sweep_method("free-rigid-body", method_name)
    states = sweep.initial_conditions(model, state0, 4, 0.1, 3)
    # One device: the program the sweep runs once per device's share (sweep.batch._Shares)
    return sweep.batch_arguments(model, method, states, 0.01, 50, devices=jax.devices()[:1])


def _assert_same(out, ref):
    assert set(out) == set(ref)
    for k in ref:
        np.testing.assert_array_equal(np.asarray(out[k]), np.asarray(ref[k]), err_msg=k)


def test_traced_program_is_stored_reloaded_and_bit_identical(traces, monkeypatch):
    """A miss stores one export; a later process (a cleared memo) deserialises it without
    tracing; a damaged entry is traced again; every result equals the direct call's to the
    last bit (the scalar engine's batched rollout: the sweep's program)."""
    from jax import export

    fn, args = _batch()
    before = set(traces.glob("*.jaxexport"))  # the initial conditions' program
    ref = fn(*args)
    _assert_same(_cache.call("test", fn, *args), ref)
    stored = sorted(set(traces.glob("*.jaxexport")) - before)
    assert len(stored) == 1

    monkeypatch.setattr(_cache, "_loaded", {})
    with monkeypatch.context() as m:
        m.setattr(export, "export", lambda *a, **k: pytest.fail("traced again on a hit"))
        _assert_same(_cache.call("test", fn, *args), ref)

    stored[0].write_bytes(b"not an export")
    monkeypatch.setattr(_cache, "_loaded", {})
    _assert_same(_cache.call("test", fn, *args), ref)
    assert sorted(set(traces.glob("*.jaxexport")) - before) == stored
    assert stored[0].stat().st_size > 1000  # rewritten whole

    # another method (static part) or another batch size (shapes) is another program
    fn2, args2 = _batch("lgvi")
    _assert_same(_cache.call("test", fn2, *args2), fn2(*args2))
    assert len(set(traces.glob("*.jaxexport")) - before) == 2


def test_the_sweeps_initial_conditions_are_stored_and_reloaded(traces, monkeypatch):
    """``sweep.initial_conditions`` returns a state class that jax.export cannot serialise:
    its cached program returns the leaves, so a later process loads it instead of tracing
    it again; the states are the same to the last bit."""
    from jax import export

    from lgvi_jax import sweep
    from lgvi_jax.systems import get_system

    model, state0 = get_system("car-pendulum").build({})
    first = sweep.initial_conditions(model, state0, 3, 0.1, 5)
    assert type(first) is type(state0)
    assert len(list(traces.glob("*.jaxexport"))) == 1
    monkeypatch.setattr(_cache, "_loaded", {})
    with monkeypatch.context() as m:
        m.setattr(export, "export", lambda *a, **k: pytest.fail("traced again on a hit"))
        again = sweep.initial_conditions(model, state0, 3, 0.1, 5)
    for a, b in zip(jax.tree.leaves(first), jax.tree.leaves(again), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_compiler_options_apply_with_and_without_the_cache(traces, monkeypatch):
    """``_cache.call(..., compiler_options=...)`` compiles the loaded program with them and,
    without the cache, jits ``fn`` with them (once per function and options): the sweep's
    initial conditions (``IC_COMPILER_OPTIONS``: LLVM's optimisations off) reach the
    compiler with their options on both paths, and are the same to the last bit either
    way and in any chunking."""
    from jax import stages

    from lgvi_jax import sweep
    from lgvi_jax.sweep import batch
    from lgvi_jax.systems import get_system

    model, state0 = get_system("car-pendulum").build({})
    seen = []
    real = stages.Lowered.compile
    monkeypatch.setattr(stages.Lowered, "compile",
                        lambda self, options=None: seen.append(options) or real(self, options))
    cached = sweep.initial_conditions(model, state0, 8, 0.1, 5)
    assert len(list(traces.glob("*.jaxexport"))) == 1
    assert seen == [batch.IC_COMPILER_OPTIONS]
    monkeypatch.setattr(_cache, "_traces", None)
    uncached = sweep.initial_conditions(model, state0, 8, 0.1, 5)
    tail = sweep.initial_conditions(model, state0, 3, 0.1, 5, start=5)
    key = (batch._initial_condition_leaves, tuple(batch.IC_COMPILER_OPTIONS.items()))
    assert key in _cache._UNCACHED
    for a, b, c in zip(jax.tree.leaves(cached), jax.tree.leaves(uncached),
                       jax.tree.leaves(tail), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        np.testing.assert_array_equal(np.asarray(a)[5:], np.asarray(c))


def test_a_program_that_cannot_be_exported_is_not_traced_for_export_again(traces,
                                                                         monkeypatch):
    """A program jax.export refuses (here: an output of an unregistered pytree class) runs
    directly, and a marker keeps later processes from paying for the failed export."""
    from jax import export

    from lgvi_jax.systems import get_system

    _, state0 = get_system("car-pendulum").build({})
    out = _cache.call("test", lambda s: jax.tree.map(lambda x: 2 * x, s), state0)
    assert type(out) is type(state0)
    assert not list(traces.glob("*.jaxexport")) and len(list(traces.glob("*.noexport"))) == 1
    monkeypatch.setattr(_cache, "_loaded", {})
    with monkeypatch.context() as m:
        m.setattr(export, "export", lambda *a, **k: pytest.fail("export tried again"))
        again = _cache.call("test", lambda s: jax.tree.map(lambda x: 2 * x, s), state0)
    np.testing.assert_array_equal(np.asarray(again.q), 2 * np.asarray(state0.q))


def test_static_parts_without_a_faithful_key_bypass_the_cache(traces):
    import jax.numpy as jnp

    x = jnp.arange(3.0)
    out = _cache.call("test", lambda f, v: f(v), lambda v: 2 * v, x)  # a function: no key
    np.testing.assert_array_equal(out, 2 * x)
    assert not traces.exists() or not list(traces.glob("*.jaxexport"))
    out = _cache.call("test", lambda v, k: v * k, x, 3.0)  # numbers are keyed
    np.testing.assert_array_equal(out, 3 * x)
    assert len(list(traces.glob("*.jaxexport"))) == 1


def test_a_prepared_rollout_is_loaded_once_and_gives_the_same_results(traces, monkeypatch):
    """The sweep prepares its first rollout in a thread from the shapes and shardings its
    states will have (``_cache.prepare`` with ``ShapeDtypeStruct`` leaves) while it computes
    the initial conditions; the later call then runs the prepared program (no second load)
    and gives the direct call's results to the last bit."""
    import threading

    from lgvi_jax import sweep
    from lgvi_jax.systems import get_system

    model, state0 = get_system("free-rigid-body").build({})
    method = sweep.sweep_method("free-rigid-body", "hamel")
    devices = tuple(jax.devices())
    batch = 2 * len(devices)
    thread = threading.Thread(target=sweep.batch._prepare_batch, args=(
        model, method, state0, batch, 0.01, 50, 1, devices))
    thread.start()
    states = sweep.initial_conditions(model, state0, batch, 0.1, 3)
    thread.join()
    assert len(_cache._loaded) == 2  # the initial conditions and the rollout
    fn, args = sweep.batch_arguments(model, method, states, 0.01, 50, devices=devices)
    with monkeypatch.context() as m:
        m.setattr(_cache, "_load_or_export", lambda *a: pytest.fail("loaded again"))
        out = sweep.run_batch(model, method, states, 0.01, 50, devices=devices)
    _assert_same(out, fn(*args))


def test_a_loaded_program_serves_several_threads(traces, monkeypatch):
    """``_cache.program`` loads (here: traces and stores) the program once, compiled, and
    its callable gives ``fn``'s results from several threads at once (the sweep's shares,
    one per CPU device) without loading it again."""
    import threading

    loads = []
    real = _cache._load_or_export
    monkeypatch.setattr(_cache, "_load_or_export", lambda *a: loads.append(1) or real(*a))
    fn = jax.jit(lambda x, k: jnp.cumsum(jnp.sin(k * x)))
    xs = [jnp.linspace(0.0, 1.0 + i, 64) for i in range(4)]
    run = _cache.program("test", fn, xs[0], 3.0)
    outs = [None] * len(xs)

    def one(i):
        outs[i] = run(xs[i], 3.0)

    threads = [threading.Thread(target=one, args=(i,)) for i in range(len(xs))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert loads == [1]
    for x, out in zip(xs, outs, strict=True):
        np.testing.assert_array_equal(np.asarray(out), np.asarray(fn(x, 3.0)))
