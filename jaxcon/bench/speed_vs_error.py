"""`python -m jaxcon bench --speed-vs-error`: every solver swept over iterations, substeps and dt, error against
independent references versus wall time per simulated second.

Scenes (full mode; `--small` shrinks every one):
  double pendulum, mild (0.5, 0.5 rad) and hard (pi/2, pi/2) start, float64, 1 s: max |x - x_ref| over both bobs
    and both coordinates at t = 1 s, x_ref from the reduced-coordinate ODE (`jaxcon.bench.references.scipy_ode`);
  chain(50, 5.0, 0.5, end_mass=10.0) (1000:1, released from horizontal), float32, 1 s: max link stretch
    |d - L| / L over all steps and the tip error at t = 1 s against the 50-angle reduced-coordinate ODE;
  cloth(32, 32) (two corners pinned), float32, 1 s: max particle position error at t = 1 s against a converged
    run (XPBD, 1 iteration, 400 substeps of dt = 1/60, compliance 0, float64; its distance to the 200-substep run
    is reported as the reference's own uncertainty).
Cost: median wall time of the jit-compiled `jc.rollout` per simulated second (compile time apart).
"""
from __future__ import annotations

import csv
import importlib.util
import json
import math
import os
import time

import jax
import numpy as np

from jaxcon import scenes
from jaxcon.bench.references import scipy_ode as ref
from jaxcon.bench.timing import compile_and_time, machine
from jaxcon.core.sim import rollout
from jaxcon.diagnostics import energy_drift, nan_max, penetration, violation
from jaxcon.solvers.direct import Direct
from jaxcon.solvers.jacobi import Jacobi
from jaxcon.solvers.penalty import Penalty
from jaxcon.solvers.pgs import PGS
from jaxcon.solvers.rattle import RATTLE
from jaxcon.solvers.softstep import SoftStep
from jaxcon.solvers.xpbd import XPBD

SOLVERS = ("PGS", "Jacobi", "XPBD", "Penalty", "Direct", "SoftStep", "RATTLE", "PGS-split", "Direct-split")
# Section 7 of the method article (rows it has), plus the library's other solvers.
METHOD = {
    "Penalty": ("stiff spring", "Toy demos"),
    "Direct": ("direct lambda solve", "Few-body robotics"),
    "PGS": ("sequential impulse", "Box2D, Bullet, PhysX"),
    "XPBD": ("PBD / XPBD", "Cloth, this project"),
    "Jacobi": ("projected Jacobi", "GPU particle solvers (Flex)"),
    "SoftStep": ("soft step", "Box2D v3"),
    "RATTLE": ("RATTLE / SHAKE", "Molecular dynamics"),
    "PGS-split": ("sequential impulse, split impulses", "Box2D v2, Bullet (splitImpulse)"),
    "Direct-split": ("direct lambda solve, split impulses", "this project"),
}


def _name(s):
    """Series name of a solver: its class, with '-split' for split-impulse stabilisation."""
    return type(s).__name__ + ("-split" if getattr(s, "stabilization", None) == "split" else "")


def _pen(stiffness, model, dt, safety=0.5):
    """Penalty with enough substeps to stay below `safety` x its stability limit."""
    lim = Penalty(stiffness=stiffness).stability_limit(model)
    return Penalty(stiffness=stiffness, substeps=max(1, int(math.ceil(dt / (safety * lim)))))


def _soft(substeps, dt):
    return SoftStep(substeps=substeps, hertz=0.25 * substeps / dt)


def _label(s):
    base = _label_base(s)
    return base[:-1] + ",split)" if _name(s).endswith("-split") else base


def _label_base(s):
    name = type(s).__name__
    if name == "PGS":
        return f"PGS(it={s.iterations},sub={s.substeps})"
    if name == "Jacobi":
        return f"Jacobi(it={s.iterations},sub={s.substeps})"
    if name == "XPBD":
        return f"XPBD(it={s.iterations},sub={s.substeps})"
    if name == "Penalty":
        return f"Penalty(k={float(s.stiffness):.0e},sub={s.substeps})"
    if name == "Direct":
        return f"Direct(sub={s.substeps})"
    if name == "SoftStep":
        return f"SoftStep(sub={s.substeps},hz={float(s.hertz):.0f})"
    return f"RATTLE(it={s.iterations})"


def _knobs(s):
    return {"iterations": getattr(s, "iterations", None), "substeps": getattr(s, "substeps", 1)}


# ---------------------------------------------------------------- grids: (solver, dt) per scene

