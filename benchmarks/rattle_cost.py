"""Cost and error of cheap RATTLE settings on the mild double pendulum (0.5, 0.5), float64: median wall time
per simulated second of the compiled rollout (compile timed apart), recording every step and final state only,
and the bob position error at t = 1 s against the SciPy DOP853 reference. Run: python benchmarks/rattle_cost.py
"""
import jax; jax.config.update("jax_enable_x64", True)
import numpy as np, jaxcon as jc
from jaxcon._cli import compile_and_time
from jaxcon import _reference as ref
model, state = jc.scenes.double_pendulum(angles=(0.5, 0.5), dtype=np.float64)
xr = ref.double_pendulum_positions((0.5, 0.5), (1.0, 1.0), (1.0, 1.0), [1.0])[0]
for it in (2, 3, 4):
  for dt in (1/200, 1/250, 1/280, 1/300):
    steps = int(round(1/dt))
    for se in (1, steps):
        f = lambda s, se=se: jc.rollout(model, s, jc.RATTLE(it), dt, steps, save_every=se)[0]
        tc, tr, c = compile_and_time(f, state, repeats=21)
        err = np.max(np.abs(np.asarray(c(state).x[1:]) - xr))
        print(f"RATTLE({it}) dt 1/{steps} save_every {se:4d}: {tr*1e3:.3f} ms per sim-s, {tr/steps*1e6:.2f} us/step, err {err:.2e}", flush=True)
