import os

import jax
import pytest

from hartrao_jax._config import release_compiled_programs
from hartrao_jax._programs import PROGRAMS_ENV

jax.config.update("jax_enable_x64", True)
# no compiled programs kept on disk by the suite (its processes and subprocesses): a test that
# rebinds a module constant would otherwise leave a program its key does not describe
# (hartrao_jax._programs); tests/test_programs.py turns them on for itself
os.environ[PROGRAMS_ENV] = "0"


@pytest.fixture(autouse=True)
def _bounded_memory_maps():
    """The suite compiles thousands of programs in one process: past three quarters of the
    kernel's limit of memory maps the in-memory ones are dropped (else XLA dies near
    vm.max_map_count; one test adds at most a few thousand)."""
    yield
    release_compiled_programs(fraction=0.75)
