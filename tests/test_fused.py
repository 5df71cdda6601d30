"""The fused car-pendulum steps solve the general engine's discrete equations: the same
steps and trajectories, the same conservation, failures as values, and the engine choice."""

import csv
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import SHARED_ROLLOUT_STEPS

import lgvi_jax as lj
from lgvi_jax.cli import main
from lgvi_jax.integrators import fused
from lgvi_jax.sweep import initial_conditions, run_batch


@pytest.fixture(scope="module")
def car():
    model = lj.CarPendulum()
    return model, model.default_state()


def _max_diff(a, b):
    return max(float(jnp.max(jnp.abs(x - y))) for x, y in
               zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


def _rotation_angle(R0, R1):
    F = jnp.swapaxes(R0, -1, -2) @ R1
    return jnp.arccos(jnp.clip((jnp.trace(F, axis1=-2, axis2=-1) - 1) / 2, -1, 1))


@pytest.mark.parametrize("kind", list(fused.KINDS))
def test_one_step_equals_the_general_engine(car, kind):
    model, s0 = car
    states = initial_conditions(model, s0, 16, 0.3, seed=3)
    # The fused steps batched (one compilation for all step sizes); the general engine's
    # step one state at a time through final_state (one step; n and dt are run-time
    # values): the program tests/test_reference.py and tests/test_scalarize.py run for
    # the same model and method, compiled once for the suite.
    f = jax.jit(jax.vmap(lambda s, dt: fused.FusedCarPendulum(kind).step(model, s, dt),
                         in_axes=(0, None)))
    general = fused.KINDS[kind]()

    def g(states, dt):
        ends = [lj.final_state(model, general, jax.tree.map(lambda x, i=i: x[i], states),
                               dt, 1) for i in range(len(states.mu))]
        return (jax.tree.map(lambda *x: jnp.stack(x), *(e[0] for e in ends)),
                np.array([int(e[1]) for e in ends]))

    for dt in (5e-3, 0.05, 0.1):
        a, ia = f(states, dt)
        b, codes = g(states, dt)
        assert np.all(np.asarray(ia.result) == 0) and np.all(codes == 0)
        # Both solve to |Δξ_i| <= 1e-12 (1 + |ξ_i|) from different starts; the states agree
        # to that tolerance times the state's scale (measured 6e-13 at dt = 0.1).
        assert _max_diff(a, b) < 5e-12, dt
        assert np.all(np.asarray(ia.residual) < 1e-12)
        np.testing.assert_array_equal(a.p, states.p)  # the cart momentum is exact
    # dt = 0.1 reaches rotation angles beyond the series branch (θ > 0.1) of the exp maps.
    assert float(jnp.max(_rotation_angle(states.R, a.R))) > 0.1


# The one-step test covers every method; over a trajectory, lgvi (the exp-map path is
# covered over 4000 steps by the conservation test and the nested-vmap test).
@pytest.mark.parametrize("kind", ["lgvi"])
def test_trajectory_equals_the_general_engine(car, kind):
    model, s0 = car
    a, ca = lj.final_state(model, fused.FusedCarPendulum(kind), s0, 5e-3, 2000)
    b, cb = lj.final_state(model, fused.KINDS[kind](), s0, 5e-3, 2000)
    assert int(ca) == 0 and int(cb) == 0
    # Per-step differences ~1e-14 (the solver tolerance) accumulate over 2000 steps of a
    # chaotic-looking but regular motion: measured 9e-12.
    assert _max_diff(a, b) < 1e-10


def _run(model, method, s0, dt, n, every=1):
    """``(ok, states, invariants)``: the states after 0, every, 2 every, ..., n steps and
    their invariants, from a run of SHARED_ROLLOUT_STEPS steps (every state saved; one
    compiled rollout per method for this module: n_steps and save_every are compile-time
    constants, dt and the state are not); ``ok``: every step of that run succeeded."""
    traj = lj.simulate(model, method, s0, dt, SHARED_ROLLOUT_STEPS)
    states, invariants = jax.tree.map(lambda x: x[: n + 1 : every],
                                      (traj.state, traj.invariants))
    return bool(traj.ok), states, invariants


def test_conservation_over_a_long_run(car):
    """lgvi and hamel-exact (exactly variational, one Cayley and one exp method) conserve
    the vertical angular momentum to round-off (discrete Noether), keep the energy error
    bounded, and the cart momentum exact (4000 steps, every 50th state)."""
    model, s0 = car
    inv0 = model.invariants(s0)
    for kind in ("lgvi", "hamel-exact"):
        ok, states, invariants = _run(model, fused.FusedCarPendulum(kind), s0, 0.01, 4000,
                                      every=50)
        assert ok
        lz = invariants["angular_momentum_z"]
        # Round-off and the solver tolerance (FusedCarPendulum.tol): measured 2.2e-13 for
        # lgvi; with tol = 1e-12 it was 8.8e-12, which this bound catches.
        assert float(jnp.max(jnp.abs(lz - inv0["angular_momentum_z"]))) < 1e-12, kind
        np.testing.assert_array_equal(states.p[-1], s0.p)
        err = np.abs(np.asarray(invariants["energy"]) - float(inv0["energy"]))
        err /= abs(float(inv0["energy"]))
        # Second order at h = 0.01: O(1e-3) oscillations, no secular growth (the second half
        # of the run no worse than the first: the error is bounded, not drifting).
        half = len(err) // 2
        assert err.max() < 2e-2 and err[half:].max() < 1.5 * err[:half].max(), kind


def test_batch_equals_a_loop_and_failures_are_isolated(car):
    model, s0 = car
    method = fused.FusedCarPendulum("lgvi")
    states = initial_conditions(model, s0, 4, 0.05, seed=4)
    good = run_batch(model, method, states, 0.01, 100)
    for i in range(4):
        # The first 100 steps of a single run (the long-run test's compiled rollout).
        traj = lj.simulate(model, method, jax.tree.map(lambda x, i=i: x[i], states), 0.01,
                           SHARED_ROLLOUT_STEPS)
        newton_max = int(np.max(np.asarray(traj.newton_steps_max)[1:101]))
        assert int(good["newton_max"][i]) == newton_max
        e0 = model.invariants(jax.tree.map(lambda x, i=i: x[i], states))["energy"]
        err = jnp.abs(traj.invariants["energy"][:101] - e0) / jnp.abs(e0)
        # The batched code contracts differently (vector loops): round-off, ~1e-15 absolute.
        np.testing.assert_allclose(good["energy_error_max"][i], float(jnp.max(err)),
                                   rtol=1e-9, atol=1e-13)
    mu = states.mu.at[1, 0].set(jnp.nan).at[2].multiply(1e4)
    bad = run_batch(model, method, lj.RigidState(R=states.R, mu=mu, q=states.q, p=states.p),
                    0.01, 100)
    assert bad["result"][1] == lj.RESULTS.nonfinite and bad["failed_step"][1] == 0
    assert bad["result"][2] != 0 and bad["failed_step"][2] >= 0
    for i in (0, 3):
        for key in good:
            np.testing.assert_array_equal(bad[key][i], good[key][i], err_msg=key)


def test_large_steps_converge_like_the_general_engine(car):
    # h = 0.1 (20x the benchmark's step) with 30 % perturbations: the chord contracts
    # slowly. Handing over to Broyden only when an update fails to halve left 17 of these
    # 256 trajectories at the iteration cap (the general engine: none); at contraction 0.25
    # all converge, in fewer iterations.
    model, s0 = car
    states = initial_conditions(model, s0, 256, 0.3, seed=1)
    res = run_batch(model, fused.FusedCarPendulum("hamel-cayley"), states, 0.1, 200)
    assert int(np.sum(res["result"] != 0)) == 0
    assert float(np.mean(res["newton_mean"])) < 14


def test_very_large_steps_restart_broyden_where_the_chord_stalls(car):
    # h = 0.2 (40x the benchmark's step) with 30 % perturbations, 50 steps: the chord at
    # w = 0 stalls in most steps. Broyden continued from the chord's last iterate with its
    # matrix converged 4 of these 256 trajectories; restarted at the chord's first iterate
    # with the Jacobian there, all 256, as the general engine does (measured).
    model, s0 = car
    method = fused.FusedCarPendulum("hamel-exact")
    states = initial_conditions(model, s0, 256, 0.3, seed=1)
    res = run_batch(model, method, states, 0.2, 50)
    # At the edge of convergence another rounding (CPU, XLA version) may tip a trajectory
    # over: 256 of 256 converge in both the default and the --alt-numerics compilation
    # (measured); at most 2 failures are allowed, against 252 without the restart.
    assert int(np.sum(res["result"] != 0)) <= 2
    # One trajectory (the packed loop, its restart under a scalar cond) takes the same
    # steps as the batch (the batch-wide cond): three steps of the first four states.
    some = jax.tree.map(lambda x: x[:4], states)
    batch = jax.jit(jax.vmap(lambda s: lj.final_state(model, method, s, 0.2, 3)))(some)
    assert np.all(np.asarray(batch[1]) == 0)
    for i in range(4):
        # final_state itself (compiled, n and dt run-time values): one program with the
        # single-trajectory steps of the next test.
        state, code = lj.final_state(model, method, jax.tree.map(lambda x, i=i: x[i], some),
                                     0.2, 3)
        assert int(code) == 0
        # Both layouts iterate alike to the tolerance 1e-14 relative; they round
        # differently (vector loops, FMA) and can stop an iteration apart: measured ~1e-15.
        assert _max_diff(state, jax.tree.map(lambda x, i=i: x[i], batch[0])) < 1e-12


def test_single_and_batched_layouts_agree_under_nested_vmap(car):
    """One trajectory runs the packed loop, a batch the structure-of-arrays loop
    (``custom_vmap``); nested batches and batches over parameters (the model is a pytree)
    take the batched path with whatever is batched."""
    model, s0 = car
    method = fused.FusedCarPendulum("hamel-exact")
    states = initial_conditions(model, s0, 6, 0.1, seed=5)

    def step(m, s):
        return method.step(m, s, 0.02)[0]

    def single(m, s):  # one step of one trajectory: final_state's compiled program
        state, code = lj.final_state(m, method, s, 0.02, 1)
        assert int(code) == 0
        return state

    singles = [single(model, jax.tree.map(lambda x, i=i: x[i], states)) for i in range(6)]
    grid = jax.tree.map(lambda x: x.reshape(2, 3, *x.shape[1:]), states)
    nested = jax.jit(jax.vmap(jax.vmap(lambda s: method.step(model, s, 0.02)[0])))(grid)
    for i in range(6):
        one = jax.tree.map(lambda x, i=i: x[i // 3, i % 3], nested)
        # The two layouts round differently (vector loops, FMA): a few ulps.
        assert _max_diff(one, singles[i]) < 1e-14
    models = jax.tree.map(lambda *x: jnp.stack(x), lj.CarPendulum(m=0.5), lj.CarPendulum(m=2.0))
    over_params = jax.jit(jax.vmap(step, in_axes=(0, None)))(models, s0)
    for k, m in enumerate((0.5, 2.0)):
        ref = single(lj.CarPendulum(m=m), s0)
        assert _max_diff(jax.tree.map(lambda x, k=k: x[k], over_params), ref) < 1e-14


@pytest.mark.parametrize("kind", list(fused.KINDS))
def test_closed_form_chord_jacobian_equals_autodiff(car, kind):
    # The hand-linearised residual at w = 0 against forward-mode autodiff of the residual
    # itself, on 8 perturbed states (random rotations, non-zero cart momentum) and an
    # anisotropic, off-centre body, so that every term of the linearisation is non-zero.
    model, s0 = car
    model = lj.CarPendulum(J=jnp.array([[0.3, 0.02, -0.01], [0.02, 0.2, 0.03],
                                        [-0.01, 0.03, 0.25]]),
                           rho_c=jnp.array([0.1, -0.2, 0.5]))
    s0 = lj.RigidState(R=s0.R, mu=s0.mu, q=s0.q, p=jnp.array([0.7, -0.4]))
    states = initial_conditions(model, s0, 8, 0.5, seed=11)
    h = jnp.float64(0.02)
    R0 = tuple(tuple(states.R[:, i, j] for j in range(3)) for i in range(3))
    prm = {"m": model.m, "M": model.M, "rho": tuple(model.rho_c[i] for i in range(3)),
           "J": tuple(tuple(model.J[i, j] for j in range(3)) for i in range(3))}
    K = tuple(states.mu[:, i] for i in range(3))
    p = tuple(states.p[:, i] for i in range(2))
    assert float(jnp.min(jnp.abs(p[0]))) > 0.1

    def residual(w):
        return fused._equations(kind, prm, h, R0, K, p, w)[0]

    # w shared by the 8 trajectories (a scalar): each residual depends on it alone, so the
    # tangents are the 8 Jacobians.
    auto = jnp.stack(fused._jacobian(residual, tuple(jnp.zeros(()) for _ in range(3))), -1)
    closed = jnp.stack(fused._chord_jacobian(kind, prm, h, R0, p), -1)
    scale = float(jnp.max(jnp.abs(auto)))
    assert scale > 1.0
    np.testing.assert_allclose(np.asarray(closed), np.asarray(auto), rtol=0,
                               atol=1e-13 * scale)


SOLVERS = pytest.mark.parametrize("solver", [fused._solve, fused._solve_packed],
                                  ids=["soa", "packed"])


@SOLVERS
def test_solver_falls_back_to_broyden_when_the_chord_stalls(solver):
    # f = e^w − 2 componentwise: the chord from J(0) = I has the map's slope 1 − e^w = −1
    # at the root and oscillates; Broyden from the last iterate converges to log 2.
    w, its, status = solver(lambda w: tuple(jnp.exp(x) - 2.0 for x in w), 1.0, 1e-12, 40,
                            jnp.float64)
    assert int(status) == fused._CONVERGED
    np.testing.assert_allclose(np.asarray(w), np.log(2.0), rtol=1e-14)
    assert 2 < int(its) < 40


@SOLVERS
def test_solver_reports_failures(solver):
    _, _, status = solver(lambda w: tuple(jnp.sqrt(x - 5.0) for x in w), 1.0, 1e-12, 40,
                          jnp.float64)
    assert int(status) == fused._NONFINITE
    # No real root: the iteration wanders until the cap.
    _, its, status = solver(lambda w: tuple(x * x + 2.0 * x + 2.0 for x in w), 1.0, 1e-12,
                            40, jnp.float64)
    assert int(status) != fused._CONVERGED and int(its) <= 40


def test_step_reports_a_failed_solve_as_a_code(car):
    model, s0 = car
    state = lj.RigidState(R=s0.R, mu=s0.mu * 1e4, q=s0.q, p=s0.p)
    _, info = fused.FusedCarPendulum("lgvi", max_steps=3).step(model, state, 0.01)
    assert int(info.result) == lj.RESULTS.max_steps_reached and int(info.newton_steps) == 3
    with pytest.raises(lj.IntegrationError, match="step"):
        lj.simulate(model, fused.FusedCarPendulum("lgvi", max_steps=3), state, 0.01,
                    5).raise_if_failed()


def test_bad_arguments_and_models():
    with pytest.raises(ValueError, match="method must be one of"):
        fused.FusedCarPendulum("rk4")
    with pytest.raises(ValueError, match="max_steps"):
        fused.FusedCarPendulum("lgvi", max_steps=0)
    with pytest.raises(ValueError, match="model must be a CarPendulum"):
        fused.FusedCarPendulum("lgvi").check_model(lj.FreeRigidBody())


def test_engine_choice(car):
    model, _ = car
    assert isinstance(fused.fused_method("hamel", model), fused.FusedCarPendulum)
    assert fused.fused_method("hamel", model, "general") is None
    assert fused.fused_method("lgvi", model, chord="mass") is None  # --chord: general
    assert fused.fused_method("lgvi@4", model) is None  # compositions: general
    assert fused.fused_method("lgvi", lj.FreeRigidBody()) is None
    with pytest.raises(ValueError, match="--engine fused: only"):
        fused.fused_method("rk4", model, "fused")
    with pytest.raises(ValueError, match="--engine must be one of"):
        fused.fused_method("lgvi", model, "fast")


def test_sweep_engines_give_the_same_results(tmp_path, capsys):
    rows = {}
    for engine in ("general", "fused"):
        out = tmp_path / engine
        argv = ["sweep", "car-pendulum", "--method", "lgvi", "--dt", "0.01",
                "--t-final", "1", "--n", "4", "--out", str(out), "--json",
                "--engine", engine]
        assert main(argv) == 0
        capsys.readouterr()
        rows[engine] = list(csv.DictReader(open(out / "trajectories.csv")))
        config = json.loads((out / "manifest.json").read_text())["config"]
        assert config.get("engine", "general") == engine
    for a, b in zip(rows["general"], rows["fused"], strict=True):
        assert (a["method"], a["index"]) == (b["method"], b["index"])
        assert int(a["result"]) == 0 and int(b["result"]) == 0
        # Round-off of two solvers of the same equations (measured ~1e-13 absolute).
        assert abs(float(a["energy_error_max"]) - float(b["energy_error_max"])) <= 1e-11
    code = main(["sweep", "oscillator", "--method", "verlet", "--dt", "0.1", "--t-final",
                 "1", "--n", "2", "--engine", "fused", "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert code == 2 and "--engine fused: only" in err and "Traceback" not in err
