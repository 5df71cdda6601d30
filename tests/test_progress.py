"""lgvi_jax.progress: the bar (tqdm) on a terminal, silence elsewhere, the rate's count."""

import io
import re
import time

import pytest

from lgvi_jax.progress import Progress, format_duration


class Terminal(io.StringIO):
    def isatty(self):
        return True


def frames(text):
    """The bar's successive drawings (each starts with a carriage return)."""
    return [f.rstrip() for f in text.split("\r") if f.strip()]


def test_draws_label_count_rate_and_ends_the_line():
    out = Terminal()
    bar = Progress(10, label="sweep heavy-top", unit="traj", stream=out, min_interval=0)
    bar.advance(4, computed=False)  # resumed chunks: counted, not in the rate
    time.sleep(0.05)
    bar.advance(2)
    bar.label = "sweep done"
    bar.close()
    text = out.getvalue()
    assert text.endswith("\n") and text.count("\n") == 1
    shown = frames(text)
    # Every drawing, the final one included: label [bar] done/total unit rate ETA.
    assert re.fullmatch(r"sweep heavy-top \[#{11}\.{17}\] 4/10 traj +\?traj/s +ETA \?",
                        shown[-3]), shown
    assert shown[-2].startswith("sweep heavy-top [") and " 6/10 traj " in shown[-2]
    assert shown[-1].startswith("sweep done [") and " 6/10 traj " in shown[-1]
    # The rate counts the 2 computed items only (over >= 0.05 s), not the 4 skipped:
    # at most 2 / 0.05 = 40/s, where counting all 6 could show up to 120/s.
    rate = float(re.search(r"([\d.]+)traj/s", shown[-1]).group(1))
    assert 0 < rate <= 40
    assert bar.done == 6 and bar.computed == 2
    assert 0 < bar.rate <= 40


def test_total_can_be_lowered_to_the_items_done():
    # identify.fit sets the total to the iterations taken when it stops early.
    out = Terminal()
    bar = Progress(300, label="fit", unit="it", stream=out, min_interval=0)
    for _ in range(7):
        bar.advance(1)
    bar.total = 7
    bar.close()
    final = frames(out.getvalue())[-1]
    assert re.match(r"fit \[#{28}\] 7/7 it ", final), final


@pytest.mark.parametrize("stream, enabled", [(io.StringIO(), True), (Terminal(), False)],
                         ids=["not-a-terminal", "disabled"])
def test_silent_off_a_terminal_or_when_disabled(stream, enabled):
    bar = Progress(5, label="x", stream=stream, enabled=enabled, min_interval=0)
    bar.advance(3)
    bar.advance(2, computed=False)
    bar.close()
    assert stream.getvalue() == ""
    assert not bar.enabled and bar.done == 5 and bar.computed == 3
    assert " 5/5 " in bar.line()  # the text is still available


def test_format_duration():
    assert format_duration(65) == "01:05"
    assert format_duration(3725.4) == "1:02:05"
    assert format_duration(-3) == "00:00"
    assert format_duration(float("nan")) == "?" and format_duration(float("inf")) == "?"


def test_draws_on_a_terminal_that_reports_no_size():
    """A fresh pseudo-terminal has 0 rows and 0 columns (a bare ``pty``, some CI runners):
    tqdm alone would truncate the line to nothing; the bar is drawn whole."""
    pty = pytest.importorskip("pty")
    import os

    master, slave = pty.openpty()
    try:
        with os.fdopen(slave, "w") as stream:
            bar = Progress(3, label="fit", unit="it", stream=stream, min_interval=0)
            assert bar.enabled
            for _ in range(3):
                bar.advance(1)
            bar.close()
        text = os.read(master, 65536).decode()
    finally:
        os.close(master)
    final = frames(text.replace("\n", ""))[-1]
    assert re.match(r"fit \[#{28}\] 3/3 it ", final), text
