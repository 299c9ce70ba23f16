"""Gradient growth with horizon for every solver and scene, and the effect of the remedies on a fit.

    python benchmarks/gradient_growth.py            # growth table (float64), then the fit comparison
    python benchmarks/gradient_growth.py --no-fit   # growth table only
    python benchmarks/gradient_growth.py --json out.json

Growth: norm of d mean(x_T^2) / d rest_length at T = 50, 200, 800, 2000 steps, dt = 1/240 s, float64, via
`jaxcon._gradgrowth.gradient_norms` (exact reverse mode, chunked). Rate: slope of log(norm) between the two
last finite horizons, per second of simulated time.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402

import jaxcon as jc  # noqa: E402
from jaxcon._gradgrowth import gradient_norms, growth_rate  # noqa: E402

DT = 1 / 240
HORIZONS = (50, 200, 800, 2000)


def cases(n=16):
    cloth = jc.scenes.cloth(n, n, dtype=np.float64)
    pen = jc.Penalty(stiffness=1e3, damping=0.5)
    sub = math.ceil(DT / (0.5 * pen.stability_limit(cloth[0])))
    pen = jc.Penalty(stiffness=1e3, damping=0.5, substeps=sub)
    chaotic = jc.scenes.double_pendulum(angles=(1.5708, 1.5708), dtype=np.float64)
    regular = jc.scenes.double_pendulum(angles=(0.1, 0.1), dtype=np.float64)
    c = f"cloth {n}x{n}"
    return [
        (c, "PGS(5) warm start", cloth, jc.PGS(iterations=5)),
        (c, "PGS(5) no warm start", cloth, jc.PGS(iterations=5, warm_start=False)),
        (c, "PGS(5) warm_start_gradient=False", cloth, jc.PGS(iterations=5, warm_start_gradient=False)),
        (c, "PGS(5) warm_start_factor=0.85", cloth, jc.PGS(iterations=5, warm_start_factor=0.85)),
        (c, "PGS(20) warm start", cloth, jc.PGS(iterations=20)),
        (c, "XPBD(10 substeps, 1 it)", cloth, jc.XPBD()),
        (c, "Jacobi(20)", cloth, jc.Jacobi()),
        (c, f"Penalty(k=1e3, c=0.5, {sub} substeps)", cloth, pen),
        ("double pendulum 90/90 deg (chaotic)", "PGS(10)", chaotic, jc.PGS()),
        ("double pendulum 90/90 deg (chaotic)", "PGS(10) warm_start_gradient=False", chaotic,
         jc.PGS(warm_start_gradient=False)),
        ("double pendulum 90/90 deg (chaotic)", "XPBD", chaotic, jc.XPBD()),
        ("double pendulum 6/6 deg (regular)", "PGS(10)", regular, jc.PGS()),
        ("double pendulum 6/6 deg (regular)", "XPBD", regular, jc.XPBD()),
    ]


def growth_table(n=16):
    rows = []
    for scene, name, (model, state), solver in cases(n):
        t0 = time.perf_counter()
        norms = gradient_norms(model, state, solver, DT, HORIZONS)
        wall = time.perf_counter() - t0
        rate = growth_rate(HORIZONS, norms, DT)
        final = jc.rollout(model, state, solver, DT, HORIZONS[-1])[0]
        stretch = float(np.max(np.abs(np.asarray(jc.violation(model, final.x)))))
        rows.append(dict(scene=scene, solver=name, norms=[float(g) for g in norms],
                         rate_per_s=float(rate["slope_per_second"]), violation_T=stretch, wall_s=wall))
        print(f"{scene:38s} {name:40s} " + " ".join(f"{g:9.2e}" for g in norms)
              + f"  rate {rate['slope_per_second']:7.2f}/s  |C|max {stretch:.1e}  ({wall:.0f} s)", flush=True)
    return rows


def fit_table(n=8, steps=300, iters=150):
    """Fit the rest lengths of an n x n cloth from positions observed every 10 steps, from nominal lengths
    (truth: nominal * (1 + U(-5%, 5%))), with each remedy. Reported: relative rest-length error after fit."""
    model, state = jc.scenes.cloth(n, n, dtype=np.float64)
    rng = np.random.default_rng(0)
    true_r = np.asarray(model.rest_length) * (1 + rng.uniform(-0.05, 0.05, model.n_constraints))
    truth = jc._fit._tree_replace(model, {"rest_length": true_r})
    ref_solver = jc.PGS(iterations=50)
    _, traj = jc.rollout(truth, state, ref_solver, DT, steps)
    sample = np.arange(10, steps + 1, 10)
    obs = np.asarray(traj.x)[sample - 1]
    err0 = np.max(np.abs(np.asarray(model.rest_length) / true_r - 1))
    variants = [
        ("PGS(5) warm start, full horizon", jc.PGS(iterations=5), {}),
        ("PGS(5) warm_start_gradient=False", jc.PGS(iterations=5, warm_start_gradient=False), {}),
        ("PGS(5) warm start, windows of 50 steps", jc.PGS(iterations=5), {"window": 50}),
        ("PGS(20) warm start, full horizon", jc.PGS(iterations=20), {}),
    ]
    rows = []
    for name, solver, kw in variants:
        norm = gradient_norms(model, state, solver, DT, [steps])[0]
        t0 = time.perf_counter()
        res = jc.fit(model, state, solver, DT, obs, params=("rest_length",), sample_steps=sample,
                     steps=iters, learning_rate=3e-3, progress=False, **kw)
        wall = time.perf_counter() - t0
        err = np.max(np.abs(np.asarray(res.params["rest_length"]) / true_r - 1))
        rows.append(dict(variant=name, grad_norm_T=float(norm), final_loss=float(np.min(res.history)),
                         max_rel_err=float(err), initial_max_rel_err=float(err0), iterations=res.iterations,
                         wall_s=wall))
        print(f"{name:42s} |grad| at T {norm:9.2e}  loss {np.min(res.history):9.2e}  "
              f"max rel err {err:.4f} (start {err0:.4f})  {res.iterations} it  {wall:.0f} s", flush=True)
    return rows


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("--n", type=int, default=16)
    p.add_argument("--no-fit", action="store_true")
    p.add_argument("--json")
    a = p.parse_args(argv)
    out = {"growth": growth_table(a.n)}
    if not a.no_fit:
        out["fit"] = fit_table()
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
