"""Trace, compile and run time of a cloth rollout's gradient: jaxcon against the plain scatter-add PGS."""
from __future__ import annotations

import time

import jax
import numpy as np

from jaxcon import scenes
from jaxcon.core.sim import _rollout_jit, rollout
from jaxcon.solvers.pgs import PGS


def gradient_compile(small: bool, repeats: int) -> dict:
    """Trace, compile and run time of jax.grad of a cloth rollout's loss (PGS(10), float32, final state) with
    respect to the rest lengths: jaxcon against the plain scatter-add PGS of `_plain_pgs`, in one process,
    alternating (jaxcon, plain, jaxcon, plain) on this noisy host. Full size: 16x16 cloth, 100 steps."""
    from jaxcon.bench.references.plain_pgs import plain_pgs_rollout

    n, steps, it, dt = (4, 5, 10, 1 / 240) if small else (16, 100, 10, 1 / 240)
    model, state = scenes.cloth(n, n, dtype=np.float32)
    t = model.topology

    def jaxcon_loss(rest, stored=False):
        m, solver = model.replace(rest_length=rest), PGS(it, beta=0.2)
        if stored:      # every step's intermediates stored instead of recomputed: the program before that change
            final, _ = _rollout_jit(m, state, solver, dt, steps, steps, None, False)
        else:           # what users get: steps rematerialised in reverse mode
            final, _ = rollout(m, state, solver, dt, steps, save_every=steps)
        return jax.numpy.mean(final.x[..., 2] ** 2)

    def plain_loss(rest):
        x, _, _ = plain_pgs_rollout(state.x, state.v, state.lam, model.inv_mass, rest, t.i, t.j, t.colour,
                                    model.gravity, 0.2, dt, steps, it)
        return jax.numpy.mean(x[..., 2] ** 2)

    losses = {"jaxcon": jaxcon_loss, "plain": plain_loss, "jaxcon_stored": lambda r: jaxcon_loss(r, stored=True)}

    row = {"case": f"cloth_{n}x{n}", "steps": steps, "solver": f"PGS({it})", "dtype": "float32"}
    names = ("jaxcon", "plain") if small else ("jaxcon", "plain", "jaxcon_stored")
    for _ in range(1 if small else 2):
        for name in names:
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
    total = {k: row[f"{k}_trace_s"] + row[f"{k}_compile_s"] for k in ("jaxcon", "plain")}
    row["trace_plus_compile_ratio"] = total["jaxcon"] / total["plain"]
    print(f"\ngradient of a {n}x{n} cloth rollout ({steps} steps, PGS({it}), float32) w.r.t. rest lengths, best of "
          f"{1 if small else 2} alternating round(s): jaxcon trace {row['jaxcon_trace_s']:.2f} s + compile "
          f"{row['jaxcon_compile_s']:.2f} s, "
          f"run {row['jaxcon_run_s'] * 1e3:.1f} ms ({row['jaxcon_stablehlo_ops']} StableHLO ops); plain scatter-add "
          f"PGS trace {row['plain_trace_s']:.2f} s + compile {row['plain_compile_s']:.2f} s, run "
          f"{row['plain_run_s'] * 1e3:.1f} ms ({row['plain_stablehlo_ops']} ops); trace + compile ratio "
          f"{row['trace_plus_compile_ratio']:.2f}")
    if "jaxcon_stored_compile_s" in row:
        print(f"  jaxcon storing every step's intermediates instead: trace {row['jaxcon_stored_trace_s']:.2f} s "
              f"+ compile "
              f"{row['jaxcon_stored_compile_s']:.2f} s, run {row['jaxcon_stored_run_s'] * 1e3:.1f} ms "
              f"({row['jaxcon_stored_stablehlo_ops']} ops)")
    return row
