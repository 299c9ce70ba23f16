"""`python -m jaxcon demo | bench`."""
from __future__ import annotations

import argparse
import json
import os
import platform
import time

import jax
import numpy as np

from . import _reference, scenes
from ._diagnostics import energy_drift, nan_max, violation
from ._sim import rollout
from ._solver import PGS


def machine() -> dict:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    dev = jax.devices()[0]
    return {"cpu": cpu, "cores": os.cpu_count(), "platform": dev.platform, "device": dev.device_kind,
            "jax": jax.__version__, "python": platform.python_version()}


def _cpu_jiffies():
    """(steal, total) CPU time of this machine in clock ticks, summed over its CPUs (/proc/stat), or None where
    the file is missing. Steal is time a virtual machine's CPUs were ready to run but the hypervisor ran
    another guest: one sign of a loaded host (contention for shared caches and memory does not show in it)."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
    except OSError:
        return None
    if not fields or fields[0] != "cpu":
        return None
    ticks = [int(v) for v in fields[1:9]]      # user nice system idle iowait irq softirq steal
    return (ticks[7] if len(ticks) > 7 else 0), sum(ticks)


def steal_fraction(before, after, min_ticks=40):
    """Share of the machine's CPU time stolen by the hypervisor between two `_cpu_jiffies()` readings, or None
    when it cannot be told: no /proc/stat, or fewer than `min_ticks` clock ticks in between (at the usual 100
    ticks per second and CPU, one tick more or less would move a shorter reading by over 2.5 points)."""
    if before is None or after is None or after[1] - before[1] < min_ticks:
        return None
    return (after[0] - before[0]) / (after[1] - before[1])


def compile_and_time(fn, *args, repeats=7, stats=None):
    """(compile seconds, median run seconds after compilation, compiled) of jit(fn)(*args).

    stats: an optional dict, filled with the fastest run ("min_s") and the hypervisor's steal share of the
    machine's CPU time during the timed runs ("steal", None where unknown)."""
    jf = jax.jit(fn)
    t0 = time.perf_counter()
    compiled = jf.lower(*args).compile()
    t_compile = time.perf_counter() - t0
    jax.block_until_ready(compiled(*args))
    times = []
    before = _cpu_jiffies()
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t0)
    if stats is not None:
        stats.update(min_s=float(np.min(times)), steal=steal_fraction(before, _cpu_jiffies()))
    return t_compile, float(np.median(times)), compiled


def _pct(fraction):
    return "   n/a" if fraction is None else f"{100 * fraction:5.1f}%"


def _scene_list(small: bool):
    if small:
        return [("pendulum", lambda d: scenes.pendulum(angle=0.5, dtype=d), 120),
                ("double_pendulum", lambda d: scenes.double_pendulum(angles=(0.5, 0.5), dtype=d), 120),
                ("chain_20", lambda d: scenes.chain(20, 2.0, 0.2, dtype=d), 120),
                ("cloth_8x8", lambda d: scenes.cloth(8, 8, dtype=d), 60)]
    return [("pendulum", lambda d: scenes.pendulum(angle=0.5, dtype=d), 480),
            ("double_pendulum", lambda d: scenes.double_pendulum(angles=(0.5, 0.5), dtype=d), 480),
            ("chain_50_1000to1", lambda d: scenes.chain(50, 5.0, 0.5, 10.0, dtype=d), 480),
            ("cloth_32x32", lambda d: scenes.cloth(32, 32, dtype=d), 240)]


def demo(args) -> int:
    dt = 1 / 240
    solver = PGS(iterations=10, beta=0.2)
    print(f"jaxcon demo: PGS(iterations=10, beta=0.2), dt = 1/240 s, float32, on {machine()['cpu']}")
    head = (f"{'scene':18s} {'particles':>9s} {'constr':>7s} {'colours':>7s} {'compile s':>9s} "
            f"{'steps/s':>10s} {'max viol':>9s} {'E drift':>9s}")
    print(head)
    print("-" * len(head))
    for name, make, steps in _scene_list(args.small):
        model, state = make(np.float32)
        fn = lambda s, model=model, steps=steps: rollout(model, s, solver, dt, steps)  # noqa: E731
        t_c, t_run, compiled = compile_and_time(fn, state, repeats=3)
        _, tr = compiled(state)
        viol = float(nan_max(violation(model, tr.x)))
        drift = float(energy_drift(model, state, tr))
        print(f"{name:18s} {model.n_particles:9d} {model.n_constraints:7d} {model.topology.n_colours:7d} "
              f"{t_c:9.2f} {steps / t_run:10.3g} {viol:9.2e} {drift:+9.2e}")
    print("max viol: largest |d - L| / L over constraints and steps; "
          "E drift: (E_end - E_0) / max kinetic energy.")
    identification(n=8 if args.small else 20, steps=120 if args.small else 240)
    return 0


