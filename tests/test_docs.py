"""Every code block of the README and docs/ runs (Python), parses (the `mqd` command lines, TOML) or names
files that exist (scripts, extras)."""

import dataclasses
import pathlib
import re
import shlex

import pytest

from mqd_jax import Config
from mqd_jax.experiment import cli

ROOT = pathlib.Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def blocks(path, language):
    """The code blocks of `language` in the markdown file `path`, in order."""
    return re.findall(rf"^```{language}\n(.*?)^```", path.read_text(), flags=re.S | re.M)


def small_repertoires(monkeypatch):
    """Configs made without a capacity get 256 skills and archive slots, not 4096: the blocks' code is the
    reader's, run as written, at a size whose programs compile in half the time (4096 slots double it). Their
    searches then fill the repertoire, which the runs warn about (`RunWarning`, not shown)."""
    defaults = dict(zip([f.name for f in dataclasses.fields(Config) if f.init], Config.__init__.__defaults__,
                        strict=True))
    monkeypatch.setattr(Config.__init__, "__defaults__",
                        tuple({**defaults, "capacity": 256, "archive_capacity": 256}.values()))
    assert Config().capacity == 256


@pytest.mark.filterwarnings("ignore::mqd_jax.core.diagnostics.RunWarning")
@pytest.mark.parametrize("path", [p for p in DOCS if blocks(p, "python")], ids=lambda p: p.name)
def test_python_blocks_run_each_on_its_own(path, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # examples may write files: they must write none where they are run
    small_repertoires(monkeypatch)
    for code in blocks(path, "python"):  # each alone, as a reader pastes one: it imports what it uses
        exec(compile(code, str(path), "exec"), {"__name__": "__main__"})
    assert not list(tmp_path.iterdir()), "an example left files in the folder it was run from"


def commands(text):
    """The shell commands of a bash block: lines without comments, split at `&&`."""
    for line in text.splitlines():
        line = line.split(" #")[0].strip()
        yield from (c.strip() for c in line.split("&&") if c.strip())


@pytest.mark.parametrize("path", [p for p in DOCS if blocks(p, "bash")], ids=lambda p: p.name)
def test_shell_blocks_name_real_commands_flags_and_files(path):
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    parser, _ = cli._parser()
    for block in blocks(path, "bash"):
        for command in commands(block):
            words = shlex.split(command)
            if words[0] == "mqd":
                parser.parse_args(words[1:])  # exits (fails) on an unknown subcommand or flag
            elif words[:1] == ["python"] and words[1].startswith("experiments/"):
                assert (ROOT / words[1]).is_file(), command
            elif words[:2] == ["pip", "install"]:
                wanted = re.findall(r"\[(.*?)\]", command)
                assert all(e in extras for w in wanted for e in w.split(",")), command


def test_toml_blocks_parse():
    tomllib = pytest.importorskip("tomllib")
    for path in DOCS:
        for block in blocks(path, "toml"):
            assert tomllib.loads(block)


CITED = re.compile(r"(?:docs/)?((?:data|figures)/[\w.\-]+\.(?:md|json|png|gif))")
TEMPLATE = re.compile(r"_(T|vN)_|_vN\.")  # a command's path with a placeholder (the task T, version N)


def test_every_data_file_and_figure_is_cited_and_every_citation_exists():
    """docs/data and docs/figures hold what the documents cite, and nothing else (earlier data: git history)."""
    texts = [p.read_text() for p in [*DOCS, ROOT / "CHANGELOG.md"]]
    cited = {m for text in texts for m in CITED.findall(text) if not TEMPLATE.search(m)}
    held = {str(p.relative_to(ROOT / "docs")) for folder in ("data", "figures")
            for p in (ROOT / "docs" / folder).iterdir()}
    assert not sorted(cited - held), "cited but missing"
    assert not sorted(held - cited), "held but cited nowhere"
