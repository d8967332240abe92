"""fit_lens's border: the photo pixels that light from outside the frame reaches are left out.

A photo pixel within a circle's reach of the frame's edge receives light from scene points outside
the frame, which the all-in-focus image lacks: the forward model puts zeros there. These tests
render the true photo from a larger frame and crop it, so that its border holds that outside
light, as a real photo's does.
"""

import json
import math

import numpy as np
import pytest

import jaxdof
from jaxdof import ThinLens, fit_lens, render, solve_lens
from jaxdof._fit import strategies

from .helpers import EXACT


H = W = 32
PITCH = 8e-5  # m, as in tests/test_fit.py: a 50 mm f/2 lens makes circles of a few pixels
WINDOW = 6.0  # px: the truth's largest circle here is 3.1 px
PAD = 10  # px of scene around the photo's frame: more than the window
FREE = ("f_number", "focus_distance")


def lens(n=2.0, d_f=1.6):
    return ThinLens(0.05, n, d_f, PITCH)


def cropped_scene(seed=0):
    """A random texture on a plane slanted from 1 to 3 m across a frame `PAD` px wider than the
    photo on every side, the photo rendered through the true lens there and cropped: its border
    pixels hold the light from outside the frame. Returns the cropped image, depth and photo."""
    rng = np.random.default_rng(seed)
    h, w = H + 2 * PAD, W + 2 * PAD
    image = rng.uniform(size=(h, w))
    depth = np.broadcast_to(1.0 + 2.0 * np.arange(w) / (w - 1), (h, w)).copy()
    photo = np.asarray(render(image, depth, lens(), max_radius=WINDOW))
    crop = (slice(PAD, PAD + H), slice(PAD, PAD + W))
    return image[crop], depth[crop], photo[crop]


def rel_err(fit, fields=FREE):
    true = lens()
    return max(abs(float(getattr(fit.lens, n)) / float(getattr(true, n)) - 1) for n in fields)


def test_border_on_by_default_recovers_the_lens():
    """The default fit leaves out the band of ceil(max_radius) px and recovers the lens (within
    0.5 %, the issue's figure; noise-free, so far better); keeping every pixel biases it, as the
    model's zeros stand in for the outside light."""
    image, depth, photo = cropped_scene()
    init = lens(n=3.0, d_f=2.0)
    kw = dict(free=FREE, max_radius=WINDOW, starts=2, **EXACT)
    res = fit_lens(image, depth, photo, init, **kw)
    assert bool(res.success), res.message
    # Inside the band every pixel's light comes from inside the frame: the fit is exact up to the
    # solver's tolerance (1e-8 in the log coordinates, float64).
    assert rel_err(res) < 1e-6, rel_err(res)
    assert res.border == math.ceil(WINDOW)
    assert int(res.pixels_used) == (H - 2 * 6) * (W - 2 * 6)
    assert "pixels used 400 (border 6 px)" in res.summary()
    obj = json.loads(json.dumps(res.to_dict(), allow_nan=False))
    assert (obj["border"], obj["pixels_used"]) == (6, 400)
    every = fit_lens(image, depth, photo, init, border=False, **kw)
    assert every.border == 0 and int(every.pixels_used) == H * W
    # Measurably biased: at least 10 times the 1e-4 that noise-free fits are held to elsewhere.
    assert rel_err(every) > 1e-3, rel_err(every)
    # The same compiled solve: the band is a zero weight, data and not code.
    assert float(every.loss) > 1e3 * float(res.loss) + 1e-12


def test_border_is_a_weight():
    """The band multiplies the user's weight: a weighted fit with the band is the fit with
    weight * band and no band, to rounding, and an int is that band in photo pixels."""
    image, depth, photo = cropped_scene(seed=1)
    kw = dict(free=FREE, max_radius=WINDOW, starts=2, **EXACT)
    weight = np.random.default_rng(2).uniform(0.5, 1.5, size=(H, W))
    band = strategies.border_mask((H, W), 6)
    a = fit_lens(image, depth, photo, lens(), weight=weight, **kw)
    b = fit_lens(image, depth, photo, lens(), weight=weight * band, border=0, **kw)
    # The band keeps 400 of 1024 pixels, so the banded fit first searches its basin on every
    # pixel (`fit._SEARCH_ALL_BELOW`) and reaches the same minimum by another path: the two agree
    # to the solver's tolerance (1e-8 in the log coordinates, float64), not to rounding.
    np.testing.assert_allclose(float(a.lens.f_number), float(b.lens.f_number), rtol=1e-8)
    assert (a.border, b.border) == (6, 0) and int(a.pixels_used) == int(b.pixels_used) == 400
    two = fit_lens(image, depth, photo, lens(), border=2, **kw)
    assert two.border == 2 and int(two.pixels_used) == (H - 4) * (W - 4)


