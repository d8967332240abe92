import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxdof import ThinLens, coc_radius, linearize_depth, signed_coc_radius


LENS = ThinLens(0.05, 2.0, 3.0, 36e-3 / 6000)


def test_formula_and_seed_form():
    f, n, d_f, p = 0.05, 2.0, 3.0, 36e-3 / 6000
    d = np.array([0.5, 1.0, 2.9, 3.0, 3.1, 10.0, 1e6])
    expected = f * f / (2 * n * (d_f - f)) * np.abs(1 - d_f / d) / p
    np.testing.assert_allclose(np.asarray(coc_radius(d, LENS)), expected, rtol=1e-13)
    # The seeds' form a |s (1/f - 1/d) - 1| with a = f / 2N and the sensor at s = f d_f / (d_f - f).
    a, s = f / (2 * n), f * d_f / (d_f - f)
    np.testing.assert_allclose(
        np.asarray(coc_radius(d, LENS)),
        a * np.abs(s * (1 / f - 1 / d) - 1) / p,
        rtol=1e-12,
        atol=1e-10,
    )  # atol: the seed form rounds to ~5e-13 px at the focus plane, where ours is exactly 0


def test_sign_focus_and_infinity():
    r = signed_coc_radius(jnp.array([1.0, 3.0, 10.0, jnp.inf]), LENS)
    assert r[0] < 0 and r[1] == 0 and r[2] > 0
    assert float(r[3]) == pytest.approx(float(LENS.blur_scale))
    g = jax.grad(lambda d: coc_radius(d, LENS))(jnp.inf)
    assert g == 0.0
    # At the focus plane |.| has a kink; the derivative is the finite subgradient 0.
    assert float(jax.grad(lambda d: coc_radius(d, LENS))(3.0)) == 0.0


def test_blur_grows_with_defocus_in_diopters():
    d = 1 / np.linspace(1 / 3.0 - 0.3, 1 / 3.0 + 0.3, 50)  # symmetric in diopters about the focus
    r = np.asarray(coc_radius(jnp.asarray(d), LENS))
    dio = np.abs(1 / d - 1 / 3.0)
    assert np.all(np.diff(r[np.argsort(dio)]) >= -1e-12)


def test_grads_every_field():
    # Pixel pitch in micrometres so that one finite-difference step suits every argument.
    def f(depth, fl, n, d_f, pitch_um):
        return coc_radius(depth, ThinLens(fl, n, d_f, pitch_um * 1e-6))

    args = tuple(jnp.asarray(v) for v in (1.7, 0.05, 2.0, 3.0, 6.0))
    check_grads(f, args, order=2, modes=("fwd", "rev"), eps=1e-6)


def test_from_sensor():
    lens = ThinLens.from_sensor(0.05, 2.0, 3.0, sensor_width=0.036, image_width=6000)
    assert float(lens.pixel_pitch) == pytest.approx(6e-6)
    with pytest.raises(ValueError, match="image_width"):
        ThinLens.from_sensor(0.05, 2.0, 3.0, sensor_width=0.036, image_width=0)


@pytest.mark.parametrize("field", ["focal_length", "f_number", "focus_distance", "pixel_pitch"])
@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan, math.inf])
def test_invalid_fields_named(field, bad):
    kwargs = dict(focal_length=0.05, f_number=2.0, focus_distance=3.0, pixel_pitch=6e-6)
    kwargs[field] = bad
    with pytest.raises(ValueError, match=field):
        ThinLens(**kwargs)


def test_focus_inside_focal_length():
    with pytest.raises(ValueError, match="focus_distance must exceed focal_length"):
        ThinLens(0.05, 2.0, 0.04, 6e-6)


def test_lens_is_a_pytree_under_jit_and_vmap():
    lenses = jax.vmap(lambda d_f: ThinLens(0.05, 2.0, d_f, 6e-6))(jnp.array([2.0, 3.0]))
    r = jax.jit(jax.vmap(coc_radius, in_axes=(None, 0)))(jnp.array([1.0, 5.0]), lenses)
    assert r.shape == (2, 2)


def _glu_perspective(fovy_deg, aspect, near, far):
    f = 1 / math.tan(math.radians(fovy_deg) / 2)
    return np.array(
        [
            [f / aspect, 0, 0, 0],
            [0, f, 0, 0],
            [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)],
            [0, 0, -1, 0],
        ]
    )


def test_linearize_depth_inverts_glu_perspective():
    near, far = 0.1, 100.0
    proj = _glu_perspective(60.0, 4 / 3, near, far)
    z_true = np.array([0.1, 0.25, 1.0, 3.7, 42.0, 100.0])
    eye = np.stack(
        [0.3 * z_true, -0.2 * z_true, -z_true, np.ones_like(z_true)]
    )  # camera looks down -z
    clip = proj @ eye
    window_z = (clip[2] / clip[3] + 1) / 2  # glDepthRange(0, 1)
    np.testing.assert_allclose(np.asarray(linearize_depth(window_z, near, far)), z_true, rtol=1e-9)
