"""The occlusion-aware filter (`jaxdof.Occlusion`, `jaxdof/_filters/occlusion.py`)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy.ndimage import distance_transform_edt

from jaxdof import Occlusion, ThinLens, coc_filter, coc_radius, render
from jaxdof._filters.common import check_bool
from jaxdof._filters.occlusion import depth_layers, nearest_seed


# One small frame and one window for every test, and jitted entry points with the options static,
# so that the few compilations are shared between tests (compiling dominates their cost).
H, W = 14, 16
MAXR = 3.0
RNG = np.random.default_rng(3)
IMAGE = RNG.uniform(0.1, 1.0, (H, W, 3))


@functools.partial(jax.jit, static_argnames=("fill",))
def _occ(image, radius, depth, fill=True):
    return coc_filter(image, radius, method=Occlusion(fill=fill), depth=depth, max_radius=MAXR)


@jax.jit
def _soft(image, radius):
    return coc_filter(image, radius, max_radius=MAXR)


def two_depths(fg_radius: float, bg_radius: float, *, fg_cols: int = W // 2):
    """Foreground (1 m) on the left `fg_cols` columns, background (4 m) on the right."""
    depth = np.full((H, W), 4.0)
    depth[:, :fg_cols] = 1.0
    radius = np.where(depth < 2, fg_radius, bg_radius)
    return depth, radius


def occ(image, radius, depth, fill=True):
    image = (
        np.broadcast_to(np.asarray(image, float)[..., None], (H, W, 3))
        if np.ndim(image) == 2
        else image
    )
    return _occ(image, radius, depth, fill=fill)


@pytest.mark.parametrize("fill", [True, False])
def test_one_depth_or_smooth_depth_is_the_soft_filter(fill):
    radius = RNG.uniform(0.0, 2.9, (H, W))
    soft = _soft(IMAGE, radius)
    # a ramp from 1 to 6 m: consecutive sorted depths differ far less than 3%, so one layer
    ramp = np.linspace(1.0, 6.0, H * W).reshape(H, W)
    for depth in (np.full((H, W), 2.5), ramp):
        out = occ(IMAGE, radius, depth, fill=fill)
        np.testing.assert_array_equal(np.asarray(out), np.asarray(soft))
    # no depth at all: one layer too
    out = jax.jit(lambda i, r: coc_filter(i, r, method=Occlusion(), max_radius=MAXR))(IMAGE, radius)
    np.testing.assert_array_equal(np.asarray(out), np.asarray(soft))


def test_depth_layers_cut_at_gaps_nearest_first():
    depth = np.full((H, W), 1.0)
    depth[:, 4:8], depth[:, 8:12], depth[:, 12:] = 1.02, 2.0, np.inf  # 2% is no gap
    layers = jax.jit(depth_layers, static_argnums=1)
    idx = np.asarray(layers(jnp.asarray(depth), 4))
    assert np.array_equal(np.unique(idx[:, :8]), [0])
    assert np.array_equal(np.unique(idx[:, 8:12]), [1])
    assert np.array_equal(np.unique(idx[:, 12:]), [2])  # inf is the farthest layer
    # two layers allowed: the largest gap (2 m -> inf) is kept
    idx2 = np.asarray(layers(jnp.asarray(depth), 2))
    assert np.array_equal(np.unique(idx2[:, :12]), [0]) and np.all(idx2[:, 12:] == 1)


def test_nearest_seed_matches_exact_distance_transform():
    seed = np.random.default_rng(0).uniform(size=(37, 41)) < 0.03
    by, bx = (np.asarray(a) for a in nearest_seed(jnp.asarray(seed)))
    assert np.all(seed[by, bx])
    d = np.hypot(by - np.arange(37)[:, None], bx - np.arange(41)[None, :])
    # ties may pick another seed at the same distance; the distance itself must be exact
    np.testing.assert_allclose(d, distance_transform_edt(~seed), rtol=0, atol=1e-12)


def test_sharp_foreground_is_not_overlaid_by_the_blurred_background():
    depth, radius = two_depths(0.0, 2.9)
    fg = depth < 2
    soft = np.asarray(_soft(IMAGE, radius))
    out = np.asarray(occ(IMAGE, radius, depth))
    # the plain scatter spreads background light over the in-focus foreground (up to ~3 px in)
    assert np.max(np.abs(soft - IMAGE)[fg]) > 0.05
    # the occluder is opaque: its pixels are exactly the sharp image
    np.testing.assert_array_equal(out[fg], IMAGE[fg])


def test_defocused_foreground_edge_is_a_mix_of_the_two_colours():
    """Flat colours: fg 0.9 (radius 2.9) over an in-focus bg 0.2. A real aperture sees a mix of
    the two across the edge, never more light than the brighter nor less than the darker."""
    depth, radius = two_depths(2.9, 0.0)
    image = np.where(depth[..., None] < 2, 0.9, 0.2) * np.ones((1, 1, 3))
    inner = np.s_[3:-3, 3:-3]  # the frame's border loses light to the outside: not the edge
    soft = np.asarray(_soft(image, radius))[inner]
    filled = np.asarray(occ(image, radius, depth))[inner]
    bare = np.asarray(occ(image, radius, depth, fill=False))[inner]
    eps = 1e-12  # round-off of sums of a few dozen weights of size ~1
    assert filled.min() >= 0.2 - eps and filled.max() <= 0.9 + eps
    # the fill is what makes it so: without it the background hidden behind the defocused
    # occluder is missing, so the occluder's partly transparent rim is darker than the mix (by
    # 0.2 (1 - alpha), alpha ~ 1/2 on its last column)
    rim = W // 2 - 1 - 3  # the foreground's last column, in `inner` coordinates
    assert np.all(bare[:, rim] < filled[:, rim] - 0.05)
    # and the plain scatter adds the foreground's light on top of the background's (a bright rim
    # beyond the edge)
    assert soft[:, rim + 1 :].max() > filled[:, rim + 1 :].max() + 0.05
    # and the edge is actually blurred (a ramp, not a step)
    row = filled[4, :, 0]
    assert np.sum((row > 0.25) & (row < 0.85)) >= 4


@pytest.mark.parametrize("fill", [True, False])
def test_constant_image_stays_constant_in_the_interior(fill):
    """Coverage adds up to one: the layers composited with `over` pass a flat field through."""
    depth = np.full((H, W), 4.0)
    depth[4:10, 4:9] = 1.0
    depth[7:, 10:14] = 2.0
    radius = np.where(depth < 1.5, 2.6, np.where(depth < 3, 1.3, 2.9))
    out = np.asarray(occ(np.ones((H, W)), radius, depth, fill=fill))
    inner = out[3:-3, 3:-3]
    if fill:
        np.testing.assert_allclose(inner, 1.0, rtol=0, atol=1e-12)  # round-off only
    else:
        # without the fill, light is missing where a defocused occluder uncovers a hole
        assert inner.max() <= 1 + 1e-12 and inner.min() < 0.9


def _grad_scene():
    rng = np.random.default_rng(1)
    depth = np.full((7, 8), 3.0)
    depth[2:5, 1:4] = 1.2
    radius = np.where(depth < 2, 1.9, 1.1) + rng.uniform(-0.3, 0.3, depth.shape)
    return rng.uniform(size=(7, 8, 2)), radius, depth


def test_gradients_image_and_radius():
    image, radius, depth = _grad_scene()
    f = jax.jit(
        lambda i, r: coc_filter(i, r, method=Occlusion(layers=2), depth=depth, max_radius=2.5)
    )
    # float64. Linear in the image; in the radius a product of smooth soft weights, and the only
    # kinks (the clip of 1 - alpha at 0 and 1; r = 1/2, r = max_radius) are far from these radii,
    # so central differences of step 1e-6 px are accurate to ~1e-10 relative; 1e-6 is ample.
    # (fill=False shares every step but the fill, a gather of the same image and radii.)
    check_grads(f, (image, radius), order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-6, rtol=1e-6)


def test_no_gradient_through_the_depth_order():
    image, radius, depth = _grad_scene()
    g = jax.jit(
        jax.grad(
            lambda z: jnp.sum(
                coc_filter(image, radius, method=Occlusion(layers=2), depth=z, max_radius=2.5) ** 2
            )
        )
    )(jnp.asarray(depth))
    assert np.array_equal(np.asarray(g), np.zeros_like(depth))


def test_render_gradient_in_depth_and_lens_through_the_radius():
    image, _, depth = _grad_scene()
    pitch = 0.05 / 500  # f = 500 px: circles of ~1.1 and 2.1 px at these depths

    def f(z, n):
        lens = ThinLens(0.05, n, 2.0, pitch)
        return render(image, z, lens, method=Occlusion(layers=2), max_radius=2.5)

    r = coc_radius(depth, ThinLens(0.05, 2.0, 2.0, pitch))
    assert float(jnp.min(r)) > 0.6 and float(jnp.max(r)) < 2.5  # off the kinks at 1/2 and 2.5
    # depth moves the radii (smoothly), not the layers (a 1e-6 m step never crosses a 3% gap).
    # Forward mode (what fit_lens uses); reverse mode of the same filter is checked above.
    check_grads(jax.jit(f), (depth, 2.0), order=1, modes=("fwd",), eps=1e-6, atol=1e-6, rtol=1e-6)


def test_render_passes_its_depth():
    depth, _ = two_depths(0, 0)
    lens = ThinLens(0.05, 5.6, 2.0, 0.05 / 1000)  # circles of 2.3 px (1 m) and 1.1 px (4 m)
    radius = np.asarray(coc_radius(depth, lens))
    assert radius.max() < MAXR
    a = jax.jit(lambda i, z: render(i, z, lens, method=Occlusion(), max_radius=MAXR))(IMAGE, depth)
    np.testing.assert_allclose(np.asarray(a), np.asarray(occ(IMAGE, radius, depth)), atol=1e-13)
    assert not np.allclose(np.asarray(a), np.asarray(_soft(IMAGE, radius)))


def test_jit_and_vmap():
    depth, radius = two_depths(2.2, 1.3)
    eager = coc_filter(IMAGE, radius, method=Occlusion(), depth=depth, max_radius=MAXR)
    np.testing.assert_allclose(np.asarray(occ(IMAGE, radius, depth)), eager, rtol=0, atol=1e-13)
    images = np.stack([IMAGE, IMAGE[::-1]])
    depths = np.stack([depth, depth[:, ::-1]])
    radii = np.stack([radius, radius[:, ::-1]])
    batched = np.asarray(jax.vmap(_occ)(images, radii, depths))
    for k in range(2):
        single = np.asarray(occ(images[k], radii[k], depths[k]))
        np.testing.assert_allclose(batched[k], single, rtol=0, atol=1e-13)


def test_float32():
    depth, radius = two_depths(2.2, 1.3)
    out = _occ(IMAGE.astype(np.float32), radius.astype(np.float32), depth.astype(np.float32))
    assert out.dtype == jnp.float32 and np.all(np.isfinite(np.asarray(out)))


def test_bad_options():
    depth, radius = two_depths(1.0, 2.0)
    # the jaxtyping hook of the test run refuses a non-bool `fill` at the signature already
    # (TypeError); without it, the method's own check (ValueError). The check itself:
    with pytest.raises((TypeError, ValueError), match="fill"):
        Occlusion(fill=1)
    with pytest.raises(ValueError, match="fill must be a Python bool"):
        check_bool("fill", 1)
    with pytest.raises(ValueError, match="layers must be in"):
        Occlusion(layers=0)
    with pytest.raises(ValueError, match="depth must be a floating-point"):
        coc_filter(IMAGE, radius, method=Occlusion(), depth=depth[:, :-1], max_radius=MAXR)
    with pytest.raises(ValueError, match="does not use depth"):
        coc_filter(IMAGE, radius, depth=depth, max_radius=MAXR)
