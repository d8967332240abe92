"""`retain_freed_memory`: glibc keeps freed memory (opt-in for libraries, made by the CLI)."""

import platform
import subprocess
import sys

import pytest

import jaxdof
from jaxdof import _allocator


GLIBC = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"


@pytest.mark.skipif(not GLIBC, reason="mallopt is glibc's")
def test_glibc_accepts_the_settings():
    assert jaxdof.retain_freed_memory() is True
    assert jaxdof.retain_freed_memory(top_pad_mib=0) is True  # idempotent, any pad


def test_other_c_libraries_change_nothing(monkeypatch):
    monkeypatch.setattr(platform, "libc_ver", lambda: ("", ""))
    calls = []
    monkeypatch.setattr(_allocator.ctypes, "CDLL", lambda *a, **k: calls.append(a))
    assert jaxdof.retain_freed_memory() is False
    assert calls == []  # the C library was not even loaded


@pytest.mark.parametrize("bad", [-1, True])
def test_bad_pad_is_refused_by_name(bad):
    with pytest.raises(ValueError, match="top_pad_mib"):
        jaxdof.retain_freed_memory(top_pad_mib=bad)


# A fresh process: mallocs a 64 MiB block after (optionally) running the CLI, and prints whether
# the heap grew by it. glibc serves blocks above its mmap threshold (at most 32 MiB by default on
# 64-bit) by `mmap`, leaving the heap's end (`sbrk(0)`) where it was; after the CLI's setting
# (threshold 1 GiB) the block comes from the heap, which grows. The effect, not a stub, is checked.
_HEAP_PROBE = """
import ctypes, sys
if sys.argv[1] == "cli":
    from jaxdof._cli import main
    assert main(["info", "missing.png"]) == 2
libc = ctypes.CDLL("libc.so.6")
libc.sbrk.restype = libc.malloc.restype = ctypes.c_void_p
libc.sbrk.argtypes, libc.malloc.argtypes = (ctypes.c_long,), (ctypes.c_size_t,)
before = libc.sbrk(0)
block = libc.malloc(64 << 20)
print(libc.sbrk(0) - before >= 64 << 20)
"""


@pytest.mark.skipif(not GLIBC, reason="mallopt is glibc's")
def test_the_command_line_tool_makes_the_setting(tmp_path):
    def heap_grew(mode: str) -> bool:
        out = subprocess.run(
            [sys.executable, "-c", _HEAP_PROBE, mode],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            check=True,
        )
        return out.stdout.strip() == "True"

    # `info` (as `demo`) makes the setting before it reads its input (`render` and `fit` decide
    # by the frame's size, after reading it)
    assert heap_grew("cli")  # a missing input (exit status 2), after the setting was made
    assert not heap_grew("plain")  # without the CLI: the block was mmapped
    assert list(tmp_path.iterdir()) == []  # nothing written
