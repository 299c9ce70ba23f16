"""jaxcon: differentiable constrained particle dynamics in JAX.

The public API is what this module exports (see docs/api.md). The package is laid out as:

  core/            the model, its static topology and internal layout, contact topology, argument checks,
                   step / rollout loops
  solvers/         one module per solver (PGS, Jacobi, Direct, Penalty, XPBD, SoftStep, RATTLE), and contact.py
                   (contacts as unilateral velocity constraints)
  identification/  fitting physical parameters to observed motion (`fit`)
  diagnostics.py   violation, penetration, energies, drift and `diagnose`
  scenes.py        ready-made scenes (pendulums, chains, cloth; billiards, drape, falling chain, disc box)
  bench/           the command line, benchmarks and their independent references (not library API)
"""
from jaxcon import scenes as scenes
from jaxcon.core import constraints as constraints
from jaxcon.core.constraints import Constraint as Constraint
from jaxcon.core.model import Model as Model, State as State, Trajectory as Trajectory, build as build
from jaxcon.core.batch import batched_rollout as batched_rollout
from jaxcon.core.sim import rollout as rollout, step as step
from jaxcon.core.system import Solver as Solver
from jaxcon.diagnostics import (
    Diagnosis as Diagnosis,
    diagnose as diagnose,
    energy as energy,
    energy_drift as energy_drift,
    kinetic_energy as kinetic_energy,
    penetration as penetration,
    violation as violation,
)
from jaxcon.identification.fit import FitResult as FitResult, fit as fit
from jaxcon.identification.uncertainty import (
    IdentifiabilityWarning as IdentifiabilityWarning,
    MisfitWarning as MisfitWarning,
)
from jaxcon.solvers.direct import Direct as Direct
from jaxcon.solvers.jacobi import Jacobi as Jacobi
from jaxcon.solvers.penalty import Penalty as Penalty
from jaxcon.solvers.pgs import PGS as PGS
from jaxcon.solvers.rattle import RATTLE as RATTLE
from jaxcon.solvers.softstep import SoftStep as SoftStep
from jaxcon.solvers.xpbd import XPBD as XPBD

__version__ = "0.1.0"
