"""Compiled code that a long-running process lets go of.

Every XLA:CPU executable holds a few memory mappings of the process (its code and data sections)
for as long as a jit cache keeps it. A process that compiles thousands of programs (a test worker,
a study of many scenes and lenses) reaches the kernel's limit, `vm.max_map_count` (65530 by
default), and dies inside the compiler: LLVM's "Cannot allocate memory", or a segfault. Measured
(session 15): 300 compiles add ~1400 mappings and `jax.clear_caches()` returns them all, equinox's
`filter_jit` caches included; a slow-test worker segfaulted with ~41,500 mappings seen beside it.
"""

from __future__ import annotations

import jax


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
