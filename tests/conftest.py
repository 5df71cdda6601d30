"""Test-session setup, done in :func:`pytest_configure`, before any test module is imported
(so before :mod:`lgvi_jax` applies its XLA settings at import and before JAX's backend
starts; this file must not import :mod:`jax` or :mod:`lgvi_jax` at the top):

* two XLA host devices, so that the sharded code paths (sweeps) run on a CPU-only machine
  too;
* the command line's persistent compilation cache (lgvi_jax._cache) in a temporary folder
  of this run, shared by its workers and children, instead of the user's ~/.cache; turned
  on in the workers too (not only in command-line runs), so that a program compiled by
  one worker or child is loaded, not compiled again, by the others. The folder is new for
  each run (nothing compiled from an earlier state of the code is reused), and an entry's
  key covers the program, the JAX/XLA versions and ``XLA_FLAGS``, so a hit is the same
  compiled program (before, a worker's first in-process ``main([...])`` turned the cache
  on for the rest of that worker's tests anyway, depending on the order of the tests);
* with ``--alt-numerics`` (docs/testing.md), a numerically different but valid compilation
  of every program: the bounds of the suite must hold under both. Set in ``os.environ``,
  so the children that tests start (CLI runs, experiment scripts) inherit it;
* with ``--tolerance-report`` (docs/testing.md, tests/_tolerance_report.py), a list after
  the run of the tolerance checks that came within 10x of failing.
"""

from __future__ import annotations

import os
import platform
import shutil
import tempfile

import _tolerance_report

#: Opt-out of lgvi_jax's own XLA settings (lgvi_jax._xla.OPT_OUT; not imported from there,
#: since importing lgvi_jax here would apply them before the option is read).
_OPT_OUT = "LGVI_JAX_XLA_TUNING"


def alt_xla_flags() -> list[str]:
    """The ``XLA_FLAGS`` entries of ``--alt-numerics``: XLA's MLIR fusion emitters (the
    default of jaxlib, which lgvi_jax replaces by the elemental emitter) and, on x86-64,
    code for SSE4.2 only: no FMA contraction and 128-bit vectors instead of AVX-512/AVX2, so
    products and sums round separately (measured: the car-pendulum rollout of test_xla ends
    3e-12 to 1e-11 from both the tuned and the untuned default compilation)."""
    entries = ["--xla_cpu_use_fusion_emitters=true"]
    if platform.machine().lower() in ("x86_64", "amd64"):
        entries.append("--xla_cpu_max_isa=SSE4_2")
    return entries


def pytest_addoption(parser):
    parser.addoption(
        "--alt-numerics", action="store_true", default=False,
        help="run under a numerically different but valid XLA configuration: "
             f"{_OPT_OUT}=0 and XLA_FLAGS += {' '.join(alt_xla_flags())} (docs/testing.md)")
    parser.addoption(
        "--tolerance-report", action="store_true", default=False,
        help="after the run, list the tolerance checks that came within 10x of failing "
             "(every numpy.testing.assert_allclose, and plain asserts against numbers below "
             "1e-9); needs -o enable_assertion_pass_hook=true (docs/testing.md)")


_CACHE_ENV = "LGVI_JAX_CACHE_DIR"  # lgvi_jax._cache.ENV


def pytest_configure(config):
    if _CACHE_ENV not in os.environ:  # the xdist controller runs first; workers inherit it
        os.environ[_CACHE_ENV] = tempfile.mkdtemp(prefix="lgvi-jax-test-cache-")
        config._lgvi_cache_dir = os.environ[_CACHE_ENV]
    if config.getoption("--alt-numerics"):
        os.environ[_OPT_OUT] = "0"
        current = os.environ.get("XLA_FLAGS", "").split()
        os.environ["XLA_FLAGS"] = " ".join([*current, *(
            entry for entry in alt_xla_flags() if entry not in current)])
    if config.getoption("--tolerance-report"):
        _tolerance_report.start(config)
    import jax  # after the environment is set; JAX reads XLA_FLAGS when its backend starts

    jax.config.update("jax_num_cpu_devices", 2)
    from lgvi_jax import _cache  # after the environment is set, as jax above

    _cache.enable()


#: The car-pendulum rollouts that several modules share (tests/test_lie.py,
#: tests/test_numba_baseline.py, tests/test_composition.py): ``simulate``'s ``n_steps``
#: and ``save_every`` are compile-time constants, while ``dt``, the model's parameters and
#: the initial state are not, so every ``simulate(car_pendulum, method, state, dt,
#: SHARED_ROLLOUT_STEPS, save_every=SHARED_SAVE_EVERY)`` of one method is one compiled
#: program: the first test that needs it compiles it, the others load it from the run's
#: persistent compilation
#: cache (above) or from the worker's memory. A test that needs N < 10^4 steps takes the
#: first N of such a run (the steps are the same; compiling is most of these tests' time,
#: running 10^4 steps a fraction of a second). 10^4 steps saving every 10th state are also
#: the quick reproduction's paper runs (lgvi_jax/studies/car_pendulum.py, quick mode: the four
#: VIs from the paper's state), which tests/test_experiments.py then loads instead of
#: compiling.
SHARED_ROLLOUT_STEPS = 10_000
SHARED_SAVE_EVERY = 10


#: The modules that take longest (wall seconds each, measured on a 2-core machine under
#: ``-n auto``), longest first. pytest-xdist's ``--dist loadscope`` hands out whole modules,
#: by default those with the most tests first, which put the few-test modules with the
#: longest fixtures (the reproductions, the notebooks) at the end of the run, where one
#: worker finishes them while the other has nothing left. With ``--no-loadscope-reorder``
#: (pyproject.toml) the order below is the order they are handed out (longest first: the
#: short modules fill in at the end); the others follow in their usual order. Only the
#: order changes: a module missing here, or a stale estimate, costs time, not a test.
#: (test_lie.py first also because its long runs compile the rollouts the later modules
#: share: SHARED_ROLLOUT_STEPS above.)
LONGEST_FIRST = (
    "test_lie.py", "test_scalarize.py", "test_distributed.py", "test_identify.py",
    "test_notebooks.py", "test_integrators.py", "test_blindspots.py",
    "test_reproduce_full.py", "test_numba_baseline.py", "test_sweep.py",
    "test_composition.py", "test_properties.py", "test_experiments.py", "test_cli.py",
    "test_cache.py", "test_xla.py", "test_simulate.py", "test_newton.py",
    "test_reference.py", "test_so3.py", "test_rigid_models.py",
)


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}

    def key(item):
        module = item.nodeid.split("::", 1)[0].rsplit("/", 1)[-1]
        return rank.get(module, len(rank))

    items.sort(key=key)  # stable: the order within a module, and of the others, is kept


def pytest_assertion_pass(item, lineno, orig, expl):
    if item.config.getoption("--tolerance-report"):
        _tolerance_report.assertion_passed(item, lineno, orig, expl)


def pytest_sessionfinish(session, exitstatus):
    if session.config.getoption("--tolerance-report"):
        _tolerance_report.finish(session.config)


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    if config.getoption("--tolerance-report"):
        _tolerance_report.summary(terminalreporter, config)


def pytest_unconfigure(config):
    for name in ("_lgvi_cache_dir", "_lgvi_tolerance_dir", "_lgvi_pycache_dir"):
        path = getattr(config, name, None)
        if path:
            shutil.rmtree(path, ignore_errors=True)


def pytest_report_header(config):
    if config.getoption("--alt-numerics"):
        return (f"alt-numerics: {_OPT_OUT}={os.environ.get(_OPT_OUT)} "
                f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")
    return None
