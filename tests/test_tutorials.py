"""The tutorials (docs/tutorials/) are committed as one full run top to bottom left them, linked in order and from
the README; each runs at tiny sizes in a test file of its own (test_tutorial_*.py: the two test processes share
them)."""

import re

import pytest
from tutorial_runs import ROOT, TINY, nbformat, tutorials


def test_there_are_three_tutorials_in_order_each_linking_the_next_and_the_readme_links_them():
    names = [p.stem for p in tutorials.paths()]
    assert names == sorted(TINY) and len(names) == 3
    readme = (ROOT / "README.md").read_text()
    for path, following in zip(tutorials.paths(), [*tutorials.paths()[1:], None], strict=True):
        assert f"docs/tutorials/{path.name}" in readme, path.name
        if following:
            text = "".join(c.source for c in nbformat.read(path, as_version=4).cells if c.cell_type == "markdown")
            assert f"]({following.name})" in text, f"{path.name} does not link {following.name}"


@pytest.mark.parametrize("path", tutorials.paths(), ids=lambda p: p.stem)
def test_a_tutorial_is_committed_with_the_outputs_of_one_run_top_to_bottom(path):
    cells = [c for c in nbformat.read(path, as_version=4).cells if c.cell_type == "code"]
    assert [c.execution_count for c in cells] == list(range(1, len(cells) + 1)), "not run top to bottom once"
    outputs = [o for c in cells for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error" or o.get("name") == "stderr"]
    assert sum("image/png" in o.get("data", {}) for o in outputs) >= 2, "its pictures are not saved"


def test_parameters_a_tutorial_does_not_have_are_refused():
    with pytest.raises(ValueError, match=re.escape("does not assign ['GENRATIONS']")):
        tutorials.execute(tutorials.paths()[0], {"GENRATIONS": 6})
