"""Nuisances chosen by the photo (`jaxdof/_fit/select.py`, `jaxdof/_fit/photo.py`, issue 34): a
gain and an offset, a radial vignetting gain, a registration (shift and magnification) per photo,
each fitted by default only where a score test at the fit without it rejects; reported in
`FitResult.nuisances`; forced on or off; their residual's gradients checked. And the luma
comparison of a camera JPEG, chosen from the photo's colour detail."""

import logging
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxdof
from jaxdof._fit import layout, photo, prepare, residual
from jaxdof._fit.solve import nuisance_columns, score_statistic
from jaxdof._fit.strategies import _next_starts


def _scene(h=40, w=56, seed=0):
    rng = np.random.default_rng(seed)
    image = rng.uniform(0.05, 1.0, size=(h, w, 3)).astype(np.float32)
    x = np.linspace(0.0, 1.0, w)
    depth = np.where(x < 0.5, 1.2 + x, 3.0 + 2 * x)[None].repeat(h, 0).astype(np.float32)
    return image, depth


def _lens(n, d_f, w=56):
    return jaxdof.ThinLens.from_sensor(0.05, n, d_f, sensor_width=0.0048, image_width=w)


def _held(*but: str) -> dict:
    """`fit_lens` options that hold every nuisance but `but` off and the treatment at the render's
    own model (the photos here are soft renders): a test of one nuisance or of the luma does not
    also run the photo's say in the others (each has its own tests), which keeps its fit to the
    refits that nuisance asks for (a cold default fit of these scenes compiles a dozen solves)."""
    held = dict(exposure=False, vignetting=False, illumination=False, registration=False)
    for name in but:
        held.pop(name)
    return dict(held, method="soft", footprint=False)


def test_exposure_is_fitted_where_the_photo_needs_it(caplog):
    """A photo at 0.85 of the render's exposure (with 1 % noise): the score test rejects (p
    under 1e-3), the gain is fitted and the lens is right. The refits with the gain (one start
    from the lens found, then the photo's say from the caller's starts) share one compiled solve
    (`path.padded_starts`, `path.compiled_windows`): at most one per free set is traced."""
    with caplog.at_level(logging.DEBUG, logger="jax._src.dispatch"):
        _exposure_case(0.85)
    messages = [r.getMessage() for r in caplog.records]
    traced = [m.split()[2] for m in messages if m.startswith("Finished tracing")]
    traced = [t for t in traced if t == "fit_starts"]
    assert len(traced) <= 2, traced


def test_no_exposure_where_the_photo_has_the_renders():
    """At the render's exposure (with 1 % noise) the test passes and nothing is added."""
    _exposure_case(1.0)


def _exposure_case(gain: float):
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
    held = _held("exposure")
    off = jaxdof.fit_lens(image, depth, photo, _lens(4.0, 2.0), exposure=False, **held)
    assert off.nuisances["exposure"] == {
        **off.nuisances["exposure"],
        "fitted": False,
        "forced": True,
    }
    assert "gain" not in off.stderr
    on = jaxdof.fit_lens(image, depth, photo, _lens(4.0, 2.0), exposure=True, **held)
    assert on.nuisances["exposure"]["fitted"] and on.nuisances["exposure"]["forced"]
    np.testing.assert_allclose(float(on.gain[0]), 0.85, rtol=1e-3)


def test_exposure_score_is_the_projection_on_the_nuisance_columns():
    """`score_statistic` of the exposure's columns against its definition in float64: `||P_X r||^2 / sigma^2` with `X` the
    lens Jacobian's columns and the gain and offset columns."""
    image, depth = (x.astype(np.float64) for x in _scene(16, 20))
    lens = _lens(2.8, 2.5, 20)
    target = 0.9 * np.asarray(jaxdof.render(image, depth, lens)) + 0.02
    image, depth, targets, sqrt_w, base, _ = prepare._prepare(
        image, depth, target, lens, None, jaxdof.DefocusModel()
    )
    spec = layout._Spec(("f_number", "focus_distance"), (), 1)
    lay = spec.layout(base, depth)
    model = residual._Model(1, 4.0, (), jaxdof.DefocusModel(), n_live=2)
    args = (image, depth, targets, sqrt_w, lay)
    y = model.pack(jnp.asarray(base), lay)
    r = np.asarray(model(y, args), np.float64)
    jac = np.asarray(jax.jacfwd(model)(y, args), np.float64)
    pred = r + np.asarray(targets).reshape(-1)
    x = np.concatenate([jac[:, list(spec.used)], pred[:, None], np.ones((r.size, 1))], axis=1)
    fitted = x @ np.linalg.lstsq(x, r, rcond=None)[0]
    want = (fitted @ fitted) / ((r @ r) / (r.size - len(spec.used)))
    extra = nuisance_columns(model, y, args)["exposure"]
    got = float(score_statistic(jnp.asarray(r), jnp.asarray(jac), extra, args, spec))
    np.testing.assert_allclose(got, want, rtol=1e-6)


