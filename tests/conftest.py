import dataclasses
import functools
import os
import subprocess
import sys
import tempfile
from xml.etree import ElementTree

# MuJoCo's offscreen renderer (tests that render skip where no EGL context can be made); read at mujoco's import.
os.environ.setdefault("MUJOCO_GL", "egl")
# The tests compile far more than they compute (tiny populations, short horizons). XLA's CPU backend compiles
# their programs faster at optimization level 0 (a third to 40%, two test files, measured) and with its older
# elemental emitters instead of its fusion emitters (a tiny "mqd" run: 9.0 s to 5.8 s; the MJX program: 56 s to
# 36 s; with the suite's other changes of the same commit, 944 s to 424 s on 2 cores). Read when the backend
# starts, so set before it does; a setting the caller chose is kept, and subprocesses inherit them. A test that
# simulates for long in JAX (MJX) compiles that program at the default level (`optimized_jit`). The elemental
# emitters may round a result differently from one program to another (measured: ask/tell's actions one
# float32 ulp from the fused run's), so the tests that two different programs of a computation agree bit for
# bit are marked `fusion_emitters` (test_programs_agree.py) and run in a process with XLA's default emitters, as
# users run, one process per module (`pytest_pyfunc_call`).
if "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_backend_optimization_level=0".strip()
if not os.environ.get("MQD_TESTS_FUSION_EMITTERS") and "xla_cpu_use_fusion_emitters" not in os.environ["XLA_FLAGS"]:
    os.environ["XLA_FLAGS"] += " --xla_cpu_use_fusion_emitters=false"

import compiled
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mqd_jax import Config, Task
from mqd_jax.core import algorithms, registry
from mqd_jax.experiment import cli

FUSION_EMITTERS = "MQD_TESTS_FUSION_EMITTERS"  # set: this process keeps XLA's default (fusion) emitters


def pytest_configure(config):
    config.addinivalue_line("markers", "fusion_emitters: runs in a process with XLA's default (fusion) emitters")


_FUSED: dict[str, str | None] = {}  # a fusion_emitters test's node id -> None (passed) or why it failed


def _run_fused(item: pytest.Item) -> None:
    """Runs the `fusion_emitters` tests of `item`'s module that have not run, in one pytest process with XLA's
    default emitters (one start-up for them all), and records each one's outcome in `_FUSED`."""
    group = [i for i in item.session.items if i.get_closest_marker("fusion_emitters") is not None
             and i.path == item.path and i.nodeid not in _FUSED]
    flags = " ".join(f for f in os.environ.get("XLA_FLAGS", "").split() if "xla_cpu_use_fusion_emitters" not in f)
    with tempfile.TemporaryDirectory() as folder:
        report = os.path.join(folder, "report.xml")
        out = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--junitxml", report,
                              *(i.nodeid for i in group)], env={**os.environ, FUSION_EMITTERS: "1", "XLA_FLAGS": flags},
                             cwd=item.config.rootpath, capture_output=True, text=True)
        cases = ({case.get("name"): case for case in ElementTree.parse(report).iter("testcase")}
                 if os.path.exists(report) else {})
    for i in group:
        case = cases.get(i.name)
        if case is None:
            _FUSED[i.nodeid] = f"it did not run:\n{out.stdout[-6000:]}{out.stderr[-2000:]}"
            continue
        failed = [e for e in case if e.tag in ("failure", "error", "skipped")]
        _FUSED[i.nodeid] = (f"{failed[0].tag}: {failed[0].get('message', '')}\n{(failed[0].text or '')[-6000:]}"
                            if failed else None)


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem):
    """A `fusion_emitters` test runs in a pytest process with XLA's default emitters (see above), with the others
    of its module."""
    if pyfuncitem.get_closest_marker("fusion_emitters") is None or os.environ.get(FUSION_EMITTERS):
        return None
    if pyfuncitem.nodeid not in _FUSED:
        _run_fused(pyfuncitem)
    if _FUSED[pyfuncitem.nodeid] is not None:
        pytest.fail(f"in a process with XLA's fusion emitters: {_FUSED[pyfuncitem.nodeid]}", pytrace=False)
    return True


@pytest.fixture(scope="session", autouse=True)
def compilation_cache(tmp_path_factory):
    """The command line's persistent compilation cache in a folder of this test session, not the user's."""
    os.environ["MQD_JAX_CACHE_DIR"] = str(tmp_path_factory.mktemp("jax-cache"))
    yield
    os.environ.pop("MQD_JAX_CACHE_DIR", None)


