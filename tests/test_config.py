"""Process-wide settings: a process drops its in-memory compiled programs before it runs out
of memory maps."""

from __future__ import annotations

import jax


def test_compiled_programs_are_dropped_near_the_memory_map_limit():
    """Past the share of vm.max_map_count the in-memory programs go (and their maps with
    them); below it nothing happens."""
    from hartrao_jax._config import memory_maps, release_compiled_programs

    m = memory_maps()
    if m is None:
        return  # no /proc here: nothing to measure
    f = jax.jit(lambda x: x * 2.0)
    f(1.0)
    assert not release_compiled_programs(fraction=1.0)
    assert f._cache_size() == 1
    assert release_compiled_programs(fraction=0.0)
    assert f._cache_size() == 0
