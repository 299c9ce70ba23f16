"""Independent references for the tests: planar pendulum chains in reduced (angle) coordinates, scipy DOP853.

The implementation lives in `jaxcon.bench.references.scipy_ode` (shared with the speed-vs-error bench)."""
from __future__ import annotations

from jaxcon.bench.references.scipy_ode import (  # noqa: F401
    RECORDING, _chain_rhs, chain_positions, double_pendulum_positions, double_pendulum_recording, driven_pendulum)

