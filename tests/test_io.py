"""Result files respect the user's umask: every atomic write (temporary file and rename)
ends with the mode ``open(path, "w")`` gives, ``0o666 & ~umask``, never mkstemp's 0600."""

import json
import os
import re
import stat
from pathlib import Path

import numpy as np
import pytest

from lgvi_jax import _io
from lgvi_jax.cli import main

UMASKS = [0o022, 0o077, 0o002]


@pytest.fixture(params=UMASKS, ids=[f"umask{m:03o}" for m in UMASKS])
def umask(request):
    old = os.umask(request.param)
    try:
        yield request.param
    finally:
        os.umask(old)


def mode(path):
    return stat.S_IMODE(os.stat(path).st_mode)


def plain_open_mode(folder):
    """The mode a plain ``open(..., "w")`` gives here (the reference, not a formula)."""
    probe = folder / "plain-open-probe"
    with open(probe, "w") as fh:
        fh.write("x")
    m = mode(probe)
    probe.unlink()
    return m


def test_current_umask_is_read_without_changing_it(umask):
    assert _io.current_umask() == umask
    assert _io.default_file_mode() == 0o666 & ~umask
    assert os.umask(umask) == umask  # unchanged by the read


def test_atomic_writers_give_the_plain_open_mode(tmp_path, umask):
    expected = plain_open_mode(tmp_path)
    assert expected == 0o666 & ~umask
    _io.atomic_write_bytes(tmp_path / "a.bin", b"\x00\x01")
    _io.atomic_write_text(tmp_path / "b.txt", "hello\n")
    _io.atomic_write_json(tmp_path / "c.json", {"x": [1, 2]})
    _io.save_npz_atomic(tmp_path / "d.npz", {"x": np.arange(3)})
    with _io.atomic_open(tmp_path / "e.csv", "w", newline="") as fh:
        fh.write("a,b\n")
    for name in ("a.bin", "b.txt", "c.json", "d.npz", "e.csv"):
        assert mode(tmp_path / name) == expected, name
    assert (tmp_path / "a.bin").read_bytes() == b"\x00\x01"
    assert (tmp_path / "b.txt").read_text() == "hello\n"
    assert json.loads((tmp_path / "c.json").read_text()) == {"x": [1, 2]}
    np.testing.assert_array_equal(np.load(tmp_path / "d.npz")["x"], [0, 1, 2])
    assert (tmp_path / "e.csv").read_text() == "a,b\n"
    # Overwriting an existing file keeps the umask's mode, and no temporary file remains.
    _io.atomic_write_text(tmp_path / "b.txt", "again\n")
    assert mode(tmp_path / "b.txt") == expected
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "b.txt", "c.json",
                                                          "d.npz", "e.csv"]


def test_a_failed_write_leaves_nothing_behind(tmp_path):
    (tmp_path / "keep.txt").write_text("old")

    def boom(fh):
        fh.write(b"partial")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        _io.atomic_write(tmp_path / "keep.txt", boom)
    assert (tmp_path / "keep.txt").read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]


def test_cli_outputs_get_the_plain_open_mode(tmp_path, capsys, umask):
    expected = plain_open_mode(tmp_path)
    sim = tmp_path / "sim" / "run.npz"
    assert main(["simulate", "oscillator", "--method", "verlet", "--dt", "0.1",
                 "--t-final", "1", "--out", str(sim), "--json"]) == 0
    assert mode(sim) == expected
    out = tmp_path / "sweep"
    assert main(["sweep", "oscillator", "--method", "verlet", "--dt", "0.1", "--t-final", "1",
                 "--n", "3", "--chunk", "2", "--out", str(out),
                 "--json"]) == 0
    capsys.readouterr()
    files = [p for p in out.rglob("*") if p.is_file()]
    names = {p.relative_to(out).as_posix() for p in files}
    assert {"manifest.json", "trajectories.csv", "summary.json", "summary.md",
            "energy_error.png", "chunks/verlet__dt0__0000000-0000002.npz",
            "chunks/verlet__dt0__0000002-0000003.npz"} == names
    for p in files:
        assert mode(p) == expected, p.name


def test_no_result_file_is_written_in_place():
    """Every file the library, the command line and the experiment scripts write goes
    through lgvi_jax._io (a temporary file renamed over the destination): no
    ``write_text``/``write_bytes`` or ``open(..., "w")`` outside it, which an interrupted
    run would leave truncated; figures are saved by ``savefig`` into the writer's file
    handle (``fh``), never onto a path."""
    root = Path(__file__).resolve().parent.parent
    in_place = re.compile(r"\.write_(text|bytes)\(|\bopen\([^)]*[\"'][wax]b?\+?[\"']"
                          r"|\.savefig\((?!fh\b)")
    files = {p.resolve() for p in [*(root / "lgvi_jax").rglob("*.py"),
                                   *(root / "experiments").glob("*.py")]}
    assert len(files) > 20  # the scan sees the package and the experiments
    offenders = [f"{path.relative_to(root)}:{i}: {line.strip()}"
                 for path in sorted(files) if path.name != "_io.py"
                 for i, line in enumerate(path.read_text().splitlines(), 1)
                 if in_place.search(line)]
    assert not offenders, offenders
