"""The XLA setting applied at import (lgvi_jax._xla): it is in a fresh process's XLA_FLAGS
(or not, with the opt-out), gives the same trajectories as the opt-out to rounding,
and says so when it comes too late. Each case runs in a child process, since the setting
only acts before JAX's backend starts."""

import json
import os
import subprocess
import sys

import pytest

import lgvi_jax  # noqa: F401  (the setting is applied by this import)
from lgvi_jax import _xla

_ROLLOUT = """
import json, sys
import jax, numpy as np
import lgvi_jax as lj
model = lj.CarPendulum()
out = {}
for name in ("lgvi", "hamel-exact"):
    method = lj.integrators.with_scalar_newton(lj.RIGID_METHODS[name]())
    run = jax.jit(lambda s: lj.final_state(model, method, s, 5e-3, 2000))
    state, code = run(model.default_state())
    out[name] = {"R": np.asarray(state.R).tolist(), "mu": np.asarray(state.mu).tolist(),
                 "q": np.asarray(state.q).tolist(), "code": int(code)}
out["flags"] = __import__("os").environ.get("XLA_FLAGS", "")
out["added"] = list(lj._xla.added())
print(json.dumps(out))
"""


def _child(code: str, *args: str, **env) -> subprocess.CompletedProcess:
    full = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", _xla.OPT_OUT)}
    full.update(env)
    return subprocess.run([sys.executable, "-c", code, *args], env=full, capture_output=True,
                          text=True, timeout=300, check=False)


def test_setting_is_applied_at_import_and_changes_only_rounding():
    tuned, plain = (_child(_ROLLOUT, **env) for env in ({}, {_xla.OPT_OUT: "0"}))
    assert tuned.returncode == 0 and plain.returncode == 0, tuned.stderr + plain.stderr
    tuned, plain = json.loads(tuned.stdout), json.loads(plain.stdout)
    assert all(entry in tuned["flags"].split() for entry in _xla.flags())
    # What the import says it added is what it added: everything in a clean environment,
    # nothing with the opt-out.
    assert tuned["added"] == _xla.flags() and plain["added"] == []
    assert "xla_backend_extra_options" not in plain["flags"]
    assert "xla_cpu_use_fusion_emitters" not in plain["flags"]
    assert "xla_cpu_prefer_vector_width" not in plain["flags"]
    # Behaviour, not XLA's internals: the setting is in the child's XLA_FLAGS (read by
    # the CPU backend when it starts, after the import) or not, and the trajectories are
    # those of the plain compilation to rounding. (How XLA then compiles the loops is its
    # business and changes between jaxlib versions; the speed-up is measured by
    # `lgvi-jax bench`, not asserted here.)
    for name in ("lgvi", "hamel-exact"):
        a, b = tuned[name], plain[name]
        assert a["code"] == b["code"] == 0
        # 2000 steps of the same equations: the two compilations round differently
        # (instruction selection, contraction to FMA), and the pendulum's motion amplifies
        # rounding over t = 10 (measured: 6e-12 apart for lgvi, 4e-12 for hamel-exact);
        # 1e-10 leaves room for other CPUs, far below what a wrong step would give.
        for key in ("R", "mu", "q"):
            assert max(abs(x - y) for x, y in zip(
                _flat(a[key]), _flat(b[key]), strict=True)) < 1e-10, (name, key)


def _flat(x):
    return [z for y in x for z in (_flat(y) if isinstance(y, list) else [y])]


def test_user_options_are_kept():
    """Four settings of ``XLA_FLAGS`` in one child (one import of JAX instead of four): the
    first as the import of lgvi_jax applies it, the others through the function the import
    calls (``_xla.configure``), each before JAX's backend starts (checked)."""
    mine = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=4096"
    emitters = "--xla_cpu_use_fusion_emitters=true"
    other = "--xla_force_host_platform_device_count=2"
    width = "--xla_cpu_prefer_vector_width=256"
    both = f"{mine} {emitters}"
    cases = [mine, emitters, other, both, width]
    code = ("import json, os, sys\n"
            "import lgvi_jax\n"
            "from lgvi_jax import _xla\n"
            "out = [os.environ['XLA_FLAGS']]\n"
            "for flags in json.loads(sys.argv[1])[1:]:\n"
            "    os.environ['XLA_FLAGS'] = flags\n"
            "    _xla.configure()\n"
            "    out.append(os.environ['XLA_FLAGS'])\n"
            "print(json.dumps({'flags': out, 'started': _xla._backend_started()}))\n")
    out = _child(code, json.dumps(cases), XLA_FLAGS=mine)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    assert result["started"] is False  # every case was configured as at import
    got = [flags.split() for flags in result["flags"]]
    assert got[0] == [mine, *_xla.flags()[1:]]  # the emitter flag where jaxlib knows it
    assert got[1] == [emitters, _xla.flag(), _xla.VECTOR_FLAG]
    assert got[2] == [other, *_xla.flags()]
    assert got[3] == [*both.split(), _xla.VECTOR_FLAG]
    assert got[4] == [width, *_xla.flags()[:-1]]


@pytest.mark.parametrize("version, known", [("0.4.30", True), ("0.10.2", True),
                                            ("0.11.0", False), ("0.11.2", False),
                                            ("1.0.0", False), ("unknown", False)])
