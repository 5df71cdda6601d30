"""The batched rollout of a sweep: initial conditions drawn from ``(seed, i)``, one
trajectory's running metrics (:mod:`lgvi_jax.rollout` with an observer), ``vmap`` in blocks
and split over the devices (:func:`run_batch`, :func:`batch_arguments`)."""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import rollout, so3
from ..newton import batched_trace
from ..scalarize import on_scalars
from .config import engine_name

# ---------------------------------------------------------------------------------------
# Initial conditions
# ---------------------------------------------------------------------------------------


def _perturb_vector(key, x, eps):
    """``x + eps |x| z/√d`` (``eps z/√d`` if ``x = 0``), ``z`` standard normal."""
    if x.size == 0:
        return x
    z = jax.random.normal(key, x.shape, x.dtype) / jnp.sqrt(x.size)
    norm = jnp.linalg.norm(x)
    return x + eps * jnp.where(norm > 0, norm, 1.0) * z


def _one_initial_condition(model, state0, eps, key):
    k_rot, k_w, k_v = jax.random.split(key, 3)
    if hasattr(state0, "R"):
        omega, v = model.velocities(state0.R, state0.mu, state0.q, state0.p)
        u = jax.random.normal(k_rot, (3,), state0.R.dtype)
        u = u / jnp.linalg.norm(u)
        R = state0.R @ so3.exp(eps * u)
        return model.state_from_velocities(
            R, _perturb_vector(k_w, omega, eps), state0.q, _perturb_vector(k_v, v, eps)
        )
    flat = jnp.concatenate([state0.q, state0.p])
    new = _perturb_vector(k_w, flat, eps)
    n = state0.q.shape[0]
    return type(state0)(q=new[:n], p=new[n:])


#: XLA's options for the initial conditions' program: LLVM's optimisations off (level 0).
#: It runs in milliseconds once per chunk, and a sweep compiles it while the rollout is
#: traced, where its optimised compile (~0.56 s against ~0.26 s, on both cores) slowed that
#: tracing (docs/engine.md, "the initial conditions compiled without optimisation").
IC_COMPILER_OPTIONS = {"xla_backend_optimization_level": 0}


def _initial_conditions(model, state0, eps, seed, indices):
    base = jax.random.key(seed)
    keys = jax.vmap(lambda i: jax.random.fold_in(base, i))(indices)
    # One condition at a time (lax.map), not vmap: every condition is then computed by the
    # same unbatched code whatever n is, so condition i is bit-for-bit the same in any
    # chunking (under vmap, XLA's vector and remainder loops can round differently: 1 ulp).
    return jax.lax.map(lambda key: _one_initial_condition(model, state0, eps, key), keys)


def initial_conditions(model, state0, n: int, perturb: float, seed: int,
                       start: int = 0) -> Any:
    """Initial conditions ``start, ..., start + n - 1`` of a sweep, batched (leading axis
    ``n``). Condition ``i`` depends only on ``(seed, i)`` (``jax.random.fold_in``), so any
    chunking of the index range gives the same states."""
    from .. import _cache

    indices = np.arange(start, start + n, dtype=np.uint32)
    # The cached program returns the states' leaves: jax.export serialises only the
    # pytree nodes registered with it, and a state class is not (every run traced again).
    leaves = _cache.call("sweep.initial_conditions", _initial_condition_leaves, model,
                         state0, np.float64(perturb), np.uint32(seed % 2**32), indices,
                         compiler_options=IC_COMPILER_OPTIONS)
    return jax.tree.unflatten(jax.tree.structure(state0), leaves)


def _initial_condition_leaves(model, state0, eps, seed, indices):
    return jax.tree.leaves(_initial_conditions(model, state0, eps, seed, indices))


# ---------------------------------------------------------------------------------------
# The batched rollout
# ---------------------------------------------------------------------------------------


