"""jaxcon: differentiable constrained particle dynamics in JAX."""
from . import scenes as scenes
from ._model import Model as Model, State as State, Trajectory as Trajectory, build as build
from ._sim import rollout as rollout, step as step
from ._solver import PGS as PGS, Solver as Solver
from ._diagnostics import energy as energy, energy_drift as energy_drift, kinetic_energy as kinetic_energy, violation as violation

__version__ = "0.1.0"
from ._direct import Direct as Direct
from ._softstep import SoftStep as SoftStep
from ._rattle import RATTLE as RATTLE
