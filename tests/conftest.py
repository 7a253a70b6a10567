import atexit
import gc
import os
import shutil
import subprocess
import sys
import tempfile

# XLA's CPU compiler: the settings the README recommends for compile-bound
# work (many small programs, each run briefly, as here), set before JAX
# starts its backend. Values differ from XLA's defaults in round-off only.
# Left alone when XLA_FLAGS is set
# (`XLA_FLAGS= pytest` runs under XLA's defaults). An XLA that does not know
# a flag aborts the process, so they are tried in a subprocess first; the
# xdist workers and the processes the end-to-end tests start inherit the
# choice through the environment.
LLVM_PASSES_OFF = "--xla_backend_optimization_level=0"
FAST_COMPILING_XLA_FLAGS = f"--xla_cpu_use_fusion_emitters=false {LLVM_PASSES_OFF} --xla_cpu_parallel_codegen_split_count=1"
if "XLA_FLAGS" not in os.environ:
    _probe = subprocess.run(
        [sys.executable, "-c", "import jax.numpy as jnp; jnp.zeros(1).block_until_ready()"],
        env=dict(os.environ, XLA_FLAGS=FAST_COMPILING_XLA_FLAGS),
        capture_output=True,
        timeout=120,
    )
    os.environ["XLA_FLAGS"] = FAST_COMPILING_XLA_FLAGS if _probe.returncode == 0 else ""

import jax  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402

# The cyclic garbage collector less often: tracing allocates many
# short-lived objects, and each collection walks JAX's large caches. This
# process and the xdist workers only.
gc.set_threshold(100_000, 50, 1000)

# One persistent compilation cache for the whole test run, shared with the
# xdist workers and the processes they start through the environment, fresh
# for each run. JAX stores only programs without host callbacks (not the
# integrations, whose run-time checks are callbacks).
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="prkmk-tests-xla-")
    atexit.register(shutil.rmtree, os.environ["JAX_COMPILATION_CACHE_DIR"], ignore_errors=True)
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "-1"
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", float(os.environ.get("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")))
jax.config.update("jax_persistent_cache_min_entry_size_bytes", int(os.environ.get("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "-1")))
jax.config.update("jax_enable_x64", True)
# Four host devices: the sharding tests place batches on them; everything
# else runs on the first, as on a one-device machine.
jax.config.update("jax_num_cpu_devices", 4)
# No Python tracebacks in the programs' debug locations, which XLA keeps as
# metadata only; lowering is quicker without them.
jax.config.update("jax_include_full_tracebacks_in_locations", False)
jax.config.update("jax_traceback_in_locations_limit", 0)

settings.register_profile("prkmk", deadline=None, max_examples=40, suppress_health_check=[HealthCheck.too_slow], derandomize=True)
settings.load_profile("prkmk")
