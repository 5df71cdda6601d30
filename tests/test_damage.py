"""Damaged result folders and input files: repaired or refused in one line, never a
traceback, never a silently wrong summary (issue 20, section 3)."""

import csv
import json
import re
import shutil

import numpy as np
import pytest

from lgvi_jax.cli import main
from lgvi_jax.sweep import SweepError, load_results

# Two methods x one step x chunks of 2 over 5 conditions: 6 chunk files, fast (oscillator).
SWEEP = ["sweep", "oscillator", "--method", "verlet,rk4", "--dt", "0.1", "--t-final", "2",
         "--n", "5", "--chunk", "2", "--perturb", "0.1", "--seed", "3", "--json"]
CHUNK = "chunks/verlet__dt0__0000002-0000004.npz"


def sweep(out, capsys, *extra):
    code = main([*SWEEP, "--out", str(out), *extra])
    stdout, stderr = capsys.readouterr()
    return code, stdout, stderr


def rows(out):
    with open(out / "trajectories.csv") as fh:
        return sorted(csv.reader(fh))


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """An undamaged sweep folder (the reference) and its trajectories."""
    out = tmp_path_factory.mktemp("clean") / "sweep"
    assert main([*SWEEP, "--out", str(out)]) == 0
    return out


@pytest.fixture
def copy(clean, tmp_path):
    out = tmp_path / "sweep"
    shutil.copytree(clean, out)
    return out


