import os

import jax
import pytest


@pytest.fixture(scope="session", autouse=True)
def compilation_cache(tmp_path_factory):
    """The command line's persistent compilation cache in a folder of this test session, not the user's."""
    os.environ["MQD_JAX_CACHE_DIR"] = str(tmp_path_factory.mktemp("jax-cache"))
    yield
    os.environ.pop("MQD_JAX_CACHE_DIR", None)


@pytest.fixture(scope="module", autouse=True)
def release_compiled_programs():
    """Drops each test module's compiled programs when it ends: hundreds of them would fill the memory."""
    yield
    jax.clear_caches()
