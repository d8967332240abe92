"""The seeds' filter family behind `coc_filter(..., method=...)`: method objects and their aliases,
a method of the user's own, limits, energy, keys, options, gradients."""

import functools
import inspect
import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxdof import (
    AbstractMethod,
    Aperture,
    Auto,
    Hard,
    Jitter,
    Layered,
    LocalOcclusion,
    Occlusion,
    Soft,
    Supersample,
    ThinLens,
    coc_filter,
    coc_radius,
    fit_lens,
    render,
    scene_treatment,
)
from jaxdof._filters import METHOD_ALIASES, as_method, layered
from jaxdof._filters.auto import choose_method, max_layers
from jaxdof._filters.common import tap_offsets, unique_with_index, window_half_width
from jaxdof._filters.layered import (
    assign_levels,
    assign_numpy,
    fft_length,
    level_radii,
    sharp_first_level,
)
from jaxdof._filters.shape import polygon_pixel_overlap, unit_halfplanes
from jaxdof._filters.tabulated import Tabulated, radius_levels, tabulated_filter
from jaxdof.internal import tuning

from .helpers import CATALOGUE, method_id


KEY = jax.random.key(0)


def _scene(h=18, w=20, rmax=5.0, seed=0, c=2):
    rng = np.random.default_rng(seed)
    return rng.uniform(size=(h, w, c)), rng.uniform(0, rmax, (h, w))


def _interior_scene(h=30, w=30, rmax=5.0, seed=1):
    """Sources only where their discs (radius <= rmax) stay inside the frame: energy is conserved."""
    rng = np.random.default_rng(seed)
    image = np.zeros((h, w, 2))
    m = math.ceil(rmax) + 2
    image[m:-m, m:-m] = rng.uniform(size=(h - 2 * m, w - 2 * m, 2))
    return image, rng.uniform(0, rmax, (h, w))


def _err(a, b):
    return float(np.abs(np.asarray(a) - np.asarray(b)).max())


# --- methods are objects; strings are aliases of the default objects ---------------------------

BUILT_IN = (Soft, Hard, Supersample, Jitter, Aperture, Layered, Occlusion, LocalOcclusion, Auto)


def test_aliases_are_the_catalogue():
    assert METHOD_ALIASES == tuple(CATALOGUE)
    assert {type(m) for m in CATALOGUE.values()} == set(BUILT_IN)


@pytest.mark.parametrize("cls", [*BUILT_IN, Tabulated, layered._LayeredLevels])
def test_every_method_is_an_equinox_module(cls):
    """Built-in methods are final `eqx.Module` subclasses of `AbstractMethod` that say whether they
    can drive a fit (a bool class variable)."""
    assert issubclass(cls, AbstractMethod) and issubclass(cls, eqx.Module)
    assert isinstance(cls.differentiable_in_radius, bool) and isinstance(cls.uses_depth, bool)
    assert cls.uses_depth == (cls in (Occlusion, LocalOcclusion))


@pytest.mark.parametrize("name", [n for n in METHOD_ALIASES if n != "jitter"])
def test_alias_gives_the_default_object(name):
    """A string is the class with its default options: the same object, the same image."""
    method = as_method(name)
    assert type(method) is type(CATALOGUE[name]) and method == type(method)()
    image, radius = _scene(7, 8, 2.5)
    np.testing.assert_array_equal(
        coc_filter(image, radius, method=name), coc_filter(image, radius, method=type(method)())
    )


def test_as_method_refuses_what_is_not_a_method():
    soft = Soft(blades=6)
    assert as_method(soft) is soft
    with pytest.raises(ValueError, match=r"jaxdof.Jitter\(key=jax.random.key\(0\)\)"):
        as_method("jitter")  # the alias of a method that needs a key says how to give one
    for bad in ("nope", "Soft"):
        with pytest.raises(ValueError, match="is not a filter method.*'soft', 'hard'"):
            as_method(bad)
    # not even a string: the test run's jaxtyping hook refuses it at the signature (TypeError);
    # without the hook, the same ValueError
    for bad in (3, Soft):
        with pytest.raises((TypeError, ValueError), match="method"):
            as_method(bad)


# --- a method of the user's own ----------------------------------------------------------------


class GaussianBlur(AbstractMethod):
    """A user's method: each source spread as a Gaussian of `sigma = r / 2` pixels, normalised over
    the window (so energy is conserved), written as a dense scatter over the window's offsets.
    Smooth in the radius, so a lens can be fitted through it."""

    differentiable_in_radius: ClassVar[bool] = True

    def spread(self, image, radius, *, max_radius, depth):
        w = math.ceil(max_radius)
        h, wd, _ = image.shape
        o = np.arange(-w, w + 1)
        offsets = np.stack(np.meshgrid(o, o, indexing="ij"), -1).reshape(-1, 2)
        sigma = jnp.maximum(radius, 1e-3) / 2  # r = 0 would be a delta: keep sigma > 0
        d2 = jnp.asarray((offsets**2).sum(-1), radius.dtype)
        weights = jax.nn.softmax(-d2[:, None, None] / (2 * sigma * sigma)[None], axis=0)
        padded = jnp.pad(image[None] * weights[..., None], ((0, 0), (w, w), (w, w), (0, 0)))
        out = jnp.zeros_like(image)
        for k, (oy, ox) in enumerate(offsets):  # source q lands on q + o
            out = out + padded[k, w - oy : w - oy + h, w - ox : w - ox + wd]
        return out


def _gaussian_reference(image, radius, max_radius):
    """The same scatter written source by source in numpy."""
    h, w, _ = image.shape
    half = math.ceil(max_radius)
    o = np.arange(-half, half + 1)
    oy, ox = np.meshgrid(o, o, indexing="ij")
    out = np.zeros_like(image)
    for y, x in np.ndindex(h, w):
        sigma = max(min(radius[y, x], max_radius), 1e-3) / 2
        k = np.exp(-(oy**2 + ox**2) / (2 * sigma**2))
        k /= k.sum()
        for dy, dx in zip(oy.ravel(), ox.ravel()):
            if 0 <= y + dy < h and 0 <= x + dx < w:
                out[y + dy, x + dx] += image[y, x] * k[dy + half, dx + half]
    return out