def _grid_pendulum(model, small):
    if small:
        return [(PGS(10), 1 / 240), (Jacobi(20), 1 / 240), (XPBD(substeps=4), 1 / 60),
                (_pen(1e4, model, 1 / 60), 1 / 60), (Direct(), 1 / 240), (_soft(4, 1 / 60), 1 / 60),
                (RATTLE(4, tolerance=0.0), 1 / 250), (PGS(10, stabilization="split"), 1 / 240),
                (Direct(stabilization="split"), 1 / 240)]
    g = []
    for dt in (1 / 240, 1 / 960, 1 / 3840):
        g += [(PGS(10), dt), (Jacobi(20), dt), (Direct(), dt), (PGS(10, stabilization="split"), dt),
              (Direct(stabilization="split"), dt)]
    for sub in (4, 16, 64):
        g += [(XPBD(substeps=sub), 1 / 60), (_soft(sub, 1 / 60), 1 / 60)]
    for k in (1e4, 1e5, 1e6):
        g.append((_pen(k, model, 1 / 60), 1 / 60))
    for dt in (1 / 100, 1 / 250, 1 / 1000):
        g.append((RATTLE(4, tolerance=0.0), dt))
    for dt in (1 / 250, 1 / 260, 1 / 280):   # cheapest configurations near the 1e-5 m target
        g.append((RATTLE(3, tolerance=0.0), dt))
    return g


def _grid_chain(model, small):
    dt = 1 / 60
    if small:      # the test suite's run: every solver already has a point on the pendulum; each point compiles
        return [(PGS(4, substeps=16), dt), (XPBD(substeps=16), dt), (Direct(substeps=16), dt)]
    g = []
    for sub in (16, 64, 256):
        g += [(PGS(4, substeps=sub), dt), (Jacobi(20, substeps=sub), dt), (XPBD(substeps=sub), dt),
              (_soft(sub, dt), dt), (PGS(4, substeps=sub, stabilization="split"), dt)]
    for sub in (16, 32, 64):
        g += [(Direct(substeps=sub), dt), (Direct(substeps=sub, stabilization="split"), dt)]
    for k in (1e4, 1e5, 1e6):
        g.append((_pen(k, model, dt), dt))
    for rdt in (1 / 240, 1 / 960, 1 / 3840):
        g.append((RATTLE(10, tolerance=0.0), rdt))
    return g


def _grid_cloth(model, small):
    dt = 1 / 60
    if small:
        return [(PGS(10), dt), (XPBD(substeps=4), dt)]
    g = []
    for sub in (1, 4, 16):
        g += [(PGS(10, substeps=sub), dt), (Jacobi(20, substeps=sub), dt),
              (PGS(10, substeps=sub, stabilization="split"), dt)]
    for sub in (4, 16, 64):
        g += [(XPBD(substeps=sub), dt), (_soft(sub, dt), dt)]
    for k in (1e2, 1e3, 1e4):
        g.append((_pen(k, model, dt), dt))
    for rdt in (1 / 60, 1 / 240):
        g.append((RATTLE(10, tolerance=0.0), rdt))
    # Direct: a dense solve of 3906 constraints per step (about 0.7 s here): one point, timed once
    g.append((Direct(), dt))
    return g


# ---------------------------------------------------------------- measuring one point

def _run(model, state, solver, dt, steps, repeats):
    fn = lambda s: rollout(model, s, solver, dt, steps)  # noqa: E731
    t_c, t_run, compiled = compile_and_time(fn, state, repeats=repeats)
    final, tr = compiled(state)
    return t_c, t_run, final, tr


def _point(scene, model, state, solver, dt, T, repeats, error_fn):
    steps = int(round(T / dt))
    t_c, t_run, final, tr = _run(model, state, solver, dt, steps, repeats)
    errs = error_fn(final, tr)
    row = {"scene": scene, "solver": _name(solver), "config": _label(solver), "dt": dt, "steps": steps,
           "t_end": steps * dt, **_knobs(solver), "compile_s": t_c, "wall_s": t_run,
           "cost_s_per_sim_s": t_run / (steps * dt), "cost_us_per_step": t_run / steps * 1e6, **errs}
    return row


def _finite_or_inf(x):
    x = float(x)
    return x if math.isfinite(x) else float("inf")


# ---------------------------------------------------------------- scenes

