"""Physical and symmetry properties of the filters, with hypothesis-drawn inputs.

Reproducible: examples are derandomized (a fixed sequence per test), few and small, no deadline
(the first example compiles). Shapes are fixed per test so that each method compiles once.
All in float64; tolerances are float64 round-off of sums of a few hundred terms of size <= 1.
"""

import numpy as np
import pytest
from hypothesis import Phase, given, settings, strategies as st
from hypothesis.extra.numpy import arrays

from jaxdof import ThinLens, coc_filter, render

from .helpers import CATALOGUE, method_id


# no shrinking: on a failure the first counterexample is reported at once (shrinking a filter
# call takes minutes)
SETTINGS = settings(
    max_examples=8,
    deadline=None,
    derandomize=True,
    database=None,
    phases=[Phase.explicit, Phase.generate],
)

# The reference method. The other methods of the catalogue (hard, supersample, jitter, aperture,
# layered, auto, occlusion) have their own property tests in tests/test_methods.py; running all
# of these properties over them is left open (not yet verified here, and each adds ~1 min of
# compiles).
METHODS = (CATALOGUE["soft"],)
# Methods whose weights depend on a random key per output pixel (a different noise pattern at
# each position): not translation-, flip- or transpose-equivariant, linear for a fixed key.
RANDOM = tuple(m for m in METHODS if getattr(m, "key", None) is not None)
DETERMINISTIC = tuple(m for m in METHODS if m not in RANDOM)

# float64 round-off: each output is a sum of <= ~100 terms of size <= 1 (weights <= 1, pixel
# values <= 10 after scaling): a few hundred ulps of 1 is < 1e-12.
TOL = 1e-12


def _filter(method, image, radius, max_radius=3.0):
    out = coc_filter(image, radius, method=method, max_radius=max_radius)
    return np.asarray(out)


H, W = 7, 8
values = arrays(np.float64, (H, W, 2), elements=st.floats(0, 1, allow_subnormal=False))
radii = arrays(np.float64, (H, W), elements=st.floats(0, 3))


@pytest.mark.parametrize("method", METHODS, ids=method_id)
@SETTINGS
@given(x=values, y=values, r=radii, a=st.floats(-3, 3), b=st.floats(-3, 3))
def test_linear_in_image(method, x, y, r, a, b):
    lhs = _filter(method, a * x + b * y, r)
    rhs = a * _filter(method, x, r) + b * _filter(method, y, r)
    np.testing.assert_allclose(lhs, rhs, rtol=0, atol=10 * TOL)  # |a x + b y| <= 6: 10 TOL


# Energy: methods documented as conserving it exactly (weights normalised per source pixel).
ENERGY_EXACT = METHODS  # soft: weights normalised per source pixel, exact to round-off


@pytest.mark.parametrize("method", ENERGY_EXACT, ids=method_id)
@SETTINGS
@given(x=values, r=arrays(np.float64, (H + 6, W + 6), elements=st.floats(0, 3)))
def test_energy_conserved_in_interior(method, x, r):
    """Sources at least ceil(max_radius) = 3 px from the border keep all their light."""
    image = np.zeros((H + 6, W + 6, 2))
    image[3:-3, 3:-3] = x
    out = _filter(method, image, r)
    # atol: an all-zero draw sums to 0 on both sides
    np.testing.assert_allclose(out.sum((0, 1)), image.sum((0, 1)), rtol=TOL, atol=TOL)


SYMMETRIES = {
    "flip_rows": lambda a: a[::-1],
    "flip_cols": lambda a: a[:, ::-1],
    "transpose": lambda a: np.swapaxes(a, 0, 1),
}


@pytest.mark.parametrize("sym", list(SYMMETRIES))
@pytest.mark.parametrize("method", DETERMINISTIC, ids=method_id)
@SETTINGS
@given(x=values, r=radii)
def test_flip_and_transpose_equivariant(method, sym, x, r):
    s = SYMMETRIES[sym]
    lhs = _filter(method, s(x), s(r))
    rhs = s(_filter(method, x, r))
    np.testing.assert_allclose(lhs, rhs, rtol=0, atol=TOL)


@pytest.mark.parametrize("method", DETERMINISTIC, ids=method_id)
@SETTINGS
@given(x=values, r=radii, dy=st.integers(-3, 3), dx=st.integers(-3, 3))
def test_translation_equivariant_away_from_borders(method, x, r, dy, dx):
    """Content placed with a margin of ceil(max_radius) + 3 px: shifting it shifts the output."""
    m = 6
    image = np.zeros((H + 2 * m, W + 2 * m, 2))
    radius = np.zeros((H + 2 * m, W + 2 * m))
    image[m:-m, m:-m], radius[m:-m, m:-m] = x, r
    shift = lambda a: np.roll(a, (dy, dx), axis=(0, 1))  # the rolled-out part is all zeros
    np.testing.assert_allclose(
        _filter(method, shift(image), shift(radius)),
        shift(_filter(method, image, radius)),
        rtol=0,
        atol=TOL,
    )


# Blur grows with defocus: a point's spread (second moment about it) grows with |1/d - 1/d_f|.
LENS = ThinLens(0.05, 2.0, 3.0, 2e-5)  # K = f^2 / (2 N (d_f - f) p) = 10.6 px
MAXR = 6.0
SIZE = 2 * 6 + 5


def _spread(method, depth):
    image = np.zeros((SIZE, SIZE))
    c = SIZE // 2
    image[c, c] = 1.0
    out = np.asarray(
        render(
            image,
            np.full((SIZE, SIZE), depth),
            LENS,
            method=method,
            max_radius=MAXR,
        )
    )
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] - c
    return float(np.sum(out * (yy**2 + xx**2)) / np.sum(out))


# |1 - d_f/d| <= 0.5 keeps K |1 - d_f/d| <= 5.3 px under MAXR: inverse depths 1/6 .. 1/2 per metre
inv_depth = st.floats(1 / 6, 1 / 2)


@pytest.mark.parametrize("method", METHODS, ids=method_id)
@SETTINGS
@given(u=inv_depth, v=inv_depth)
def test_blur_grows_with_defocus(method, u, v):
    d_f = float(LENS.focus_distance)
    (lo, hi) = sorted((u, v), key=lambda w: abs(w - 1 / d_f))
    # the spread is a non-decreasing function of the defocus |1/d - 1/d_f| (equal inside the
    # r <= 1/2 dead zone); 1e-12: round-off of the moment sums
    assert _spread(method, 1 / lo) <= _spread(method, 1 / hi) + 1e-12


def test_spread_matches_the_disc():
    """A sanity anchor for the property above: the soft filter's spread of a point is that of a
    uniform disc (r^2 / 2) plus a pixel's own (1/6), within the pixelation error."""
    for depth in (1 / 0.2, 1 / 0.45):
        r = float(LENS.blur_scale) * abs(1 - 3.0 * 1 / depth)
        spread = _spread(CATALOGUE["soft"], depth)
        # exact areas: the only error is the pixel-centre quantisation of |p|^2, O(1) px^2 at most
        assert abs(spread - (r * r / 2 + 1 / 6)) < 0.5 * max(1.0, r)
