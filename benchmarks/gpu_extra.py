"""Two GPU measurements that `python -m jaxcon bench` has no flag for (benchmarks/gpu_session.sh runs them).

    python benchmarks/gpu_extra.py packed B [B ...]        double pendulums, PGS(10), 240 steps, float32, one piece:
                                                           packed sweeps against plain ones, both as a fori_loop and
                                                           with the sweeps unrolled
    python benchmarks/gpu_extra.py billiards B [B ...]     16-ball billiards tables, PGS(10), 240 steps: vmap of rollout
                                                           against batched_rollout
    python benchmarks/gpu_extra.py box SECONDS N [N ...]   the disc box (jc.scenes.disc_box, grid, PGS(10), float32)
                                                           alone on JAX's default backend: ms/step, compile, rest
"""
from __future__ import annotations

import sys
import time

import jax
import numpy as np


def packed(sizes):
    import jaxcon as jc
    from jaxcon.bench.kernels import step_kernels
    from jaxcon.bench.throughput import _batch
    from jaxcon.bench.timing import compile_and_time
    from jaxcon.core import batch

    print(f"backend {jax.default_backend()}, {jax.devices()[0].device_kind}")
    for B in sizes:
        model, s = _batch("double_pendulum", B, np.float32)
        for p in (True, False):
            f = lambda s, p=p: batch._minor(model, s, jc.PGS(), 1 / 240, 240, 240, packed=p)[0].x  # noqa: E731
            c, t, compiled = compile_and_time(f, s, repeats=5)
            try:
                k = step_kernels(compiled.as_text(), 240)["total"]
            except (ValueError, KeyError, TypeError):
                k = None
            print(f"B {B:8d} {'packed' if p else 'plain ':6s} compile {c:6.2f} s  {B * 240 / t:10.3g} "
                  f"pendulum-steps/s  kernels/step {k}", flush=True)


def billiards(sizes):
    from jaxcon.bench.throughput import batched_throughput

    for r in batched_throughput(sizes, scene="billiards", repeats=3, modes=("vmap", "batched_rollout")):
        print(f"billiards_16 B {r['batch']:7d} {r['mode']:>16s} compile {r['compile_s']:6.2f} s  "
              f"{r['system_steps_per_s']:10.3g} table-steps/s  kernels {r['kernels']}", flush=True)


def box(seconds, sizes):
    from jaxcon.bench.contacts import CHUNK, run_jaxcon

    print(f"backend {jax.default_backend()}, {jax.devices()[0].device_kind}; disc box, PGS(10), grid, float32, "
          f"{seconds} s simulated")
    for n in sizes:
        t0 = time.perf_counter()
        r = run_jaxcon(n, seconds=seconds)
        ms = 1e3 * float(np.median(r.chunks)) / CHUNK
        print(f"N {n:6d}: {ms:8.2f} ms/step (median chunk), min {1e3 * min(r.chunks) / CHUNK:8.2f}, compile "
              f"{r.compile_s:5.1f} s, wall {time.perf_counter() - t0:5.1f} s; row {r.row(n)[0]}", flush=True)


if __name__ == "__main__":
    what, args = sys.argv[1], [float(a) if "." in a else int(a) for a in sys.argv[2:]]
    if what == "packed":
        packed(args)
    elif what == "billiards":
        billiards(args)
    elif what == "box":
        box(args[0], args[1:])
    else:
        raise SystemExit(f"gpu_extra.py: unknown measurement {what!r} (packed, billiards or box)")
