"""The one rollout loop (lgvi_jax.rollout): its three loop forms agree, a run split in two
equals the whole run, observers fold what simulate saves, ``until`` stops at the first step
that meets it, a failure is kept with its step while later states are NaN, and Python's
garbage collector is paused while a loop is traced."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lgvi_jax as lj
from lgvi_jax import rollout
from lgvi_jax.trajectory import RESULTS

DT = 0.1
N = 40


@pytest.fixture
def setup():
    model = lj.HarmonicOscillator(m=1.3, k=0.7)
    return model, lj.GaussLegendre(), model.state(q0=0.4, p0=-0.9)


def _leaves(carry):
    return [np.asarray(x) for x in jax.tree.leaves(carry)]


def _run(model, method, s0, n, loop, carry=None):
    carry = rollout.start(model, method, s0, DT) if carry is None else carry
    return jax.jit(lambda c: rollout.advance(model, method, DT, c, n, loop=loop)[0])(carry)


def test_scan_fori_while_agree_and_a_split_run_equals_the_whole(setup):
    model, method, s0 = setup
    runs = {loop: _run(model, method, s0, N, loop) for loop in ("scan", "fori", "while")}
    half = _run(model, method, s0, 15, "fori")
    runs["split"] = _run(model, method, s0, N - 15, "scan", carry=half)
    ref = _leaves(runs["scan"])
    # The same operations in the same order: equal to the bit, whatever the loop.
    for name, carry in runs.items():
        for a, b in zip(_leaves(carry), ref, strict=True):
            np.testing.assert_array_equal(a, b, err_msg=name)
    end = runs["scan"]
    assert int(end.k) == N and int(end.result) == RESULTS.successful
    assert int(end.failed_step) == -1
    # The state is simulate's last state, and the Newton counts are simulate's.
    traj = lj.simulate(model, method, s0, DT, N)
    np.testing.assert_array_equal(np.asarray(end.state.q), np.asarray(traj.state.q[-1]))
    assert int(end.newton_steps) == int(np.sum(traj.newton_steps))
    assert int(end.newton_steps_max) == int(np.max(traj.newton_steps_max))


def test_an_observer_folds_what_simulate_saves_and_until_stops_at_the_first_hit(setup):
    model, method, s0 = setup
    e0 = model.energy(s0)

    def observe(acc, c):
        return jnp.maximum(acc, jnp.abs(model.energy(c.state) - e0))

    carry = rollout.start(model, method, s0, DT)
    _, emax = rollout.advance(model, method, DT, carry, N, observe, jnp.zeros(()))
    errors = np.abs(np.asarray(lj.simulate(model, method, s0, DT, N).energy) - float(e0))
    assert float(emax) == float(np.max(errors))
    # Stop once the running maximum passes its median over the run: at the first step k
    # whose error passes it, after k steps.
    threshold = float(np.median(errors[1:]))
    first = int(np.argmax(errors > threshold))
    end, emax = rollout.advance(model, method, DT, carry, N, observe, jnp.zeros(()),
                                loop="while", until=lambda c, a: a > threshold)
    assert int(end.k) == first and float(emax) == float(np.max(errors[: first + 1]))


@pytest.mark.parametrize("loop", ["fori", "scan"])
def test_a_batch_with_its_body_vmapped_in_the_loop_equals_vmap_of_the_loop(setup, loop):
    """``batch_axes``: the loop's body ``vmap``-ed inside the loop (the step index shared)
    gives what ``vmap`` of the whole loop gives, member by member, observer included, and
    (``scan``) the same gradient with respect to a model parameter."""
    model, method, _ = setup
    states = jax.vmap(lambda q, p: model.state(q0=q, p0=p))(
        jnp.linspace(-0.8, 0.9, 5), jnp.linspace(0.7, -1.1, 5))

    def prelude(s):
        return rollout.start(model, method, s, DT), (jnp.zeros(()), model.energy(s))

    def observe(acc, c):
        emax, e0 = acc
        return jnp.maximum(emax, jnp.abs(model.energy(c.state) - e0)), e0

    def one(s):
        carry, acc = prelude(s)
        return rollout.advance(model, method, DT, carry, N, observe, acc, loop=loop)

    ref_carry, ref_acc = jax.jit(jax.vmap(one))(states)

    def batched(states):
        carry, acc = jax.vmap(prelude)(states)
        carry = eqx.tree_at(lambda c: c.k, carry, carry.k[0])
        axes = jax.tree.map(lambda _: 0, (carry, acc))
        axes = (eqx.tree_at(lambda c: c.k, axes[0], None), axes[1])
        return rollout.advance(model, method, DT, carry, N, observe, acc, loop=loop,
                               batch_axes=axes)

    carry, acc = jax.jit(batched)(states)
    assert carry.k.shape == () and int(carry.k) == N  # shared, not per member
    np.testing.assert_array_equal(np.asarray(ref_carry.k), N)
    # The same operations on the same values: equal to round-off (N steps of a few ulp of
    # O(1) values; a fused multiply-add here or there is all another program may change).
    for a, b in zip(jax.tree.leaves((eqx.tree_at(lambda c: c.k, carry, ref_carry.k), acc)),
                    jax.tree.leaves((ref_carry, ref_acc)), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-14)
    assert float(jnp.max(acc[0])) > 0  # the observer ran
    if loop == "scan":  # reverse mode through the batched loop: vmap of the loop's gradient
        def final_q(k, states, run):
            m = eqx.tree_at(lambda x: x.k, model, k)
            carry = jax.vmap(lambda s: rollout.start(m, method, s, DT))(states)
            if run == "vmap":
                end, _ = jax.vmap(lambda c: rollout.advance(m, method, DT, c, N,
                                                            loop="scan"))(carry)
            else:
                carry = eqx.tree_at(lambda c: c.k, carry, carry.k[0])
                axes = eqx.tree_at(lambda c: c.k, jax.tree.map(lambda _: 0, carry), None)
                end, _ = rollout.advance(m, method, DT, carry, N, loop="scan",
                                         batch_axes=(axes, None))
            return jnp.sum(end.state.q ** 2)

        grads = [jax.grad(final_q)(model.k, states, run) for run in ("vmap", "inside")]
        # The same operations differentiated: equal to round-off, as the values above.
        np.testing.assert_allclose(float(grads[1]), float(grads[0]), rtol=1e-12)
        assert float(grads[0]) != 0
    with pytest.raises(ValueError, match="batch_axes"):
        rollout.advance(model, method, DT, carry, N, observe, acc, loop="while",
                        batch_axes=(None, None))


def test_a_failure_keeps_its_step_and_the_later_states_are_nan(setup):
    model, _, s0 = setup
    # Newton with one iteration can never confirm convergence: step 0 fails.
    method = lj.GaussLegendre(newton=lj.Newton(max_steps=1))
    end = _run(model, method, s0, 10, "fori")
    assert int(end.result) == RESULTS.max_steps_reached and int(end.failed_step) == 0
    assert float(end.failed_residual) > 0
    assert np.all(np.isnan(np.asarray(end.state.q))) and int(end.k) == 10
    # Iterations count only the steps taken before the failure, the failed step's included.
    assert int(end.newton_steps) == 1 and int(end.newton_steps_max) == 1
    # A later failure of another kind does not overwrite the first.
    again = rollout.advance(model, lj.RK4(), DT, end, 3)[0]
    assert int(again.result) == RESULTS.max_steps_reached and int(again.failed_step) == 0


def test_bad_loop_is_named():
    with pytest.raises(ValueError, match="loop must be"):
        rollout.advance(None, None, DT, None, 1, loop="unroll")


def test_the_collector_is_paused_while_tracing_and_restored_after(setup):
    """``advance`` pauses Python's garbage collector while it traces the loop (the step and
    the observer run with it off) and gives back the caller's setting afterwards, also when
    the trace raises, from nested pauses and from several threads at once."""
    import gc
    import threading

    from lgvi_jax import _gc

    model, method, s0 = setup
    seen = []

    def observe(acc, c):
        seen.append(gc.isenabled())
        return acc

    assert gc.isenabled()
    carry = rollout.start(model, method, s0, DT)
    jax.jit(lambda c: rollout.advance(model, method, DT, c, 3, observe, 0.0))(carry)
    assert seen and not any(seen) and gc.isenabled()

    def fail(acc, c):
        raise RuntimeError("observer failed")

    with pytest.raises(RuntimeError, match="observer failed"):
        rollout.advance(model, method, DT, carry, 3, fail, 0.0, loop="scan")
    assert gc.isenabled()

    gc.disable()  # the caller's choice is kept
    try:
        with _gc.paused():
            pass
        assert not gc.isenabled()
    finally:
        gc.enable()

    # Nested and concurrent pauses: off until the last one ends.
    inside = threading.Barrier(3)
    leave = threading.Event()

    def hold():
        with _gc.paused():
            inside.wait()
            leave.wait()

    threads = [threading.Thread(target=hold) for _ in range(2)]
    for t in threads:
        t.start()
    with _gc.paused():
        inside.wait()
        with _gc.paused():
            assert not gc.isenabled()
    assert not gc.isenabled()  # the threads' pauses are still active
    leave.set()
    for t in threads:
        t.join()
    assert gc.isenabled()
