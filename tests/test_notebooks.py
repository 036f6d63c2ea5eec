"""The Colab notebooks run top to bottom at tiny scale."""
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = Path(__file__).parent.parent / "notebooks"


# The MJX notebooks compile MuJoCo's step on a CPU for minutes (own_task: 190 s of a 14-minute CI run);
# their parts run in the default suite (test_contract's pusher and user-env CLI, test_peg_training).
@pytest.mark.parametrize("name", ["quickstart.ipynb", "ratio_sweep.ipynb",
                                  pytest.param("own_task.ipynb", marks=pytest.mark.slow),
                                  pytest.param("peg_in_hole.ipynb", marks=pytest.mark.slow)])
def test_notebook_executes(name, tmp_path, monkeypatch):
    monkeypatch.setenv("CCP_NOTEBOOK_SCALE", "tiny")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb = nbformat.read(NOTEBOOKS / name, as_version=4)
    NotebookClient(nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    outputs = [o for cell in nb.cells if cell.cell_type == "code" for o in cell.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    assert any("image/png" in o.get("data", {}) or "image/gif" in o.get("data", {}) for o in outputs)


def test_notebooks_are_generated_from_their_script():
    """The committed notebooks match notebooks/make_notebooks.py (edit the script, then rerun it)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_notebooks", NOTEBOOKS / "make_notebooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    for name, cells in (("quickstart.ipynb", module.QUICKSTART), ("ratio_sweep.ipynb", module.SWEEP),
                        ("peg_in_hole.ipynb", module.PEG), ("own_task.ipynb", module.OWN_TASK)):
        committed = nbformat.read(NOTEBOOKS / name, as_version=4)
        assert [c.source for c in committed.cells] == [c.source for c in module.with_badge(name, cells)], name
        assert "colab.research.google.com/github/" in committed.cells[0].source and name in committed.cells[0].source
