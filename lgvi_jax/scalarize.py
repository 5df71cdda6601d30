r"""Scalarisation: re-emit a function of small arrays as scalar elementwise operations.

The discrete equations of the Lie-group methods are built by autodiff through 3-vectors and
3x3 matrices (matrix products, transposes, cross products, reductions over size-3 axes).
XLA compiles each such small operation as a kernel of its own (CPU matrix products even
become library calls), and a Newton iteration then costs dozens of kernel launches per step:
the price is per kernel, not per flop. :func:`scalarize` removes the small arrays: it traces
a function to a jaxpr and evaluates that jaxpr on **arrays of scalars** (NumPy object arrays
whose entries are 0-d JAX values), so that every matrix product becomes a handful of scalar
multiply-adds, every transpose, slice, reshape or broadcast becomes a re-indexing at trace
time (no operation at all), and what is left is one long chain of scalar elementwise
operations that XLA fuses into a few kernels. Under ``jax.vmap`` each scalar becomes one
contiguous array over the batch (a structure of arrays), under ``jit`` of one trajectory a
register.

While interpreting it folds constants and applies the identities ``x + 0 = x``,
``x * 0 = 0``, ``x * 1 = x``, ``select(c, a, b)`` with a known ``c``: autodiff of
matrix-form energies is full of structural zeros (``hat`` maps, identity matrices), and a
scalar program only keeps the arithmetic that reaches the result. (``x * 0 = 0`` drops the
propagation of a NaN in ``x`` into that product; every non-finite state still reaches the
outputs through its other uses, where the rollouts test it.)

The values are those of the original function up to the order of floating-point additions
(sums of products are accumulated left to right, as a matrix product of size 3 would).
Supported: elementwise primitives, ``broadcast_in_dim``, ``reshape``, ``squeeze``,
``expand_dims``, ``transpose``, ``slice``, ``concatenate``, ``pad``, ``split``, ``stack``,
``unstack``, ``rev``, ``iota``, ``reduce_sum/max/min/and/or``, ``dot_general``, ``select_n``,
``cond`` (a branch of scalars; on a batch's vectors both branches, selected per member),
``while``, nested ``jit`` and the primal of ``custom_jvp`` /
``custom_vjp`` calls (the result is differentiated through its scalar operations, which is
exact since they are the same function). Anything else raises ``NotImplementedError``
naming the primitive.
"""

from __future__ import annotations

import functools
import itertools
import math
import weakref
from collections.abc import Callable
from typing import Any

import jax
import jax.extend as jex
import jax.numpy as jnp
import numpy as np
from jax import lax

__all__ = ["ScalarFunction", "join", "on_scalars", "program_for", "scalarize", "split"]


# ---------------------------------------------------------------------------------------
# Scalars: a known constant is a NumPy scalar (np.generic), anything else a 0-d JAX value.
# ---------------------------------------------------------------------------------------

def _is_const(x) -> bool:
    return isinstance(x, np.generic)


def _const(value, dtype) -> np.generic:
    return np.asarray(value, dtype=dtype)[()]


def split(x) -> np.ndarray:
    """An array as an object array of its scalar entries (NumPy scalars when ``x`` is
    concrete NumPy data, so that constants fold)."""
    if isinstance(x, np.ndarray | np.generic | float | int | bool):
        arr = np.asarray(x)
        out = np.empty(arr.shape, dtype=object)
        for idx in np.ndindex(arr.shape):
            out[idx] = arr[idx]
        return out
    x = jnp.asarray(x)
    out = np.empty(x.shape, dtype=object)
    if x.ndim == 0:
        out[()] = x
        return out
    flat = x.reshape(-1)
    # lax.slice, not flat[i]: the same operations, bound directly rather than through
    # jax.numpy's indexing (a jitted function per entry; tracing a batch splits hundreds).
    items = [lax.squeeze(lax.slice(flat, (i,), (i + 1,)), (0,)) for i in range(flat.shape[0])]
    for i, idx in enumerate(np.ndindex(x.shape)):
        out[idx] = items[i]
    return out


def join(obj: np.ndarray, dtype=None) -> jax.Array:
    """The array with the scalar entries of ``obj`` (inverse of :func:`split`)."""
    obj = np.asarray(obj, dtype=object)
    if dtype is None:
        dtype = _dtype_of(obj)
    items = [jnp.asarray(v, dtype) for v in obj.reshape(-1)]
    if not items:
        return jnp.zeros(obj.shape, dtype)
    return jnp.stack(items).reshape(obj.shape)


def _dtype_of(obj):
    for v in obj.reshape(-1):
        return jnp.result_type(v)
    return jnp.float64


# ---------------------------------------------------------------------------------------
# Elementwise primitives, with constant folding and the identities of the docstring.
# ---------------------------------------------------------------------------------------

_NUMPY_UNARY = {
    "neg": np.negative, "sin": np.sin, "cos": np.cos, "tan": np.tan, "sqrt": np.sqrt,
    "exp": np.exp, "log": np.log, "log1p": np.log1p, "expm1": np.expm1, "abs": np.abs,
    "sign": np.sign, "tanh": np.tanh, "sinh": np.sinh, "cosh": np.cosh, "atan": np.arctan,
    "asin": np.arcsin, "acos": np.arccos, "floor": np.floor, "ceil": np.ceil,
    "not": np.logical_not, "is_finite": np.isfinite, "square": np.square,
}
_NUMPY_BINARY = {
    "add": np.add, "add_any": np.add, "sub": np.subtract, "mul": np.multiply,
    "div": np.divide, "max": np.maximum, "min": np.minimum, "pow": np.power,
    "atan2": np.arctan2, "eq": np.equal, "ne": np.not_equal, "lt": np.less,
    "le": np.less_equal, "gt": np.greater, "ge": np.greater_equal, "and": np.logical_and,
    "or": np.logical_or, "rem": np.fmod,
}
_ELEMENTWISE = set(_NUMPY_UNARY) | set(_NUMPY_BINARY) | {
    "integer_pow", "convert_element_type", "select_n", "clamp", "copy", "copy_p", "rsqrt",
    "cbrt", "logistic", "erf", "erfc", "erf_inv", "exp2", "asinh", "acosh", "atanh",
    "round", "nextafter", "reduce_precision", "xor", "lgamma", "digamma", "stop_gradient",
}


