"""Test configuration.

- x64 on, as physics users run JAX. Scenes and `jc.build` then default to float64 (JAX's default float dtype);
  float32 paths are exercised through explicit `dtype=np.float32`. tests/test_precision.py also runs the main
  calls under strict dtype promotion, and a subprocess with x64 off.
- Most of the suite's time is XLA compiling small programs that then run for milliseconds. Two settings cut it;
  neither changes what is computed beyond rounding, and speed is measured by `python -m jaxcon bench`, never
  here. Both are exported through the environment, so the notebook kernels and subprocesses the suite starts
  use them too, and a value already set in the environment is kept.
  - XLA at its lowest optimisation effort (JAX_DISABLE_MOST_OPTIMIZATIONS=1). Tests that run one program for
    many iterations (the long fits) carry `@pytest.mark.optimised` and compile at the default effort. Set
    JAX_DISABLE_MOST_OPTIMIZATIONS=0 to run everything fully optimised.
  - One persistent compilation cache for the run (JAX_COMPILATION_CACHE_DIR, a temporary folder removed at the
    end), shared by the pytest-xdist workers, notebook kernels and subprocesses, so a program that several of
    them build is compiled once.
- Each compiled XLA CPU executable holds about six memory maps, and JAX's jit caches keep every executable that
  a long-lived function (`jc.rollout`, the solvers) compiled, one per model size and setting. A pytest worker
  that runs 300 tests reaches Linux's default limit of 65,530 maps (vm.max_map_count), after which the next
  compile aborts or segfaults inside XLA (seen in full runs on 2026-11-24, in `backend_compile_and_load` and in
  the persistent cache's `put_executable_and_time`). After each test, a worker above `_MAX_MAPS` maps clears
  JAX's caches (`_bound_live_executables`); later tests recompile what they need, or read it from the
  persistent cache.
"""
import gc
import os
import shutil
import tempfile

import pytest

os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:     # the controller makes it; the xdist workers inherit it
    os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="jaxcon-test-xla-cache-")
    os.environ["JAXCON_TEST_CACHE_OWNED"] = str(os.getpid())
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
SUITE_DISABLES_OPTIMIZATIONS = os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"].lower() in ("1", "true", "t", "yes",
                                                                                       "y", "on")
jax.config.update("jax_disable_most_optimizations", SUITE_DISABLES_OPTIMIZATIONS)
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs",
                  float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))
jax.config.update("jax_persistent_cache_min_entry_size_bytes",
                  int(os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"]))

@pytest.fixture(autouse=True)
def _optimised(request):
    """`@pytest.mark.optimised`: this test's programs compile at XLA's default effort (module docstring)."""
    if request.node.get_closest_marker("optimised") is None:
        yield
        return
    jax.config.update("jax_disable_most_optimizations", False)
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", SUITE_DISABLES_OPTIMIZATIONS)


def pytest_unconfigure(config):
    if os.environ.get("JAXCON_TEST_CACHE_OWNED") == str(os.getpid()):
        shutil.rmtree(os.environ["JAX_COMPILATION_CACHE_DIR"], ignore_errors=True)


_MAX_MAPS = 24_000      # well under vm.max_map_count = 65,530; the most one test added was 2,942 (2026-11-24)


def _map_count():
    try:
        with open("/proc/self/maps", "rb") as f:
            return sum(1 for _ in f)
    except OSError:
        return None       # not Linux: no /proc/self/maps to count, nothing done


@pytest.fixture(autouse=True)
def _bound_live_executables():
    """Keeps this worker's compiled executables (and their memory maps) bounded (module docstring)."""
    yield
    n = _map_count()
    if n is not None and n > _MAX_MAPS:
        jax.clear_caches()
        gc.collect()
