"""Batched sweeps: batch = loop of single runs, sharding, failure isolation, resume after a
kill, initial conditions, and clear errors for bad arguments."""

import csv
import json
import os
import signal
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lgvi_jax as lj
from lgvi_jax import so3
from lgvi_jax.cli import main
from lgvi_jax.diagnostics import rk4_energy_factor, summarize
from lgvi_jax.sweep import (
    KILL_HOOK_ENV,
    SweepConfig,
    SweepError,
    engine_name,
    initial_conditions,
    run_batch,
    run_sweep,
    sweep_method,
)
from lgvi_jax.systems import get_system

DT = 5e-3
N_STEPS = 200


@pytest.fixture(scope="module")
def car():
    model = lj.CarPendulum()
    return model, model.default_state()


@eqx.filter_jit
def velocities(model, s):
    return model.velocities(s.R, s.mu, s.q, s.p)


def _take(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


def test_sweep_method_builds_what_each_engine_names():
    """``sweep_method`` (what ``lgvi-jax sweep`` runs, also timed by ``lgvi-jax bench``)
    and ``engine_name``: the autodiff engine on scalars for every system and method,
    compositions included; ``--chord mass`` (which the scalar engine does not take) and
    ``scalar=False`` stay on arrays."""
    cases = [("car-pendulum", "lgvi", "exact", True, "scalar"),
             ("car-pendulum", "hamel-exact", "exact", True, "scalar"),
             ("car-pendulum", "lgvi", "exact", False, "general"),
             ("car-pendulum", "lgvi", "mass", True, "general"),
             ("car-pendulum", "lgvi@6", "exact", True, "scalar"),
             ("heavy-top", "hamel", "exact", True, "scalar"),
             ("heavy-top", "lgvi@4", "exact", False, "general"),
             # the Galerkin VIs solve on arrays (their scalar program compiles for minutes)
             ("car-pendulum", "galerkin4", "exact", True, "general")]
    for system, name, chord, scalar, expected in cases:
        method = sweep_method(system, name, chord, scalar=scalar)
        assert engine_name(method) == expected, (system, name, chord, scalar)
        assert method.name.partition("@")[0] == name.partition("@")[0]
    assert sweep_method("car-pendulum", "lgvi@6").gammas == lj.compose(
        lj.LGVI(), order=6).gammas


def test_initial_conditions_reproducible_and_sized(car):
    model, s0 = car
    eps = 0.03
    batch = initial_conditions(model, s0, 6, eps, seed=7)
    # Independent of chunking: condition i depends on (seed, i) only.
    tail = initial_conditions(model, s0, 3, eps, seed=7, start=3)
    for a, b in zip(jax.tree.leaves(_take(batch, slice(3, 6))), jax.tree.leaves(tail),
                    strict=True):
        np.testing.assert_array_equal(a, b)
    other = initial_conditions(model, s0, 6, eps, seed=8)
    assert not np.allclose(batch.mu, other.mu)
    # Rotation by exactly eps, R stays in SO(3); velocities moved by O(eps) relative.
    angles = jax.jit(jax.vmap(so3.rotation_angle))(jnp.einsum("ji,bjk->bik", s0.R, batch.R))
    np.testing.assert_allclose(angles, eps, rtol=1e-9)
    assert float(jnp.max(so3.orthogonality_error(batch.R))) < 1e-14
    w0, v0 = velocities(model, s0)
    w, v = jax.vmap(velocities, in_axes=(None, 0))(model, batch)
    rel = np.linalg.norm(w - w0, axis=1) / np.linalg.norm(w0)
    assert 0 < rel.max() < 5 * eps and rel.mean() > 0.2 * eps
    rel_v = np.linalg.norm(v - v0, axis=1) / np.linalg.norm(v0)
    assert 0 < rel_v.max() < 5 * eps
    np.testing.assert_array_equal(batch.q, np.broadcast_to(s0.q, (6, 2)))
    # eps = 0 gives the central state itself.
    same = initial_conditions(model, s0, 2, 0.0, seed=1)
    np.testing.assert_allclose(same.mu, np.broadcast_to(s0.mu, (2, 3)), atol=1e-14)


def test_large_batches_run_in_blocks_with_the_same_results(car, monkeypatch):
    """A device's share larger than ``sweep.batch.BLOCK`` runs as equal vectorised blocks in
    sequence (the last one padded): the same per-trajectory results as one vmap, in the
    original order, padding dropped."""
    from lgvi_jax import sweep

    model, s0 = car
    # 4 trajectories on one device: the one-vmap program is the single-device run of the
    # test below (the batch's shape, not dt or the steps, makes the program).
    states = initial_conditions(model, s0, 4, 0.05, seed=3)
    one_vmap = run_batch(model, lj.LGVI(), states, DT, N_STEPS, devices=jax.devices()[:1])
    monkeypatch.setattr(sweep.batch, "BLOCK", 3)  # 4 -> 2 blocks of 3, two padded entries
    blocks = run_batch(model, lj.LGVI(), states, DT, N_STEPS, devices=jax.devices()[:1])
    assert set(blocks) == set(one_vmap)
    for key in one_vmap:
        assert blocks[key].shape == (4,), key
        # The same equations on the same inputs, but vector code for another block size
        # may round differently (SIMD body against remainder loop): measured equal on one
        # machine, up to 3e-14 apart on another (AVX2) after 200 steps, in the energy error,
        # a difference of O(1) energies. So round-off-level quantities (the drifts, ~1e-14)
        # agree only absolutely, to a few hundred ulps of O(1).
        np.testing.assert_allclose(blocks[key], one_vmap[key], rtol=1e-12, atol=2e-13,
                                   err_msg=key)
    # The trajectories really differ, so a permutation or a repeated block would show.
    assert len(np.unique(np.round(one_vmap["energy_error_max"], 15))) == 4


def test_a_batch_traces_no_unrolled_jacobian(car, monkeypatch):
    """A batch's solves compute their chord matrix in a loop over the unit vectors
    (``Newton(jacobian_loop="batched")``), and so does the unbatched form of each solve that
    JAX traces before batching it (``newton.batched_trace``): tracing a batched rollout, in
    one block or several, builds no unrolled Jacobian program, which would only lengthen
    the trace. One trajectory builds it."""
    from lgvi_jax import newton, sweep

    built = []
    real = newton._scalar_jacobian

    def counting(*args, **kwargs):
        built.append(args[0])
        return real(*args, **kwargs)

    monkeypatch.setattr(newton, "_scalar_jacobian", counting)
    monkeypatch.setattr(sweep.batch, "SCALAR_BLOCK", 4)  # a runner of its own: traced here
    newton.clear_scalar_programs()
    model, s0 = car
    method = sweep.sweep_method("car-pendulum", "hamel")
    states = initial_conditions(model, s0, 7, 0.05, seed=5)
    for n in (3, 7):  # one block of 3; two blocks of 4 (one padded entry)
        fn, args = sweep.batch.batch_arguments(model, method, _take(states, slice(0, n)), DT,
                                               3, devices=jax.devices()[:1])
        fn.trace(*args)
        assert built == [], n
    fn, args = sweep.batch.batch_arguments(model, method, _take(states, slice(0, 1)), DT, 3,
                                           devices=jax.devices()[:1])
    fn.trace(*args)
    assert built


def _conds_in_loops(jaxpr, in_loop=False) -> int:
    """The ``cond`` equations inside ``while`` loops of ``jaxpr``, its sub-jaxprs included."""
    from jax._src import core

    count = 0
    for eqn in jaxpr.eqns:
        count += in_loop and eqn.primitive.name == "cond"
        for sub in core.jaxprs_in_params(eqn.params):
            count += _conds_in_loops(sub, in_loop or eqn.primitive.name == "while")
    return count


def test_a_batch_samples_its_metrics_in_a_branch(car, monkeypatch):
    """In a batch the members share the step index (the loop's body is ``vmap``-ed inside
    the loop, ``rollout.advance``'s ``batch_axes``), so the metrics' ``cond`` on it stays a
    branch, taken every K-th step (``--sample-every``), not a selection that computes the
    metrics at every step: the metrics' program has one more ``cond`` in its loops than the
    final state's, in one block and in several."""
    from lgvi_jax import sweep

    monkeypatch.setattr(sweep.batch, "SCALAR_BLOCK", 4)  # a runner of its own: traced here
    model, s0 = car
    method = sweep.sweep_method("car-pendulum", "hamel")
    states = initial_conditions(model, s0, 7, 0.05, seed=5)
    for n in (3, 7):  # one block of 3; two blocks of 4
        conds = {}
        for kind in ("metrics", "final"):
            fn, args = sweep.batch.batch_arguments(
                model, method, _take(states, slice(0, n)), DT, 3, devices=jax.devices()[:1],
                kind=kind)
            conds[kind] = _conds_in_loops(fn.trace(*args).jaxpr.jaxpr)
        assert conds["metrics"] == conds["final"] + 1, (n, conds)


def test_accelerators_run_the_whole_share_as_one_block():
    """On a CPU a device's share runs in cache-sized blocks; on an accelerator the block is
    the whole share (a sequence of blocks would serialise a GPU: measured on an H200, the
    car-pendulum batch of 524288 at 2.2e8 steps/s as one block)."""
    from types import SimpleNamespace

    from lgvi_jax import sweep

    cpu, gpu = (SimpleNamespace(platform=p) for p in ("cpu", "gpu"))
    scalar = sweep.sweep_method("car-pendulum", "hamel")
    arrays = sweep.sweep_method("car-pendulum", "hamel", scalar=False)
    assert sweep.batch._block(scalar, (cpu,), 4096) == sweep.batch.SCALAR_BLOCK
    assert sweep.batch._block(arrays, (cpu, cpu), 4096) == sweep.batch.BLOCK
    assert sweep.batch._block(scalar, (gpu,), 524288) == 524288
    assert sweep.batch._block(arrays, (gpu, gpu), 1001) == 501  # the share of each device


@pytest.mark.parametrize("name", ["lgvi"])
def test_batch_equals_loop_of_single_runs(car, name):
    """The vmapped batch split over the devices reproduces each single-trajectory run."""
    model, s0 = car
    method = lj.RIGID_METHODS[name]()
    states = initial_conditions(model, s0, 4, 0.05, seed=2)
    sharded = run_batch(model, method, states, DT, N_STEPS)
    assert len(jax.devices()) == 2  # tests/conftest.py: the batch is split over 2 devices
    single_device = run_batch(model, method, states, DT, N_STEPS, devices=jax.devices()[:1])
    for key in sharded:
        # Round-off: 2 trajectories per device vs 4 on one device run through different
        # vector code paths, so the states differ by round-off accumulated over the run
        # (energy errors differ by up to 1.4e-13 measured); the drifts are themselves
        # round-off (~1e-14).
        np.testing.assert_allclose(sharded[key], single_device[key], rtol=1e-9, atol=1e-12,
                                   err_msg=key)
    for i in range(4):
        traj = lj.simulate(model, method, _take(states, i), DT, N_STEPS)
        ref = summarize(traj)
        assert sharded["result"][i] == 0
        assert sharded["newton_max"][i] == int(traj.newton_max)
        np.testing.assert_allclose(sharded["newton_mean"][i], float(traj.newton_mean),
                                   rtol=1e-15)
        # Round-off: the batched code may contract differently (FMA, vector loops), and
        # computes the chord matrix in a loop (another order of sums, other iterates
        # within the solver's tolerance, 1e-12 relative to O(1) unknowns). Each
        # metric is a difference of O(1) quantities, so its round-off is absolute (~1e-15);
        # its growth over 200 steps, if every step added in the same direction, ~2e-13
        # (measured up to 6.4e-14, 1.1e-13 with --alt-numerics): 2e-12.
        for key in ("energy_error_max", "energy_error_final", "momentum_drift_max",
                    "angular_momentum_z_drift_max", "orthogonality_error_max"):
            np.testing.assert_allclose(sharded[key][i], ref[key], rtol=1e-9, atol=2e-12,
                                       err_msg=key)


def test_cpu_devices_run_the_one_device_program_once_per_share(car, monkeypatch):
    """On several CPU devices a batch is the one-device program run once per device's
    share, the shares concurrently (``sweep.batch._Shares``: no SPMD partitioning to
    compile). Each share's metrics equal that program run on the share alone, bit for bit,
    through the call, the compiled form and ``run_batch``; inside a transformation the
    runner is the one-device program on the whole batch; a share's error reaches the
    caller."""
    from lgvi_jax import sweep

    model, s0 = car
    method = sweep.sweep_method("car-pendulum", "hamel")
    states = initial_conditions(model, s0, 6, 0.05, seed=7)
    fn, args = sweep.batch_arguments(model, method, states, DT, 40)
    assert isinstance(fn, sweep.batch._Shares) and fn.n == 2
    one, _ = sweep.batch.batch_arguments(model, method, states, DT, 40,
                                         devices=jax.devices()[:1])
    assert fn.program is one  # the same jitted program
    alone = [one(*part) for part in fn.shares(args)]  # 3 states each, one after the other
    want = {k: np.concatenate([np.asarray(a[k]) for a in alone]) for k in alone[0]}
    compiled = fn.lower(*args).compile()
    for got in (fn(*args), compiled(args[0], *args[2:]),
                run_batch(model, method, states, DT, 40)):
        assert set(got) == set(want)
        for k in want:
            np.testing.assert_array_equal(got[k], want[k], err_msg=k)
    assert (want["result"] == 0).all() and len(np.unique(want["energy_error_max"])) == 6
    traced = jax.jit(lambda p, st: fn(p, args[1], st, *args[3:]))(args[0], args[2])
    # Round-off only: 6 states in one block against two blocks of 3 (other vector code
    # paths), as in test_batch_equals_loop_of_single_runs.
    np.testing.assert_allclose(np.asarray(traced["energy_error_max"]),
                               want["energy_error_max"], rtol=1e-9, atol=1e-12)

    # Beyond MAX_SHARES devices (and on accelerators) the batch is sharded with shard_map:
    # the same metrics up to round-off (another compilation).
    monkeypatch.setattr(sweep.batch, "MAX_SHARES", 1)
    monkeypatch.setattr(sweep.batch, "_RUNNERS", {})
    sharded, sharded_args = sweep.batch_arguments(model, method, states, DT, 40)
    assert not isinstance(sharded, sweep.batch._Shares)
    out = sharded(*sharded_args)
    for k in ("energy_error_max", "orthogonality_error_max", "momentum_drift_max"):
        np.testing.assert_allclose(np.asarray(out[k]), want[k], rtol=1e-9, atol=1e-12,
                                   err_msg=k)

    def broken(params, static, states, *rest):  # the second share only (a thread's)
        if float(np.asarray(states.q)[0, 0]) == float(np.asarray(args[2].q)[3, 0]):
            raise RuntimeError("share failed")
        return {"x": np.zeros(3)}

    with pytest.raises(RuntimeError, match="share failed"):
        fn.run(broken, fn.shares(args))


def test_failed_trajectory_is_flagged_and_isolated(car):
    model, s0 = car
    method = lj.LGVI()
    states = initial_conditions(model, s0, 4, 0.05, seed=4)
    good = run_batch(model, method, states, DT, N_STEPS)
    # Trajectory 1 starts with a NaN; trajectory 2 spins far too fast for Newton at dt.
    mu = states.mu.at[1, 0].set(jnp.nan).at[2].multiply(1e4)
    bad_states = lj.RigidState(R=states.R, mu=mu, q=states.q, p=states.p)
    res = run_batch(model, method, bad_states, DT, N_STEPS)
    assert res["result"][1] == lj.RESULTS.nonfinite and res["failed_step"][1] == 0
    assert res["result"][2] != 0 and res["failed_step"][2] >= 0
    assert np.isnan(res["energy_error_final"][1]) and np.isnan(res["energy_error_final"][2])
    for i in (0, 3):
        assert res["result"][i] == 0 and res["failed_step"][i] == -1
        for key in good:
            np.testing.assert_array_equal(res[key][i], good[key][i], err_msg=key)


def test_sweep_api_outputs_and_summary(tmp_path):
    spec = get_system("oscillator")
    model, s0 = spec.build({})
    config = SweepConfig(system="oscillator", methods=("verlet", "rk4"), dts=(0.1, 0.05),
                         t_final=10.0, n=5, perturb=0.1, seed=0, chunk=2, sample_every=3)
    summary = run_sweep(config, model, s0, spec.method, tmp_path, progress=False)
    assert summary["chunks_computed"] == 2 * 2 * 3 and summary["chunks_skipped"] == 0
    for name in ("manifest.json", "trajectories.csv", "summary.json", "summary.md",
                 "energy_error.png"):
        assert (tmp_path / name).exists(), name
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert manifest["format"] == "lgvi-jax-sweep" and manifest["config"]["n"] == 5
    rows = list(csv.DictReader(open(tmp_path / "trajectories.csv")))
    assert len(rows) == 2 * 2 * 5
    # Störmer–Verlet on the oscillator: energy error <= (h ω)^2/8-ish relative, bounded;
    # compare with the closed-form bound of the modified energy: |ΔH|/H <= h^2/4 (ω = 1).
    for row in rows:
        if row["method"] == "verlet":
            assert float(row["energy_error_max"]) <= float(row["dt"]) ** 2 / 4 + 1e-15
        else:
            # RK4 on the oscillator multiplies the energy by a known factor per step, the
            # same for every initial condition (closed form, diagnostics.rk4_energy_factor).
            dt = float(row["dt"])
            exact = abs(rk4_energy_factor(dt, round(10.0 / dt)) - 1.0)
            # atol: the energy's own round-off (a few ulps of ~0.5 per step, over 200
            # steps if all in one direction: ~2e-13; measured up to 1.2e-14).
            np.testing.assert_allclose(float(row["energy_error_final"]), exact, rtol=1e-8,
                                       atol=1e-12)


def _sweep_args(out, extra=()):
    return [sys.executable, "-m", "lgvi_jax.cli", "sweep", "car-pendulum", "--method", "lgvi",
            "--dt", "0.005", "--t-final", "10", "--n", "24", "--chunk", "2", "--seed", "5",
            "--perturb", "0.02", "--devices", "1", "--out", str(out), "--json", *extra]


def _csv_rows(path):
    return sorted(csv.reader(open(path)))


#: Each child sweep takes ~10-30 s on a loaded 2-core machine; a hung child fails the test
#: after this long instead of blocking the suite.
CHILD_TIMEOUT_S = 300


def _run(args, **kwargs):
    return subprocess.run(args, capture_output=True, text=True, timeout=CHILD_TIMEOUT_S,
                          **kwargs)


def _refused_in_process(args, capsys):
    """The child's command line run in this process (``main``) where it is refused before
    any work: the exit status and stderr. Without ``--devices 1``, which this process,
    whose JAX already runs, would refuse first (the folder checks do not depend on it)."""
    argv = args[3:]  # after "python -m lgvi_jax.cli"
    i = argv.index("--devices")
    del argv[i : i + 2]
    capsys.readouterr()
    code = main(argv)
    return code, capsys.readouterr().err


def test_resume_after_kill_matches_uninterrupted_run(tmp_path, capsys):
    killed, clean = tmp_path / "killed", tmp_path / "clean"
    chunks = killed / "chunks"
    # The child kills itself with SIGKILL (no chance to clean up) right after writing its
    # 5th chunk: a deterministic interruption mid-sweep, no polling race.
    env = {**os.environ, KILL_HOOK_ENV: "4"}
    child = _run(_sweep_args(killed), env=env)
    assert child.returncode == -signal.SIGKILL, child.stderr
    before = {p.name: p.stat().st_mtime_ns for p in chunks.glob("*.npz")}
    assert len(before) == 5, sorted(before)
    assert not (killed / "trajectories.csv").exists()

    # Without --resume the folder is refused; with it, finished chunks are kept as they are.
    # (The refusals run in this process: a child each cost ~3 s of importing JAX.)
    code, err = _refused_in_process(_sweep_args(killed), capsys)
    assert code == 2 and "--resume" in err
    resumed = _run(_sweep_args(killed, ["--resume"]))
    assert resumed.returncode == 0, resumed.stderr
    summary = json.loads(resumed.stdout)
    assert summary["chunks_skipped"] == len(before)
    assert summary["chunks_computed"] == 12 - len(before)
    for name, mtime in before.items():
        assert (chunks / name).stat().st_mtime_ns == mtime, f"{name} was recomputed"

    full = _run(_sweep_args(clean))
    assert full.returncode == 0, full.stderr
    assert _csv_rows(killed / "trajectories.csv") == _csv_rows(clean / "trajectories.csv")

    # A resume with other arguments is refused, naming what differs.
    code, err = _refused_in_process(_sweep_args(killed, ["--resume", "--seed", "6"]), capsys)
    assert code == 2 and "seed" in err


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--method", ","], "--method: give at least one method"),
        (["--method", "lgvi,nope"], "--method 'nope' is not available"),
        (["--n", "0"], "--n must be an integer >= 1"),
        (["--n", "-3"], "--n must be an integer >= 1"),
        (["--perturb", "-0.1"], "--perturb must be a finite number >= 0"),
        (["--dt", "0.003"], "must be a positive multiple of every --dt"),
        (["--dt", ""], "--dt: give at least one step"),
        (["--chunk", "0"], "--chunk must be an integer >= 1"),
        (["--devices", "x"], "--devices must be 'auto' or an integer"),
    ],
)
def test_bad_arguments_exit_2_with_a_clear_message(tmp_path, capsys, args, message):
    base = {"--method": "lgvi", "--dt": "0.01", "--t-final": "1", "--n": "4",
            "--out": str(tmp_path / "out")}
    extra = dict(zip(args[::2], args[1::2], strict=True))
    argv = ["sweep", "car-pendulum"]
    for k, v in {**base, **extra}.items():
        argv += [k, v]
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "out" / "chunks").exists() or message.startswith("--devices")