def test_exposure_residual_gradients():
    """The residual with a gain and an offset (`exposure=True`): float64 finite differences of its
    derivatives in every coordinate, lens and exposure, forward and reverse."""
    image, depth = (x.astype(np.float64) for x in _scene(12, 14))
    lens = _lens(2.8, 2.5)  # circles of 1-2 px (out of the dead zone) on the 14 px scene
    target = 0.9 * np.asarray(jaxdof.render(image, depth, lens)) + 0.02
    image, depth, targets, sqrt_w, base, _ = prepare._prepare(
        image, depth, target, lens, None, jaxdof.DefocusModel()
    )
    lay = layout._Spec(("f_number", "focus_distance"), (), 1, ("exposure",)).layout(base, depth)
    model = residual._Model(1, 4.0, ("exposure",), jaxdof.DefocusModel(), n_live=4)
    args = (image, depth, targets, sqrt_w, lay)
    off = np.asarray(base).copy()
    off[:, 1] *= 1.2
    y = model.pack(jnp.asarray(off), lay).at[-2:].set(jnp.asarray([0.95, 0.01]))
    # A step of 1e-6: a circle's coverage of a pixel is C1 in its radius where the circle crosses
    # the pixel's corner, so the default step's differences see the second derivative's jump.
    check_grads(jax.jit(lambda y: model(y, args)), (y,), order=1, modes=("fwd", "rev"), eps=1e-6)


def test_materialised_jacobian_renders_the_lens_columns_and_is_the_plain_one():
    """The residual's Jacobian-materialising JVP rule (`_Model.jacobian`: the render
    differentiated along the lens slots only, the nuisances' columns through the camera) against
    the plain forward-mode Jacobian of the same residuals, float64, two targets with a shared
    f-number, exposure and illumination fitted: every column the same, the unread ones 0."""
    image, depth = (x.astype(np.float64) for x in _scene(12, 14))
    lenses = [_lens(2.8, 2.5), _lens(2.8, 1.6)]  # circles of 1-2 px on the 14 px wide scene
    targets = [0.9 * np.asarray(jaxdof.render(image, depth, x)) + 0.02 for x in lenses]
    image, depth, targets, sqrt_w, base, _ = prepare._prepare(
        image, depth, targets, lenses, None, jaxdof.DefocusModel()
    )
    on = ("exposure", "illumination")
    spec = layout._Spec(("f_number", "focus_distance"), ("f_number",), 2, on)
    lay = spec.layout(base, depth)
    model = residual._Model(2, 4.0, on, jaxdof.DefocusModel(), len(spec.used))
    args = (image, depth, targets, sqrt_w, lay)
    off = np.asarray(base).copy()
    off[:, 1] *= 1.2
    y = model.pack(jnp.asarray(off), lay)
    y = y.at[6:].set(jnp.asarray([0.95, 0.9, 0.01, -0.02, -0.1, 0.05, 0.02, 0.1]))
    got = np.asarray(jax.jacfwd(lambda y: model(y, args))(y))
    want = np.asarray(jax.jacfwd(lambda y: model.residuals(y, args))(y))
    used = list(spec.used)
    assert np.all(np.abs(want[:, used]).max(axis=0) > 0)  # every free slot moves the photos
    np.testing.assert_allclose(got[:, used], want[:, used], rtol=1e-12, atol=1e-14)
    assert not np.any(got[:, [i for i in range(y.shape[0]) if i not in used]])


