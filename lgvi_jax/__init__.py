"""lgvi_jax: differentiable, structure-preserving integrators for rigid-body mechanics.

Importing the package switches JAX to 64-bit floats (``jax_enable_x64``): long-horizon
energy and momentum checks are meaningless in float32.
"""

import jax

jax.config.update("jax_enable_x64", True)

from . import so3  # noqa: E402

__version__ = "0.1.0"

__all__ = ["__version__", "so3"]
