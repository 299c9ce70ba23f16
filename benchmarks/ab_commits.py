"""The disc box's step at another commit against the working tree, in one process, runs interleaved.

    python benchmarks/ab_commits.py REV [--n 1024] [--at 7] [--solver "PGS(10)"] [--rounds 31]

This host's load moves the same program's step time by 20% between processes and within minutes, which is as
large as most changes to the contact path. Here both programs are compiled in one process and timed in turns
(the order alternating each round), and the ratio reported is the median over rounds of new / old, in wall time
and in the process's CPU time (the second is less sensitive to a busy neighbour on the host).

The commit's `jaxcon` package is copied out of git (`git archive`) under a temporary folder and renamed
`jaxcon_at_REV`, its imports rewritten, so that the two versions import side by side. The state timed is the
box after `--at` seconds of `PGS(10)` from the drop, simulated by the working tree's code (both programs then
start from the same arrays); each timed run is a 15-step rollout, as the bench's chunks.
"""
from __future__ import annotations

import argparse
import importlib
import os
import re
import subprocess
import sys
import tempfile
import time

import jax
import numpy as np


def package_at(rev: str, root: str) -> str:
    """Import name of a copy of `jaxcon` at `rev`, written under `root`."""
    name = "jaxcon_at_" + re.sub(r"\W", "_", rev)
    dest = os.path.join(root, name)
    repo = subprocess.run(["git", "rev-parse", "--show-toplevel"], capture_output=True, text=True,
                          check=True).stdout.strip()
    archive = subprocess.run(["git", "-C", repo, "archive", rev, "jaxcon"], capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", root], input=archive, check=True)
    os.rename(os.path.join(root, "jaxcon"), dest)
    for folder, _, files in os.walk(dest):
        for f in files:
            if f.endswith(".py"):
                path = os.path.join(folder, f)
                with open(path) as fh:
                    text = fh.read()
                text = re.sub(r"\bjaxcon(?=[.\s])", name, text)
                with open(path, "w") as fh:
                    fh.write(text)
    sys.path.insert(0, root)
    return name


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("rev")
    p.add_argument("--n", type=int, default=1024)
    p.add_argument("--at", type=float, default=7.0, help="simulated seconds before the timed state")
    p.add_argument("--solver", default="PGS(10)")
    p.add_argument("--rounds", type=int, default=31)
    a = p.parse_args(argv)
    # the working tree's package, not an installed copy (this script's folder, not the root, is on the path)
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    import jaxcon as jc
    with tempfile.TemporaryDirectory() as root:
        old = importlib.import_module(package_at(a.rev, root))
        model, state = jc.scenes.disc_box(a.n, dtype=np.float32)
        settle = jax.jit(lambda s: jc.rollout(model, s, jc.PGS(10), 1 / 60, 15, save_every=15)[0])
        for _ in range(int(round(a.at / (15 / 60)))):
            state = settle(state)
        fields = ("x", "v", "lam", "contact_n", "contact_t", "contact_partners")
        runs = []
        for lib in (old, jc):
            m, _ = lib.scenes.disc_box(a.n, dtype=np.float32)
            s = lib.State(**{k: getattr(state, k) for k in fields})
            solver = eval("lib." + a.solver, {"lib": lib})
            t = time.perf_counter()
            c = jax.jit(lambda s, m=m, so=solver, lib=lib: lib.rollout(m, s, so, 1 / 60, 15, save_every=15)[0])
            c = c.lower(s).compile()
            print(f"{lib.__name__} ({os.path.dirname(lib.__file__)}): compile {time.perf_counter() - t:.2f} s")
            jax.block_until_ready(c(s))
            runs.append((c, s))
        wall, cpu = [[], []], [[], []]
        for r in range(a.rounds):
            for k in ((0, 1) if r % 2 == 0 else (1, 0)):
                c, s = runs[k]
                t, q = time.perf_counter(), time.process_time()
                jax.block_until_ready(c(s))
                wall[k].append((time.perf_counter() - t) / 15e-3)
                cpu[k].append((time.process_time() - q) / 15e-3)
        wall, cpu = np.array(wall), np.array(cpu)
        for k, name in enumerate((a.rev, "working tree")):
            print(f"{name:14s} ms/step wall median {np.median(wall[k]):.3f} min {wall[k].min():.3f} | "
                  f"CPU median {np.median(cpu[k]):.3f} min {cpu[k].min():.3f}")
        print(f"working tree / {a.rev}, median of paired ratios: wall {np.median(wall[1] / wall[0]):.3f}, "
              f"CPU {np.median(cpu[1] / cpu[0]):.3f}")


if __name__ == "__main__":
    main()
