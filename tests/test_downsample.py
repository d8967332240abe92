"""`downsample`: an all-in-focus image at `s` times the photo's resolution.

`render(..., downsample=s)` scatters at the input's resolution (circles `s r` input pixels) and
averages `s x s` blocks into the photo's pixels; `fit_lens(..., downsample=s)` fits photos of the
smaller shape through it.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxdof
from jaxdof._render import box_downsample

from .helpers import EXACT


LENS = jaxdof.ThinLens(0.05, 2.8, 2.0, 2e-5)  # K = 11.4 px


def fine_lens(lens, s):
    """The same lens seen by a sensor with `s` times smaller pixels."""
    return dataclasses.replace(lens, pixel_pitch=lens.pixel_pitch / s)


def scene(h, w, seed=0, channels=3):
    rng = np.random.default_rng(seed)
    image = rng.uniform(0.05, 1.0, (h, w, channels))
    depth = np.broadcast_to(np.linspace(1.2, 4.0, w)[None, :], (h, w)).copy()
    return image, depth


@pytest.mark.parametrize("s", [1, 2, 3])
@pytest.mark.parametrize("max_radius", [None, 3.0])
def test_render_downsample_is_the_block_mean_of_the_fine_render(s, max_radius):
    # By definition: the scatter at the input's resolution (the lens's pitch divided by s, the
    # window in photo pixels times s), then the mean of each s x s block.
    lens = jaxdof.ThinLens(0.05, 8.0, 2.0, 2e-5)  # circles up to 3.2 photo px here
    image, depth = scene(6 * s, 9 * s)
    out = jaxdof.render(image, depth, lens, max_radius=max_radius, downsample=s)
    fine = jaxdof.render(
        image,
        depth,
        fine_lens(lens, s),
        max_radius=None if max_radius is None else max_radius * s,
    )
    expect = np.asarray(fine).reshape(6, s, 9, s, 3).mean(axis=(1, 3))
    assert out.shape == (6, 9, 3)
    np.testing.assert_allclose(np.asarray(out), expect, rtol=0, atol=1e-13)
    if s == 1:
        np.testing.assert_array_equal(
            np.asarray(out), np.asarray(jaxdof.render(image, depth, lens, max_radius=max_radius))
        )


@pytest.mark.parametrize("footprint", [False, True])
def test_a_finer_input_approaches_the_photo_of_the_finer_scene(footprint):
    # The photo's truth here: a white-noise scene at 8x the photo's resolution, scattered there
    # and averaged into photo pixels. A 1x all-in-focus image (its 8 x 8 block means) has lost the
    # detail inside each photo pixel that blur of circles of a pixel or so depends on; 2x and 4x
    # inputs keep more of it. Constant depth. Measured RMS error against the 1x input's, footprint
    # off / on: 2x 0.53 / 0.47 (r = 0.8 px), 0.54 / 0.53 (1.6), 0.50 / 0.48 (3.0); 4x 0.26 / 0.23,
    # 0.26 / 0.26, 0.23 / 0.22; at r = 0.4 px only 4x gains much (0.28 / 0.33; 2x 0.59 / 0.75).
    rng = np.random.default_rng(3)
    n, up = 24, 8
    fine = rng.uniform(0.0, 1.0, (n * up, n * up, 1))
    depth = np.full((n * up, n * up), 3.0)
    inner = np.s_[4:-4, 4:-4]
    for r_photo in (0.4, 0.8, 1.6, 3.0):
        # circles of r_photo px at 3 m with d_f = 2 m: r = K |1 - d_f / d| = K / 3
        n_f = 0.05**2 / (2 * (3 * r_photo) * (2.0 - 0.05) * 2e-5)
        lens = jaxdof.ThinLens(0.05, n_f, 2.0, 2e-5)
        truth = np.asarray(jaxdof.render(fine, depth, lens, downsample=up))
        err = {}
        for s in (1, 2, 4):
            image = box_downsample(jnp.asarray(fine), up // s)
            out = jaxdof.render(
                image, depth[:: up // s, :: up // s], lens, downsample=s, footprint=footprint
            )
            err[s] = float(np.sqrt(np.mean((np.asarray(out) - truth)[inner] ** 2)))
        assert err[4] < 0.4 * err[1], (r_photo, err)
        if r_photo >= 0.8:
            assert err[2] < 0.6 * err[1], (r_photo, err)


def test_downsample_gradients():
    # Every differentiable path (image, depth, lens fields) through the fine scatter and the block
    # mean, float64, forward and reverse mode.
    image, depth = scene(8, 8, seed=1, channels=2)
    depth = depth * 0.7 + 0.65  # 1.49-3.45 m, none at the focus kink |1 - d_f/d| = 0
    lens = jaxdof.ThinLens(0.05, 4.0, 2.0, 2e-5)

    def f(image, depth, f_number, focus):
        lens_ = jaxdof.ThinLens(lens.focal_length, f_number, focus, lens.pixel_pitch)
        return jaxdof.render(image, depth, lens_, max_radius=3.0, downsample=2, footprint=True)

    # Finite differences with a step of 1e-5 (check_grads' default is 1e-4): the footprint
    # correction's fourth-order coefficients follow the pixel grid, so their third derivative in
    # the radius reaches ~500 px^-3 near 2 px (these circles: 0.4-6.7 input px), and a depth step
    # of 1e-4 m moves a circle by ~1.4e-3 px, whose central-difference truncation error
    # (h^2 f'''/6) is then above the 1e-6 tolerance (measured 1.3e-5 in depth). The smaller step
    # cuts it 100x; its rounding error, ~1e-16 / 1e-5, stays far below the tolerance.
    check_grads(
        f, (image, depth, 4.0, 2.0), order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6, eps=1e-5
    )
    g = jax.grad(lambda n: jnp.sum(f(image, depth, n, 2.0) ** 2))(4.0)
    assert np.isfinite(float(g)) and float(g) != 0.0


def test_downsample_composes_with_jit_and_vmap():
    image, depth = scene(8, 10)

    def one(n):
        lens = jaxdof.ThinLens(0.05, n, 2.0, 2e-5)
        return jaxdof.render(image, depth, lens, max_radius=12.0, downsample=2)

    out = jax.jit(jax.vmap(one))(jnp.array([2.8, 4.0, 5.6]))
    assert out.shape == (3, 4, 5, 3)
    one = jaxdof.render(
        image, depth, jaxdof.ThinLens(0.05, 4.0, 2.0, 2e-5), max_radius=12.0, downsample=2
    )
    np.testing.assert_allclose(np.asarray(out[1]), np.asarray(one), rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("pyramid", [1, 2])
def test_fit_lens_with_a_finer_input_recovers_the_lens(pyramid):
    # Noise-free targets rendered through the same model: recovery to 1e-4 (float64), from a start
    # 30% off in N and 15% in d_f. Photo 25 x 27 (odd: the pyramid's crop must keep the 2:1 ratio).
    image, depth = scene(50, 54, seed=2)
    lens = jaxdof.ThinLens(0.05, 5.6, 2.0, 2e-5)
    target = np.asarray(jaxdof.render(image, depth, lens, downsample=2))
    assert target.shape == (25, 27, 3)
    init = jaxdof.ThinLens(0.05, 5.6 * 1.3, 2.0 * 1.15, 2e-5)
    res = jaxdof.fit_lens(
        image, depth, target, init, downsample=2, pyramid=pyramid, starts=1, **EXACT
    )
    assert bool(res.success), res.message
    assert res.levels == pyramid
    np.testing.assert_allclose(float(res.lens.f_number), 5.6, rtol=1e-4)
    np.testing.assert_allclose(float(res.lens.focus_distance), 2.0, rtol=1e-4)


def test_solve_lens_with_a_finer_input():
    image, depth = scene(32, 32, seed=4)
    lens = jaxdof.ThinLens(0.05, 5.6, 2.0, 2e-5)
    target = jaxdof.render(image, depth, lens, downsample=2)
    init = jaxdof.ThinLens(0.05, 5.6 * 1.2, 2.0 * 1.1, 2e-5)
    res = jaxdof.solve_lens(image, depth, target, init, max_radius=12.0, downsample=2)
    assert bool(res.success)
    np.testing.assert_allclose(float(res.lens.f_number), 5.6, rtol=1e-4)


@pytest.mark.parametrize(
    "downsample, match",
    [(0, ">= 1"), (1.5, "downsample"), (True, "Python int"), (4, "multiples of 4")],
)
def test_render_rejects_bad_downsample(downsample, match):
    # (a float is caught by the signature's run-time type check, a TypeError naming the argument)
    image, depth = scene(6, 10)
    with pytest.raises((ValueError, TypeError), match=match):
        jaxdof.render(image, depth, LENS, downsample=downsample)


@pytest.mark.parametrize("s", [1, 2])
def test_a_one_axis_image_is_named_not_unpacked(s):
    # (under the test suite's jaxtyping hook render's signature refuses it first: a TypeError)
    with pytest.raises((ValueError, TypeError), match="image"):
        jaxdof.render(np.ones(6), np.ones(6), LENS, downsample=s)
    with pytest.raises(ValueError, match=r"image must have shape \(H, W\) or \(H, W, C\)"):
        jaxdof.fit_lens(np.ones(6), np.ones(6), np.ones(6 // s), LENS, downsample=s)


def test_fit_lens_names_the_photo_shape():
    image, depth = scene(16, 20)
    target = np.asarray(jaxdof.render(image, depth, LENS, downsample=2))
    with pytest.raises(ValueError, match=r"divided by downsample=2 \(8, 10, 3\)"):
        jaxdof.fit_lens(image, depth, image, LENS, downsample=2)  # a target at the image's size
    with pytest.raises(ValueError, match="weight must have the targets' pixels"):
        jaxdof.fit_lens(image, depth, target, LENS, downsample=2, weight=np.ones((16, 20)))
    with pytest.raises(ValueError, match="multiples of 3"):
        jaxdof.fit_lens(image, depth, target, LENS, downsample=3)
