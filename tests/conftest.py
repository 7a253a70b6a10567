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
# - `--xla_cpu_use_fusion_emitters=false`, XLA's older code generator: the
#   whole suite took 5 min 11 s against 7 min 04 s (one run each, one after
#   the other); benchmarks/xla_codegen.py has the per-program ratios.
# - `--xla_backend_optimization_level=0`, LLVM without its optimisation
#   passes: the whole suite took 4 min 21 s and 4 min 24 s (510–515 CPU-s)
#   against 5 min 10 s and 5 min 18 s (605–621 CPU-s) with the first flag
#   alone, two runs each, alternating. The compiled code runs slower (the
#   notebooks' batches up to 3×), so the kernels of the notebooks whose
#   batches run long keep LLVM's passes (`xla_flags_with_llvm_passes`,
#   `KEEP_LLVM_PASSES` in test_notebooks.py).
# - `--xla_cpu_parallel_codegen_split_count=1`, each program's LLVM module
#   compiled in one piece instead of split into parts for parallel code
#   generation, which on 2 cores kept busy by 2 workers only adds work: the
#   whole suite took 4 min 09 s and 4 min 23 s (486–513 CPU-s) against
#   4 min 30 s and 4 min 42 s (524–551 CPU-s) with the two flags above
#   alone, two runs each, alternating; `pytest -m "not end_to_end"` 2 min
#   08 s and 2 min 14 s against 2 min 26 s and 2 min 24 s.
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
# traced and compiled functions). With these, `pytest -m "not end_to_end"`
# took 2 min 41 s and 2 min 35 s (286–288 CPU-s) against 2 min 51 s and
# 2 min 48 s (307–308 CPU-s) with the defaults, alternating. Collections
# still run; test_step.py and test_composed.py in one process peaked at
# 1.91 GB either way. This process and the xdist workers only: the
# notebook kernels and scripts the end-to-end tests start keep Python's
# defaults, as a user's would.
gc.set_threshold(100_000, 50, 1000)

# One persistent compilation cache for the whole test run: the xdist workers,
# the notebook kernels and the benchmark scripts the tests start inherit it
# through the environment, so a program compiled by one of them is loaded,
# not compiled, by the others. JAX stores only programs without host
# callbacks: the small programs of eager operations, not the integrations,
# whose run-time checks (`eqx.error_if`) are callbacks. In a run of
# `pytest -m "not end_to_end"`, 937 of 2902 programs came from it. A
# cached program is the compiled one, bit for bit. The controller creates
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
# the tests check do not come from it). `pytest -m "not end_to_end"`:
# 2 min 52 s and 2 min 48 s (312–314 CPU-s) against 2 min 54 s and
# 2 min 57 s (316–324 CPU-s) with them, alternating; test_step.py and
# test_composed.py in one process: 70.0–70.5 s against 72.2–73.0 s. Set
# here, not in the environment, so the notebook kernels and scripts the
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
# (a subprocess compiling under XLA's defaults, ~6 s) is collected last and
# goes first instead: the two workers' last tests ended 5.8 s and 5.9 s
# apart without this, 0.0 s and 0.1 s apart with it (two runs each).
RUN_FIRST = ("test_xla_codegen.py",)


def pytest_collection_modifyitems(items):
    items.sort(key=lambda item: item.path.name not in RUN_FIRST)  # stable: otherwise collection order


# An xdist worker ends with `os._exit` once its session is over. By then it
# has sent its last report to the controller (xdist sends "workerfinished"
# in pytest_sessionfinish, a synchronous write to the pipe); a normal exit
# only adds tearing down what the worker built up: JAX's `clean_up` at exit
# drops the backend and the caches of the programs it compiled (~1300 each
# in `-m "not end_to_end"`, 2616 in all), then the interpreter frees a heap
# of millions of objects. From the last worker's end of session to the
# controller's took 5.1–5.4 s, 1.2–1.4 s with this. With RUN_FIRST, the
# whole suite took 3 min 29 s – 3 min 51 s against 3 min 34 s – 4 min 04 s
# without either, five runs each, alternating, each run 3–16 s shorter than
# the one paired with it. Test outcomes and the exit status come from the
# reports, so they are unchanged. Not in a run without xdist (`-n0`), which
# exits as usual.
@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    if os.environ.get("PYTEST_XDIST_WORKER"):
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
