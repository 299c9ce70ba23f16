"""The solvers, one module each. Each is a pytree dataclass (static options, differentiable physical
parameters) implementing `Solver._step`; `common` holds what the velocity-level ones share."""
