"""``lgvi-jax fit SYSTEM --data OBS.npz``: fit a rigid-body model's parameters (inertia,
mass, ..., initial velocities) to observed attitudes (and, for the car-pendulum, cart
positions) by differentiating a variational integrator's rollout; ``SYSTEM`` is a system
with a rigid-body model (``car-pendulum``, ``heavy-top``, ``free-rigid-body``). Writes the
fit to ``--out`` (.json) and prints it (``--json``: one object). Exit status 1 when a
rollout fails (the last good iterate is written), 2 on bad input."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from .._io import atomic_write_json
from ._common import (
    PROG,
    UsageError,
    _check_writable_file,
    _csv_list,
    _float,
    _positive_int,
    parse_set,
)

#: ``--init`` names of ``lgvi-jax fit car-pendulum`` (the initial state's R0 and q0 come
#: from the data); other systems: ``lgvi_jax.identify.fittable`` of their model.
FIT_INIT_NAMES = ("J", "rho_c", "m", "M", "g", "omega0", "v0")


def fit_systems() -> list[str]:
    """The systems ``fit`` accepts: those whose model is a rigid-body model."""
    from ..models import AbstractRigidBodyModel
    from ..systems import SYSTEMS

    return [name for name, spec in SYSTEMS.items()
            if isinstance(spec.build()[0], AbstractRigidBodyModel)]


def _scene(name: str):
    from ..models import AbstractRigidBodyModel
    from ..systems import SYSTEMS

    valid = fit_systems()
    spec = SYSTEMS.get(name)
    if spec is None or not isinstance(spec.build()[0], AbstractRigidBodyModel):
        why = ("unknown system" if spec is None else
               "no rigid-body model to fit (fit identifies a rigid body from its observed "
               "attitudes) in system")
        raise UsageError(f"{why} {name!r}; valid systems: {', '.join(valid)}")
    return spec


def cmd_fit(args: argparse.Namespace) -> int:
    from ..identify import fit, fittable, load_observations

    spec = _scene(args.system)
    if args.method not in spec.methods:
        raise UsageError(f"--method {args.method!r} is not available for {spec.name}; "
                         f"choose from: {', '.join(spec.methods)}")
    if not math.isfinite(args.dt) or args.dt <= 0:
        raise UsageError(f"--dt must be a finite number > 0, got {args.dt!r}")
    default_model = spec.build()[0]
    valid = fittable(default_model)
    dof = default_model.dof
    names = _csv_list(args.fit, str, "--fit")
    if not names:
        raise UsageError(f"--fit {args.fit!r}: name at least one of {', '.join(valid)}")
    for name in names:
        if name not in valid:
            raise UsageError(f"--fit {name!r}: choose from {', '.join(valid)} (for "
                             f"{spec.name})")
    if len(set(names)) != len(names):
        raise UsageError(f"--fit {args.fit!r}: a name is given twice")
    if args.lr is not None and not (math.isfinite(args.lr) and args.lr > 0):
        raise UsageError(f"--lr must be a finite number > 0, got {args.lr!r}")
    out = Path(args.out)
    if out.suffix != ".json":
        raise UsageError(f"--out {out}: expected a file name ending in .json")
    from_data = ("the initial attitude and cart position come from --data" if dof
                 else "the initial attitude comes from --data")
    init = {}
    for name, value in parse_set(args.init).items():
        if name not in valid:
            raise UsageError(f"--init {name}: choose from {', '.join(valid)} ({from_data})")
        init[name] = value
    for key, size in (("omega0", 3), ("v0", dof)):
        if key in init:
            if key not in names:
                raise UsageError(f"--init {key} is only allowed with --fit {key} (otherwise "
                                 "the observed initial velocity is used)")
            if init[key].size != size:
                raise UsageError(f"--init {key} takes {size} number(s), got "
                                 f"{init[key].size}")
    data = Path(args.data)
    if not data.is_file():
        raise UsageError(f"--data {data}: no such file")
    try:
        obs = load_observations(data, args.dt, dof=dof)
    except ValueError as err:
        raise UsageError(f"--data {err}") from None
    try:
        model, _ = spec.build({k: v for k, v in init.items() if k not in ("omega0", "v0")})
    except ValueError as err:
        raise UsageError(f"--init: {err}") from None
    _check_writable_file(out)
    try:
        result = fit(obs, args.dt, names=names, model=model, method=args.method,
                     optimizer=args.optimizer, iterations=args.iterations, lr=args.lr,
                     progress=not args.json, omega0=init.get("omega0"), v0=init.get("v0"))
    except ValueError as err:
        raise UsageError(str(err)) from None
    report = {
        "system": spec.name,
        "data": str(data),
        **result.to_json(),
        "observations": int(np.size(obs.t)),
        "init": {k: v.tolist() for k, v in init.items()},
    }
    atomic_write_json(out, report)
    if args.json:
        print(json.dumps({k: v for k, v in report.items() if k != "loss_history"}))
    else:
        J = np.asarray(report["values"]["J"])
        rows = "\n".join("  " + "  ".join(f"{x:12.6g}" for x in row) for row in J)
        fitted = ", ".join(f"{k} = {np.round(report['values'][k], 6).tolist()}"
                           for k in names if k != "J")
        about = "about the pivot" if "rho_c" in valid else "about the mass centre"
        print(f"{spec.name} / {result.method}: fitted {', '.join(names)} to "
              f"{report['observations']} observations with {args.optimizer}, "
              f"{result.iterations} iterations ({result.stopped}) in "
              f"{result.wall_time_s:.3g} s\n"
              f"loss {result.loss_initial:.4e} -> {result.loss_final:.4e}")
        if "J" in names:
            print(f"J {about}:\n{rows}")
        if fitted:
            print(fitted)
        print(f"wrote {out}")
    if result.stopped == "non-finite":
        print(f"{PROG} fit: stopped: a rollout failed (non-finite values); wrote the last "
              "good iterate", file=sys.stderr)
        return 1
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``fit`` command to the subcommands ``sub``."""
    fi = sub.add_parser(
        "fit", help="fit parameters (inertia, ...) to an observed trajectory",
        description="Fit a rigid-body model's parameters to observed attitudes (and, for "
        "the car-pendulum, cart positions) by differentiating a variational integrator's "
        "rollout; writes FIT.json. OBS.npz: t (n,), R (n,3,3), R0 (3,3), omega0 (3,); "
        "for car-pendulum also q (n,2), q0 (2,), v0 (2,).")
    fi.add_argument("system", metavar="SYSTEM",
                    help="car-pendulum, heavy-top or free-rigid-body (a system with a "
                    "rigid-body model)")
    fi.add_argument("--data", required=True, metavar="OBS.npz", help="observations (.npz)")
    fi.add_argument("--method", required=True, help="integrator (see `lgvi-jax info`)")
    fi.add_argument("--dt", required=True, type=_float,
                    help="step size; every observation time must be a multiple of it")
    fi.add_argument("--fit", required=True, metavar="NAME[,NAME...]",
                    help="quantities to fit: J, rho_c, m, M, g, omega0, v0 (car-pendulum); "
                    "J, rho_c, m, g, omega0 (heavy-top); J, omega0 (free-rigid-body)")
    fi.add_argument("--init", action="append", metavar="NAME=V1[,V2...]",
                    help="starting value of a fitted quantity, or value of a fixed one "
                    "(repeatable; J: 9 numbers row-major, about the pivot; default: the "
                    "system's values, the paper's for car-pendulum and heavy-top)")
    fi.add_argument("--iterations", type=_positive_int, default=300, metavar="N",
                    help="most optimiser iterations (default 300)")
    fi.add_argument("--lr", type=_float, default=None,
                    help="initial damping (gauss-newton, default 1e-3), learning rate "
                    "(adam, default 1e-2), or first-step scale (lbfgs, default 1)")
    fi.add_argument("--optimizer", choices=["lbfgs", "adam", "gauss-newton"],
                    default="gauss-newton", help="Levenberg-Marquardt with forward-mode "
                    "Jacobians (default), L-BFGS, or optax Adam")
    fi.add_argument("--out", required=True, metavar="FIT.json", help="output file (.json)")
    fi.add_argument("--json", action="store_true",
                    help="print a one-object JSON summary (no progress bar)")
    fi.set_defaults(func=cmd_fit)
