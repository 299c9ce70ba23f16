"""Independent references for the tests: planar pendulum chains in reduced (angle) coordinates, scipy DOP853.

The implementation lives in `jaxcon._reference` (shared with `python -m jaxcon bench --speed-vs-error`)."""
from __future__ import annotations

from jaxcon._reference import _chain_rhs, chain_positions, double_pendulum_positions  # noqa: F401