def _is(x, value) -> bool:
    return _is_const(x) and x.dtype.kind in "fiu" and x == value


def _fold(name, params, args, dtype):
    """Evaluate an elementwise primitive on constants with NumPy (or return None)."""
    with np.errstate(all="ignore"):
        if name in _NUMPY_UNARY:
            return _const(_NUMPY_UNARY[name](args[0]), dtype)
        if name in _NUMPY_BINARY:
            return _const(_NUMPY_BINARY[name](args[0], args[1]), dtype)
        if name == "integer_pow":
            return _const(np.power(args[0], params["y"]), dtype)
        if name == "convert_element_type":
            return _const(args[0], dtype)
        if name == "select_n":
            return _const(args[1 + int(args[0])], dtype)
        if name in ("copy", "copy_p"):
            return args[0]
        if name == "rsqrt":
            return _const(1.0 / np.sqrt(args[0]), dtype)
    return None


def _simplify(name, params, args, dtype):
    """Identities with one known operand; None if none applies."""
    if name in ("add", "add_any"):
        a, b = args
        if _is(a, 0):
            return b
        if _is(b, 0):
            return a
    elif name == "sub":
        a, b = args
        if _is(b, 0):
            return a
        if _is(a, 0):
            return _apply("neg", {}, [b], dtype)
    elif name == "mul":
        a, b = args
        if _is(a, 0) or _is(b, 0):
            return _const(0, dtype)
        if _is(a, 1):
            return b
        if _is(b, 1):
            return a
        if _is(a, -1):
            return _apply("neg", {}, [b], dtype)
        if _is(b, -1):
            return _apply("neg", {}, [a], dtype)
    elif name == "div":
        a, b = args
        if _is(a, 0) and not _is(b, 0):
            return _const(0, dtype)
        if _is(b, 1):
            return a
    elif name == "neg":
        (a,) = args
        if _is(a, 0):
            return _const(0, dtype)
    elif name == "select_n":
        pred, *cases = args
        if _is_const(pred):
            return cases[int(pred)]
        if all(c is cases[0] for c in cases[1:]):
            return cases[0]
    elif name == "convert_element_type":
        (a,) = args
        if not _is_const(a) and jnp.result_type(a) == dtype:
            return a
    elif name == "integer_pow":
        (a,) = args
        if params["y"] == 1:
            return a
        if _is(a, 0) and params["y"] > 0:
            return _const(0, dtype)
    elif name in ("copy", "copy_p", "optimization_barrier"):
        return args[0]
    return None


def _bind_params(name, params):
    if name == "convert_element_type":
        return dict(params, weak_type=False)
    if not params:
        return _default_params().get(name, params)
    return params


@functools.cache
def _default_params() -> dict[str, dict]:
    """The parameters JAX itself binds for the operations the hand-written scalar code
    emits (read off a traced example, so that they follow the installed JAX)."""
    def example(a, b):
        p = a > b
        return (a * b, a + b, a - b, a / b, -a, lax.max(a, b), lax.min(a, b), jnp.abs(a),
                p & p, p | p, ~p, jnp.isfinite(a), a < b, a >= b, a <= b, lax.sqrt(a),
                lax.sin(a), lax.cos(a))

    closed = jax.make_jaxpr(example)(1.0, 2.0)
    return {eqn.primitive.name: dict(eqn.params) for eqn in closed.jaxpr.eqns}


_PRIMITIVES: dict[str, Any] = {}


def _apply(name, params, args, dtype, primitive=None):
    """One scalar elementwise operation."""
    if all(_is_const(a) for a in args):
        folded = _fold(name, params, args, dtype)
        if folded is not None:
            return folded
    simple = _simplify(name, params, args, dtype)
    if simple is not None:
        return simple
    if primitive is None:
        primitive = _PRIMITIVES[name]
    # lax primitives take operands of one dtype; constants carry theirs already.
    out = primitive.bind(*_operands(args), **_bind_params(name, params))
    return out


def _operand(a):
    if _is_const(a):
        return np.asarray(a)
    return a


def _operands(args):
    """The operands of one operation, of one shape: a "scalar" may be a vector over a batch
    (a program replayed on a structure of arrays, :func:`_iterate_scalar` with ``lanes`` in
    :mod:`lgvi_jax.newton`), and constants and unbatched values then enter broadcast."""
    ops = [_operand(a) for a in args]
    shape = ()
    for o in ops:
        if np.ndim(o):
            shape = np.shape(o)
            break
    if shape:
        ops = [o if np.shape(o) == shape else lax.broadcast_in_dim(o, shape, ()) for o in ops]
    return ops


def _dt(x):
    return x.dtype if _is_const(x) else jnp.result_type(x)


def _register_lax():
    for name in _ELEMENTWISE | {"add_any"}:
        prim = getattr(lax, f"{name}_p", None)
        if prim is not None:
            _PRIMITIVES[name] = prim
    _PRIMITIVES["add_any"] = lax.add_p  # add_any is addition of values


_register_lax()


# ---------------------------------------------------------------------------------------
# Structural primitives on object arrays.
# ---------------------------------------------------------------------------------------

def _reduce(x: np.ndarray, axes, op: Callable, dtype) -> np.ndarray:
    axes = tuple(sorted(axes))
    keep = [d for d in range(x.ndim) if d not in axes]
    moved = np.transpose(x, keep + list(axes))
    out_shape = moved.shape[: len(keep)]
    k = math.prod(moved.shape[len(keep):])
    flat = moved.reshape((*out_shape, k))
    out = np.empty(out_shape, dtype=object)
    for idx in np.ndindex(out_shape):
        items = list(flat[idx])
        acc = items[0]
        for item in items[1:]:
            acc = op(acc, item)
        out[idx] = acc
    return out


