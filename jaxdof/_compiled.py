"""Compiled code that a long-running process lets go of.

Every XLA:CPU executable holds a few memory mappings of the process (its code and data sections)
for as long as a jit cache keeps it. A process that compiles thousands of programs (a test worker,
a study of many scenes and lenses) reaches the kernel's limit, `vm.max_map_count` (65530 by
default), and dies inside the compiler: LLVM's "Cannot allocate memory", or a segfault. 300
compiles add about 1400 mappings and `jax.clear_caches()` returns them all, equinox's
`filter_jit` caches included; a slow-test worker segfaulted with about 41,500 mappings.

And compiled code that a process keeps: `enable_compilation_cache`, JAX's persistent cache, so
that a second run of the same shapes loads its programs instead of compiling them.
"""

from __future__ import annotations

import os
from pathlib import Path

import jax

from . import _traced


def memory_maps() -> int:
    """The memory mappings this process holds (Linux `/proc/self/maps`); 0 where unknown."""
    try:
        with open("/proc/self/maps") as f:
            return sum(1 for _ in f)
    except OSError:
        return 0


def release_compiled_code(*, max_maps: int = 20_000) -> bool:
    """Drop every compiled executable (`jax.clear_caches()`) once this process holds more than
    `max_maps` memory mappings; returns whether it did. Call it between units of work (tests,
    fits) of a long process: below the bound the executables stay for the next call that compiles
    the same shapes, and reading the count costs milliseconds."""
    if memory_maps() <= max_maps:
        return False
    jax.clear_caches()
    return True


#: The persistent cache's bound (bytes): JAX evicts the least recently used programs beyond it.
CACHE_MAX_BYTES = 2 * 2**30
#: Programs that compile faster than this (seconds) are not written: reading a file costs about as
#: much as compiling them, and the many small ones would crowd out the large.
_CACHE_MIN_COMPILE_SECONDS = 0.2


def default_cache_dir() -> Path:
    """Where `enable_compilation_cache` keeps programs by default: `$JAXDOF_CACHE_DIR`, else
    `$XDG_CACHE_HOME/jaxdof`, else `~/.cache/jaxdof` (the XDG base directory specification),
    each with a folder per jaxdof, JAX and jaxlib version below it."""
    from importlib.metadata import version

    from . import __version__

    root = os.environ.get("JAXDOF_CACHE_DIR")
    if not root:
        xdg = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        root = os.path.join(xdg, "jaxdof")
    return Path(root) / f"jaxdof-{__version__}_jax-{jax.__version__}_jaxlib-{version('jaxlib')}"


def enable_compilation_cache(
    *, path: str | os.PathLike[str] | None = None, max_bytes: int = CACHE_MAX_BYTES
) -> Path:
    """Keep the compiled XLA programs on disk, so that the next process that runs the same shapes
    (a second photo of the same size, the same command again) loads them instead of compiling.

    JAX's persistent compilation cache, switched on for this process: its keys hold the program,
    the compiler options and the device, so a stale entry is never used; the folder is
    per version of jaxdof, JAX and jaxlib (`default_cache_dir`) so that old versions' entries are
    not kept forever, and it is bounded to `max_bytes` (least recently used evicted). The `jaxdof`
    command line calls this unless given `--no-cache`.

    It also keeps `fit_lens`'s traced stages in `traced/` below the folder (`jax.export`, keyed
    by the stage's static arguments, its shapes, jaxdof's source and the versions of JAX and its
    libraries: `jaxdof/_traced.py`), so that the next process neither traces nor lowers them.

    **Arguments:**

    - `path`: the folder (created if missing); `None`: `default_cache_dir()`.
    - `max_bytes`: the cache's bound in bytes (JAX's `jax_compilation_cache_max_size`).

    **Returns:** the folder used.

    **Raises:** `ValueError` naming the folder where it cannot be created or written.
    """
    if int(max_bytes) < 0:
        raise ValueError(f"max_bytes must be non-negative, got {max_bytes}")
    folder = Path(path) if path is not None else default_cache_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise ValueError(
            f"cannot use {folder} as the compilation cache ({err.strerror or err}): pass another "
            "folder, set JAXDOF_CACHE_DIR, or switch the cache off"
        ) from None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", _CACHE_MIN_COMPILE_SECONDS)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    jax.config.update("jax_compilation_cache_max_size", int(max_bytes))
    _traced.use_folder(folder / "traced")
    return folder
