"""``python -m lgvi_jax.cli``: the ``lgvi-jax`` console script."""

from . import run

if __name__ == "__main__":  # pragma: no cover
    run()