def _diagnostics(model, state):
    """The model's invariants and, on SO(3) x Rⁿ, the orthogonality error ‖RᵀR − I‖_F."""
    out = dict(model.invariants(state))
    if hasattr(state, "R"):
        out["orthogonality_error"] = so3.orthogonality_error(state.R)
    return out


class _Parts(NamedTuple):
    """A batched rollout written for one trajectory: ``prelude(state0) -> (carry, acc)``,
    the loop's ``observe(acc, carry) -> acc`` (or ``None``) and ``finish(end, acc) -> out``.
    :func:`_run_one` runs it for one trajectory, :func:`_run_block` for a block (the loop's
    body ``vmap``-ed inside the loop, ``rollout.advance``'s ``batch_axes``)."""

    prelude: Callable
    observe: Callable | None
    finish: Callable


def _sweep_parts(model, method, example, dt, n_steps, sample_every) -> _Parts:
    """One trajectory of ``n_steps`` (a run-time value) with running metrics; ``example``:
    a state of its shapes (arrays or :class:`jax.ShapeDtypeStruct`)."""
    # On scalars (scalarize.on_scalars): the invariants of a model derived by autodiff (the
    # inverse Legendre map through the kinetic-energy Hessian) are dozens of small array
    # operations that in a loop cost more than the step (docs/engine.md).
    on_scalars_ = on_scalars(_diagnostics, model, example)

    def diagnostics(state):
        return on_scalars_(model, state)

    def metrics(inv, context):
        inv0, scale = context
        out = {"energy_error": jnp.abs(inv["energy"] - inv0["energy"]) / scale}
        for k, v in inv.items():
            if k not in ("energy", "orthogonality_error"):
                out[f"{k}_drift"] = jnp.max(jnp.abs(v - inv0[k]))
        if "orthogonality_error" in inv:
            out["orthogonality_error"] = inv["orthogonality_error"]
        return out

    def prelude(state0):
        inv0 = diagnostics(state0)
        e0 = inv0["energy"]
        # What the metrics compare with: the initial invariants (not the orthogonality
        # error, which is not a drift) and the energy's scale.
        context = ({k: v for k, v in inv0.items() if k != "orthogonality_error"},
                   jnp.where(e0 != 0, jnp.abs(e0), 1.0))
        zero_metrics = jax.tree.map(jnp.zeros_like, metrics(inv0, context))
        # The maxima start at NaN (fmax ignores it): a trajectory that fails before its
        # first sample records NaN, not a misleading 0.
        nan_metrics = jax.tree.map(lambda x: jnp.full_like(x, jnp.nan), zero_metrics)
        return (rollout.start(model, method, state0, dt),
                (nan_metrics, zero_metrics, context))

    def observe(acc, c):
        sample = (c.k % sample_every == 0) | (c.k == n_steps)
        # The initial invariants and energy scale ride in the accumulator, unchanged: each
        # member's own where the body is vmap-ed (a closure would be shared by the block).
        context = acc[2]

        def update(args):
            maxima, last = args
            m = metrics(diagnostics(c.state), context)
            maxima = jax.tree.map(lambda a, b: jnp.where(c.ok, jnp.fmax(a, b), a), maxima, m)
            last = jax.tree.map(lambda b: jnp.where(c.ok, b, jnp.nan), m)
            return maxima, last

        return (*jax.lax.cond(sample, update, lambda a: a, acc[:2]), context)

    def finish(end, acc):
        maxima, last, context = acc
        steps_done = jnp.where(end.failed_step >= 0, end.failed_step + 1, n_steps)
        out = {
            "energy_error_max": maxima["energy_error"],
            "energy_error_final": last["energy_error"],
        }
        for k, v in maxima.items():  # the invariants' drifts, the orthogonality error
            if k != "energy_error":
                out[f"{k}_max"] = v
        ftype = context[1].dtype
        out["newton_mean"] = end.newton_steps / jnp.maximum(steps_done, 1).astype(ftype)
        out["newton_max"] = end.newton_steps_max
        out["result"] = end.result
        out["failed_step"] = end.failed_step
        return out

    return _Parts(prelude, observe, finish)


