import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxdof import circle_pixel_overlap
from jaxdof._overlap import _asin

from .helpers import fits_module, overlap_by_integration


textbook_overlap = fits_module("_textbook").textbook_overlap  # the study's comparison


EDGE_CASES = [
    (0.0, 0.0, 0.0),  # r = 0
    (0.0, 0.0, 0.3),  # disc inside its square
    (0.0, 0.0, 0.5),  # touching all four edges
    (0.0, 0.0, math.sqrt(0.5)),  # through the four corners: square inside
    (0.0, 0.0, 3.0),  # square deep inside
    (5.0, 0.0, 2.0),  # outside
    (2.5, 0.0, 2.0),  # square touching the disc at one point
    (1.0, 0.0, 0.5),  # disc touching the square's edge
    (0.3, -0.2, 0.25),  # r < 0.5 off centre, crossing an edge
    (0.7, 0.6, 1.0),  # corner region
    (-3.0, 4.0, 5.0),  # circle through the square's centre
    (0.5, 0.5, 1e-3),  # tiny disc on a corner
]


@pytest.mark.parametrize("dx,dy,r", EDGE_CASES)
def test_edge_cases_against_integration(dx, dy, r):
    expected = overlap_by_integration(dx, dy, r)
    assert float(circle_pixel_overlap(dx, dy, r)) == pytest.approx(expected, abs=1e-13)


def test_random_against_integration():
    rng = np.random.default_rng(0)
    r = rng.uniform(0, 6, 300)
    ang = rng.uniform(0, 2 * np.pi, 300)
    rho = r + rng.uniform(-1.5, 1.5, 300)  # concentrate on squares the circle crosses
    dx, dy = rho * np.cos(ang), rho * np.sin(ang)
    got = np.asarray(circle_pixel_overlap(dx, dy, r))
    expected = np.array([overlap_by_integration(*args) for args in zip(dx, dy, r)])
    # 30-digit quadrature; the analytic formula is exact to a few float64 rounding units.
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-13)


def test_partition_of_the_disc():
    """Summed over every pixel of the plane, the areas add up to pi r^2."""
    o = np.arange(-30, 31, dtype=np.float64)
    yy, xx = np.meshgrid(o, o, indexing="ij")
    for r in (0.0, 0.2, 0.5, 0.9, 3.3, 17.0, 29.4):
        for cx, cy in ((0.0, 0.0), (0.3, -0.45)):
            total = float(jnp.sum(circle_pixel_overlap(xx - cx, yy - cy, r)))
            assert total == pytest.approx(math.pi * r * r, abs=1e-12 * max(1.0, r * r))


def test_supersampled_coverage_converges():
    """n x n sub-pixel sampling converges to the analytic area, error O(1/n)."""
    dx, dy, r = 1.3, 0.6, 1.7
    exact = float(circle_pixel_overlap(dx, dy, r))
    errs = []
    for n in (4, 16, 64, 256):
        s = (np.arange(n) + 0.5) / n - 0.5
        x, y = np.meshgrid(dx + s, dy + s)
        errs.append(abs(np.mean(x * x + y * y <= r * r) - exact))
    assert errs[-1] < 2e-3
    assert errs[-1] < errs[0] / 10


@pytest.mark.parametrize("r0", [0.5, math.sqrt(0.5), 1.0])
def test_continuous_across_regime_changes(r0):
    eps = 1e-9
    for dx, dy in ((0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.5, 0.5)):
        lo = float(circle_pixel_overlap(dx, dy, r0 - eps))
        hi = float(circle_pixel_overlap(dx, dy, r0 + eps))
        assert abs(hi - lo) < 1e-8


def _exact64(dx, dy, r):
    return np.asarray(
        circle_pixel_overlap(dx.astype(np.float64), dy.astype(np.float64), r.astype(np.float64))
    )


