"""`retain_freed_memory`: glibc keeps freed memory (opt-in for libraries, made by the CLI)."""

import platform

import pytest

import jaxdof
from jaxdof import _allocator, _cli


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


def test_the_command_line_tool_makes_the_setting(monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(_cli, "retain_freed_memory", lambda: calls.append(1) or True)
    monkeypatch.chdir(tmp_path)
    # a missing input: exit status 2, after the setting was made
    args = [
        "missing.png",
        "missing.npy",
        "-o",
        "out.png",
        "--focal-length",
        "50mm",
        "--focus",
        "2m",
    ]
    assert _cli.main(["render", *args, "--f-number", "2"]) == 2
    assert not (tmp_path / "out.png").exists()
    assert calls == [1]