# ---------------------------------------------------------------------------------------------
# Vignetting, registration and the luma comparison.
# ---------------------------------------------------------------------------------------------


def _camera(clean, nuisances, **params):
    """`clean` `(H, W[, C])` through `photo.camera` with the given parameters (the rest null)."""
    t = {k: jnp.asarray([v], clean.dtype) for k, v in params.items()}
    names = [n for k in nuisances for n in photo.NUISANCES[k]]
    full = {n: t.get(n, jnp.full((1,), photo.NULL.get(n, 0.0), clean.dtype)) for n in names}
    return np.asarray(photo.camera(jnp.asarray(clean)[None], full, nuisances, False))[0]


def test_register_is_the_identity_at_null_and_shifts_band_limited_detail_exactly():
    """At zero shift and magnification `register` returns the image unchanged; a shift of
    0.4 px of a sinusoid at a quarter of the sampling rate comes out as the sinusoid shifted,
    to 0.5 % of its amplitude (the order-6 Lanczos kernel, away from the edges: measured
    0.27 %)."""
    x = np.arange(64, dtype=np.float64)
    img = np.sin(2 * np.pi * 0.25 * x)[None, :, None].repeat(8, 0)
    same = np.asarray(photo.register(jnp.asarray(img), 0.0, 0.0, 0.0))
    np.testing.assert_array_equal(same, img)
    r = photo.half_diagonal(8, 64)
    moved = np.asarray(photo.register(jnp.asarray(img), 0.4 / r, 0.0, 0.0))
    want = np.sin(2 * np.pi * 0.25 * (x - 0.4))
    np.testing.assert_allclose(moved[4, 16:-16, 0], want[16:-16], atol=0.005)


def _noisy(clean, sigma, seed=1):
    noise = np.random.default_rng(seed).normal(0, sigma * clean.mean(), clean.shape)
    return (clean + noise).astype(np.float32)


def test_registration_is_fitted_where_the_photo_is_shifted_and_magnified():
    """A photo 0.7 px off and magnified 1 % (focus breathing), 0.5 % noise: the score test asks
    for the registration, which comes back within 0.05 px and 0.1 %, and the lens within 1 %;
    a photo in register fits without it."""
    image, depth = _scene(48, 64)
    clean = np.asarray(jaxdof.render(image, depth, _lens(2.8, 2.5, 64)))
    r = photo.half_diagonal(48, 64)
    moved = _camera(clean, ("registration",), shift_x=0.4 / r, shift_y=-0.6 / r, magnification=0.01)
    held = _held("registration")
    fit = jaxdof.fit_lens(image, depth, _noisy(moved, 0.005), _lens(4.0, 2.0, 64), **held)
    entry = fit.nuisances["registration"]
    assert entry["fitted"] and entry["chosen"] and entry["p_value"] < 1e-3, entry
    assert bool(fit.success), fit.message
    np.testing.assert_allclose(entry["values"]["shift_x"][0], 0.4, atol=0.05)
    np.testing.assert_allclose(entry["values"]["shift_y"][0], -0.6, atol=0.05)
    np.testing.assert_allclose(entry["values"]["magnification"][0], 0.01, atol=1e-3)
    np.testing.assert_allclose(float(fit.lenses.f_number[0]), 2.8, rtol=0.01)
    np.testing.assert_allclose(float(fit.lenses.focus_distance[0]), 2.5, rtol=0.01)
    assert "shift_x" in fit.stderr and "registration: fitted" in fit.summary()
    # The band grows by the registration's reach (0.6 px + 1 % of the half diagonal + 6 taps).
    assert int(fit.border) >= 7
    still = jaxdof.fit_lens(image, depth, _noisy(clean, 0.005), _lens(4.0, 2.0, 64), **held)
    assert not still.nuisances["registration"]["fitted"], still.nuisances


