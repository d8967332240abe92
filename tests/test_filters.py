import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxdof
from jaxdof import ThinLens, circle_pixel_overlap, coc_filter, render
from jaxdof._filters.common import tap_offsets, window_half_width

from .helpers import scatter_reference, step_scene


RADIUS_MAPS = {
    "zero": lambda h, w: np.zeros((h, w)),
    "constant": lambda h, w: np.full((h, w), 3.2),
    "steps": lambda h, w: step_scene(h, w)[1],
    "random": lambda h, w: np.random.default_rng(3).uniform(0, 20, (h, w)),
}


def _reference(image, radius):
    return scatter_reference(image, radius, lambda dx, dy, r: circle_pixel_overlap(dx, dy, r))


@pytest.mark.parametrize("name", list(RADIUS_MAPS))
def test_matches_scatter_reference_float64(name):
    image, _ = step_scene(22, 26)
    radius = RADIUS_MAPS[name](22, 26)
    got = np.asarray(coc_filter(image, radius, max_radius=20.0))
    np.testing.assert_allclose(got, _reference(image, radius), rtol=0, atol=1e-10)


@pytest.mark.parametrize("name", list(RADIUS_MAPS))
def test_matches_scatter_reference_float32(name):
    image, _ = step_scene(22, 26)
    radius = RADIUS_MAPS[name](22, 26)
    got = coc_filter(image.astype(np.float32), radius.astype(np.float32), max_radius=20.0)
    assert got.dtype == jnp.float32
    expected = _reference(image.astype(np.float32), radius.astype(np.float32))
    err = np.abs(np.asarray(got, np.float64) - expected).max() / np.ptp(image)
    assert err <= 2e-5


def test_identity_at_zero_radius():
    image, _ = step_scene(9, 7)
    for r in (0.0, 1e-7, 0.3, 0.5):
        out = coc_filter(image, np.full((9, 7), r), max_radius=4.0)
        assert np.array_equal(np.asarray(out), image)


def test_energy_conserved_in_interior():
    rng = np.random.default_rng(1)
    image = rng.uniform(size=(40, 40, 2))
    radius = np.zeros((40, 40))
    radius[10:30, 10:30] = rng.uniform(0, 8, (20, 20))  # discs stay inside the frame
    out = coc_filter(image, radius, max_radius=8.0)
    np.testing.assert_allclose(np.asarray(out).sum((0, 1)), image.sum((0, 1)), rtol=1e-12)


def test_normalize_keeps_flat_field_flat():
    radius = np.random.default_rng(2).uniform(0, 5, (16, 20))
    flat = np.full((16, 20), 0.7)
    out = coc_filter(flat, radius, max_radius=5.0, normalize=True)
    np.testing.assert_allclose(np.asarray(out), 0.7, rtol=1e-12)
    assert not np.allclose(np.asarray(coc_filter(flat, radius, max_radius=5.0)), 0.7)


def test_window_is_no_wider_than_needed():
    for R in (0.0, 0.5, 1.0, 2.3, 2.5, 2.7, 8.0, 16.0):
        assert window_half_width(R) <= math.ceil(R)
        offs = tap_offsets(R)
        # every dropped offset gets zero area; every kept one can get some
        o = np.arange(-math.ceil(R) - 1, math.ceil(R) + 2)
        oy, ox = np.meshgrid(o, o, indexing="ij")
        area = np.asarray(circle_pixel_overlap(ox.astype(float), oy.astype(float), R))
        kept = {tuple(x) for x in offs}
        for y, x, a in zip(oy.ravel(), ox.ravel(), area.ravel()):
            if (y, x) not in kept:
                assert a == 0.0


def test_radii_above_max_radius_are_clamped():
    image, _ = step_scene(20, 20)
    big = coc_filter(image, np.full((20, 20), 50.0), max_radius=3.0)
    ref = coc_filter(image, np.full((20, 20), 3.0), max_radius=3.0)
    np.testing.assert_array_equal(np.asarray(big), np.asarray(ref))


