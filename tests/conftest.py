"""Test-session setup: two XLA host devices, so that the sharded code paths (sweeps) run
on a CPU-only machine too. Must happen before JAX's backend starts."""

import jax

jax.config.update("jax_num_cpu_devices", 2)
