"""The package's shape: no import cycles, the library never imports the benchmarks, no function over 100 lines,
and the public names stay where users find them."""
import ast
import pathlib

import jaxcon as jc

PKG = pathlib.Path(jc.__file__).parent
LIBRARY = ("jaxcon.core", "jaxcon.solvers", "jaxcon.identification", "jaxcon.diagnostics", "jaxcon.scenes")


def _modules():
    out = {}
    for p in sorted(PKG.rglob("*.py")):
        parts = p.relative_to(PKG.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = (p, ast.parse(p.read_text()))
    return out


def _resolve(module, node, names):
    """Modules of the package that an import statement (anywhere in `module`, function bodies included) loads."""
    out = set()
    if isinstance(node, ast.Import):
        return {a.name for a in node.names if a.name in names}
    base = node.module or ""
    if node.level:
        pkg = module.split(".")
        pkg = pkg[: len(pkg) - node.level + (1 if module in _PACKAGES else 0)]
        base = ".".join(pkg + ([base] if base else []))
    for a in node.names:
        if f"{base}.{a.name}" in names:
            out.add(f"{base}.{a.name}")       # a submodule
        elif base in names:
            out.add(base)                     # a name from a module (or from a package's __init__)
    return out


_PACKAGES = set()


def _graph():
    mods = _modules()
    _PACKAGES.update(n for n, (p, _) in mods.items() if p.name == "__init__.py")
    graph = {}
    for name, (_, tree) in mods.items():
        deps = set()
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                deps |= _resolve(name, node, mods)
        graph[name] = deps - {name}
    return graph


def test_no_import_cycles():
    graph = _graph()
    # the top-level package re-exports the API and may import anything; nothing inside may import it back, except
    # the conformance cases, which run the public API as a user does (the library never imports bench: below)
    for name, deps in graph.items():
        user = name == "jaxcon" or name.startswith("jaxcon.bench.conformance")
        assert "jaxcon" not in deps or user, f"{name} imports the top-level package (a cycle)"
    state, stack = {}, []

    def visit(n):
        state[n] = "open"
        stack.append(n)
        for d in sorted(graph[n]):
            if state.get(d) == "open":
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(d):] + [d]))
            if d not in state:
                visit(d)
        stack.pop()
        state[n] = "done"

    for n in sorted(graph):
        if n not in state:
            visit(n)


def test_library_does_not_import_the_benchmarks():
    graph = _graph()
    for name, deps in graph.items():
        if name.startswith(LIBRARY):
            bad = sorted(d for d in deps if d.startswith("jaxcon.bench"))
            assert not bad, f"{name} imports {bad}: the library must not depend on the benchmarks"


def test_core_imports_nothing_above_it():
    """`core` (models, layouts, rows, the time loop, the contact data types) depends on no solver and nothing else
    of the package: an import inside a function counts as one at the top (`_graph` reads every import
    statement). Solvers consume what core makes (docs/architecture.md)."""
    graph = _graph()
    assert graph["jaxcon.core.sim"] and graph["jaxcon.core.system"]            # the graph sees their imports
    for name, deps in graph.items():
        if name.startswith("jaxcon.core"):
            bad = sorted(d for d in deps if not d.startswith("jaxcon.core"))
            assert not bad, f"{name} imports {bad}: core must not depend on solvers or anything above it"


def test_the_import_graph_counts_imports_inside_functions(tmp_path):
    """The check above would miss `def f(): from jaxcon.solvers import contact` if `_graph` read only the
    module's top level."""
    tree = ast.parse("def f():\n    from jaxcon.solvers.contact import rows\n")
    names = {"jaxcon.solvers.contact": None, "jaxcon.solvers": None}
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            found |= _resolve("jaxcon.core.sim", node, names)
    assert found == {"jaxcon.solvers.contact"}


#: The contact system's obstacle-shape leaves and counts: only `core` may read them.
_SHAPE_NAMES = {"plane_normal", "plane_offset", "sphere_centre", "sphere_radius", "n_planes", "n_spheres"}


def test_solvers_know_no_obstacle_shape():
    """Obstacle shapes (planes, spheres) are the contact kind's, in `core` (`contact_rows.obstacle_gap`, the rows):
    no module under `jaxcon/solvers` reads a shape's leaves or counts, so a new shape changes no solver. Code
    only: names in docstrings and comments do not count."""
    bad = []
    for name, (path, tree) in _modules().items():
        if not name.startswith("jaxcon.solvers"):
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and node.attr in _SHAPE_NAMES:
                bad.append(f"{name}:{node.lineno} .{node.attr}")
    assert not bad, bad
    probe = ast.parse("def f(cs, q):\n    return cs.plane_normal[q]\n")      # the check sees an attribute read
    assert any(isinstance(n, ast.Attribute) and n.attr in _SHAPE_NAMES for n in ast.walk(probe))


def test_no_function_longer_than_100_lines():
    long = []
    for name, (path, tree) in _modules().items():
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                start = min([node.lineno] + [d.lineno for d in node.decorator_list])
                if node.end_lineno - start + 1 > 100:
                    long.append(f"{name}.{node.name}: {node.end_lineno - start + 1} lines")
    assert not long, long


def test_public_api_is_where_users_find_it():
    public = {"scenes", "Model", "State", "Trajectory", "build", "rollout", "batched_rollout", "step", "Solver",
              "PGS", "Jacobi", "XPBD", "Penalty", "Direct", "SoftStep", "RATTLE", "energy", "energy_drift",
              "kinetic_energy", "violation", "penetration", "Diagnosis", "diagnose", "FitResult", "fit"}
    missing = sorted(n for n in public if not hasattr(jc, n))
    assert not missing, missing
    assert callable(jc.fit) and callable(jc.diagnose)          # not shadowed by a submodule of the same name
    for name in ("PGS", "Jacobi", "XPBD", "Penalty", "Direct", "SoftStep", "RATTLE"):
        assert issubclass(getattr(jc, name), jc.Solver)
        assert getattr(jc, name).__module__ == f"jaxcon.solvers.{name.lower()}"   # one module per solver


def test_model_repr_speaks_to_users():
    model, state = jc.scenes.cloth(8, 8)
    r = repr(model)
    assert r == (f"Model(64 particles (2 fixed), {model.n_constraints} constraints ({model.n_constraints} rods), "
                 f"{model.topology.n_colours} colours, dim=3, dtype={model.rest_length.dtype})"), r
    for internal in ("strided", "parity", "view", "block"):
        assert internal not in r
    rope, _ = jc.scenes.chain(n_links=3, kind="rope")
    assert "3 constraints (3 ropes)" in repr(rope) and "(1 fixed)" in repr(rope)
    assert repr(state) == f"State(x=(64, 3), v=(64, 3), lam=({model.n_constraints},), dtype={state.x.dtype})"