def _final_parts(model, method, example, dt, n_steps, sample_every) -> _Parts:
    """One trajectory, no metrics: the final state and the result code (benchmarks)."""
    del example, n_steps, sample_every

    def finish(end, acc):
        return {"state": end.state, "result": end.result, "failed_step": end.failed_step}

    return _Parts(lambda state0: (rollout.start(model, method, state0, dt), None), None,
                  finish)


_PARTS = {"metrics": _sweep_parts, "final": _final_parts}


def _run_one(model, method, parts: _Parts, state0, dt, n_steps):
    """``parts`` for one trajectory."""
    carry, acc = parts.prelude(state0)
    end, acc = rollout.advance(model, method, dt, carry, n_steps, parts.observe, acc)
    return parts.finish(end, acc)


def _run_block(model, method, parts: _Parts, states0, dt, n_steps):
    """``parts`` for a block of trajectories (leading axis), as ``vmap`` of
    :func:`_run_one` computes them, with the loop outside the ``vmap`` (its body traced
    once, batched: ``rollout.advance``'s ``batch_axes``). Every leaf of the carry is per
    member except the step index, which stays shared: the metrics' ``cond`` on it then
    stays a branch (metrics every K steps cost 1/K), where a per-member index would turn it
    into a selection."""
    carry, acc = jax.vmap(parts.prelude)(states0)
    carry = eqx.tree_at(lambda c: c.k, carry, carry.k[0])  # the same for all members
    axes = jax.tree.map(lambda _: 0, (carry, acc))
    axes = (eqx.tree_at(lambda c: c.k, axes[0], None), axes[1])
    end, acc = rollout.advance(model, method, dt, carry, n_steps, parts.observe, acc,
                               batch_axes=axes)
    return jax.vmap(parts.finish, in_axes=axes)(end, acc)


_RUNNERS: dict[Any, Callable] = {}

#: The most trajectories one device integrates as one vectorised batch; a larger share runs
#: as a sequence of equal blocks (a loop over ``vmap``), whose working set stays in
#: cache. 512: 2048 trajectories in blocks of 512 run as fast as 512, at once they run
#: slower (docs/engine.md).
BLOCK = 512
#: The block size for the steps emitted on scalars (the scalar engine): their hundreds of
#: live values are each a vector over the block, so the working set grows with it. 32:
#: with 16 the fastest of 16-512 across models and methods, compiling as fast
#: (docs/engine.md; an AVX-512 CPU); the array engine has no such preference.
SCALAR_BLOCK = 32


#: The most CPU devices whose shares run as calls of one device's program
#: (:class:`_Shares`): PJRT's CPU client runs at most 32 computations of a device at once
#: (``max_inflight_computations_per_device``); more devices are sharded with ``shard_map``.
MAX_SHARES = 32