def test_user_method_runs_through_coc_filter_render_jit_and_grad():
    rng = np.random.default_rng(8)
    image = rng.uniform(size=(7, 9, 2))
    depth = rng.uniform(1.5, 5.0, (7, 9))
    pitch = 0.05 / 800  # blur scale 4.1 px: circles of up to 2.7 px at these depths
    lens = ThinLens(0.05, 2.0, 2.5, pitch)
    radius = np.asarray(coc_radius(depth, lens))
    method = GaussianBlur()
    assert as_method(method) is method
    out = coc_filter(image, radius, method=method, max_radius=3.0)
    # the numpy reference sums the same terms in another order: float64 rounding
    np.testing.assert_allclose(out, _gaussian_reference(image, radius, 3.0), rtol=0, atol=1e-13)
    np.testing.assert_allclose(
        render(image, depth, lens, method=method, max_radius=3.0), out, rtol=0, atol=1e-14
    )
    jitted = jax.jit(lambda i, r: coc_filter(i, r, method=method, max_radius=3.0))(image, radius)
    np.testing.assert_allclose(jitted, out, rtol=0, atol=1e-14)  # XLA may fuse it otherwise

    def loss(f_number):
        lens = ThinLens(0.05, f_number, 2.5, pitch)
        return jnp.sum(render(image, depth, lens, method=method, max_radius=3.0) ** 2)

    # smooth in the f-number (radii well inside the 3 px window): central differences with step
    # 1e-6 in float64 are accurate to ~1e-10 relative; 1e-6 is ample
    check_grads(jax.jit(loss), (2.0,), order=1, modes=("fwd", "rev"), eps=1e-6, rtol=1e-6)
    # A user's method drives a fit like a built-in one: the photo made through it, a start 20 %
    # off in N and focus, fitted back through the same method. `border=False`: the photo is made
    # by this very model (zeros outside the frame on both sides), and the 7 x 9 frame's border
    # band of 3 px would leave 3 of its 63 pixels.
    photo = render(image, depth, lens, method=method, max_radius=3.0)
    start = ThinLens(0.05, 2.4, 2.0, pitch)
    fit = fit_lens(
        image,
        depth,
        photo,
        start,
        method=method,
        max_radius=3.0,
        starts=1,
        border=False,
        footprint=False,
    )
    assert bool(fit.success), fit.message
    # noise-free, float64: the solver's tolerance (1e-8 in log coordinates) bounds the error
    np.testing.assert_allclose(float(fit.lens.f_number), 2.0, rtol=1e-6)
    np.testing.assert_allclose(float(fit.lens.focus_distance), 2.5, rtol=1e-6)


# --- limits: the analytic overlap is the n -> infinity limit of supersampling and jitter ---------


def test_supersample_converges_to_soft():
    image, radius = _scene()
    soft = coc_filter(image, radius)
    errs = [
        _err(coc_filter(image, radius, method=Supersample(samples=n)), soft) for n in (2, 4, 8, 32)
    ]
    assert all(b < a for a, b in zip(errs, errs[1:])), errs
    # midpoint-rule coverage error is O(1/n) per crossed pixel: 16x more samples per axis should
    # cut the worst error by well over 4x (observed ~20x); 1e-2 at n = 32 is 3x above what we see.
    assert errs[-1] < errs[0] / 4 and errs[-1] < 1e-2, errs


def test_supersample_kernel_converges_like_one_over_n():
    # one bright pixel: the output is the kernel itself
    image = np.zeros((21, 21))
    image[10, 10] = 1.0
    radius = np.full((21, 21), 6.3)
    soft = coc_filter(image, radius)
    e8 = _err(coc_filter(image, radius, method=Supersample(samples=8)), soft)
    e64 = _err(coc_filter(image, radius, method=Supersample(samples=64)), soft)
    # the weight error of a pixel the circle crosses is <= (its arc's sub-cells) / n^2 / (pi r^2),
    # i.e. O(1/n); 8x more samples must give at least 4x less error (the rate, with slack for the
    # lattice's irregular phase against the circle)
    assert e64 < e8 / 4, (e8, e64)


def _supersample_reference(image, radius, n, half, blades=None, rotation=0.0):
    """The n x n count, scattered source by source in numpy (no symmetry, no row ranges); with
    `blades`, a sub-sample is inside when it is inside every edge's half-plane."""
    h, w, _ = image.shape
    sub = (np.arange(n) + 0.5) / n - 0.5
    o = np.arange(-half, half + 1)
    # (offset y, offset x, sub y, sub x): coordinates of every sub-sample of the window
    ys = (o[:, None, None, None] + sub[None, None, :, None]) + 0 * o[None, :, None, None]
    xs = (o[None, :, None, None] + sub[None, None, None, :]) + 0 * o[:, None, None, None]
    if blades is None:
        d2 = ys**2 + xs**2  # inside: d2 <= r^2
    else:  # the polygon scaled by r: max_k (n_k . (x, y)) / apothem <= r, squared to match
        normals, apothem = unit_halfplanes(blades, rotation)
        proj = (
            normals[:, 0, None, None, None, None] * xs + normals[:, 1, None, None, None, None] * ys
        )
        d2 = np.maximum(proj.max(0), 0) ** 2 / apothem**2
    out = np.zeros_like(image)
    for y in range(h):
        for x in range(w):
            r = radius[y, x]
            if r <= 0.5:
                out[y, x] += image[y, x]
                continue
            count = (d2 <= r * r).sum((2, 3))
            share = count / count.sum()
            for iy, oy in enumerate(o):
                for ix, ox in enumerate(o):
                    if 0 <= y + oy < h and 0 <= x + ox < w:
                        out[y + oy, x + ox] += image[y, x] * share[iy, ix]
    return out


