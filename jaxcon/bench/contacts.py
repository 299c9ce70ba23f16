"""The disc box in jaxcon, and in pymunk and Box2D 2.3 when they are installed, in the same run.

    python -m jaxcon bench --contacts [N ...]          (default 64 256 1024; sizes up to 16384)

N discs (R = 0.5 m, 1 kg, friction 0.5, restitution 0) in staggered rows 1 m above the floor of a box
(`jc.scenes.disc_box`) fall and come to rest; dt = 1/60 s, 8 s simulated, 10 velocity iterations everywhere:

* jaxcon: `jc.scenes.disc_box(N, collide="grid")` (the neighbour grid), `jc.PGS(10)`, float32, and
  `jc.PGS(8, substeps=2, contact_passes=1)` (two substeps of 8 sweeps and one position pass, sharing the step's
  one neighbour search; it rests at 4096 discs, where PGS(10) and Box2D do not, at about PGS(10)'s cost there),
  and `jc.PGS(10, substeps=4, contact_passes=1)`, which rests at 4096 discs with every overlap under 5% of R
  (docs/contacts.md, piles at rest);
* pymunk (Chipmunk 7): `space.iterations = 10`, `collision_slop = 0.005` m (Box2D's linear slop; pymunk's
  default, 0.1 m, is meant for pixels and lets discs of 0.5 m sink 20% of R into each other), friction
  sqrt(0.5) on every shape (pymunk multiplies the two shapes' values: 0.5 per contact), no sleeping;
* Box2D 2.3 (the `box2d` package): `Step(dt, 10, 3)` (10 velocity, 3 position iterations), sleeping off
  (a sleeping pile costs nothing and would not be compared), friction 0.5 (Box2D takes the geometric mean).

pymunk's and Box2D's discs rotate (they are rigid bodies); jaxcon's are particles. Every engine is stepped in
chunks of `CHUNK` steps (jaxcon: one compiled rollout of CHUNK steps, called again and again; the others: a
Python loop of `step` calls), and at each N the engines take turns chunk by chunk (`_drive`), so a change in
the host's load falls on all of them alike. The cost is the median over the chunks of a chunk's wall time per
step, after compilation; jaxcon's compile time (lower + compile of that rollout, with the grid's search and
solve) is reported apart. The ratios (`paired_ratio`) are the median over the chunks of jaxcon's chunk time
over the peer's chunk at the same simulated time, measured side by side; in brackets, the same over the second
half of the run alone (the piles landed, at rest or nearly). At 4 s and 8 s: the fastest disc's speed (m/s;
"rest" is below 0.05) and the deepest overlap of two discs or a disc and a wall (as a fraction of R), all
measured the same way from each engine's positions (`deepest_overlap`); `overlap max` is the deepest at the
ends of all chunks.
"""
from __future__ import annotations

import time

import jax
import numpy as np

from jaxcon.bench.timing import machine

DT = 1 / 60
SECONDS = 8.0
CHUNK = 15
RADIUS = 0.5
FRICTION = 0.5
REST = 0.05


def deepest_overlap(x, width, radius=RADIUS) -> float:
    """Deepest overlap (m) of discs of `radius` at x [n, 2] with each other, the floor y = 0 and the walls x = 0,
    x = width: a cell list of side 2 radius (NumPy)."""
    x = np.asarray(x, np.float64)
    walls = max(0.0, float(np.max(radius - x[:, 1])), float(np.max(radius - x[:, 0])),
                float(np.max(x[:, 0] + radius - width)))
    cell = np.floor(x / (2 * radius)).astype(np.int64)
    cell -= cell.min(0)
    span = int(cell[:, 1].max()) + 3
    key = cell[:, 0] * span + cell[:, 1]
    order = np.argsort(key, kind="stable")
    skey = key[order]
    deepest = 0.0
    for dx in (0, 1):
        for dy in (-1, 0, 1):
            if dx == 0 and dy < 0:
                continue
            q = key + dx * span + dy
            lo, hi = np.searchsorted(skey, q, "left"), np.searchsorted(skey, q, "right")
            width_max = int((hi - lo).max()) if len(lo) else 0
            for s in range(width_max):
                ok = lo + s < hi
                i = np.nonzero(ok)[0]
                j = order[lo[ok] + s]
                keep = j != i if (dx, dy) != (0, 0) else j > i
                i, j = i[keep], j[keep]
                if len(i):
                    d = np.sqrt(np.sum((x[j] - x[i]) ** 2, 1))
                    deepest = max(deepest, float(np.max(2 * radius - d)))
    return max(deepest, walls)


