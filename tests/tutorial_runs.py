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


# Configs made without a capacity get 256 skills and archive slots, not 4096: each tutorial's code runs as written,
# its programs compiling in about half the time (as the docs' blocks do, test_docs.py).
SMALL_REPERTOIRES = ("import dataclasses as _dataclasses\n"
                     "from mqd_jax import Config as _Config\n"
                     "_Config.__init__.__defaults__ = tuple({**dict(zip([f.name for f in _dataclasses.fields(_Config) "
                     "if f.init], _Config.__init__.__defaults__, strict=True)), 'capacity': 256, "
                     "'archive_capacity': 256}.values())")


def _kinds(notebook):
    """Per code cell: the kinds of output it shows (text on stdout or stderr, a picture, an error)."""
    return [sorted({o.get("name", "") if o.output_type == "stream" else "image" if "image/png" in o.get("data", {})
                    else o.output_type for o in c.outputs}) for c in notebook.cells if c.cell_type == "code"]


def runs_at_tiny_sizes_as_committed(stem):
    """Runs the tutorial `stem` at its tiny sizes (raising, naming the cell, where one fails) and checks that each
    cell shows the kinds of output the committed full run shows: none newly silent, failing, or without its
    picture."""
    path = tutorials.TUTORIALS / f"{stem}.ipynb"
    ran = tutorials.execute(path, TINY[stem], setup=SMALL_REPERTOIRES)
    assert _kinds(ran) == _kinds(nbformat.read(path, as_version=4))