def _dot_general(lhs, rhs, dimension_numbers, dtype):
    (lc, rc), (lb, rb) = dimension_numbers
    lf = [d for d in range(lhs.ndim) if d not in lc and d not in lb]
    rf = [d for d in range(rhs.ndim) if d not in rc and d not in rb]
    L = np.transpose(lhs, list(lb) + lf + list(lc))
    Rm = np.transpose(rhs, list(rb) + rf + list(rc))
    bshape = L.shape[: len(lb)]
    lfs = L.shape[len(lb): len(lb) + len(lf)]
    rfs = Rm.shape[len(rb): len(rb) + len(rf)]
    k = math.prod(L.shape[len(lb) + len(lf):])
    L = L.reshape(bshape + lfs + (k,))
    Rm = Rm.reshape(bshape + rfs + (k,))
    out = np.empty(bshape + lfs + rfs, dtype=object)
    for b in np.ndindex(bshape):
        for i in np.ndindex(lfs):
            for j in np.ndindex(rfs):
                acc = _const(0, dtype)
                for t in range(k):
                    acc = _apply("add", {}, [acc, _apply("mul", {}, [L[b + i][t], Rm[b + j][t]],
                                                        dtype)], dtype)
                out[b + i + j] = acc
    return out


def _pad(x, padval, config):
    """``lax.pad``: interior and edge padding (edges may be negative: cropping)."""
    grown = [max(lo, 0) + max(hi, 0) + n + max(n - 1, 0) * it
             for n, (lo, hi, it) in zip(x.shape, config, strict=True)]
    out = _full(tuple(grown), padval)
    place = tuple(slice(max(lo, 0), max(lo, 0) + n + max(n - 1, 0) * it, it + 1)
                  for n, (lo, hi, it) in zip(x.shape, config, strict=True))
    out[place] = x
    crop = tuple(slice(max(-lo, 0), g - max(-hi, 0))
                 for g, (lo, hi, _) in zip(grown, config, strict=True))
    return out[crop]


def _full(shape, value):
    out = np.empty(shape, dtype=object)
    for idx in np.ndindex(shape):
        out[idx] = value
    return out


def _flatten(vals):
    """Object arrays -> a flat list of scalars (for loop carries and branch outputs)."""
    return [v for x in vals for v in x.reshape(-1)]


def _unflatten(flat, avals):
    out, i = [], 0
    for aval in avals:
        n = math.prod(aval.shape)
        arr = np.empty(aval.shape, dtype=object)
        for j, idx in enumerate(np.ndindex(aval.shape)):
            arr[idx] = flat[i + j]
        out.append(arr)
        i += n
    return out


# ---------------------------------------------------------------------------------------
# The interpreter.
# ---------------------------------------------------------------------------------------

def _eval_jaxpr(jaxpr, consts, args) -> list[np.ndarray]:
    env: dict = {}

    def read(v):
        if isinstance(v, jex.core.Literal):
            return split(np.asarray(v.val, dtype=v.aval.dtype))
        return env[v]

    for var, val in zip(jaxpr.constvars, consts, strict=True):
        env[var] = val
    for var, val in zip(jaxpr.invars, args, strict=True):
        env[var] = val
    for eqn in jaxpr.eqns:
        invals = [read(v) for v in eqn.invars]
        outs = _eval_eqn(eqn, invals)
        for var, val in zip(eqn.outvars, outs, strict=True):
            env[var] = val
    return [read(v) for v in jaxpr.outvars]


def _closed(jaxpr_like):
    if hasattr(jaxpr_like, "jaxpr"):
        return jaxpr_like.jaxpr, [split(c) for c in jaxpr_like.consts]
    return jaxpr_like, []


def _call_closed(closed, invals):
    jaxpr, consts = _closed(closed)
    return _eval_jaxpr(jaxpr, consts, invals)


