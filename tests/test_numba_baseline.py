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
    R, mu, q, p = (np.asarray(x) for x in (s0.R, s0.mu, s0.q, s0.p))
    R1, mu1, q1, p1, its, code = nb.rollout("lgvi", R, mu, q, p, 5e-3, 200,
                                            nb.params_from_model(model))
    traj = lj.simulate(model, lj.LGVI(), s0, 5e-3, 200)
    assert code == 0 and traj.ok
    # Both solve to |Δξ| <= 1e-12 (1 + |ξ|) per step, from different initial guesses, so
    # the end states agree to the accumulated solver tolerance, not to the last bit.
    for ours, theirs in zip((traj.state.R, traj.state.mu, traj.state.q, traj.state.p),
                            (R1, mu1, q1, p1), strict=True):
        np.testing.assert_allclose(theirs, np.asarray(ours)[-1], atol=1e-11)
    assert 2.0 <= its / 200 <= 4.0
    # Failure is reported, not hidden: a step far too large for Newton.
    *_, code = nb.rollout("lgvi", R, mu * 1e4, q, p, 5e-3, 5, nb.params_from_model(model))
    assert code != 0
