"""Every notebook runs top to bottom in a fresh Jupyter kernel (nbclient), as a user runs it, at reduced size
(JAXCON_NOTEBOOK_SMALL=1), and draws its figures. The committed notebooks carry their full-size outputs (made
by `python notebooks/_make.py --execute`), so a reader sees every plot without running anything; their cell
sources must be the ones `notebooks/_make.py` writes."""
import importlib.util
import json
import pathlib

import pytest

HERE = pathlib.Path(__file__).parent.parent / "notebooks"
NOTEBOOKS = sorted(HERE.glob("*.ipynb"))


def _make():
    spec = importlib.util.spec_from_file_location("notebooks_make", HERE / "_make.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _images(nb):
    return [o for c in nb["cells"] if c["cell_type"] == "code" for o in c.get("outputs", [])
            if "image/png" in o.get("data", {})]


def test_notebooks_found():
    assert {p.name for p in NOTEBOOKS} == {
        "01_constraints.ipynb", "02_speed_vs_error.ipynb", "03_system_identification.ipynb", "04_contacts.ipynb",
        "05_driven_systems.ipynb", "06_constraints.ipynb"}


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_committed_notebook_matches_its_source_and_shows_its_plots(path):
    make = _make()
    committed = json.loads(path.read_text())
    source = make.build(path.stem, dict(make.NOTEBOOKS)[path.stem])
    text = lambda src: "".join(src) if isinstance(src, list) else src     # noqa: E731
    assert [text(c["source"]) for c in committed["cells"]] == [text(c["source"]) for c in source["cells"]], (
        f"{path.name} is out of date: run `python notebooks/_make.py --execute`")
    code = [c for c in committed["cells"] if c["cell_type"] == "code"]
    assert all(c["execution_count"] is not None for c in code), f"{path.name} was not executed"
    errors = [o for c in code for o in c["outputs"] if o["output_type"] == "error"]
    assert not errors, errors
    assert _images(committed), f"{path.name} holds no figure"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs_in_a_kernel(path):
    make = _make()
    nb = make.execute(make.build(path.stem, dict(make.NOTEBOOKS)[path.stem]), small=True, timeout=600)
    code = [c for c in nb["cells"] if c["cell_type"] == "code"]
    assert all(c["execution_count"] is not None for c in code)
    assert len(_images(nb)) >= 1, f"{path.name} drew no figure"