def test_vignetting_is_fitted_where_the_corners_are_dark():
    """A photo 25 % darker in the corners (`1 - 0.25 rho^2`), 0.5 % noise: the vignetting is
    fitted, its `r^2` coefficient within 0.03 of -0.25, the lens within 1 %."""
    image, depth = _scene(48, 64)
    clean = np.asarray(jaxdof.render(image, depth, _lens(2.8, 2.5, 64)))
    dark = _camera(clean, ("vignetting",), vignetting_r2=-0.25)
    held = _held("vignetting")
    fit = jaxdof.fit_lens(image, depth, _noisy(dark, 0.005), _lens(4.0, 2.0, 64), **held)
    entry = fit.nuisances["vignetting"]
    assert entry["fitted"] and entry["chosen"], fit.nuisances
    assert bool(fit.success), fit.message
    v = entry["values"]
    np.testing.assert_allclose(v["vignetting_r2"][0] + v["vignetting_r4"][0], -0.25, atol=0.03)
    np.testing.assert_allclose(float(fit.lenses.f_number[0]), 2.8, rtol=0.01)
    np.testing.assert_allclose(float(fit.lenses.focus_distance[0]), 2.5, rtol=0.01)


def test_illumination_is_fitted_where_light_falls_from_one_side():
    """A photo lit 30 % brighter on the right than the left (`1 + 0.25 u`, `u` over the half
    diagonal), 0.5 % noise: the illumination is fitted, its `c_x` within 0.03 of 0.25 and `c_y`
    of 0, the lens within 1 %. The other nuisances and the treatment are held (each has its own
    tests), which keeps the selection to this one: 34 s instead of 152 s."""
    image, depth = _scene(48, 64)
    clean = np.asarray(jaxdof.render(image, depth, _lens(2.8, 2.5, 64)))
    lit = _camera(clean, ("illumination",), illumination_x=0.25)
    held = _held("illumination")
    fit = jaxdof.fit_lens(image, depth, _noisy(lit, 0.005), _lens(4.0, 2.0, 64), **held)
    entry = fit.nuisances["illumination"]
    assert entry["fitted"] and entry["chosen"], fit.nuisances
    assert bool(fit.success), fit.message
    v = entry["values"]
    np.testing.assert_allclose(v["illumination_x"][0], 0.25, atol=0.03)
    np.testing.assert_allclose(v["illumination_y"][0], 0.0, atol=0.03)
    np.testing.assert_allclose(float(fit.lenses.f_number[0]), 2.8, rtol=0.01)
    np.testing.assert_allclose(float(fit.lenses.focus_distance[0]), 2.5, rtol=0.01)


def test_gains_forced_on_tiles():
    """On tiles (a budget that leaves a few of them) the forced gains see each pixel's place in
    the whole frame: a photo lit `1 + 0.25 u` and darkened `1 - 0.2 rho^2` at the corners comes
    back with both, and the lens within 1 %; registration, which resamples across the frame,
    asks for the whole frame."""
    image, depth = _scene(120, 160)
    clean = np.asarray(jaxdof.render(image, depth, _lens(2.8, 2.5, 160)))
    lit = _camera(clean, ("vignetting", "illumination"), vignetting_r2=-0.2, illumination_x=0.25)
    held = dict(exposure=False, registration=False, footprint=False, method="soft")
    kw = dict(vignetting=True, illumination=True, tiles=2048, **held)
    fit = jaxdof.fit_lens(image, depth, _noisy(lit, 0.005), _lens(4.0, 2.0, 160), **kw)
    assert len(fit.tiles) > 1 and int(fit.pixels_used) < 120 * 160 // 2
    v = {**fit.nuisances["illumination"]["values"], **fit.nuisances["vignetting"]["values"]}
    np.testing.assert_allclose(v["illumination_x"][0], 0.25, atol=0.03)
    np.testing.assert_allclose(v["illumination_y"][0], 0.0, atol=0.03)
    np.testing.assert_allclose(v["vignetting_r2"][0], -0.2, atol=0.05)
    np.testing.assert_allclose(float(fit.lenses.f_number[0]), 2.8, rtol=0.01)
    np.testing.assert_allclose(float(fit.lenses.focus_distance[0]), 2.5, rtol=0.01)
    with pytest.raises(ValueError, match="registration is fitted on the whole frame"):
        jaxdof.fit_lens(image, depth, lit, _lens(4.0, 2.0, 160), registration=True, tiles=2048)


