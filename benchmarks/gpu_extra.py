"""Two GPU measurements that `python -m jaxcon bench` has no flag for (benchmarks/gpu_session.sh runs them; the
sweep variants of the batch in one piece are `benchmarks/gpu_sweeps.py`).

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
    if what == "billiards":
        billiards(args)
    elif what == "box":
        box(args[0], args[1:])
    else:
        raise SystemExit(f"gpu_extra.py: unknown measurement {what!r} (billiards or box)")
