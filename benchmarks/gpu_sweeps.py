"""PGS's sweeps in the batch-minor layout, run in one piece (what an accelerator runs): the hand-written reference
against packed and plain sweeps, each with the loop over sweeps kept (`fori_loop`) and unrolled
(`Topology.unroll`). Double pendulums, PGS(10), dt 1/240, 240 steps, float32, final state only.

    python benchmarks/gpu_sweeps.py B [B ...]

Prints compile time, pendulum-steps/s (median of 5 after compilation), the ratio to the reference measured in
the same run, kernels per step (`jaxcon.bench.kernels`) and the largest difference from the reference's final
positions. With HLO_DIR set, writes each variant's optimised HLO at the first size there."""
import os
import sys

import jax
import numpy as np

import jaxcon as jc
from jaxcon.bench.kernels import step_kernels
from jaxcon.bench.references.batch_minor_pgs import chain_pgs_rollout
from jaxcon.bench.throughput import _batch
from jaxcon.bench.timing import compile_and_time
from jaxcon.core import batch


def main(sizes):
    print(f"backend {jax.default_backend()}, {jax.devices()[0].device_kind}, jax {jax.__version__}")
    solver = jc.PGS()
    for B in sizes:
        model, s = _batch("double_pendulum", B, np.float32)
        w = np.asarray(model.inv_mass)
        variants = [("reference", lambda s: chain_pgs_rollout(s.x, s.v, s.lam, w, model.rest_length, model.gravity,
                                                               solver.beta, 1 / 240, 240, solver.iterations)[0])]
        for p in (True, False):
            for u in (False, True):
                variants.append((("packed" if p else "plain") + (" unrolled" if u else ""),
                                 lambda s, p=p, u=u: batch._minor(model, s, solver, 1 / 240, 240, 240, packed=p,
                                                                  unroll=u)[0].x))
        ref_x = ref_t = None
        for name, f in variants:
            c, t, compiled = compile_and_time(f, s, repeats=5)
            try:
                k = step_kernels(compiled.as_text(), 240)
                k = f"{k['total']} ({k['fusion']}f+{k['copy']}c)"
            except ValueError:
                k = "?"
            if os.environ.get("HLO_DIR") and B == sizes[0]:      # the optimised HLO, to read the fusions
                with open(os.path.join(os.environ["HLO_DIR"], f"hlo_{name.replace(' ', '_')}.txt"), "w") as fh:
                    fh.write(compiled.as_text())
            x = np.asarray(compiled(s))
            ref_x = x if ref_x is None else ref_x
            ref_t = t if ref_t is None else ref_t
            print(f"B {B:8d} {name:16s} compile {c:5.2f} s {B * 240 / t:10.3g} pendulum-steps/s {ref_t / t:6.2f}x "
                  f"kernels/step {k:14s} max |x - x_ref| {np.abs(x - ref_x).max():.1e}", flush=True)


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [16384, 131072, 1048576])