@pytest.mark.parametrize("n", [1, 3, 4, 17])  # 17: the sub-rows in a loop, not written out
def test_supersample_equals_a_brute_force_count(n):
    """The per-class count (mirrored taps, row ranges) is the plain count of sub-pixel centres."""
    image, radius = _scene(9, 11, 3.4)
    radius[::4] = 0.4
    radius[1::3, ::2] = 2.0  # sub-sample centres exactly on the circle for even n
    out = coc_filter(image, radius, method=Supersample(samples=n), max_radius=3.4)
    ref = _supersample_reference(image, radius, n, window_half_width(3.4))
    assert _err(out, ref) < 1e-14


@pytest.mark.parametrize("blades, rotation, n", [(5, 0.3, 3), (6, 1.1, 17)])
def test_supersample_polygon_equals_a_brute_force_count(blades, rotation, n):
    """With blades every tap is counted by row ranges on the polygon's rows: the plain count."""
    image, radius = _scene(9, 11, 3.4, seed=5)
    radius[::4] = 0.4
    method = Supersample(samples=n, blades=blades, rotation=rotation)
    out = coc_filter(image, radius, method=method, max_radius=3.4)
    ref = _supersample_reference(image, radius, n, window_half_width(3.4), blades, rotation)
    assert _err(out, ref) < 1e-14


def test_supersample_with_one_sample_is_hard():
    image, radius = _scene()
    np.testing.assert_allclose(
        coc_filter(image, radius, method=Supersample(samples=1)),
        coc_filter(image, radius, method=Hard()),
        rtol=0,
        atol=1e-14,  # the same integer counts, divided in a different order
    )


def test_jitter_converges_to_soft_and_is_unbiased():
    image, radius = _scene(14, 15, 4.0)
    soft = np.asarray(coc_filter(image, radius))
    keys = jax.random.split(jax.random.key(1), 8)
    compiled = {
        n: jax.jit(
            lambda k, n=n: coc_filter(
                image, radius, method=Jitter(samples=n, key=k), max_radius=4.0
            )
        )
        for n in (4, 16, 256)
    }
    one = lambda n, k: np.asarray(compiled[n](k))
    e4 = np.mean([_err(one(4, k), soft) for k in keys[:4]])
    e256 = np.mean([_err(one(256, k), soft) for k in keys[:4]])
    # 64x the samples: Monte Carlo alone gives 8x less error, stratification more
    assert e256 < e4 / 4, (e4, e256)
    # unbiased: the mean over 8 independent keys is closer to soft than one draw (by ~sqrt(8))
    mean8 = np.mean([one(16, k) for k in keys], axis=0)
    assert _err(mean8, soft) < 0.6 * np.mean([_err(one(16, k), soft) for k in keys[:4]])


@pytest.mark.parametrize("path, rmax", [("dense", 3.0), ("spans", 13.0)])
# 5: compared with every point (up to `_tuning.COMPARE_ALL_MAX`); 40: the binary search. (1, 16
# and the counts between run the same two paths: 305 s of the slow run for 8 cases, 140 s for 4.)
@pytest.mark.parametrize("samples", [5, 40])
def test_jitter_equals_its_definition(samples, path, rmax):
    # the counts over precomputed thresholds against the paper's direct test of every point
    from jaxdof._filters.jitter import PATTERNS, jitter_filter, jitter_points

    image, radius = _scene(9, 11, rmax, seed=3)
    radius[2, 3], radius[4, 4], radius[5, 6] = 0.5, 0.0, rmax  # the identity branch; the window
    out = np.asarray(
        jitter_filter(
            jnp.asarray(image),
            jnp.asarray(radius),
            max_radius=rmax,
            samples=samples,
            key=KEY,
            path=path,
        )
    )
    k_points, k_choice = jax.random.split(KEY)
    pts = np.asarray(jitter_points(k_points, PATTERNS, samples, jnp.float64))
    choice = np.asarray(jax.random.randint(k_choice, radius.shape, 0, PATTERNS, jnp.int32))
    h, w = radius.shape
    ref = np.zeros_like(image)
    for y, x in np.ndindex(h, w):  # output pixel p = (y, x) gathers from every source q
        s = pts[choice[y, x]]  # its points, (dy, dx) from its centre
        for qy, qx in np.ndindex(h, w):
            r = radius[qy, qx]
            if r <= 0.5:
                wgt = float((qy, qx) == (y, x))
            else:
                d2 = (y + s[:, 0] - qy) ** 2 + (x + s[:, 1] - qx) ** 2
                wgt = np.sum(d2 <= r * r) / (math.pi * r * r * samples)
            ref[y, x] += wgt * image[qy, qx]
    np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-14)
    # the public method (whichever path it picks: same counts) and a traced key, which builds the
    # thresholds at run time (a concrete one at compile time)
    public = coc_filter(image, radius, method=Jitter(samples=samples, key=KEY), max_radius=rmax)
    np.testing.assert_allclose(public, out, rtol=1e-12)  # spans and dense round differently
    traced = jax.jit(
        lambda k: coc_filter(image, radius, method=Jitter(samples=samples, key=k), max_radius=rmax)
    )
    np.testing.assert_allclose(traced(KEY), public, rtol=1e-14, atol=1e-15)  # same hits; rounding