def _in_blocks(one, block_fn, states, block: int):
    """``vmap(one)(states)`` over the leading axis, computed by ``block_fn`` (the same
    function of a block of states) as a sequence of at most ``block``-sized vectorised
    blocks: ``ceil(B / block)`` blocks of equal size, the last padded with copies of the
    first state (computed and dropped), so that the step is compiled once."""
    batch = jax.tree.leaves(states)[0].shape[0]
    if batch == 1:  # one trajectory: the unbatched program (compiles faster than a vmap
        # of one, runs as fast)
        out = one(jax.tree.map(lambda x: x[0], states))
        return jax.tree.map(lambda y: y[None], out)
    if batch <= block:
        with batched_trace():
            return block_fn(states)
    n_blocks = -(-batch // block)
    size = -(-batch // n_blocks)
    pad = n_blocks * size - batch

    def blocks(x):
        x = jnp.concatenate([x, jnp.broadcast_to(x[:1], (pad, *x.shape[1:]))]) if pad else x
        return x.reshape(n_blocks, size, *x.shape[1:])

    xs = jax.tree.map(blocks, states)

    def block_of(_, i):
        j = _opaque_index(i, n_blocks)
        x = jax.tree.map(lambda a: jax.lax.dynamic_index_in_dim(a, j, keepdims=False), xs)
        with batched_trace():
            return None, block_fn(x)

    _, out = jax.lax.scan(block_of, None, jnp.arange(n_blocks, dtype=jnp.int32))
    return jax.tree.map(lambda y: y.reshape(n_blocks * size, *y.shape[2:])[:batch], out)


def _opaque_index(i, n: int):
    """``i`` (``0 <= i < n``) read through a sort of ``[i, n]``. XLA's CPU backend compiles
    a small loop whole, as one function, unless it holds a sort (``SmallWhileLoopHoistingPass``),
    so the loop over blocks stays on XLA's runtime (a few kernel launches per block) while
    the rollout inside it is compiled as a function of its own, which LLVM compiles in less
    time with the run as fast (docs/engine.md). Elsewhere the sort of two integers costs
    nothing measurable."""
    return jax.lax.sort(jnp.stack([i, jnp.asarray(n, i.dtype)]))[0]


def _runner(devices: tuple, kind: str = "metrics", block: int = BLOCK) -> Callable:
    """A batched rollout (``kind`` = ``"metrics"`` or ``"final"``) over ``devices``, each
    device's share in blocks of at most ``block`` (cached per device set, kind and block
    size): jitted for one device; on several CPU devices (up to :data:`MAX_SHARES`), that
    program run once per share (:class:`_Shares`); otherwise sharded with ``shard_map``."""
    key = (devices, kind, block)
    if key in _RUNNERS:
        return _RUNNERS[key]
    if 1 < len(devices) <= MAX_SHARES and all(d.platform == "cpu" for d in devices):
        _RUNNERS[key] = _Shares(_runner(devices[:1], kind, block), len(devices), devices[0])
        return _RUNNERS[key]
    make_parts = _PARTS[kind]

    def batched(params, static, states, dt, n_steps, sample_every):
        model, method = eqx.combine(params, static)
        example = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape[1:], x.dtype), states)
        parts = make_parts(model, method, example, dt, n_steps, sample_every)
        return _in_blocks(lambda s: _run_one(model, method, parts, s, dt, n_steps),
                          lambda s: _run_block(model, method, parts, s, dt, n_steps),
                          states, block)

    if len(devices) == 1:
        fn = jax.jit(batched, static_argnums=1)
    else:
        from jax.sharding import PartitionSpec as P

        mesh = jax.sharding.Mesh(np.array(devices), ("batch",))

        def sharded(params, static, states, dt, n_steps, sample_every):
            inner = jax.shard_map(
                lambda p, s, d, n, e: batched(p, static, s, d, n, e),
                mesh=mesh,
                in_specs=(P(), P("batch"), P(), P(), P()),
                out_specs=P("batch"),
                check_vma=False,
            )
            return inner(params, states, dt, n_steps, sample_every)

        fn = jax.jit(sharded, static_argnums=1)
    _RUNNERS[key] = fn
    return fn


