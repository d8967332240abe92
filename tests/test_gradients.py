"""Gradients of every public differentiable function against finite differences, float64.

`jax.test_util.check_grads` checks forward and reverse mode along a random direction in all
arguments at once, so the arguments are passed in units that make them O(1) (pixel pitch in
micrometres or 10 um, the f-number in units of 1e4 near the pinhole limit): one finite-difference
step then suits every argument.

Tolerances. Central differences with step `eps` on O(1) arguments have a truncation error
`eps^2 |f'''| / 6` and a round-off error `~1e-16 |f| / eps`; with `eps = 1e-6` both are below
1e-9 relative for the smooth functions here, so we assert the issue's target, 1e-6 relative
(`RTOL`), with an absolute floor `ATOL` for outputs whose derivative is ~0. Where a function is
not smooth (the kink of |.| at the focus plane, the coverage regime changes at r = 1/2 and
sqrt(2)/2, r = 0 at the edge of the domain) we check one-sided difference quotients instead, and
that they converge to the derivative at the rate the local expansion predicts.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxdof import (
    Aperture,
    ThinLens,
    circle_pixel_overlap,
    coc_filter,
    coc_radius,
    linearize_depth,
    render,
    signed_coc_radius,
)

from .helpers import METHODS, RADIUS_METHODS, method_id


# The target: float64 gradients agree with finite differences to 1e-6 relative.
RTOL = 1e-6
# Absolute floor for derivatives that are ~0: float64 round-off of a central difference of an
# O(1..100) output with eps = 1e-6 is ~1e-16 * 100 / 1e-6 = 1e-8.
ATOL = 1e-8


def check(f, args, order=1, eps=1e-6, atol=ATOL, rtol=RTOL, jit=False):
    args = tuple(jnp.asarray(a, jnp.float64) for a in args)
    if jit:  # pays off for the filters (one scan); scalar functions run faster op by op
        f = jax.jit(f)
    check_grads(f, args, order=order, modes=("fwd", "rev"), eps=eps, atol=atol, rtol=rtol)


def jvp_along(f, args, tangent):
    args = tuple(jnp.asarray(a, jnp.float64) for a in args)
    tangent = tuple(jnp.asarray(t, jnp.float64) for t in tangent)
    return np.asarray(jax.jvp(f, args, tangent)[1])


def one_sided_errors(f, args, tangent, side, hs=(1e-3, 1e-4, 1e-5)):
    """|(f(x + s h v) - f(x)) / (s h) - jvp(v)| (max over outputs) for each step `h`, `s = side`.

    Also checks the reverse mode agrees with the forward mode (vjp against jvp).
    """
    args = tuple(jnp.asarray(a, jnp.float64) for a in args)
    tangent = tuple(jnp.asarray(t, jnp.float64) for t in tangent)
    y, t_out = jax.jvp(f, args, tangent)
    y, vjp = jax.vjp(f, *args)
    ct = jnp.asarray(np.random.default_rng(0).normal(size=np.shape(y)))
    ip_rev = sum(float(jnp.vdot(g, t)) for g, t in zip(vjp(ct), tangent))
    # forward and reverse mode are the same linear map: agreement to float64 round-off
    assert ip_rev == pytest.approx(float(jnp.vdot(ct, t_out)), rel=1e-12, abs=1e-12)
    errs = []
    for h in hs:
        moved = tuple(a + side * h * t for a, t in zip(args, tangent))
        quotient = (np.asarray(f(*moved)) - np.asarray(y)) / (side * h)
        errs.append(float(np.max(np.abs(quotient - np.asarray(t_out)))))
    return np.asarray(errs)


def assert_converges(errs, rate, hs=(1e-3, 1e-4, 1e-5)):
    """The one-sided error falls like `h^rate` (first order at a C1 kink, 1/2 at a tangency).

    Over the two decades of `hs` the leading term falls by `100^rate`; the factor 3 leaves room
    for the next-order term, and 1e-9 for the round-off of a one-sided quotient at h = 1e-5
    (~1e-16 |f| / h with |f| <= 100).
    """
    assert errs[-1] <= 3 * errs[0] * (hs[-1] / hs[0]) ** rate + 1e-9, errs


# ---------------------------------------------------------------------------------------------
# Optics: coc_radius, signed_coc_radius, linearize_depth


def _coc(fn, n_unit=1.0):
    """`fn(depth, lens)` as a function of (depth m, f m, N / n_unit, d_f m, pitch um)."""

    def g(depth, f, n, d_f, pitch_um):
        return fn(depth, ThinLens(f, n * n_unit, d_f, pitch_um * 1e-6))

    return g


F, N, DF, P_UM = 0.05, 2.0, 3.0, 6.0

LENS_POINTS = {
    # name: (depth, f, N (in units of n_unit), d_f, pitch_um, n_unit, eps)
    "front": (1.7, F, N, DF, P_UM, 1.0, 1e-6),
    "behind": (5.0, F, N, DF, P_UM, 1.0, 1e-6),
    "far": (1e6, F, N, DF, P_UM, 1.0, 1e-6),
    # depth 0.1% beyond the focal length (gap 5e-5 m): eps well below the gap, so every evaluation
    # stays valid; truncation (eps / gap)^2 ~ 4e-8, round-off 1e-16 / eps ~ 1e-8 relative.
    "depth_near_focal_length": (F * 1.001, F, N, DF, P_UM, 1.0, 1e-8),
    # focus distance 0.1% beyond the focal length: blur scale K ~ 2e6 px, same eps argument.
    "focus_near_focal_length": (1.7, F, N, F * 1.001, P_UM, 1.0, 1e-8),
    # f-number 1e4 (nearly a pinhole), passed in units of 1e4 so that eps suits it.
    "pinhole": (1.7, F, 1.0, DF, P_UM, 1e4, 1e-6),
}


@pytest.mark.parametrize("fn", [coc_radius, signed_coc_radius], ids=["abs", "signed"])
@pytest.mark.parametrize("point", list(LENS_POINTS))
def test_coc_radius_every_input(fn, point):
    depth, f, n, d_f, p, n_unit, eps = LENS_POINTS[point]
    args = (depth, f, n, d_f, p)
    check_coc(fn, args, n_unit, eps)


def check_coc(fn, args, n_unit=1.0, eps=1e-6):
    """First and second order. The order-2 check compares d/dx (f grad f) (check_grads builds it
    from `vjp(f)(x)(f(x))`), of size |grad f|^2 + |f| |H|: the absolute floor scales with it."""
    x = tuple(jnp.asarray(a) for a in args)
    g = _coc(fn, n_unit)
    val = float(g(*x))
    jac = np.asarray(jax.jacfwd(g, argnums=tuple(range(5)))(*x))
    hess = np.asarray(jax.hessian(g, argnums=tuple(range(5)))(*x))
    assert np.isfinite(val) and np.all(np.isfinite(jac)) and np.all(np.isfinite(hess))
    scale = max(1.0, np.abs(jac).max() ** 2 + abs(val) * np.abs(hess).max())
    check(g, args, order=2, eps=eps, atol=ATOL * scale)


def test_coc_radius_at_focus_plane():
    """At d = d_f, |.| has a kink: the derivative is the subgradient 0 (documented); one-sided
    derivatives are +-(the signed radius's derivative), which is smooth there."""
    args = (DF, F, N, DF, P_UM)
    g = jax.grad(_coc(coc_radius), argnums=tuple(range(5)))(*(jnp.asarray(a) for a in args))
    assert all(float(x) == 0.0 for x in g)
    check_coc(signed_coc_radius, args)  # the signed radius is smooth at the focus
    v = (1.0, 0.3, -0.7, 0.5, 0.2)  # a direction in every input
    s_dot = float(jvp_along(_coc(signed_coc_radius), args, v))
    assert s_dot != 0.0
    for side in (1, -1):
        h = 1e-7
        moved = tuple(jnp.asarray(a + side * h * t) for a, t in zip(args, v))
        quotient = float(_coc(coc_radius)(*moved)) / (side * h)  # r(focus) = 0 exactly
        # |s(x + h v)| / h = |s_dot| + O(h): the one-sided derivatives are +-|s_dot|
        assert quotient == pytest.approx(side * abs(s_dot), rel=1e-5)


def test_coc_radius_depth_at_infinity():
    """d = inf is valid: r = K, dr/dd = 0 (the limit of K d_f / d^2), and every lens gradient is
    that of K; the depth cannot be perturbed by finite differences there, the lens can."""
    d = jnp.asarray(jnp.inf)
    g = jax.grad(coc_radius)(d, ThinLens(F, N, DF, P_UM * 1e-6))
    assert float(g) == 0.0

    def at_inf(f, n, d_f, pitch_um):
        return coc_radius(d, ThinLens(f, n, d_f, pitch_um * 1e-6))

    check(at_inf, (F, N, DF, P_UM), order=2)
    r = at_inf(*(jnp.asarray(a) for a in (F, N, DF, P_UM)))
    assert float(r) == pytest.approx(F * F / (2 * N * (DF - F)) / (P_UM * 1e-6), rel=1e-14)


@pytest.mark.parametrize("z", [0.0, 0.37, 1.0])
def test_linearize_depth(z):
    # far in units of 100 m keeps the arguments O(1). Near z = 1 the denominator
    # far - z (far - near) -> near = 0.1 varies ~1e3 times faster than z: eps = 1e-8 keeps the
    # truncation error (1e3 eps)^2 ~ 1e-10 relative; round-off 1e-16 / 1e-8 * 1e3 ~ 1e-5 of an
    # O(1) output is covered by the derivative's own size (~1e5 at z = 1).
    check(lambda z, n, f100: linearize_depth(z, n, f100 * 100), (z, 0.1, 1.0), order=2, eps=1e-8)


# ---------------------------------------------------------------------------------------------
# circle_pixel_overlap

SMOOTH_OVERLAP = [
    (1.3, 0.6, 1.7),
    (0.9, -2.2, 2.5),
    (30.2, 40.1, 50.3),  # large radius: the circle crosses the square
    (0.1, -0.05, 0.3),  # disc inside its square
]
# delta = 1e-3 from a regime change: smooth, but the area's k-th derivative grows like
# delta^(3/2 - k) (circular segments of height ~delta), so the order-2 check's central difference
# of f' has a truncation error ~ eps^2 delta^(-5/2) ~ 3e-5 eps^2 / 1e-12: eps = 1e-7 keeps it
# ~3e-7 absolute on second derivatives of O(10..100); round-off 1e-16 / 1e-7 ~ 1e-9.
NEAR_REGIME_CHANGE = [
    (0.0, 0.0, 0.5 + 1e-3),  # just past the inscribed circle (smooth on this side)
    (0.0, 0.0, math.sqrt(0.5) - 1e-3),  # just before the circumscribed circle
    (1.5 - 1e-3, 0.2, 1.0),  # an edge of a neighbouring pixel about to touch the disc
]


def test_overlap_smooth_points():
    # all points in one call: the function is elementwise, and the JVP check compares every
    # element (the VJP check their weighted sum)
    check(circle_pixel_overlap, tuple(np.array(SMOOTH_OVERLAP).T), order=2)
    check(circle_pixel_overlap, tuple(np.array(NEAR_REGIME_CHANGE).T), order=2, eps=1e-7)


def test_overlap_tiny_radius():
    # r = 1e-7: eps = 1e-9 keeps r > 0; A = pi r^2 ~ 3e-14, dA/dr = 2 pi r, d2A/dr2 = 2 pi;
    # the absolute floor is scaled to these tiny values (round-off 1e-16 * 3e-14 / 1e-9 ~ 1e-21).
    check(circle_pixel_overlap, (0.2, -0.1, 1e-7), order=2, eps=1e-9, atol=1e-15)


def test_overlap_at_zero_radius():
    """r = 0 is the edge of the domain: one-sided (r >= 0) derivatives. A = pi r^2 inside a square,
    so dA/dr = 0 and the one-sided quotient is pi h, first order."""
    args = (0.2, -0.1, 0.0)
    g = jax.grad(circle_pixel_overlap, argnums=(0, 1, 2))(*(jnp.asarray(a) for a in args))
    assert all(float(x) == 0.0 for x in g)
    errs = one_sided_errors(circle_pixel_overlap, args, (0.0, 0.0, 1.0), side=1)
    np.testing.assert_allclose(errs, math.pi * np.array([1e-3, 1e-4, 1e-5]), rtol=1e-9)
    # a disc at a corner of its square: still zero derivative at r = 0, finite everywhere
    g = jax.grad(circle_pixel_overlap, argnums=(0, 1, 2))(
        *(jnp.asarray(a) for a in (0.5, 0.5, 0.0))
    )
    assert all(float(x) == 0.0 for x in g)


def test_overlap_at_inscribed_circle():
    """r = 1/2 centred: the disc touches the four edges. dA/dr = 2 pi r = pi from both sides, but
    for r > 1/2 the disc loses four circular segments of height h = r - 1/2, ~ (4/3) h^(3/2) each,
    so the right quotient converges like sqrt(h) (the left one, inside the square, like h)."""
    args, v = (0.0, 0.0, 0.5), (0.0, 0.0, 1.0)
    assert float(jvp_along(circle_pixel_overlap, args, v)) == pytest.approx(math.pi, rel=1e-14)
    right = one_sided_errors(circle_pixel_overlap, args, v, side=1)
    # leading term (16/3) sqrt(h), next order ~h: within 2% at h <= 1e-3
    np.testing.assert_allclose(right, 16 / 3 * np.sqrt([1e-3, 1e-4, 1e-5]), rtol=2e-2)
    left = one_sided_errors(circle_pixel_overlap, args, v, side=-1)
    np.testing.assert_allclose(left, math.pi * np.array([1e-3, 1e-4, 1e-5]), rtol=1e-6)  # pi r^2
    # moving the square: d/d(dx) = 0 by symmetry, and one-sided first-order convergence
    for side in (1, -1):
        assert_converges(one_sided_errors(circle_pixel_overlap, args, (1.0, 0.3, 0.0), side), 0.5)


def test_overlap_at_circumscribed_circle():
    """r = sqrt(2)/2 centred: the circle passes through the corners. Beyond it A = 1 (dA/dr = 0);
    before it the four corners outside the disc are right triangles of height delta = sqrt(2)/2 - r,
    area delta^2 each: A = 1 - 4 delta^2, so dA/dr -> 0 and the left quotient is 4h."""
    args, v = (0.0, 0.0, math.sqrt(0.5)), (0.0, 0.0, 1.0)
    assert float(jvp_along(circle_pixel_overlap, args, v)) == 0.0
    right = one_sided_errors(circle_pixel_overlap, args, v, side=1)
    assert np.all(right == 0.0)
    left = one_sided_errors(circle_pixel_overlap, args, v, side=-1)
    # 4h up to the curvature of the arc across the corner: O(h^2) relative
    np.testing.assert_allclose(left, 4 * np.array([1e-3, 1e-4, 1e-5]), rtol=1e-2)


# ---------------------------------------------------------------------------------------------
# coc_filter and render, every method
#
# Each check_grads call on a filter compiles a scan in several transformed forms, which dominates
# the run time, so one radius map mixes the regimes that are smooth (random radii away from the
# regime changes, radii far above max_radius, a constant block) and is checked in one call per
# method; the non-smooth points get their own one-sided checks.

# The catalogue's methods (tests/helpers.py). Those documented as having no true derivative in the
# radius (`differentiable_in_radius = False`: piecewise constant output, or a gradient shared over
# a level) are checked in the image only.


MAXR = 2.5


def _mixed_scene(h=4, w=5, c=2, seed=0):
    """Random radii in [0.6, 2.4] (away from 1/2 and from max_radius, where the output is not
    smooth), a clamped block far above max_radius and a constant block."""
    rng = np.random.default_rng(seed)
    image = rng.uniform(size=(h, w, c))
    radius = rng.uniform(0.6, 2.4, (h, w))
    radius[0, :2] = 50.0  # clamped to MAXR: derivative 0, locally constant
    radius[-1, -2:] = 1.37  # a constant patch
    return image, radius


@pytest.mark.parametrize("method", METHODS, ids=method_id)
def test_filter_every_method(method):
    """Image and (where documented differentiable) radius, forward and reverse. Linear in the
    image, so order 2 adds nothing there; order 2 in the radius for the soft filter below."""
    image, radius = _mixed_scene()
    if method.differentiable_in_radius:
        f = lambda i, r: coc_filter(i, r, method=method, max_radius=MAXR)
        check(f, (image, radius), jit=True)
        g = jax.grad(lambda r: jnp.sum(f(jnp.asarray(image), r) ** 2))(jnp.asarray(radius))
        assert np.all(np.asarray(g)[0, :2] == 0.0)  # the clamped radii
    else:
        check(
            lambda i: coc_filter(i, radius, method=method, max_radius=MAXR),
            (image,),
            jit=True,
        )


def test_filter_soft_second_order():
    image, radius = _mixed_scene(2, 3, c=1, seed=1)  # order 2 compiles many transforms: small
    check(lambda i, r: coc_filter(i, r, max_radius=MAXR), (image, radius), order=2, jit=True)


def test_filter_dead_zone_and_regime_changes():
    """The soft filter is exactly the identity for r <= 1/2 with derivative 0 (r = 0, 1e-7, 1/2).
    Right of 1/2 the weights leave the identity like h^(3/2) (the circular segments above), so
    the right quotient converges like sqrt(h); at sqrt(2)/2 every tap's area has a continuous
    derivative and a jump in the second (the circle crosses pixel corners): first order."""
    rng = np.random.default_rng(3)
    image = jnp.asarray(rng.uniform(size=(3, 4)))
    f = jax.jit(lambda r: coc_filter(image, jnp.full((3, 4), r), max_radius=2.0))
    for r in (0.0, 1e-7, 0.5):
        assert np.array_equal(np.asarray(f(jnp.asarray(r))), np.asarray(image))
        assert np.all(jvp_along(f, (r,), (1.0,)) == 0.0)
    # r = 0 and 1e-7: only r >= 0 exists, and there the map is constant: exact zero quotients
    assert np.all(one_sided_errors(f, (0.0,), (1.0,), side=1) == 0.0)
    assert np.all(one_sided_errors(f, (1e-7,), (1.0,), side=1, hs=(1e-8, 1e-9)) == 0.0)
    assert np.all(one_sided_errors(f, (0.5,), (1.0,), side=-1) == 0.0)
    assert_converges(one_sided_errors(f, (0.5,), (1.0,), side=1), rate=0.5)
    for side in (1, -1):
        assert_converges(one_sided_errors(f, (math.sqrt(0.5),), (1.0,), side), rate=1.0)


# ----- render: image, depth and every lens field (pitch in units of 10 um: radii of a few px)


def _render(method="soft", max_radius=3.0, inf_mask=None, **options):
    """render as a function of (image, depth, f, N, d_f, pitch / 10 um); `inf_mask` pins those
    depths at infinity (they cannot be perturbed by finite differences)."""

    def f(image, depth, fl, n, d_f, pitch):
        if inf_mask is not None:
            depth = jnp.where(inf_mask, jnp.inf, depth)
        lens = ThinLens(fl, n, d_f, pitch * 1e-5)
        return render(image, depth, lens, method=method, max_radius=max_radius, **options)

    return f


LENS_ARGS = (0.05, 2.0, 3.0, 8.0)  # K = f^2 / (2N (d_f - f)) / p = 2.65 px


def _extreme_depths(h=4, w=5, seed=0):
    """Depths 1.5..2 m and 4.5..6 m (radii 0.9 .. 2.6 px, away from 1/2 and max_radius = 3), one
    row at infinity, pixels exactly at the focus plane (radius 0: the dead zone) and just beyond
    the focal length (radius ~156 px, clamped)."""
    rng = np.random.default_rng(seed)
    image = rng.uniform(size=(h, w))
    depth = np.where(
        rng.uniform(size=(h, w)) < 0.5, rng.uniform(1.5, 2.0, (h, w)), rng.uniform(4.5, 6, (h, w))
    )
    inf_mask = np.zeros((h, w), bool)
    inf_mask[0] = True
    depth[0] = 1.0  # placeholder, replaced by inf inside the function
    depth[1, :2] = 3.0  # the focus plane
    # 0.1% beyond the focal length: the gap 5e-5 m is 10x the largest finite-difference step
    depth[2, :2] = 0.05 * 1.001
    return image, depth, inf_mask


@pytest.mark.parametrize("method", RADIUS_METHODS, ids=method_id)
def test_render_every_input(method):
    """Image, depth and every lens field, on a scene with depths at infinity, at the focus plane
    and just beyond the focal length. (Methods without a radius derivative: the image check in
    test_filter_every_method covers them; render only composes it with the radius.)

    The focus plane is kept for the methods that are the identity for r <= 1/2 (then the kink of
    |.| is invisible). `aperture` splats bilinearly at `q + u r`: at r = 0 every sample sits on a
    pixel centre, the kink of the bilinear hat, so its output has a kink in the depth there and
    the symmetric subgradient differs from a central difference; that pixel is moved off focus.
    """
    image, depth, inf_mask = _extreme_depths()
    aperture = isinstance(method, Aperture)
    if aperture:
        depth[1, :2] = 2.0
    f = _render(method, inf_mask=inf_mask)
    # `aperture` is piecewise linear in the radius (a kink wherever a lens sample crosses a pixel
    # centre, dozens per pixel of radius): a central difference must not straddle one. The
    # focal length moves the radii fastest (dr/df ~ 2r/f ~ 100 px/m), so eps = 1e-8 keeps every
    # radius step below ~1e-6 px; round-off 1e-16 / 1e-8 ~ 1e-8 relative still meets RTOL.
    check(f, (image, depth, *LENS_ARGS), jit=True, eps=1e-8 if aperture else 1e-6)
    args = tuple(jnp.asarray(a) for a in (image, depth, *LENS_ARGS))
    out, vjp = jax.vjp(f, *args)
    g_depth = np.asarray(vjp(jnp.ones_like(out))[1])
    assert np.all(np.isfinite(np.asarray(out))) and np.all(np.isfinite(g_depth))
    # pinned at infinity, at the focus plane (subgradient, dead zone) or clamped: exactly 0
    assert np.all(g_depth[0] == 0.0) and np.all(g_depth[2, :2] == 0.0)
    if not aperture:
        assert np.all(g_depth[1, :2] == 0.0)


def test_render_second_order_soft():
    # The 1e-6 target is for gradients; second derivatives are checked to 1e-5: with radii
    # from a continuum of depths some circle passes within delta of a pixel corner or edge, where
    # the area's fourth derivative grows like delta^(-5/2), and the central difference of the
    # first derivative (eps = 1e-6) carries eps^2 / 6 of it (measured: 2.6e-6 relative here).
    image, depth, inf_mask = _extreme_depths(3, 4, seed=1)
    f = _render(inf_mask=inf_mask)
    check(f, (image, depth, *LENS_ARGS), order=2, jit=True, rtol=1e-5)


@pytest.mark.parametrize("shape", [(1, 1), (1, 5), "constant"])
def test_render_degenerate_scenes(shape):
    rng = np.random.default_rng(2)
    if shape == "constant":
        image, depth = rng.uniform(size=(4, 5)), np.full((4, 5), 1.8)  # one depth plane
    else:
        image, depth = rng.uniform(size=shape), rng.uniform(1.5, 2.0, shape)
    check(_render(), (image, depth, *LENS_ARGS), jit=True)


def _locally_constant(f, args):
    """Derivative exactly 0 in forward and reverse mode, and f unchanged by a step along a
    random direction: the finite difference is exactly 0 too."""
    args = tuple(jnp.asarray(a) for a in args)
    t = tuple(jnp.asarray(np.random.default_rng(0).normal(size=np.shape(a))) for a in args)
    y, t_out = jax.jvp(f, args, t)
    assert np.all(np.asarray(t_out) == 0.0)
    y, vjp = jax.vjp(f, *args)
    assert all(np.all(np.asarray(g) == 0.0) for g in vjp(jnp.ones_like(y)))
    moved = tuple(a + 1e-7 * v for a, v in zip(args, t))
    assert np.array_equal(np.asarray(f(*moved)), np.asarray(y))


def test_render_lens_extremes():
    """Through the radius, locally constant lenses: f/1e4 (every radius < 1/2: the identity) and
    a focus distance just beyond the focal length (every radius ~1e4 px: clamped). The image
    enters linearly, so its gradient is checked on its own."""
    rng = np.random.default_rng(4)
    image, depth = rng.uniform(size=(4, 5)), rng.uniform(1.5, 6.0, (4, 5))
    f = jax.jit(_render())
    for lens in [(0.05, 1e4, 3.0, 8.0), (0.05, 2.0, 0.05 * 1.001, 8.0)]:
        _locally_constant(lambda d, *lens: f(jnp.asarray(image), d, *lens), (depth, *lens))
    out = f(*(jnp.asarray(a) for a in (image, depth, 0.05, 1e4, 3.0, 8.0)))
    assert np.array_equal(np.asarray(out), image)
