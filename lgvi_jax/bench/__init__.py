"""What ``lgvi-jax bench`` runs: :mod:`lgvi_jax.bench.throughput` (the sweep's work for every
VI and composition, one trajectory and a batch, the gradient and the fit) and its reference,
the same discrete equations reduced by hand and compiled by Numba
(:mod:`lgvi_jax.bench.numba_lgvi`, :mod:`lgvi_jax.bench.numba_hamel`; the ``bench`` extra).
Hand-reduced code for one model lives here as a benchmark baseline only, never as a step
of the library."""
