"""``lgvi-jax info``: list the systems, the methods available for each (and how to
compose the symmetric ones) and the parameters ``--set`` accepts, with their
defaults."""

from __future__ import annotations

import argparse


def cmd_info(args: argparse.Namespace) -> int:
    from ..integrators import SCHEMES
    from ..systems import SYSTEMS

    for spec in SYSTEMS.values():
        print(f"{spec.name}: {spec.description}")
        print("  methods:")
        for name, make in spec.methods.items():
            print(f"    {name:<11} {make().describe()}")
        composable = [n for n, make in spec.methods.items() if make().symmetric]
        print(f"    METHOD@ORDER (4, 6, 8) or METHOD@SCHEME ({', '.join(SCHEMES)}): a "
              f"symmetric composition of {', '.join(composable)}")
        print("  --set parameters:")
        for p in spec.parameters:
            default = ",".join(f"{v:g}" for v in p.default)
            print(f"    {p.name:<11} {p.size} number(s), default {default}: {p.doc}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``info`` command to the subcommands ``sub``."""
    info = sub.add_parser("info", help="list systems, methods and parameters")
    info.set_defaults(func=cmd_info)
