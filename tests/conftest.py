"""Configuration only: float64, the four host devices, the hypothesis
profile. The tests compile under XLA's default settings, as users do."""

import jax
from hypothesis import HealthCheck, settings

jax.config.update("jax_enable_x64", True)
# Four host devices: the sharding tests place batches on them; everything
# else runs on the first, as on a one-device machine.
jax.config.update("jax_num_cpu_devices", 4)

settings.register_profile("prkmk", deadline=None, max_examples=40, suppress_health_check=[HealthCheck.too_slow], derandomize=True)
settings.load_profile("prkmk")