def _pendulum_scene(name, angles, small, repeats, log):
    model, state = scenes.double_pendulum(angles=angles, dtype=np.float64)
    T = 0.25 if small else 1.0
    x_ref = ref.double_pendulum_positions(angles, (1.0, 1.0), (1.0, 1.0), [T])[0]

    def err(final, tr):
        return {"error": _finite_or_inf(np.max(np.abs(np.asarray(final.x[1:]) - x_ref))),
                "max_stretch": _finite_or_inf(nan_max(violation(model, tr.x))),
                "energy_drift": _finite_or_inf(energy_drift(model, state, tr))}

    rows = []
    for solver, dt in _grid_pendulum(model, small):
        rows.append(_point(name, model, state, solver, dt, T, repeats, err))
        log(rows[-1])
    return rows, {"error": f"max bob position error (m) at t = {T} s", "reference": ref.describe(),
                  "dtype": "float64", "scene": f"double_pendulum(lengths=(1, 1), masses=(1, 1), angles={angles})"}


def _chain_setup(small, links=50):
    """The 1000:1 chain: links of 0.1 m, 0.01 kg bobs, a 10 kg end (10 links of 0.1 m in small mode)."""
    if small:
        n, L, m, end = 10, 1.0, 0.1, 10.0
    else:
        n, L, m, end = links, 0.1 * links, 0.01 * links, 10.0
    model, state = scenes.chain(n, L, m, end, dtype=np.float32)
    masses = np.r_[np.full(n - 1, m / n), end]
    return n, L, m, end, model, state, masses


def _chain_scene(small, repeats, log, T, links=50):
    n, L, m, end, model, state, masses = _chain_setup(small, links)
    t0 = time.perf_counter()
    tip_ref = ref.chain_positions(np.full(n, 1.5708), np.full(n, L / n), masses, [T], rtol=1e-9, atol=1e-9)[0, -1]
    t_ref = time.perf_counter() - t0

    def err(final, tr):
        return {"error": _finite_or_inf(np.max(np.abs(np.asarray(final.x[-1], np.float64) - tip_ref))),
                "max_stretch": _finite_or_inf(nan_max(violation(model, tr.x)))}

    name = f"chain_{n}"
    rows = []
    for solver, dt in _grid_chain(model, small):
        rows.append(_point(name, model, state, solver, dt, T, repeats, err))
        log(rows[-1])
    meta = {"error": f"tip position error (m) at t = {T} s; max_stretch: max |d - L| / L over links and steps",
            "reference": ref.describe().replace("1e-12", "1e-9") + f" ({t_ref:.1f} s to compute)",
            "dtype": "float32", "scene": f"chain({n}, {L}, {m}, end_mass={end}) released at 1.5708 rad, "
                                         f"mass ratio {end / (m / n):.0f}:1",
            "tip_reference": [float(v) for v in tip_ref]}
    return rows, meta, (model, state, err, name, T)


def _cloth_scene(small, repeats, log):
    nx = 6 if small else 32
    T = 0.25 if small else 1.0
    dt = 1 / 60
    steps = int(round(T / dt))
    m64, s64 = scenes.cloth(nx, nx, dtype=np.float64)
    subs = (25, 50) if small else (200, 400)
    finals = []
    for sub in subs:
        f, _ = jax.jit(lambda s, sub=sub: rollout(m64, s, XPBD(substeps=sub), dt, steps))(s64)
        finals.append(np.asarray(f.x))
    x_ref = finals[-1]
    ref_unc = float(np.max(np.abs(finals[0] - finals[1])))
    model, state = scenes.cloth(nx, nx, dtype=np.float32)

    def err(final, tr):
        return {"error": _finite_or_inf(np.max(np.abs(np.asarray(final.x, np.float64) - x_ref))),
                "max_stretch": _finite_or_inf(nan_max(violation(model, tr.x)))}

    name = f"cloth_{nx}x{nx}"
    rows = []
    for solver, sdt in _grid_cloth(model, small):
        slow = isinstance(solver, Direct) and not small
        rows.append(_point(name, model, state, solver, sdt, T, 1 if slow else repeats, err))
        if slow:
            rows[-1]["note"] = "timed once (dense solve of every constraint per step)"
        log(rows[-1])
    meta = {"error": f"max particle position error (m) at t = {T} s",
            "reference": f"XPBD(iterations=1, substeps={subs[1]}, compliance=0), dt = 1/60, float64; "
                         f"distance to the {subs[0]}-substep run {ref_unc:.2e} m",
            "dtype": "float32", "scene": f"cloth({nx}, {nx}, 1.0, 1.0)"}
    return rows, meta