@pytest.mark.parametrize(
    "r", [0.0, 1e-8, 1e-3, 0.3, 0.5, 0.7071, 1.0, 3.0, 10.0, 100.0, 333.3, 1000.0]
)
def test_float32_accuracy_every_radius(r):
    """float32 error <= 2e-6 max(1, r) of a pixel (and relative to pi r^2 for tiny r)."""
    rng = np.random.default_rng(int(r * 1000) % 2**31)
    n = 4000
    ang = rng.uniform(0, 2 * np.pi, n)
    rho = r + rng.uniform(-1.2, 1.2, n)
    dx = (rho * np.cos(ang)).astype(np.float32)
    dy = (rho * np.sin(ang)).astype(np.float32)
    r32 = np.full(n, r, np.float32)
    got = np.asarray(jax.jit(circle_pixel_overlap)(dx, dy, r32))
    assert got.dtype == np.float32
    err = np.abs(got.astype(np.float64) - _exact64(dx, dy, r32))
    tol = 2e-6 * max(1.0, r) if r >= 1e-3 else 2e-6 * math.pi * r * r
    assert err.max() <= tol


def test_textbook_formula_is_what_we_avoid():
    """Document the measured failure of inclusion-exclusion in float32 (motivates the local form)."""
    r = np.float32(1000.0)
    dx, dy = np.float32(707.0), np.float32(707.0)  # a square the circle crosses
    exact = float(_exact64(np.array([dx]), np.array([dy]), np.array([r]))[0])
    ours = float(circle_pixel_overlap(dx, dy, r))
    naive = float(jax.jit(textbook_overlap)(dx, dy, r))
    assert abs(ours - exact) < 2e-6 * 1000
    assert abs(naive - exact) > 1e-2  # digits lost to r^2-sized cancellation


GRAD_POINTS = [
    (0.2, -0.1, 0.0),  # r = 0 exactly
    (0.2, -0.1, 1e-7),
    (0.0, 0.0, 0.5),  # tangent to all four edges: finite, but not smooth (checked below)
    (0.0, 0.0, math.sqrt(0.5) + 1e-3),
    (1.3, 0.6, 1.7),
    (0.9, -2.2, 2.5),
    (30.2, 40.1, 50.3),
]


@pytest.mark.parametrize("point", GRAD_POINTS)
def test_gradients_finite_and_checked(point):
    dx, dy, r = (jnp.asarray(p, jnp.float64) for p in point)
    grads = jax.grad(circle_pixel_overlap, argnums=(0, 1, 2))(dx, dy, r)
    assert all(np.isfinite(g) for g in grads)
    if point[2] > 1e-6 and point[2] != 0.5:
        # Smooth away from tangencies: forward and reverse, first order, against central
        # differences (check_grads' default float64 tolerance is 1e-5 relative).
        check_grads(circle_pixel_overlap, (dx, dy, r), order=1, modes=("fwd", "rev"), eps=1e-6)


def test_gradient_matches_geometry():
    # dA/dr of a disc inside its square is its circumference; square inside the disc: 0.
    assert float(jax.grad(circle_pixel_overlap, argnums=2)(0.0, 0.0, 0.3)) == pytest.approx(
        2 * math.pi * 0.3
    )
    assert float(jax.grad(circle_pixel_overlap, argnums=2)(0.0, 0.0, 3.0)) == 0.0
    # At r = 1/2 the inscribed circle lies wholly in the square: dA/dr = pi (one-sided limits agree).
    assert float(jax.grad(circle_pixel_overlap, argnums=2)(0.0, 0.0, 0.5)) == pytest.approx(math.pi)
    # A half-plane-like cut: moving the square right by dx removes a full edge of length 1.
    assert float(jax.grad(circle_pixel_overlap, argnums=0)(99.5, 0.0, 100.0)) == pytest.approx(
        -1.0, abs=1e-3
    )


def test_series_asin():
    s = np.linspace(0, math.sqrt(0.5), 1001)
    np.testing.assert_allclose(np.asarray(_asin(jnp.asarray(s))), np.arcsin(s), rtol=0, atol=4e-16)


def test_negative_radius_rejected():
    with pytest.raises(ValueError, match="radius"):
        circle_pixel_overlap(0.0, 0.0, -1.0)
