"""`jaxdof.LocalOcclusion` (`method="local_occlusion"`): occlusion decided per pair of pixels. Exactly the soft filter where no
source leaves its receiver's surface (planes, even receding ones), a sharp foreground keeps its
edge in front of a blurred background, a blurred foreground is semi-transparent over a sharp
background; the fill: a blurred background keeps its brightness beside a sharp card (no dark
halo), a blurred foreground's edge shows the background that the pinhole image hides behind it;
gradients in image, depth and every lens field, through the fill (float64 `check_grads`)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxdof
from jaxdof import LocalOcclusion


H, W, MAXR = 24, 28, 6.0
RNG = np.random.default_rng(3)
IMAGE = RNG.uniform(0.2, 0.9, (H, W, 3)).astype(np.float32)
LOCAL = LocalOcclusion()
UNFILLED = LocalOcclusion(fill=False)


def _filter(method, image, radius, depth):
    def f(i, r, z):
        z = z if method.uses_depth else None
        return jaxdof.coc_filter(i, r, method=method, depth=z, max_radius=MAXR)

    return np.asarray(jax.jit(f)(image, radius, depth))


@pytest.mark.parametrize("method", [LOCAL, UNFILLED], ids=["fill", "no fill"])
@pytest.mark.parametrize("kind", ["flat", "receding floor", "slanted wall"])
def test_soft_where_no_source_leaves_its_surface(kind, method):
    """A plane (inverse depth affine in the pixel, as perspective makes it) predicts itself, so
    every source is on its receiver's surface: the soft filter, to rounding, with radii of every
    size in the window, although the depth changes by up to 50 % across it."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    inverse = {
        "flat": np.full((H, W), 0.5, np.float32),
        "receding floor": 0.2 + 0.03 * yy,  # 5 m at the top row to 1.1 m at the bottom
        "slanted wall": 0.4 + 0.02 * xx - 0.005 * yy,
    }[kind]
    depth = 1 / inverse
    radius = RNG.uniform(0.0, MAXR, (H, W)).astype(np.float32)
    soft = _filter(jaxdof.Soft(), IMAGE, radius, depth)
    local = _filter(method, IMAGE, radius, depth)
    np.testing.assert_allclose(local, soft, rtol=0, atol=4 * np.finfo(np.float32).eps)


def _two_planes(fg_radius: float, bg_radius: float):
    """A foreground (1 m) over the left half in front of a background (4 m) over the right."""
    left = np.arange(W)[None, :] < W // 2
    depth = np.where(left, 1.0, 4.0).astype(np.float32) + np.zeros((H, 1), np.float32)
    radius = np.where(left, fg_radius, bg_radius).astype(np.float32) + np.zeros((H, 1), np.float32)
    return np.broadcast_to(left, (H, W)), depth, radius