class _Shares:
    """The batched rollout on ``n`` CPU devices: the one-device program (``program``,
    jitted) run once per device's share, the shares at the same time from threads on the
    first device, whose CPU client runs concurrent calls in parallel (one core each).

    Why not ``shard_map``: the same work, but its program goes through XLA's SPMD
    partitioner, which lengthens every compile (docs/engine.md); on an accelerator the
    devices are real and ``shard_map`` stays.
    Called like the jitted function (``runner(*args)``, ``runner.lower(*args).compile()``
    then ``compiled(*dynamic_args)``), with the states whole on the first device
    (:func:`batch_arguments`); returns NumPy arrays. Called inside a JAX transformation
    (traced arguments), it is the one-device program on the whole batch."""

    def __init__(self, program: Callable, n: int, device):
        self.program, self.n, self.device = program, n, device

    def shares(self, args: tuple) -> list[tuple]:
        """``args`` (of the whole batch) once per share: the states cut along their
        leading axis (on the host; a :class:`jax.ShapeDtypeStruct` gets the share's
        shape), the other arguments as they are."""
        params, static, states, *rest = args

        def cut(x, i):
            size = x.shape[0] // self.n
            if isinstance(x, jax.ShapeDtypeStruct):
                return jax.ShapeDtypeStruct((size, *x.shape[1:]), x.dtype,
                                            sharding=x.sharding)
            part = np.asarray(x)[i * size:(i + 1) * size]
            return jax.device_put(part, self.device)

        return [(params, static, jax.tree.map(lambda x, i=i: cut(x, i), states), *rest)
                for i in range(self.n)]

    def run(self, call: Callable, parts: list[tuple]) -> dict[str, np.ndarray]:
        """``call(*part)`` for every share at the same time; their outputs joined.
        ``call`` must be compiled already (concurrent first calls would each trace and
        compile it): :func:`_with_static` of a compiled program, or a loaded one."""
        outs: list = [None] * len(parts)
        errors: list[BaseException] = []

        def share(i):
            try:
                outs[i] = jax.block_until_ready(call(*parts[i]))
            except BaseException as err:  # re-raised in the calling thread
                errors.append(err)

        threads = [threading.Thread(target=share, args=(i,), daemon=True)
                   for i in range(1, len(parts))]
        for t in threads:
            t.start()
        try:  # the first share in this thread (an interrupt ends the wait at once)
            outs[0] = jax.block_until_ready(call(*parts[0]))
        except Exception:
            for t in threads:
                t.join()
            raise
        for t in threads:
            t.join()
        if errors:
            raise errors[0]
        return jax.tree.map(lambda *xs: np.concatenate([np.asarray(x) for x in xs]), *outs)

    def __call__(self, *args):
        if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(args)):
            return self.program(*args)  # inside a transformation: the whole batch at once
        parts = self.shares(args)
        compiled = self.program.lower(*parts[0]).compile()  # kept by JAX's caches
        return self.run(_with_static(compiled), parts)

    def trace(self, *args):
        """One share's program traced (its ``jaxpr``; ``lower()`` as :meth:`lower`)."""
        return _SharesStage(self, self.program.trace(*self.shares(args)[0]))

    def lower(self, *args):
        return _SharesStage(self, self.program.lower(*self.shares(args)[0]))


class _SharesStage:
    """A stage of one share's program (traced or lowered; its attributes), whose
    ``lower()`` and ``compile()`` stay shares: the compiled form is a function of the
    dynamic arguments (those of the jitted function's compiled form: the static one left
    out) of the whole batch."""

    def __init__(self, shares: _Shares, stage):
        self.shares, self.stage = shares, stage

    def __getattr__(self, name):
        return getattr(self.stage, name)

    def lower(self):
        return _SharesStage(self.shares, self.stage.lower())

    def compile(self, *args, **kwargs):
        compiled = self.stage.compile(*args, **kwargs)
        shares, call = self.shares, _with_static(compiled)

        def run(params, states, *rest):
            return shares.run(call, shares.shares((params, None, states, *rest)))

        run.memory_analysis = compiled.memory_analysis  # one device's (as shard_map's)
        return run


def _with_static(compiled: Callable) -> Callable:
    """A compiled form of the jitted rollout (a function of the dynamic arguments) as a
    function of all of them, the static one ignored (it is compiled in)."""
    def call(params, static, *rest):
        return compiled(params, *rest)

    return call


def _sharding(devices, batch: bool):
    if len(devices) == 1:
        return jax.sharding.SingleDeviceSharding(devices[0])
    from jax.sharding import NamedSharding
    from jax.sharding import PartitionSpec as P

    mesh = jax.sharding.Mesh(np.array(devices), ("batch",))
    return NamedSharding(mesh, P("batch") if batch else P())