# The smallest window and one of 61 rows, whose spans hold every case the rows in between do
# (8 and 13 px added 270 s to the slow run and no path).
@pytest.mark.parametrize("rmax", [3.0, 30.0])
@pytest.mark.parametrize(
    "method, counts", [("jitter", (1, 5, 16)), ("supersample", (1, 2, 3, 4, 17))]
)  # supersample 17: the sub-rows in a loop, not written out
def test_spans_equal_the_dense_gather(method, counts, rmax):
    """Row spans give every fully covered pixel all its points (jitter's `n` hits, supersample's
    `n^2` sub-samples) and count only the boundary taps: the dense gather's counts, so the same
    image to rounding, at any window."""
    from jaxdof._filters.jitter import jitter_filter
    from jaxdof._filters.supersample import supersample_filter

    filt = {"jitter": functools.partial(jitter_filter, key=KEY), "supersample": supersample_filter}
    image, radius = _scene(23, 29, rmax, seed=4)
    radius[::5, ::4] = 0.3  # sharp sources among the blurred ones
    radius[1::6, 2::5] = 2.0  # sub-sample centres exactly on the circle for even n
    image, radius = jnp.asarray(image), jnp.asarray(radius)
    for n in counts:
        f = lambda path, n=n: filt[method](  # noqa: E731
            image, radius, max_radius=rmax, samples=n, path=path
        )
        assert _err(f("spans"), f("dense")) < 1e-13
    with pytest.raises(ValueError, match="path='rows' is not one of"):
        f("rows")


# --- energy --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "method",
    [
        Hard(),
        Supersample(samples=3),
        Supersample(samples=4, blades=5, rotation=0.3),
        Soft(blades=6, rotation=0.1),
        Aperture(samples=16),
        Aperture(samples=16, pattern="disc", key=KEY),
        Aperture(samples=8, pattern="ring", blades=5),
        Layered(layers=3),
        Auto(),
    ],
    ids=method_id,
)
def test_energy_conserved_exactly(method):
    image, radius = _interior_scene()
    out = coc_filter(image, radius, method=method, max_radius=5.0)
    # every weight set sums to one by construction; 1e-12 leaves room for the float64 sums and FFT
    np.testing.assert_allclose(np.asarray(out).sum((0, 1)), image.sum((0, 1)), rtol=1e-12)


def test_jitter_energy_conserved_in_expectation_only():
    image, radius = _interior_scene()
    f = jax.jit(
        lambda k: coc_filter(image, radius, method=Jitter(samples=4, key=k), max_radius=5.0).sum()
    )
    totals = np.array([float(f(k)) for k in jax.random.split(jax.random.key(2), 6)])
    rel = totals / image.sum() - 1
    assert np.all(rel != 0)  # a single draw does not conserve energy exactly...
    # ...but its mean does: each draw's error is ~1e-3 (thousands of independent hits), the mean
    # of six must be within 4 standard errors of zero
    assert abs(rel.mean()) < 4 * rel.std(ddof=1) / math.sqrt(len(rel)) + 1e-12


@pytest.mark.parametrize(
    "method", [Hard(), Supersample(), Jitter(key=KEY), Layered(), Soft(blades=5)], ids=method_id
)
def test_identity_at_subpixel_radius(method):
    image, _ = _scene(9, 8)
    radius = np.random.default_rng(0).uniform(0, 0.5, (9, 8))
    out = coc_filter(image, radius, method=method, max_radius=3.0)
    np.testing.assert_allclose(out, image, rtol=0, atol=1e-15)  # FFT rounding for layered


def test_hard_spreads_evenly_over_covered_centres():
    image = np.zeros((7, 7))
    image[3, 3] = 1.0
    out = np.asarray(coc_filter(image, np.full((7, 7), 1.0), method=Hard()))
    expected = np.zeros((7, 7))
    expected[3, 2:5] = expected[2:5, 3] = 0.2  # centre + 4 neighbours at distance exactly 1
    np.testing.assert_array_equal(out, expected)


# --- keys ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "make",
    [
        functools.partial(Jitter, samples=4),
        functools.partial(Aperture, pattern="jittered", samples=8),
        functools.partial(Aperture, pattern="weighted_disc", samples=8),
    ],
    ids=["jitter", "aperture-jittered", "aperture-weighted_disc"],
)
def test_deterministic_for_a_key(make):
    image, radius = _scene(12, 13)
    f = jax.jit(lambda k: coc_filter(image, radius, method=make(key=k), max_radius=5.0))
    run = lambda k: np.asarray(f(k))
    np.testing.assert_array_equal(run(jax.random.key(7)), run(jax.random.key(7)))
    np.testing.assert_array_equal(run(jax.random.PRNGKey(7)), run(jax.random.PRNGKey(7)))
    assert not np.array_equal(run(jax.random.key(7)), run(jax.random.key(8)))


# --- polygonal diaphragms --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "make",
    [Soft, functools.partial(Supersample, samples=8), functools.partial(Aperture, samples=256)],
    ids=["soft", "supersample", "aperture"],
)
def test_many_blades_approach_the_disc(make):
    image, radius = _scene(16, 16, 6.0)
    disc = coc_filter(image, radius, method=make())
    errs = [_err(coc_filter(image, radius, method=make(blades=b)), disc) for b in (5, 12, 96)]
    assert errs[0] > errs[1] > errs[2], errs
    # a b-gon inscribed in the circle misses a fraction ~ (2 pi^2 / 3) / b^2 of the disc's area:
    # 7e-4 at b = 96, so the outputs differ by a few 1e-4 of the image scale
    assert errs[2] < 2e-3, errs


def test_square_aperture_kernel_is_exact():
    # 4 blades at 45 degrees with circumradius sqrt(2) * 2.5: the square [-2.5, 2.5]^2, i.e. exactly
    # a 5x5 box of pixels
    image = np.zeros((9, 9))
    image[4, 4] = 1.0
    radius = np.full((9, 9), 2.5 * math.sqrt(2))
    out = np.asarray(coc_filter(image, radius, method=Soft(blades=4, rotation=math.pi / 4)))
    expected = np.zeros((9, 9))
    expected[2:7, 2:7] = 1 / 25
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-14)