def test_vignetting_and_registration_forced():
    """`vignetting=False, registration=False` never fit them; `=True` always does (forced)."""
    image, depth = _scene()
    clean = np.asarray(jaxdof.render(image, depth, _lens(2.8, 2.5)))
    kw = _held("vignetting", "registration")
    off = jaxdof.fit_lens(
        image, depth, clean, _lens(4.0, 2.0), vignetting=False, registration=False, **kw
    )
    assert not off.nuisances["vignetting"]["fitted"] and off.nuisances["vignetting"]["forced"]
    on = jaxdof.fit_lens(
        image, depth, clean, _lens(4.0, 2.0), vignetting=True, registration=True, **kw
    )
    for name in ("vignetting", "registration"):
        assert on.nuisances[name]["fitted"] and on.nuisances[name]["forced"], on.nuisances
    np.testing.assert_allclose(on.nuisances["registration"]["values"]["shift_x"][0], 0, atol=1e-3)
    np.testing.assert_allclose(float(on.lenses.f_number[0]), 2.8, rtol=1e-3)


def test_nuisance_columns_are_the_derivatives_of_the_model_with_the_nuisance():
    """`nuisance_columns` (the score test's columns, from one render) against the Jacobian of
    the residual of a model that has the nuisances, at their null values, in float64."""
    image, depth = (x.astype(np.float64) for x in _scene(12, 14))
    lens = _lens(2.8, 2.5)  # circles of 1-2 px (out of the dead zone) on the 14 px scene
    target = 0.9 * np.asarray(jaxdof.render(image, depth, lens)) + 0.02
    image, depth, targets, sqrt_w, base, _ = prepare._prepare(
        image, depth, target, lens, None, jaxdof.DefocusModel()
    )
    free = ("f_number", "focus_distance")
    args0 = (image, depth, targets, sqrt_w, layout._Spec(free, (), 1).layout(base, depth))
    model0 = residual._Model(1, 4.0, (), jaxdof.DefocusModel(), n_live=2)
    got = nuisance_columns(model0, model0.pack(jnp.asarray(base), args0[-1]), args0)
    every = ("exposure", "vignetting", "illumination", "registration")
    spec = layout._Spec(free, (), 1, every)
    lay = spec.layout(base, depth)
    model = residual._Model(1, 4.0, every, jaxdof.DefocusModel(), n_live=len(spec.used))
    y = model.pack(jnp.asarray(base), lay)
    jac = np.asarray(jax.jacfwd(model)(y, (*args0[:4], lay)))
    for k, name in enumerate(every):
        first = 3 + sum(len(photo.NUISANCES[n]) for n in every[:k])
        cols = list(range(first, first + len(photo.NUISANCES[name])))
        np.testing.assert_allclose(np.asarray(got[name]), jac[:, cols], rtol=1e-9, atol=1e-12)


def test_residual_gradients_with_every_nuisance_and_luma():
    """The residual with exposure, vignetting, illumination, registration and the luma
    comparison: float64 finite differences of its derivatives in every coordinate, forward and
    reverse, away from the null values (a shift of 0.3 px, 1 % magnification)."""
    image, depth = (x.astype(np.float64) for x in _scene(12, 14))
    lens = _lens(2.8, 2.5)  # circles of 1-2 px (out of the dead zone) on the 14 px scene
    target = 0.9 * np.asarray(jaxdof.render(image, depth, lens)) + 0.02
    image, depth, targets, sqrt_w, base, _ = prepare._prepare(
        image, depth, target, lens, None, jaxdof.DefocusModel()
    )
    targets, sqrt_w = prepare.luma_targets(targets, sqrt_w)
    every = ("exposure", "vignetting", "illumination", "registration")
    spec = layout._Spec(("f_number", "focus_distance"), (), 1, every, luma=True)
    lay = spec.layout(base, depth)
    model = residual._Model(1, 4.0, every, jaxdof.DefocusModel(), len(spec.used), luma=True)
    args = (image, depth, targets, sqrt_w, lay)
    off = np.asarray(base).copy()
    off[:, 1] *= 1.2
    r = photo.half_diagonal(12, 14)
    extra = jnp.asarray([0.95, 0.01, -0.1, 0.02, 0.15, -0.1, 0.3 / r, -0.2 / r, 0.01])
    y = model.pack(jnp.asarray(off), lay).at[3:].set(extra)
    # A step of 1e-6: the resampling kernel is C1 where a source position crosses a pixel (its
    # taps change there), so finite differences of the default step see its second derivative's
    # jump wherever the 1 % magnification puts a position within a step of a crossing.
    check_grads(jax.jit(lambda y: model(y, args)), (y,), order=1, modes=("fwd", "rev"), eps=1e-6)


