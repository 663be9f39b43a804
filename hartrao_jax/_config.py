"""Process-wide JAX configuration: float64 and the persistent compilation cache."""

from __future__ import annotations

import os
from pathlib import Path

import jax


def enable_x64() -> None:
    """The adjustment needs float64 (focal length to 1e-7 relative, angles to 1e-8 rad)."""
    jax.config.update("jax_enable_x64", True)


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path:
    """Persistent XLA compilation cache, so a second CLI run does not compile again.

    Default location ``$HARTRAO_JAX_CACHE`` or ``~/.cache/hartrao-jax/xla``; every compiled
    program is cached (minimum compile time 0 s).
    """
    p = Path(path or os.environ.get("HARTRAO_JAX_CACHE") or Path.home() / ".cache" / "hartrao-jax" / "xla")
    p.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(p))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return p
