"""Compile and run time with XLA's CPU fusion emitters and without them, in the same run.

    python -m jaxcon bench --emitters

XLA compiles a CPU program's fused loops with its MLIR fusion emitters by default. The flag
`XLA_FLAGS=--xla_cpu_use_fusion_emitters=false` sends them through its older elemental emitters instead. The
flag is process-wide and read when the backend starts, so each setting runs in a child process of its own.
Children of the two settings alternate, `ROUNDS` of each. Every child compiles each case at XLA's default
effort (what a user gets) and times `repeats` runs after compilation. A case's compile time is the lower +
compile of a fresh `jax.jit`, with no persistent cache. The table gives the median over the rounds. The
`|diff|` column is the largest difference of the cases' outputs between the settings: rounding, not a change
in what is computed.

The cases are programs users compile again and again:
- a recorded double pendulum rollout (PGS(10), 480 steps);
- a 32x32 cloth (PGS(10), 50 steps);
- the gradient of a 16x16 cloth's loss with respect to its rest lengths (PGS(10), 100 steps);
- the gradient of a billiards shot (4 balls, PGS(10), 120 steps, contacts with times of impact);
- a chunk of the 1024-disc box on the neighbour grid (PGS(10), float32, 15 steps: `--contacts`' program).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np

FLAG = "--xla_cpu_use_fusion_emitters=false"
ROUNDS = 2
CASES = ("double_pendulum_480", "cloth_32x32_50", "cloth_16x16_grad_100", "billiards_grad_120", "disc_box_1024_15")


def _case(name):
    """(function, argument) of one case: jit(function)(argument) is compiled and timed."""
    import jax
    import jax.numpy as jnp

    from jaxcon import scenes
    from jaxcon.core.sim import rollout
    from jaxcon.solvers.pgs import PGS

    if name == "double_pendulum_480":
        model, state = scenes.double_pendulum(angles=(0.5, 0.5), dtype=np.float32)
        return (lambda s: rollout(model, s, PGS(10), 1 / 240, 480)[1].x), state
    if name == "cloth_32x32_50":
        model, state = scenes.cloth(32, 32, dtype=np.float32)
        return (lambda s: rollout(model, s, PGS(10), 1 / 240, 50, save_every=50)[0].x), state
    if name == "cloth_16x16_grad_100":
        model, state = scenes.cloth(16, 16, dtype=np.float32)

        def loss(rest):
            final, _ = rollout(model.replace(rest_length=rest), state, PGS(10), 1 / 240, 100, save_every=100)
            return jnp.mean(final.x[..., 2] ** 2)
        return jax.grad(loss), model.rest_length
    if name == "billiards_grad_120":
        model, state = scenes.billiards(rows=2, friction=0.0)

        def shot(v0):
            final, _ = rollout(model, state.replace(v=state.v.at[0].set(v0)), PGS(10), 1 / 120, 120,
                               save_every=120)
            return jnp.sum(final.x[2] ** 2)
        return jax.grad(shot), jnp.array([3.5, 0.08])
    if name == "disc_box_1024_15":
        model, state = scenes.disc_box(1024, dtype=np.float32)
        return (lambda s: rollout(model, s, PGS(10), 1 / 60, 15, save_every=15)[0].x), state
    raise ValueError(f"unknown case {name!r}")


def child(repeats: int, cases=CASES):
    """Runs in a child process: each case's compile time, median run time and output, and the XLA_FLAGS it ran
    under, as one JSON line."""
    import jax
    jax.config.update("jax_enable_x64", True)        # the cases pick their dtypes themselves
    out = {"xla_flags": os.environ.get("XLA_FLAGS", ""), "backend": jax.default_backend(),
           "disable_most_optimizations": bool(jax.config.values.get("jax_disable_most_optimizations")),
           "compilation_cache_dir": jax.config.values.get("jax_compilation_cache_dir")}
    for name in cases:
        fn, arg = _case(name)
        t0 = time.perf_counter()
        compiled = jax.jit(fn).lower(arg).compile()
        compile_s = time.perf_counter() - t0
        y = jax.block_until_ready(compiled(arg))
        runs = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(arg))
            runs.append(time.perf_counter() - t0)
        out[name] = {"compile_s": compile_s, "run_s": float(np.median(runs)), "out": np.asarray(y).ravel().tolist()}
    print(json.dumps(out))


def _run_child(off: bool, repeats: int, cases) -> dict:
    env = dict(os.environ)
    flags = " ".join(f for f in env.get("XLA_FLAGS", "").split() if "xla_cpu_use_fusion_emitters" not in f)
    env["XLA_FLAGS"] = (flags + (" " + FLAG if off else "")).strip()
    for key in ("JAX_DISABLE_MOST_OPTIMIZATIONS", "JAX_COMPILATION_CACHE_DIR", "JAX_ENABLE_COMPILATION_CACHE"):
        env.pop(key, None)                                   # XLA's default effort, nothing read from a cache
    env["JAX_PLATFORMS"] = "cpu"                             # the flag is the CPU backend's, also on a GPU host
    code = f"from jaxcon.bench.emitters import child; child({int(repeats)}, {tuple(cases)!r})"
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"the {'elemental' if off else 'fusion'}-emitter child failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _setting(run: dict) -> dict:
    """What a child ran under: its XLA_FLAGS, backend, effort and persistent cache."""
    return {k: run[k] for k in ("xla_flags", "backend", "disable_most_optimizations", "compilation_cache_dir")}


def main(repeats: int = 5, rounds: int = ROUNDS, out_path: str | None = None, cases=CASES) -> dict:
    from jaxcon.bench.timing import machine

    unknown = sorted(set(cases) - set(CASES))
    if unknown:
        raise ValueError(f"`cases`: unknown {unknown}; choose from {list(CASES)}")
    info = machine()
    print(f"XLA CPU fusion emitters on (the default) and off ({FLAG}), {rounds} alternating child processes of "
          f"each, XLA's default effort, CPU backend, median of {repeats} runs after compilation; {info['cpu']}, "
          f"{info['cores']} cores, jax {info['jax']}")
    runs = {False: [], True: []}
    for _ in range(rounds):
        for off in (False, True):
            runs[off].append(_run_child(off, repeats, cases))
    head = (f"{'case':22s} {'compile on':>10s} {'compile off':>11s} {'ratio':>6s} {'run on ms':>10s} "
            f"{'run off ms':>10s} {'ratio':>6s} {'|diff|':>8s}")
    print(head)
    print("-" * len(head))
    rows = []
    for name in cases:
        med = {off: {k: float(np.median([r[name][k] for r in runs[off]])) for k in ("compile_s", "run_s")}
               for off in (False, True)}
        diff = float(np.max(np.abs(np.subtract(runs[False][0][name]["out"], runs[True][0][name]["out"]))))
        row = {"case": name, "compile_s_fusion": med[False]["compile_s"], "compile_s_elemental": med[True]["compile_s"],
               "run_s_fusion": med[False]["run_s"], "run_s_elemental": med[True]["run_s"], "max_abs_diff": diff}
        row["compile_ratio"] = row["compile_s_elemental"] / row["compile_s_fusion"]
        row["run_ratio"] = row["run_s_elemental"] / row["run_s_fusion"]
        rows.append(row)
        print(f"{name:22s} {row['compile_s_fusion']:10.2f} {row['compile_s_elemental']:11.2f} "
              f"{row['compile_ratio']:6.2f} {1e3 * row['run_s_fusion']:10.2f} {1e3 * row['run_s_elemental']:10.2f} "
              f"{row['run_ratio']:6.2f} {diff:8.1e}")
    print("compile: lower + compile seconds of a fresh jax.jit; ratio: off / on (below 1: the flag is faster); "
          "|diff|: largest difference of the outputs between the two settings")
    result = {"machine": info, "flag": FLAG, "rounds": rounds, "repeats": repeats, "cases": rows,
              "children": {"fusion": _setting(runs[False][0]), "elemental": _setting(runs[True][0])}}
    if out_path:
        with open(out_path, "w") as f:
            json.dump(result, f, indent=1)
    return result
