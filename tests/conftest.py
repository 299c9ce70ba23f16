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
"""
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
# Off unless JAXCON_TEST_XLA_CACHE=1: writing executables to the persistent cache segfaulted inside JAX's
# put_executable_and_time (jax 0.10.2, XLA CPU) in two full runs on 2026-11-24, in fit and contact tests alike
# (three crashes, not yet reduced to a reproducer).
if os.environ.get("JAXCON_TEST_XLA_CACHE", "0") != "1":
    jax.config.update("jax_enable_compilation_cache", False)


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