def _truncate(path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _garbage(path):
    path.write_bytes(np.random.default_rng(0).bytes(700))


def _empty(path):
    path.write_bytes(b"")


def _flip_a_byte(path):  # the CRC of a member no longer matches
    data = bytearray(path.read_bytes())
    data[100] ^= 0xFF
    path.write_bytes(bytes(data))


def _rewrite(path, change):
    with np.load(path) as d:
        arrays = {k: d[k] for k in d.files}
    change(arrays)
    np.savez(path, **arrays)


def _drop_field(path):
    _rewrite(path, lambda a: a.pop("energy_error_max"))


def _extra_field(path):
    _rewrite(path, lambda a: a.update(bogus=np.zeros(2)))


def _wrong_shape(path):
    _rewrite(path, lambda a: a.update(energy_error_max=np.zeros((2, 3))))


def _other_trajectories(path):  # e.g. a chunk copied over another one
    _rewrite(path, lambda a: a.update(index=a["index"] + 1))


def _objects(path):
    _rewrite(path, lambda a: a.update(energy_error_max=np.array([{}, {}], dtype=object)))


def _single_npy(path):
    with open(path, "wb") as fh:
        np.save(fh, np.arange(2))


def _a_folder(path):
    path.unlink()
    path.mkdir()


DAMAGE = {
    "truncated": (_truncate, "truncated or corrupt"),
    "garbage": (_garbage, "not an .npz archive"),
    "empty": (_empty, "empty"),
    "bad-crc": (_flip_a_byte, "truncated or corrupt"),
    "missing-field": (_drop_field, "missing field(s) energy_error_max"),
    "extra-field": (_extra_field, "unexpected field(s) bogus"),
    "wrong-shape": (_wrong_shape, "field energy_error_max is float64 of shape (2, 3)"),
    "other-trajectories": (_other_trajectories, "holds other trajectories than 2..3"),
    "pickled-objects": (_objects, "pickled data"),
    "single-npy": (_single_npy, "single .npy array"),
    "a-folder": (_a_folder, "not a file"),
}


@pytest.mark.parametrize("kind", list(DAMAGE))
def test_resume_recomputes_a_damaged_chunk(clean, copy, capsys, kind):
    damage, reason = DAMAGE[kind]
    damage(copy / CHUNK)
    # Reading the damaged folder is refused in one line naming the chunk.
    with pytest.raises(SweepError, match=re.escape(CHUNK)) as info:
        load_results(copy)
    assert "--resume" in str(info.value) and "\n" not in str(info.value)
    code, stdout, stderr = sweep(copy, capsys, "--resume")
    if kind == "a-folder":  # cannot be replaced by a file: refused, naming it
        assert code == 2 and "Traceback" not in stderr
        assert stderr.strip().splitlines()[-1].startswith(
            f"lgvi-jax sweep: error: cannot write {copy / CHUNK}: ")
        return
    assert code == 0, stderr
    assert "Traceback" not in stderr
    lines = stderr.strip().splitlines()
    assert lines == [f"lgvi-jax sweep: chunk {CHUNK} is damaged ({lines[0].split('(', 1)[1]}"]
    assert reason in lines[0] and lines[0].endswith("): recomputing it")
    summary = json.loads(stdout)
    assert (summary["chunks_computed"], summary["chunks_skipped"],
            summary["chunks_repaired"]) == (1, 5, 1)
    assert rows(copy) == rows(clean)  # the repaired results are the undamaged run's


def test_resume_repairs_several_files_one_line_each(clean, copy, capsys):
    _truncate(copy / CHUNK)
    _garbage(copy / "chunks/rk4__dt0__0000000-0000002.npz")
    (copy / "chunks/rk4__dt0__0000004-0000005.npz").unlink()  # missing: just computed
    stray = [copy / "chunks/.rk4__dt0__0000004-0000005.npz.abc123.tmp",
             copy / ".manifest.json.xyz.tmp", copy / ".trajectories.csv.q1.tmp"]
    for p in stray:
        p.write_bytes(b"half-written")
    code, stdout, stderr = sweep(copy, capsys, "--resume")
    assert code == 0, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 5 and "Traceback" not in stderr
    assert sum("is damaged" in line and "recomputing it" in line for line in lines) == 2
    assert sum("a temporary file left by an interrupted write" in line for line in lines) == 3
    for p in stray:
        assert not p.exists()
        assert any(p.name in line for line in lines)
    summary = json.loads(stdout)
    assert (summary["chunks_computed"], summary["chunks_repaired"]) == (3, 2)
    assert rows(copy) == rows(clean)
    assert not list(copy.rglob("*.tmp"))


def test_stray_temporary_files_alone_are_removed(clean, copy, capsys):
    (copy / "chunks" / ".x.npz.1.tmp").write_bytes(b"")
    code, stdout, stderr = sweep(copy, capsys, "--resume")
    assert code == 0 and json.loads(stdout)["chunks_computed"] == 0
    assert stderr.strip() == ("lgvi-jax sweep: removed chunks/.x.npz.1.tmp: a temporary file "
                              "left by an interrupted write")
    assert rows(copy) == rows(clean)


@pytest.mark.parametrize("manifest", [
    b'{"format": "lgvi-jax-sweep", "version": 1, "config": {"system": "osc',  # cut short
    b"\x00\xff\xfe garbage",
    b"[1, 2, 3]",
    b'{"format": "lgvi-jax-sweep", "version": 1}',
    b"",
], ids=["truncated", "binary", "a-list", "no-config", "empty"])
@pytest.mark.parametrize("resume", [True, False])
def test_a_damaged_manifest_is_refused_in_one_line(copy, capsys, manifest, resume):
    (copy / "manifest.json").write_bytes(manifest)
    before = {p: p.read_bytes() for p in copy.rglob("*") if p.is_file()}
    code, stdout, stderr = sweep(copy, capsys, *(["--resume"] if resume else []))
    assert code == 2 and stdout == ""
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in stderr
    assert f"{copy / 'manifest.json'} is damaged (" in lines[0]
    assert "delete" in lines[0] and "another folder" in lines[0]
    # Nothing was changed on disk.
    assert {p: p.read_bytes() for p in copy.rglob("*") if p.is_file()} == before
    with pytest.raises(SweepError, match=r"manifest\.json is damaged"):
        load_results(copy)


def test_chunks_without_a_manifest(clean, copy, capsys):
    (copy / "manifest.json").unlink()
    code, stdout, stderr = sweep(copy, capsys, "--resume")
    assert code == 2 and len(stderr.strip().splitlines()) == 1
    assert "manifest.json is missing" in stderr and "6 chunk file(s)" in stderr
    assert "delete" in stderr and "Traceback" not in stderr
    with pytest.raises(SweepError, match=r"no manifest\.json"):
        load_results(copy)
    # Without --resume the folder is recomputed from scratch, to the same results.
    code, stdout, stderr = sweep(copy, capsys)
    assert code == 0 and json.loads(stdout)["chunks_computed"] == 6
    assert rows(copy) == rows(clean)


def test_resume_of_a_fresh_folder_and_of_a_finished_one(clean, copy, capsys, tmp_path):
    code, stdout, _ = sweep(tmp_path / "fresh", capsys, "--resume")
    assert code == 0 and json.loads(stdout)["chunks_computed"] == 6
    code, stdout, stderr = sweep(copy, capsys, "--resume")
    assert code == 0 and stderr == ""
    summary = json.loads(stdout)
    assert (summary["chunks_computed"], summary["chunks_skipped"]) == (0, 6)
    assert rows(copy) == rows(clean)


# ---------------------------------------------------------------------------------------
# fit --data with a file that is not an observations .npz
# ---------------------------------------------------------------------------------------


def _observations(path):
    from lgvi_jax import CarPendulum
    from lgvi_jax.identify import observe

    np.savez(path, **observe(CarPendulum(), np.linspace(0.0, 0.2, 5)))


@pytest.mark.parametrize("kind, write, message", [
    ("text", lambda p: p.write_text("t,R,q\n0,1,2\n"), "not an .npz archive"),
    ("garbage", lambda p: p.write_bytes(np.random.default_rng(1).bytes(500)),
     "not an .npz archive"),
    ("empty", lambda p: p.write_bytes(b""), "is empty"),
    ("truncated", lambda p: (_observations(p), _truncate(p)), "truncated or corrupt"),
    ("npy", _single_npy, "single .npy array"),
    ("objects", lambda p: np.savez(p, t=np.array([{}], dtype=object)), "pickled data"),
    ("missing-keys", lambda p: np.savez(p, t=np.zeros(3)), "missing key(s) R, q"),
])
def test_fit_data_that_is_not_observations(tmp_path, capsys, kind, write, message):
    data = tmp_path / f"{kind}.npz"
    write(data)
    out = tmp_path / "fit.json"
    code = main(["fit", "car-pendulum", "--data", str(data), "--method", "lgvi", "--dt",
                 "0.05", "--fit", "J", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err
    assert lines[0].startswith(f"lgvi-jax fit: error: --data {data}")
    assert message in lines[0]
    if kind not in ("objects",):
        assert "pickle" not in lines[0]
    assert not out.exists()


# ---------------------------------------------------------------------------------------
# A failed run's summary shows no made-up numbers
# ---------------------------------------------------------------------------------------


def test_simulate_failing_at_step_0_prints_no_energy_error(tmp_path, capsys):
    out = tmp_path / "fail.npz"
    # 10^4 steps saving every 10th state: the compiled rollout tests/test_lie.py runs for
    # lgvi on the car-pendulum (tests/conftest.py: SHARED_ROLLOUT_STEPS), loaded, not
    # compiled again (the failure at step 0 makes the length irrelevant to the output).
    run = ["simulate", "car-pendulum", "--method", "lgvi", "--dt", "0.01", "--t-final",
           "100", "--save-every", "10", "--set", "omega0=1e6,0,0", "--out", str(out)]
    code = main(run)
    stdout, stderr = capsys.readouterr()
    assert code == 1
    assert "relative energy error: max n/a (failed at step 0), final n/a" in stdout
    assert "0.000e+00" not in stdout
    assert "integration failed: step 0" in stderr
    code = main([*run, "--json"])
    report = json.loads(capsys.readouterr().out)
    assert code == 1 and report["failed_step"] == 0
    for key in ("energy_error_max", "energy_error_final", "momentum_drift_max"):
        assert np.isnan(report[key]), key


def test_energy_error_line_of_a_run_failing_later():
    from lgvi_jax.cli import energy_error_line

    ok = {"result": 0, "energy_error_max": 1.5e-4, "energy_error_final": 1e-4}
    assert energy_error_line(ok) == "max 1.500e-04, final 1.000e-04"
    late = {"result": 1, "failed_step": 7, "energy_error_max": 2e-3,
            "energy_error_final": float("nan")}
    assert energy_error_line(late) == ("max 2.000e-03 before the failure (failed at step 7), "
                                       "final n/a")


def test_sweep_of_trajectories_failing_at_step_0_reads_n_a(tmp_path, capsys):
    out = tmp_path / "fail"
    code = main(["sweep", "car-pendulum", "--method", "lgvi", "--dt", "0.01", "--t-final",
                 "0.02", "--n", "2", "--set", "omega0=1e6,0,0", "--out", str(out)])
    stdout, stderr = capsys.readouterr()
    assert code == 0 and "2 trajectories failed" in stderr
    assert "| lgvi | 0.01 | 2/2 | n/a | n/a | n/a | n/a |" in stdout
    with open(out / "trajectories.csv") as fh:
        for row in csv.DictReader(fh):  # no misleading 0 for a trajectory never measured
            assert row["energy_error_max"] == "nan" and row["failed_step"] == "0"