def _contact_grid(small):
    """Solver configurations for the contact scenes: every solver whose `supports_contacts` is True."""
    dt = 1 / 60
    if small:      # the test suite's run: one point per scene (each point is a compile of a contact rollout)
        return [(PGS(10), dt)]
    g = [(PGS(10), dt), (PGS(20), dt), (PGS(10, substeps=2), dt), (PGS(10), dt / 2), (PGS(40), dt),
         (PGS(10, substeps=4), dt)]
    extra = [(XPBD(substeps=10), dt), (XPBD(substeps=20), dt), (Jacobi(iterations=20), dt),
             (Jacobi(iterations=40), dt), (SoftStep(substeps=4), dt), (SoftStep(substeps=8), dt)]
    return g + [(s, h) for s, h in extra if s.supports_contacts]


def _billiards_scene(small, repeats, log):
    """A break: error = deepest overlap between balls as a fraction of a diameter over the run; also the
    momentum change before the first cushion contact and the largest kinetic energy increase in one step."""
    rows_ = 2 if small else 5
    model, state = scenes.billiards(rows=rows_, dtype=np.float64)
    T = 0.5 if small else 2.0
    n, D = model.n_particles, 2 * scenes.BALL_RADIUS
    v0 = np.asarray(state.v)

    def err(final, tr):
        x, v = np.asarray(tr.x), np.concatenate([v0[None], np.asarray(tr.v)])
        d = np.linalg.norm(x[:, :, None] - x[:, None], axis=-1) + np.eye(n) * 1e9
        cushion = np.asarray(tr.contact_n)[:, : 4 * n].max(1) > 0
        first = int(np.argmax(cushion)) if cushion.any() else len(cushion)
        p, ke = v.sum(1), 0.5 * (v ** 2).sum((1, 2))
        return {"error": _finite_or_inf(max(0.0, float((D - d).max())) / D),
                "momentum_error": _finite_or_inf(np.abs(p[: first + 1] - p[0]).max() * scenes.BALL_MASS),
                "max_ke_increase": _finite_or_inf(max(0.0, float(np.diff(ke).max())) / ke[0])}

    name = f"billiards_{n}"
    rows = []
    for solver, dt in _contact_grid(small):
        rows.append(_point(name, model, state, solver, dt, T, repeats, err))
        log(rows[-1])
    meta = {"error": f"deepest ball overlap / diameter over {T} s; also momentum_error (N s, before the first "
                     "cushion) and max_ke_increase (largest one-step kinetic energy gain / KE_0)",
            "reference": "analytic: no overlap, momentum conserved between cushion contacts, no energy gain",
            "dtype": "float64", "scene": f"billiards(rows={rows_}): 10 m/s break, restitution 0.95"}
    return rows, meta


def _drape_scene(small, repeats, log):
    """A cloth dropped on a sphere: error = largest rod stretch over the run (the overlap with the sphere is
    also reported: the position pass ends on the obstacles, so it is 0 for every PGS configuration)."""
    nx = 6 if small else 16
    T = 0.5 if small else 1.5
    model, state = scenes.drape(nx, dtype=np.float64)
    R = float(model.sphere_radius[0])

    def err(final, tr):
        pen = np.asarray(penetration(model, tr.x))[:, model.n_particles: 2 * model.n_particles]   # the sphere
        return {"error": _finite_or_inf(nan_max(violation(model, tr.x))), "penetration": _finite_or_inf(pen.max() / R)}

    name = f"drape_{nx}x{nx}"
    rows = []
    for solver, dt in _contact_grid(small):
        rows.append(_point(name, model, state, solver, dt, T, repeats, err))
        log(rows[-1])
    meta = {"error": f"largest rod stretch |d - L| / L over {T} s; penetration: deepest overlap with the sphere / "
                     "its radius (0 wherever the position pass ends on the obstacles)",
            "reference": "analytic: rods at length, no overlap", "dtype": "float64",
            "scene": f"drape({nx}): a free cloth dropped from 1 m onto a sphere of radius 0.3 m"}
    return rows, meta


# ---------------------------------------------------------------- extra studies

def _tradeoff(chain_ctx, small, repeats, log):
    """n substeps x 1 iteration vs 1 step x n iterations, same dt, for PGS and XPBD on the heavy chain."""
    model, state, err, name, T = chain_ctx
    dt = 1 / 60
    rows = []
    for n in ((4,) if small else (16, 64, 256)):
        for solver in (PGS(1, substeps=n), PGS(n, substeps=1), XPBD(1, substeps=n), XPBD(n, substeps=1)):
            r = _point(name, model, state, solver, dt, T, repeats, err)
            r["n"] = n
            r["form"] = "substeps" if solver.substeps == n else "iterations"
            rows.append(r)
            log(r)
    return rows


