"""Kernels per time step of a compiled rollout, counted in XLA's optimised HLO.

`step_kernels(compiled_text, steps)` finds the time loop (the outermost `while` whose known trip count is
`steps`) and counts what one pass of its body launches: its fusions and copies, with every loop nested in it
(a solver's sweeps over `iterations`) counted as many times as it runs. Instructions that produce a scalar
(loop counters and their copies) are left out: they are not passes over the batch. On a GPU every counted
kernel is a launch and a pass over memory; on the CPU each is a loop over the arrays it writes.

This reads the HLO text of `jax.jit(f).lower(...).compile().as_text()`; it does not time anything.
"""
from __future__ import annotations

import re
from typing import Dict, List, Tuple

_HEAD = re.compile(r"^(?:ENTRY )?%?([\w.\-]+) ")
_INSTR = re.compile(r"^(?:ROOT )?%?([\w.\-]+) = ")
_TRIP = re.compile(r'"known_trip_count":\{"n":"(\d+)"\}')
_BODY = re.compile(r"body=%?([\w.\-]+)")
_CALLS = re.compile(r"(?:to_apply|calls|true_computation|false_computation)=%?([\w.\-]+)")
_BRANCHES = re.compile(r"branch_computations=\{([^}]*)\}")

#: What an instruction that does no work of its own is (no kernel, no pass over memory).
_FREE = {"parameter", "get-tuple-element", "tuple", "constant", "bitcast", "after-all", "partition-id",
         "replica-id", "opt-barrier"}


def _computations(text: str) -> Dict[str, List[str]]:
    comps, cur = {}, None
    for line in text.splitlines():
        if not line.startswith((" ", "}")) and line.rstrip().endswith("{"):
            m = _HEAD.match(line)
            if m:
                cur = m.group(1)
                comps[cur] = []
            continue
        if line.startswith("}"):
            cur = None
        elif cur is not None and _INSTR.match(line.strip()):
            comps[cur].append(line.strip())
    return comps


def _shape_and_op(instr: str) -> Tuple[str, str]:
    """(result shape text, opcode) of one HLO instruction."""
    rhs = instr.split(" = ", 1)[1]
    if rhs.startswith("("):                           # a tuple shape: skip to its closing parenthesis
        depth = 0
        for k, c in enumerate(rhs):
            depth += (c == "(") - (c == ")")
            if depth == 0:
                return rhs[: k + 1], rhs[k + 1:].strip().split("(", 1)[0]
    shape, rest = rhs.split(" ", 1)
    return shape, rest.split("(", 1)[0]


def _scalar(shape: str) -> bool:
    return re.fullmatch(r"[a-z]+\d*\[\](\{[^}]*\})?", shape) is not None


def _count(comps, name, mult, out):
    for instr in comps[name]:
        shape, op = _shape_and_op(instr)
        if op == "while":
            trip = _TRIP.search(instr)
            inner = _BODY.search(instr).group(1)
            _count(comps, inner, mult * (int(trip.group(1)) if trip else 1), out)
            if not trip:
                out["unknown_trip_loops"] = out.get("unknown_trip_loops", 0) + 1
            continue
        if op in ("call", "conditional"):
            for sub in _CALLS.findall(instr) + [b.strip().lstrip("%") for m in _BRANCHES.findall(instr)
                                                for b in m.split(",")]:
                if sub in comps:
                    _count(comps, sub, mult, out)
            continue
        if op in _FREE or _scalar(shape):
            continue
        key = op if op in ("fusion", "copy") else "other"
        out[key] = out.get(key, 0) + mult


def step_kernels(text: str, steps: int) -> dict:
    """Kernels one time step launches: {"fusion", "copy", "other", "total"} (see the module docstring). `text`
    is a compiled program's HLO (`.compile().as_text()`), `steps` the rollout's number of steps, which
    identifies the time loop; a loop inside it counts `trip count` times."""
    comps = _computations(text)
    calls = {c: set(_BODY.findall(" ".join(lines))) | set(_CALLS.findall(" ".join(lines))) for c, lines in
             comps.items()}
    depth, frontier = {}, [c for c in comps if not any(c in v for v in calls.values())]
    level = 0
    while frontier:                                   # nesting depth of every computation from the roots
        nxt = []
        for c in frontier:
            if c not in depth:
                depth[c] = level
                nxt += [s for s in calls[c] if s in comps]
        frontier, level = nxt, level + 1
    loops = []
    for c, lines in comps.items():
        for instr in lines:
            trip = _TRIP.search(instr)
            if " while(" in instr and trip and int(trip.group(1)) == int(steps):
                loops.append((depth.get(c, 0), _BODY.search(instr).group(1)))
    if not loops:
        raise ValueError(f"step_kernels: no loop of {steps} trips in this program (is `steps` the rollout's?)")
    out = {"fusion": 0, "copy": 0, "other": 0}
    _count(comps, min(loops)[1], 1, out)
    out["total"] = out["fusion"] + out["copy"] + out["other"]
    return out


def compiled_step_kernels(fn, args, steps: int) -> dict:
    """`step_kernels` of `jax.jit(fn)` compiled for `args` (a tuple)."""
    import jax
    return step_kernels(jax.jit(fn).lower(*args).compile().as_text(), steps)
