"""Measurements for docs/solvers.md: accuracy and wall time of Direct, SoftStep, RATTLE (and PGS).

Run from the repository root: python benchmarks/solvers_b.py [pendulum|chain|direct]
"""
import sys
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, "tests")

import jaxcon as jc  # noqa: E402
from reference import chain_positions, double_pendulum_positions  # noqa: E402


def wall(fn, repeats=7):
    jax.block_until_ready(fn())  # compile
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), float(np.min(ts))


def run(model, state, solver, dt, steps):
    f = jax.jit(lambda s: jc.rollout(model, s, solver, dt, steps)[0])
    return f, lambda: f(state)


def pendulum():
    model, state = jc.scenes.double_pendulum(angles=(0.5, 0.5), dtype=np.float64)
    ref = double_pendulum_positions((0.5, 0.5), (1.0, 1.0), (1.0, 1.0), [1.0])[0]
    print("| solver | dt (s) | position error at 1 s (m) | wall per simulated s (ms), median (min) |")
    print("|---|---|---|---|")
    cases = [
        (jc.PGS(iterations=10), [1 / 240, 1 / 960]),
        (jc.Direct(beta=0.2), [1 / 240, 1 / 960]),
        (jc.SoftStep(substeps=4), [1 / 60, 1 / 240]),
        (jc.RATTLE(iterations=4), [1 / 100, 1 / 200, 1 / 250, 1 / 400]),
        (jc.RATTLE(iterations=10), [1 / 200, 1 / 250, 1 / 400]),
    ]
    for solver, dts in cases:
        for dt in dts:
            steps = int(round(1 / dt))
            f, call = run(model, state, solver, dt, steps)
            err = np.abs(np.asarray(f(state).x[1:]) - ref).max()
            t, tmin = wall(call, 15)
            print(f"| {solver!r} | 1/{steps} | {err:.2e} | {t * 1e3:.2f} ({tmin * 1e3:.2f}) |")


def chain(dtype=np.float32):
    model, state = jc.scenes.chain(50, 5.0, 0.5, 10.0, dtype=dtype)
    n = 50
    masses = np.full(n, 0.5 / n)
    masses[-1] = 10.0
    tip_ref = chain_positions(np.full(n, 1.5708), np.full(n, 5.0 / n), masses, [2.0])[0, -1]
    print(f"reference tip at 2 s (scipy DOP853 reduced coordinates, rtol=atol=1e-12): {tip_ref}")
    print("| solver | dt (s) | max link stretch over 2 s (%) | tip error at 2 s (m) | wall per simulated s (ms), median (min) |")
    print("|---|---|---|---|---|")
    dt = 1 / 60
    # Box2D's stiffness rule hertz = 0.25 / h (h the substep), and Box2D's default joint softness (60 Hz).
    cases = [(jc.SoftStep(substeps=s, hertz=0.25 * 60 * s, damping_ratio=2.0, relax_iterations=1), dt)
             for s in (16, 32, 64, 128)]
    cases += [(jc.SoftStep(substeps=16, hertz=60.0), dt), (jc.SoftStep(substeps=32, hertz=0.25 * 60 * 32,
                                                                       relax_iterations=4), dt)]
    cases += [(jc.PGS(iterations=1, substeps=64), dt), (jc.Direct(beta=0.2, substeps=8), dt),
              (jc.Direct(beta=0.2, substeps=16), dt)]
    for solver, dt in cases:
        steps = int(round(2 / dt))
        f = jax.jit(lambda s, solver=solver, dt=dt, steps=steps: jc.rollout(model, s, solver, dt, steps))
        final, traj = f(state)
        stretch = float(np.max(np.asarray(jc.violation(model, traj.x)))) * 100
        tip = float(np.linalg.norm(np.asarray(final.x[-1], np.float64) - tip_ref))
        t, tmin = wall(lambda: f(state))
        print(f"| {solver!r} | 1/{steps // 2} | {stretch:.3f} | {tip:.2e} | {t / 2 * 1e3:.2f} ({tmin / 2 * 1e3:.2f}) |")


def direct_scaling():
    print("| links n | wall per step (us, min of 7), tridiagonal | dense |")
    print("|---|---|---|")
    ns, ts = [100, 200, 400, 800], []
    for n in ns:
        model, state = jc.scenes.chain(n, 5.0, 0.5, 10.0)
        steps = 200
        _, call = run(model, state, jc.Direct(), 1 / 240, steps)
        t = wall(call)[1] / steps
        ts.append(t)
        dense = ""
        if n <= 200:
            _, call = run(model, state, jc.Direct(method="dense"), 1 / 240, 10)
            dense = f"{wall(call, 3)[1] / 10 * 1e6:.0f}"
        print(f"| {n} | {t * 1e6:.1f} | {dense} |")
    slope = np.polyfit(np.log(ns), np.log(ts), 1)[0]
    print(f"fitted exponent (tridiagonal, wall per step ~ n^p): p = {slope:.2f}")


if __name__ == "__main__":
    which = sys.argv[1:] or ["pendulum", "chain", "direct"]
    for w in which:
        globals()[{"direct": "direct_scaling"}.get(w, w)]()
