"""The persistent compilation cache: where it lives, what it switches on, and its refusals."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdof
from jaxdof import _traced
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
    traced = _traced.folder()
    yield
    for k, v in saved.items():
        jax.config.update(k, v)
    _traced.use_folder(traced)


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
    assert _traced.folder() == folder / "traced"  # the traced stages beside the programs


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


def _lowered(model, lens):
    image = jnp.linspace(0.1, 1.0, 8 * 8 * 3, dtype=jnp.float32).reshape(8, 8, 3)
    depth = jnp.full((8, 8), 2.0, jnp.float32).at[:, 4:].set(3.0)
    return jax.jit(lambda ln: model(image, depth, ln, max_radius=4.0)).lower(lens).as_text()


def test_the_fits_model_has_no_host_callback():
    """A program with a host callback is not kept in the persistent cache: the fit's own forward
    model (`checks=False`) has none, and gives NaN where a lens is invalid; the public default
    (`checks=True`) raises through one."""
    lens = jaxdof.ThinLens.from_sensor(0.05, 2.0, 2.5, sensor_width=0.0048, image_width=8)
    assert "callback" not in _lowered(jaxdof.DefocusModel(checks=False), lens)
    assert "callback" in _lowered(jaxdof.DefocusModel(), lens)
    image = jnp.ones((8, 8, 3), jnp.float32)
    depth = jnp.full((8, 8), 2.0, jnp.float32)
    bad = eqx.tree_at(lambda ln: ln.f_number, lens, jnp.asarray(-1.0))  # past the check
    out = jax.jit(lambda ln: jaxdof.DefocusModel(checks=False)(image, depth, ln, max_radius=4.0))(
        bad
    )
    assert np.isnan(np.asarray(out)).all()


def test_cli_stages_are_watched_without_callbacks():
    """`watch_stages` tells each compiled stage as it starts and ends (the CLI's progress)."""
    from jaxdof._fit.solve import run_stage, watch_stages

    seen = []
    with watch_stages(lambda name, seconds: seen.append((name, seconds))):
        out = run_stage("fit_starts", lambda x: x + 1, jnp.ones(3))
    assert np.asarray(out).tolist() == [2.0, 2.0, 2.0]
    assert seen[0] == ("fit_starts", None) and seen[1][0] == "fit_starts" and seen[1][1] >= 0
