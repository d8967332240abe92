"""Opt-in: keep freed memory in the process, so that XLA's per-call scratch is not faulted in anew.

XLA on CPU takes each call's scratch arena from `malloc`. glibc serves large blocks by `mmap` and
unmaps them on `free` (and trims the top of the heap), so the next call's arena is fresh memory
that the kernel faults in page by page. For the soft filter at a megapixel the arena is ~50 MB
(the padded image and radius and a few weight maps) and at small radii the faults cost as much as
the filter's arithmetic: by `python fits/bench_filter.py` at 1024^2, R = 2, the soft filter costs
3.40x a constant-weight gather as the process starts (`fits/results/bench_filter.md`) and 1.76x
after this call (`--retain-memory`, `bench_filter_retain.md`); at R = 4 and 8 the two runs give
2.30x / 1.61x and 1.60x / 1.48x. Frames of a few hundred pixels (scratch of ~10 MB) gain little.

The setting is process-wide and belongs to the application, not to a library import: the `jaxdof`
command-line tool makes it, and `import jaxdof` does not.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import platform


# mallopt parameters of glibc's malloc.h
_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3


def retain_freed_memory(*, top_pad_mib: int = 256) -> bool:
    """Ask glibc's allocator to keep freed memory for reuse instead of returning it to the kernel.

    Sets `M_MMAP_THRESHOLD` to 1 GiB (blocks below it come from the heap, not from `mmap`),
    `M_TRIM_THRESHOLD` to its maximum (the heap is never trimmed) and `M_TOP_PAD` to
    `top_pad_mib` MiB (the heap grows in large steps), through `mallopt`. Afterwards memory the
    process frees stays with it: its resident size does not shrink back after a large computation.

    **Arguments:**

    - `top_pad_mib`: extra MiB requested whenever the heap grows, `>= 0`.

    **Returns:** `True` if glibc accepted all three settings; `False`, changing nothing, where the C
    library is not glibc (macOS, musl, Windows).
    """
    if isinstance(top_pad_mib, bool) or not isinstance(top_pad_mib, int) or top_pad_mib < 0:
        raise ValueError(f"top_pad_mib must be an int >= 0 (MiB), got {top_pad_mib!r}")
    libc = _glibc()
    if libc is None:
        return False
    settings = (
        (_M_MMAP_THRESHOLD, 1 << 30),
        (_M_TRIM_THRESHOLD, 2**31 - 1),
        (_M_TOP_PAD, top_pad_mib << 20),
    )
    return all(libc.mallopt(param, value) == 1 for param, value in settings)


def _glibc():
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None
    if not hasattr(libc, "mallopt"):
        return None
    libc.mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    libc.mallopt.restype = ctypes.c_int
    return libc
