"""`python -m jaxcon demo`: each scene run with a solver that suits it."""
from __future__ import annotations

import dataclasses
import time

import jax
import numpy as np

from jaxcon import scenes
from jaxcon.bench.timing import compile_and_time, machine
from jaxcon.core.sim import rollout
from jaxcon.diagnostics import energy_drift, nan_max, violation
from jaxcon.solvers.direct import Direct
from jaxcon.solvers.pgs import PGS
from jaxcon.solvers.rattle import RATTLE
from jaxcon.solvers.xpbd import XPBD

#: A run "holds" its constraints when its largest relative stretch stays under this; the demo labels the rest.
HOLDS = 0.05


def _scene_list(small: bool):
    """(name, make(dtype), steps, solver that suits the scene, why)."""
    rattle = (RATTLE(), "second order, energy-conserving: a few pendulums need no more")
    heavy = (Direct(substeps=4), "exact multipliers each substep: a 1000:1 mass ratio defeats iterative sweeps")
    cloth = (XPBD(substeps=20), "position-level, many cheap substeps: stiff, redundant cloth")
    if small:
        return [("pendulum", lambda d: scenes.pendulum(angle=0.5, dtype=d), 120, *rattle),
                ("double_pendulum", lambda d: scenes.double_pendulum(angles=(0.5, 0.5), dtype=d), 120, *rattle),
                ("chain_20_1000to1", lambda d: scenes.chain(20, 2.0, 0.2, 10.0, dtype=d), 120, *heavy),
                ("cloth_8x8", lambda d: scenes.cloth(8, 8, dtype=d), 60, *cloth)]
    return [("pendulum", lambda d: scenes.pendulum(angle=0.5, dtype=d), 480, *rattle),
            ("double_pendulum", lambda d: scenes.double_pendulum(angles=(0.5, 0.5), dtype=d), 480, *rattle),
            ("chain_50_1000to1", lambda d: scenes.chain(50, 5.0, 0.5, 10.0, dtype=d), 480, *heavy),
            ("cloth_32x32", lambda d: scenes.cloth(32, 32, dtype=d), 240, *cloth)]


def solver_label(solver) -> str:
    """A solver's name with the options that differ from its defaults, e.g. Direct(substeps=4)."""
    default = type(solver)()
    changed = [f"{f.name}={getattr(solver, f.name)!r}" for f in dataclasses.fields(solver)
               if not np.array_equal(getattr(solver, f.name), getattr(default, f.name))]
    return f"{type(solver).__name__}({', '.join(changed)})"


def _run(model, state, solver, dt, steps):
    fn = lambda s: rollout(model, s, solver, dt, steps)  # noqa: E731
    t_c, t_run, compiled = compile_and_time(fn, state, repeats=3)
    _, tr = compiled(state)
    return t_c, steps / t_run, float(nan_max(violation(model, tr.x))), float(energy_drift(model, state, tr))


def verdict(viol: float) -> str:
    if not np.isfinite(viol):
        return "FAILS: diverged (non-finite positions)"
    return "holds" if viol < HOLDS else f"FAILS: stretched {viol:.0%}"


def demo(args) -> int:
    """Each scene with a solver that suits it, then the same scenes with plain PGS(10) for comparison."""
    dt = 1 / 240
    print(f"jaxcon demo: dt = 1/240 s, float32, {jax.default_backend()} backend, on {machine()['cpu']}")
    head = (f"{'scene':18s} {'solver':20s} {'particles':>9s} {'constr':>7s} {'compile s':>9s} {'steps/s':>9s} "
            f"{'max viol':>9s} {'E drift':>9s}")
    print(head + "\n" + "-" * len(head))
    runs, reasons = [], {}
    for name, make, steps, solver, why in _scene_list(args.small):
        model, state = make(np.float32)
        t_c, rate, viol, drift = _run(model, state, solver, dt, steps)
        runs.append((name, model, state, steps))
        reasons.setdefault(solver_label(solver), why)
        print(f"{name:18s} {solver_label(solver):20s} {model.n_particles:9d} {model.n_constraints:7d} {t_c:9.2f} "
              f"{rate:9.3g} {viol:9.2e} {drift:+9.2e}")
    print("max viol: largest |d - L| / L over constraints and steps; E drift: (E_end - E_0) / max kinetic energy.")
    for label, why in reasons.items():
        print(f"  {label}: {why}")
    pgs = PGS(iterations=10, beta=0.2)
    print("\nThe same scenes with PGS(iterations=10, beta=0.2) (the defaults: textbook sequential impulses), for "
          "comparison:")
    print(f"{'scene':18s} {'compile s':>9s} {'steps/s':>9s} {'max viol':>9s} {'E drift':>9s}  verdict")
    for name, model, state, steps in runs:
        t_c, rate, viol, drift = _run(model, state, pgs, dt, steps)
        print(f"{name:18s} {t_c:9.2f} {rate:9.3g} {viol:9.2e} {drift:+9.2e}  {verdict(viol)}")
    print(f"(a run holds its constraints when every length stays within {HOLDS:.0%} of its rest length; "
          "docs/speed-vs-error.md maps each solver's error against its cost)")
    identification(n=8 if args.small else 20, steps=120 if args.small else 240)
    return 0


def identification(n: int = 20, steps: int = 240) -> None:
    """Hide the rest lengths and beta of a chain, observe 1 mm-noisy positions, recover them with jc.fit."""
    from jaxcon.identification.experiments import chain_identification
    from jaxcon.identification.fit import fit

    dt = 1 / 240
    guess, state, true_L, obs = chain_identification(n=n, beta=0.2, dt=dt, steps=steps, dtype=np.float32)
    print(f"\nsystem identification: a {n}-link chain with hidden rest lengths (each 2/{n} m +- 10%) and "
          f"beta = 0.2, {steps} steps observed with 1 mm noise; fitting from the nominal lengths and beta = 0.3")
    t0 = time.perf_counter()
    res = fit(guess, state, PGS(iterations=10, beta=0.3), dt, obs, ("rest_length", "beta"), optimizer="lm",
              steps=40, patience=5)
    elapsed = time.perf_counter() - t0
    fitted = np.asarray(res.model.rest_length)
    print(f"{'link':>4s} {'true L (m)':>11s} {'fitted (m)':>11s} {'error':>8s}")
    for k in range(n):
        print(f"{k:4d} {true_L[k]:11.5f} {fitted[k]:11.5f} {fitted[k] / true_L[k] - 1:+8.2%}")
    print(f"beta: true 0.2, fitted {float(res.solver.beta):.4f}; worst length error "
          f"{np.max(np.abs(fitted / true_L - 1)):.3%}; {res.iterations} iterations, {elapsed:.1f} s "
          f"(compilation included)")