def test_border_follows_the_window():
    """The automatic band is the window the fit used, at every downsample (the window is in the
    photo's pixels already), two pixels more with the footprint correction, whose stencils read
    two neighbours."""
    image, depth, photo = cropped_scene(seed=3)
    res = fit_lens(
        image, depth, photo, lens(n=2.4), free=FREE, starts=1, **EXACT
    )  # automatic window
    assert bool(res.success), res.message
    assert res.border == math.ceil(res.max_radius)
    model = jaxdof.DefocusModel
    assert model().border_band(6.0) == model(downsample=2).border_band(6.0) == 6
    assert model(downsample=2).border_band(5.3) == 6  # ceil(ceil(10.6) / 2) = ceil(5.3)
    assert model(footprint=True).border_band(6.0) == 8
    assert model(downsample=2, footprint=True).border_band(5.5) == 7  # ceil((11 + 2) / 2)
    # Each pyramid level: the band of that level's window, or a given band halved (rounded up).
    assert strategies.level_band(None, model(), 3.0, 1) == 3
    assert strategies.level_band(5, model(), 3.0, 1) == 3
    assert strategies.level_band(5, model(), 3.0, 2) == 2


def test_border_with_downsample_and_pyramid():
    """A finer all-in-focus input (downsample=2) and a coarse-to-fine fit both leave out the
    band in photo pixels and recover the lens from the cropped photo."""
    rng = np.random.default_rng(4)
    h, w = 2 * (H + 2 * PAD), 2 * (W + 2 * PAD)
    image = rng.uniform(size=(h, w))
    depth = np.broadcast_to(1.0 + 2.0 * np.arange(w) / (w - 1), (h, w)).copy()
    photo = np.asarray(render(image, depth, lens(), max_radius=WINDOW, downsample=2))
    crop = (slice(2 * PAD, 2 * (PAD + H)), slice(2 * PAD, 2 * (PAD + W)))
    photo = photo[PAD : PAD + H, PAD : PAD + W]
    kw = dict(free=FREE, max_radius=WINDOW, downsample=2, starts=1, **EXACT)
    res = fit_lens(image[crop], depth[crop], photo, lens(n=2.4, d_f=1.8), **kw)
    assert bool(res.success), res.message
    assert res.border == 6 and int(res.pixels_used) == 400
    assert rel_err(res) < 1e-6, rel_err(res)
    image, depth, photo = cropped_scene(seed=5)
    kw = dict(free=FREE, max_radius=WINDOW, starts=2, pyramid=2, **EXACT)
    res = fit_lens(image, depth, photo, lens(n=2.6, d_f=1.9), **kw)
    assert bool(res.success) and res.levels == 2, res.message
    assert res.border == 6 and rel_err(res) < 1e-6, rel_err(res)


def test_border_falls_back_on_a_tiny_image():
    """A band that leaves no pixel: every pixel is kept, and the message says so."""
    image, depth, photo = (x[:10, :10] for x in cropped_scene(seed=6))
    kw = dict(free=("f_number",), max_radius=WINDOW, starts=1, **EXACT)
    res = fit_lens(image, depth, photo, lens(n=2.4), **kw)
    assert res.border == 0 and int(res.pixels_used) == 100
    assert "border band of 6 px" in res.message and "every pixel" in res.message


def test_solve_lens_border():
    """solve_lens leaves out the same band (decided from the shapes, under jit)."""
    image, depth, photo = cropped_scene(seed=7)
    res = solve_lens(image, depth, photo, lens(n=2.4), max_radius=WINDOW)
    assert bool(res.success), jaxdof.RESULTS[res.status]
    assert res.border == 6 and int(res.pixels_used) == 400
    assert rel_err(res) < 1e-6
    assert solve_lens(image, depth, photo, lens(), max_radius=WINDOW, border=False).border == 0


@pytest.mark.parametrize("border", ["none", -1])
def test_bad_border(border):
    # (A float or None never gets this far under the tests' type-checking hook; without it,
    # fit_lens raises the same ValueError for them.)
    image, depth, photo = cropped_scene()
    with pytest.raises(ValueError, match="border must be"):
        fit_lens(image, depth, photo, lens(), border=border)