def test_aperture_splat_has_the_discs_second_moment():
    image = np.zeros((25, 25))
    image[12, 12] = 1.0
    r = 6.3
    out = np.asarray(coc_filter(image, np.full((25, 25), r), method=Aperture(samples=4096)))
    y, x = np.mgrid[0:25, 0:25] - 12.0
    assert abs((out * x).sum()) < 1e-3 and abs((out * y).sum()) < 1e-3  # centred
    # uniform disc: E[x^2] = r^2 / 4 per axis; the bilinear splat adds t(1 - t), 1/6 on average.
    # 0.5 % covers the lattice's finite sampling of the disc (4096 points)
    var = (out * x * x).sum()
    assert abs(var / (r * r / 4 + 1 / 6) - 1) < 5e-3, var


# --- layered and auto ------------------------------------------------------------------------------


@pytest.fixture(params=["fft", "direct"])
def layered_path(request):
    """Force `layered`'s FFTs or its direct sum (normally chosen by cost from the window and L)."""
    cost = 0.0 if request.param == "fft" else math.inf
    with tuning.override(FFT_LEVEL_COST_IN_TAPS=cost):
        yield request.param


def _levels_scene(levels, h=26, w=28, seed=3):
    rng = np.random.default_rng(seed)
    image = rng.uniform(size=(h, w, 3))
    radius = rng.choice(np.asarray(levels), (h, w))  # depth edges everywhere
    return image, radius


@pytest.mark.parametrize("jit", [False, True])
def test_layered_equals_soft_with_exactly_L_levels(jit, layered_path):
    image, radius = _levels_scene([0.0, 1.7, 3.25, 6.0])
    soft = coc_filter(image, radius)
    f = lambda i, r: coc_filter(i, r, method=Layered(layers=4), max_radius=6.0)
    out = jax.jit(f)(image, radius) if jit else f(image, radius)
    # The scatter has no occlusion, so layering is exact everywhere, depth edges included; what is
    # left is FFT rounding (a few 1e-16 of the image's sum in float64).
    assert _err(out, soft) < 1e-12
    # with fewer layers than levels, two levels share a kernel: no longer the soft filter
    assert _err(coc_filter(image, radius, method=Layered(layers=3)), soft) > 1e-2


def test_layered_scan_path_equals_soft():
    """More FFT levels than are unrolled: the scan over levels gives the same scatter."""
    radii = [0.0] + [1.0 + 0.5 * k for k in range(tuning.UNROLL_LEVELS + 2)]
    image, radius = _levels_scene(radii, 24, 23)
    with tuning.override(FFT_LEVEL_COST_IN_TAPS=0.0):  # the FFTs, whatever the cost
        out = coc_filter(image, radius, method=Layered(layers=len(radii)), max_radius=radii[-1])
    assert _err(out, coc_filter(image, radius)) < 1e-12


@pytest.mark.parametrize("traced", [False, True])
def test_layered_level_radius_is_exact_in_float32(traced):
    """A level of 1e5 equal float32 radii is blurred with exactly that radius: a plain float32 mean
    drifts by ~1e-4 relative, which put the layered render 1.5e-4 off the soft one at R = 6."""
    rng = np.random.default_rng(7)
    values = np.float32([0.0, 1.4895833, 5.958332, 7.999999])
    idx = rng.integers(0, 4, (320, 320))
    radius = values[idx]
    assignment = None if traced else assign_numpy(radius, 4)
    _, levels = jax.jit(lambda r: assign_levels(r, 4, assignment))(jnp.asarray(radius))
    assert np.array_equal(np.asarray(levels), values)
    if not traced:  # the levels a concrete map's kernels are built from at compile time
        assert np.array_equal(level_radii(radius, assignment, 4).astype(np.float32), values)
    # and the render: the soft filter's to float32 FFT rounding
    image = rng.uniform(size=(320, 320, 3)).astype(np.float32)
    out = coc_filter(image, radius, method=Auto(), max_radius=8.0)
    assert choose_method(radius, max_radius=8.0) == "layered"
    assert _err(out, coc_filter(image, radius, max_radius=8.0)) < 2e-6


def test_traced_level_search_equals_numpy():
    """The traced assignment (`layers` min-reductions, no sort) gives `assign_numpy`'s index map:
    exact levels, binned ones, all-sharp, one distinct value, fewer values than layers, L = 1."""
    rng = np.random.default_rng(21)
    values = np.asarray([0.0, 0.3, 0.5, 0.7, 1.0, 2.0, 3.5, 5.0, 8.0, 9.25, 20.0])
    search = {n: jax.jit(lambda r, n=n: assign_levels(r, n)[0]) for n in (1, 2, 3, 5, 9)}
    for trial in range(60):
        radius = rng.choice(rng.choice(values, rng.integers(1, 9)), (7, 9))
        if trial % 3 == 0:  # a continuum: every pixel its own radius
            radius = radius + rng.uniform(0, 2, radius.shape)
        for layers, f in search.items():
            idx = np.asarray(f(jnp.asarray(radius)))
            assert np.array_equal(idx, assign_numpy(radius, layers)), (trial, layers)


