"""Execute every notebooks/*.ipynb top to bottom (code cells exec-ed in one fresh namespace, no jupyter) in
small mode with the Agg backend; each must run without exception and draw at least one figure."""
import json
import pathlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pytest  # noqa: E402

NOTEBOOKS = sorted((pathlib.Path(__file__).parent.parent / "notebooks").glob("*.ipynb"))


def test_notebooks_found():
    assert {p.name for p in NOTEBOOKS} >= {
        "01_constraints.ipynb", "02_speed_vs_error.ipynb", "03_system_identification.ipynb"}


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(path, monkeypatch):
    monkeypatch.setenv("JAXCON_NOTEBOOK_SMALL", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = json.loads(path.read_text())
    assert nb["nbformat"] == 4
    cells = [c for c in nb["cells"] if c["cell_type"] == "code"]
    assert cells and all(c["outputs"] == [] and c["execution_count"] is None for c in cells)  # stripped
    plt.close("all")
    ns = {"__name__": "__main__"}
    for i, cell in enumerate(cells):
        code = compile("".join(cell["source"]), f"{path.name}[cell {i}]", "exec")
        exec(code, ns)
    assert plt.get_fignums(), f"{path.name} drew no figure"
    plt.close("all")
