r"""Identification of a rigid-body model's parameters from observed trajectories.

Any :class:`~lgvi_jax.models.AbstractRigidBodyModel` (the car-pendulum, the heavy top, the
free rigid body, ...): what is fitted is the model's own parameters and the problem's
initial velocities; the model holds no initial state.

**Data.** Observations :math:`(t_i, R_i^{obs}, q_i^{obs})`, ``i = 1..n``, at times on the
integrator's step grid (:math:`t_i = k_i h`), and the initial state
``(R0, omega0, q0, v0)`` (:class:`Observations`, :func:`check_observations`). The
Euclidean coordinates ``q`` (and ``q0``, ``v0``) are observed only for a model with
``dof > 0`` (the car-pendulum's cart); a ``dof = 0`` model (heavy top, free body) is
observed by its attitudes alone.

**Model.** A rollout of a variational integrator (:func:`~lgvi_jax.simulate.simulate`,
saving every :math:`\gcd(k_i)` steps) of the model :math:`\mathcal M(\theta)` from the
state :math:`\mathcal M(\theta)`.``state_from_velocities(R0, omega0, q0, v0)`` gives
:math:`R_i(\theta), q_i(\theta)`. The fitted quantities (:func:`fittable`) are those of
``J, rho_c, m, M, g`` that are fields of the model, and the initial velocities
``omega0`` and, when ``dof > 0``, ``v0`` (part of the problem's initial state; ``R0`` and
``q0`` are the observed ones). Each goes through an unconstrained parameter
(:func:`to_unconstrained`); :func:`model_and_state` builds ``(model, state0)`` from them:

* ``J``: six log-Cholesky coordinates (:mod:`lgvi_jax.inertia`) of the inertia **about
  the mass centre** :math:`J_c` when the model has a mass ``m`` and a mass-centre offset
  ``rho_c`` (car-pendulum, heavy top), whose inertia about the pivot is then
  :math:`J = J_c + m(|\rho_c|^2 I - \rho_c\rho_c^\top)` with the current ``m`` and
  ``rho_c``; of ``J`` itself otherwise (the free body, whose ``J`` is about its mass
  centre). Every iterate is a physical inertia (positive definite, triangle
  inequalities), whatever the start. When ``J`` is not fitted, ``J_c`` is held fixed;
* ``m``, ``M``: their logarithms (positive); ``g``, ``rho_c``, ``omega0``, ``v0``: as they
  are.

**Loss.** The mean over observations of

.. math::  \ell_i = \tfrac{1}{3 + d}\left(\tfrac12\|R_i(\theta) - R_i^{obs}\|_F^2 +
    |q_i(\theta) - q_i^{obs}|^2\right), \qquad d = \text{dof},

the mean squared error per observed degree of freedom (3 for the attitude: for
:math:`R^{obs} = R\exp(\hat\xi)`, :math:`\tfrac12\|R - R^{obs}\|_F^2 = |\xi|^2 + O(|\xi|^4)`;
``d`` for the Euclidean part, 2 for the cart, so 1/5 for the car-pendulum). It is the
Gaussian negative log-likelihood for isotropic noise of equal size on attitude and
position, up to constants, so its minimiser is the maximum-likelihood estimate and its
value at the truth is about the noise variance.

**Identifiability.** A free body's attitudes determine its inertia only up to a positive
factor: Euler's equation :math:`J\dot\omega = J\omega\times\omega` is unchanged by
:math:`J \to cJ`, so the loss is flat along that direction (Levenberg–Marquardt's damping
keeps its steps finite; the ratios :math:`J/\operatorname{tr}J` are what the data fix).
Gravity breaks the scaling for the heavy top and the car-pendulum.

**Gradients.** Reverse mode through the rollout; every Newton solve is differentiated by
the implicit function theorem (:mod:`lgvi_jax.newton`), never by unrolling, and
``checkpoint_every`` bounds the memory of long rollouts (:mod:`lgvi_jax.simulate`).

**Optimisers.** ``"gauss-newton"`` (default): Levenberg–Marquardt on the residuals with
forward-mode Jacobians (:class:`_LevenbergMarquardt`; Moré 1978); ``"lbfgs"``: L-BFGS
(optax's memory, SciPy's strong-Wolfe line search; Nocedal & Wright, *Numerical
Optimization*, 2nd ed., ch. 6–7); ``"adam"`` (optax; Kingma & Ba, 2015). The loss is a
small-residual nonlinear least-squares problem in 3–20 unknowns, where Gauss–Newton
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

from . import _cache, _gc, so3
from .inertia import centroidal_inertia, inertia_from_params, params_from_inertia, pivot_inertia
from .integrators import RIGID_METHODS, AbstractIntegrator, with_scalar_newton
from .models import AbstractRigidBodyModel, CarPendulum, RigidState
from .progress import Progress
from .simulate import simulate

__all__ = [
    "FITTABLE",
    "MODEL_PARAMETERS",
    "FitResult",
    "Observations",
    "check_observations",
    "fit",
    "fittable",
    "from_unconstrained",
    "load_observations",
    "make_loss",
    "model_and_state",
    "observe",
    "to_unconstrained",
]

#: The model parameters that :func:`fit` can estimate, where they are fields of the model.
MODEL_PARAMETERS = ("J", "rho_c", "m", "M", "g")
#: Quantities that :func:`fit` can estimate for the car-pendulum (``fittable(CarPendulum())``;
#: other models: :func:`fittable`).
FITTABLE = ("J", "rho_c", "m", "M", "g", "omega0", "v0")
OPTIMIZERS = ("lbfgs", "adam", "gauss-newton")
#: Default horizon stages of :func:`fit`, as fractions of the observed time span.
HORIZONS = (0.125, 0.25, 0.5, 1.0)
SO3_ATOL = 1e-6  # observed attitudes must be rotations to this accuracy (‖RᵀR − I‖_F)
#: Keys of the observations that only a model with Euclidean coordinates (dof > 0) has.
_EUCLIDEAN_KEYS = ("q", "q0", "v0")


def _check_model(model: Any, who: str = "fit") -> AbstractRigidBodyModel:
    if not isinstance(model, AbstractRigidBodyModel):
        raise ValueError(f"{who}: the model must be a rigid-body model "
                         f"(AbstractRigidBodyModel), got {type(model).__name__}")
    return model


def _field_names(model: AbstractRigidBodyModel) -> set[str]:
    return {f.name for f in dataclasses.fields(model)}


def fittable(model: AbstractRigidBodyModel) -> tuple[str, ...]:
    """The quantities :func:`fit` can estimate for ``model``: its parameter fields among
    :data:`MODEL_PARAMETERS` (in that order), then the initial velocities ``omega0`` and,
    when ``model.dof > 0``, ``v0``. ``CarPendulum``: :data:`FITTABLE`; ``HeavyTop``:
    ``J, rho_c, m, g, omega0``; ``FreeRigidBody``: ``J, omega0``."""
    fields = _field_names(_check_model(model, "fittable"))
    names = [name for name in MODEL_PARAMETERS if name in fields]
    names.append("omega0")
    if model.dof:
        names.append("v0")
    return tuple(names)


def _about_mass_centre(model: AbstractRigidBodyModel) -> bool:
    """Whether ``J`` is fitted as the inertia about the mass centre plus the parallel-axis
    term (the model has ``m`` and ``rho_c``), rather than as itself."""
    return {"m", "rho_c"} <= _field_names(model)


def _centroidal(model: AbstractRigidBodyModel) -> jax.Array:
    """The model's inertia about its mass centre (its ``J`` when it has no ``m``, ``rho_c``:
    the free body's ``J`` is about its mass centre)."""
    if _about_mass_centre(model):
        return centroidal_inertia(model.J, model.m, model.rho_c)
    return jnp.asarray(model.J, jnp.float64)


