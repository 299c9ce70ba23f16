"""Trace, compile and run time of a cloth rollout's gradient: jaxcon against the plain scatter-add PGS."""
from __future__ import annotations

import time

import jax
import numpy as np

from jaxcon import scenes
from jaxcon.core.sim import rollout
from jaxcon.solvers.pgs import PGS


def gradient_compile(small: bool, repeats: int) -> dict:
    """Trace, compile and run time of jax.grad of a cloth rollout's loss (PGS(10), float32, final state) with
    respect to the rest lengths: jaxcon in its default layout, jaxcon with one block per colour
    (layout='unrolled'), and the plain scatter-add PGS of `references.plain_pgs`, in one process, alternating on
    this noisy host. Full size: 16x16 cloth, 100 steps (compact by default). The ratio compares jaxcon's default
    with the plain version; "runtime_cost" is the default layout's run time over the unrolled one's, the price
    of the faster compile."""
    from jaxcon.bench.references.plain_pgs import plain_pgs_rollout

    n, steps, it, dt = (4, 5, 10, 1 / 240) if small else (16, 100, 10, 1 / 240)
    model, state = scenes.cloth(n, n, dtype=np.float32)
    unrolled, _ = scenes.cloth(n, n, dtype=np.float32, layout="unrolled")
    t = model.topology

    def jaxcon_loss(rest, m=model):
        final, _ = rollout(m.replace(rest_length=rest), state, PGS(it, beta=0.2), dt, steps, save_every=steps)
        return jax.numpy.mean(final.x[..., 2] ** 2)

    def plain_loss(rest):
        x, _, _ = plain_pgs_rollout(state.x, state.v, state.lam, model.inv_mass, rest, t.i, t.j, t.colour,
                                    model.gravity, 0.2, dt, steps, it)
        return jax.numpy.mean(x[..., 2] ** 2)

    losses = {"jaxcon": jaxcon_loss, "plain": plain_loss,
              "jaxcon_unrolled": lambda r: jaxcon_loss(r, unrolled)}
    row = {"case": f"cloth_{n}x{n}", "steps": steps, "solver": f"PGS({it})", "dtype": "float32",
           "layout": t.layout}
    for _ in range(1 if small else 2):
        for name in losses:
            g = jax.jit(jax.grad(losses[name]))
            t0 = time.perf_counter()
            lowered = g.lower(model.rest_length)
            t1 = time.perf_counter()
            compiled = lowered.compile()
            t2 = time.perf_counter()
            jax.block_until_ready(compiled(model.rest_length))
            runs = []
            for _ in range(max(1, min(repeats, 5))):
                t3 = time.perf_counter()
                jax.block_until_ready(compiled(model.rest_length))
                runs.append(time.perf_counter() - t3)
            for key, val in (("trace_s", t1 - t0), ("compile_s", t2 - t1), ("run_s", float(np.median(runs)))):
                row.setdefault(f"{name}_{key}", []).append(val)
            row[f"{name}_stablehlo_ops"] = lowered.as_text().count(" = ")
    for key in [k for k in row if k.endswith("_s")]:
        row[key] = float(np.min(row[key]))        # the quieter of the alternating rounds
    total = {k: row[f"{k}_trace_s"] + row[f"{k}_compile_s"] for k in losses}
    row["trace_plus_compile_ratio"] = total["jaxcon"] / total["plain"]
    row["unrolled_trace_plus_compile_ratio"] = total["jaxcon_unrolled"] / total["plain"]
    row["runtime_cost"] = row["jaxcon_run_s"] / row["jaxcon_unrolled_run_s"]
    print(f"\ngradient of a {n}x{n} cloth rollout ({steps} steps, PGS({it}), float32) w.r.t. rest lengths, best of "
          f"{1 if small else 2} alternating round(s), trace + compile, run:")
    for name, label in (("jaxcon", f"jaxcon ({t.layout}, the default)"), ("jaxcon_unrolled", "jaxcon (unrolled)"),
                        ("plain", "plain scatter-add PGS")):
        print(f"  {label:32s} {row[f'{name}_trace_s']:.2f} + {row[f'{name}_compile_s']:.2f} s, run "
              f"{row[f'{name}_run_s'] * 1e3:.1f} ms ({row[f'{name}_stablehlo_ops']} StableHLO ops)")
    print(f"  trace + compile against plain: {row['trace_plus_compile_ratio']:.2f} (default), "
          f"{row['unrolled_trace_plus_compile_ratio']:.2f} (unrolled); run time of the default over the unrolled "
          f"layout: {row['runtime_cost']:.2f}x")
    return row