def test_unwritable_out_dir_is_refused(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    code = main(["sweep", "oscillator", "--method", "verlet", "--dt", "0.1", "--t-final", "1",
                 "--n", "2", "--out", str(blocker / "sub")])
    err = capsys.readouterr().err
    assert code == 2 and "cannot create folder" in err and "Traceback" not in err
    with pytest.raises(SweepError, match="cannot create folder"):
        spec = get_system("oscillator")
        model, s0 = spec.build({})
        run_sweep(SweepConfig("oscillator", ("verlet",), (0.1,), 1.0, 2, 0.0, 0), model, s0,
                  spec.method, blocker / "sub", progress=False)


def test_a_sweep_started_with_engine_in_its_manifest_resumes(tmp_path, capsys):
    """Manifests written before the hand-reduced steps were retired may hold ``engine``
    (``--engine auto``): a choice between solvers of the same equations, not part of the
    configuration any more, so ``--resume`` continues such a sweep instead of refusing it;
    another difference is still refused."""
    out = tmp_path / "old"
    argv = ["sweep", "oscillator", "--method", "verlet", "--dt", "0.1", "--t-final", "1",
            "--n", "4", "--chunk", "2", "--out", str(out), "--json"]
    assert main(argv) == 0
    manifest = out / "manifest.json"
    data = json.loads(manifest.read_text())
    data["config"]["engine"] = "auto"
    manifest.write_text(json.dumps(data))
    capsys.readouterr()
    assert main([*argv, "--resume"]) == 0
    assert "engine" not in json.loads(manifest.read_text())["config"]
    data = json.loads(manifest.read_text())
    data["config"]["seed"] = 5
    manifest.write_text(json.dumps(data))
    capsys.readouterr()
    assert main([*argv, "--resume"]) == 2
    assert "differs in: seed" in capsys.readouterr().err


def test_mass_chord_sweep_gives_the_same_results(tmp_path, capsys):
    """``--chord mass`` solves the same discrete equations: per trajectory the same energy
    errors and momentum drifts as the default chord, recorded in the manifest (the default
    is not, so that manifests of earlier sweeps stay resumable). On ``lgvi@4``, whose
    sub-steps take the chord of its base (the base methods' mass chord itself, state by
    state over 2000 steps: tests/test_lie.py)."""
    outs = {}
    for chord in ("exact", "mass"):
        out = tmp_path / chord
        argv = ["sweep", "car-pendulum", "--method", "lgvi@4", "--dt", "0.01",
                "--t-final", "2", "--n", "4", "--out", str(out), "--json",
                "--chord", chord]
        assert main(argv) == 0
        capsys.readouterr()
        outs[chord] = list(csv.DictReader(open(out / "trajectories.csv")))
        config = json.loads((out / "manifest.json").read_text())["config"]
        assert config.get("chord", "exact") == chord and ("chord" in config) == (chord != "exact")
    for a, b in zip(outs["exact"], outs["mass"], strict=True):
        assert a["method"] == b["method"] and a["index"] == b["index"]
        # The two solves differ at round-off: relative energy errors (1e-6 for lgvi@4)
        # agree to ~1e-13 absolute (measured 2e-13); 1e-11 leaves room.
        assert abs(float(a["energy_error_max"]) - float(b["energy_error_max"])) <= 1e-11
        assert int(b["result"]) == 0
        assert float(b["newton_mean"]) > float(a["newton_mean"])  # more, cheaper iterations


class _SortedInvariants(lj.HeavyTop):
    """A model (defined here) whose invariants use an operation the scalariser does not
    support (``sort``): the sweep's diagnostics fall back to the array form."""

    def invariants(self, state):
        inv = dict(super().invariants(state))
        inv["sorted_momenta"] = jnp.sort(state.mu)
        return inv


@pytest.mark.parametrize("make", [lj.CarPendulum, lj.HeavyTop, lj.FreeRigidBody,
                                  _SortedInvariants],
                         ids=["car-pendulum", "heavy-top", "free-rigid-body", "fallback"])
def test_diagnostics_on_scalars_equal_the_array_form(make):
    """The sweep's per-step diagnostics (the model's invariants and the orthogonality
    error) run as a scalar program (``scalarize.on_scalars``); they equal the array form
    (model.invariants, so3.orthogonality_error) on perturbed states, one and vmapped.
    Bound: energies and momenta of order 10 from sums of <= ~50 products, through the
    inverse Legendre map (mass-matrix condition <= ~1e2): 50 * eps * 10 * 1e2 ~ 1e-11,
    taken as 1e-10."""
    from lgvi_jax.scalarize import on_scalars
    from lgvi_jax.sweep.batch import _diagnostics

    model = make()
    states = initial_conditions(model, model.default_state(), 4, 0.3, 2)
    one = _take(states, 1)
    # the scalar program, except where the model's invariants cannot be scalarised
    assert ((on_scalars(_diagnostics, model, one) is _diagnostics)
            == (make is _SortedInvariants))

    @jax.jit
    def both(model, state):
        return on_scalars(_diagnostics, model, state)(model, state), _diagnostics(model, state)

    got, want = both(model, one)
    assert set(got) == set(want) and "orthogonality_error" in got
    for k in want:
        np.testing.assert_allclose(got[k], want[k], rtol=0, atol=1e-10, err_msg=k)
    got_b, want_b = jax.jit(jax.vmap(lambda s: both(model, s)))(states)
    for k in want:
        np.testing.assert_allclose(got_b[k], want_b[k], rtol=0, atol=1e-10, err_msg=k)


def _violin_payload():
    rng = np.random.default_rng(0)
    return {"data": [rng.normal(-3.0, 0.1, 200), np.array([np.nan])],
            "labels": ["hamel\ndt=0.005", "lgvi\ndt=0.01\n3 failed"], "colors": ["C1", "C0"],
            "ylabel": r"$\log_{10}$ max $|H - H_0|/|H_0|$", "title": "t\n(u)",
            "width": 6.0, "height": 4.2}


def test_plot_helper_draws_the_same_png_as_the_process():
    """The helper process (started early by the command line) returns the bytes the
    in-process drawing makes; asking again (no helper left) draws in process."""
    from lgvi_jax import _plot_worker

    payload = _violin_payload()
    here = _plot_worker.violin_png(payload)
    assert here.startswith(b"\x89PNG")
    _plot_worker.start()
    helper = _plot_worker._helper
    assert helper is not None
    assert _plot_worker.render(payload) == here
    assert helper.wait(timeout=30) == 0
    assert _plot_worker._helper is None and _plot_worker.render(payload) == here


def test_plot_helper_failure_falls_back_to_the_process():
    """A helper that died (or never answers) costs nothing but its head start: the plot is
    drawn in process; an unused helper exits when its input closes."""
    from lgvi_jax import _plot_worker

    payload = _violin_payload()
    _plot_worker.start()
    dead = _plot_worker._helper
    dead.kill()
    dead.wait(timeout=30)
    assert _plot_worker.render(payload) == _plot_worker.violin_png(payload)
    _plot_worker.start()
    unused, _plot_worker._helper = _plot_worker._helper, None
    unused.stdin.close()
    assert unused.wait(timeout=60) == 0
