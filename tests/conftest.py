"""Configuration only: float64, the four host devices, the hypothesis
profile, compiled programs freed after each file. The tests compile under
XLA's default settings, as users do."""

import jax
import pytest
from hypothesis import HealthCheck, settings

jax.config.update("jax_enable_x64", True)
# Four host devices: the sharding tests place batches on them; everything
# else runs on the first, as on a one-device machine.
jax.config.update("jax_num_cpu_devices", 4)

settings.register_profile("prkmk", deadline=None, max_examples=40, suppress_health_check=[HealthCheck.too_slow], derandomize=True)
settings.load_profile("prkmk")


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs_after_each_file():
    """A jitted function's cache keeps every program it compiled, and XLA maps
    each program's code in dozens of memory regions. One worker runs half the
    suite, thousands of programs: without this, it reaches Linux's limit on
    memory maps per process (`vm.max_map_count`) and XLA aborts while compiling."""
    yield
    jax.clear_caches()
