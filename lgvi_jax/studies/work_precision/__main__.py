"""``python -m lgvi_jax.studies.work_precision --out DIR [--quick]``: the study alone."""

import sys

from lgvi_jax.studies import script_main

from . import __doc__, run

if __name__ == "__main__":
    sys.exit(script_main(run, __doc__, quick_help="a few methods, short horizons"))