class _Run:
    """What one engine's run measured."""

    def __init__(self, name, settings):
        self.name, self.settings = name, settings
        self.chunks, self.compile_s, self.at, self.overlap_max = [], None, {}, 0.0

    def record(self, t, x, v, width):
        ov = deepest_overlap(x, width) / RADIUS
        self.overlap_max = max(self.overlap_max, ov)
        for mark in (4.0, 8.0):
            if abs(t - mark) < DT / 2:
                self.at[mark] = (float(np.max(np.sqrt(np.sum(np.asarray(v) ** 2, -1)))), ov)

    def row(self, n):
        ms = 1e3 * float(np.median(self.chunks)) / CHUNK
        cells = [self.name, f"{n}", f"{ms:.2f}", "-" if self.compile_s is None else f"{self.compile_s:.1f}"]
        for mark in (4.0, 8.0):
            speed, ov = self.at.get(mark, (np.nan, np.nan))
            cells += [f"{speed:.3f}", f"{100 * ov:.2f}%"]
        rest = self.at.get(8.0, (np.inf,))[0] < REST
        return cells + [f"{100 * self.overlap_max:.2f}%", "yes" if rest else "no"], ms


def _steps(seconds):
    return int(round(seconds / DT / CHUNK)) * CHUNK


def _drive(engines, seconds):
    """Advance every engine `(run, chunk)` chunk by chunk in turn (engine 1's chunk k, engine 2's chunk k, ...):
    a change in the host's load between chunks then falls on every engine alike, and the same-run ratios
    (`main`) compare chunks measured side by side. Returns the runs."""
    for k in range(_steps(seconds) // CHUNK):
        for _, chunk in engines:
            chunk(k)
    return [run for run, _ in engines]


def jaxcon_engine(n, solver=None, name="jaxcon", **scene):
    """jaxcon's disc box as an engine for `_drive`: (run, chunk), compiled here (the compile time is the run's)."""
    from jaxcon.core.sim import rollout
    from jaxcon.scenes import disc_box, disc_box_layout
    from jaxcon.solvers.pgs import PGS

    solver = PGS(10) if solver is None else solver
    model, state = disc_box(n, dtype=np.float32, **scene)
    _, width = disc_box_layout(n)
    passes = "" if solver.contact_passes is None else f", contact_passes={solver.contact_passes}"
    out = _Run(name, f"PGS({solver.iterations}, substeps={solver.substeps}{passes}) grid float32")
    fn = jax.jit(lambda s: rollout(model, s, solver, DT, CHUNK, save_every=CHUNK)[0])
    t0 = time.perf_counter()
    compiled = fn.lower(state).compile()
    out.compile_s = time.perf_counter() - t0
    box = [state]

    def chunk(k):
        t0 = time.perf_counter()
        box[0] = jax.block_until_ready(compiled(box[0]))
        out.chunks.append(time.perf_counter() - t0)
        out.record((k + 1) * CHUNK * DT, np.asarray(box[0].x), np.asarray(box[0].v), width)
    return out, chunk


def run_jaxcon(n, seconds=SECONDS, solver=None, name="jaxcon", **scene):
    """jaxcon's disc box alone (`jaxcon_engine`), `seconds` of it."""
    return _drive([jaxcon_engine(n, solver, name, **scene)], seconds)[0]


def box2d_engine(n):
    """Box2D 2.3's disc box as an engine for `_drive` (module docstring)."""
    import Box2D
    from jaxcon.scenes import disc_box_layout

    x0, width = disc_box_layout(n)
    world = Box2D.b2World(gravity=(0, -9.81), doSleep=False)
    top = float(x0[:, 1].max()) + 10
    ground = world.CreateStaticBody()
    for a, b in (((0, 0), (width, 0)), ((0, 0), (0, top)), ((width, 0), (width, top))):
        ground.CreateEdgeFixture(vertices=[a, b], friction=FRICTION)
    density = 1.0 / (np.pi * RADIUS ** 2)
    bodies = []
    for p in x0:
        b = world.CreateDynamicBody(position=(float(p[0]), float(p[1])))
        b.CreateCircleFixture(radius=RADIUS, density=density, friction=FRICTION, restitution=0.0)
        bodies.append(b)
    out = _Run("Box2D " + Box2D.__version__, "Step(1/60, 10 velocity, 3 position), no sleeping")

    def chunk(k):
        t0 = time.perf_counter()
        for _ in range(CHUNK):
            world.Step(DT, 10, 3)
        out.chunks.append(time.perf_counter() - t0)
        x = np.array([tuple(b.position) for b in bodies])
        v = np.array([tuple(b.linearVelocity) for b in bodies])
        out.record((k + 1) * CHUNK * DT, x, v, width)
    return out, chunk


def run_box2d(n, seconds=SECONDS):
    return _drive([box2d_engine(n)], seconds)[0]


def pymunk_engine(n):
    """pymunk's disc box as an engine for `_drive` (module docstring)."""
    import pymunk
    from jaxcon.scenes import disc_box_layout

    x0, width = disc_box_layout(n)
    space = pymunk.Space()
    space.iterations = 10
    space.gravity = (0, -9.81)
    space.collision_slop = 0.005
    mu = float(np.sqrt(FRICTION))
    top = float(x0[:, 1].max()) + 10
    for a, b in (((0, 0), (width, 0)), ((0, 0), (0, top)), ((width, 0), (width, top))):
        seg = pymunk.Segment(space.static_body, a, b, 0.0)
        seg.friction, seg.elasticity = mu, 0.0
        space.add(seg)
    bodies = []
    for p in x0:
        body = pymunk.Body(1.0, pymunk.moment_for_circle(1.0, 0, RADIUS))
        body.position = (float(p[0]), float(p[1]))
        shape = pymunk.Circle(body, RADIUS)
        shape.friction, shape.elasticity = mu, 0.0
        space.add(body, shape)
        bodies.append(body)
    out = _Run("pymunk " + pymunk.version, "iterations 10, collision_slop 0.005 m, no sleeping")

    def chunk(k):
        t0 = time.perf_counter()
        for _ in range(CHUNK):
            space.step(DT)
        out.chunks.append(time.perf_counter() - t0)
        x = np.array([tuple(b.position) for b in bodies])
        v = np.array([tuple(b.velocity) for b in bodies])
        out.record((k + 1) * CHUNK * DT, x, v, width)
    return out, chunk


def run_pymunk(n, seconds=SECONDS):
    return _drive([pymunk_engine(n)], seconds)[0]


def paired_ratio(a: _Run, b: _Run, start: int = 0) -> float:
    """The median over chunks (from chunk `start` on) of a's chunk time over b's same chunk (measured side by
    side, `_drive`)."""
    return float(np.median(np.asarray(a.chunks[start:]) / np.asarray(b.chunks[start:])))


PEERS = (("Box2D", "Box2D", box2d_engine), ("pymunk", "pymunk", pymunk_engine))
#: jaxcon's configurations, (name, iterations, substeps, contact_passes or None for the default): the plain
#: PGS(10); 2 substeps of 8 sweeps with one position pass each (at rest at 4096 discs, overlaps to 12% of R while
#: landing, 1.79x to 1.82x Box2D there; with 10 sweeps 1.95x to 1.99x, with 7 the pile only just rests and with 5
#: it does not, docs/contacts.md); 4 substeps of 10 with one pass (every overlap under 5% of R at 4096 discs)
JAXCON = (("jaxcon", 10, 1, None), ("jaxcon 2 substeps 1 pass", 8, 2, 1), ("jaxcon 4 substeps 1 pass", 10, 4, 1))


def main(sizes=(64, 256, 1024), seconds=SECONDS):
    import importlib.util

    m = machine()
    print(f"disc box: R {RADIUS} m, 1 kg, friction {FRICTION}, restitution 0, dt 1/60 s, {seconds:g} s; "
          f"{m['cpu']}, {m['cores']} cores, {m['platform']}, jax {m['jax']}")
    peers = [(label, fn) for mod, label, fn in PEERS if importlib.util.find_spec(mod) is not None]
    missing = [label for mod, label, _ in PEERS if importlib.util.find_spec(mod) is None]
    if missing:
        print(f"not installed (pip install 'jaxcon[bench]'): {', '.join(missing)}")
    head = ["engine", "N", "ms/step", "compile s", "max v 4 s", "overlap/R 4 s", "max v 8 s", "overlap/R 8 s",
            "overlap max", "rest"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    results = []
    for n in sizes:
        from jaxcon.solvers.pgs import PGS
        engines = [jaxcon_engine(n, PGS(it, substeps=sub, contact_passes=cp), name) for name, it, sub, cp in JAXCON]
        runs = _drive(engines + [fn(n) for _, fn in peers], seconds)
        ours, others = runs[:len(JAXCON)], runs[len(JAXCON):]
        for r in runs:
            print("| " + " | ".join(r.row(n)[0]) + " |", flush=True)
        half = len(ours[0].chunks) // 2
        ratio = "; ".join(f"{j.name} / {k.name} {paired_ratio(j, k):.2f}x (second half {paired_ratio(j, k, half):.2f}x)"
                          for j in ours for k in others)
        if ratio:
            print(f"|  | {n} | {ratio} |", flush=True)
        results.append((n, runs))
    print("settings: " + "; ".join(f"{r.name}: {r.settings}" for r in results[0][1]))
    if len(results) > 1:
        print("cost growth with N (ms/step ratio between successive N, N ratio in brackets):")
        for name in [r.name for r in results[0][1]]:
            ms = [1e3 * float(np.median(next(r for r in runs if r.name == name).chunks)) / CHUNK for _, runs in results]
            steps = ", ".join(f"{ms[k + 1] / ms[k]:.1f}x ({results[k + 1][0] / results[k][0]:g}x)" for k in range(len(ms) - 1))
            print(f"  {name}: {steps}")
    return results
