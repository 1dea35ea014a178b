"""Runs the tutorials (docs/tutorials/*.ipynb) and saves them with their outputs, as they are committed.

    python experiments/tutorials.py                      # every tutorial, at the sizes its parameters cell gives
    python experiments/tutorials.py 02_your_own_task     # one

Each runs top to bottom in a fresh kernel (nbclient and ipykernel, the `dev` extra) inside a temporary folder,
so a tutorial that writes files leaves none behind. `execute(path, parameters)` is what the tests call, with
tiny sizes written after the notebook's own in its cell tagged "parameters".
"""

from __future__ import annotations

import argparse
import pathlib
import re
import tempfile
from typing import Any

import nbclient
import nbformat

TUTORIALS = pathlib.Path(__file__).resolve().parent.parent / "docs" / "tutorials"


def paths() -> list[pathlib.Path]:
    """The tutorials, in their reading order (their names start with it)."""
    return sorted(TUTORIALS.glob("*.ipynb"))


def execute(path: pathlib.Path, parameters: dict[str, Any] | None = None, timeout: int = 900, setup: str = "") -> Any:
    """The notebook at `path` run top to bottom (raises nbclient's CellExecutionError naming a failing cell).

    `parameters` override names its "parameters" cell assigns; a name it does not assign is refused (a test
    would otherwise run the notebook at its full size without saying so). `setup`: code the kernel runs before
    the notebook's first cell, in that cell (it must print nothing: a test compares each cell's outputs).
    """
    notebook = nbformat.read(path, as_version=4)
    if setup:
        first = next(c for c in notebook.cells if c.cell_type == "code")
        first.source = f"{setup}\n{first.source}"
    if parameters:
        cells = [c for c in notebook.cells if "parameters" in c.metadata.get("tags", ())]
        if len(cells) != 1:
            raise ValueError(f"{path.name}: {len(cells)} cells are tagged 'parameters'; expected one")
        unknown = set(parameters) - set(re.findall(r"^(\w+) =", cells[0].source, flags=re.M))
        if unknown:
            raise ValueError(f"{path.name}: its parameters cell does not assign {sorted(unknown)}")
        cells[0].source += "".join(f"\n{name} = {value!r}  # overridden" for name, value in parameters.items())
    with tempfile.TemporaryDirectory() as folder:
        nbclient.NotebookClient(notebook, timeout=timeout, kernel_name="python3", record_timing=False,
                                resources={"metadata": {"path": folder}}).execute()
    return notebook


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("names", nargs="*", help="tutorials to run (default: all), by name without .ipynb")
    args = parser.parse_args()
    chosen = [p for p in paths() if not args.names or p.stem in args.names]
    missing = set(args.names) - {p.stem for p in chosen}
    if missing:
        parser.error(f"no tutorial named {sorted(missing)}; there are {[p.stem for p in paths()]}")
    for path in chosen:
        nbformat.write(execute(path), path)
        print(f"ran and saved {path}")


if __name__ == "__main__":
    main()