def test_layered_direct_sum_equals_the_ffts():
    """The two ways of summing the levels, on a binned map (more radii than layers, sharp pixels
    among them): the same render, the same image gradient, the same radius derivative (through
    the level means), traced and on a concrete map."""
    rng = np.random.default_rng(13)
    image = rng.uniform(size=(17, 19, 2))
    radius = np.where(rng.uniform(size=(17, 19)) < 0.3, 0.4, rng.uniform(0.8, 3.5, (17, 19)))
    direction = rng.normal(size=radius.shape)

    def render_and_slope(path, concrete):
        f = lambda i, r: layered.layered_filter(  # noqa: E731
            jnp.asarray(i), r, max_radius=3.5, layers=4, path=path
        )
        if concrete:
            return f(image, jnp.asarray(radius)), None
        out, slope = jax.jvp(lambda r: f(image, r), (jnp.asarray(radius),), (direction,))
        return out, slope

    for concrete in (False, True):
        (fft, s_fft), (direct, s_direct) = (
            render_and_slope(p, concrete) for p in ("fft", "direct")
        )
        assert _err(direct, fft) < 1e-12
        assert _err(direct, coc_filter(image, radius, max_radius=3.5)) > 1e-3  # binned, not soft
        if s_fft is not None:
            assert _err(s_direct, s_fft) < 1e-12 and _err(s_direct, 0 * s_direct) > 1e-3
    f = jax.jit(
        lambda i: layered.layered_filter(
            i, jnp.asarray(radius), max_radius=3.5, layers=4, path="direct"
        )
    )
    check_grads(f, (image,), order=1, modes=("fwd", "rev"), eps=1e-3, atol=1e-8, rtol=1e-8)
    with pytest.raises(ValueError, match="path must be"):
        layered.layered_filter(
            jnp.asarray(image), jnp.asarray(radius), max_radius=3.5, layers=4, path="x"
        )


def test_layered_takes_the_direct_sum_for_small_windows():
    """The cost rule: the direct sum for a 5 x 5 window at any L, the FFTs for R = 24 at any L and for
    R = 8 with two levels (the measured crossovers in `FFT_LEVEL_COST_IN_TAPS`' comment)."""
    for layers in (1, 2, 4, 8, 16, 32):
        assert layered.direct_is_cheaper(2.0, layers, layers)
        assert not layered.direct_is_cheaper(24.0, layers, layers)
    assert not layered.direct_is_cheaper(8.0, 2, 2) and layered.direct_is_cheaper(4.0, 2, 2)
    assert layered.direct_is_cheaper(6.0, 8, 8) and not layered.direct_is_cheaper(8.0, 8, 8)


def test_fft_length_is_5_smooth_and_minimal():
    for n in range(1, 400):
        m = fft_length(n)
        k = m
        for p in (2, 3, 5):
            while k % p == 0:
                k //= p
        assert m >= n and k == 1
        assert all(fft_length(j) == m for j in range(n, m + 1))  # nothing 5-smooth in between


def test_layered_copies_the_sharp_level(layered_path):
    """On a concrete map the level of radii <= 1/2 is copied, not convolved (one FFT fewer); the
    result is the traced map's (every level summed) and the soft filter's, on either path."""
    image, radius = _levels_scene([0.3, 2.5, 7.0])
    assert sharp_first_level(radius, assign_numpy(radius, 3))
    assert not sharp_first_level(radius, assign_numpy(radius, 1))  # one level mixes every radius
    assert not sharp_first_level(np.full_like(radius, 2.5), np.zeros(radius.shape, np.int32))
    f = lambda i, r: coc_filter(i, r, method=Layered(layers=3), max_radius=7.0)  # noqa: E731
    concrete, traced = f(image, radius), jax.jit(f)(image, radius)
    assert _err(concrete, traced) < 1e-12 and _err(concrete, coc_filter(image, radius)) < 1e-12
    # every pixel sharp: no convolution at all, the image itself
    assert _err(f(image, np.full_like(radius, 0.3)), image) == 0.0


def test_layered_concrete_map_binned_equals_traced(layered_path):
    """More radii than layers: the concrete map's levels (numpy means, kernels built at compile
    time) are the traced map's (`assign_levels`), so the two renders agree to rounding."""
    rng = np.random.default_rng(11)
    image = rng.uniform(size=(21, 19, 3))
    radius = np.where(rng.uniform(size=(21, 19)) < 0.3, 0.2, rng.uniform(1.0, 5.0, (21, 19)))
    f = lambda i, r: coc_filter(i, r, method=Layered(layers=4), max_radius=5.0)  # noqa: E731
    concrete, traced = f(image, radius), jax.jit(f)(image, radius)
    assert _err(concrete, traced) < 1e-12
    assert _err(concrete, coc_filter(image, radius)) > 1e-3  # binned: not the soft filter


def test_layered_float32_matches_soft(layered_path):
    image, radius = _levels_scene([0.0, 2.5, 7.0])
    image, radius = image.astype(np.float32), radius.astype(np.float32)
    out = coc_filter(image, radius, method=Layered(layers=3))
    assert out.dtype == jnp.float32
    # float32 FFT over a 40 x 40 frame: rounding ~ eps * log(n) * max|image| ~ 1e-6
    assert _err(out, coc_filter(image, radius)) < 5e-6


def test_layered_keeps_sharp_pixels_sharp_when_binning(layered_path):
    """More radii than layers: the radii <= 1/2 keep a level of their own, so they stay the identity."""
    rng = np.random.default_rng(5)
    image = rng.uniform(size=(20, 22, 3))
    sharp = rng.uniform(size=(20, 22)) < 0.4
    radius = np.where(sharp, 0.3, rng.uniform(1.0, 6.0, (20, 22)))
    out = coc_filter(image, radius, method=Layered(layers=3), max_radius=6.0)
    # a sharp pixel whose neighbours within 6 px are all sharp receives only its own light
    isolated = sharp.copy()
    for dy in range(-6, 7):
        for dx in range(-6, 7):
            isolated &= np.roll(np.roll(sharp, dy, 0), dx, 1)
    # every such pixel's light: its own (the identity), whatever the binning of the others
    src = np.zeros((20, 22, 3))
    src[sharp] = image[sharp]
    ref = coc_filter(src, np.where(sharp, 0.3, 0.0), max_radius=6.0)
    np.testing.assert_allclose(np.asarray(out)[isolated], np.asarray(ref)[isolated], atol=1e-12)
    # and a sharp pixel's own light is never spread: the layer of level 0 is the identity
    only_sharp = coc_filter(src, radius, method=Layered(layers=3), max_radius=6.0)
    np.testing.assert_allclose(only_sharp, src, atol=1e-12)