def _eval_eqn(eqn, invals) -> list[np.ndarray]:
    name = eqn.primitive.name
    params = eqn.params
    out_avals = [v.aval for v in eqn.outvars]
    aval = out_avals[0] if out_avals else None

    if name in _ELEMENTWISE:
        shape, dtype = aval.shape, aval.dtype
        b = [np.broadcast_to(x, shape) for x in invals]
        out = np.empty(shape, dtype=object)
        for idx in np.ndindex(shape):
            out[idx] = _apply(name, params, [x[idx] for x in b], dtype, eqn.primitive)
        return [out]
    if name == "broadcast_in_dim":
        (x,) = invals[:1]
        shape, dims = params["shape"], params["broadcast_dimensions"]
        expanded = [1] * len(shape)
        for i, d in enumerate(dims):
            expanded[d] = x.shape[i]
        return [np.broadcast_to(x.reshape(expanded), shape).copy()]
    if name == "reshape":
        return [invals[0].reshape(params["new_sizes"])]
    if name == "squeeze":
        return [np.squeeze(invals[0], axis=tuple(params["dimensions"]))]
    if name == "expand_dims":
        return [np.expand_dims(invals[0], tuple(params["dimensions"]))]
    if name == "transpose":
        return [np.transpose(invals[0], params["permutation"])]
    if name == "rev":
        return [np.flip(invals[0], axis=tuple(params["dimensions"]))]
    if name == "slice":
        strides = params["strides"] or (1,) * invals[0].ndim
        idx = tuple(slice(s, e, st) for s, e, st in
                    zip(params["start_indices"], params["limit_indices"], strides, strict=True))
        return [invals[0][idx]]
    if name == "concatenate":
        return [np.concatenate(invals, axis=params["dimension"])]
    if name == "pad":
        x, padval = invals
        return [_pad(x, padval[()], params["padding_config"])]
    if name == "split":
        bounds = list(itertools.accumulate(int(s) for s in params["sizes"]))[:-1]
        return list(np.split(invals[0], bounds, axis=params["axis"]))
    if name == "stack":
        return [np.stack(invals, axis=params["axis"])]
    if name == "unstack":
        x = invals[0]
        axis = params["axis"]
        return [np.squeeze(np.take(x, [i], axis=axis), axis=axis) for i in range(x.shape[axis])]
    if name == "iota":
        shape, dim = aval.shape, params["dimension"]
        ramp = np.arange(shape[dim], dtype=aval.dtype).reshape(
            [shape[dim] if d == dim else 1 for d in range(len(shape))])
        return [split(np.broadcast_to(ramp, shape))]
    if name in ("reduce_sum", "reduce_max", "reduce_min", "reduce_and", "reduce_or",
                "reduce_prod"):
        op_name = {"reduce_sum": "add", "reduce_max": "max", "reduce_min": "min",
                   "reduce_and": "and", "reduce_or": "or", "reduce_prod": "mul"}[name]
        dtype = aval.dtype
        prim = _PRIMITIVES[op_name]
        x = invals[0]
        axes = params["axes"]
        if any(x.shape[a] == 0 for a in axes):
            return [split(np.asarray(_reduce_identity(op_name, dtype, aval.shape)))]
        return [_reduce(x, axes, lambda a, b: _apply(op_name, {}, [a, b], dtype, prim), dtype)]
    if name == "dot_general":
        return [_dot_general(invals[0], invals[1], params["dimension_numbers"], aval.dtype)]
    if name in ("pjit", "jit", "closed_call", "core_call", "remat", "checkpoint"):
        inner = params.get("jaxpr") or params.get("call_jaxpr")
        return _call_closed(inner, invals)
    if name == "custom_jvp_call":
        return _call_closed(params["call_jaxpr"], invals)
    if name == "custom_vjp_call" or name == "custom_vjp_call_jaxpr":
        inner = params.get("call_jaxpr") or params.get("fun_jaxpr")
        return _call_closed(inner, invals)
    if name == "cond":
        index, *ops = invals
        branches = params["branches"]
        idx = index[()]
        if _is_const(idx):
            return _call_closed(branches[int(idx)], ops)
        # A branch of scalars: only the branch taken runs (replayed on a batch's vectors,
        # _replay_cond). Scalar outputs of the branches, as the loop's carries are.
        flat = _switch(idx, [lambda br=br: _flatten(_call_closed(br, ops)) for br in branches],
                       _flat_dtypes(out_avals))
        return _unflatten(list(flat), out_avals)
    if name == "while":
        return _while(eqn, invals)
    if name in ("empty", "empty2"):  # a residual of a branch not taken (cond's transpose)
        return [split(np.zeros(v.aval.shape, v.aval.dtype)) for v in eqn.outvars]
    if name in _IDENTITY:
        return list(invals)
    raise NotImplementedError(
        f"scalarize: primitive {name!r} is not supported (shapes "
        f"{[v.aval.str_short() for v in eqn.invars]})"
    )


#: Primitives that only annotate placement (values unchanged): the identity on scalars.
_IDENTITY = {"reshard", "sharding_constraint", "mesh_cast", "pvary", "device_put",
             "copy", "copy_p", "optimization_barrier"}


def _reduce_identity(op_name, dtype, shape):
    value = {"add": 0, "mul": 1, "max": -np.inf, "min": np.inf, "and": True, "or": False}
    return np.full(shape, value[op_name], dtype=dtype)


def _materialise(x, dtype):
    """A loop carry must be a JAX value of a fixed dtype."""
    return jnp.asarray(np.asarray(x) if _is_const(x) else x, dtype)


def _while(eqn, invals):
    params = eqn.params
    cj, bj = params["cond_jaxpr"], params["body_jaxpr"]
    cn, bn = params["cond_nconsts"], params["body_nconsts"]
    cconsts, bconsts, init = invals[:cn], invals[cn: cn + bn], invals[cn + bn:]
    avals = [v.aval for v in eqn.outvars]
    dtypes = [a.dtype for a in avals for _ in range(math.prod(a.shape))]
    flat0 = [_materialise(x, d) for x, d in zip(_flatten(init), dtypes, strict=True)]

    def cond(flat):
        (out,) = _call_closed(cj, [*cconsts, *_unflatten(list(flat), avals)])
        return _materialise(out[()], np.bool_)

    def body(flat):
        outs = _call_closed(bj, [*bconsts, *_unflatten(list(flat), avals)])
        return tuple(_materialise(x, d) for x, d in zip(_flatten(outs), dtypes, strict=True))

    flat = lax.while_loop(cond, body, tuple(flat0))
    return _unflatten(list(flat), avals)


# ---------------------------------------------------------------------------------------
# Public entry points.
# ---------------------------------------------------------------------------------------

