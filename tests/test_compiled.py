"""The persistent compilation cache: where it lives, what it switches on, and its refusals."""

from __future__ import annotations

import jax
import pytest

import jaxdof
from jaxdof._cli.parse import build_parser
from jaxdof._compiled import default_cache_dir


_KEYS = (
    "jax_compilation_cache_dir",
    "jax_persistent_cache_min_compile_time_secs",
    "jax_persistent_cache_min_entry_size_bytes",
    "jax_compilation_cache_max_size",
)


@pytest.fixture
def restore_cache_config():
    """The test session's own cache settings (`conftest.py`), put back after the test."""
    saved = {k: getattr(jax.config, k) for k in _KEYS}
    yield
    for k, v in saved.items():
        jax.config.update(k, v)


def test_default_folder_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("JAXDOF_CACHE_DIR", str(tmp_path / "own"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert default_cache_dir().parent == tmp_path / "own"
    monkeypatch.delenv("JAXDOF_CACHE_DIR")
    assert default_cache_dir().parent == tmp_path / "xdg" / "jaxdof"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_cache_dir().parent == tmp_path / "home" / ".cache" / "jaxdof"
    # one folder per version of jaxdof, JAX and jaxlib: old entries do not pile up in one
    name = default_cache_dir().name
    assert name.startswith(f"jaxdof-{jaxdof.__version__}_jax-{jax.__version__}_jaxlib-")


def test_enable_switches_on_jax_cache(tmp_path, restore_cache_config):
    folder = jaxdof.enable_compilation_cache(path=tmp_path / "c", max_bytes=10**8)
    assert folder == tmp_path / "c" and folder.is_dir()
    assert jax.config.jax_compilation_cache_dir == str(folder)
    assert jax.config.jax_compilation_cache_max_size == 10**8


def test_enable_refuses_a_folder_it_cannot_write(tmp_path, restore_cache_config):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    before = jax.config.jax_compilation_cache_dir
    with pytest.raises(ValueError, match="cannot use .*file.* as the compilation cache"):
        jaxdof.enable_compilation_cache(path=blocker / "cache")
    assert jax.config.jax_compilation_cache_dir == before  # nothing switched on
    with pytest.raises(ValueError, match="max_bytes"):
        jaxdof.enable_compilation_cache(path=tmp_path / "ok", max_bytes=-1)


@pytest.mark.parametrize("command", ["demo", "render", "fit", "calibrate"])
def test_cli_cache_flag(command):
    """On by default for the commands that compile; `--no-cache` switches it off."""
    needs = {
        "demo": [],
        "render": "a.png d.npy -o o.png --focal-length 50mm --f-number 2 --focus 2m".split(),
        "fit": ["a.png", "d.npy", "p.png"],
        "calibrate": ["p.jpg", "--chart", "c.json"],
    }[command]
    parser = build_parser()
    assert parser.parse_args([command, *needs]).cache is True
    assert parser.parse_args([command, *needs, "--no-cache"]).cache is False