def _place(tree, devices, batch: bool):
    """``tree`` on ``devices``; a :class:`jax.ShapeDtypeStruct` leaf (an input not computed
    yet, :func:`_prepare_batch`) gets the sharding the array will have."""
    sharding = _sharding(devices, batch)

    def put(x):
        if isinstance(x, jax.ShapeDtypeStruct):
            return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding)
        return jax.device_put(x, devices[0] if len(devices) == 1 else sharding)

    return jax.tree.map(put, tree)


def _prepare_batch(model, method, state0, batch: int, dt, n_steps, sample_every,
                   devices) -> None:
    """Load and compile the batched rollout that :func:`run_batch` will run on ``batch``
    states shaped like ``state0`` (``_cache.prepare``; for a thread beside the initial
    conditions)."""
    from .. import _cache

    try:
        states = jax.tree.map(lambda x: jax.ShapeDtypeStruct((batch, *jnp.shape(x)),
                                                             jnp.result_type(x)), state0)
        fn, args = batch_arguments(model, method, states, dt, n_steps,
                                   sample_every=sample_every, devices=devices)
        if isinstance(fn, _Shares):
            fn, args = fn.program, fn.shares(args)[0]
        _cache.prepare("sweep.run_batch", fn, *args)
    except Exception:  # only a head start: run_batch reports any error itself
        pass


def batch_arguments(model, method, states, dt, n_steps, *, sample_every=1, devices=None,
                    kind="metrics"):
    """``(runner, args)`` of a batched rollout, the arguments placed on ``devices``: call
    ``runner(*args)``, or ``runner.lower(*args).compile()`` to time compilation apart.
    ``states`` may be :class:`jax.ShapeDtypeStruct` leaves (given their sharding here)."""
    method.check_model(model)
    batch = jax.tree.leaves(states)[0].shape[0]
    devices = tuple(jax.devices() if devices is None else devices)
    if batch % len(devices):
        devices = devices[:1]
    params, static = eqx.partition((model, method), eqx.is_array)
    block = _block(method, devices, batch)
    runner = _runner(devices, kind, block)
    on = devices[:1] if isinstance(runner, _Shares) else devices  # cut into shares there
    args = (_place(params, on, False), static, _place(states, on, True),
            # placed from the host: jnp.float64(dt) would compile a conversion program
            *jax.device_put((np.float64(dt), np.int32(n_steps), np.int32(sample_every))))
    return runner, args


def _block(method, devices, batch: int) -> int:
    """The vectorised block of one device's share: :data:`BLOCK` or :data:`SCALAR_BLOCK`
    on CPUs (whose caches the working set must fit), the whole share on accelerators
    (whose throughput needs every trajectory at once; a sequence of blocks would
    serialise them)."""
    if devices[0].platform != "cpu":
        return max(1, -(-batch // len(devices)))
    return BLOCK if engine_name(method) == "general" else min(BLOCK, SCALAR_BLOCK)


def run_batch(model, method, states, dt: float, n_steps: int, *, sample_every: int = 1,
              devices: Sequence | None = None) -> dict[str, np.ndarray]:
    """Integrate a batch of initial states (leading axis ``B``) for ``n_steps`` steps of
    ``dt`` and return the per-trajectory metrics as NumPy arrays of shape ``(B,)``.

    The batch is split over ``devices`` (default: all of ``jax.devices()`` that divide
    ``B``, else one). ``dt``, ``n_steps`` and ``sample_every`` are run-time values.
    """
    from .. import _cache

    fn, args = batch_arguments(model, method, states, dt, n_steps, sample_every=sample_every,
                               devices=devices)
    if isinstance(fn, _Shares):  # one share's program, loaded once, run per share
        parts = fn.shares(args)
        return fn.run(_cache.program("sweep.run_batch", fn.program, *parts[0]), parts)
    out = _cache.call("sweep.run_batch", fn, *args)  # traced once per cache (CLI)
    return {k: np.asarray(v) for k, v in out.items()}