@pytest.mark.parametrize("select_max", [16, 0], ids=["select-chain", "take"])
@pytest.mark.parametrize("max_radius", [6.5, 2.0, 2.5], ids=["class-loop", "fused-21", "fused-25"])
def test_tabulated_equals_soft(select_max, max_radius):
    """The looked-up weights are the soft filter's: same result, depth edges and identity level
    included, through either look-up (a chain of selects for few levels, a gather for many) and
    either loop (the class loop, or every tap fused for windows of at most 25 taps)."""
    radii = sorted({r for r in [0.2, 1.7, 3.25, 6.0, 6.5] if r <= max_radius} | {max_radius})
    image, radius = _levels_scene(radii)
    levels, index = radius_levels(radius)
    assert np.array_equal(levels, [0.0] + radii[1:])
    fused = len(tap_offsets(max_radius)) <= tuning.FUSED_MAX_TAPS
    assert fused == (max_radius < 3)
    with tuning.override(SELECT_MAX_LEVELS=select_max):
        out = tabulated_filter(
            jnp.asarray(image), max_radius=max_radius, levels=levels, index=index
        )
    assert _err(out, coc_filter(image, radius, max_radius=max_radius)) < 1e-13


def test_auto_picks_what_the_scene_needs():
    image, _ = _levels_scene([0.0])
    const = np.full(image.shape[:2], 5.5)
    few = _levels_scene([0.0, 3.0, 8.0])[1]
    many = np.random.default_rng(0).uniform(0, 8, image.shape[:2])
    # FFT layers only where L of them cost less than the window's taps (LAYER_COST_IN_TAPS each)
    assert max_layers(5.5) == 1 and max_layers(8.0) == 3
    assert choose_method(const) == "convolution"
    # 0.3 is the identity level: copied, not convolved, so one blurred plane needs one FFT layer
    assert choose_method(np.where(few > 0, 5.5, 0.3)) == "layered"
    assert choose_method(np.where(few > 0, 5.5, 3.0)) == "tabulated"  # two blurred levels
    assert choose_method(few) == "layered"
    assert choose_method(few, max_radius=12.0) == "layered"
    assert choose_method(np.where(few > 0, few, 0.3), max_radius=3.0) == "tabulated"
    # every pixel its own radius: no table to share
    assert choose_method(many) == "soft"
    for radius in (const, few, many, np.minimum(few, 3.0)):
        # always the soft filter's result, whatever it chose
        assert _err(coc_filter(image, radius, method=Auto()), coc_filter(image, radius)) < 1e-12
    # traced radius: the documented fallback to the soft gather
    traced = jax.jit(lambda i, r: coc_filter(i, r, method=Auto(), max_radius=8.0))(image, few)
    assert _err(traced, coc_filter(image, few, max_radius=8.0)) < 1e-12
    # a concrete radius closed over inside jit is still inspected
    closed = jax.jit(lambda i: coc_filter(i, few, method=Auto(), max_radius=8.0))(image)
    assert _err(closed, coc_filter(image, few)) < 1e-12


def test_render_passes_the_method_and_auto_works_outside_jit():
    lens = ThinLens(0.05, 2.0, 2.0, 2e-4)
    image = np.random.default_rng(0).uniform(size=(16, 18, 3))
    depth = np.where(np.arange(18)[None, :] < 9, 2.0, 4.0) + np.zeros((16, 1))
    soft = render(image, depth, lens)
    # a depth step with circles of 0.8 px: the scene's treatment (`scene_treatment`), occlusion
    # and the footprint correction, not the soft render
    t = scene_treatment(depth, lens)
    assert (t.method, t.footprint) == ("local_occlusion", True)
    want = render(image, depth, lens, method=LocalOcclusion(), footprint=True)
    assert _err(render(image, depth, lens, method=Auto()), want) < 1e-12
    out = render(image, depth, lens, method=Jitter(samples=4, key=KEY))
    assert out.shape == image.shape and _err(out, soft) > 0
    # the options live in the method object: render has no keywords for them
    with pytest.raises(TypeError, match="layers"):
        render(image, depth, lens, method=Soft(), layers=3)


# --- bad options -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "cls, options, match",
    [
        (Jitter, {}, r"needs an explicit key: pass e.g. jaxdof.Jitter\(key=jax.random.key\(0\)\)"),
        (Aperture, {"pattern": "disc"}, "needs an explicit key"),
        (Aperture, {"key": KEY}, "does not use key"),
        (Aperture, {"pattern": "spiral"}, "pattern='spiral'"),
        (Aperture, {"samples": 0}, "samples must be"),
        (Supersample, {"samples": 0}, "samples must be"),
        (Supersample, {"samples": 65}, r"samples must be in \[1, 64\]"),
        (Jitter, {"samples": True, "key": KEY}, "samples must be a Python int"),
        (Soft, {"blades": 2}, "blades must be"),
        (Soft, {"rotation": 0.5}, "rotation=0.5 has no effect"),
        (Supersample, {"rotation": 0.5}, "rotation=0.5 has no effect"),
        (Soft, {"blades": 5, "rotation": math.inf}, "rotation must be finite"),
        (Layered, {"layers": 0}, "layers must be"),
        (Occlusion, {"layers": 257}, "layers must be"),
        (Jitter, {"key": np.zeros(3, np.uint32)}, "key must be"),
        (Jitter, {"key": jax.random.split(KEY)}, "key must be a single PRNG key"),
    ],
)
def test_bad_options_rejected(cls, options, match):
    """A wrong value is a `ValueError` from the method's constructor, naming it and the fix."""
    with pytest.raises(ValueError, match=match):
        cls(**options)


