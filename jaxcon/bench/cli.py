"""Command line: `python -m jaxcon demo` and `python -m jaxcon bench`."""
from __future__ import annotations

import argparse
import os

import jax

from jaxcon.bench.demo import demo
from jaxcon.bench.suite import bench


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {value}")
    return value


DESCRIPTION = """jaxcon: differentiable constrained particle dynamics in JAX.

  demo    each scene with a solver that suits it (violation and energy drift), plain PGS for comparison,
          and a rest-length identification with jc.fit
  bench   speed against error: median step times after compilation, compile time apart, the error reached,
          batched throughput and gradient compile time; --speed-vs-error sweeps every solver; --contacts runs
          the disc box against pymunk and Box2D; --conformance runs every solver on every case against
          independent references (docs/conformance.md); --emitters measures XLA's CPU emitters' compile times"""


class _Parser(argparse.ArgumentParser):
    """Bad arguments end in one line naming the problem (and a pointer to --help), not a usage dump."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _parser() -> argparse.ArgumentParser:
    p = _Parser(prog="python -m jaxcon", description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", metavar="{demo,bench}", parser_class=_Parser)
    d = sub.add_parser("demo", help="run each scene with a suitable solver, then plain PGS, then a fit",
                       description="Each scene with a solver that suits it, the same scenes with PGS(10) for "
                                   "comparison (failures labelled), and a rest-length identification.")
    d.add_argument("--small", action="store_true", help="reduced sizes (seconds instead of a minute; the tests use it)")
    b = sub.add_parser("bench", help="speed against error: step times after compilation, compile time, error",
                       description="Median step time after compilation, compile time apart, and the error reached, "
                                   "for each scene in float32 and float64; batched throughput; gradient compile "
                                   "time against a plain PGS. Writes JSON.")
    b.add_argument("--small", action="store_true", help="reduced sizes (seconds instead of minutes; the tests use it)")
    b.add_argument("--repeats", type=_positive_int, default=7, metavar="N",
                   help="timed runs per measurement after compilation; the median is reported (default 7)")
    b.add_argument("--out", default="bench.json", metavar="PATH",
                   help="JSON output path, checked before running ('' for none; default bench.json)")
    b.add_argument("--f32-only", action="store_true", help="skip the float64 runs")
    b.add_argument("--no-batched", action="store_true", help="skip the batched (vmap) throughput section")
    b.add_argument("--batched", nargs="*", type=_positive_int, metavar="N",
                   help="instead: only the batched section on JAX's default backend (throughput and kernels per "
                        "step of vmap, batched_rollout, batched_rollout in one piece and the plain reference), "
                        "double pendulums at batch sizes N (default 1 1024 16384 131072) and 64 cloths")
    b.add_argument("--speed-vs-error", action="store_true",
                   help="instead: sweep every solver over iterations, substeps and dt; error against cost "
                        "(JSON, CSV and, with matplotlib, plots)")
    b.add_argument("--contact-grid", nargs="*", type=_positive_int, metavar="N",
                   help="instead: PGS(10)'s cost per step with all-pairs contacts against the neighbour grid, for "
                        "lattices of N discs (default 256 1024 2048; with --small 16 64, 2 steps); JSON to --out")
    b.add_argument("--contacts", nargs="*", type=_positive_int, metavar="N",
                   help="instead: the disc box (N discs dropped into a box, PGS(10) on the grid, float32) "
                        "against pymunk and Box2D 2.3 when installed, in the same run: ms/step, compile time, "
                        "max speed and overlap at 4 s and 8 s (default 64 256 1024; up to 16384)")
    b.add_argument("--emitters", action="store_true",
                   help="instead: compile and run time of five programs with XLA's CPU fusion emitters (the "
                        "default) and without them (XLA_FLAGS=--xla_cpu_use_fusion_emitters=false), in alternating "
                        "child processes, and the difference of their outputs (JSON to --out, default bench.json)")
    b.add_argument("--conformance", nargs="*", metavar="CASE",
                   help="instead: the conformance matrix, every case (or the named ones) with every solver at "
                        "full size, with Box2D and pymunk where a case has them; writes a Markdown table to --out "
                        "(default docs/conformance.md; --small: the suite's reduced sizes). Exit status 1 if a "
                        "cell fails")
    b.add_argument("--out-dir", default="speed_vs_error", metavar="DIR",
                   help="output folder of --speed-vs-error (created if missing; default speed_vs_error)")
    return p


def _writable_folder(path) -> bool:
    folder = os.path.abspath(path)
    while not os.path.exists(folder):           # a folder that does not exist yet: its nearest existing parent
        folder = os.path.dirname(folder)
    return os.path.isdir(folder) and os.access(folder, os.W_OK)


def _unwritable_file(path) -> str:
    """Why the bench could not write its JSON to `path` ('' if it can): checked before anything runs."""
    path = os.path.abspath(path)
    folder = os.path.dirname(path)
    if os.path.isdir(path):
        return "is a directory; give a file path for the JSON (e.g. DIR/bench.json)"
    if not os.path.isdir(folder) or not os.access(folder, os.W_OK | os.X_OK):
        return f"folder {folder} does not exist or is not writable"
    if os.path.exists(path) and not os.access(path, os.W_OK):
        return "exists and is not writable"
    return ""


def main(argv=None) -> int:
    p = _parser()
    args = p.parse_args(argv)
    if args.cmd is None:
        p.error("choose a command: demo or bench")
    if args.cmd == "bench" and args.conformance is not None and args.out == "bench.json":
        args.out = os.path.join("docs", "conformance.md")
    if args.cmd == "bench" and args.out:
        problem = _unwritable_file(args.out)
        if problem:
            p.error(f"--out {args.out}: {problem}")
    if args.cmd == "bench" and args.speed_vs_error:
        if os.path.exists(args.out_dir) and not os.path.isdir(args.out_dir) or not _writable_folder(args.out_dir):
            p.error(f"--out-dir {args.out_dir}: not a writable folder")
        from jaxcon.bench.speed_vs_error import run
        run(small=args.small, out_dir=args.out_dir)
        return 0
    if args.cmd == "bench" and args.conformance is not None:
        from jaxcon.bench.conformance.table import main as conformance
        return conformance(full=not args.small, out=args.out, cases=args.conformance or None)
    if args.cmd == "bench" and args.contact_grid is not None:
        from jaxcon.bench.contact_grid import main as contact_grid
        contact_grid(tuple(args.contact_grid), small=args.small, out_path=args.out or None)
        return 0
    if args.cmd == "bench" and args.contacts is not None:
        from jaxcon.bench.contacts import main as contacts
        contacts(tuple(args.contacts) or (64, 256, 1024))
        return 0
    if args.cmd == "bench" and args.emitters:
        from jaxcon.bench.emitters import main as emitters
        emitters(args.repeats, out_path=args.out or None)
        return 0
    if args.cmd == "bench" and args.batched is not None:
        from jaxcon.bench.suite import batched_only
        return batched_only(args)
    if args.cmd == "bench" and not args.f32_only:
        jax.config.update("jax_enable_x64", True)
    return {"demo": demo, "bench": bench}[args.cmd](args)