def test_the_emitter_flag_only_for_a_jaxlib_that_knows_it(monkeypatch, version, known):
    """jaxlib 0.11 aborts on the retired ``xla_cpu_use_fusion_emitters`` flag (seen on a GPU
    machine with jaxlib 0.11.2: every computation of the process died), so the import adds
    it only for older versions; the small-loop setting stays for all."""
    from importlib import metadata

    real = metadata.version
    monkeypatch.setattr(metadata, "version",
                        lambda name: version if name == "jaxlib" else real(name))
    assert (_xla.EMITTER_FLAG in _xla.flags()) is known
    assert _xla.flags()[0] == _xla.flag()


def test_too_late_warns_and_says_how_to_fix():
    """The import after JAX's first computation warns; with the opt-out the same call
    (``_xla.configure``, what the import runs) is silent. One child for both."""
    code = ("import json, os, warnings, jax, jax.numpy as jnp\n"
            "jnp.zeros(1).block_until_ready()\n"
            "with warnings.catch_warnings(record=True) as w:\n"
            "    warnings.simplefilter('always')\n"
            "    import lgvi_jax\n"
            "from lgvi_jax import _xla\n"
            f"os.environ['{_xla.OPT_OUT}'] = '0'\n"
            "with warnings.catch_warnings(record=True) as w2:\n"
            "    warnings.simplefilter('always')\n"
            "    _xla.configure()\n"
            "print(json.dumps([[(x.category.__name__, str(x.message)) for x in ws]\n"
            "                  for ws in (w, w2)]))\n")
    out = _child(code)
    assert out.returncode == 0, out.stderr
    late, silenced = (json.dumps(ws) for ws in json.loads(out.stdout))
    assert "XlaSettingWarning" in late and "before the first JAX computation" in late
    assert "XlaSettingWarning" not in silenced


@pytest.fixture(scope="module")
def opted_out():
    """``XLA_FLAGS`` in one child with the opt-out as each value below: the first at the
    import of lgvi_jax, the second through the function the import calls."""
    values = ["0", " 0 "]
    code = ("import json, os, sys\n"
            "import lgvi_jax\n"
            "from lgvi_jax import _xla\n"
            "out = [os.environ.get('XLA_FLAGS', '')]\n"
            "os.environ.pop('XLA_FLAGS', None)\n"
            f"os.environ['{_xla.OPT_OUT}'] = sys.argv[1]\n"
            "_xla.configure()\n"
            "out.append(os.environ.get('XLA_FLAGS', ''))\n"
            "print(json.dumps(out))\n")
    out = _child(code, values[1], **{_xla.OPT_OUT: values[0]})
    assert out.returncode == 0, out.stderr
    return dict(zip(values, json.loads(out.stdout), strict=True))


@pytest.mark.parametrize("value", ["0", " 0 "])
def test_opt_out(opted_out, value):
    flags = opted_out[value]
    assert "xla_backend_extra_options" not in flags
    assert "xla_cpu_use_fusion_emitters" not in flags
    assert "xla_cpu_prefer_vector_width" not in flags


def test_alt_numerics_environment(request):
    """Under ``pytest --alt-numerics`` (tests/conftest.py, docs/testing.md) this process
    runs untuned with the alternative flags, and lgvi_jax's own settings are absent; in an
    ordinary run, the tuned default is in effect."""
    flags = os.environ.get("XLA_FLAGS", "").split()
    if request.config.getoption("--alt-numerics"):
        from conftest import alt_xla_flags

        assert os.environ.get(_xla.OPT_OUT) == "0"
        assert all(entry in flags for entry in alt_xla_flags())
        assert not {_xla.flag(), _xla.EMITTER_FLAG, _xla.VECTOR_FLAG} & set(flags)
    elif os.environ.get(_xla.OPT_OUT, "1").strip() != "0":
        assert _xla.flag() in flags


def test_alt_numerics_option_is_applied_before_jax_starts():
    """The option works end to end: a child pytest session with it passes the check above
    (its conftest sets the environment before lgvi_jax's import and JAX's backend)."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", _xla.OPT_OUT)}
    out = subprocess.run(
        [sys.executable, "-m", "pytest", "--alt-numerics", "-o", "addopts=", "-q",
         "-p", "no:cacheprovider", "tests/test_xla.py::test_alt_numerics_environment"],
        cwd=root, env=env, capture_output=True, text=True, timeout=300, check=False)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "1 passed" in out.stdout


@pytest.mark.parametrize(("cpu_flags", "unrolled"), [
    ({"sse4_2", "avx2", "avx512f"}, False), ({"sse4_2", "avx2"}, False), ({"sse4_2"}, True),
    (set(), True)])
def test_loops_unrolled_only_without_avx2(monkeypatch, cpu_flags, unrolled):
    """Unrolling is turned off on the CPUs where that was measured to pay (AVX2 and AVX-512:
    batches compile 35–55 % faster, run as fast); elsewhere, or where the flags cannot be
    read, XLA's default stays. The small-loop setting and the vector width are there
    either way."""
    monkeypatch.setattr(_xla, "_cpu_flags", lambda: cpu_flags)
    assert (_xla.NO_UNROLL_OPTION in _xla.flag()) is not unrolled
    assert _xla._wide_vectors() is ("avx512f" in cpu_flags)
    assert f"{_xla._OPTION}={_xla.SMALL_LOOP_BYTES}" in _xla.flag()
    assert _xla.VECTOR_FLAG in _xla.flags()
