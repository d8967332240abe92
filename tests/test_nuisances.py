"""Nuisances chosen by the photo (`jaxdof/_fit/select.py`, issue 34): a gain and an offset per
photo, fitted by default only where a score test at the fit without them rejects; reported in
`FitResult.nuisances`; forced on or off by `exposure=`; their residual's gradients checked."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxdof
from jaxdof._fit import layout, prepare, residual
from jaxdof._fit.solve import exposure_score


def _scene(h=40, w=56, seed=0):
    rng = np.random.default_rng(seed)
    image = rng.uniform(0.05, 1.0, size=(h, w, 3)).astype(np.float32)
    x = np.linspace(0.0, 1.0, w)
    depth = np.where(x < 0.5, 1.2 + x, 3.0 + 2 * x)[None].repeat(h, 0).astype(np.float32)
    return image, depth


def _lens(n, d_f, w=56):
    return jaxdof.ThinLens.from_sensor(0.05, n, d_f, sensor_width=0.0048, image_width=w)


@pytest.mark.parametrize("gain", [1.0, 0.85])
def test_exposure_is_fitted_where_the_photo_needs_it(gain):
    """A photo at 0.85 of the render's exposure (with 1 % noise): the score test rejects (p
    under 1e-3), the gain is fitted and the lens is right; at the same exposure the test passes
    and nothing is added."""
    image, depth = _scene()
    clean = np.asarray(jaxdof.render(image, depth, _lens(2.8, 2.5)))
    noise = np.random.default_rng(1).normal(0, 0.01 * clean.mean(), clean.shape)
    photo = (gain * clean + noise).astype(np.float32)
    fit = jaxdof.fit_lens(image, depth, photo, _lens(4.0, 2.0))
    entry = fit.nuisances["exposure"]
    assert entry["fitted"] == (gain != 1.0) and entry["chosen"] == (gain != 1.0)
    assert not entry["forced"] and entry["dof"] == 2
    assert (entry["p_value"] < 1e-3) == (gain != 1.0)
    assert bool(fit.success), fit.message
    np.testing.assert_allclose(float(fit.lenses.f_number[0]), 2.8, rtol=0.01)
    np.testing.assert_allclose(float(fit.lenses.focus_distance[0]), 2.5, rtol=0.01)
    if gain != 1.0:
        np.testing.assert_allclose(float(fit.gain[0]), gain, rtol=0.01)
        assert "gain" in fit.stderr and "exposure: fitted" in fit.summary()
    assert fit.to_dict()["nuisances"]["exposure"]["fitted"] == (gain != 1.0)


def test_exposure_forced_off_and_on():
    """`exposure=False` never fits it, `exposure=True` always does; both say they were forced."""
    image, depth = _scene()
    photo = 0.85 * np.asarray(jaxdof.render(image, depth, _lens(2.8, 2.5)))
    off = jaxdof.fit_lens(image, depth, photo, _lens(4.0, 2.0), exposure=False)
    assert off.nuisances["exposure"] == {
        **off.nuisances["exposure"],
        "fitted": False,
        "forced": True,
    }
    assert "gain" not in off.stderr
    on = jaxdof.fit_lens(image, depth, photo, _lens(4.0, 2.0), exposure=True)
    assert on.nuisances["exposure"]["fitted"] and on.nuisances["exposure"]["forced"]
    np.testing.assert_allclose(float(on.gain[0]), 0.85, rtol=1e-3)


def test_exposure_score_is_the_projection_on_the_nuisance_columns():
    """`exposure_score` against its definition in float64: `||P_X r||^2 / sigma^2` with `X` the
    lens Jacobian's columns and the gain and offset columns."""
    image, depth = (x.astype(np.float64) for x in _scene(16, 20))
    lens = _lens(2.8, 2.5, 20)
    target = 0.9 * np.asarray(jaxdof.render(image, depth, lens)) + 0.02
    image, depth, targets, sqrt_w, base, _ = prepare._prepare(
        image, depth, target, lens, None, jaxdof.DefocusModel()
    )
    spec = layout._Spec(("f_number", "focus_distance"), (), 1, False)
    lay = spec.layout(base, depth)
    model = residual._Model(1, 4.0, False, jaxdof.DefocusModel(), n_live=2)
    args = (image, depth, targets, sqrt_w, lay)
    y = model.pack(jnp.asarray(base), lay)
    r = np.asarray(model(y, args), np.float64)
    jac = np.asarray(jax.jacfwd(model)(y, args), np.float64)
    pred = r + np.asarray(targets).reshape(-1)
    x = np.concatenate([jac[:, list(spec.used)], pred[:, None], np.ones((r.size, 1))], axis=1)
    fitted = x @ np.linalg.lstsq(x, r, rcond=None)[0]
    want = (fitted @ fitted) / ((r @ r) / (r.size - len(spec.used)))
    got = float(exposure_score(jnp.asarray(r), jnp.asarray(jac), args, spec))
    np.testing.assert_allclose(got, want, rtol=1e-6)


def test_exposure_residual_gradients():
    """The residual with a gain and an offset (`exposure=True`): float64 finite differences of its
    derivatives in every coordinate, lens and exposure, forward and reverse."""
    image, depth = (x.astype(np.float64) for x in _scene(12, 14))
    lens = _lens(2.8, 2.5, 14)
    target = 0.9 * np.asarray(jaxdof.render(image, depth, lens)) + 0.02
    image, depth, targets, sqrt_w, base, _ = prepare._prepare(
        image, depth, target, lens, None, jaxdof.DefocusModel()
    )
    lay = layout._Spec(("f_number", "focus_distance"), (), 1, True).layout(base, depth)
    model = residual._Model(1, 4.0, True, jaxdof.DefocusModel(), n_live=4)
    args = (image, depth, targets, sqrt_w, lay)
    off = np.asarray(base).copy()
    off[:, 1] *= 1.2
    y = model.pack(jnp.asarray(off), lay).at[-2:].set(jnp.asarray([0.95, 0.01]))
    check_grads(jax.jit(lambda y: model(y, args)), (y,), order=1, modes=("fwd", "rev"))