def identification(n: int = 20, steps: int = 240) -> None:
    """Hide the rest lengths and beta of a chain, observe 1 mm-noisy positions, recover them with jc.fit."""
    from ._experiments import chain_identification
    from ._fit import fit

    dt = 1 / 240
    guess, state, true_L, obs = chain_identification(n=n, beta=0.2, dt=dt, steps=steps, dtype=np.float32)
    print(f"\nsystem identification: a {n}-link chain with hidden rest lengths (each 2/{n} m +- 10%) and "
          f"beta = 0.2, {steps} steps observed with 1 mm noise; fitting from the nominal lengths and beta = 0.3")
    t0 = time.perf_counter()
    res = fit(guess, state, PGS(iterations=10, beta=0.3), dt, obs, ("rest_length", "beta"), optimizer="lm",
              steps=40, patience=5)
    elapsed = time.perf_counter() - t0
    fitted = np.asarray(res.model.rest_length)
    print(f"{'link':>4s} {'true L (m)':>11s} {'fitted (m)':>11s} {'error':>8s}")
    for k in range(n):
        print(f"{k:4d} {true_L[k]:11.5f} {fitted[k]:11.5f} {fitted[k] / true_L[k] - 1:+8.2%}")
    print(f"beta: true 0.2, fitted {float(res.solver.beta):.4f}; worst length error "
          f"{np.max(np.abs(fitted / true_L - 1)):.3%}; {res.iterations} iterations, {elapsed:.1f} s "
          f"(compilation included)")


def _bench_cases(small: bool):
    if small:
        return [("double_pendulum", lambda d: scenes.double_pendulum(angles=(0.5, 0.5), dtype=d), 480),
                ("chain_20", lambda d: scenes.chain(20, 2.0, 0.2, dtype=d), 100),
                ("cloth_8x8", lambda d: scenes.cloth(8, 8, dtype=d), 10)]
    return [
        ("double_pendulum", lambda d: scenes.double_pendulum(angles=(0.5, 0.5), dtype=d), 20000),
        ("chain_100", lambda d: scenes.chain(100, 5.0, 1.0, dtype=d), 2000),
        ("cloth_32x32", lambda d: scenes.cloth(32, 32, dtype=d), 200),
        ("cloth_64x64", lambda d: scenes.cloth(64, 64, dtype=d), 50),
    ]


