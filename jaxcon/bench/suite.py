"""`python -m jaxcon demo | bench`."""
from __future__ import annotations

import json

import jax
import numpy as np

from jaxcon import scenes
from jaxcon.bench.gradient_compile import gradient_compile
from jaxcon.bench.references import scipy_ode as _reference
from jaxcon.bench.timing import (
    _cpu_jiffies,
    _pct,
    compile_and_time,
    machine,
    steal_fraction,
)
from jaxcon.core.batch import CPU_CHUNK
from jaxcon.core.sim import rollout
from jaxcon.diagnostics import energy_drift, nan_max, violation
from jaxcon.solvers.pgs import PGS


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
    # --f32-only skips the float64 runs even where x64 is already on (a notebook, the test suite)
    f64 = jax.config.jax_enable_x64 and not getattr(args, "f32_only", False)
    dtypes = [np.float32] + ([np.float64] if f64 else [])
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
    out["user_constraints"] = user_constraint_cloth(args.small, args.repeats)
    out["gradient_compile"] = gradient_compile(args.small, args.repeats)
    if f64:
        out["double_pendulum_best"] = _best_double_pendulum(args.repeats)
    if not args.no_batched:
        out["batched"] = batched(args.small, args.repeats)
    return _finish(out, start, args.out, "the whole bench")


def _xpbd_cloth(small: bool, repeats: int) -> dict:
    """XPBD(iterations=1, substeps=10) on the largest bench cloth, float32: the other solver the cloth speed
    target names. ns per constraint-iteration counts every substep's sweep."""
    from jaxcon.solvers.xpbd import XPBD

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


def user_constraint_cloth(small: bool, repeats: int) -> dict:
    """The cost of constraints written by the user: the bench cloth (32x32, float32, PGS(10), dt 1/240) with its
    edges as built-in rods and again as a `jc.Constraint` distance set (`jc.constraints.distance`: C and J from
    autodiff), built on the cloth's grid (`grid_shape`: its colours are strided boxes) and without it (gathers),
    measured in the same run; and with `bending` on every interior edge, XPBD. us per step, final state only,
    median after compilation."""
    from jaxcon.core import constraints
    from jaxcon.core.model import build
    from jaxcon.solvers.xpbd import XPBD

    n, steps, dt = (8, 10, 1 / 240) if small else (32, 50, 1 / 240)
    rods_model, state = scenes.cloth(n, n, dtype=np.float32)
    pairs = np.asarray(rods_model.pairs)
    user = constraints.distance(pairs, rest=np.asarray(rods_model.rest_length))
    user_model, _ = build(np.asarray(state.x), 1.0 / (n * n), fixed=[0, n - 1], constraints=[user],
                          dtype=np.float32, grid_shape=(n, n))
    flat_model, _ = build(np.asarray(state.x), 1.0 / (n * n), fixed=[0, n - 1], constraints=[user],
                          dtype=np.float32)
    bend_model, bend_state = scenes.cloth(n, n, dtype=np.float32, bending=1e-3)
    row = {"case": f"cloth_{n}x{n}", "dtype": "float32", "dt": dt, "steps": steps}
    for key, model, solver, s0 in (("rods", rods_model, PGS(10), state), ("user_constraint", user_model, PGS(10), state),
                                   ("user_constraint_no_grid", flat_model, PGS(10), state),
                                   ("rods_xpbd", rods_model, XPBD(), state),
                                   ("bending_xpbd", bend_model, XPBD(), bend_state)):
        fn = lambda s, model=model, solver=solver: rollout(model, s, solver, dt, steps, save_every=steps)  # noqa: E731
        t_c, t_run, _ = compile_and_time(fn, s0, repeats=repeats)
        row[key] = {"us_per_step": t_run / steps * 1e6, "compile_s": t_c, "constraints": model.n_constraints,
                    "colours": model.topology.n_colours}
    row["user_over_rods"] = row["user_constraint"]["us_per_step"] / row["rods"]["us_per_step"]
    row["user_no_grid_over_rods"] = row["user_constraint_no_grid"]["us_per_step"] / row["rods"]["us_per_step"]
    row["bending_over_rods_xpbd"] = row["bending_xpbd"]["us_per_step"] / row["rods_xpbd"]["us_per_step"]
    print(f"\n{row['case']}, float32, dt 1/240, final state only (us/step, compile s):")
    for key, label in (("rods", "PGS(10), built-in rods"), ("user_constraint", "PGS(10), edges as a jc.Constraint"),
                       ("user_constraint_no_grid", "PGS(10), the same without grid_shape"),
                       ("rods_xpbd", "XPBD(), built-in rods"), ("bending_xpbd", "XPBD(), rods + bending 1e-3")):
        r = row[key]
        print(f"  {label:36s} {r['us_per_step']:10.1f} {r['compile_s']:7.2f}  ({r['constraints']} constraints, "
              f"{r['colours']} colours)")
    print(f"  user Constraint / rods: {row['user_over_rods']:.2f}x (without grid_shape: "
          f"{row['user_no_grid_over_rods']:.2f}x); bending / rods (XPBD): "
          f"{row['bending_over_rods_xpbd']:.2f}x")
    return row


