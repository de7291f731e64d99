"""The example notebook runs from top to bottom (its own assertions included) and writes its
figures, so that it cannot rot."""

import os
import pathlib

import pytest

from conftest import ROOT

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")


def test_the_notebook_runs_and_writes_its_figures(tmp_path):
    # The figures go where the README links them, unless PHOTOSTEREO_FIGURES says otherwise
    # (a read-only checkout, say).
    figures = pathlib.Path(
        os.environ.get("PHOTOSTEREO_FIGURES", ROOT / "docs" / "python" / "figures")
    )
    nb = nbformat.read(ROOT / "examples" / "python_notebook.ipynb", as_version=4)
    before = {p: p.stat().st_mtime_ns for p in figures.glob("*.png")} if figures.exists() else {}
    os.environ["PHOTOSTEREO_ROOT"] = str(ROOT)
    os.environ["PHOTOSTEREO_FIGURES"] = str(figures)
    client = nbclient.NotebookClient(
        nb, timeout=600, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    )
    client.execute()
    outputs = "".join(
        o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
    )
    assert "mean angular error: auto" in outputs
    for name in ("vase_solve.png", "vase_surface.png"):
        p = figures / name
        assert p.exists() and p.stat().st_size > 10_000, p
        assert p.stat().st_mtime_ns != before.get(p), f"{p} was not rewritten"
