r"""Identification of the car-pendulum's parameters from observed trajectories.

**Data.** Observations :math:`(t_i, R_i^{obs}, q_i^{obs})`, ``i = 1..n``, at times on the
integrator's step grid (:math:`t_i = k_i h`), and the initial state
``(R0, omega0, q0, v0)`` (:class:`Observations`, :func:`check_observations`).

**Model.** A rollout of a variational integrator (:func:`~lgvi_jax.simulate.simulate`,
saving every :math:`\gcd(k_i)` steps) from the initial state gives :math:`R_i(\theta),
q_i(\theta)`. The fitted quantities are a subset of ``J, rho_c, m, M, g, omega0, v0``
(:data:`FITTABLE`), each through an unconstrained parameter (:func:`to_unconstrained`):

* ``J``: six log-Cholesky coordinates of the inertia **about the mass centre**
  :math:`J_c` (:mod:`lgvi_jax.inertia`); the model's inertia about the pivot is
  :math:`J = J_c + m(|\rho_c|^2 I - \rho_c\rho_c^\top)` with the current ``m`` and
  ``rho_c``. Every iterate is a physical inertia (positive definite, triangle
  inequalities), whatever the start. When ``J`` is not fitted, ``J_c`` is held fixed;
* ``m``, ``M``: their logarithms (positive); ``g``, ``rho_c``, ``omega0``, ``v0``: as they
  are.

**Loss.** The mean over observations of

.. math::  \ell_i = \tfrac15\left(\tfrac12\|R_i(\theta) - R_i^{obs}\|_F^2 + |q_i(\theta) -
    q_i^{obs}|^2\right),

the mean squared error per observed degree of freedom (3 for the attitude: for
:math:`R^{obs} = R\exp(\hat\xi)`, :math:`\tfrac12\|R - R^{obs}\|_F^2 = |\xi|^2 + O(|\xi|^4)`;
2 for the cart). It is the Gaussian negative log-likelihood for isotropic noise of equal
size on attitude and position, up to constants, so its minimiser is the maximum-likelihood
estimate and its value at the truth is about the noise variance.

**Gradients.** Reverse mode through the rollout; every Newton solve is differentiated by
the implicit function theorem (:mod:`lgvi_jax.newton`), never by unrolling, and
``checkpoint_every`` bounds the memory of long rollouts (:mod:`lgvi_jax.simulate`).

**Optimisers.** ``"gauss-newton"`` (default): Levenberg–Marquardt on the residuals with
forward-mode Jacobians (:class:`_LevenbergMarquardt`; Moré 1978); ``"lbfgs"``: L-BFGS
(optax's memory, SciPy's strong-Wolfe line search; Nocedal & Wright, *Numerical
Optimization*, 2nd ed., ch. 6–7); ``"adam"`` (optax; Kingma & Ba, 2015). The loss is a
small-residual nonlinear least-squares problem in 6–20 unknowns, where Gauss–Newton
converges about quadratically, quasi-Newton superlinearly and Adam only linearly
(``lgvi_jax/studies/identify_inertia.py`` measures them). The first two run their iteration on
the host around one compiled program each (the loss and gradient, or the residuals and
Jacobian), so that a fit compiles the rollout's derivative once.

Levenberg–Marquardt is ours rather than ``optimistix.LevenbergMarquardt`` or
``optimistix.GaussNewton`` because it measured better on these fits: the same final loss
and inertia, in 40 iterations against optimistix's 76, about 60% of the compile time and a
fifth of the run time at h = 0.005, and optimistix's Gauss–Newton does not converge on a
1 s horizon (``docs/identification.md``, ``experiments/compare_least_squares.py``).
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optax
import scipy.optimize

from . import _cache, so3
from .inertia import centroidal_inertia, inertia_from_params, params_from_inertia, pivot_inertia
from .integrators import RIGID_METHODS, AbstractIntegrator
from .models import CarPendulum
from .progress import Progress
from .simulate import simulate

__all__ = [
    "FITTABLE",
    "FitResult",
    "Observations",
    "check_observations",
    "fit",
    "from_unconstrained",
    "load_observations",
    "make_loss",
    "observe",
    "to_unconstrained",
]

#: Quantities that :func:`fit` can estimate.
FITTABLE = ("J", "rho_c", "m", "M", "g", "omega0", "v0")
OPTIMIZERS = ("lbfgs", "adam", "gauss-newton")
#: Default horizon stages of :func:`fit`, as fractions of the observed time span.
HORIZONS = (0.125, 0.25, 0.5, 1.0)
_SHAPES = {"t": None, "R": (3, 3), "q": (2,), "R0": (3, 3), "omega0": (3,), "q0": (2,),
           "v0": (2,)}
SO3_ATOL = 1e-6  # observed attitudes must be rotations to this accuracy (‖RᵀR − I‖_F)


class Observations(eqx.Module):
    """Observed car-pendulum trajectory: times ``t`` (n,), attitudes ``R`` (n, 3, 3), cart
    positions ``q`` (n, 2), and the initial state ``R0`` (3, 3), ``omega0`` (3,), ``q0``
    (2,), ``v0`` (2,) at ``t = 0``. Build with :func:`check_observations`."""

    t: jax.Array
    R: jax.Array
    q: jax.Array
    R0: jax.Array
    omega0: jax.Array
    q0: jax.Array
    v0: jax.Array


def check_observations(data: Mapping[str, Any], dt: float, *,
                       source: str = "observations") -> Observations:
    """Validate observation arrays and return :class:`Observations`.

    ``data`` maps ``t, R, q, R0, omega0, q0, v0`` to arrays. If the four initial-state keys
    are all missing but ``omega`` and ``v`` (per-observation velocities, as written by
    ``lgvi-jax simulate car-pendulum``) are present and ``t[0] = 0``, the initial state is
    the first row. Refused with a ``ValueError`` naming the key: a missing key, a wrong
    shape, a non-finite value, times that are not increasing, negative, or not multiples
    of ``dt`` (to ``1e-9`` relative), no observation after ``t = 0``, and an ``R`` or
    ``R0`` not in SO(3) (``‖RᵀR − I‖_F <= 1e-6``, ``det R > 0``).
    """
    if not (isinstance(dt, (int, float, np.floating)) and math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a finite number > 0, got {dt!r}")
    arrays = {k: np.asarray(v) for k, v in data.items()}
    initial = ("R0", "omega0", "q0", "v0")
    if all(k not in arrays for k in initial) and {"omega", "v", "t", "R", "q"} <= set(arrays):
        t = np.asarray(arrays["t"], dtype=np.float64)
        if t.ndim == 1 and t.size and t[0] == 0.0:
            arrays.update(R0=arrays["R"][0], omega0=arrays["omega"][0], q0=arrays["q"][0],
                          v0=arrays["v"][0])
    missing = [k for k in _SHAPES if k not in arrays]
    if missing:
        raise ValueError(f"{source}: missing key(s) {', '.join(missing)}; need t (n,), "
                         "R (n,3,3), q (n,2), R0 (3,3), omega0 (3,), q0 (2,), v0 (2,)")
    out = {}
    for key in _SHAPES:
        arr = arrays[key]
        if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
            raise ValueError(f"{source}: {key} must hold numbers, got dtype {arr.dtype}")
        out[key] = arr.astype(np.float64)
    n = out["t"].shape[0] if out["t"].ndim == 1 else -1
    if out["t"].ndim != 1 or n < 1:
        raise ValueError(f"{source}: t must have shape (n,) with n >= 1, got {out['t'].shape}")
    for key, shape in _SHAPES.items():
        if shape is None:
            continue
        expected = (n, *shape) if key in ("R", "q") else shape
        if out[key].shape != expected:
            raise ValueError(f"{source}: {key} must have shape {expected}, got "
                             f"{out[key].shape}")
    for key, arr in out.items():
        if not np.all(np.isfinite(arr)):
            bad = int(np.sum(~np.isfinite(arr)))
            raise ValueError(f"{source}: {key} has {bad} non-finite value(s) (NaN or inf)")
    t = out["t"]
    if t[0] < 0 or np.any(np.diff(t) <= 0):
        raise ValueError(f"{source}: t must be increasing and >= 0")
    k = t / dt
    off = np.abs(k - np.round(k))
    if np.any(off > 1e-9 * np.maximum(1.0, np.abs(k))):
        i = int(np.argmax(off))
        raise ValueError(f"{source}: t[{i}] = {float(t[i]):.12g} is not a multiple of dt = "
                         f"{float(dt):g} "
                         "(observations must lie on the integrator's step grid)")
    if np.round(k[-1]) < 1:
        raise ValueError(f"{source}: need at least one observation at t > 0")
    for key in ("R", "R0"):
        R = out[key].reshape(-1, 3, 3)
        err = np.linalg.norm(np.swapaxes(R, -1, -2) @ R - np.eye(3), axis=(-2, -1))
        det = np.linalg.det(R)
        bad = (err > SO3_ATOL) | (det <= 0)
        if np.any(bad):
            i = int(np.argmax(bad))
            where = f"{key}[{i}]" if key == "R" else key
            raise ValueError(f"{source}: {where} is not in SO(3): ‖RᵀR − I‖_F = "
                             f"{err[i]:.3e}, det = {det[i]:.6g} (tolerance {SO3_ATOL:g})")
    # Within tolerance: project the initial attitude onto SO(3) exactly, for the model.
    out["R0"] = np.asarray(so3.project_to_so3(jnp.asarray(out["R0"])))
    return Observations(**{k: jnp.asarray(v) for k, v in out.items()})


def load_observations(path, dt: float) -> Observations:
    """Read and validate an ``.npz`` of observations (:func:`check_observations`)."""
    from ._io import read_npz

    try:
        arrays = read_npz(path)
    except OSError as err:
        raise ValueError(f"{path}: cannot read observations: {err.strerror or err}") from None
    except ValueError as err:
        raise ValueError(f"{path}: cannot read observations: the file {err} (expected an "
                         ".npz with t, R, q, R0, omega0, q0, v0)") from None
    return check_observations(arrays, dt, source=str(path))


def observe(model: CarPendulum, times: Sequence[float], *, noise: float = 0.0,
            seed: int = 0) -> dict[str, np.ndarray]:
    """Synthetic observations from the independent reference
    (:class:`~lgvi_jax.reference.HandReference`: hand-derived equations, SciPy DOP853 at
    ``1e-13``) at ``times``: ``R_obs = R exp(hat(σ ξ))``, ``q_obs = q + σ ζ`` with ``ξ, ζ``
    standard normal (``σ = noise``), so noisy attitudes stay in SO(3). Returns the arrays
    of the ``OBS.npz`` format (the initial state exact, from the model)."""
    from .reference import HandReference

    ref = HandReference(model)
    states = ref.at(np.asarray(times, dtype=np.float64))
    R = states[:, :9].reshape(-1, 3, 3)
    q = states[:, 12:14].copy()
    if noise:
        rng = np.random.default_rng(seed)
        xi = noise * rng.standard_normal((len(R), 3))
        R = np.asarray(R @ np.asarray(jax.vmap(so3.exp)(jnp.asarray(xi))))
        q = q + noise * rng.standard_normal(q.shape)
    return {"t": np.asarray(times, dtype=np.float64), "R": R, "q": q,
            "R0": np.asarray(model.R0), "omega0": np.asarray(model.omega0),
            "q0": np.asarray(model.q0), "v0": np.asarray(model.v0)}


# ---------------------------------------------------------------------------------------
# Parametrisation
# ---------------------------------------------------------------------------------------


def _check_names(names: Sequence[str]) -> tuple[str, ...]:
    names = tuple(names)
    if not names:
        raise ValueError(f"fit: name at least one quantity to fit, from {', '.join(FITTABLE)}")
    for name in names:
        if name not in FITTABLE:
            raise ValueError(f"fit: cannot fit {name!r}; choose from {', '.join(FITTABLE)}")
    if len(set(names)) != len(names):
        raise ValueError(f"fit: a quantity is named twice in {list(names)}")
    return names


def to_unconstrained(names: Sequence[str], model: CarPendulum) -> dict[str, jax.Array]:
    """The unconstrained parameters (a dict pytree) of the quantities ``names`` of
    ``model`` (module docstring); ``omega0``, ``v0`` are the model's initial velocities.
    Raises ``ValueError`` if the model's inertia about the mass centre is not strictly
    physical (then no finite log-Cholesky coordinates exist)."""
    names = _check_names(names)
    params = {}
    for name in names:
        if name == "J":
            J_c = centroidal_inertia(model.J, model.m, model.rho_c)
            try:
                params["J"] = params_from_inertia(J_c)
            except ValueError as err:
                raise ValueError(f"fit: the starting J gives an inertia about the mass centre "
                                 f"J - m(|rho_c|^2 I - rho_c rho_cᵀ) that is not physical: "
                                 f"{err}") from None
        elif name in ("m", "M"):
            params[name] = jnp.log(jnp.asarray(getattr(model, name), jnp.float64))
        else:
            params[name] = jnp.asarray(getattr(model, name), jnp.float64)
    return params


def from_unconstrained(params: Mapping[str, jax.Array], model: CarPendulum) -> CarPendulum:
    """The model with the fitted quantities set from ``params`` and the others from
    ``model`` (``J_c`` held fixed when ``J`` is not fitted). Differentiable; works under
    tracing."""
    m = jnp.exp(params["m"]) if "m" in params else model.m
    M = jnp.exp(params["M"]) if "M" in params else model.M
    rho_c = params.get("rho_c", model.rho_c)
    if "J" in params:
        J_c = inertia_from_params(params["J"])
    else:
        J_c = centroidal_inertia(model.J, model.m, model.rho_c)
    return CarPendulum(
        m=m, M=M, g=params.get("g", model.g), rho_c=rho_c, J=pivot_inertia(J_c, m, rho_c),
        q0=model.q0, v0=params.get("v0", model.v0), R0=model.R0,
        omega0=params.get("omega0", model.omega0),
    )


# ---------------------------------------------------------------------------------------
# Loss
# ---------------------------------------------------------------------------------------


class _Problem(eqx.Module):
    """Everything the loss needs besides the parameters (passed in, never closed over)."""

    model: CarPendulum
    method: AbstractIntegrator
    dt: jax.Array
    index: jax.Array
    R_obs: jax.Array
    q_obs: jax.Array
    weights: jax.Array
    n_steps: int = eqx.field(static=True)
    save_every: int = eqx.field(static=True)
    checkpoint_every: int | None = eqx.field(static=True)


def _problem(obs: Observations, model: CarPendulum, method: AbstractIntegrator, dt: float,
             checkpoint_every: int | None) -> _Problem:
    k = np.round(np.asarray(obs.t) / dt).astype(np.int64)
    stride = int(np.gcd.reduce(k[k > 0]))
    n_steps = int(k[-1])
    if checkpoint_every is not None:
        # Round to a multiple of the stride that divides the number of steps.
        blocks = n_steps // stride
        want = max(1, round(checkpoint_every / stride))
        divisors = [d for d in range(1, blocks + 1) if blocks % d == 0]
        checkpoint_every = stride * min(divisors, key=lambda d: abs(d - want))
    return _Problem(model=model, method=method, dt=jnp.asarray(dt, jnp.float64),
                    index=jnp.asarray(k // stride), R_obs=obs.R, q_obs=obs.q,
                    weights=jnp.ones(k.shape, jnp.float64),
                    n_steps=n_steps, save_every=stride, checkpoint_every=checkpoint_every)


def _loss(params, problem: _Problem) -> jax.Array:
    model = from_unconstrained(params, problem.model)
    state0 = model.default_state()
    traj = simulate(model, problem.method, state0, problem.dt, problem.n_steps,
                    save_every=problem.save_every, checkpoint_every=problem.checkpoint_every)
    R = traj.state.R[problem.index]
    q = traj.state.q[problem.index]
    per_obs = 0.5 * jnp.sum((R - problem.R_obs) ** 2, axis=(-2, -1)) + jnp.sum(
        (q - problem.q_obs) ** 2, axis=-1)
    return jnp.sum(problem.weights * per_obs) / (5.0 * jnp.sum(problem.weights))


def _residuals(params, problem: _Problem) -> jax.Array:
    """The weighted residual vector ``r`` with ``|r|² = loss`` (for Gauss–Newton)."""
    model = from_unconstrained(params, problem.model)
    traj = simulate(model, problem.method, model.default_state(), problem.dt,
                    problem.n_steps, save_every=problem.save_every,
                    checkpoint_every=problem.checkpoint_every)
    dR = (traj.state.R[problem.index] - problem.R_obs).reshape(-1, 9) / jnp.sqrt(2.0)
    dq = traj.state.q[problem.index] - problem.q_obs
    scale = jnp.sqrt(problem.weights / (5.0 * jnp.sum(problem.weights)))[:, None]
    return jnp.concatenate([scale * dR, scale * dq], axis=1).ravel()


def _base_model(obs: Observations, model: CarPendulum | None) -> CarPendulum:
    model = CarPendulum() if model is None else model
    return CarPendulum(m=model.m, M=model.M, g=model.g, rho_c=model.rho_c, J=model.J,
                       q0=obs.q0, v0=obs.v0, R0=obs.R0, omega0=obs.omega0)


def _method(method: str | AbstractIntegrator) -> AbstractIntegrator:
    if isinstance(method, AbstractIntegrator):
        return method
    if method not in RIGID_METHODS:
        raise ValueError(f"fit: unknown method {method!r}; choose from {', '.join(RIGID_METHODS)}")
    return RIGID_METHODS[method]()


def make_loss(obs: Observations, dt: float, *, names: Sequence[str] = ("J",),
              model: CarPendulum | None = None, method: str | AbstractIntegrator = "lgvi",
              checkpoint_every: int | None = None):
    """``(loss, params0, problem)``: the loss ``loss(params, problem)`` (module docstring;
    a pure function of two pytrees, to be ``jit``-ted, ``grad``-ed or ``jvp``-ed), the
    unconstrained starting parameters of ``names`` from ``model`` (default: the paper's
    parameters) and the problem (data, method, step). The initial state is the
    observations'; with ``omega0``/``v0`` in ``names`` those are only starting values."""
    base = _base_model(obs, model)
    params0 = to_unconstrained(names, base)
    return _loss, params0, _problem(obs, base, _method(method), dt, checkpoint_every)