def test_sharp_foreground_keeps_its_edge():
    """The background's large circles reach over the sharp foreground in the soft filter; here the
    foreground's own coverage (1) blocks them: every foreground pixel is its own value."""
    left, depth, radius = _two_planes(0.0, 5.0)
    local = _filter(LOCAL, IMAGE, radius, depth)
    soft = _filter(jaxdof.Soft(), IMAGE, radius, depth)
    np.testing.assert_allclose(local[left], IMAGE[left], rtol=0, atol=1e-6)
    edge = np.zeros((H, W), bool)
    edge[:, W // 2 - 3 : W // 2] = True  # the foreground's last 3 columns
    assert np.abs(soft[edge] - IMAGE[edge]).max() > 0.05  # the bleeding that local removes


def test_blurred_foreground_is_semi_transparent():
    """A black blurred foreground in front of a sharp white background: beside the edge the
    background shows through what the foreground's circles leave open, `1 - coverage`, where
    the soft filter adds the two (white everywhere on the background)."""
    left, depth, radius = _two_planes(4.0, 0.0)
    image = np.where(left[..., None], 0.0, 1.0).astype(np.float32) * np.ones(3, np.float32)
    local = _filter(LOCAL, image, radius, depth)
    soft = _filter(jaxdof.Soft(), image, radius, depth)
    coverage = _filter(jaxdof.Soft(), left[..., None].astype(np.float32), radius, depth)[..., 0]
    right = ~left
    np.testing.assert_allclose(local[right][:, 0], 1 - coverage[right], rtol=0, atol=1e-6)
    assert coverage[:, W // 2].min() > 0.1  # the first background column is partly covered
    np.testing.assert_allclose(soft[right], 1.0, atol=1e-6)


def _card(fg_radius: float, bg_radius: float):
    """A foreground card (1 m) over rows 9-14, columns 11-16, in front of a background (4 m)."""
    card = np.zeros((H, W), bool)
    card[9:15, 11:17] = True
    depth = np.where(card, 1.0, 4.0).astype(np.float32)
    radius = np.where(card, fg_radius, bg_radius).astype(np.float32)
    return card, depth, radius


@pytest.mark.parametrize("texture", ["uniform", "checkerboard"])
def test_fill_no_dark_halo_beside_a_sharp_card(texture):
    """A sharp card in front of a blurred background: the background's circles beside the card
    reach behind it, where the pinhole image shows the card, not the background. Unfilled, that
    part of every circle is missing (a dark halo around the card); filled with the mean colour of
    the background seen, the background keeps its brightness (exactly, for a uniform colour), and
    the card keeps its own sharp edge."""
    card, depth, radius = _card(0.0, 4.0)
    yy, xx = np.mgrid[0:H, 0:W]
    bg = {"uniform": np.full((H, W), 0.6), "checkerboard": 0.6 + 0.2 * (-1.0) ** (yy + xx)}
    image = np.where(card[..., None], 0.1, bg[texture][..., None]).astype(np.float32)
    image = image * np.float32([1.0, 0.8, 0.5])  # a colour, not grey
    filled = _filter(LOCAL, image, radius, depth)
    unfilled = _filter(UNFILLED, image, radius, depth)
    # the background within 3 px of the card (circles within the frame: none reaches past it)
    ring = np.zeros((H, W), bool)
    ring[6:18, 8:20] = True
    ring &= ~card
    colour = 0.6 * np.float32([1.0, 0.8, 0.5])
    # uniform: exact to rounding; checkerboard: the blurred checkerboard's ripple (< 2 %)
    atol = 1e-6 if texture == "uniform" else 0.02
    np.testing.assert_allclose(filled[ring], np.broadcast_to(colour, filled[ring].shape), atol=atol)
    assert (unfilled[ring] / colour).min() < 0.75  # the halo the fill removes
    np.testing.assert_allclose(filled[card], image[card], rtol=0, atol=1e-6)


def test_fill_shows_the_background_behind_a_blurred_foreground_edge():
    """A black blurred foreground in front of a sharp white background: inside the foreground's
    edge its own circles cover the pixel only in part, and the aperture sees the white background
    behind it there, which the pinhole image hides. Filled: `1 - coverage` of white (as a layered
    render with the background continued behind the foreground); unfilled: black."""
    left, depth, radius = _two_planes(4.0, 0.0)
    image = np.where(left[..., None], 0.0, 1.0).astype(np.float32) * np.ones(3, np.float32)
    filled = _filter(LOCAL, image, radius, depth)
    unfilled = _filter(UNFILLED, image, radius, depth)
    coverage = _filter(jaxdof.Soft(), left[..., None].astype(np.float32), radius, depth)[..., 0]
    edge = np.zeros((H, W), bool)
    edge[5:-5, W // 2 - 3 : W // 2] = True  # the foreground's last 3 columns, away from the border
    assert (1 - coverage[edge]).min() > 0.05  # partly covered: the background shows through
    # the fill's mean is a weighted mean of white (1) with a floor of 1e-4 in its weight: < 1 %
    np.testing.assert_allclose(filled[edge][:, 0], 1 - coverage[edge], rtol=0, atol=0.01)
    np.testing.assert_allclose(unfilled[edge], 0.0, atol=1e-6)


def test_options():
    assert LocalOcclusion(jump=0.1).jump == 0.1
    assert LocalOcclusion().fill and not UNFILLED.fill
    for bad in (0.0, -0.1, 2.0):
        with pytest.raises(ValueError, match="jump must be"):
            LocalOcclusion(jump=bad)
    # the jaxtyping hook of the test run refuses a non-bool `fill` at the signature already
    # (TypeError); without it, the method's own check (ValueError, as `Occlusion`'s)
    with pytest.raises((TypeError, ValueError), match="fill"):
        LocalOcclusion(fill=1)  # type: ignore[arg-type]
    # without a depth map there is no order to decide: the soft filter
    radius = RNG.uniform(0.0, MAXR, (H, W)).astype(np.float32)
    a = jaxdof.coc_filter(IMAGE, radius, method=LOCAL, max_radius=MAXR)
    b = jaxdof.coc_filter(IMAGE, radius, method="soft", max_radius=MAXR)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_gradients_every_input():
    """Image, depth (a step, a slope, a row at infinity) and every lens field, forward and
    reverse, float64, through `jaxdof.render`; radii away from 1/2 and the window. Both fills are
    active: beside the step the background's circles reach behind the foreground (hidden
    surface) and the foreground's own circles leave part of it open (hidden background)."""
    rng = np.random.default_rng(0)
    image = rng.uniform(size=(5, 6, 2))
    depth = np.where(np.arange(6)[None, :] < 3, 1.6, 5.0) + 0.05 * rng.uniform(size=(5, 6))
    inf_row = np.zeros((5, 6), bool)
    inf_row[0] = True

    def f(image, depth, f_, n, d_f, method=LOCAL):
        z = jnp.where(inf_row, jnp.inf, depth)
        lens = jaxdof.ThinLens(f_, n, d_f, 2e-5)
        return jaxdof.render(image, z, lens, method=method, max_radius=7.0)

    args = (image, depth, 0.05, 4.0, 3.0)  # circles 2.1-5.3 px
    # the fill is active on both sides of the step (the test exercises its derivative)
    change = np.abs(np.asarray(f(*args)) - np.asarray(f(*args, method=UNFILLED))).max(-1)
    assert (change[1:, :3] > 1e-3).all() and (change[1:, 3:] > 1e-3).all()
    check_grads(f, args, order=1, modes=("fwd", "rev"), eps=1e-6, atol=2e-7, rtol=2e-5)


def test_occlusion_off_is_soft_bit_for_bit_and_chosen_at_run_time():
    """`occlude=False` renders the soft filter bit for bit beside a depth step (where the
    occlusion render differs from it by a third of the image's range); a scalar boolean array
    chooses at run time with one compiled program: off the soft filter bit for bit, on the
    occlusion render to rounding (a run-time factor against a compiled-in constant)."""
    _, depth, _ = _two_planes(0.0, 0.0)
    radius = RNG.uniform(0.0, MAXR, (H, W)).astype(np.float32)
    for dtype in (np.float32, np.float64):
        image, z, r = (x.astype(dtype) for x in (IMAGE, depth, radius))
        soft = _filter(jaxdof.Soft(), image, r, z)
        local = _filter(LOCAL, image, r, z)
        assert np.abs(local - soft).max() > 0.1  # the step changes the render
        np.testing.assert_array_equal(_filter(LocalOcclusion(occlude=False), image, r, z), soft)
        switch = jax.jit(
            lambda flag, i, r, z: jaxdof.coc_filter(
                i, r, method=LocalOcclusion(occlude=flag), depth=z, max_radius=MAXR
            )
        )
        off, on = (np.asarray(switch(jnp.asarray(v), image, r, z)) for v in (False, True))
        np.testing.assert_array_equal(off, soft)
        np.testing.assert_allclose(on, local, rtol=0, atol=8 * np.finfo(dtype).eps)
        assert switch._cache_size() == 1
    for bad in (jnp.asarray([True, False]), jnp.asarray(1.0)):
        with pytest.raises(ValueError, match="occlude must be"):
            LocalOcclusion(occlude=bad)


@pytest.mark.parametrize("occlude", [False, True])
def test_gradients_with_occlusion_chosen_at_run_time(occlude):
    """Image, radius and depth through the run-time switch, both values, forward and reverse,
    float64, beside a depth step."""
    rng = np.random.default_rng(1)
    image = rng.uniform(size=(5, 6, 2))
    depth = np.where(np.arange(6)[None, :] < 3, 1.6, 5.0) + 0.05 * rng.uniform(size=(5, 6))
    radius = 1.2 + 2.5 * rng.uniform(size=(5, 6))  # away from 1/2 and the window
    method = LocalOcclusion(occlude=jnp.asarray(occlude))

    def f(image, radius, depth):
        return jaxdof.coc_filter(image, radius, method=method, depth=depth, max_radius=5.0)

    check_grads(f, (image, radius, depth), order=1, modes=("fwd", "rev"), eps=1e-6, atol=2e-7)
