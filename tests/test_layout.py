"""The package's layout, read from its imports: core <- surrogate <- emitters <- experiment, no circles."""

import ast
import pathlib

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / "mqd_jax"
# What each part may import of mqd_jax (besides itself and the leaf `version`).
ALLOWED = {
    "core": set(),
    "surrogate": {"core"},
    "emitters": {"core", "surrogate"},
    "adaptation": {"core", "surrogate", "emitters"},  # skill adaptation: the model's Jacobian on a run's state
    "__init__": {"core", "surrogate", "emitters", "adaptation"},  # `import mqd_jax` leaves the tooling out
    "experiment": {"core", "surrogate", "emitters", "adaptation", "__init__"},
}


def modules():
    """{dotted name: path} of every module of the package."""
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def imports(name, path, known):
    """The modules of the package that the module `name` imports (anywhere in it)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("mqd_jax")}
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("mqd_jax"):
            for alias in node.names:  # `from mqd_jax.core import run`: the module run, else the module itself
                sub = f"{node.module}.{alias.name}"
                found.add(sub if sub in known else node.module)
    return found - {name}


def part(name):
    """The layer of a module: its subpackage, or the top-level module's own name."""
    pieces = name.split(".")
    return "__init__" if len(pieces) == 1 else pieces[1]


GRAPH = {name: imports(name, path, modules()) for name, path in modules().items()}


@pytest.mark.parametrize("name", sorted(GRAPH))
def test_every_module_imports_only_the_layers_below_it(name):
    mine = part(name)
    if mine == "version":
        assert not GRAPH[name]
        return
    wrong = {other for other in GRAPH[name] if part(other) not in {mine, "version", *ALLOWED[mine]}}
    assert not wrong, f"{name} imports {sorted(wrong)}"


def test_the_imports_have_no_circle():
    """Subpackages' __init__ only describe (no imports), so a circle is one among the modules themselves."""
    state = {}

    def visit(name, path):
        state[name] = "open"
        for other in GRAPH[name]:
            if state.get(other) == "open":
                pytest.fail(f"a circle: {' -> '.join([*path, name, other])}")
            if other not in state:
                visit(other, [*path, name])
        state[name] = "done"

    for name in GRAPH:
        if name not in state:
            visit(name, [])


def test_no_import_hides_under_type_checking():
    hidden = [name for name, path in modules().items() if "TYPE_CHECKING" in path.read_text()]
    assert not hidden


def test_importing_mqd_jax_leaves_flax_optax_and_the_tooling_out():
    """flax and optax are imported where a model is first built or a checkpoint written, not by `import mqd_jax`."""
    import subprocess
    import sys

    code = ("import sys, mqd_jax; print(sorted({m.split('.')[0] for m in sys.modules} & {'flax', 'optax', "
            "'matplotlib'}), sorted(m for m in sys.modules if m.startswith('mqd_jax.experiment')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["[]", "[]"]
