"""jaxcon: differentiable constrained particle dynamics in JAX."""
from . import scenes as scenes
from ._model import Model as Model, State as State, Trajectory as Trajectory, build as build
from ._sim import batched_rollout as batched_rollout, rollout as rollout, step as step
from ._solver import PGS as PGS, Solver as Solver
from ._jacobi import Jacobi as Jacobi
from ._xpbd import XPBD as XPBD
from ._penalty import Penalty as Penalty
from ._direct import Direct as Direct
from ._softstep import SoftStep as SoftStep
from ._rattle import RATTLE as RATTLE
from ._diagnostics import (
    energy as energy,
    energy_drift as energy_drift,
    kinetic_energy as kinetic_energy,
    violation as violation,
)
from ._diagnose import Diagnosis as Diagnosis, diagnose as diagnose
from ._fit import FitResult as FitResult, fit as fit

__version__ = "0.1.0"
