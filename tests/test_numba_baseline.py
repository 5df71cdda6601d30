"""The Numba baseline of the benchmark solves the same discrete equations as our ``lgvi``."""

import numpy as np
import pytest

import lgvi_jax as lj

pytest.importorskip("numba")
from lgvi_jax.experiments import numba_lgvi as nb


@pytest.mark.parametrize("moving", [False, True])
def test_numba_lgvi_matches_the_engine(moving):
    R0 = np.asarray(lj.so3.exp(np.array([0.3, -0.2, 1.0])))
    model = lj.CarPendulum() if not moving else lj.CarPendulum(
        v0=(1.5, -0.7), omega0=(1.0, -0.5, 3.0), R0=R0)
    s0 = model.default_state()
    params = nb.params_from_model(model)
    R, mu, q, p = (np.asarray(x) for x in (s0.R, s0.mu, s0.q, s0.p))
    R1, mu1, q1, p1, its, code = nb.rollout("lgvi", R, mu, q, p, 5e-3, 200, params)
    traj = lj.simulate(model, lj.LGVI(), s0, 5e-3, 200)
    assert code == 0 and traj.ok
    # Both solve to |Δξ| <= 1e-12 (1 + |ξ|) per step, from different initial guesses, so
    # the end states agree to the accumulated solver tolerance, not to the last bit.
    for ours, theirs in zip((traj.state.R, traj.state.mu, traj.state.q, traj.state.p),
                            (R1, mu1, q1, p1), strict=True):
        np.testing.assert_allclose(theirs, np.asarray(ours)[-1], atol=1e-11)
    # The engine's solver: chord iterations (one Jacobian per step), ~4 per step.
    assert 2.0 <= its / 200 <= 5.0
    # The batch runs the same compiled loop: the same iterates, bit for bit.
    batch = [np.stack([x, x]) for x in (R, mu, q, p)]
    *theirs, its_b, codes = nb.rollout_batch("lgvi", *batch, 5e-3, 200, params)
    assert np.all(codes == 0) and np.all(its_b == its)
    for a, b in zip((R1, mu1, q1, p1), theirs, strict=True):
        np.testing.assert_array_equal(b, np.stack([a, a]))
    # A large step (θ = h|ξ| ≈ 0.2; the engine's compiled rollout is reused: dt is not
    # static): agreement to the accumulated solver tolerance.
    traj = lj.simulate(model, lj.LGVI(), s0, 0.04, 200)
    *theirs, its, code = nb.rollout("lgvi", R, mu, q, p, 0.04, 200, params)
    assert traj.ok and code == 0
    for a, b in zip((traj.state.R, traj.state.mu, traj.state.q, traj.state.p), theirs,
                    strict=True):
        np.testing.assert_allclose(b, np.asarray(a)[-1], rtol=0, atol=2e-10)
    # Failure is reported, not hidden: a non-finite state, and a step far too large for
    # Newton.
    *_, code = nb.rollout("lgvi", R, mu * np.nan, q, p, 5e-3, 5, params)
    assert code == 2
    *_, code = nb.rollout("lgvi", R, mu * 1e4, q, p, 5e-3, 5, params)
    assert code != 0


def test_every_vi_of_the_benchmark_has_a_baseline():
    assert nb.METHODS == ("lgvi", "hamel", "hamel-cayley", "hamel-exact")
    with pytest.raises(ValueError, match="method must be one of"):
        nb.rollout("rk4", np.eye(3), np.zeros(3), np.zeros(2), np.zeros(2), 5e-3, 1,
                   nb.params_from_model(lj.CarPendulum()))


@pytest.mark.parametrize("name", ["hamel", "hamel-cayley", "hamel-exact"])
def test_numba_hamel_matches_the_engine(name):
    from lgvi_jax.reference import moving_scene

    # The paper's state and a moving cart (generic attitude, cart momentum); both scenes
    # share their parameters, so one batch holds both.
    models = (lj.CarPendulum(), moving_scene())
    params = nb.params_from_model(models[0])
    np.testing.assert_array_equal(nb.params_from_model(models[1]), params)
    starts = [tuple(np.asarray(x) for x in (s.R, s.mu, s.q, s.p))
              for s in (m.default_state() for m in models)]
    ends = []
    for model, (R, mu, q, p) in zip(models, starts, strict=True):
        traj = lj.simulate(model, lj.RIGID_METHODS[name](), model.default_state(), 5e-3, 200)
        assert traj.ok
        ours = [np.asarray(x)[-1] for x in (traj.state.R, traj.state.mu, traj.state.q,
                                            traj.state.p)]
        ends.append(ours)
        *theirs, its, code = nb.rollout(name, R, mu, q, p, 5e-3, 200, params)
        # The engine's solver: chord iterations (one Jacobian per step), ~4 per step.
        assert code == 0 and 2.0 <= its / 200 <= 5.0
        # Same equations, solved to |Δξ| <= 1e-12 (1 + |ξ|) from different initial guesses:
        # the end states agree to round-off.
        for a, b in zip(ours, theirs, strict=True):
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-12)
    batch = [np.stack(x) for x in zip(*starts, strict=True)]
    *theirs, its, codes = nb.rollout_batch(name, *batch, 5e-3, 200, params)
    assert np.all(codes == 0) and np.all(its >= 400)
    for k, b in enumerate(theirs):
        np.testing.assert_allclose(b, np.stack([e[k] for e in ends]), rtol=0, atol=1e-12)
    # A large step (θ = h|ξ| ≈ 0.2): the closed-form branches of exp and dexp⁻¹ (the
    # engine's compiled rollout is reused: dt is not static). Both solvers stop at the
    # same tolerance from different iterates; a single step agrees to ~1e-15, 200 steps
    # to the accumulated tolerance.
    model, (R, mu, q, p) = models[1], starts[1]
    traj = lj.simulate(model, lj.RIGID_METHODS[name](), model.default_state(), 0.04, 200)
    *theirs, its, code = nb.rollout(name, R, mu, q, p, 0.04, 200, params)
    assert traj.ok and code == 0
    for a, b in zip((traj.state.R, traj.state.mu, traj.state.q, traj.state.p), theirs,
                    strict=True):
        np.testing.assert_allclose(b, np.asarray(a)[-1], rtol=0, atol=5e-11)
    # Failure is reported, not hidden: a non-finite state, and (exp map: Newton cannot
    # follow a rotation of ~250 rad per step; the Cayley map has a root there) a step far
    # too large, which hits the iteration cap as in the engine.
    R, mu, q, p = starts[0]
    *_, code = nb.rollout(name, R, mu * np.nan, q, p, 5e-3, 5, params)
    assert code == 2
    if name != "hamel-cayley":
        *_, code = nb.rollout(name, R, mu * 1e4, q, p, 5e-3, 5, params)
        assert code == 1
