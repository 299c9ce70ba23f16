"""Cost and error of cheap RATTLE settings on the mild double pendulum (0.5, 0.5), float64: median wall time
per simulated second of the compiled rollout (compile timed apart), recording every step and final state only,
and the bob position error at t = 1 s against the SciPy DOP853 reference.

Run from the repository root: python benchmarks/rattle_cost.py
"""
import jax
import numpy as np

import jaxcon as jc
from jaxcon.bench.references import scipy_ode as ref
from jaxcon.bench.timing import compile_and_time

jax.config.update("jax_enable_x64", True)


def main():
    model, state = jc.scenes.double_pendulum(angles=(0.5, 0.5), dtype=np.float64)
    x_ref = ref.double_pendulum_positions((0.5, 0.5), (1.0, 1.0), (1.0, 1.0), [1.0])[0]
    for iterations in (2, 3, 4):
        for steps in (200, 250, 280, 300):
            dt = 1.0 / steps
            for every in (1, steps):
                def fn(s, every=every):
                    return jc.rollout(model, s, jc.RATTLE(iterations), dt, steps, save_every=every)[0]
                _, t_run, compiled = compile_and_time(fn, state, repeats=21)
                err = np.max(np.abs(np.asarray(compiled(state).x[1:]) - x_ref))
                print(f"RATTLE({iterations}) dt 1/{steps} save_every {every:4d}: {t_run * 1e3:.3f} ms per "
                      f"simulated s, {t_run / steps * 1e6:.2f} us/step, error {err:.2e} m", flush=True)


if __name__ == "__main__":
    main()
