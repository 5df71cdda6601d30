"""Experiment scripts, one per figure or table of the paper.

Installed inside the package as ``lgvi_jax.experiments`` (see ``pyproject.toml``), so that
``lgvi-jax reproduce`` runs them from any install; each also runs as a script:
``python experiments/<name>.py --out DIR``.
"""