def test_jit_vmap_match_eager():
    image, radius = step_scene(16, 18)
    eager = coc_filter(image, radius, max_radius=20.0)
    jitted = jax.jit(coc_filter, static_argnames=("max_radius",))(image, radius, max_radius=20.0)
    np.testing.assert_allclose(np.asarray(jitted), np.asarray(eager), rtol=1e-14, atol=1e-14)
    batch = jax.vmap(lambda i, r: coc_filter(i, r, max_radius=20.0))(
        jnp.stack([image, 2 * image]), jnp.stack([radius, radius / 2])
    )
    np.testing.assert_allclose(np.asarray(batch[0]), np.asarray(eager), rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(
        np.asarray(batch[1]),
        np.asarray(coc_filter(2 * image, radius / 2, max_radius=20.0)),
        rtol=1e-13,
    )


def test_grads_image_and_radius():
    rng = np.random.default_rng(4)
    image = jnp.asarray(rng.uniform(size=(7, 8, 2)))
    radius = jnp.asarray(rng.uniform(0.6, 3.5, (7, 8)))  # away from the r <= 1/2 dead zone
    f = lambda i, r: coc_filter(i, r, max_radius=4.0)
    # central differences in float64: check_grads' default tolerance (1e-5 relative) holds
    check_grads(f, (image, radius), order=1, modes=("fwd", "rev"), eps=1e-6)
    g = jax.grad(lambda r: jnp.sum(coc_filter(image, r, max_radius=4.0) ** 2))(jnp.zeros((7, 8)))
    assert np.all(np.isfinite(np.asarray(g)))


def test_grads_render_every_input():
    rng = np.random.default_rng(5)
    image = jnp.asarray(rng.uniform(size=(6, 7)))
    depth = jnp.asarray(rng.uniform(1.5, 6.0, (6, 7)))

    # Pixel pitch in units of 10 um so that one finite-difference step suits every argument.
    def f(image, depth, fl, n, d_f, pitch):
        return render(image, depth, ThinLens(fl, n, d_f, pitch * 1e-5), max_radius=6.0)

    args = (image, depth, *(jnp.asarray(v) for v in (0.05, 2.0, 3.0, 6.0)))
    lens = ThinLens(0.05, 2.0, 3.0, 6e-5)
    assert 1.0 < float(jnp.max(jaxdof.coc_radius(depth, lens))) < 6.0
    check_grads(f, args, order=1, modes=("fwd", "rev"), eps=1e-6)


def test_render_picks_smallest_window():
    image = np.ones((5, 5))
    depth = np.full((5, 5), 3.0)
    lens = ThinLens(0.05, 2.0, 3.0, 6e-6)
    np.testing.assert_array_equal(np.asarray(render(image, depth, lens)), image)
    with pytest.raises(ValueError, match="max_radius"):
        jax.jit(lambda d: render(image, d, lens))(depth)
    jax.jit(lambda d: render(image, d, lens, max_radius=2.0))(depth)


def test_bad_inputs():
    image = np.ones((4, 5))
    with pytest.raises(ValueError, match="radius must have the image's"):
        coc_filter(image, np.zeros((5, 4)), max_radius=1.0)
    with pytest.raises(ValueError, match="floating-point"):
        coc_filter(np.ones((4, 5), np.uint8), np.zeros((4, 5)), max_radius=1.0)
    with pytest.raises(ValueError, match=">= 0"):
        coc_filter(image, -np.ones((4, 5)), max_radius=1.0)
    with pytest.raises(ValueError, match="method='nope' is not a filter method"):
        coc_filter(image, np.zeros((4, 5)), method="nope", max_radius=1.0)
    with pytest.raises(ValueError, match="shape"):
        coc_filter(np.ones((2, 3, 4, 5)), np.zeros((2, 3)), max_radius=1.0)
    lens = ThinLens(0.05, 2.0, 3.0, 6e-6)
    with pytest.raises(ValueError, match="beyond the focal length"):
        render(image, np.full((4, 5), 0.01), lens)
    with pytest.raises(ValueError, match="depth must have"):
        render(image, np.ones((3, 3)), lens)


def test_lens_module_is_equinox():
    assert isinstance(ThinLens(0.05, 2.0, 3.0, 6e-6), eqx.Module)
