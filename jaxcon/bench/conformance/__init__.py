"""The conformance matrix: every solver on every case, against a reference nobody in the project wrote.

A *case* is a scene with an independent reference (an analytic value, SciPy, Box2D or pymunk in the same set-up)
and an acceptance bound. It is a function `fn(solver_name, full) -> Outcome` registered with `@case`; `full`
chooses the sizes `python -m jaxcon bench --conformance` runs, `full=False` the reduced sizes the suite runs
(`tests/test_conformance.py`). The solvers come from one list, `SOLVERS`, which the tests share.

A *cell* is one case run by one solver. It passes, fails, or is refused: the solver raised a ValueError before
anything ran whose message names another solver from `SOLVERS` that handles the case. Any other exception is a
failure, never a skip.

Case modules are the `cases_*.py` files of this package; each registers its cases on import.
"""
from __future__ import annotations

import importlib
import math
import pkgutil
from typing import Callable, NamedTuple

import jaxcon as jc

#: The solvers at their documented settings, in the order the tables print them. A case may pass keyword
#: overrides (a Penalty stiffness that suits its scene, say) and says so in its description.
SOLVERS: dict[str, Callable[..., jc.Solver]] = {
    "Penalty": lambda **kw: jc.Penalty(**{"stiffness": 1e5, "substeps": 30, **kw}),
    "Direct": lambda **kw: jc.Direct(**kw),
    "PGS": lambda **kw: jc.PGS(**{"iterations": 20, **kw}),
    "Jacobi": lambda **kw: jc.Jacobi(**{"iterations": 40, **kw}),
    "XPBD": lambda **kw: jc.XPBD(**kw),
    "SoftStep": lambda **kw: jc.SoftStep(**kw),
    "RATTLE": lambda **kw: jc.RATTLE(**kw),
}

CONTACT_SOLVERS = tuple(name for name, make in SOLVERS.items() if make().supports_contacts)

def for_compliance(solver_name: str) -> jc.Solver:
    """The solver at the settings docs/solvers.md gives for compliant constraints: its defaults, and XPBD with 16
    iterations (XPBD restarts its multipliers every substep, so a stiff spring's force needs the substep's sweeps
    to converge: at its default 1 iteration a compliant chain's static stretch is 35% off at dt 1/240 and 556% at
    dt 1/60, alpha 1e-4)."""
    return SOLVERS[solver_name](**({"iterations": 16} if solver_name == "XPBD" else {}))

#: Standard gravity (m/s^2), the cases' g (the library's default as well).
G = 9.81


def crossing_frequency(s, dt, centre=None) -> float:
    """The frequency (Hz) of a signal sampled every `dt` from its crossings of `centre` (default: its mean), each
    crossing time interpolated linearly between samples; NaN with fewer than three crossings."""
    import numpy as np
    s = np.asarray(s, np.float64)
    s = s - (np.mean(s) if centre is None else centre)
    k = np.nonzero(np.sign(s[:-1]) * np.sign(s[1:]) < 0)[0]
    if len(k) < 3:
        return float("nan")
    t = (k + s[k] / (s[k] - s[k + 1])) * dt
    return 0.5 * (len(t) - 1) / (t[-1] - t[0])


class Outcome(NamedTuple):
    """What a case measured for one solver: the number that the table prints, whether it meets the bound, and
    a line of detail (the bound and the reference)."""

    value: float
    ok: bool
    detail: str = ""


class Cell(NamedTuple):
    case: str
    solver: str
    status: str          # "PASS", "FAIL" or "REFUSED"
    value: float
    detail: str


class Case(NamedTuple):
    name: str
    fn: Callable[[str, bool], Outcome]
    description: str     # the scene, the reference and the bound, one paragraph
    reference: str       # the independent reference, a few words
    peers: dict          # {"Box2D": fn(full) -> float, ...}: the same number from a peer engine, where it has one
    solvers: tuple       # the solvers this case applies to (contacts: CONTACT_SOLVERS plus refusals)


CASES: dict[str, Case] = {}


def case(name: str, description: str, reference: str, *, peers: dict | None = None, solvers=None):
    """Register `fn(solver_name, full) -> Outcome` as the case `name`."""

    def register(fn):
        if name in CASES:
            raise ValueError(f"conformance case {name!r} registered twice")
        CASES[name] = Case(name, fn, " ".join(description.split()), reference, dict(peers or {}),
                           tuple(SOLVERS if solvers is None else solvers))
        return fn

    return register


def names_a_solver(message: str, refused: str) -> bool:
    """Whether a refusal's message names a solver of `SOLVERS` other than the refused one."""
    return any(f"jc.{name}" in message or f"{name}(" in message for name in SOLVERS if name != refused)


def run_cell(case_name: str, solver_name: str, full: bool = False) -> Cell:
    """Runs one cell: PASS or FAIL by the case's bound, REFUSED where the solver refused the case with a
    ValueError naming another solver (anything else raised is a FAIL with the error in the detail)."""
    c = CASES[case_name]
    try:
        out = c.fn(solver_name, full)
    except ValueError as e:
        if names_a_solver(str(e), solver_name):
            return Cell(case_name, solver_name, "REFUSED", math.nan, str(e).splitlines()[0])
        return Cell(case_name, solver_name, "FAIL", math.nan, f"ValueError: {e}")
    except Exception as e:  # noqa: BLE001 -- a cell that raises is a failure, reported with its cause
        first = (str(e).strip().splitlines() or [""])[0]
        return Cell(case_name, solver_name, "FAIL", math.nan, f"{type(e).__name__}: {first}")
    value = float(out.value)
    ok = bool(out.ok) and math.isfinite(value)
    return Cell(case_name, solver_name, "PASS" if ok else "FAIL", value, out.detail)


def load() -> dict:
    """Imports every `cases_*` module of this package (each registers its cases) and returns `CASES`."""
    for info in pkgutil.iter_modules(__path__):
        if info.name.startswith("cases_"):
            importlib.import_module(f"{__name__}.{info.name}")
    return CASES
