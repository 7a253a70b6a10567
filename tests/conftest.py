import atexit
import gc
import os
import shutil
import subprocess
import sys
import tempfile

# XLA's CPU compiler, set before JAX starts its backend. The tests compile
# thousands of programs (3×3 matrices, short loops; counted below, at the
# compilation cache) and run most of them for milliseconds, so compiling
# is most of their time. Three flags make XLA compile them sooner:
# - `--xla_cpu_use_fusion_emitters=false`, XLA's older code generator,
#   which compiles these small programs sooner (benchmarks/xla_codegen.py
#   has the per-program ratios).
# - `--xla_backend_optimization_level=0`, LLVM without its optimisation
#   passes. The compiled code runs slower, so the kernels of the notebooks
#   whose batches run long keep LLVM's passes (`xla_flags_with_llvm_passes`,
#   `KEEP_LLVM_PASSES` in test_notebooks.py).
# - `--xla_cpu_parallel_codegen_split_count=1`, each program's LLVM module
#   compiled in one piece instead of split into parts for parallel code
#   generation, which on 2 cores kept busy by 2 workers only adds work.
# Each of the three shortened the whole suite when it was added.
# Values differ in round-off only, which tests/test_xla_codegen.py checks
# against XLA's defaults. Left alone when XLA_FLAGS is set (`XLA_FLAGS=
# pytest` runs the tests under XLA's defaults). An XLA that does not know a
# flag aborts the process, so they are tried once in a subprocess first;
# the xdist workers and the subprocesses of the end-to-end tests inherit the
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
import pytest  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402

# Python's cyclic garbage collector, less often. Tracing and transforming
# the unit tests' ~2900 programs allocates millions of short-lived
# objects, and with the default thresholds (700, 10, 10) the collector
# keeps walking the workers' large, long-lived heaps (JAX's caches of
# traced and compiled functions); fewer collections shorten the run.
# Collections still run, and the peak memory is the same either way. This
# process and the xdist workers only: the
# notebook kernels and scripts the end-to-end tests start keep Python's
# defaults, as a user's would.
gc.set_threshold(100_000, 50, 1000)

# One persistent compilation cache for the whole test run: the xdist workers,
# the notebook kernels and the benchmark scripts the tests start inherit it
# through the environment, so a program compiled by one of them is loaded,
# not compiled, by the others. JAX stores only programs without host
# callbacks: the small programs of eager operations, not the integrations,
# whose run-time checks (`eqx.error_if`) are callbacks, so about a third of
# the unit tests' programs come from it. A cached program is the compiled one, bit for bit. The controller creates
# the directory before it starts the workers; a fresh one per run, so
# nothing carries over between runs.
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="prkmk-tests-xla-")
    atexit.register(shutil.rmtree, os.environ["JAX_COMPILATION_CACHE_DIR"], ignore_errors=True)
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "-1"
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", float(os.environ.get("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")))
jax.config.update("jax_persistent_cache_min_entry_size_bytes", int(os.environ.get("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "-1")))
jax.config.update("jax_enable_x64", True)
# No Python tracebacks in the compiled programs' debug locations: lowering
# a program writes up to 100 frames per operation into its MLIR, which XLA
# keeps only as metadata (error messages and profiles; the Python errors
# the tests check do not come from it), and lowering without them is
# slightly quicker. Set here, not in the environment, so the notebook kernels and scripts the
# end-to-end tests start keep JAX's defaults.
jax.config.update("jax_include_full_tracebacks_in_locations", False)
jax.config.update("jax_traceback_in_locations_limit", 0)

settings.register_profile("prkmk", deadline=None, max_examples=40, suppress_health_check=[HealthCheck.too_slow], derandomize=True)
settings.load_profile("prkmk")


@pytest.fixture
def xla_flags_with_llvm_passes() -> str:
    """This run's XLA_FLAGS without `LLVM_PASSES_OFF`, for a process whose
    compiled code runs long enough that LLVM's passes pay for themselves."""
    return " ".join(flag for flag in os.environ.get("XLA_FLAGS", "").split() if flag != LLVM_PASSES_OFF)


# The xdist workers take tests in collection order, so a long test
# collected last runs while the other worker, done, waits. test_xla_codegen
# (a subprocess compiling under XLA's defaults, one of the longest tests)
# is collected last and goes first instead, so the workers end together.
RUN_FIRST = ("test_xla_codegen.py",)


def pytest_collection_modifyitems(items):
    items.sort(key=lambda item: item.path.name not in RUN_FIRST)  # stable: otherwise collection order


# An xdist worker ends with `os._exit` once its session is over. By then it
# has sent its last report to the controller (xdist sends "workerfinished"
# in pytest_sessionfinish, a synchronous write to the pipe); a normal exit
# only adds tearing down what the worker built up: JAX's `clean_up` at exit
# drops the backend and the caches of the programs it compiled (over a
# thousand per worker), then the interpreter frees a heap of millions of
# objects, seconds in which the controller waits. Test outcomes and the
# exit status come from the reports, so they are unchanged. Not in a run without xdist (`-n0`), which
# exits as usual.
@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    if os.environ.get("PYTEST_XDIST_WORKER"):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