class ScalarFunction:
    """``fn`` traced once for arguments shaped like ``example`` (a pytree of arrays or
    ``jax.ShapeDtypeStruct``), evaluated on pytrees of object arrays of scalars.

    ``sf(*scalar_args)`` takes the arguments with every leaf replaced by its
    :func:`split` and returns the outputs likewise; chaining scalar functions this way
    never materialises the small arrays in between.

    The scalar program is built once (a jaxpr of 0-d operations, after folding and the
    identities) and replayed at every call. Replayed under ``vmap``, the values that
    several operations read and that cost enough to compute (:data:`MATERIALIZE_COST`) are
    materialised (:func:`_materialization_points`): XLA would otherwise recompute them inside
    every kernel that reads them.
    """

    def __init__(self, fn: Callable, *example):
        structs = jax.tree.map(lambda x: jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)),
                               example)
        closed, out_shape = jax.make_jaxpr(fn, return_shape=True)(*structs)
        self.in_tree = jax.tree.structure(example)
        self.out_shape = out_shape
        self.out_tree = jax.tree.structure(out_shape)
        jaxpr = closed.jaxpr
        # Concrete constants fold into the program; traced ones (closures) become inputs.
        known = [_concrete(c) for c in closed.consts]
        self.traced_consts = [c for c, k in zip(closed.consts, known, strict=True) if not k]
        in_avals = ([v.aval for v, k in zip(jaxpr.constvars, known, strict=True) if not k]
                    + [v.aval for v in jaxpr.invars])
        self.in_avals = in_avals
        self.out_avals = [v.aval for v in jaxpr.outvars]

        def program(*flat):
            arrays = _unflatten(list(flat), in_avals)
            n_traced = len(self.traced_consts)
            it = iter(arrays[:n_traced])
            consts = [split(np.asarray(c)) if k else next(it)
                      for c, k in zip(closed.consts, known, strict=True)]
            outs = _flatten(_eval_jaxpr(jaxpr, consts, arrays[n_traced:]))
            self.const_outputs = {i: v for i, v in enumerate(outs) if _is_const(v)}
            return [_materialise(v, d) for v, d in
                    zip(outs, _flat_dtypes(self.out_avals), strict=True)]

        scalars = [jax.ShapeDtypeStruct((), a.dtype) for a in in_avals
                   for _ in range(math.prod(a.shape))]
        self.program = _simplify_program(jax.make_jaxpr(program)(*scalars))
        self.keep = _materialization_points(self.program.jaxpr)
        self._splits: dict = {}  # _split_by_directions, per number of directions

    @property
    def size(self) -> int:
        """Operations in the scalar program."""
        return len(self.program.jaxpr.eqns)

    def __call__(self, *scalar_args, batched: bool | None = None):
        """``batched``: materialise the shared values (see the class docstring); default:
        when called under ``vmap`` (not visible inside a loop's body: pass it there)."""
        flat, one, keep = self._inputs(scalar_args, batched)
        outs = [self._output(i, v, one)
                for i, v in enumerate(_replay(self.program, flat, keep, one))]
        return jax.tree.unflatten(self.out_tree, _unflatten(outs, self.out_avals))

    def _inputs(self, scalar_args, batched: bool | None):
        """The program's flat inputs (traced constants first), the runtime one that
        materialises shared values (``None`` unless ``batched``) and those values."""
        leaves = self.in_tree.flatten_up_to(scalar_args)
        consts = [split(c) for c in self.traced_consts]
        flat = _flatten([np.asarray(x, dtype=object) for x in consts + list(leaves)])
        batched = _under_vmap() if batched is None else batched
        one = _runtime_one(flat) if batched else None
        return flat, one, self.keep if batched else frozenset()

    def _output(self, index: int, value, one):
        """Flat output ``index``: its constant if it is one, materialised when batched."""
        value = self.const_outputs.get(index, value)
        return value if one is None or _is_const(value) else _over(value, one)

    def on_unit_vectors(self, *scalar_args,
                        batched: bool | None = None) -> list[list[jax.Array]]:
        """For a program ``(*args, d_1, ..., d_k) -> (o_1, ..., o_k)`` whose output ``o_b``
        reads only ``d_b`` of the directions (each one array), called with ``args``: for
        each ``b``, ``o_b`` (flat) at every unit vector of ``d_b``, the others zero,
        computed in a loop over them at run time. The operations that read no direction run
        once, before the loops; each loop runs those that read its own. Each output is an
        array whose leading axis is the unit vector's index.

        Given the program of the JVPs along blocks of the unknowns, a Jacobian block of
        columns by block of columns: each loop runs only its block's tangent operations (in
        the program: ~1/size of its block of the unrolled Jacobian, where the one-hot
        tangents fold at trace time). ``batched``: as :meth:`__call__`."""
        k = len(self.in_tree.children()) - len(scalar_args)
        directions = self.in_avals[len(self.in_avals) - k:]
        placeholders = [np.full(a.shape, _const(0, a.dtype), dtype=object) for a in directions]
        flat, one, keep = self._inputs((*scalar_args, *placeholders), batched)
        sizes, out_sizes, fixed, per_direction = self._split_by_directions(k)
        n = sum(sizes)
        flat = flat[:-n]
        jaxpr = self.program.jaxpr
        env: dict = dict(zip(jaxpr.constvars, self.program.consts, strict=True))
        env.update(zip(jaxpr.invars[:-n], flat, strict=True))
        _replay_eqns(fixed, env, keep, one)
        shape = np.broadcast_shapes(*[np.shape(v) for v in flat if not _is_const(v)])
        dtypes = _flat_dtypes(self.out_avals)
        results = []
        first_in, first_out = len(jaxpr.invars) - n, 0
        for b in range(k):
            d_vars = jaxpr.invars[first_in: first_in + sizes[b]]
            outs = list(range(first_out, first_out + out_sizes[b]))
            first_in, first_out = first_in + sizes[b], first_out + out_sizes[b]

            def body(j, columns, d_vars=d_vars, outs=outs, eqns=per_direction[b]):
                env_j = dict(env)
                env_j.update((v, (j == i).astype(v.aval.dtype)) for i, v in enumerate(d_vars))
                _replay_eqns(eqns, env_j, keep, one)
                vals = [self._output(o, _read(env_j, jaxpr.outvars[o]), one) for o in outs]
                return [lax.dynamic_update_index_in_dim(
                            c, jnp.broadcast_to(_materialise(v, dtypes[o]), shape), j, 0)
                        for c, v, o in zip(columns, vals, outs, strict=True)]

            init = [jnp.zeros((sizes[b], *shape), dtypes[o]) for o in outs]
            results.append(lax.fori_loop(0, sizes[b], body, init))
        return results

    def _split_by_directions(self, k: int) -> tuple[list, list, list, list[list]]:
        """For the last ``k`` inputs as directions (one array each) and the ``k`` outputs:
        their sizes, the program's operations that read no direction, and for each
        direction those that read it (directly or through others), each in program order.
        Refuses an operation that reads two directions, or an output that reads another
        output's direction."""
        if k not in self._splits:
            sizes = [math.prod(a.shape) for a in self.in_avals[len(self.in_avals) - k:]]
            out_sizes = [math.prod(a.shape) for a in self.out_avals]
            if len(out_sizes) != k:
                raise ValueError(f"on_unit_vectors: {k} directions but {len(out_sizes)} "
                                 "outputs")
            jaxpr = self.program.jaxpr
            block_of: dict = {}
            start = len(jaxpr.invars) - sum(sizes)
            for b, size in enumerate(sizes):
                block_of.update((v, b) for v in jaxpr.invars[start: start + size])
                start += size
            fixed: list = []
            per_block: list[list] = [[] for _ in sizes]
            for eqn in jaxpr.eqns:
                blocks = {block_of[v] for v in eqn.invars
                          if not isinstance(v, jex.core.Literal) and v in block_of}
                if not blocks:
                    fixed.append(eqn)
                    continue
                if len(blocks) > 1:
                    raise ValueError("on_unit_vectors: an operation reads two directions")
                (b,) = blocks
                block_of.update((v, b) for v in eqn.outvars)
                per_block[b].append(eqn)
            groups = [b for b, size in enumerate(out_sizes) for _ in range(size)]
            for b, v in zip(groups, jaxpr.outvars, strict=True):
                if not isinstance(v, jex.core.Literal) and block_of.get(v, b) != b:
                    raise ValueError(f"on_unit_vectors: output {b} reads direction "
                                     f"{block_of[v]}")
            self._splits[k] = (sizes, out_sizes, fixed, per_block)
        return self._splits[k]


