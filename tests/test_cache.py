"""The command line's persistent compilation cache (lgvi_jax._cache): where it lives, that a
repeated run reuses it with identical results, that concurrent runs share it safely, and
that it can be switched off."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

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
    assert _entries(cache) == stored  # nothing recompiled: every program was a hit
    _finish(_simulate(tmp_path / "d.npz", "off"))
    ref = np.load(tmp_path / "a.npz")
    for name in ("b", "c", "d"):
        data = np.load(tmp_path / f"{name}.npz")
        for key in ("q", "p", "energy"):
            np.testing.assert_array_equal(data[key], ref[key])
