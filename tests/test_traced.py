"""Traced fit stages kept on disk (`jaxdof/_traced.py`): the same results, keys that name every
static value, and the cases that run the stage untouched."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest

import jaxdof
from jaxdof import _traced
from jaxdof._fit.solve import run_stage
from jaxdof.internal import tuning


@pytest.fixture
def kept(tmp_path, monkeypatch):
    """Traced stages kept in a fresh folder for the test, the session's setting put back; this
    module's stages and modules named as jaxdof's are (a caller's are not: `_Foreign`)."""
    monkeypatch.setattr(_traced, "_TRUSTED", (*_traced._TRUSTED, "tests"))
    before = _traced.folder()
    _traced.use_folder(tmp_path / "traced")
    yield tmp_path / "traced"
    _traced.use_folder(before)


def _files(folder):
    return sorted(folder.glob("*.traced")) if folder.exists() else []


class _Scaled(eqx.Module):
    """A module with an array field and a static value, as the fit's models and layouts are."""

    weight: jax.Array
    power: float = eqx.field(static=True)


@eqx.filter_jit
def _stage(module: _Scaled, x, scale: float, names: tuple[str, ...]):
    # a LAPACK custom call (QR), an optimistix enumeration item and a dict of outputs
    q, r = jnp.linalg.qr(x * module.weight**module.power)
    ok = optx.RESULTS.where(
        jnp.all(jnp.isfinite(r)), optx.RESULTS.successful, optx.RESULTS.nonlinear_divergence
    )
    return {"q": q * scale, "r": r, "status": ok, "names": names, "count": len(names)}


def _args(power=2.0, scale=0.5):
    x = jnp.asarray(np.random.default_rng(0).normal(size=(6, 3)), jnp.float32)
    return _Scaled(jnp.float32(1.5), power), x, scale, ("a", "b")


def _same(a, b):
    for k in ("q", "r"):
        np.testing.assert_array_equal(np.asarray(a[k]), np.asarray(b[k]))
    assert a["status"] == b["status"] and a["names"] == b["names"] and a["count"] == b["count"]


def test_a_kept_stage_gives_the_stage_result(kept):
    direct = _stage(*_args())
    first = run_stage("test", _stage, *_args())  # traced, exported and kept
    assert len(_files(kept)) == 1
    _traced._loaded.clear()  # as a new process: read from the file
    again = run_stage("test", _stage, *_args())
    _same(direct, first)
    _same(direct, again)
    assert again["status"] == optx.RESULTS.successful and again["names"] == ("a", "b")


def test_the_key_names_every_static_value_and_shape(kept):
    base = run_stage("test", _stage, *_args())
    other_power = run_stage("test", _stage, *_args(power=3.0))
    other_scale = run_stage("test", _stage, *_args(scale=0.25))
    module, x, scale, names = _args()
    wider = run_stage("test", _stage, module, jnp.concatenate([x, x]), scale, names)
    with tuning.override(SPANS_MIN_RADIUS=3.0):  # read by the filters as they are traced
        run_stage("test", _stage, *_args())
    assert len(_files(kept)) == 5
    _same(other_power, _stage(*_args(power=3.0)))
    _same(other_scale, _stage(*_args(scale=0.25)))
    assert not np.array_equal(np.asarray(base["q"]), np.asarray(other_scale["q"]))
    assert np.asarray(wider["q"]).shape == (12, 3)


class _Foreign:
    """A class from outside jaxdof and its dependencies (a caller's script): the key cannot vouch
    for its code."""

    def __init__(self, scale):
        self.scale = scale


_Foreign.__module__ = "__main__"


@eqx.filter_jit
def _with_foreign(x, foreign):
    return x * foreign.scale


@eqx.filter_jit
def _apply(x, fn):
    return fn(x)


def test_what_the_key_cannot_name_runs_untouched(kept):
    x = jnp.arange(3.0)
    out = run_stage("test", _with_foreign, x, _Foreign(2.0))
    np.testing.assert_array_equal(np.asarray(out), [0.0, 2.0, 4.0])
    out = run_stage("test", _apply, x, lambda v: v * 3)  # a lambda: its code is not named
    np.testing.assert_array_equal(np.asarray(out), [0.0, 3.0, 6.0])
    assert _files(kept) == []


def test_a_damaged_file_is_traced_again(kept):
    direct = _stage(*_args())
    run_stage("test", _stage, *_args())
    (path,) = _files(kept)
    path.write_bytes(path.read_bytes()[:100])
    _traced._loaded.clear()
    _same(direct, run_stage("test", _stage, *_args()))
    assert path.stat().st_size > 100  # rewritten whole


def test_a_kept_stage_that_cannot_be_rebuilt_runs_as_before(kept):
    """A file whose outputs name a class that is not there (a stale or foreign entry): the stage
    runs as it would without the cache."""
    run_stage("test", _stage, *_args())
    (path,) = _files(kept)
    raw = path.read_bytes()
    n = int.from_bytes(raw[:8], "little")
    template = raw[8 : 8 + n].replace(b'"EnumerationItem"', b'"Missing"')
    path.write_bytes(len(template).to_bytes(8, "little") + template + raw[8 + n :])
    _traced._loaded.clear()
    _same(_stage(*_args()), run_stage("test", _stage, *_args()))


def test_debug_nans_runs_the_stage_untouched(kept):
    with jax.debug_nans(True):
        run_stage("test", _stage, *_args())
    assert _files(kept) == []


def test_the_folder_is_bounded(kept):
    run_stage("test", _stage, *_args())
    (path,) = _files(kept)
    bound = int(1.5 * path.stat().st_size)
    _traced.use_folder(kept, max_bytes=bound)
    run_stage("test", _stage, *_args(power=3.0))
    run_stage("test", _stage, *_args(power=4.0))
    assert len(_files(kept)) == 1 and not path.exists()  # the oldest went first
    assert sum(p.stat().st_size for p in _files(kept)) <= bound


def test_a_fit_from_kept_stages_is_the_fit(kept):
    """`fit_lens` with its stages read back (as a second process would) returns what it returns
    without them, to the bit."""
    rng = np.random.default_rng(3)
    image = rng.uniform(0.2, 1.0, (24, 24)).astype(np.float32)
    depth = np.tile(np.linspace(1.5, 4.0, 24, dtype=np.float32), (24, 1))
    lens = jaxdof.ThinLens.from_sensor(0.05, 2.8, 2.5, sensor_width=0.0036, image_width=24)
    photo = np.asarray(jaxdof.render(image, depth, lens))
    init = jaxdof.ThinLens.from_sensor(0.05, 4.0, 2.0, sensor_width=0.0036, image_width=24)
    options = dict(
        starts=1, exposure=False, vignetting=False, illumination=False, registration=False
    )
    _traced.use_folder(None)
    plain = jaxdof.fit_lens(image, depth, photo, init, **options)
    _traced.use_folder(kept)
    jaxdof.fit_lens(image, depth, photo, init, **options)
    assert _files(kept)
    _traced._loaded.clear()
    read = jaxdof.fit_lens(image, depth, photo, init, **options)
    for field in ("f_number", "focus_distance"):
        assert float(getattr(read.lens, field)) == float(getattr(plain.lens, field))
    assert float(read.loss) == float(plain.loss) and read.status == plain.status
