"""The tolerance report's measure (tests/_tolerance_report.py): the fraction of a
tolerance that a check used is at most 1 exactly when numpy's ``assert_allclose`` passes,
and the values of a plain assert's explanation are read back."""

import _tolerance_report as tr
import numpy as np
import pytest


def _passes(a, d, rtol, atol) -> bool:
    # assert_allclose's test (|a - d| <= atol + rtol |d|, NaNs equal), without calling it:
    # under --tolerance-report its failures here would be recorded as this file's.
    return bool(np.all(np.isclose(a, d, rtol=rtol, atol=atol, equal_nan=True)))


@pytest.mark.parametrize("seed", range(5))
def test_fraction_used_is_at_most_one_exactly_when_allclose_passes(seed):
    rng = np.random.default_rng(seed)
    for _ in range(200):
        d = rng.normal(size=4) * 10.0 ** rng.integers(-3, 3)
        a = d + rng.normal(size=4) * 10.0 ** rng.integers(-16, -8)
        rtol, atol = 10.0 ** rng.integers(-15, -9), [0.0, 1e-13][rng.integers(2)]
        ratio = tr._allclose_ratio(a, d, rtol, atol)
        assert (ratio <= 1.0) == _passes(a, d, rtol, atol), (ratio, rtol, atol)
    assert tr._allclose_ratio([1.0, np.nan], [1.0, np.nan], 0.0, 0.0) == 0.0  # NaNs match
    assert tr._allclose_ratio(1.0 + 1e-12, 1.0, 0.0, 0.0) == np.inf  # no tolerance at all


def test_values_of_an_explanation_are_read():
    assert tr._value("np.float64(4.4e-14)") == 4.4e-14
    assert tr._value("(1e-12 * np.float64(3.0))") == pytest.approx(3e-12, rel=1e-15)
    assert tr._value("summary['x']") is None
    assert tr._TIGHT.search("x <= 1e-12") and tr._TIGHT.search("x < 2e-9")
    assert not tr._TIGHT.search("x <= 1e-6") and not tr._TIGHT.search("x <= 0.5")


class _Item:
    path = "tests/test_example.py"


def test_plain_and_approx_asserts_are_recorded(monkeypatch):
    monkeypatch.setattr(tr, "_records", {})
    tr.assertion_passed(_Item, 3, "x <= 1e-12", "np.float64(4e-13) <= 1e-12")
    tr.assertion_passed(_Item, 4, "x <= 0.5", "0.25 <= 0.5")  # not a tight number: skipped
    tr.assertion_passed(_Item, 5, "x == pytest.approx(y, rel=1e-12)",
                        "1.0000000000005 == 1.0 ± 1.0e-12")
    assert tr._records.keys() == {"test_example.py:3", "test_example.py:5"}
    assert tr._records["test_example.py:3"] == pytest.approx(0.4, rel=1e-12)
    assert tr._records["test_example.py:5"] == pytest.approx(0.5, rel=1e-3)
