import jax
import pytest

from hartrao_jax._config import release_compiled_programs

jax.config.update("jax_enable_x64", True)


@pytest.fixture(autouse=True)
def _bounded_memory_maps():
    """The suite compiles thousands of programs in one process: past three quarters of the
    kernel's limit of memory maps the in-memory ones are dropped (else XLA dies near
    vm.max_map_count; one test adds at most a few thousand)."""
    yield
    release_compiled_programs(fraction=0.75)