def bench(args) -> int:
    iterations, dt = 10, 1 / 240
    solver = PGS(iterations=iterations, beta=0.2)
    info = machine()
    start = _cpu_jiffies()
    results = []
    print(f"jaxcon bench: PGS(iterations={iterations}), dt = 1/240 s; {info['cpu']}, {info['cores']} cores, "
          f"jax {info['jax']} on {info['platform']}")
    head = (f"{'case':18s} {'dtype':7s} {'compile s':>9s} {'us/step':>10s} {'no record':>10s} {'ns/c-iter':>9s} "
            f"{'max viol':>9s} {'E drift':>9s} {'pos err':>9s} {'steal':>6s}")
    print(head)
    print("-" * len(head))
    dtypes = [np.float32] + ([np.float64] if jax.config.jax_enable_x64 else [])
    for name, make, steps in _bench_cases(args.small):
        for dtype in dtypes:
            model, state = make(dtype)
            fn = lambda s, model=model, steps=steps: rollout(model, s, solver, dt, steps)  # noqa: E731
            rec, fin = {}, {}
            t_c, t_run, compiled = compile_and_time(fn, state, repeats=args.repeats, stats=rec)
            _, tr = compiled(state)
            per_step = t_run / steps
            bare = lambda s, model=model, steps=steps: rollout(model, s, solver, dt, steps, save_every=steps)[0]  # noqa: E731
            _, t_bare, _ = compile_and_time(bare, state, repeats=args.repeats, stats=fin)
            row = {"case": name, "dtype": np.dtype(dtype).name, "particles": model.n_particles,
                   "constraints": model.n_constraints, "colours": model.topology.n_colours,
                   "iterations": iterations, "dt": dt, "steps": steps, "compile_s": t_c,
                   "median_s_per_step": per_step, "median_s_per_step_final_state_only": t_bare / steps,
                   "ns_per_constraint_iteration": per_step / (model.n_constraints * iterations) * 1e9,
                   "min_s_per_step": rec["min_s"] / steps,
                   "min_s_per_step_final_state_only": fin["min_s"] / steps,
                   "host_steal": rec["steal"], "host_steal_final_state_only": fin["steal"],
                   "max_violation": float(nan_max(violation(model, tr.x))),
                   "energy_drift": float(energy_drift(model, state, tr))}
            if name == "double_pendulum":
                k = int(round(1.0 / dt))
                ref = _reference.double_pendulum_positions((0.5, 0.5), (1.0, 1.0), (1.0, 1.0), [k * dt])[0]
                row["position_error_at_1s"] = float(np.max(np.abs(np.asarray(tr.x[k - 1, 1:]) - ref)))
                row["error_reference"] = _reference.describe()
            results.append(row)
            err = row.get("position_error_at_1s")
            print(f"{name:18s} {row['dtype']:7s} {t_c:9.2f} {per_step * 1e6:10.3f} {t_bare / steps * 1e6:10.3f} "
                  f"{row['ns_per_constraint_iteration']:9.2f} {row['max_violation']:9.2e} "
                  f"{row['energy_drift']:+9.2e} {'' if err is None else f'{err:9.2e}':9s} {_pct(rec['steal'])}")
    print("us/step: median of repeated compiled rollouts recording the trajectory every step; no record: the same "
          "rollout keeping only the final state (save_every=steps); compile time measured apart (lower + "
          "compile); ns/c-iter from us/step; pos err: bob positions at t = 1 s against the stated reference; "
          "steal: share of this machine's CPU time the hypervisor gave to other guests while the recording "
          "rollouts ran (/proc/stat), one sign of a loaded host; fastest runs are in the JSON.")
    out = {"machine": info, "solver": f"PGS(iterations={iterations}, beta=0.2)", "results": results}
    out["xpbd_cloth"] = _xpbd_cloth(args.small, args.repeats)
    out["gradient_compile"] = gradient_compile(args.small, args.repeats)
    if jax.config.jax_enable_x64:
        out["double_pendulum_best"] = _best_double_pendulum(args.repeats)
    if not args.no_batched:
        out["batched"] = batched(args.small, args.repeats)
    out["host_steal"] = steal_fraction(start, _cpu_jiffies())
    print(f"\nhost steal over the whole bench: {_pct(out['host_steal']).strip()} of this machine's CPU time")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(out, f, indent=2)
        print(f"wrote {args.out}")
    return 0


def _xpbd_cloth(small: bool, repeats: int) -> dict:
    """XPBD(iterations=1, substeps=10) on the largest bench cloth, float32: the other solver the cloth speed
    target names. ns per constraint-iteration counts every substep's sweep."""
    from ._xpbd import XPBD

    n, steps, dt = (8, 10, 1 / 240) if small else (64, 50, 1 / 240)
    solver = XPBD(iterations=1, substeps=10)
    model, state = scenes.cloth(n, n, dtype=np.float32)
    row = {"case": f"cloth_{n}x{n}", "solver": "XPBD(iterations=1, substeps=10)", "dtype": "float32", "dt": dt,
           "steps": steps, "constraints": model.n_constraints}
    sweeps = model.n_constraints * solver.iterations * solver.substeps
    for key, every in (("final_state_only", steps), ("recording", 1)):
        fn = lambda s, every=every: rollout(model, s, solver, dt, steps, save_every=every)  # noqa: E731
        stats = {}
        t_c, t_run, compiled = compile_and_time(fn, state, repeats=repeats, stats=stats)
        row[f"median_s_per_step_{key}"] = t_run / steps
        row[f"ns_per_constraint_iteration_{key}"] = t_run / steps / sweeps * 1e9
        row[f"min_ns_per_constraint_iteration_{key}"] = stats["min_s"] / steps / sweeps * 1e9
        row[f"host_steal_{key}"] = stats["steal"]
        if key == "recording":
            row["compile_s"] = t_c
            row["max_violation"] = float(nan_max(violation(model, compiled(state)[1].x)))
    print(f"\n{row['case']}, float32, {row['solver']}: {row['ns_per_constraint_iteration_recording']:.2f} ns per "
          f"constraint-iteration recording every step, {row['ns_per_constraint_iteration_final_state_only']:.2f} "
          f"final state only ({row['median_s_per_step_recording'] * 1e6:.0f} us/step); max violation "
          f"{row['max_violation']:.2e}; compile {row['compile_s']:.2f} s; fastest runs "
          f"{row['min_ns_per_constraint_iteration_recording']:.2f} / "
          f"{row['min_ns_per_constraint_iteration_final_state_only']:.2f} ns; host steal "
          f"{_pct(row['host_steal_recording']).strip()} / {_pct(row['host_steal_final_state_only']).strip()}")
    return row