# ---------------------------------------------------------------------------------------
# Fitting
# ---------------------------------------------------------------------------------------


@dataclasses.dataclass
class FitResult:
    """Outcome of :func:`fit`.

    Attributes:
        model: the fitted model (its initial state has the fitted velocities).
        params: the final unconstrained parameters.
        names: the fitted quantities.
        loss_history: the loss before each iteration (over the current stage's horizon),
            and at the end (over the whole horizon).
        loss_initial, loss_final: the loss over the whole horizon at the start and the end.
        iterations: optimiser iterations taken.
        wall_time_s: wall time of the fit, compilation included.
        compile_time_s: of which the time to the end of the first iteration (the
            compilation, the initial loss and the first iteration's evaluations).
        stopped: why it stopped (``"converged"``, ``"iterations"`` or ``"non-finite"``).
        stage_starts: the iteration at which each horizon stage began.
        horizons: each stage's last observation time.
    """

    model: CarPendulum
    params: dict[str, jax.Array]
    names: tuple[str, ...]
    loss_history: list[float]
    iterations: int
    wall_time_s: float
    compile_time_s: float
    stopped: str
    method: str
    optimizer: str
    dt: float
    loss_initial: float = math.nan
    loss_final: float = math.nan
    stage_starts: list[int] = dataclasses.field(default_factory=list)
    horizons: list[float] = dataclasses.field(default_factory=list)

    @property
    def J_c(self) -> np.ndarray:
        """The fitted inertia about the mass centre."""
        m = self.model
        return np.asarray(centroidal_inertia(m.J, m.m, m.rho_c))

    def values(self) -> dict[str, Any]:
        """Physical values of every model parameter (fitted or fixed) as lists."""
        m = self.model
        out = {name: np.asarray(getattr(m, name)).tolist()
               for name in ("J", "rho_c", "m", "M", "g", "omega0", "v0")}
        out["J_c"] = self.J_c.tolist()
        return out

    def to_json(self) -> dict[str, Any]:
        values = self.values()
        return {
            # The fitted quantities at the top level too (J as a 3x3 list, about the pivot).
            **{name: values[name] for name in self.names},
            "fitted": list(self.names),
            "values": values,
            "loss_initial": self.loss_initial,
            "loss_final": self.loss_final,
            "loss_history": self.loss_history,
            "iterations": self.iterations,
            "wall_time_s": self.wall_time_s,
            "compile_time_s": self.compile_time_s,
            "stopped": self.stopped,
            "method": self.method,
            "optimizer": self.optimizer,
            "dt": self.dt,
            "stage_starts": self.stage_starts,
            "horizons_s": self.horizons,
        }


