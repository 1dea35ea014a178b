"""What the tutorial tests share: experiments/tutorials.py, the tutorials' tiny sizes, and the check that one runs."""

import importlib.util
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
nbformat = pytest.importorskip("nbformat")
pytest.importorskip("nbclient")
_spec = importlib.util.spec_from_file_location("tutorials", ROOT / "experiments" / "tutorials.py")
tutorials = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(tutorials)

# Tiny sizes: each tutorial's searches compile as at full size and run a few generations.
TINY = {"01_first_search": {"GENERATIONS": 6, "POPULATION": 16, "SEEDS": 2, "WARMUP": 32},
        "02_your_own_task": {"GENERATIONS": 6, "POPULATION": 16, "WARMUP": 32},
        "03_the_model": {"GENERATIONS": 8, "POPULATION": 16, "WARMUP": 32, "GOALS": 4}}


def _kinds(notebook):
    """Per code cell: the kinds of output it shows (text on stdout or stderr, a picture, an error)."""
    return [sorted({o.get("name", "") if o.output_type == "stream" else "image" if "image/png" in o.get("data", {})
                    else o.output_type for o in c.outputs}) for c in notebook.cells if c.cell_type == "code"]


def runs_at_tiny_sizes_as_committed(stem):
    """Runs the tutorial `stem` at its tiny sizes (raising, naming the cell, where one fails) and checks that each
    cell shows the kinds of output the committed full run shows: none newly silent, failing, or without its
    picture."""
    path = tutorials.TUTORIALS / f"{stem}.ipynb"
    assert _kinds(tutorials.execute(path, TINY[stem])) == _kinds(nbformat.read(path, as_version=4))