#: A value read by ``n >= 2`` operations is materialised under ``vmap``
#: (:class:`ScalarFunction`) when ``cost * (n - 1)``, the operations XLA would repeat by
#: recomputing it in every reader, is at least this (``cost``: its operations, counting a
#: value read twice twice). 40: the fastest of the thresholds scanned over the Lie-group VIs
#: of three models, one trajectory and batches (docs/engine.md).
MATERIALIZE_COST = 40


#: Elementwise primitives whose operands commute (for :func:`_simplify_program`).
_COMMUTATIVE = {"add", "add_any", "mul", "max", "min", "and", "or", "eq", "ne"}


def _simplify_program(closed):
    """Common subexpressions merged (the same elementwise primitive on the same operands,
    commutative operands in either order) and dead operations removed: autodiff emits the
    same products in the residual, its tangents and the transposed products several times
    over, and the interpreter emits every operation the jaxpr names, used or not. Fewer
    operations to replay (tracing time) and to compile; the same values bit for bit."""
    jaxpr = closed.jaxpr
    subst: dict = {}
    seen: dict = {}
    eqns = []

    def sub(v):
        return v if isinstance(v, jex.core.Literal) else subst.get(v, v)

    def key(v):
        if isinstance(v, jex.core.Literal):
            return ("literal", str(v.aval.dtype), repr(v.val))
        return ("var", id(v))

    for eqn in jaxpr.eqns:
        invars = [sub(v) for v in eqn.invars]
        name = "add" if eqn.primitive.name == "add_any" else eqn.primitive.name
        if (name in _ELEMENTWISE and len(eqn.outvars) == 1
                and not eqn.outvars[0].aval.shape):
            operands = [key(v) for v in invars]
            if name in _COMMUTATIVE:
                operands.sort()
            k = (name, tuple(sorted((p, repr(val)) for p, val in eqn.params.items())),
                 tuple(operands))
            if k in seen:
                subst[eqn.outvars[0]] = seen[k]
                continue
            seen[k] = eqn.outvars[0]
        elif name == "cond":  # the same branches on the same operands (one angle's cond)
            k = ("cond", str(eqn.params["branches"]), tuple(key(v) for v in invars))
            if k in seen:
                subst.update(zip(eqn.outvars, seen[k], strict=True))
                continue
            seen[k] = eqn.outvars
        eqns.append(eqn.replace(invars=invars))
    outvars = [sub(v) for v in jaxpr.outvars]
    live = {v for v in outvars if not isinstance(v, jex.core.Literal)}
    kept = []
    for eqn in reversed(eqns):  # dead code: nothing here has effects
        if eqn.effects or any(v in live for v in eqn.outvars):
            kept.append(eqn)
            live.update(v for v in eqn.invars if not isinstance(v, jex.core.Literal))
    jaxpr = jaxpr.replace(eqns=kept[::-1], outvars=outvars)
    return jex.core.ClosedJaxpr(jaxpr, closed.consts)


def _flat_dtypes(avals):
    return [a.dtype for a in avals for _ in range(math.prod(a.shape))]


def _materialization_points(jaxpr) -> frozenset:
    """The floating-point variables to compute once: read ``n >= 2`` times, with
    ``cost * (n - 1) >=`` :data:`MATERIALIZE_COST`, ``cost`` the operations XLA would emit for
    it (its expression tree, down to inputs and other such variables)."""
    uses: dict = {}
    for eqn in jaxpr.eqns:
        for v in eqn.invars:
            if not isinstance(v, jex.core.Literal):
                uses[v] = uses.get(v, 0) + 1
    for v in jaxpr.outvars:
        if not isinstance(v, jex.core.Literal):
            uses[v] = uses.get(v, 0) + 1
    cost: dict = {}
    keep = set()
    for eqn in jaxpr.eqns:
        c = 1 + sum(cost.get(v, 0) for v in eqn.invars if not isinstance(v, jex.core.Literal))
        for out in eqn.outvars:
            n = uses.get(out, 0)
            if (n >= 2 and c * (n - 1) >= MATERIALIZE_COST and not out.aval.shape
                    and jnp.issubdtype(out.aval.dtype, jnp.floating)):
                keep.add(out)
                cost[out] = 0
            else:
                cost[out] = c
    return frozenset(keep)