@pytest.fixture(scope="module", autouse=True)
def release_compiled_programs():
    """Drops each test module's compiled programs when it ends: every compiled program maps its code, and a
    process that kept those of the whole suite aborted past Linux's limit on memory mappings (vm.max_map_count)."""
    yield
    compiled.release()
    jax.clear_caches()


@pytest.fixture(scope="session")
def optimized_jit():
    """`jax.jit` at XLA's default optimization level (2), for programs whose run time matters more than their
    compile time (at the tests' level 0 the MJX tests ran several times longer: over 10 minutes instead of 4)."""
    return functools.partial(jax.jit, compiler_options={"xla_backend_optimization_level": 2})


# Shared helpers, as fixtures: test modules do not import each other, and no test registers a task at import.

def _tiny(**kw):
    """A Config small enough for a unit test (16 candidates, 12 generations); keywords that are not Config
    fields are the algorithm's options (`tiny(algorithm="mqd", warmup_samples=64)`), of which a preset gets those
    it takes (one call serves "qd" and "mqd" alike)."""
    fields = {f.name for f in dataclasses.fields(Config)}
    base = dict(population_size=16, max_generations=12, capacity=256, archive_capacity=64)
    options = {k: v for k, v in kw.items() if k not in fields}
    algorithm = kw.get("algorithm", Config.algorithm)
    if isinstance(algorithm, str):
        options = {k: v for k, v in options.items() if k in algorithms.options(algorithm)}
    return Config(**{**base, **{k: v for k, v in kw.items() if k in fields}, "algorithm_options": options})


@pytest.fixture(scope="session")
def tiny():
    """`tiny(**fields)`: a small Config."""
    return _tiny


@pytest.fixture(scope="session")
def assert_same():
    """Exact for integers and masks; floats may differ in the last bit when vmap reorders a reduction."""
    def check(a, b):
        a, b = np.asarray(a), np.asarray(b)
        if np.issubdtype(a.dtype, np.floating):
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
        else:
            np.testing.assert_array_equal(a, b)

    return check


_TINY_FLAGS = ["--generations", "3", "--population", "8", "--capacity", "64", "--archive-capacity", "16"]


@pytest.fixture(scope="session")
def tiny_flags():
    """Command-line flags of a tiny run."""
    return _TINY_FLAGS


@pytest.fixture(scope="session")
def tiny_mqd_flags():
    """Command-line flags of a tiny M-QD run (its model trains from the second generation)."""
    return [*_TINY_FLAGS, "--algorithm-option", "warmup_samples=8", "num_batches=2"]


@pytest.fixture
def refused(capsys):
    """`refused(argv, match)`: runs `mqd argv`, which must exit with a usage error whose message contains `match`."""
    def run(argv, match):
        with pytest.raises(SystemExit) as e:
            cli.main(argv)
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert match in err, err
        return err

    return run


@dataclasses.dataclass(frozen=True, eq=False)
class Linear(Task):
    """Behavior and quality are known affine maps of a 3D action."""

    def evaluate(self, actions, key):
        b = 0.5 + 0.2 * jnp.stack([actions[:, 0] - actions[:, 1], actions[:, 2] + 0.5 * actions[:, 0]], axis=1)
        return b, 0.5 + 0.3 * actions[:, 1], jnp.ones(actions.shape[0], bool)


@pytest.fixture(scope="session")
def linear_task():
    """A task whose behavior and quality are known affine maps of a 3D action in [-1, 1]^3."""
    return Linear((-1.0,) * 3, (1.0,) * 3, (0.0, 0.0), (1.0, 1.0))


@pytest.fixture
def registered():
    """`registered(name, factory)`: registers a task for one test; it is unregistered afterwards."""
    names = []

    def register(name, factory):
        registry.register(name, factory)
        names.append(name)

    yield register
    for name in names:
        registry._FACTORIES.pop(name)
        registry._SOURCES.pop(name)
    registry._make.cache_clear()


@pytest.fixture
def entry_points_rescanned():
    """The installed packages' task entry points are read afresh in this test, and again after it."""
    registry._entry_points.cache_clear()
    yield
    registry._entry_points.cache_clear()
    registry._make.cache_clear()
