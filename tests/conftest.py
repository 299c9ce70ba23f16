"""Test configuration: x64 on, as physics users run JAX. Scenes and `jc.build` then default to float64 (JAX's
default float dtype); float32 paths are exercised through explicit `dtype=np.float32`. tests/test_precision.py
also runs the main calls under strict dtype promotion, and a subprocess with x64 off."""
import jax

jax.config.update("jax_enable_x64", True)

