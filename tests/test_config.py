"""Process-wide settings: the persistent compilation cache is bounded (so that JAX locks every
read and write of it: concurrent processes never load a half-written entry) and adopts
entries written without an access-time stamp (else JAX's LRU refuses every later write)."""

from __future__ import annotations

import jax

from hartrao_jax._config import CACHE_MAX_BYTES, enable_compilation_cache


def test_compilation_cache_is_bounded_and_adopts_unstamped_entries(tmp_path, monkeypatch):
    keys = ("jax_compilation_cache_dir", "jax_compilation_cache_max_size",
            "jax_persistent_cache_min_compile_time_secs",
            "jax_persistent_cache_min_entry_size_bytes")
    before = {k: getattr(jax.config, k) for k in keys}
    monkeypatch.delenv("HARTRAO_JAX_CACHE_MAX_BYTES", raising=False)
    (tmp_path / "jit_f-abc-cache").write_bytes(b"entry")  # no -atime beside it
    try:
        assert enable_compilation_cache(tmp_path) == tmp_path
        assert jax.config.jax_compilation_cache_max_size == CACHE_MAX_BYTES > 0
        assert (tmp_path / "jit_f-abc-atime").exists()
        assert (tmp_path / "jit_f-abc-cache").read_bytes() == b"entry"  # untouched
    finally:
        for k, v in before.items():
            jax.config.update(k, v)


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