def gradient_compile(small: bool, repeats: int) -> dict:
    """Trace, compile and run time of jax.grad of a cloth rollout's loss (PGS(10), float32, final state) with
    respect to the rest lengths: jaxcon against the plain scatter-add PGS of `_plain_pgs`, in one process,
    alternating (jaxcon, plain, jaxcon, plain) on this noisy host. Full size: 16x16 cloth, 100 steps."""
    from ._plain_pgs import plain_pgs_rollout

    n, steps, it, dt = (6, 10, 10, 1 / 240) if small else (16, 100, 10, 1 / 240)
    model, state = scenes.cloth(n, n, dtype=np.float32)
    t = model.topology

    def jaxcon_loss(rest):
        final, _ = rollout(model.replace(rest_length=rest), state, PGS(it, beta=0.2), dt, steps, save_every=steps)
        return jax.numpy.mean(final.x[..., 2] ** 2)

    def plain_loss(rest):
        x, _, _ = plain_pgs_rollout(state.x, state.v, state.lam, model.inv_mass, rest, t.i, t.j, t.colour,
                                    model.gravity, 0.2, dt, steps, it)
        return jax.numpy.mean(x[..., 2] ** 2)

    from . import _sim

    def variant(name):
        # jaxcon: steps rematerialised in reverse mode (the library's default); jaxcon_stored: every step's
        # intermediates stored (the program before that change), to show what the default trades
        _sim.REMAT_STEPS = name != "jaxcon_stored"
        return plain_loss if name == "plain" else jaxcon_loss

    row = {"case": f"cloth_{n}x{n}", "steps": steps, "solver": f"PGS({it})", "dtype": "float32"}
    names = ("jaxcon", "plain") if small else ("jaxcon", "plain", "jaxcon_stored")
    for _ in range(1 if small else 2):
        for name in names:
            fn = variant(name)
            g = jax.jit(jax.grad(fn))
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
    _sim.REMAT_STEPS = True
    for key in [k for k in row if k.endswith("_s")]:
        row[key] = float(np.min(row[key]))        # the quieter of the alternating rounds
    total = {k: row[f"{k}_trace_s"] + row[f"{k}_compile_s"] for k in ("jaxcon", "plain")}
    row["trace_plus_compile_ratio"] = total["jaxcon"] / total["plain"]
    print(f"\ngradient of a {n}x{n} cloth rollout ({steps} steps, PGS({it}), float32) w.r.t. rest lengths, best of "
          f"{1 if small else 2} alternating round(s): jaxcon trace {row['jaxcon_trace_s']:.2f} s + compile {row['jaxcon_compile_s']:.2f} s, "
          f"run {row['jaxcon_run_s'] * 1e3:.1f} ms ({row['jaxcon_stablehlo_ops']} StableHLO ops); plain scatter-add "
          f"PGS trace {row['plain_trace_s']:.2f} s + compile {row['plain_compile_s']:.2f} s, run "
          f"{row['plain_run_s'] * 1e3:.1f} ms ({row['plain_stablehlo_ops']} ops); trace + compile ratio "
          f"{row['trace_plus_compile_ratio']:.2f}")
    if "jaxcon_stored_compile_s" in row:
        print(f"  jaxcon storing every step's intermediates instead: trace {row['jaxcon_stored_trace_s']:.2f} s + compile "
              f"{row['jaxcon_stored_compile_s']:.2f} s, run {row['jaxcon_stored_run_s'] * 1e3:.1f} ms "
              f"({row['jaxcon_stored_stablehlo_ops']} ops)")
    return row