def _scaling_solvers(dt):
    return [PGS(10), Jacobi(20), XPBD(substeps=10), Penalty(stiffness=1e4, substeps=10), Direct(),
            SoftStep(substeps=4, hertz=0.25 * 4 / dt), RATTLE(10, tolerance=0.0), PGS(10, stabilization="split"),
            Direct(stabilization="split")]


def _scaling(small, repeats, log):
    """Cost per step of a chain(n, 5.0, 0.5, 10.0) as n doubles; fitted exponent of cost ~ n^p."""
    sizes = (8, 16) if small else (25, 50, 100, 200)
    dt, steps = 1 / 240, (10 if small else 120)
    rows = []
    # the small run (the test suite's) times three solvers: each point is a compile
    solvers = [s for s in _scaling_solvers(dt) if _label(s) in ("PGS(it=10,sub=1)", "XPBD(it=1,sub=10)",
                                                              "Direct(sub=1)")] if small else _scaling_solvers(dt)
    for n in sizes:
        model, state = scenes.chain(n, 5.0, 0.5, 10.0, dtype=np.float32)
        for solver in solvers:
            t_c, t_run, _, _ = _run(model, state, solver, dt, steps, repeats)
            rows.append({"solver": _name(solver), "config": _label(solver), "links": n, "dt": dt,
                         "steps": steps, "compile_s": t_c, "cost_us_per_step": t_run / steps * 1e6})
            log(rows[-1])
    expo = {}
    for s in SOLVERS:
        pts = [(r["links"], r["cost_us_per_step"]) for r in rows if r["solver"] == s]
        if len(pts) < 2:
            continue
        x, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
        expo[s] = float(np.polyfit(x, y, 1)[0])
    return rows, expo


def _drift_solvers(model):
    return [(PGS(10), 1 / 240), (Jacobi(20), 1 / 240), (XPBD(substeps=4), 1 / 60),
            (_pen(1e5, model, 1 / 60), 1 / 60), (Direct(), 1 / 240), (_soft(4, 1 / 60), 1 / 60),
            (RATTLE(4, tolerance=0.0), 1 / 250), (PGS(10, stabilization="split"), 1 / 240),
            (Direct(stabilization="split"), 1 / 240)]


def _drift(small, log):
    T = 2.0 if small else 10.0
    model, state = scenes.double_pendulum(angles=(0.5, 0.5), dtype=np.float64)
    rows = []
    for solver, dt in _drift_solvers(model):
        steps = int(round(T / dt))
        _, tr = jax.jit(lambda s, solver=solver, dt=dt, steps=steps: rollout(model, s, solver, dt, steps))(state)
        rows.append({"solver": _name(solver), "config": _label(solver), "dt": dt, "t_end": steps * dt,
                     "energy_drift": _finite_or_inf(energy_drift(model, state, tr)),
                     "violation_end": _finite_or_inf(nan_max(violation(model, tr.x[-1])))})
        log(rows[-1])
    return rows, T