@functools.lru_cache(maxsize=32)
def _optimizer(name: str, lr: float | None):
    # Cached: an optax transformation is a tuple of closures, static under jit and hashed by
    # identity, so a new one for every fit would recompile its update every time.
    if name == "lbfgs":
        # lr scales the initial step of the line search (1 = the quasi-Newton step).
        return _HostLBFGS(scale=1.0 if lr is None else float(lr))
    if name == "adam":
        return optax.adam(1e-2 if lr is None else lr)
    if name == "gauss-newton":
        return _LevenbergMarquardt() if lr is None else _LevenbergMarquardt(damping0=lr)
    raise ValueError(f"fit: unknown optimizer {name!r}; choose from {', '.join(OPTIMIZERS)}")


@eqx.filter_jit
def _value_and_grad(params, problem):
    return jax.value_and_grad(_loss)(params, problem)


@eqx.filter_jit
def _residuals_and_jacobian(params, problem):
    """``(r, ∂r/∂θ)`` with respect to the flattened parameters, one forward-mode pass (the
    primal rides along with the tangents)."""
    flat, unravel = jax.flatten_util.ravel_pytree(params)

    def res(x):
        r = _residuals(unravel(x), problem)
        return r, r

    J, r = jax.jacfwd(res, has_aux=True)(flat)
    return r, J