def _best_double_pendulum(repeats: int) -> dict:
    """The cheapest configuration found to reach 1e-5 m on the mild double pendulum at t = 1 s (float64):
    RATTLE(3) at dt = 1/260 (9.6e-6 m; 1/250 gives 1.04e-5), timed with the final state only and recording
    every step."""
    from ._rattle import RATTLE

    steps = 260
    solver, dt = RATTLE(iterations=3), 1.0 / steps
    model, state = scenes.double_pendulum(angles=(0.5, 0.5), dtype=np.float64)
    ref = _reference.double_pendulum_positions((0.5, 0.5), (1.0, 1.0), (1.0, 1.0), [steps * dt])[0]
    row = {"solver": "RATTLE(iterations=3)", "dt": dt, "dtype": "float64", "reference": _reference.describe()}
    for key, every in (("final_state_only", steps), ("recording", 1)):
        # the recording variant returns the trajectory too (otherwise XLA drops the recording as dead code)
        fn = lambda s, every=every: rollout(model, s, solver, dt, steps, save_every=every)  # noqa: E731
        stats = {}
        # a rollout here takes well under a millisecond: 301 runs give a steady median and a steal reading
        t_c, t_run, compiled = compile_and_time(fn, state, repeats=max(repeats, 301), stats=stats)
        row[f"ms_per_sim_s_{key}"] = t_run / (steps * dt) * 1e3
        row[f"host_steal_{key}"] = stats["steal"]
        if key == "final_state_only":
            row["compile_s"] = t_c
            row["position_error_at_1s"] = float(np.max(np.abs(np.asarray(compiled(state)[0].x[1:]) - ref)))
    print(f"\ndouble pendulum (0.5, 0.5), float64, {row['solver']} at dt = 1/{steps}: position error at 1 s "
          f"{row['position_error_at_1s']:.2e} m for {row['ms_per_sim_s_final_state_only']:.2f} ms per simulated "
          f"second ({row['ms_per_sim_s_recording']:.2f} ms recording every step; compile {row['compile_s']:.2f} s; "
          f"host steal {_pct(row['host_steal_final_state_only']).strip()})")
    return row


def batched(small: bool, repeats: int) -> list:
    """jax.vmap of whole rollouts over batches of initial states: particle-steps per second."""
    from ._throughput import batched_throughput

    steps = 24 if small else 240
    cases = [("double_pendulum", (1, 64) if small else (1, 64, 1024, 16384)),
             ("cloth", (2,) if small else (64,))]
    print(f"\nbatched rollouts over initial states, PGS(10), {steps} steps, float32, final state only; "
          f"on {jax.devices()[0].platform}. vmap: one jax.vmap; chunks: jc.batched_rollout")
    print(f"{'scene':18s} {'batch':>6s} {'mode':>15s} {'compile s':>9s} {'run s':>9s} {'particle-steps/s':>17s}")
    rows = []
    chunk = 32 if small else 1024
    for scene, sizes in cases:
        # chunked runs only where the batch is larger than a chunk (otherwise they are the vmap run)
        for c, sz in ((None, sizes), (chunk, tuple(b for b in sizes if b > chunk))):
            if not sz:
                continue
            for r in batched_throughput(sz, steps=steps, scene=scene, repeats=max(1, min(repeats, 3)), chunk=c):
                name = "cloth_16x16" if scene == "cloth" else scene
                print(f"{name:18s} {r['batch']:6d} {r['mode']:>15s} {r['compile_s']:9.2f} {r['run_s']:9.4f} "
                      f"{r['particle_steps_per_s']:17.3g}")
                rows.append(r)
    return rows


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {value}")
    return value


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m jaxcon", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("demo", help="run the four scenes and print a summary")
    d.add_argument("--small", action="store_true", help="reduced sizes (for tests)")
    b = sub.add_parser("bench", help="time rollouts (median after compilation) and report their error")
    b.add_argument("--small", action="store_true", help="reduced sizes (for tests)")
    b.add_argument("--repeats", type=_positive_int, default=7,
                   help="timed runs per measurement after compilation; the median is reported (default 7)")
    b.add_argument("--out", default="bench.json", help="JSON output path ('' for none)")
    b.add_argument("--f32-only", action="store_true", help="skip float64")
    b.add_argument("--no-batched", action="store_true", help="skip the batched (vmap) throughput section")
    b.add_argument("--speed-vs-error", action="store_true",
                   help="sweep every solver over iterations, substeps and dt; error vs cost (JSON, CSV, plots)")
    b.add_argument("--out-dir", default="speed_vs_error", help="output folder of --speed-vs-error")
    args = p.parse_args(argv)
    if args.cmd == "bench" and args.out:
        folder = os.path.dirname(os.path.abspath(args.out))
        if not os.path.isdir(folder) or not os.access(folder, os.W_OK):
            p.error(f"--out {args.out}: folder {folder} does not exist or is not writable")
    if args.cmd == "bench" and args.speed_vs_error:
        from ._speed_vs_error import run
        run(small=args.small, out_dir=args.out_dir)
        return 0
    if args.cmd == "bench" and not args.f32_only:
        jax.config.update("jax_enable_x64", True)
    return {"demo": demo, "bench": bench}[args.cmd](args)