@pytest.mark.parametrize(
    "cls, option",
    [
        (Soft, "samples"),
        (Hard, "key"),
        (Layered, "blades"),
        (Supersample, "pattern"),
        (Auto, "layers"),
    ],
)
def test_options_a_method_does_not_have_are_rejected(cls, option):
    """An option the method does not take is not silently ignored: Python names it."""
    with pytest.raises(TypeError, match=f"unexpected keyword argument '{option}'"):
        cls(**{option: 2})


def test_options_are_keyword_only_fields():
    for cls in BUILT_IN:
        params = list(inspect.signature(cls).parameters.values())
        assert all(p.kind == p.KEYWORD_ONLY for p in params), cls
    # a rotation is ignored on a disc only when zero; the aperture's lattice turns with it
    assert Soft(rotation=0.0) == Soft() and Aperture(rotation=0.5).rotation == 0.5


# --- gradients -------------------------------------------------------------------------------------

# float64, small frame; radii kept away from 1/2 (the identity's dead zone) and from max_radius
_GRAD_RADIUS = np.random.default_rng(5).uniform(1.2, 2.6, (6, 7))
_GRAD_IMAGE = np.random.default_rng(6).uniform(size=(6, 7))


@pytest.mark.parametrize(
    "method",
    [
        Hard(),
        Supersample(samples=3),
        Jitter(samples=4, key=KEY),
        Layered(layers=3),
        Aperture(samples=8),
        Soft(blades=5, rotation=0.2),
    ],
    ids=method_id,
)
def test_gradients_wrt_image(method):
    f = jax.jit(lambda img: coc_filter(img, _GRAD_RADIUS, method=method, max_radius=3.0))
    # linear in the image: finite differences are exact up to rounding; eps = 1e-3 in float64
    check_grads(f, (_GRAD_IMAGE,), order=1, modes=("fwd", "rev"), eps=1e-3, atol=1e-8, rtol=1e-8)


@pytest.mark.parametrize(
    "method", [Aperture(samples=8), Soft(blades=5, rotation=0.2), Auto()], ids=method_id
)
def test_gradients_wrt_radius(method):
    assert method.differentiable_in_radius
    f = jax.jit(lambda r: coc_filter(_GRAD_IMAGE, r, method=method, max_radius=3.0))
    # Piecewise smooth in r (bilinear splats / polygon clipping): a step of 1e-6 px almost never
    # crosses a kink at these random radii; central differences then have error ~eps^2 * f'''
    # plus rounding 1e-16 / 1e-6, so 1e-6 relative is ample.
    check_grads(f, (_GRAD_RADIUS,), order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-6, rtol=1e-6)


def test_polygon_overlap_radius_tangent_is_finite():
    # Compiled at XLA level 0 (the tests' level, conftest.py) the tangent of a jnp.min/jnp.max over
    # the edges was inf or NaN at a fifth of these taps: its count of the elements equal to the
    # result, recomputed in another kernel with an FMA, was 0 (shape._extreme). Vectors, not
    # scalars: one radius at a time compiled to kernels that agreed.
    oy, ox = jnp.asarray(np.mgrid[-3:4, -3:4].reshape(2, -1), float)
    r = jnp.asarray(np.random.default_rng(7).uniform(0.6, 3.5, ox.shape))
    f = jax.jit(lambda r: polygon_pixel_overlap(ox, oy, r, 5, 0.2))
    tangent = jax.jvp(f, (r,), (jnp.ones_like(r),))[1]
    assert np.all(np.isfinite(tangent))
    # piecewise smooth in r: central differences at random radii, as in the test above
    np.testing.assert_allclose(tangent, (f(r + 1e-6) - f(r - 1e-6)) / 2e-6, rtol=0, atol=1e-6)


@pytest.mark.parametrize(
    "method", [Hard(), Supersample(samples=3), Jitter(samples=4, key=KEY)], ids=method_id
)
def test_no_gradient_wrt_radius_is_zero_not_noise(method):
    assert not method.differentiable_in_radius
    g = jax.grad(lambda r: coc_filter(_GRAD_IMAGE, r, method=method, max_radius=3.0).sum())
    assert np.array_equal(np.asarray(g(_GRAD_RADIUS)), np.zeros_like(_GRAD_RADIUS))


def test_layered_radius_gradient_is_exact_for_depth_planes(layered_path):
    # every pixel of a plane shares a radius: the derivative along "move the whole plane" is exact
    image, radius = _levels_scene([0.0, 1.7, 3.2], 12, 13)
    mask = (radius == 3.2).astype(float)

    def directional(method):
        f = lambda t: coc_filter(image, radius + t * mask, method=method, max_radius=4.0)
        return jax.jit(lambda t: jax.jvp(f, (t,), (1.0,))[1])(0.0)

    # the same analytic derivative; FFT rounding aside
    assert _err(directional(Layered(layers=3)), directional(Soft())) < 1e-10


@pytest.mark.parametrize(
    "method", [m for name, m in CATALOGUE.items() if name != "auto"], ids=method_id
)
def test_float32_in_float32_out(method):
    image, radius = _scene(10, 11)
    out = coc_filter(image.astype(np.float32), radius.astype(np.float32), method=method)
    assert out.dtype == jnp.float32 and out.shape == image.shape
    assert np.all(np.isfinite(np.asarray(out)))


@pytest.mark.parametrize("n_levels", [1, 2, 3, 16, 17, 300])
def test_unique_with_index_matches_numpy(n_levels):
    """The level index of auto's inspection equals `np.unique(..., return_inverse=True)`, on both
    sides of the size where it switches from comparisons to the argsort."""
    rng = np.random.default_rng(n_levels)
    values = rng.choice(rng.uniform(0, 5, n_levels).astype(np.float32), size=(37, 53))
    uniq, index = unique_with_index(values)
    expected_uniq, inverse = np.unique(values, return_inverse=True)
    np.testing.assert_array_equal(uniq, expected_uniq)
    np.testing.assert_array_equal(index, inverse.reshape(values.shape))
    assert index.dtype == np.int32