def _gradient(params, problem):
    """:func:`_value_and_grad`, traced once per cache (the command line's, ``_cache``)."""
    return _cache.call("identify.value_and_grad", _value_and_grad, params, problem)


def _jacobian(params, problem):
    """:func:`_residuals_and_jacobian`, traced once per cache (as :func:`_gradient`)."""
    return _cache.call("identify.residuals_and_jacobian", _residuals_and_jacobian, params,
                       problem)


class _Evaluator:
    """The loss and its gradient at flat parameters through the one compiled
    :func:`_value_and_grad`, remembering the last point (a line search asks for the value
    and then the gradient at the same point)."""

    def __init__(self, unravel, problem):
        self.unravel, self.problem = unravel, problem
        self.x = self.value = self.grad = None

    def __call__(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        if self.x is None or not np.array_equal(x, self.x):
            v, g = _gradient(self.unravel(jnp.asarray(x)), self.problem)
            g = np.asarray(jax.flatten_util.ravel_pytree(g)[0])
            self.x, self.value, self.grad = np.array(x), float(v), g
        return self.value, self.grad

    def f(self, x):
        v = self(x)[0]
        return v if math.isfinite(v) else math.inf

    def fprime(self, x):
        return self(x)[1]


class _HostLBFGSState:
    """Per stage: optax's L-BFGS memory and the loss and gradient at the current
    parameters (``None`` until the stage's first iteration)."""

    def __init__(self, memory):
        self.memory, self.value, self.grad, self.stuck = memory, None, None, False


@dataclasses.dataclass(frozen=True)
class _HostLBFGS:
    """L-BFGS driven from the host: the direction from optax's memory
    (:func:`optax.scale_by_lbfgs`, Nocedal & Wright alg. 7.4), the step length by SciPy's
    line search on the strong Wolfe conditions (:func:`scipy.optimize.line_search`, N&W
    alg. 3.5–3.6; a backtracking Armijo search if it fails), every loss and gradient by
    the one compiled program :func:`_value_and_grad`. ``optax.lbfgs`` runs its line search
    inside the compiled update, which holds two more copies of the rollout's gradient (its
    zoom search and the value-and-gradient reuse): three times the compilation for the same
    iterates' mathematics."""

    scale: float = 1.0

    def init(self, params):
        return _HostLBFGSState(_lbfgs_memory_init(jax.flatten_util.ravel_pytree(params)[0]))

    def step(self, params, state: _HostLBFGSState, problem):
        flat, unravel = jax.flatten_util.ravel_pytree(params)
        x = np.asarray(flat)
        ev = _Evaluator(unravel, problem)
        if state.value is None:
            state.value, state.grad = ev(x)
        else:
            ev.x, ev.value, ev.grad = x, state.value, state.grad
        value, grad = state.value, state.grad
        if not (math.isfinite(value) and np.all(np.isfinite(grad))):
            return params, state, value
        direction, memory = _lbfgs_direction(jnp.asarray(grad), state.memory, jnp.asarray(x))
        d = -self.scale * np.asarray(direction)
        slope = float(grad @ d)
        if not slope < 0:  # not a descent direction: steepest descent
            d, slope = -grad, -float(grad @ grad)
        alpha = None
        if not state.stuck:
            with warnings.catch_warnings():  # a failed search is handled below
                warnings.simplefilter("ignore", RuntimeWarning)  # SciPy's LineSearchWarning
                alpha = scipy.optimize.line_search(
                    ev.f, ev.fprime, x, d, gfk=grad, old_fval=value,
                    maxiter=10)[0]  # first trial: the quasi-Newton step
            if alpha is None:  # Armijo backtracking on finite values
                alpha = 1.0
                for _ in range(10):
                    if ev.f(x + alpha * d) <= value + 1e-4 * alpha * slope:
                        break
                    alpha *= 0.5
                else:
                    alpha = None
        if alpha is None:
            # No decrease along the direction (the loss at its rounding level): stay; the
            # fit's stopping rule sees the loss unchanged.
            state.stuck = True
            return params, state, value
        x_new = x + alpha * d
        new = _HostLBFGSState(memory)
        new.value, new.grad = ev(x_new)
        return unravel(jnp.asarray(x_new)), new, value


@jax.jit
def _lbfgs_memory_init(params):
    return optax.scale_by_lbfgs().init(params)


@jax.jit
def _lbfgs_direction(grad, memory, x):
    return optax.scale_by_lbfgs().update(grad, memory, x)


@eqx.filter_jit
def _adam_step(opt, params, state, problem):
    value, grad = jax.value_and_grad(_loss)(params, problem)
    updates, state = opt.update(grad, state, params)
    return optax.apply_updates(params, updates), state, value


class _LMState:
    """The damping and the residuals and Jacobian at the current parameters (``None``
    until the stage's first iteration)."""

    def __init__(self, damping):
        self.damping, self.r, self.J = damping, None, None


@dataclasses.dataclass(frozen=True)
class _LevenbergMarquardt:
    """Levenberg–Marquardt on the residuals (Moré 1978, with Marquardt's scaling by the
    diagonal of ``JᵀJ``): the step solves ``(JᵀJ + λ diag(JᵀJ)) δ = −Jᵀr``, with the
    Jacobian ``J = ∂r/∂θ`` by forward mode (one tangent per parameter through the rollout
    and the implicit-function-theorem Newton derivatives). A step that lowers the loss is
    taken and ``λ`` divided by 3; otherwise it is refused and ``λ`` multiplied by 4. Near a
    small-residual optimum this is Gauss–Newton: quadratic-like convergence in a few
    iterations. Driven from the host: residuals and Jacobian come from one compiled
    program (:func:`_residuals_and_jacobian`), also at the trial point, whose Jacobian is
    the next iteration's when the step is taken. (Kept over optimistix's solvers by
    measurement: module docstring.)"""

    damping0: float = 1e-3

    def init(self, params):
        return _LMState(self.damping0)

    def step(self, params, state: _LMState, problem):
        flat, unravel = jax.flatten_util.ravel_pytree(params)
        if state.r is None:
            state.r, state.J = (np.asarray(a) for a in _jacobian(params, problem))
        r, J, lam = state.r, state.J, state.damping
        value = float(np.sum(r**2))
        if not (math.isfinite(value) and np.all(np.isfinite(J))):
            return params, state, value
        JtJ = J.T @ J
        A = JtJ + lam * np.diag(np.diag(JtJ) + 1e-300)
        try:
            delta = -np.linalg.solve(A, J.T @ r)
        except np.linalg.LinAlgError:
            delta = -np.linalg.lstsq(A, J.T @ r, rcond=None)[0]
        trial = np.asarray(flat) + delta
        r_new, J_new = (np.asarray(a) for a in _jacobian(unravel(jnp.asarray(trial)), problem))
        value_new = float(np.sum(r_new**2))
        new = _LMState(lam)
        if math.isfinite(value_new) and value_new < value:
            new.damping, new.r, new.J = max(lam / 3.0, 1e-12), r_new, J_new
            return unravel(jnp.asarray(trial)), new, value
        new.damping, new.r, new.J = min(lam * 4.0, 1e12), r, J
        return params, new, value


_loss_jit = eqx.filter_jit(_loss)


def _loss_value(optimizer: str, params, problem) -> float:
    """The loss through the program the optimiser compiles anyway (no extra compilation):
    the gradient's for L-BFGS, the residuals' and Jacobian's for Gauss–Newton."""
    if optimizer == "lbfgs":
        return float(_gradient(params, problem)[0])
    if optimizer == "gauss-newton":
        return float(jnp.sum(_jacobian(params, problem)[0] ** 2))
    return float(_loss_jit(params, problem))


def fit(obs: Observations, dt: float, *, names: Sequence[str] = ("J",),
        model: CarPendulum | None = None, method: str | AbstractIntegrator = "lgvi",
        optimizer: str = "gauss-newton", iterations: int = 300, lr: float | None = None,
        horizons: Sequence[float] = HORIZONS, tol: float = 1e-10, patience: int = 3,
        checkpoint_every: int | None = None, progress: bool = False,
        callback: Callable[[int, float], None] | None = None) -> FitResult:
    """Fit ``names`` (from :data:`FITTABLE`) to the observations ``obs`` by minimising the
    trajectory loss (module docstring) with an optax optimiser.

    **Horizon continuation.** Over a long horizon the loss of a spinning pendulum is far
    from convex: a wrong inertia shifts the phase of the motion, and the loss has local
    minima at phase slips (measured: L-BFGS from the paper's inertia on the full 5 s stalls
    at a 47% error). The fit therefore proceeds in stages: the loss counts only the
    observations up to ``horizons[j] * t_final``, and each stage starts from the previous
    stage's optimum (with a fresh optimiser state), which is inside the basin of the next.
    All stages share one compiled program (the observations are weighted 0 or 1).

    Args:
        obs: validated observations (:func:`check_observations`, :func:`load_observations`).
        dt: the integrator's step; every observation time must be a multiple of it.
        names: the quantities to fit; the others keep ``model``'s values.
        model: the starting (and fixed) parameters; default the paper's ``CarPendulum()``.
            Its initial state is replaced by the observations'.
        method: an integrator or its name (``lgvi``, ``hamel-exact``, ...).
        optimizer: ``"gauss-newton"`` (default), ``"lbfgs"`` or ``"adam"``.
        iterations: the most optimiser iterations in all (>= 1), shared by the stages:
            each stage may use up to the iterations the earlier ones left, less one per
            stage still to come.
        lr: Levenberg–Marquardt's initial damping (default 1e-3), Adam's learning rate
            (default 1e-2), or the scale of L-BFGS's first trial step (default 1, the
            quasi-Newton step).
        horizons: increasing fractions of the observed time span, the last 1.0; ``(1.0,)``
            fits the whole trajectory at once.
        tol, patience: a stage ends when the loss has changed by at most ``tol`` relative
            for ``patience`` successive iterations (``"converged"`` if the last stage does).
        checkpoint_every: checkpoint the rollout about every this many steps (rounded to a
            multiple of the observation stride dividing the horizon); see
            :func:`~lgvi_jax.simulate.simulate`.
        progress: draw a progress bar on a terminal (stderr; silent when not a terminal).
        callback: called as ``callback(iteration, loss)`` after each iteration (the loss of
            the current stage).

    Returns:
        A :class:`FitResult`.
    """
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"fit: iterations must be an integer >= 1, got {iterations!r}")
    if lr is not None and not (math.isfinite(lr) and lr > 0):
        raise ValueError(f"fit: lr must be a finite number > 0, got {lr!r}")
    horizons = tuple(float(h) for h in horizons)
    if (not horizons or horizons[-1] != 1.0 or any(h <= 0 for h in horizons)
            or any(b <= a for a, b in itertools.pairwise(horizons))):
        raise ValueError(f"fit: horizons must increase in (0, 1] and end with 1.0, got "
                         f"{horizons!r}")
    _, params, problem = make_loss(obs, dt, names=names, model=model, method=method,
                                      checkpoint_every=checkpoint_every)
    opt = _optimizer(optimizer, lr)
    step = _adam_step if optimizer == "adam" else type(opt).step
    t_obs = np.asarray(obs.t)
    # Stages whose horizon includes no new observation are skipped (same loss).
    stages = []
    for h in horizons:
        w = (t_obs <= h * t_obs[-1] * (1 + 1e-12)).astype(np.float64)
        if not stages or w.sum() > stages[-1].sum():
            stages.append(w)
    bar = Progress(iterations, label="fit", unit="it", enabled=progress)
    start = time.perf_counter()
    loss_initial = _loss_value(optimizer, params, problem)  # over the whole horizon
    history: list[float] = []
    stage_starts: list[int] = []
    compile_s = 0.0
    stopped = "iterations"
    it = 0
    for j, w in enumerate(stages):
        problem = eqx.tree_at(lambda p: p.weights, problem, jnp.asarray(w))
        # Strong types: optax's initial state has weakly typed scalars, its updated state
        # does not, and the difference would compile the step a second time.
        state = jax.tree.map(lambda x: jnp.asarray(x, x.dtype) if isinstance(x, jax.Array)
                             else x, opt.init(params))
        budget = iterations - it - (len(stages) - 1 - j)
        quiet, stage_history, previous = 0, [], params
        stage_starts.append(it)
        stopped = "iterations"
        for _ in range(max(budget, 1 if j == len(stages) - 1 else 0)):
            new_params, new_state, value = step(opt, params, state, problem)
            value = float(value)  # the loss at ``params``, before this iteration's update
            if it == 0:
                compile_s = time.perf_counter() - start
            if not math.isfinite(value):
                # The last update led to a failed rollout (or the start did): back to the
                # iterate before it, and that update is not counted.
                params, stopped = previous, "non-finite"
                if stage_history:
                    it -= 1
                    history.pop()
                break
            it += 1
            stage_history.append(value)
            history.append(value)
            previous, params, state = params, new_params, new_state
            if len(stage_history) > 1:
                change = abs(stage_history[-2] - stage_history[-1])
                quiet = quiet + 1 if change <= tol * abs(stage_history[-2]) else 0
            bar.label = f"fit {j + 1}/{len(stages)} (loss {value:.3e})"
            bar.advance(1)
            if callback is not None:
                callback(it, value)
            if quiet >= patience:
                stopped = "converged"
                break
        if stopped == "non-finite":
            break
    bar.total = it
    bar.close()
    problem = eqx.tree_at(lambda p: p.weights, problem, jnp.asarray(stages[-1]))
    loss_final = _loss_value(optimizer, params, problem)
    history.append(loss_final)
    wall = time.perf_counter() - start
    return FitResult(
        model=from_unconstrained(params, problem.model), params=params, names=tuple(names),
        loss_history=history, iterations=it, wall_time_s=wall, compile_time_s=compile_s,
        stopped=stopped, method=problem.method.name, optimizer=optimizer, dt=float(dt),
        stage_starts=stage_starts, horizons=[float(t_obs[w > 0][-1]) for w in stages],
        loss_initial=loss_initial, loss_final=loss_final,
    )