# 2π in three parts (Cody & Waite): the first has 8 significant bits, so ``k P1`` is exact,
# and ``t - k 2π`` is accurate to ~1e-18 |k| absolute. sin(x)/x and cos(x) as polynomials
# in x²: first omitted terms < 1e-18 for |x| <= π/4.
_TWO_PI_1 = 6.28125
_TWO_PI_2 = 0.001935307179586477
_TWO_PI_3 = -1.0033115225336665e-19
_INV_TWO_PI = 0.15915494309189535
_SIN_X = tuple((-1.0) ** n / math.factorial(2 * n + 1) for n in range(9))
_COS_X = tuple((-1.0) ** n / math.factorial(2 * n) for n in range(9))


def _horner(x, coeffs):
    out = coeffs[-1]
    for c in reversed(coeffs[:-1]):
        out = lax.add(lax.mul(out, x), c)
    return out


def sin_cos(t):
    """``(sin t, cos t)`` of float64 ``t`` by arithmetic alone: ``t`` reduced by 2π to
    ``r`` in [-π, π], sine and cosine of ``r/4`` by their Taylor polynomials (9 terms),
    two doublings. Within 1e-15 of ``sin``/``cos`` for ``|t| <= 100`` (tested; measured
    8e-16 up to 1e7); NaN for a non-finite ``t``.

    The batched replay of a scalar program emits its float64 ``sin`` and ``cos`` this
    way: XLA's CPU sine costs some 30 multiply-adds per element (docs/engine.md), and
    the closed forms of :mod:`lgvi_jax.so3` are evaluated even where their Taylor branch
    is selected."""
    # lax operations rather than Python's operators, which go through jax.numpy (a jitted
    # function per operation): the same operations, traced in a fraction of the time.
    mul, add, sub = lax.mul, lax.add, lax.sub
    k = lax.round(mul(t, _INV_TWO_PI), lax.RoundingMethod.TO_NEAREST_EVEN)
    r = sub(sub(sub(t, mul(k, _TWO_PI_1)), mul(k, _TWO_PI_2)), mul(k, _TWO_PI_3))
    x = mul(0.25, r)
    x2 = mul(x, x)
    s1, c1 = mul(x, _horner(x2, _SIN_X)), _horner(x2, _COS_X)
    s2, c2 = mul(mul(2.0, s1), c1), mul(sub(c1, s1), add(c1, s1))
    return mul(mul(2.0, s2), c2), mul(sub(c2, s2), add(c2, s2))


def _replay(closed, flat, keep, one=None):
    """Evaluate a scalar program on scalars (folding with call-site constants)."""
    jaxpr = closed.jaxpr
    env: dict = dict(zip(jaxpr.constvars, closed.consts, strict=True))
    env.update(zip(jaxpr.invars, flat, strict=True))
    _replay_eqns(jaxpr.eqns, env, keep, one)
    return [_read(env, v) for v in jaxpr.outvars]


def _read(env, v):
    if isinstance(v, jex.core.Literal):
        return _const(v.val, v.aval.dtype)
    return env[v]


def _replay_eqns(eqns, env: dict, keep, one) -> None:
    """:func:`_replay`'s loop: evaluate ``eqns`` into ``env`` (variable -> scalar)."""
    trig: dict = {}  # id of an angle -> (its sine, its cosine, the angle), computed once
    for eqn in eqns:
        invals = [_read(env, v) for v in eqn.invars]
        name = eqn.primitive.name
        if (one is not None and name in ("sin", "cos") and not _is_const(invals[0])
                and eqn.outvars[0].aval.dtype == np.float64):
            angle = invals[0]
            if id(angle) not in trig:  # batched: by arithmetic, sine and cosine at once
                trig[id(angle)] = (*sin_cos(angle), angle)
            sine, cosine, _ = trig[id(angle)]
            outs = [sine if name == "sin" else cosine]
        elif name in _ELEMENTWISE and len(eqn.outvars) == 1 and not eqn.outvars[0].aval.shape:
            outs = [_apply(name, eqn.params, invals, eqn.outvars[0].aval.dtype, eqn.primitive)]
        elif name == "cond":
            outs = _replay_cond(eqn, invals, one)
        else:
            subfuns, params = eqn.primitive.get_bind_params(eqn.params)
            outs = eqn.primitive.bind(*subfuns, *[_operand(x) for x in invals], **params)
            outs = outs if eqn.primitive.multiple_results else [outs]
        for var, val in zip(eqn.outvars, outs, strict=True):
            if one is not None and var in keep and not _is_const(val):
                val = _over(val, one)
            env[var] = val


def _over(value, one):
    """``value / one`` (materialisation, :func:`_runtime_one`), bound directly when the
    dtypes agree."""
    return lax.div(value, one) if value.dtype == one.dtype else value / one


def _switch(index, branches, dtypes):
    """``lax.switch`` over ``branches``, thunks returning flat lists of scalars (constants
    among them), each output a JAX value of its dtype in ``dtypes``."""
    return jax.lax.switch(index, [lambda b=b: [_materialise(v, d) for v, d in
                                               zip(b(), dtypes, strict=True)]
                                  for b in branches])


