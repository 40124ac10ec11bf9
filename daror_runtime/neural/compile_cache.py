"""JAX's persistent compilation cache for every process that trains a network (D206).

A fit compiles its training programs (~3 s on this machine for the default PENN) before it trains
for ~1.6 s: without a cache every `daror fit penn` pays the compilation again. With it, a program
compiled once loads in milliseconds in every later process with the same shapes and settings.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

__all__ = ["default_cache_dir", "use_compilation_cache"]


def default_cache_dir() -> Path:
    """JAX's persistent compilation cache: ``$XDG_CACHE_HOME/daror/jax`` (``~/.cache/daror/jax``)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "daror" / "jax"


def use_compilation_cache(cache_dir: Path | str | None = None) -> None:
    """Cache every program this process compiles in ``cache_dir`` (default :func:`default_cache_dir`).

    Nothing changes when a cache is already set (the search's workers set theirs,
    :func:`daror_runtime.neural.hpsearch.work.prepare_worker`). Every program is cached, however
    quick to compile: a cached one loads in milliseconds.
    """
    if jax.config.jax_compilation_cache_dir:
        return
    jax.config.update("jax_compilation_cache_dir", str(cache_dir or default_cache_dir()))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
