"""Hubs and heavy chains: a particle with many constraints is solved as one block, whether its constraints are
rods or `jc.Constraint` rows; split impulses hold chains with heavy end masses."""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

import jaxcon as jc
from jaxcon.bench.conformance import SOLVERS, Outcome, case

HUB_BOUND = 1e-4


def _user_length(x, p):
    return p["L"] - jnp.sqrt(jnp.sum((x[1] - x[0]) ** 2))


def _hub(n_spokes: int, kind: str):
    """A free hub at the origin and `n_spokes` rim particles on the unit circle, every particle 1 kg, each spoke
    a rod, a `jc.Constraint` of the user's own distance function, or a `jc.constraints.distance`; float32."""
    a = 2 * np.pi * np.arange(n_spokes) / n_spokes
    x = np.concatenate([np.zeros((1, 2)), np.stack([np.cos(a), np.sin(a)], -1)]).astype(np.float32)
    spokes = [(0, k + 1) for k in range(n_spokes)]
    if kind == "rods":
        return jc.build(x, 1.0, rods=spokes, dtype=np.float32)
    if kind == "jc.Constraint":
        con = jc.Constraint(_user_length, spokes, {"L": np.ones(n_spokes, np.float32)})
    else:
        con = jc.constraints.distance(spokes, positions=x)
    return jc.build(x, 1.0, constraints=con, dtype=np.float32)


def _hub_violation(solver_name: str, runs) -> Outcome:
    """The largest violation over the runs [(spokes, kind)] of 1 s (full) at dt 1/240."""
    worst, parts = 0.0, []
    for n_spokes, kind, steps in runs:
        model, state = _hub(n_spokes, kind)
        _, traj = jc.rollout(model, state, SOLVERS[solver_name](), 1 / 240, steps)
        assert traj.x.dtype == jnp.float32
        v = float(jnp.max(jc.violation(model, traj.x)))
        worst = max(worst, v) if np.isfinite(v) else np.inf
        parts.append(f"{n_spokes} {kind} {v:.1e}")
    return Outcome(worst, worst <= HUB_BOUND, f"max violation <= {HUB_BOUND:g} (exact: 0); " + ", ".join(parts))


@case("hub of rods float32",
      """A free hub joined by rods to N rim particles on the unit circle (every particle 1 kg), released from rest
      with every spoke at its rest length under gravity, float32, dt 1/240: the exact motion is a rigid fall, with
      no constraint force and nothing stretched. N = 16 and 64 for 60 steps (full: 16, 64 and 256 for 240
      steps). The number: the largest relative violation. Bound: 1e-4.""",
      "analytic: no stretch")
def hub_of_rods(solver_name: str, full: bool) -> Outcome:
    sizes, steps = ((16, 64, 256), 240) if full else ((16, 64), 60)
    return _hub_violation(solver_name, [(n, "rods", steps) for n in sizes])


@case("hub of sets float32",
      """The hub of `hub of rods float32` with its spokes written as a `jc.Constraint` set of the user's own
      distance function and as `jc.constraints.distance`: the same rows, which must be solved as one block at the
      hub as rods are. Reduced: 16 spokes as `jc.Constraint`, 64 as `distance`, 60 steps (full: both forms at 16,
      64 and 256 spokes, 240 steps). The number: the largest violation (m). Bound: 1e-4.""",
      "analytic: no stretch")
def hub_of_sets(solver_name: str, full: bool) -> Outcome:
    if full:
        runs = [(n, kind, 240) for n in (16, 64, 256) for kind in ("jc.Constraint", "distance")]
    else:
        runs = [(16, "jc.Constraint", 60), (64, "distance", 60)]
    return _hub_violation(solver_name, runs)


#: The documented settings for split impulses on heavy chains (docs/solvers.md, "Split impulses"): PGS(20) with
#: 4 substeps. One step of PGS(20, stabilization="split") leaves a 40-link chain with a 100:1 end mass 22% long.
HEAVY_CHAIN_SOLVER = dict(iterations=20, substeps=4, stabilization="split")


@case("heavy chain split impulses",
      """A chain of N links (2 m, 0.2 kg over its bobs) hanging from a pivot with an end mass of R times a bob's,
      released at 0.3 rad with every link 25% longer than its rest length, dt 1/240, 1 s, with split impulses at
      their documented settings for heavy chains, PGS(20, substeps=4, stabilization="split"). Split impulses are
      a stabilisation option of the sequential-impulse solvers, and the acceptance asks it of PGS(20); the
      position-level solvers (XPBD, RATTLE) and the others have no such option, so the case is PGS's only.
      Reduced: N = 20, R = 100 (full: N = 10, 20, 40 by R = 20, 50, 100). The number: the largest relative
      stretch of a link at 1 s. Bound: 1%.""",
      "analytic: rest lengths", solvers=("PGS",))
def heavy_chain_split(solver_name: str, full: bool) -> Outcome:
    runs = [(n, r) for n in (10, 20, 40) for r in (20, 50, 100)] if full else [(20, 100)]
    worst, parts = 0.0, []
    for n_links, ratio in runs:
        model, state = jc.scenes.chain(n_links, 2.0, 0.2, end_mass=ratio * 0.2 / n_links, angle=0.3)
        model = model.replace(rest_length=model.rest_length * 0.8)
        final, _ = jc.rollout(model, state, SOLVERS[solver_name](**HEAVY_CHAIN_SOLVER), 1 / 240, 240)
        s = float(jnp.max(jc.violation(model, final.x)))
        worst = max(worst, s) if np.isfinite(s) else np.inf
        parts.append(f"{n_links} links {ratio}:1 {s:.2%}")
    return Outcome(worst, worst < 0.01, "largest link stretch at 1 s < 1%; " + ", ".join(parts))