class Observations(eqx.Module):
    """Observed rigid-body trajectory: times ``t`` (n,), attitudes ``R`` (n, 3, 3),
    Euclidean coordinates ``q`` (n, dof), and the initial state ``R0`` (3, 3), ``omega0``
    (3,), ``q0`` (dof,), ``v0`` (dof,) at ``t = 0`` (for the car-pendulum dof = 2: the cart;
    for a model without Euclidean coordinates ``q``, ``q0``, ``v0`` are empty). Build with
    :func:`check_observations`."""

    t: jax.Array
    R: jax.Array
    q: jax.Array
    R0: jax.Array
    omega0: jax.Array
    q0: jax.Array
    v0: jax.Array

    @property
    def dof(self) -> int:
        """The number of observed Euclidean coordinates."""
        return int(jnp.shape(self.q0)[-1])


def _shapes(dof: int) -> dict[str, tuple[int, ...] | None]:
    """The observation keys and shapes for a model with ``dof`` Euclidean coordinates
    (``None``: the times; ``R`` and ``q`` with a leading axis of observations)."""
    shapes: dict[str, tuple[int, ...] | None] = {"t": None, "R": (3, 3)}
    if dof:
        shapes["q"] = (dof,)
    shapes.update(R0=(3, 3), omega0=(3,))
    if dof:
        shapes.update(q0=(dof,), v0=(dof,))
    return shapes


