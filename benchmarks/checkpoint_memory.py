"""Peak temporary memory (XLA memory_analysis, deterministic) and wall time of jax.grad of a rollout loss on a
cloth, with and without `rollout(..., checkpoint=K)`. Usage: python benchmarks/checkpoint_memory.py [n] [steps...]"""
import math
import sys
import time

import jax
import jax.numpy as jnp

import jaxcon as jc


def measure(n, steps, checkpoint, iterations=5, dt=1 / 240, repeats=2):
    model, state = jc.scenes.cloth(nx=n, ny=n, size=1.0, mass=1.0)
    solver = jc.PGS(iterations=iterations, beta=0.2)

    def loss(rest):
        _, tr = jc.rollout(model.replace(rest_length=rest), state, solver, dt, steps, checkpoint=checkpoint)
        return jnp.mean(tr.x[:, :, 2] ** 2)

    g = jax.jit(jax.grad(loss))
    t0 = time.perf_counter()
    compiled = g.lower(model.rest_length).compile()
    t_compile = time.perf_counter() - t0
    mem = compiled.memory_analysis()
    temp = mem.temp_size_in_bytes
    compiled(model.rest_length).block_until_ready()
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        compiled(model.rest_length).block_until_ready()
        best = min(best, time.perf_counter() - t0)
    return temp, t_compile, best


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 16
    steps_list = [int(s) for s in sys.argv[2:]] or [500, 2000, 10000]
    print(f"cloth {n}x{n}, PGS 5 iterations, float32, grad of mean(z^2) over the trajectory w.r.t. rest_length")
    print("| steps | checkpoint K | temp memory (MB) | compile (s) | grad time (s) |")
    print("|---:|---:|---:|---:|---:|")
    for steps in steps_list:
        for ck in (None, int(round(math.sqrt(steps)))):
            temp, tc, tr = measure(n, steps, ck)
            print(f"| {steps} | {ck or '-'} | {temp / 2**20:.1f} | {tc:.1f} | {tr:.2f} |", flush=True)
