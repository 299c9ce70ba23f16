"""The recording fit (docs/fitting.md, "Fitting a recording"): the SciPy double pendulum
(`jaxcon.bench.references.scipy_ode.RECORDING`) fitted through `setup=` (initial angles and angular velocities,
both lengths, the mass ratio) from lengths (1.0, 0.5), ratio 1 and zero angular velocities, with default
options, for several solvers, frame rates of the simulation and noise seeds. Prints one row per fit: errors,
1-sigma std, converged / reason, RMS error, residual lag-1 correlation, wall time (compilation included).

Run from the repository root: python benchmarks/fit_recording.py [solver=rate,...] [seeds...]
  e.g. python benchmarks/fit_recording.py RATTLE=240,RATTLE=960,PGS=240,PGS=960 23 0 1 2 3
"""
import pathlib
import sys
import time
import warnings

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

import jaxcon as jc  # noqa: E402
from jaxcon.bench.references.scipy_ode import RECORDING, double_pendulum_recording  # noqa: E402
from jaxcon.bench.timing import machine  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "tests"))
from reference import pendulum_setup  # noqa: E402  (the setup tests/test_fit_recordings.py fits through)

SOLVERS = {"RATTLE": lambda: jc.RATTLE(10), "PGS": lambda: jc.PGS(10),
           "PGS-split": lambda: jc.PGS(10, stabilization="split")}


def one(solver_name, rate, seed):
    t, obs, _, spec = double_pendulum_recording(seed=seed)
    every = int(round(rate / spec["rate"]))
    x1, x2 = obs[0]
    a0 = np.array([np.arctan2(x1[0], -x1[1]), np.arctan2(x2[0] - x1[0], -(x2[1] - x1[1]))])
    theta0 = {"angles": a0, "omegas": np.zeros(2), "lengths": np.array([1.0, 0.5]), "ratio": np.array(1.0)}
    model, state = jc.scenes.double_pendulum(lengths=(1.0, 0.5), angles=tuple(a0))
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = jc.fit(model, state, SOLVERS[solver_name](), 1.0 / rate, obs, theta0, setup=pendulum_setup,
                     observed_particles=[1, 2], sample_steps=np.arange(len(t)) * every,
                     transforms={"lengths": "log", "ratio": "log"}, progress=False)
    wall = time.perf_counter() - t0
    L_true = np.array(spec["lengths"])
    ratio_true = spec["masses"][1] / spec["masses"][0]
    L, ratio = np.asarray(res.params["lengths"]), float(res.params["ratio"])
    eL, eR = 100 * (L / L_true - 1), 100 * (ratio / ratio_true - 1)
    sL = 100 * np.asarray(res.std["lengths"]) / L_true if res.std is not None else [np.nan] * 2
    sR = 100 * float(res.std["ratio"]) / ratio_true if res.std is not None else np.nan
    why = res.reason.split(": ")[0] if not res.converged else "yes"
    print(f"| {solver_name}(10) | {rate} | {seed} | {eL[0]:+.3f} +- {sL[0]:.3f} | {eL[1]:+.3f} +- {sL[1]:.3f} | "
          f"{eR:+.2f} +- {sR:.2f} | {why}{' (warned)' if caught else ''} | {1e3 * res.rms:.2f} | "
          f"{res.residual_correlation:.2f} | {res.iterations} | {wall:.1f} |", flush=True)


def main(argv):
    runs = [a.split("=") for a in (argv[0].split(",") if argv else ["RATTLE=240"])]
    seeds = [int(s) for s in argv[1:]] or [RECORDING["seed"]]
    host = machine()
    print(f"# {host['cpu']}, {host['cores']} cores, jax {host['jax']}, float64; errors and 1-sigma std in %")
    print("| solver | Hz | seed | L1 | L2 | m2/m1 | converged | RMS (mm) | lag-1 corr | updates | wall (s) |")
    print("|---|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|")
    for name, rate in runs:
        for seed in seeds:
            one(name, int(rate), seed)


if __name__ == "__main__":
    main(sys.argv[1:])