def _jpeg(linear, subsampling):
    """A linear RGB photo as a camera JPEG (quality 90) decoded back to linear light."""
    import io

    from PIL import Image

    from jaxdof._io import linear_to_srgb, srgb_to_linear

    code = np.round(np.clip(linear_to_srgb(np.clip(linear, 0, 1)), 0, 1) * 255).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(code).save(buf, "JPEG", quality=90, subsampling=subsampling)
    buf.seek(0)
    decoded = np.asarray(Image.open(buf)).astype(np.float64) / 255
    return srgb_to_linear(decoded).astype(np.float32)


def test_camera_jpeg_is_compared_in_luma():
    """A 4:2:0 JPEG of a render: its colour detail is under `LUMA_CHROMA` of the image's, the
    fit compares luma and recovers the lens within 2 %; the 4:4:4 JPEG and the linear render
    keep the colour comparison; `luma=True` forces it."""
    image, depth = _scene(48, 64)
    clean = np.asarray(jaxdof.render(image, depth, _lens(2.8, 2.5, 64)))
    held = _held()
    fit = jaxdof.fit_lens(image, depth, _jpeg(clean, 2), _lens(4.0, 2.0, 64), **held)
    entry = fit.nuisances["luma"]
    assert entry["fitted"] and not entry["forced"], entry
    assert entry["chroma_detail"] < 0.5
    np.testing.assert_allclose(float(fit.lenses.f_number[0]), 2.8, rtol=0.02)
    np.testing.assert_allclose(float(fit.lenses.focus_distance[0]), 2.5, rtol=0.02)
    assert "luma: compared in luma" in fit.summary()
    for kept in (_jpeg(clean, 0), clean):
        lens_fit = jaxdof.fit_lens(image, depth, kept, _lens(4.0, 2.0, 64), **held)
        assert not lens_fit.nuisances["luma"]["fitted"], lens_fit.nuisances["luma"]
    forced = jaxdof.fit_lens(image, depth, clean, _lens(4.0, 2.0, 64), luma=True, **held)
    assert forced.nuisances["luma"]["fitted"] and forced.nuisances["luma"]["forced"]
    np.testing.assert_allclose(float(forced.lenses.f_number[0]), 2.8, rtol=1e-3)


def test_luma_decision_on_grey_and_colour_images():
    """`_choose_luma`: an image grey in three channels (a chart's raster) has no colour detail to
    lose, whatever the photo's (`chroma_detail` nan, no luma), also where rounding leaves its
    channels a hair apart; a colour image with a photo whose chroma is smooth takes the luma."""
    from jaxdof._fit.fit import _choose_luma

    rng = np.random.default_rng(3)
    grey = np.repeat(rng.uniform(0.05, 1.0, (32, 40, 1)), 3, axis=-1).astype(np.float32)
    smooth = np.repeat(rng.uniform(0.05, 1.0, (16, 20, 3)), 2, 0).repeat(2, 1)
    photo = (0.5 * grey + 0.1 * smooth).astype(np.float32)  # luma detail, chroma at half size
    nudged = grey * np.float32([1.0, 1.0 + 1e-7, 1.0])
    for image in (grey, nudged):
        on, entry = _choose_luma(image, photo, None)
        assert not on and math.isnan(entry["chroma_detail"]) and not entry["forced"], entry
    colour = rng.uniform(0.05, 1.0, (32, 40, 3)).astype(np.float32)
    on, entry = _choose_luma(colour, photo, None)
    assert on and entry["chroma_detail"] < 0.5, entry


