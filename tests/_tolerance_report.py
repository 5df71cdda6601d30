"""``pytest --tolerance-report`` (tests/conftest.py, docs/testing.md): how close every
tolerance check of a run came to failing.

A bound that one machine meets with little room is the next machine's red CI. This records,
for every call site,

* of ``numpy.testing.assert_allclose``: the largest ``|actual - desired| / (atol + rtol
  |desired|)`` over its calls (numpy's own criterion, so 1 is the edge);
* of a plain ``assert a <= b`` / ``assert a < b`` whose source names a number below 1e-9:
  the largest ``|a| / b``; of ``assert a == pytest.approx(b, ...)`` on scalars, ``|a − b|``
  over the tolerance (pytest's ``pytest_assertion_pass`` hook; it needs ``-o
  enable_assertion_pass_hook=true``, and the test modules rewritten afresh, which
  :func:`start` arranges);

and lists after the run those above ``1 / MARGIN``: checks with less than the 10x margin the
suite asks for. Under ``pytest-xdist`` each worker writes its records to a folder the
controller made, and the controller merges them.
"""

from __future__ import annotations

import json
import os
import re
import sys
import tempfile
import traceback
from pathlib import Path

#: The folder the workers write to (set by the controller, inherited by the workers).
ENV = "LGVI_TOLERANCE_REPORT_DIR"
#: A check is listed when it used more than ``1 / MARGIN`` of its tolerance.
MARGIN = 10.0
_TIGHT = re.compile(r"\de-(9|[1-9]\d)\b")
_NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*(?:[eE][-+]?\d+)?|inf|nan)")
_records: dict[str, float] = {}


def _site() -> str | None:
    """``file:line`` of the innermost frame in a test module."""
    for frame in reversed(traceback.extract_stack()[:-2]):
        if os.path.basename(frame.filename).startswith("test_"):
            return f"{os.path.basename(frame.filename)}:{frame.lineno}"
    return None


def _keep(site: str | None, ratio: float) -> None:
    if site is not None and ratio == ratio:  # not NaN
        _records[site] = max(ratio, _records.get(site, 0.0))


def _allclose_ratio(actual, desired, rtol, atol) -> float:
    import numpy as np

    a = np.asarray(actual)
    dtype = np.complex128 if np.iscomplexobj(a) else np.float64
    a, d = np.broadcast_arrays(a.astype(dtype), np.asarray(desired).astype(dtype))
    finite = np.isfinite(a) & np.isfinite(d)
    if not finite.any():
        return 0.0
    err, tol = np.abs(a - d)[finite], (atol + rtol * np.abs(d))[finite]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(tol > 0, err / tol, np.where(err > 0, np.inf, 0.0))
    return float(np.max(ratio))


def start(config) -> None:
    """Wrap ``assert_allclose`` and make the test modules be rewritten with the pass hook."""
    import pytest

    if not config.getini("enable_assertion_pass_hook"):
        raise pytest.UsageError("--tolerance-report needs the assertion-pass hook: run "
                                "pytest --tolerance-report -o enable_assertion_pass_hook=true")
    if ENV not in os.environ:  # the xdist controller (or a run without workers)
        os.environ[ENV] = tempfile.mkdtemp(prefix="lgvi-jax-tolerances-")
        config._lgvi_tolerance_dir = os.environ[ENV]
    # Rewritten modules cached by an earlier run carry no hook calls: rewrite them afresh.
    sys.pycache_prefix = config._lgvi_pycache_dir = tempfile.mkdtemp(prefix="lgvi-jax-pycache-")
    import numpy as np
    import numpy.testing as npt

    original = npt.assert_allclose

    def assert_allclose(actual, desired, rtol=1e-7, atol=0, *args, **kwargs):
        try:
            _keep(_site(), _allclose_ratio(actual, desired, rtol, atol))
        except Exception:  # a comparison numpy itself will report
            pass
        return original(actual, desired, rtol, atol, *args, **kwargs)

    npt.assert_allclose = np.testing.assert_allclose = assert_allclose


def _value(text: str) -> float | None:
    text = re.sub(r"np\.float\d+\(([^()]*)\)", r"\1", text.strip())
    if re.fullmatch(r"[\d.eE+\-*/() ]+", text):
        try:
            return float(eval(text, {"__builtins__": {}}))  # numbers and operators only
        except (SyntaxError, ZeroDivisionError, TypeError):
            return None
    return float(text) if _NUMBER.fullmatch(text) else None


def assertion_passed(item, lineno: int, orig: str, expl: str) -> None:
    """Record ``|a| / b`` of a passing ``assert a <(=) b`` whose source has a tight number,
    and ``|a − b| / t`` of a passing ``assert a == pytest.approx(b, ...)`` on scalars
    (shown as ``a == b ± t``, ``t`` to two digits)."""
    if not expl:
        return
    first = expl.splitlines()[0]
    site = f"{os.path.basename(str(item.path))}:{lineno}"
    approx = re.match(r"^(.*?) == (.*?) ± (.*)$", first)
    if approx and "approx" in orig:
        a, b, t = (_value(g) for g in approx.groups())
        if None not in (a, b, t) and t > 0:
            _keep(site, abs(a - b) / t)
        return
    if not _TIGHT.search(orig):
        return
    match = re.match(r"^(.*?)\s(<=|<)\s(.*)$", first)
    if not match:
        return
    a, b = _value(match.group(1)), _value(match.group(3))
    if a is not None and b is not None and b > 0:
        _keep(site, abs(a) / b)


def finish(config) -> None:
    """Each process writes its records; the controller merges them (terminal summary)."""
    folder = os.environ.get(ENV)
    if folder:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "controller")
        (Path(folder) / f"{worker}.json").write_text(json.dumps(_records))


def summary(terminalreporter, config) -> None:
    folder = getattr(config, "_lgvi_tolerance_dir", None)
    if not folder:
        return
    merged: dict[str, float] = {}
    for path in Path(folder).glob("*.json"):
        for site, ratio in json.loads(path.read_text()).items():
            merged[site] = max(ratio, merged.get(site, 0.0))
    close = sorted(((r, s) for s, r in merged.items() if r > 1 / MARGIN), reverse=True)
    terminalreporter.section("tolerance report")
    terminalreporter.write_line(
        f"{len(merged)} checks recorded; {len(close)} used more than 1/{MARGIN:g} of their "
        "tolerance (fraction used, call site):")
    for ratio, site in close:
        terminalreporter.write_line(f"  {ratio:7.3f}  {site}")