def _replay_cond(eqn, invals, one):
    """A scalar program's ``cond`` (:func:`_eval_eqn`) replayed: with a constant index the
    branch itself; with one index a ``cond`` of the branches replayed; on a batch's vectors
    (an index per member) every branch and a selection per member."""
    index, *ops = invals
    branches = eqn.params["branches"]
    dtypes = [v.aval.dtype for v in eqn.outvars]

    def run(br):
        return _replay(br, ops, frozenset(), one)

    if _is_const(index):
        return run(branches[int(index)])
    lanes = jnp.shape(index)
    if not lanes:  # one member (or each member under vmap)
        return _switch(index, [lambda br=br: run(br) for br in branches], dtypes)

    def vectors(vals):
        return [jnp.broadcast_to(_materialise(v, d), lanes) for v, d in
                zip(vals, dtypes, strict=True)]

    # Every branch and a selection per member, as JAX batches a cond (computing a branch
    # only where some member takes it: faster batches, longer compiles; docs/engine.md).
    results = [vectors(run(br)) for br in branches]
    return [jax.lax.select_n(index, *[r[k] for r in results]) for k in range(len(dtypes))]


def _runtime_one(flat):
    """A one that XLA cannot fold, made from the first traced input ``x`` as ``0 x + 1``
    (XLA keeps ``0 x`` for floating point: it is NaN for a non-finite ``x``, and so is
    then every value of that trajectory, which is failed anyway).

    Dividing a value by it materialises the value: XLA's fusion duplicates cheap
    operations into every kernel that reads them (under ``vmap`` long chains of shared
    scalar arithmetic were recomputed several times over) but not a division, so the
    value becomes one kernel's output. (An ``optimization_barrier`` has no such effect,
    and one around a constant is folded away.)"""
    for x in flat:
        if not _is_const(x) and jnp.issubdtype(jnp.result_type(x), jnp.floating):
            return x * 0 + 1
    return None


def _under_vmap() -> bool:
    return jex.core.unsafe_am_i_under_a_vmap_DO_NOT_USE()


def _concrete(c) -> bool:
    return not isinstance(c, jax.core.Tracer)


#: Scalar programs of :func:`scalarize` and :func:`on_scalars`, weakly keyed by the function
#: (for a bound method its function, with the instance in the inner key), per instance and
#: shapes, dtypes and tree structure of the arguments.
_PROGRAMS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def signature(example) -> tuple:
    """What a scalar program built for ``example`` depends on besides its function: the tree
    structure and every leaf's shape and dtype (a key of the program caches)."""
    leaves, tree = jax.tree.flatten(example)
    return tree, tuple((jnp.shape(x), jnp.result_type(x)) for x in leaves)


def clear_programs() -> None:
    """Forget the programs :func:`program_for` has built."""
    _PROGRAMS.clear()


def program_for(fn: Callable, *example) -> ScalarFunction:
    """``ScalarFunction(fn, *example)``, built once per function, instance (for a bound
    method) and argument shapes, dtypes and tree structure: a rollout otherwise traces the
    same program at every place that calls it (the initial guess of a step four times in a
    batched sweep). Not remembered: programs of functions that close over traced values,
    and functions or instances that cannot be hashed or weakly referenced."""
    owner = getattr(fn, "__func__", fn)
    key = (getattr(fn, "__self__", None), *signature(example))
    try:
        per_fn = _PROGRAMS.setdefault(owner, {})
        found = per_fn.get(key)
    except TypeError:
        return ScalarFunction(fn, *example)
    if found is None:
        found = ScalarFunction(fn, *example)
        if not found.traced_consts:
            per_fn[key] = found
    return found


def scalarize(fn: Callable) -> Callable:
    """``fn`` evaluated through scalar elementwise operations (module docstring): same
    inputs, same outputs, to the order of floating-point sums."""

    @functools.wraps(fn)
    def wrapped(*args):
        sf = program_for(fn, *args)
        outs = sf(*jax.tree.map(split, args))
        return jax.tree.map(lambda o, s: join(o, s.dtype).reshape(s.shape), outs,
                            sf.out_shape, is_leaf=lambda x: isinstance(x, np.ndarray))

    return wrapped


#: The most scalar entries the arguments of :func:`on_scalars` may have (larger arrays are
#: not "small": their products would unroll into thousands of operations).
ON_SCALARS_MAX_ENTRIES = 256


def on_scalars(fn: Callable, *example) -> Callable:
    """``fn`` as a scalar program traced once for arguments shaped like ``example`` and
    replayed with its shared values materialised (as the Newton programs are), or ``fn``
    itself where that does not apply: an operation the interpreter does not support, or
    arguments with more than :data:`ON_SCALARS_MAX_ENTRIES` entries. Called like ``fn``
    with arrays; the same values to the order of floating-point sums. For small
    diagnostics evaluated inside a loop (a model's invariants), whose dozens of 3-vector
    and 3x3 operations otherwise cost a kernel each."""
    if sum(math.prod(jnp.shape(x)) for x in jax.tree.leaves(example)) > ON_SCALARS_MAX_ENTRIES:
        return fn
    try:
        program = program_for(fn, *example)
    except NotImplementedError:
        return fn

    @functools.wraps(fn)
    def wrapped(*args):
        outs = program(*jax.tree.map(split, args), batched=True)
        return jax.tree.map(lambda o, s: join(o, s.dtype).reshape(s.shape), outs,
                            program.out_shape, is_leaf=lambda x: isinstance(x, np.ndarray))

    return wrapped


# ---------------------------------------------------------------------------------------
# Scalar arithmetic for hand-written scalar algorithms (the Newton loops), with the same
# folding and identities as the interpreter.
# ---------------------------------------------------------------------------------------

def _binary(name):
    def op(a, b):
        return _apply(name, {}, [a, b], np.result_type(_dt(a), _dt(b)))
    op.__name__ = name
    return op


add, sub, mul, div = _binary("add"), _binary("sub"), _binary("mul"), _binary("div")
maximum = _binary("max")


def neg(a):
    return _apply("neg", {}, [a], _dt(a))


def absolute(a):
    return _apply("abs", {}, [a], _dt(a))


def logical_and(a, b):
    return _apply("and", {}, [a, b], np.bool_)


def isfinite(a):
    return _apply("is_finite", {}, [a], np.bool_)


def constant(value, dtype) -> np.generic:
    """A known scalar (folds, and simplifies the operations it enters)."""
    return _const(value, dtype)
