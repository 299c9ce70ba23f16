"""`python -m jaxcon bench --conformance`: every case at full size with every solver (and the peer engines
where a case has them), printed as it runs and written as a Markdown table of cases by solvers."""
from __future__ import annotations

import datetime
import math
import time

import jax

from jaxcon.bench import conformance as C
from jaxcon.bench.timing import machine


def _fmt(cell) -> str:
    if cell is None:
        return "n/a"
    if cell.status == "REFUSED":
        return "REFUSED"
    value = "error" if math.isnan(cell.value) else f"{cell.value:.3g}"
    return f"{value} {cell.status}"


def run(full: bool = True, cases=None, solvers=None, log=print) -> tuple:
    """Runs the cells; returns (cells {(case, solver): Cell}, peers {(case, peer): value or message})."""
    table = C.load()
    names = list(table) if not cases else list(cases)
    unknown = [n for n in names if n not in table]
    if unknown:
        raise ValueError(f"bench --conformance: unknown case(s) {unknown}; the cases are {sorted(table)}")
    cells, peers = {}, {}
    for name in names:
        c = table[name]
        for s in c.solvers:
            if solvers and s not in solvers:
                continue
            t = time.perf_counter()
            cells[name, s] = cell = C.run_cell(name, s, full)
            log(f"{name:34s} {s:9s} {_fmt(cell):18s} {time.perf_counter() - t:6.1f} s  {cell.detail}")
        for peer, fn in c.peers.items():
            try:
                peers[name, peer] = float(fn(full))
            except ImportError as e:
                peers[name, peer] = f"not installed ({e.name})"
            log(f"{name:34s} {peer:9s} {peers[name, peer]}")
    return cells, peers


def markdown(cells: dict, peers: dict, full: bool) -> str:
    m = machine()
    solvers = list(C.SOLVERS)
    peer_names = sorted({p for _, p in peers})
    cases = list(dict.fromkeys(c for c, _ in cells))
    out = ["# Conformance", "",
           "Every solver on every case, against a reference that jaxcon did not write. Written by "
           "`python -m jaxcon bench --conformance" + ("" if full else " --small") + "`; the suite runs the same "
           "cases at reduced sizes (`tests/test_conformance.py`). A cell is the case's number and PASS or FAIL "
           "by its bound, or REFUSED: the solver refuses the scene before running, with an error that names a "
           "solver that handles it. Peer engines, where a case has them, give the same number in the same set-up.",
           "", f"Run on {datetime.date.today().isoformat()}: {m['cpu']} ({m['cores']} cores), {m['platform']}, "
           f"jax {m['jax']}, float64 unless the case says float32. Solvers at the settings of "
           "`jaxcon.bench.conformance.SOLVERS`.", "",
           "| case | " + " | ".join(solvers + peer_names) + " |",
           "|---|" + "---|" * (len(solvers) + len(peer_names))]
    for c in cases:
        row = [_fmt(cells.get((c, s))) for s in solvers]
        row += [(f"{peers[c, p]:.3g}" if isinstance(peers.get((c, p)), float) else str(peers.get((c, p), "")))
                for p in peer_names]
        out.append(f"| {c} | " + " | ".join(row) + " |")
    out += ["", "## The cases", ""]
    table = C.CASES
    for c in cases:
        out += [f"**{c}** (reference: {table[c].reference}). {table[c].description}", ""]
    failed = [f"{c} / {s}: {cell.detail}" for (c, s), cell in cells.items() if cell.status == "FAIL"]
    if failed:
        out += ["## Failing cells", ""] + [f"- {f}" for f in failed] + [""]
    return "\n".join(out) + "\n"


def main(full: bool = True, out: str = "docs/conformance.md", cases=None, solvers=None) -> int:
    jax.config.update("jax_enable_x64", True)
    cells, peers = run(full, cases, solvers)
    text = markdown(cells, peers, full)
    if out:
        with open(out, "w") as f:
            f.write(text)
        print(f"wrote {out}")
    n_fail = sum(cell.status == "FAIL" for cell in cells.values())
    print(f"{len(cells)} cells: {sum(c.status == 'PASS' for c in cells.values())} PASS, "
          f"{sum(c.status == 'REFUSED' for c in cells.values())} REFUSED, {n_fail} FAIL")
    return 1 if n_fail else 0