def _xpbd_paper(small, log):
    """Macklin, Mueller, Chentanez 2016, hanging-chain check: 20 particles of 1 kg, compliance 1e-8, 100
    frames; support force (lam / dt of the first constraint) against a long-converged run."""
    n, frames = (20, 20) if small else (20, 100)
    dt = 1 / 60
    model, state = scenes.chain(n, 10.0, float(n), angle=1.5708, dtype=np.float64)  # 1 kg per particle
    iters = (5, 20) if small else (50, 100, 1000)
    ref_it = 200 if small else 20000

    def force(solver):
        _, tr = jax.jit(lambda s: rollout(model, s, solver, dt, frames))(state)
        return np.asarray(tr.lam[:, 0]) / dt

    f_ref = force(XPBD(ref_it, compliance=1e-8, substeps=1))
    f_ref2 = f_ref if small else force(XPBD(ref_it // 2, compliance=1e-8, substeps=1))
    f_dir = f_ref if small else force(Direct(substeps=1))
    scale = float(np.max(np.abs(f_ref)))
    paper = {50: 0.06, 100: 0.02, 1000: 0.005}
    rows = []
    for it in iters:
        f = force(XPBD(it, compliance=1e-8, substeps=1))
        rows.append({"iterations": it, "max_support_force_error_rel": float(np.max(np.abs(f - f_ref))) / scale,
                     "paper": paper.get(it)})
        log(rows[-1])
    return {"setup": f"chain({n}, 10.0, {float(n)}) (1 kg particles, 0.5 m links) released from horizontal, "
                     f"dt = 1/60, {frames} frames, XPBD(substeps=1, compliance=1e-8), float64; error = max over "
                     f"frames of |F - F_ref| / max |F_ref|, F = lam[:, 0] / dt; F_ref: XPBD {ref_it} iterations",
            "reference_self_check": float(np.max(np.abs(f_ref - f_ref2))) / scale,
            "direct_vs_reference": float(np.max(np.abs(f_dir - f_ref))) / scale,
            "max_support_force_N": scale, "rows": rows}


# ---------------------------------------------------------------- summaries, files

DIVERGED = 100.0  # m: an error above this is a blow-up, left out of the plots


def _mujoco_points(small, scene_meta, log):
    """MuJoCo hinge models of the same pendulums and chain (when `mujoco` is installed): reference curves for
    the plots, kept apart from jaxcon's points (not in the method table or the cost budgets)."""
    from jaxcon.bench.references import mujoco as mj
    if not mj.available():
        print("  mujoco not installed: no MuJoCo reference curves (pip install mujoco)", flush=True)
        return []
    import mujoco
    rows = []

    def add(scene, lengths, masses, angles, integrator, dt, T, target, index):
        pos, wall, finite = mj.run(lengths, masses, angles, dt, T, integrator, repeats=1 if small else 3)
        err = float(np.max(np.abs(pos[index] - target))) if finite else float("inf")
        steps = int(round(T / dt))
        rows.append({"scene": scene, "solver": "MuJoCo", "config": f"MuJoCo {mujoco.__version__} ({integrator})",
                     "integrator": integrator, "dt": dt, "steps": steps, "t_end": steps * dt, "wall_s": wall,
                     "cost_s_per_sim_s": wall / (steps * dt), "cost_us_per_step": wall / steps * 1e6,
                     "error": _finite_or_inf(err), "max_stretch": 0.0})
        log(rows[-1])

    T = 0.25 if small else 1.0
    for name, angles in (("double_pendulum_mild", (0.5, 0.5)), ("double_pendulum_hard", (math.pi / 2, math.pi / 2))):
        if name not in scene_meta:
            continue
        target = ref.double_pendulum_positions(angles, (1.0, 1.0), (1.0, 1.0), [T])[0]
        grid = [("Euler", 1 / 240), ("RK4", 1 / 100)] if small else \
            [("Euler", 1 / 240), ("Euler", 1 / 960), ("Euler", 1 / 3840), ("RK4", 1 / 100), ("RK4", 1 / 250),
             ("RK4", 1 / 1000)]
        for integrator, dt in grid:
            add(name, (1.0, 1.0), (1.0, 1.0), angles, integrator, dt, T, target, slice(None))
    n, L, _, _, _, _, masses = _chain_setup(small)
    name = f"chain_{n}"
    tip = np.asarray(scene_meta[name]["tip_reference"])
    grid = [("Euler", 1 / 240)] if small else \
        [("Euler", 1 / 60), ("Euler", 1 / 240), ("Euler", 1 / 1000), ("Euler", 1 / 4000), ("RK4", 1 / 240),
         ("RK4", 1 / 1000)]
    for integrator, dt in grid:
        add(name, np.full(n, L / n), masses, np.full(n, 1.5708), integrator, dt, T, tip, -1)
    return rows


def _fixed_cost(rows, budget):
    out = {}
    for s in SOLVERS:
        errs = [r["error"] for r in rows if r["solver"] == s and r["cost_s_per_sim_s"] <= budget]
        out[s] = min(errs) if errs else None
    return out


def _table(result):
    fc, scal, drift = result["fixed_cost"], result["scaling_exponent"], {r["solver"]: r for r in result["drift"]}
    cost100 = {}
    n_ref = result["scaling_ref_links"]
    for r in result["scaling"]:
        if r["links"] == n_ref:
            cost100[r["solver"]] = r["cost_us_per_step"]
    scs = list(fc)
    fmt = lambda v: "-" if v is None else ("inf" if not math.isfinite(v) else f"{v:.2e}")  # noqa: E731
    head = ["method", "solver"] + [f"err@{result['budgets'][s] * 1e3:.3g}ms/s {s}" for s in scs] + \
        [f"us/step ({n_ref} links)", "cost ~ n^p", f"E drift {result['drift_T']:.3g}s", "used in"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for s in SOLVERS:
        cells = [METHOD[s][0], s] + [fmt(fc[sc][s]) for sc in scs] + \
            [fmt(cost100.get(s)), "-" if s not in scal else f"{scal[s]:.2f}",
             fmt(drift[s]["energy_drift"]) if s in drift else "-", METHOD[s][1]]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


#: An error of exactly 0 (no overlap at all) is drawn at this value on the log-scale plots.
ZERO_SHOWN_AS = 1e-16


def _plots(result, out_dir):
    if importlib.util.find_spec("matplotlib") is None:
        print("matplotlib not installed: skipping the Pareto plots (pip install jaxcon[bench])")
        return []
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    paths = []
    for scene in result["scenes"]:
        rows = [r for r in result["points"] if r["scene"] == scene]
        fig, ax = plt.subplots(figsize=(6, 4.2), dpi=80)
        diverged = 0
        for s in SOLVERS:
            ok = [r for r in rows if r["solver"] == s and math.isfinite(r["error"]) and 0 <= r["error"] <= DIVERGED]
            diverged += sum(1 for r in rows if r["solver"] == s) - len(ok)
            pts = sorted((r["cost_s_per_sim_s"], max(r["error"], ZERO_SHOWN_AS)) for r in ok)
            if pts:
                ax.loglog([p[0] * 1e3 for p in pts], [p[1] for p in pts], "o-", label=s, ms=4)
        for integ in ("Euler", "RK4"):
            pts = sorted((r["cost_s_per_sim_s"], r["error"]) for r in result.get("mujoco", [])
                         if r["scene"] == scene and r["integrator"] == integ and 0 < r["error"] <= DIVERGED)
            if pts:
                ax.loglog([p[0] * 1e3 for p in pts], [p[1] for p in pts], "s--", color="k" if integ == "Euler"
                          else "0.5", label=f"MuJoCo hinges ({integ})", ms=4)
        ax.set_xlabel("wall time per simulated second (ms)")
        ax.set_ylabel(result["scenes"][scene]["error"].split(";")[0])
        ax.set_title(scene + (f" ({diverged} diverged points, error > {DIVERGED:g} m, not shown)" if diverged else ""),
                     fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        p = os.path.join(out_dir, f"pareto_{scene}.png")
        fig.savefig(p)
        plt.close(fig)
        paths.append(p)
    return paths


def run(small=False, out_dir=".", repeats=None, verbose=True):
    jax.config.update("jax_enable_x64", True)
    os.makedirs(out_dir, exist_ok=True)
    repeats = repeats or (1 if small else 3)
    t_start = time.perf_counter()

    def log(row):
        if verbose:
            keys = ("scene", "config", "links", "iterations", "dt", "error", "max_stretch", "cost_s_per_sim_s",
                    "cost_us_per_step", "energy_drift", "max_support_force_error_rel")
            print("  " + ", ".join(f"{k}={row[k]:.3g}" if isinstance(row[k], float) else f"{k}={row[k]}"
                                   for k in keys if k in row and row[k] is not None), flush=True)

    info = machine()
    print(f"speed vs error ({'small' if small else 'full'}): {info['cpu']}, {info['cores']} cores, "
          f"jax {info['jax']} on {info['platform']}; reference: {ref.describe()}", flush=True)
    points, scene_meta = [], {}
    for name, angles in (("double_pendulum_mild", (0.5, 0.5)), ("double_pendulum_hard", (math.pi / 2, math.pi / 2))):
        if small and name.endswith("hard"):
            continue
        print(f"[{name}]", flush=True)
        rows, meta = _pendulum_scene(name, angles, small, repeats, log)
        points += rows
        scene_meta[name] = meta
    print("[chain]", flush=True)
    rows, meta, chain_ctx = _chain_scene(small, repeats, log, T=0.25 if small else 1.0)
    points += rows
    scene_meta[chain_ctx[3]] = meta
    if not small:   # the same chain twice as long (reference: DOP853 at rtol 1e-9, about 15 s)
        print("[chain, 100 links]", flush=True)
        rows100, meta100, ctx100 = _chain_scene(small, repeats, log, T=1.0, links=100)
        points += rows100
        scene_meta[ctx100[3]] = meta100
    print("[cloth]", flush=True)
    rows, meta = _cloth_scene(small, repeats, log)
    points += rows
    scene_meta[rows[0]["scene"]] = meta
    for label, scene_fn in (("billiards", _billiards_scene), ("drape", _drape_scene)):
        print(f"[{label}]", flush=True)
        rows, meta = scene_fn(small, repeats, log)
        points += rows
        scene_meta[rows[0]["scene"]] = meta
    print("[substeps vs iterations, heavy chain]", flush=True)
    trade = _tradeoff(chain_ctx, small, repeats, log)
    print("[cost scaling with chain length]", flush=True)
    scal_rows, expo = _scaling(small, repeats, log)
    print("[energy drift, double pendulum (0.5, 0.5)]", flush=True)
    if small:  # reuse the pendulum points (one per solver) instead of compiling seven more rollouts
        drift_T = 0.25
        drift_rows = [{"solver": r["solver"], "config": r["config"], "dt": r["dt"], "t_end": r["t_end"],
                       "energy_drift": r["energy_drift"], "violation_end": None}
                      for r in points if r["scene"] == "double_pendulum_mild"]
    else:
        drift_rows, drift_T = _drift(small, log)
    print("[XPBD paper check]", flush=True)
    paper = _xpbd_paper(small, log)
    print("[MuJoCo reference curves]", flush=True)
    mujoco_rows = _mujoco_points(small, scene_meta, log)

    budgets = {s: float(np.median([r["cost_s_per_sim_s"] for r in points if r["scene"] == s])) for s in scene_meta}
    fixed = {s: _fixed_cost([r for r in points if r["scene"] == s], budgets[s]) for s in scene_meta}
    result = {"machine": info, "mode": "small" if small else "full", "repeats": repeats,
              "cost": "median wall time of the compiled rollout (lower+compile timed apart) / simulated time",
              "scenes": scene_meta, "points": points, "tradeoff": trade, "scaling": scal_rows,
              "scaling_exponent": expo, "scaling_ref_links": 16 if small else 100,
              "drift": drift_rows, "drift_T": drift_T, "xpbd_paper": paper, "budgets": budgets,
              "fixed_cost": fixed, "mujoco": mujoco_rows}
    result["table"] = _table(result)
    result["table_solvers"] = [s for s in SOLVERS if f"| {s} |" in result["table"]]
    result["plots"] = _plots(result, out_dir)
    result["total_s"] = time.perf_counter() - t_start
    with open(os.path.join(out_dir, "speed_vs_error.json"), "w") as f:
        json.dump(result, f, indent=1)
    keys = ["scene", "solver", "config", "dt", "steps", "t_end", "iterations", "substeps", "compile_s", "wall_s",
            "cost_s_per_sim_s", "cost_us_per_step", "error", "max_stretch"]
    with open(os.path.join(out_dir, "speed_vs_error.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys + ["study", "n", "form"], extrasaction="ignore")
        w.writeheader()
        for r in points:
            w.writerow({**r, "study": "pareto"})
        for r in trade:
            w.writerow({**r, "study": "tradeoff"})
        for r in mujoco_rows:
            w.writerow({**r, "study": "mujoco"})
    _print_summary(result)
    print(f"wrote {out_dir}/speed_vs_error.json, speed_vs_error.csv and {len(result['plots'])} plots "
          f"in {result['total_s']:.0f} s", flush=True)
    return result


def _print_summary(result):
    print()
    for s, meta in result["scenes"].items():
        print(f"{s}: {meta['scene']}; error = {meta['error']}; reference: {meta['reference']}; "
              f"fixed-cost budget {result['budgets'][s] * 1e3:.3g} ms per simulated s")
    print()
    print(result["table"])
    print("err@B: smallest error among the solver's points costing <= B (the scene's median cost), '-': none; "
          "us/step and cost ~ n^p: chains of " +
          "/".join(str(n) for n in sorted({r['links'] for r in result['scaling']})) + " links, dt = 1/240; "
          "E drift: (E_end - E_0) / max kinetic energy, double pendulum (0.5, 0.5) rad")
    print("\nsubsteps vs iterations (heavy chain, dt = 1/60):")
    for r in result["tradeoff"]:
        print(f"  {r['config']:26s} cost {r['cost_s_per_sim_s'] * 1e3:9.3g} ms/s  tip err {r['error']:9.3g} m  "
              f"max stretch {r['max_stretch']:9.3g}")
    if result.get("mujoco"):
        print("\nMuJoCo hinge models of the same scenes (reference curves; rollout in C, recording every step):")
        for r in result["mujoco"]:
            print(f"  {r['scene']:22s} {r['config']:24s} dt 1/{round(1 / r['dt']):<5d} cost "
                  f"{r['cost_s_per_sim_s'] * 1e3:9.3g} ms/s  error {r['error']:9.3g} m")
    p = result["xpbd_paper"]
    print(f"\nXPBD paper check ({p['setup']}):")
    for r in p["rows"]:
        paper = "" if r["paper"] is None else f"   paper {r['paper'] * 100:.1f} %"
        print(f"  {r['iterations']:5d} iterations: {r['max_support_force_error_rel'] * 100:8.3g} %{paper}")
    print(f"  reference self-check (half the iterations): {p['reference_self_check'] * 100:.3g} %; "
          f"Direct(substeps=1) vs reference: {p['direct_vs_reference'] * 100:.3g} %")