def _best_double_pendulum(repeats: int) -> dict:
    """The cheapest configuration found to reach 1e-5 m on the mild double pendulum at t = 1 s (float64):
    RATTLE(3) at dt = 1/260 (9.6e-6 m; 1/250 gives 1.04e-5), timed with the final state only and recording
    every step."""
    from jaxcon.solvers.rattle import RATTLE

    steps = 260
    solver, dt = RATTLE(iterations=3, tolerance=0.0), 1.0 / steps
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


def _kernel_text(k) -> str:
    return "" if k is None else f"{k['total']} ({k['fusion']}f+{k['copy']}c" + (f"+{k['other']}o)" if k["other"]
                                                                                else ")")


def batched(small: bool, repeats: int, sizes=None, only_default_backend: bool = False) -> list:
    """Batched rollouts of many systems on every backend found: jax.vmap of rollout, jc.batched_rollout (sharded
    over the backend's devices; where that runs in pieces, also in one piece) and the plain batch-minor
    reference measured in the same run; system-steps (pendulum-steps, cloth-steps, billiards-steps: one step
    of a 16-ball table) per second, and the kernels each program launches per time step (fusions and copies in
    XLA's optimised HLO, `jaxcon.bench.kernels`). Models with contacts are batched by jax.vmap inside
    batched_rollout (docs/contacts.md). `sizes`: the double pendulum's batch sizes (default: the bench's);
    `only_default_backend`: measure JAX's default backend only (the GPU where there is one), not every one."""
    from jaxcon.bench.throughput import backends, batched_throughput

    steps = 24 if small else 240
    pend = tuple(sizes) if sizes else (1, 64) if small else (1, 1024, 16384, 131072)
    # the small run (the suite's) has the pendulums only: tests/test_throughput.py runs the cloth's batched modes,
    # and billiards' path is a vmap of rollout
    cases = [("double_pendulum", pend)] + ([] if small else [("cloth", (64,))])
    if not small and not sizes:
        cases.append(("billiards", (64, 256)))
    rows = []
    for backend in [jax.default_backend()] if only_default_backend else backends():
        print(f"\nbatched rollouts over initial states, PGS(10), {steps} steps, float32, final state only; backend "
              f"{backend}, {len(jax.local_devices(backend=backend))} device(s). vmap: jax.vmap(jc.rollout); "
              "batched_rollout: jc.batched_rollout with its defaults (batch-minor, sharded; on CPU in pieces of "
              f"{CPU_CHUNK}); one_piece: jc.batched_rollout(chunk=batch), the whole batch in one piece (packed "
              "sweeps on the CPU, unrolled ones on an accelerator); "
              "reference: plain batch-minor PGS. kernels/step: fusions and copies per time step in the compiled "
              "program (loops inside a step counted per trip)")
        print(f"{'scene':18s} {'batch':>7s} {'mode':>16s} {'devices':>7s} {'compile s':>9s} {'run s':>9s} "
              f"{'system-steps/s':>15s} {'vs reference':>12s} {'kernels/step':>14s} {'vs reference':>12s}")
        for scene, sizes_ in cases:
            for b in sizes_:
                got = batched_throughput((b,), steps=steps, scene=scene, repeats=max(1, min(repeats, 3)),
                                         backend=backend)
                ref = {r["mode"]: r for r in got}.get("reference")
                for r in got:
                    r["vs_reference"] = None if ref is None else r["system_steps_per_s"] / ref["system_steps_per_s"]
                    r["kernels_vs_reference"] = (None if ref is None or not r["kernels"] or not ref["kernels"]
                                                 else r["kernels"]["total"] / ref["kernels"]["total"])
                    name = {"cloth": "cloth_16x16", "billiards": "billiards_16"}.get(scene, scene)
                    vs = "" if ref is None else f"{r['vs_reference']:.2f}x"
                    kvs = "" if r["kernels_vs_reference"] is None else f"{r['kernels_vs_reference']:.2f}x"
                    print(f"{name:18s} {r['batch']:7d} {r['mode']:>16s} {r['devices']:7d} {r['compile_s']:9.2f} "
                          f"{r['run_s']:9.4f} {r['system_steps_per_s']:15.3g} {vs:>12s} "
                          f"{_kernel_text(r['kernels']):>14s} {kvs:>12s}")
                    rows.append(r)
    return rows


def batched_only(args) -> int:
    """`python -m jaxcon bench --batched [N ...]`: the batched section alone (double pendulums at batch sizes N,
    and 64 cloths) on JAX's default backend, written to the JSON as {"machine", "batched", "host_steal"}."""
    info, start = machine(), _cpu_jiffies()
    print(f"jaxcon bench --batched: {info['cpu']}, {info['cores']} cores, jax {info['jax']} on {info['platform']}")
    out = {"machine": info, "batched": batched(args.small, args.repeats, args.batched or None, True)}
    return _finish(out, start, args.out, "the run")


def _finish(out: dict, start, path, what: str) -> int:
    """Record and print the host steal since `start`, and write `out` as JSON to `path` (if given)."""
    out["host_steal"] = steal_fraction(start, _cpu_jiffies())
    print(f"\nhost steal over {what}: {_pct(out['host_steal']).strip()} of this machine's CPU time")
    if path:
        with open(path, "w") as f:
            json.dump(out, f, indent=2)
        print(f"wrote {path}")
    return 0
