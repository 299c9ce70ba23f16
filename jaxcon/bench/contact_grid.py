"""Cost per step of all-pairs contacts against the neighbour grid (`collide="grid"`).

    python -m jaxcon bench --contact-grid [n ...]

A square lattice of n discs (radius 1 cm, 1 mm apart) on a floor, under gravity, stepped with PGS(10) at
dt = 1/60 s. Prints the wall time per step of a compiled rollout (compile excluded, best of 3 runs), and the
grid's first call (compile included). The all-pairs column passes every pair as an explicit list
(`all_pairs(n)`): `collide=True` would switch to the grid above `MAX_ALL_PAIRS_PARTICLES` particles, and the
column would then time the grid. It is left out above `ALL_PAIRS_MAX` particles.
"""
from __future__ import annotations

import json
import sys
import time

import jax
import numpy as np

from jaxcon.core.model import build
from jaxcon.core.sim import rollout
from jaxcon.solvers.pgs import PGS


def all_pairs(n: int) -> np.ndarray:
    """[n (n - 1) / 2, 2] every pair of n particles: all pairs as an explicit `collide` list, at any size."""
    return np.stack(np.triu_indices(n, 1), -1)


def scene(n: int, collide):
    """The lattice of n discs; `collide` "all" (every pair, listed) or anything `jc.build` takes."""
    if isinstance(collide, str) and collide == "all":
        collide = all_pairs(n)
    r = 0.01
    cols = int(np.ceil(np.sqrt(n)))
    k = np.arange(n)
    x = np.stack([(k % cols) * 2.1 * r, (k // cols) * 2.1 * r + r + 0.001], -1)
    return build(x, np.ones(n), radius=r, collide=collide, planes=[([0.0, 1.0], 0.0)])


#: Above this many particles the all-pairs column is skipped: n (n - 1) / 2 listed pairs (8.4 million at 4096)
#: take minutes to compile and gigabytes to hold.
ALL_PAIRS_MAX = 2048


def per_step(n: int, collide, steps: int):
    """(seconds of the first call, compile included; best seconds per step of 3 compiled runs) of `steps` steps
    of the lattice with PGS(10) at dt 1/60."""
    model, state = scene(n, collide)
    solver = PGS(10)
    run = jax.jit(lambda s: rollout(model, s, solver, 1 / 60, steps)[0].x)
    t = time.perf_counter()
    run(state).block_until_ready()
    first = time.perf_counter() - t
    best = np.inf
    for _ in range(3):
        t = time.perf_counter()
        run(state).block_until_ready()
        best = min(best, time.perf_counter() - t)
    return first, best / steps


#: `--small`'s sizes and steps (seconds, for the tests).
SMALL_SIZES, SMALL_STEPS = (16, 64), 2


def main(sizes=(256, 1024, 2048), *, small: bool = False, out_path=None):
    """One row per size: all pairs (up to ALL_PAIRS_MAX particles) and the grid, ms per step, and the grid's
    first call (compile and one run of the steps). `small`: SMALL_SIZES (unless `sizes` are given) and
    SMALL_STEPS steps. `out_path`: also write the rows as JSON there. Returns the rows."""
    print(f"{'n':>7} {'all pairs (ms/step)':>20} {'grid (ms/step)':>15} {'grid first call (s)':>20} {'steps':>6}")
    rows = []
    for n in (sizes or (SMALL_SIZES if small else (256, 1024, 2048))):
        steps = SMALL_STEPS if small else 20 if n <= 512 else 5 if n <= 4096 else 2
        a = 1e3 * per_step(n, "all", steps)[1] if n <= ALL_PAIRS_MAX else None
        first, g = per_step(n, "grid", steps)
        a_text = f"{a:20.2f}" if a is not None else f"{'-':>20}"
        print(f"{n:7d} {a_text} {1e3 * g:15.2f} {first:20.1f} {steps:6d}", flush=True)
        rows.append({"n": n, "steps": steps, "all_pairs_ms_per_step": a, "grid_ms_per_step": 1e3 * g,
                     "grid_first_call_s": first})
    if out_path:
        with open(out_path, "w") as f:
            json.dump({"contact_grid": rows, "jax": jax.__version__, "backend": jax.default_backend()}, f,
                      indent=1)
    return rows


if __name__ == "__main__":
    main(tuple(int(a) for a in sys.argv[1:]) or (256, 1024, 2048))
