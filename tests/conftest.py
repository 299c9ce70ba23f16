"""Test configuration: float64 is available (x64 on); float32 paths are exercised through explicit dtypes
(scenes default to float32, `dtype=np.float64` gives float64)."""
import jax

jax.config.update("jax_enable_x64", True)