def test_chroma_detail_of_a_large_photo_from_bands_spread_over_it(monkeypatch):
    """Beyond `_CHROMA_PIXELS`, `chroma_detail` reads every k-th band of rows: on a photo about
    twice that size (every second band) it comes within a few percent of every row's, for colour
    detail at the pixel scale and for chroma stored at half resolution."""
    rng = np.random.default_rng(5)
    monkeypatch.setattr(photo, "_CHROMA_PIXELS", 110_000)
    luma_detail = rng.uniform(0.05, 1.0, (512, 400, 1)).astype(np.float32)
    smooth = np.repeat(rng.uniform(0.05, 1.0, (256, 200, 3)), 2, 0).repeat(2, 1)
    for x in (rng.uniform(0.05, 1.0, (512, 400, 3)), 0.5 * luma_detail + 0.1 * smooth):
        x = x.astype(np.float32)
        part = photo.chroma_detail(x)
        monkeypatch.setattr(photo, "_CHROMA_PIXELS", 10**9)
        whole = photo.chroma_detail(x)
        monkeypatch.setattr(photo, "_CHROMA_PIXELS", 110_000)
        assert part != whole and part == pytest.approx(whole, rel=0.05), (part, whole)


def test_the_cause_of_an_inconsistency_is_named_from_the_residual_pattern():
    """`verdict._cause`: a residual growing towards the corners names vignetting; one along depth
    edges names occlusion; one alike everywhere names what every pixel shares."""
    import types

    from jaxdof._fit.verdict import _cause

    n = 8
    c = (np.arange(n) + 0.5) / n - 0.5
    rho2 = np.add.outer(c**2, c**2)
    flat = types.SimpleNamespace(d=np.full((32, 32), 2.0))
    assert "vignetting" in _cause(1 + 20 * rho2, flat)
    stepped = types.SimpleNamespace(d=np.where(np.arange(32) < 12, 1.5, 4.0)[None].repeat(32, 0))
    along = np.ones((n, n))
    along[:, 2:4] = 30.0  # the columns that hold the edge at x = 12 of 32
    assert "depth edges" in _cause(along, stepped)
    rng = np.random.default_rng(0)
    assert "alike" in _cause(1 + 0.1 * rng.random((n, n)), flat)
    # A region fitted exactly (a zero mean square) is no error.
    exact = 1 + 20 * rho2
    exact[3, 3] = 0.0  # the centre, where the pattern puts the least
    assert "vignetting" in _cause(exact, flat)
    # Light falling from one side: after the exposure's mean, the residual grows towards the
    # left and right sides alike.
    sides = 1 + 20 * np.broadcast_to(c**2, (n, n))
    assert "illumination=True" in _cause(sides, flat)


def test_next_starts_tell_lenses_apart_not_nuisances():
    """A coarse level hands the next one a second start only at a distinct lens (a near/far
    tie): two solutions of one basin whose light's tilt (near 0) differs by the coarse
    tolerance's scatter are one start; a lens 10 % away within the tie margin is two."""
    spec = layout._Spec(("f_number", "focus_distance"), (), 1, ("exposure", "illumination"))
    base = np.array([[0.05, 4.0, 0.6, 6e-6]], np.float32)
    lay = spec.layout(base, np.full((8, 8), 0.7, np.float32))
    # theta: f, N, focus power, gain, offset, illumination_x, illumination_y (the scout's starts
    # 0 and 2 of the 24 MP chart of fits/chart_speed.py)
    same = [
        [0.05, 3.764192, 1.667647, 1.000992, -4.560848e-04, 9.482035e-05, -2.713721e-04],
        [0.05, 3.764207, 1.667644, 1.000992, -4.560633e-04, 9.548868e-05, -2.715399e-04],
    ]
    other = [0.05, 3.764192 * 1.1, 1.667647 * 0.9, 1.0, 0.0, 0.0, 0.0]
    for theta, expected in ((same, 1), ([same[0], other], 2)):
        info = {
            "ys": np.arange(14, dtype=np.float32).reshape(2, 7),
            "loss": np.array([1.5705075, 1.5705081]),
            "converged": np.array([True, True]),
            "best": 0,
            "theta": np.array(theta),
        }
        ys, rows = _next_starts(info, base, info["ys"], spec, lay)
        assert ys.shape == (expected, 7) and rows.shape == (expected, 1, 4)
        np.testing.assert_array_equal(ys[0], info["ys"][0])