def _format_keys(dof: int) -> str:
    """E.g. ``t (n,), R (n,3,3), q (n,2), R0 (3,3), omega0 (3,), q0 (2,), v0 (2,)``."""
    def shape(key, s):
        if s is None:
            return "(n,)"
        dims = ",".join(map(str, s))
        if key in ("R", "q"):
            return f"(n,{dims})"
        return f"({dims},)" if len(s) == 1 else f"({dims})"

    return ", ".join(f"{k} {shape(k, s)}" for k, s in _shapes(dof).items())


def check_observations(data: Mapping[str, Any], dt: float, *, source: str = "observations",
                       dof: int = 2) -> Observations:
    """Validate observation arrays and return :class:`Observations`.

    ``data`` maps ``t, R, R0, omega0`` and, for a model with ``dof > 0`` Euclidean
    coordinates (default 2: the car-pendulum), ``q, q0, v0`` to arrays; for ``dof = 0``
    (heavy top, free body) the keys ``q, q0, v0`` must be absent. If the initial-state
    keys are all missing but ``omega`` (and ``v`` when ``dof > 0``), per-observation
    velocities as written by ``lgvi-jax simulate``, are present and ``t[0] = 0``, the
    initial state is the first row. Refused with a ``ValueError`` naming the key: a
    missing key, an extra Euclidean key for ``dof = 0``, a wrong shape, a non-finite value,
    times that are not increasing, negative, or not multiples of ``dt`` (to ``1e-9``
    relative), no observation after ``t = 0``, and an ``R`` or ``R0`` not in SO(3)
    (``‖RᵀR − I‖_F <= 1e-6``, ``det R > 0``).
    """
    if not (isinstance(dt, (int, float, np.floating)) and math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a finite number > 0, got {dt!r}")
    if isinstance(dof, bool) or not isinstance(dof, (int, np.integer)) or dof < 0:
        raise ValueError(f"dof must be an integer >= 0, got {dof!r}")
    dof = int(dof)
    shapes = _shapes(dof)
    arrays = {k: np.asarray(v) for k, v in data.items()}
    if dof == 0:
        extra = [k for k in _EUCLIDEAN_KEYS if k in arrays]
        if extra:
            raise ValueError(f"{source}: unexpected key(s) {', '.join(extra)}: this system has "
                             "no Euclidean coordinates (dof = 0) and is observed by its "
                             f"attitudes alone; need {_format_keys(0)}")
    initial = [k for k in ("R0", "omega0", "q0", "v0") if k in shapes]
    per_row = {"t", "R", "omega"} | ({"q", "v"} if dof else set())
    if all(k not in arrays for k in initial) and per_row <= set(arrays):
        t = np.asarray(arrays["t"], dtype=np.float64)
        if t.ndim == 1 and t.size and t[0] == 0.0:
            arrays.update(R0=arrays["R"][0], omega0=arrays["omega"][0])
            if dof:
                arrays.update(q0=arrays["q"][0], v0=arrays["v"][0])
    missing = [k for k in shapes if k not in arrays]
    if missing:
        raise ValueError(f"{source}: missing key(s) {', '.join(missing)}; need "
                         f"{_format_keys(dof)}")
    out = {}
    for key in shapes:
        arr = arrays[key]
        if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
            raise ValueError(f"{source}: {key} must hold numbers, got dtype {arr.dtype}")
        out[key] = arr.astype(np.float64)
    n = out["t"].shape[0] if out["t"].ndim == 1 else -1
    if out["t"].ndim != 1 or n < 1:
        raise ValueError(f"{source}: t must have shape (n,) with n >= 1, got {out['t'].shape}")
    for key, shape in shapes.items():
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
    if not dof:
        out.update(q=np.zeros((n, 0)), q0=np.zeros(0), v0=np.zeros(0))
    return Observations(**{k: jnp.asarray(v) for k, v in out.items()})


def load_observations(path, dt: float, *, dof: int = 2) -> Observations:
    """Read and validate an ``.npz`` of observations (:func:`check_observations`) for a
    model with ``dof`` Euclidean coordinates (default 2: the car-pendulum)."""
    from ._io import read_npz

    try:
        arrays = read_npz(path)
    except OSError as err:
        raise ValueError(f"{path}: cannot read observations: {err.strerror or err}") from None
    except ValueError as err:
        keys = ", ".join(_shapes(dof))
        raise ValueError(f"{path}: cannot read observations: the file {err} (expected an "
                         f".npz with {keys})") from None
    return check_observations(arrays, dt, source=str(path), dof=dof)


def observe(model: AbstractRigidBodyModel, times: Sequence[float], *,
            state: RigidState | None = None, noise: float = 0.0, seed: int = 0,
            method: str | AbstractIntegrator | None = None,
            dt: float | None = None) -> dict[str, np.ndarray]:
    """Synthetic observations of ``model`` from ``state`` (default
    ``model.default_state()``) at ``times`` (increasing, the first >= 0), in the
    ``OBS.npz`` format: ``t, R, R0, omega0`` and, when ``model.dof > 0``, ``q, q0, v0``
    (the initial state exact, its velocities from ``state``'s momenta).

    The trajectory: with ``method = None``, an integrator independent of the library's:
    for the car-pendulum the hand-derived equations of
    :class:`~lgvi_jax.systems.car_pendulum.HandReference`, for any other rigid-body model the
    model's
    continuous equations
    (:meth:`~lgvi_jax.models.AbstractRigidBodyModel.vector_field`, ``R`` as 9 numbers),
    both by SciPy's DOP853 at ``rtol = atol = 1e-13``, integrated from one time to the
    next (no interpolation). With ``method`` (an integrator or its name) and ``dt``: that
    integrator's own rollout at step ``dt`` (every time a multiple of ``dt``), so that
    :func:`fit` with the same method and step has the truth as an exact zero of its loss.

    Noise: ``R_obs = R exp(hat(σ ξ))``, ``q_obs = q + σ ζ`` with ``ξ, ζ`` standard normal
    (``σ = noise``), so noisy attitudes stay in SO(3)."""
    _check_model(model, "observe")
    times = np.asarray(times, dtype=np.float64)
    if times.ndim != 1 or times.size == 0 or times[0] < 0 or np.any(np.diff(times) <= 0):
        raise ValueError("observe: times must be a non-empty, increasing 1-D array starting "
                         f"at t >= 0, got {times!r}")
    if state is None:  # the model's defaults, the initial velocities exactly as given
        state = model.default_state()
        omega0, v0 = (np.asarray(x) for x in _initial_velocities(model, None, None))
    else:
        omega0, v0 = (np.asarray(x) for x in model.velocities(state.R, state.mu, state.q,
                                                              state.p))
    R0, q0 = np.asarray(state.R), np.asarray(state.q)
    if method is not None:
        if dt is None:
            raise ValueError("observe: a method needs its step dt")
        R, q = _rollout_at(model, _method(method), state, times, dt)
    elif dt is not None:
        raise ValueError("observe: dt is the step of a given method; without a method the "
                         "reference integrator chooses its own steps")
    elif isinstance(model, CarPendulum):
        R, q = _hand_reference_at(model, R0, omega0, q0, v0, times)
    else:
        R, q = _vector_field_at(model, state, times)
    if noise:
        rng = np.random.default_rng(seed)
        xi = noise * rng.standard_normal((len(R), 3))
        R = np.asarray(R @ np.asarray(jax.vmap(so3.exp)(jnp.asarray(xi))))
        if model.dof:
            q = q + noise * rng.standard_normal(q.shape)
    out = {"t": times, "R": R}
    if model.dof:
        out["q"] = q
    out.update(R0=R0, omega0=omega0)
    if model.dof:
        out.update(q0=q0, v0=v0)
    return out


def _hand_reference_at(model, R0, omega0, q0, v0, times):
    """The car-pendulum's hand-derived reference (:mod:`lgvi_jax.systems.car_pendulum`) from the
    given initial configuration and velocities."""
    from .systems.car_pendulum import HandReference

    ref = HandReference(model, R0=R0, omega0=omega0, q0=q0, v0=v0)
    states = ref.at(times)
    return states[:, :9].reshape(-1, 3, 3), states[:, 12:14].copy()


def _vector_field_at(model, state, times):
    """DOP853 at 1e-13 on the model's continuous equations, step by step between the
    requested times (every returned state an accepted step, as HandReference.at)."""
    from .systems.car_pendulum import dop853_at

    dof = model.dof
    y0 = np.concatenate([np.ravel(np.asarray(state.R)), np.asarray(state.mu),
                         np.asarray(state.q), np.asarray(state.p)]).astype(np.float64)

    @jax.jit
    def rhs(y):
        s = RigidState(R=y[:9].reshape(3, 3), mu=y[9:12], q=y[12:12 + dof], p=y[12 + dof:])
        d = model.vector_field(s)
        return jnp.concatenate([d.R.ravel(), d.mu, d.q, d.p])

    out = dop853_at(lambda _t, x: np.asarray(rhs(x)), y0, times, who="observe")
    return out[:, :9].reshape(-1, 3, 3), out[:, 12:12 + dof].copy()


def _rollout_at(model, method, state, times, dt):
    """The states of ``method``'s rollout at step ``dt`` at ``times`` (multiples of dt)."""
    k = times / dt
    if np.any(np.abs(k - np.round(k)) > 1e-9 * np.maximum(1.0, k)):
        raise ValueError(f"observe: every time must be a multiple of dt = {dt:g}")
    k = np.round(k).astype(np.int64)
    n_steps = int(k[-1])
    if n_steps < 1:
        raise ValueError("observe: need a time after t = 0")
    traj = simulate(model, method, state, dt, n_steps, throw=True)
    R, q = np.asarray(traj.state.R), np.asarray(traj.state.q)
    return R[k], q[k]


# ---------------------------------------------------------------------------------------
# Parametrisation
# ---------------------------------------------------------------------------------------


def _check_names(names: Sequence[str], model: AbstractRigidBodyModel) -> tuple[str, ...]:
    names = tuple(names)
    valid = fittable(model)
    owner = type(model).__name__
    if not names:
        raise ValueError(f"fit: name at least one quantity to fit, from {', '.join(valid)}")
    for name in names:
        if name not in valid:
            raise ValueError(f"fit: cannot fit {name!r} for {owner}; choose from "
                             f"{', '.join(valid)}")
    if len(set(names)) != len(names):
        raise ValueError(f"fit: a quantity is named twice in {list(names)}")
    return names


def _initial_velocities(model, omega0, v0):
    """``(omega0, v0)`` as float64 arrays of shapes (3,), (dof,); a missing one the model's
    default (its class's ``DEFAULT_OMEGA0``/``DEFAULT_V0``, else its default state's)."""
    if omega0 is None or v0 is None:
        s = model.default_state()
        w, v = model.velocities(s.R, s.mu, s.q, s.p)
        omega0 = getattr(type(model), "DEFAULT_OMEGA0", w) if omega0 is None else omega0
        v0 = getattr(type(model), "DEFAULT_V0", v) if v0 is None else v0
    omega0 = jnp.asarray(omega0, jnp.float64)
    v0 = jnp.asarray(v0, jnp.float64)
    for name, value, shape in (("omega0", omega0, (3,)), ("v0", v0, (model.dof,))):
        if value.shape != shape:
            raise ValueError(f"fit: {name} must have shape {shape} for "
                             f"{type(model).__name__}, got {value.shape}")
        if not bool(jnp.all(jnp.isfinite(value))):
            raise ValueError(f"fit: {name} must be finite, got {np.asarray(value).tolist()}")
    return omega0, v0


def to_unconstrained(names: Sequence[str], model: AbstractRigidBodyModel, *,
                     omega0: Any = None, v0: Any = None) -> dict[str, jax.Array]:
    """The unconstrained parameters (a dict pytree) of the quantities ``names`` (from
    :func:`fittable`) of ``model`` (module docstring); ``omega0``, ``v0`` are the starting
    initial velocities (default: those of ``model.default_state()``). Raises
    ``ValueError`` if the model's inertia about the mass centre is not strictly physical
    (then no finite log-Cholesky coordinates exist)."""
    _check_model(model)
    names = _check_names(names, model)
    omega0, v0 = _initial_velocities(model, omega0, v0)
    params = {}
    for name in names:
        if name == "J":
            J_c = _centroidal(model)
            try:
                params["J"] = params_from_inertia(J_c)
            except ValueError as err:
                what = ("an inertia about the mass centre J - m(|rho_c|^2 I - rho_c rho_cᵀ)"
                        if _about_mass_centre(model) else "an inertia")
                raise ValueError(f"fit: the starting J gives {what} that is not "
                                 f"physical: {err}") from None
        elif name in ("m", "M"):
            params[name] = jnp.log(jnp.asarray(getattr(model, name), jnp.float64))
        elif name == "omega0":
            params[name] = omega0
        elif name == "v0":
            params[name] = v0
        else:
            params[name] = jnp.asarray(getattr(model, name), jnp.float64)
    return params


def from_unconstrained(params: Mapping[str, jax.Array],
                       model: AbstractRigidBodyModel) -> AbstractRigidBodyModel:
    """The model with the fitted parameters set from ``params`` and the others from
    ``model`` (``J_c`` held fixed when ``J`` is not fitted); the initial velocities in
    ``params`` are not the model's (:func:`model_and_state`). Differentiable; works under
    tracing."""
    fields = _field_names(model)
    values = {}
    for name in ("m", "M"):
        if name in params:
            values[name] = jnp.exp(params[name])
    for name in ("rho_c", "g"):
        if name in params:
            values[name] = params[name]
    if _about_mass_centre(model):
        J_c = inertia_from_params(params["J"]) if "J" in params else _centroidal(model)
        J = pivot_inertia(J_c, values.get("m", model.m), values.get("rho_c", model.rho_c))
        if "J" in params or values.keys() & {"m", "rho_c"}:
            values["J"] = J
    elif "J" in params:
        values["J"] = inertia_from_params(params["J"])
    names = [n for n in MODEL_PARAMETERS if n in values and n in fields]
    if not names:
        return model
    return eqx.tree_at(lambda mod: [getattr(mod, n) for n in names], model,
                       [jnp.asarray(values[n], jnp.float64) for n in names])


def model_and_state(params: Mapping[str, jax.Array], model: AbstractRigidBodyModel,
                    obs: Observations) -> tuple[AbstractRigidBodyModel, RigidState]:
    """``(model, state0)`` at the unconstrained parameters ``params``: the model
    (:func:`from_unconstrained`) and its state from the observed initial configuration
    ``(obs.R0, obs.q0)`` and the initial velocities, fitted (``params["omega0"]``,
    ``params["v0"]``) or observed. Differentiable; works under tracing."""
    fitted = from_unconstrained(params, model)
    state0 = fitted.state_from_velocities(obs.R0, params.get("omega0", obs.omega0), obs.q0,
                                          params.get("v0", obs.v0))
    return fitted, state0


# ---------------------------------------------------------------------------------------
# Loss
# ---------------------------------------------------------------------------------------


class _Problem(eqx.Module):
    """Everything the loss needs besides the parameters (passed in, never closed over):
    the model's fixed parameters, the initial state's observed configuration and
    velocities (starting values where fitted), the method, the data."""

    model: AbstractRigidBodyModel
    initial: Observations  # R0, omega0, q0, v0 used; its t, R, q are empty
    method: AbstractIntegrator
    dt: jax.Array
    index: jax.Array
    R_obs: jax.Array
    q_obs: jax.Array
    weights: jax.Array
    n_steps: int = eqx.field(static=True)
    save_every: int = eqx.field(static=True)
    checkpoint_every: int | None = eqx.field(static=True)


def _problem(obs: Observations, model: AbstractRigidBodyModel,
             method: str | AbstractIntegrator, dt: float,
             checkpoint_every: int | None) -> _Problem:
    k = np.round(np.asarray(obs.t) / dt).astype(np.int64)
    stride = int(np.gcd.reduce(k[k > 0]))
    n_steps = int(k[-1])
    method = _method(method, n_steps)
    if checkpoint_every is not None:
        # Round to a multiple of the stride that divides the number of steps.
        blocks = n_steps // stride
        want = max(1, round(checkpoint_every / stride))
        divisors = [d for d in range(1, blocks + 1) if blocks % d == 0]
        checkpoint_every = stride * min(divisors, key=lambda d: abs(d - want))
    empty = jnp.zeros((0,), jnp.float64)
    initial = Observations(t=empty, R=jnp.zeros((0, 3, 3)), q=jnp.zeros((0, obs.dof)),
                           R0=obs.R0, omega0=obs.omega0, q0=obs.q0, v0=obs.v0)
    return _Problem(model=model, initial=initial, method=method,
                    dt=jnp.asarray(dt, jnp.float64), index=jnp.asarray(k // stride),
                    R_obs=obs.R, q_obs=obs.q, weights=jnp.ones(k.shape, jnp.float64),
                    n_steps=n_steps, save_every=stride, checkpoint_every=checkpoint_every)


def _rollout(params, problem: _Problem):
    """The saved states of the rollout at the parameters: ``(R, q)`` at the observations."""
    model, state0 = model_and_state(params, problem.model, problem.initial)
    traj = simulate(model, problem.method, state0, problem.dt, problem.n_steps,
                    save_every=problem.save_every, checkpoint_every=problem.checkpoint_every)
    return traj.state.R[problem.index], traj.state.q[problem.index]


def _per_dof(problem: _Problem) -> float:
    """The observed degrees of freedom per observation: 3 (attitude) + dof."""
    return 3.0 + problem.q_obs.shape[-1]


def _loss(params, problem: _Problem) -> jax.Array:
    R, q = _rollout(params, problem)
    per_obs = 0.5 * jnp.sum((R - problem.R_obs) ** 2, axis=(-2, -1)) + jnp.sum(
        (q - problem.q_obs) ** 2, axis=-1)
    return jnp.sum(problem.weights * per_obs) / (_per_dof(problem) * jnp.sum(problem.weights))


def _residuals(params, problem: _Problem) -> jax.Array:
    """The weighted residual vector ``r`` with ``|r|² = loss`` (for Gauss–Newton)."""
    R, q = _rollout(params, problem)
    dR = (R - problem.R_obs).reshape(-1, 9) / jnp.sqrt(2.0)
    dq = q - problem.q_obs
    scale = jnp.sqrt(problem.weights / (_per_dof(problem) * jnp.sum(problem.weights)))[:, None]
    return jnp.concatenate([scale * dR, scale * dq], axis=1).ravel()


def _base_model(obs: Observations, model: AbstractRigidBodyModel | None
                ) -> AbstractRigidBodyModel:
    model = CarPendulum() if model is None else _check_model(model)
    if obs.dof != model.dof:
        raise ValueError(f"fit: the observations have {obs.dof} Euclidean coordinate(s) q, "
                         f"{type(model).__name__} has {model.dof}")
    return model


#: A method given by name fits on scalars (the Lie-group VIs' default engine) from this many
#: steps of the rollout, on small arrays below it: the same solutions and derivatives to
#: round-off, but the derivatives on scalars compile ~3 s longer and each iteration runs
#: ~2.4x faster. Measured (2026-12-06, car-pendulum ``J`` by Gauss–Newton at h = 0.005,
#: CHANGELOG): 1000 steps 7.2 s on scalars against 5.5 s on arrays, 4000 steps 9.4
#: against 9.8 s. An integrator passed as an object is used as it is.
FIT_SCALAR_MIN_STEPS = 3000


def _method(method: str | AbstractIntegrator, n_steps: int | None = None) -> AbstractIntegrator:
    """``method`` as an integrator; a name with ``n_steps`` below
    :data:`FIT_SCALAR_MIN_STEPS` on small arrays."""
    if isinstance(method, AbstractIntegrator):
        return method
    if method not in RIGID_METHODS:
        raise ValueError(f"fit: unknown method {method!r}; choose from {', '.join(RIGID_METHODS)}")
    resolved = RIGID_METHODS[method]()
    if n_steps is not None and n_steps < FIT_SCALAR_MIN_STEPS:
        resolved = with_scalar_newton(resolved, False)
    return resolved


def _starting_obs(obs: Observations, model, omega0, v0) -> Observations:
    """The observations with the given starting values of the fitted initial velocities."""
    if omega0 is None and v0 is None:
        return obs
    omega0, v0 = _initial_velocities(model, obs.omega0 if omega0 is None else omega0,
                                     obs.v0 if v0 is None else v0)
    return eqx.tree_at(lambda o: (o.omega0, o.v0), obs, (omega0, v0))


def make_loss(obs: Observations, dt: float, *, names: Sequence[str] = ("J",),
              model: AbstractRigidBodyModel | None = None,
              method: str | AbstractIntegrator = "lgvi", checkpoint_every: int | None = None,
              omega0: Any = None, v0: Any = None):
    """``(loss, params0, problem)``: the loss ``loss(params, problem)`` (module docstring;
    a pure function of two pytrees, to be ``jit``-ted, ``grad``-ed or ``jvp``-ed), the
    unconstrained starting parameters of ``names`` (:func:`fittable`) from ``model``
    (default: the paper's ``CarPendulum()``; its ``dof`` must be the observations') and
    the problem (data, initial state, method, step). The initial state is the
    observations'; with ``omega0``/``v0`` in ``names`` their values are only starting
    values, the observed ones unless given here."""
    base = _base_model(obs, model)
    _check_names(names, base)
    if omega0 is not None and "omega0" not in names:
        raise ValueError("fit: a starting omega0 is only for a fitted omega0 (otherwise the "
                         "observed initial velocity is used)")
    if v0 is not None and "v0" not in names:
        raise ValueError("fit: a starting v0 is only for a fitted v0 (otherwise the "
                         "observed initial velocity is used)")
    obs = _starting_obs(obs, base, omega0, v0)
    params0 = to_unconstrained(names, base, omega0=obs.omega0, v0=obs.v0)
    return _loss, params0, _problem(obs, base, method, dt, checkpoint_every)


# ---------------------------------------------------------------------------------------
# Fitting
# ---------------------------------------------------------------------------------------


@dataclasses.dataclass
class FitResult:
    """Outcome of :func:`fit`.

    Attributes:
        model: the fitted model (parameters only).
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
        state0: the initial state of the fit: the observed configuration with the fitted
            (or observed) initial velocities, in the fitted model's momenta.
        omega0, v0: those initial velocities (``v0`` empty for a model with ``dof = 0``).
    """

    model: AbstractRigidBodyModel
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
    state0: RigidState | None = None
    omega0: np.ndarray | None = None
    v0: np.ndarray | None = None

    @property
    def J_c(self) -> np.ndarray:
        """The fitted inertia about the mass centre (``J`` itself for a model without a
        mass-centre offset: the free body's)."""
        return np.asarray(_centroidal(self.model))

    def values(self) -> dict[str, Any]:
        """Physical values of every fittable quantity (fitted or fixed) as lists: the
        model's parameters among ``J, rho_c, m, M, g``, the initial velocities ``omega0``
        (and ``v0`` when ``dof > 0``), and ``J_c``."""
        m = self.model
        out = {name: np.asarray(getattr(m, name)).tolist()
               for name in fittable(m) if name in MODEL_PARAMETERS}
        out["omega0"] = np.asarray(self.omega0).tolist()
        if m.dof:
            out["v0"] = np.asarray(self.v0).tolist()
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
@_gc.paused()  # while tracing (lgvi_jax._gc)
def _value_and_grad(params, problem):
    return jax.value_and_grad(_loss)(params, problem)


@eqx.filter_jit
@_gc.paused()  # while tracing (lgvi_jax._gc)
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
@_gc.paused()  # while tracing (lgvi_jax._gc)
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
        model: AbstractRigidBodyModel | None = None,
        method: str | AbstractIntegrator = "lgvi", optimizer: str = "gauss-newton",
        iterations: int = 300, lr: float | None = None,
        horizons: Sequence[float] = HORIZONS, tol: float = 1e-10, patience: int = 3,
        checkpoint_every: int | None = None, progress: bool = False,
        callback: Callable[[int, float], None] | None = None, omega0: Any = None,
        v0: Any = None) -> FitResult:
    """Fit ``names`` (from :func:`fittable`: :data:`FITTABLE` for the car-pendulum) of a
    rigid-body model to the observations ``obs`` by minimising the trajectory loss (module
    docstring).

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
        model: the rigid-body model (:class:`~lgvi_jax.models.AbstractRigidBodyModel`)
            with the starting (and fixed) parameters; default the paper's
            ``CarPendulum()``. Its ``dof`` must be the observations' (``obs.q``'s columns).
        method: an integrator (used as it is) or its name (``lgvi``, ``hamel-exact``,
            ...: solved on scalars from :data:`FIT_SCALAR_MIN_STEPS` steps, on small arrays
            below, whichever fits faster; the same results to round-off).
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
        omega0, v0: starting values of the fitted initial velocities (default: the
            observed ``obs.omega0``, ``obs.v0``); only with that name in ``names``.

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
                                   checkpoint_every=checkpoint_every, omega0=omega0, v0=v0)
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
    fitted, state0 = model_and_state(params, problem.model, problem.initial)
    return FitResult(
        model=fitted, params=params, names=tuple(names),
        loss_history=history, iterations=it, wall_time_s=wall, compile_time_s=compile_s,
        stopped=stopped, method=problem.method.name, optimizer=optimizer, dt=float(dt),
        stage_starts=stage_starts, horizons=[float(t_obs[w > 0][-1]) for w in stages],
        loss_initial=loss_initial, loss_final=loss_final, state0=state0,
        omega0=np.asarray(params.get("omega0", problem.initial.omega0)),
        v0=np.asarray(params.get("v0", problem.initial.v0)),
    )
