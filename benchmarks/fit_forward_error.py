"""Forward-model error on the recording (docs/fitting.md, "Which solver to fit with"): every solver
run with the TRUE lengths, masses and initial state, compared with the exact SciPy positions at the 30 Hz
frames over 3 s. A fit cannot recover parameters to better than the error its forward model makes with the
true ones; the recording's noise is 2 mm per coordinate.

Run from the repository root: python benchmarks/fit_forward_error.py [rates...]   (default 120 240 480 960)
"""
import sys
import time

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxcon as jc  # noqa: E402
from jaxcon.bench.references.scipy_ode import double_pendulum_recording  # noqa: E402
from jaxcon.bench.timing import machine  # noqa: E402


def true_start(spec):
    a, w, L = (np.asarray(spec[k], np.float64) for k in ("angles", "omegas", "lengths"))
    model, state = jc.scenes.double_pendulum(lengths=tuple(L), masses=spec["masses"], angles=tuple(a))
    tangent = np.stack([np.cos(a), np.sin(a)], -1) * (L * w)[:, None]
    return model, state.replace(v=state.v.at[1:].set(np.cumsum(tangent, 0)))


SOLVERS = {
    "RATTLE(10)": jc.RATTLE(10),
    "PGS(10)": jc.PGS(10),
    "PGS(10, split)": jc.PGS(10, stabilization="split"),
    "Jacobi(20)": jc.Jacobi(20),
    "Direct": jc.Direct(),
    "XPBD(10 substeps)": jc.XPBD(substeps=10),
    "SoftStep(4 substeps)": jc.SoftStep(),
}


def main(rates=(120, 240, 480, 960)):
    t, _, exact, spec = double_pendulum_recording()
    model, state = true_start(spec)
    host = machine()
    print(f"# {host['cpu']}, {host['cores']} cores, jax {host['jax']}: RMS / max position error (mm) at the "
          f"{spec['rate']:g} Hz frames over {spec['duration']:g} s, noise {1e3 * spec['noise']:g} mm")
    print("| solver | " + " | ".join(f"{r} Hz" for r in rates) + " |")
    print("|---|" + "---:|" * len(rates))
    for name, solver in SOLVERS.items():
        cells = []
        for rate in rates:
            every = int(round(rate / spec["rate"]))
            _, tr = jc.rollout(model, state, solver, 1.0 / rate, every * (len(t) - 1))
            x = np.concatenate([np.asarray(state.x)[None], np.asarray(tr.x)])[::every, 1:]
            err = np.linalg.norm(x - exact, axis=-1)
            cells.append(f"{1e3 * np.sqrt(np.mean(err ** 2)):.3g} / {1e3 * err.max():.3g}")
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    t0 = time.perf_counter()
    main(tuple(int(a) for a in sys.argv[1:]) or (120, 240, 480, 960))
    print(f"# {time.perf_counter() - t0:.0f} s")
