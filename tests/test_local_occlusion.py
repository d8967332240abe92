"""`jaxdof.internal.LocalOcclusion` (experimental): occlusion decided per pair of pixels. Exactly the soft filter where no
source leaves its receiver's surface (planes, even receding ones), a sharp foreground keeps its
edge in front of a blurred background, a blurred foreground is semi-transparent over a sharp
background; gradients in image, depth and every lens field (float64 `check_grads`)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxdof
from jaxdof.internal import LocalOcclusion


H, W, MAXR = 24, 28, 6.0
RNG = np.random.default_rng(3)
IMAGE = RNG.uniform(0.2, 0.9, (H, W, 3)).astype(np.float32)
LOCAL = LocalOcclusion()


def _filter(method, image, radius, depth):
    def f(i, r, z):
        z = z if method.uses_depth else None
        return jaxdof.coc_filter(i, r, method=method, depth=z, max_radius=MAXR)

    return np.asarray(jax.jit(f)(image, radius, depth))


@pytest.mark.parametrize("kind", ["flat", "receding floor", "slanted wall"])
def test_soft_where_no_source_leaves_its_surface(kind):
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
    local = _filter(LOCAL, IMAGE, radius, depth)
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


def test_options():
    assert LocalOcclusion(jump=0.1).jump == 0.1
    for bad in (0.0, -0.1, 2.0):
        with pytest.raises(ValueError, match="jump must be"):
            LocalOcclusion(jump=bad)
    # without a depth map there is no order to decide: the soft filter
    radius = RNG.uniform(0.0, MAXR, (H, W)).astype(np.float32)
    a = jaxdof.coc_filter(IMAGE, radius, method=LOCAL, max_radius=MAXR)
    b = jaxdof.coc_filter(IMAGE, radius, method="soft", max_radius=MAXR)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_gradients_every_input():
    """Image, depth (a step, a slope, a row at infinity) and every lens field, forward and
    reverse, float64, through `jaxdof.render`; radii away from 1/2 and the window."""
    rng = np.random.default_rng(0)
    image = rng.uniform(size=(5, 6, 2))
    depth = np.where(np.arange(6)[None, :] < 3, 1.6, 5.0) + 0.05 * rng.uniform(size=(5, 6))
    inf_row = np.zeros((5, 6), bool)
    inf_row[0] = True

    def f(image, depth, f_, n, d_f):
        z = jnp.where(inf_row, jnp.inf, depth)
        lens = jaxdof.ThinLens(f_, n, d_f, 2e-5)
        return jaxdof.render(image, z, lens, method=LOCAL, max_radius=7.0)

    args = (image, depth, 0.05, 4.0, 3.0)  # circles 2.1-5.3 px
    check_grads(f, args, order=1, modes=("fwd", "rev"), eps=1e-6, atol=2e-7, rtol=2e-5)
