"""fit_lens: recovery, identifiability, robustness, statistics, batching.

Every fit here compiles a solve (tens of seconds on a loaded CPU), so the tests share a handful of
compiled configurations: one 32x32 scene, `max_radius=WINDOW` and `starts=2` wherever the point of
the test allows, so that most fits reuse the first compilation.
"""

import json
import pathlib
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxdof
import jaxdof._fit.solve as fit_solve
from jaxdof import RESULTS, ThinLens, coc_filter, fit_lens, render, solve_lens
from jaxdof._fit import (
    auto_levels,
    layout,
    max_circle,
    prepare,
    record_stages,
    residual,
    strategies,
)

from .helpers import EXACT


H = W = 32
PITCH = 8e-5  # m: large pixels, so that a 50 mm f/2 lens gives circles of a few pixels here
TRUE = dict(focal_length=0.05, f_number=2.0, focus_distance=1.6)  # K = 5.04 px
TRAP = pathlib.Path(__file__).parent / "data" / "pyramid_trap.npz"
WINDOW = 6.0  # px: the truth's largest circle is 3.0 px; headroom for iterates
STARTS = 2

# Every identifiable free set from one photo (f and N together are not, see below).
IDENTIFIABLE = [
    ("focus_distance",),
    ("f_number",),
    ("focal_length",),
    ("f_number", "focus_distance"),
    ("focal_length", "focus_distance"),
]


def scene(dtype=np.float64, seed=0):
    """A random texture on a slanted plane 1..3 m, with a step to 1.2 m in one quadrant."""
    rng = np.random.default_rng(seed)
    image = rng.uniform(size=(H, W))
    yy, xx = np.mgrid[0:H, 0:W]
    depth = 1.0 + 2.0 * xx / (W - 1)
    depth = np.where((yy < H // 3) & (xx > W // 2), 1.2, depth)
    return image.astype(dtype), depth.astype(dtype)


def lens(dtype=np.float64, **kw):
    v = {**TRUE, **kw}
    return ThinLens(
        *(np.asarray(v[n], dtype) for n in ("focal_length", "f_number", "focus_distance")),
        np.asarray(PITCH, dtype),
    )


def wrong_init(free, dtype=np.float64):
    """Start off by a factor of 2 in K (through N, or f) and by 30% in the focus distance."""
    kw = {}
    if "f_number" in free:
        kw["f_number"] = TRUE["f_number"] * 2  # K / 2
    elif "focal_length" in free:
        kw["focal_length"] = TRUE["focal_length"] / np.sqrt(2)  # K / 2 (f << d_f)
    if "focus_distance" in free:
        kw["focus_distance"] = TRUE["focus_distance"] * 1.3
    return lens(dtype, **kw)


def rel_err(fit, true, fields):
    return {n: abs(float(getattr(fit, n)) / float(getattr(true, n)) - 1) for n in fields}


@pytest.mark.parametrize("free", IDENTIFIABLE)
def test_noise_free_recovery_float64(free):
    image, depth = scene()
    true = lens()
    target = render(image, depth, true)
    res = fit_lens(
        image, depth, target, wrong_init(free), free=free, max_radius=WINDOW, starts=STARTS, **EXACT
    )
    assert bool(res.success), res.message
    err = rel_err(res.lens, true, ("focal_length", "f_number", "focus_distance"))
    assert max(err.values()) < 1e-4, err  # the float64 target
    assert set(res.stderr) == set(free)
    assert res.covariance.shape == (len(free), len(free))


def test_noise_free_recovery_float32():
    image, depth = scene(np.float32)
    true = lens(np.float32)
    target = render(image, depth, true)
    assert target.dtype == jnp.float32
    compiled = {}
    for free in IDENTIFIABLE:
        init = wrong_init(free, np.float32)
        res = fit_lens(
            image, depth, target, init, free=free, max_radius=WINDOW, starts=STARTS, **EXACT
        )
        assert bool(res.success), (free, res.message)
        assert res.lens.f_number.dtype == jnp.float32
        err = rel_err(res.lens, true, ("focal_length", "f_number", "focus_distance"))
        assert max(err.values()) < 1e-3, (free, err)  # the float32 target
        # Free sets of one size run the same compiled solve (which fields is data, not code).
        size = compiled.setdefault(len(free), fit_solve.fit_starts._cached._cache_size())
        assert fit_solve.fit_starts._cached._cache_size() == size, free
    # The rank test also holds at float32's rounding level (same compiled solve).
    with pytest.raises(ValueError, match="not determined by the data"):
        fit_lens(
            image,
            depth,
            target,
            lens(np.float32, f_number=3.0),
            free=("focal_length", "f_number"),
            max_radius=WINDOW,
            starts=STARTS,
            **EXACT,
        )


@pytest.mark.parametrize(
    "free", [("focal_length", "f_number"), ("focal_length", "f_number", "focus_distance")]
)
def test_degenerate_free_set_refused(free):
    image, depth = scene()
    target = render(image, depth, lens())
    init = lens(f_number=3.0, focus_distance=1.8 if "focus_distance" in free else 1.6)
    with pytest.raises(ValueError, match=r"K = f\^2 / \(2 N \(d_f - f\)\).*focus bracket"):
        fit_lens(image, depth, target, init, free=free, max_radius=WINDOW, starts=STARTS, **EXACT)
    res = fit_lens(
        image,
        depth,
        target,
        init,
        free=free,
        max_radius=WINDOW,
        starts=STARTS,
        allow_degenerate=True,
        **EXACT,
    )
    assert not bool(res.success)
    assert bool(res.status == RESULTS.degenerate)
    assert "not determined" in res.message
    # JSON-ready: the undetermined standard errors (inf) become null.
    obj = json.loads(json.dumps(res.to_dict(), allow_nan=False))
    assert obj["status"] == "degenerate" and obj["success"] is False
    assert obj["stderr"]["focal_length"] is None and obj["message"] == res.message
    # f and N move together along the null direction: no standard error for them ...
    assert np.isinf(float(res.stderr["focal_length"])) and np.isinf(float(res.stderr["f_number"]))
    # ... but K and d_f are determined, so the fit still reproduces the photo and the focus.
    np.testing.assert_allclose(float(res.lens.blur_scale), float(lens().blur_scale), rtol=1e-4)
    if "focus_distance" in free:
        assert np.isfinite(float(res.stderr["focus_distance"]))
        np.testing.assert_allclose(
            float(res.lens.focus_distance), TRUE["focus_distance"], rtol=1e-4
        )


def test_dead_zone_detected():
    """Circles all under half a pixel: the render ignores the lens, and fit_lens says so."""
    image, depth = scene()
    tiny = lens(f_number=64.0, focus_distance=1.9)  # K = 0.16 px
    target = render(image, depth, tiny)
    with pytest.raises(ValueError, match="every circle is under half a pixel"):
        fit_lens(image, depth, target, tiny, max_radius=WINDOW, starts=STARTS, **EXACT)
    res = fit_lens(
        image, depth, target, tiny, max_radius=WINDOW, starts=STARTS, allow_degenerate=True, **EXACT
    )
    assert not bool(res.success) and "half a pixel" in res.message
    assert bool(res.status == RESULTS.dead_zone)


def fit_twice_warm(image, depth, target, *args, **kw):
    """Two equal `fit_lens` calls: the second re-traces nothing (both compiled stages re-used)
    and gives bit-for-bit the same result and message."""
    a = fit_lens(image, depth, target, *args, **kw)
    compiled = (fit_solve.fit_starts._cached._cache_size(), fit_solve.finish._cached._cache_size())
    b = fit_lens(image, depth, target, *args, **kw)
    assert (
        fit_solve.fit_starts._cached._cache_size(),
        fit_solve.finish._cached._cache_size(),
    ) == compiled
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert a.message == b.message
    return a, b


def test_reproducible_bit_for_bit():
    image, depth = scene()
    rng = np.random.default_rng(1)
    target = np.asarray(render(image, depth, lens())) + 0.01 * rng.standard_normal((H, W))
    init = wrong_init(("f_number", "focus_distance"))
    a, _ = fit_twice_warm(image, depth, target, init, max_radius=WINDOW, starts=STARTS, **EXACT)
    # The compiled stages can be timed without patching: `fit_starts` on every pixel (the border
    # band of this small frame keeps under half of it, `fit._SEARCH_ALL_BELOW`), `fit_starts` with
    # the band, `finish`, then the score tests of the nuisances left to decide.
    with record_stages() as log:
        c = fit_lens(image, depth, target, init, max_radius=WINDOW, starts=STARTS, **EXACT)
    stages = ["fit_starts", "fit_starts", "finish", "nuisance scores"]
    assert [name for name, _ in log] == stages
    assert all(t > 0 for _, t in log)
    np.testing.assert_array_equal(np.asarray(c.lenses.f_number), np.asarray(a.lenses.f_number))


def test_stderr_matches_noisy_spread():
    """The reported standard error agrees with the spread of the estimates over noisy trials."""
    image, depth = scene()
    true = lens()
    clean = np.asarray(render(image, depth, true))
    init = wrong_init(("f_number", "focus_distance"))
    rng = np.random.default_rng(2024)
    sigma = 0.01
    est, se, fired = [], [], 0
    for _ in range(30):
        target = clean + sigma * rng.standard_normal(clean.shape)
        res = fit_lens(image, depth, target, init, max_radius=WINDOW, starts=STARTS, **EXACT)
        # The model is right: the adequacy test fires only by chance (alpha = 0.01).
        assert res.status in (RESULTS.successful, RESULTS.inconsistent), res.message
        fired += int(res.status == RESULTS.inconsistent)
        est.append([float(res.lens.f_number), float(res.lens.focus_distance)])
        noise_only = float(res.adequacy["inflation"])  # the noise's errors: undo the inflation
        se.append([float(res.stderr[k]) / noise_only for k in ("f_number", "focus_distance")])
        np.testing.assert_allclose(float(res.sigma), sigma, rtol=0.1)  # 1024 residuals: ~3% spread
    assert fired <= 3  # Binomial(30, 0.01): P(>= 4) = 2e-4
    spread = np.std(np.array(est), axis=0, ddof=1)
    reported = np.mean(np.array(se), axis=0)
    # 30 trials estimate a standard deviation to ~13% (1 sigma): a factor 1.5 is ~3 sigma.
    ratio = spread / reported
    assert np.all((ratio > 1 / 1.5) & (ratio < 1.5)), ratio
    # And the estimates are unbiased to within their spread.
    assert np.all(
        np.abs(np.mean(est, axis=0) - [TRUE["f_number"], TRUE["focus_distance"]])
        < 3 * spread / np.sqrt(30) + 1e-12
    )


def test_focus_bracket_recovers_f_and_n(capsys):
    """Three photos at different focus distances through one lens determine f and N apart.

    Also checks `verbose=True` (progress of every start), sharing this test's compilation.
    """
    image, depth = scene()
    focus = [1.2, 1.8, 2.6]
    targets = [render(image, depth, lens(focus_distance=d)) for d in focus]
    inits = [lens(focal_length=0.06, f_number=2.6, focus_distance=d * 1.1) for d in focus]
    free = ("focal_length", "f_number", "focus_distance")
    res = fit_lens(
        image,
        depth,
        targets,
        inits,
        free=free,
        shared=("focal_length", "f_number"),
        max_radius=10.0,
        starts=STARTS,
        verbose=True,
        **EXACT,
    )
    assert bool(res.success), res.message
    out = capsys.readouterr().out
    assert "step 0: loss" in out and "d_f[2]=" in out
    assert res.lenses.focal_length.shape == (3,)
    np.testing.assert_allclose(np.asarray(res.lenses.focal_length), TRUE["focal_length"], rtol=1e-4)
    np.testing.assert_allclose(np.asarray(res.lenses.f_number), TRUE["f_number"], rtol=1e-4)
    np.testing.assert_allclose(np.asarray(res.lenses.focus_distance), focus, rtol=1e-4)
    assert res.stderr["focal_length"].shape == (3,)
    assert res.names == (
        "focal_length",
        "f_number",
        "focus_distance[0]",
        "focus_distance[1]",
        "focus_distance[2]",
    )
    # f and N are each determined (finite errors), unlike from a single photo.
    assert np.all(np.isfinite(np.asarray(res.stderr["focal_length"])))
    assert "focus_distance" in res.summary()
    # JSON-ready (SI units), one lens per target, the first one also at the top level.
    obj = json.loads(json.dumps(res.to_dict(), allow_nan=False))
    assert [x["focus_distance"] for x in obj["lenses"]] == pytest.approx(focus, rel=1e-4)
    assert obj["focal_length"] == pytest.approx(TRUE["focal_length"], rel=1e-4)
    assert obj["lenses"][2]["stderr"]["focus_distance"] == pytest.approx(
        float(res.stderr["focus_distance"][2])
    )
    assert obj["names"] == list(res.names) and len(obj["covariance"]) == len(res.names)
    assert (obj["status"], obj["success"], obj["message"]) == ("successful", True, "converged")
    assert obj["steps"] == int(res.num_steps) and obj["levels"] == 1
    assert obj["max_radius"] == 10.0 and obj["gain"] == [1.0, 1.0, 1.0]
    assert {"loss", "sigma", "condition", "offset", "pixel_pitch"} <= set(obj)


def test_solve_lens_vmap_compiles_once():
    """Many independent scenes: one jit(vmap(solve_lens)) compilation serves every batch.

    The photos differ from the renders by an exposure gain and offset, fitted as nuisance
    parameters (`exposure=True`), in the same compilation.
    """
    scenes = [scene(seed=s) for s in range(3)]
    images = np.stack([s[0] for s in scenes])
    depths = np.stack([s[1] for s in scenes])
    truths = [1.4, 1.6, 1.9]
    targets = np.stack(
        [
            1.2 * np.asarray(render(i, d, lens(focus_distance=f))) + 0.05
            for i, d, f in zip(images, depths, truths)
        ]
    )
    init = lens(f_number=2.5, focus_distance=1.7)

    @jax.jit
    def batch(images, depths, targets):
        fit = lambda i, d, t: solve_lens(i, d, t, init, max_radius=WINDOW, exposure=True)  # noqa: E731
        return jax.vmap(fit)(images, depths, targets)

    res = batch(images, depths, targets)
    assert np.all(np.asarray(res.success))
    # Batched results: fields (scenes, targets).
    np.testing.assert_allclose(np.asarray(res.lenses.focus_distance[:, 0]), truths, rtol=1e-4)
    np.testing.assert_allclose(np.asarray(res.lenses.f_number), TRUE["f_number"], rtol=1e-4)
    assert res.stderr["focus_distance"].shape == (3,)
    np.testing.assert_allclose(np.asarray(res.gain), 1.2, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(res.offset), 0.05, rtol=1e-6)
    assert set(res.stderr) == {"f_number", "focus_distance", "gain", "offset"}
    res2 = batch(images[::-1], depths[::-1], targets[::-1])
    np.testing.assert_allclose(
        np.asarray(res2.lenses.focus_distance[:, 0]), truths[::-1], rtol=1e-4
    )
    assert batch._cache_size() == 1


def test_weight_masks_pixels():
    """A zero weight removes pixels: corrupting them leaves the fit exact."""
    image, depth = scene()
    target = np.array(render(image, depth, lens()))
    weight = np.ones((H, W))
    weight[:8] = 0
    target[:8] = 7.0  # garbage where masked
    res = fit_lens(
        image,
        depth,
        target,
        wrong_init(("f_number", "focus_distance")),
        weight=weight,
        max_radius=WINDOW,
        starts=STARTS,
        **EXACT,
    )
    assert bool(res.success), res.message
    err = rel_err(res.lens, lens(), ("f_number", "focus_distance"))
    assert max(err.values()) < 1e-4, err


def test_window_too_small_is_reported():
    """Circles larger than a given max_radius are clamped: the fit says so rather than pass."""
    image, depth = scene()
    big = lens(f_number=1.0)  # K = 10 px: circles up to 6.05 px, over WINDOW
    target = render(image, depth, big)
    res = fit_lens(
        image,
        depth,
        target,
        lens(f_number=1.5, focus_distance=1.8),
        max_radius=WINDOW,
        starts=STARTS,
        **EXACT,
    )
    assert not bool(res.success) and "max_radius" in res.message
    assert bool(res.status == RESULTS.window)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(free=("pixel_pitch",)), "pixel_pitch cannot be fitted"),
        (dict(free=("f_number",), shared=("focus_distance",)), "subset of free"),
        (dict(free=("aperture",)), "free must name fields"),
        (dict(starts=0), "starts must be"),
        (dict(weight=np.ones((3, 3))), "weight must have the targets' pixels"),
        (dict(method="hard"), "cannot drive a fit"),
    ],
)
def test_bad_arguments(kwargs, match):
    image, depth = scene()
    target = np.zeros((H, W))
    with pytest.raises(ValueError, match=match):
        fit_lens(image, depth, target, lens(), **kwargs)


def test_bad_targets():
    image, depth = scene()
    with pytest.raises(ValueError, match="targets must be one image"):
        fit_lens(image, depth, np.zeros((H, W + 1)), lens())
    with pytest.raises(ValueError, match="init has 2 lenses but there are 3 targets"):
        fit_lens(image, depth, [image] * 3, [lens(), lens()])
    with pytest.raises(ValueError, match="NaN"):
        fit_lens(image, depth, np.full((H, W), np.nan), lens())


def test_exported():
    assert jaxdof.fit_lens is fit_lens and jaxdof.FitResult.__doc__
    assert jaxdof.RESULTS is RESULTS and len(RESULTS) == 8
    assert issubclass(jaxdof.DefocusModel, jaxdof.AbstractForwardModel)


def test_residual_jacobian_rule():
    """The residual's JVP rule (it builds the small Jacobian once per point, for the solver)
    gives the plain forward model's derivatives, with respect to the lens coordinates and the
    data alike, forward and reverse."""
    image, depth = (x[:12, :12] for x in scene())
    target = np.asarray(render(image, depth, lens(), max_radius=3.0)) + 0.01
    image, depth, targets, sqrt_w, base, _ = prepare._prepare(
        image, depth, target, lens(), None, jaxdof.DefocusModel()
    )
    lay = layout._Spec(("f_number", "focus_distance"), (), 1).layout(base, depth)
    model = residual._Model(1, 3.0, (), jaxdof.DefocusModel(), n_live=2)
    args = (image, depth, targets, sqrt_w, lay)
    # Off the data, circles > 1/2 px: N e^0.3 and d_f - f times e^-0.2 (the point this test has
    # always used; given as a lens, since the focus coordinate is no longer log(d_f - f)).
    off = np.asarray(base).copy()
    off[:, 1] *= np.exp(0.3)
    off[:, 2] = off[:, 0] + (off[:, 2] - off[:, 0]) * np.exp(-0.2)
    y = model.pack(jnp.asarray(off), lay)
    jac = jax.jit(jax.jacfwd(model))
    plain = jax.jit(jax.jacfwd(model.residuals))
    np.testing.assert_allclose(jac(y, args), plain(y, args), rtol=1e-12, atol=1e-15)
    # float64 finite differences, eps 1e-4 on coordinates and pixel values of order 1 (jitted, so
    # that each derivative compiles once instead of running op by op).
    check_grads(jax.jit(lambda y: model(y, args)), (y,), order=1, modes=("fwd", "rev"))
    check_grads(
        jax.jit(lambda im: model(y, (im, *args[1:]))), (image,), order=1, modes=("fwd", "rev")
    )


# ------------------------------------------------------------------------------ forward models


class GaussianDefocus(jaxdof.AbstractForwardModel):
    """A forward model of a user's own: every pixel spread by a normalised Gaussian whose variance
    is `spread * (r^2 / 4 + 1 / 4)` px^2 (the thin lens's blur variance plus the pixel's), `r` the
    circle of confusion clamped to the window. `spread` is an array field: traced in the solve."""

    spread: jax.Array
    differentiable_in_lens: ClassVar[bool] = True

    def __call__(self, image, depth, lens, *, max_radius):
        image = jnp.asarray(image)
        h, w = image.shape
        r = jnp.minimum(jaxdof.coc_radius(depth, lens), max_radius)
        var = self.spread * (r * r / 4 + 0.25)
        k = int(np.ceil(max_radius))
        offsets = [(dy, dx) for dy in range(-k, k + 1) for dx in range(-k, k + 1)]
        d2 = jnp.asarray([dy * dy + dx * dx for dy, dx in offsets], image.dtype)
        weight = jnp.exp(-d2[:, None, None] / (2 * var[None]))
        sent = image[None] * weight / jnp.sum(weight, axis=0)[None]  # (offset, H, W)
        sent = jnp.pad(sent, ((0, 0), (k, k), (k, k)))
        # out[p] = sum_o sent_o[p - o]
        return sum(
            sent[i, k - dy : k - dy + h, k - dx : k - dx + w] for i, (dy, dx) in enumerate(offsets)
        )


@pytest.mark.parametrize(
    "options",
    [{}, dict(downsample=2), dict(footprint=True), dict(normalize=True)],
    ids=["plain", "downsample", "footprint", "normalize"],
)
def test_defocus_model_is_render(options):
    """DefocusModel computes its circles from the focus power (exact derivatives through focus at
    infinity) and is otherwise `render`: the same photo to float64 rounding, infinity included."""
    image, depth = (x[:12, :12] for x in scene())
    model = jaxdof.DefocusModel(**options)
    for d_f in (1.6, np.inf):
        lens_ = lens(focus_distance=d_f)
        got = np.asarray(model(image, depth, lens_, max_radius=3.0))
        want = np.asarray(render(image, depth, lens_, max_radius=3.0, **options))
        # A few rounding units of the circles (1e-16 relative) moved through the coverage.
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-13)


def test_user_forward_model_through_fit_lens():
    """A subclass of AbstractForwardModel runs through fit_lens as it is (no patching, no cache
    clearing): it is part of the compiled solve's key, so it and the default model each get their
    own compilation, on the same shapes, in any order."""
    image, depth = scene()
    model = GaussianDefocus(spread=jnp.asarray(1.0))
    true = lens()
    target = np.asarray(model(image, depth, true, max_radius=WINDOW))
    free = ("f_number", "focus_distance")
    kw = dict(free=free, max_radius=WINDOW, starts=1, pyramid=1)
    res = fit_lens(image, depth, target, wrong_init(free), model=model, **kw)
    assert bool(res.success), res.message
    err = rel_err(res.lens, true, ("f_number", "focus_distance"))
    assert max(err.values()) < 1e-4, err  # noise-free float64, as for the default model
    # The default model on the same photo: a compilation of its own, and a worse fit (a disc is
    # not a Gaussian).
    plain = fit_lens(image, depth, target, wrong_init(free), **EXACT, **kw)
    assert float(plain.loss) > 1e6 * float(res.loss) + 1e-12
    again = fit_lens(image, depth, target, wrong_init(free), model=model, **kw)
    for x, y in zip(jax.tree_util.tree_leaves(res), jax.tree_util.tree_leaves(again)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    # A model with another array value is the same compiled solve (arrays are traced).
    size = fit_solve.fit_starts._cached._cache_size()
    wider = GaussianDefocus(spread=jnp.asarray(1.5))
    fit_lens(
        image,
        depth,
        np.asarray(wider(image, depth, true, max_radius=WINDOW)),
        true,
        model=wider,
        **kw,
    )
    assert fit_solve.fit_starts._cached._cache_size() == size


def test_user_forward_model_gradients():
    """The user's render is an ordinary differentiable function: jax.grad with respect to a lens
    field and to the model's own array, against float64 finite differences."""
    image, depth = (x[:12, :12] for x in scene())
    probe = np.random.default_rng(3).uniform(size=image.shape)  # a sum alone is conserved

    def loss(model, n, d_f):
        out = model(image, depth, ThinLens(0.05, n, d_f, PITCH), max_radius=3.0)
        return jnp.sum(out * probe)

    model = GaussianDefocus(spread=jnp.asarray(1.0))
    n, d_f = jnp.asarray(2.0), jnp.asarray(1.7)
    g_n, g_d = jax.grad(loss, argnums=(1, 2))(model, n, d_f)
    assert np.isfinite(float(g_n)) and float(g_n) != 0 and float(g_d) != 0
    g_model = jax.grad(loss)(model, n, d_f)  # a pytree: the gradient is a GaussianDefocus
    assert isinstance(g_model, GaussianDefocus) and float(g_model.spread) != 0
    # float64 finite differences, eps 1e-4 on values of order 1 (jitted: one compilation each).
    check_grads(jax.jit(lambda n, d: loss(model, n, d)), (n, d_f), order=1, modes=("fwd", "rev"))
    spread = jax.jit(lambda s: loss(GaussianDefocus(spread=s), n, d_f))
    check_grads(spread, (jnp.asarray(1.0),), order=1, modes=("fwd", "rev"))


def test_model_and_its_options_conflict():
    """The default model's keywords belong to the model: both at once is a ValueError."""
    image, depth = scene()
    target = np.zeros((H, W))
    with pytest.raises(ValueError, match="given together with method='soft'"):
        fit_lens(image, depth, target, lens(), model=jaxdof.DefocusModel(), method="soft")
    with pytest.raises(ValueError, match="given together with footprint=True, downsample=1"):
        solve_lens(
            image,
            depth,
            target,
            lens(),
            max_radius=WINDOW,
            model=GaussianDefocus(spread=jnp.asarray(1.0)),
            footprint=True,
            downsample=1,
        )
    with pytest.raises(ValueError, match="cannot drive a fit"):
        fit_lens(image, depth, target, lens(), model=jaxdof.DefocusModel(method="hard"))
    with pytest.raises(ValueError, match="cannot drive a fit"):
        solve_lens(image, depth, target, lens(), max_radius=WINDOW, method="hard")
    assert not jaxdof.DefocusModel(method=jaxdof.Hard()).differentiable_in_lens
    assert jaxdof.DefocusModel(method=jaxdof.Soft(), downsample=2).photo_shape((8, 6, 3)) == (
        4,
        3,
        3,
    )
    with pytest.raises(ValueError, match="downsample"):
        jaxdof.DefocusModel(downsample=0)


def test_status_per_batch_element():
    """`solve_lens` under vmap over two scenes, one of which cannot be fitted (the depth plane sits
    at the init's focus distance: no blur, zero Jacobian): a status and a message per scene."""
    image, depth = scene()
    init = lens(f_number=2.5, focus_distance=1.7)
    flat = np.full((H, W), 1.7)  # every circle 0 at the init, and its derivatives too
    images = np.stack([image, image])
    depths = np.stack([depth, flat])
    targets = np.stack([np.asarray(render(image, depth, lens())), image])

    def fit(i, d, t):
        return solve_lens(i, d, t, init, max_radius=WINDOW)

    res = jax.vmap(fit)(images, depths, targets)
    np.testing.assert_array_equal(np.asarray(res.success), [True, False])
    np.testing.assert_array_equal(np.asarray(res.status == RESULTS.successful), [True, False])
    one = jax.tree_util.tree_map(lambda x: x[0], res)
    two = jax.tree_util.tree_map(lambda x: x[1], res)
    assert bool(one.status == RESULTS.successful) and one.message == "converged"
    assert bool(two.status == RESULTS.dead_zone) and "half a pixel" in two.message
    assert RESULTS[two.status] == two.message  # solve_lens adds no notes
    assert json.loads(json.dumps(two.to_dict()))["status"] == "dead_zone"
    np.testing.assert_allclose(float(one.lens.focus_distance), TRUE["focus_distance"], rtol=1e-4)
    with pytest.raises(ValueError, match="batch"):
        res.message  # noqa: B018  (one fit's words: index the batch first)


# ----------------------------------------------------------------------------------- pyramid
# The 32 x 32 scene with `pyramid=2` (one 16 x 16 level below full resolution): every pyramid fit
# below shares these compiled pieces.
PYRAMID = 2


def test_pyramid_equals_full_resolution_fit():
    """Coarse-to-fine ends with the full-resolution problem at the full tolerance: same lens,
    standard errors and loss as the single-level fit, to solver tolerance (float64)."""
    image, depth = scene()
    rng = np.random.default_rng(7)
    target = np.asarray(render(image, depth, lens())) + 0.01 * rng.standard_normal((H, W))
    init = wrong_init(("f_number", "focus_distance"))
    kw = dict(max_radius=WINDOW, starts=STARTS, **EXACT)
    flat = fit_lens(image, depth, target, init, pyramid=1, **kw)
    pyr = fit_lens(image, depth, target, init, pyramid=PYRAMID, **kw)
    assert bool(flat.success) and bool(pyr.success), (flat.message, pyr.message)
    assert (flat.levels, pyr.levels) == (1, PYRAMID)
    # Both stop when a step moves the log coordinates by under 1e-8 (relative, near the minimum
    # where LM converges fast): 1e-7 leaves a decade for the last step's size.
    for name in ("f_number", "focus_distance"):
        np.testing.assert_allclose(
            float(getattr(pyr.lens, name)), float(getattr(flat.lens, name)), rtol=1e-7
        )
        # The standard errors come from the Jacobian at those points: as close, to first order.
        np.testing.assert_allclose(float(pyr.stderr[name]), float(flat.stderr[name]), rtol=1e-6)
    # The loss is stationary at the minimum: second order in the 1e-8 step.
    np.testing.assert_allclose(float(pyr.loss), float(flat.loss), rtol=1e-10)


def test_pyramid_recovers_from_wrong_starts():
    """Noise-free recovery through the pyramid, from the usual wrong starts (2x in K, 30% in d_f)."""
    image, depth = scene()
    true = lens()
    target = render(image, depth, true)
    free = ("f_number", "focus_distance")
    res = fit_lens(
        image,
        depth,
        target,
        wrong_init(free),
        max_radius=WINDOW,
        starts=STARTS,
        pyramid=PYRAMID,
        **EXACT,
    )
    assert bool(res.success), res.message
    assert res.levels == PYRAMID
    err = rel_err(res.lens, true, ("focal_length", "f_number", "focus_distance"))
    assert max(err.values()) < 1e-4, err  # the float64 target


def test_pyramid_cannot_lead_the_init_astray():
    """A coarse level whose minimum lies in a wrong basin does not decide the fit.

    `tests/data/pyramid_trap.npz` is one trial of `fits/recover.py`'s cost study (the depth-steps
    scene at 96 x 96, a texture of 0.7 px grain, sigma = 0.01): at 48 x 48 all four starts converge
    to N = 17, d_f = 0.42 m, a minimum that does not exist at full resolution (there it moves to
    N = 14, d_f = 0.48 m with four times the loss of the truth's), while the init itself converges to
    the truth at full resolution. Before the init was also refined at full resolution, the default
    call returned that wrong lens with `success=True`.
    """
    data = np.load(TRAP, allow_pickle=False)
    image, target = data["image"].astype(np.float64), data["target"].astype(np.float64)
    depth = np.broadcast_to(data["depth_row"].astype(np.float64), image.shape)
    f, pitch = float(data["focal_length"]), float(data["pitch"])
    (n0, d0), (n_true, d_true) = data["init"], data["truth"]
    init = ThinLens(f, n0, d0, pitch)
    kw = dict(free=("f_number", "focus_distance"), max_radius=float(data["window"]), **EXACT)
    flat = fit_lens(image, depth, target, init, pyramid=1, starts=1, **kw)
    assert bool(flat.success) and abs(float(flat.lens.f_number) / n_true - 1) < 0.01
    for starts, pyramid in ((1, 2), (4, None)):  # from one start the pyramid must be asked for
        res = fit_lens(image, depth, target, init, starts=starts, pyramid=pyramid, **kw)
        assert res.levels == 2, res.levels
        assert bool(res.success), res.message
        # The full-resolution minimum, not the coarse level's wrong one (N = 14, d_f = 0.48).
        np.testing.assert_allclose(float(res.lens.f_number), float(flat.lens.f_number), rtol=1e-6)
        np.testing.assert_allclose(
            float(res.lens.focus_distance), float(flat.lens.focus_distance), rtol=1e-6
        )
        assert abs(float(res.lens.focus_distance) / d_true - 1) < 0.01


def test_pyramid_reproducible_and_warm():
    """A pyramid fit is bit-for-bit reproducible and a repeated call re-traces nothing."""
    image, depth = scene()
    rng = np.random.default_rng(3)
    target = np.asarray(render(image, depth, lens())) + 0.01 * rng.standard_normal((H, W))
    init = wrong_init(("f_number", "focus_distance"))
    kw = dict(max_radius=WINDOW, starts=STARTS, pyramid=PYRAMID, **EXACT)
    a, b = fit_twice_warm(image, depth, target, init, **kw)
    assert a.levels == b.levels == PYRAMID


def test_pyramid_levels_chosen_as_documented():
    """Automatic levels: halve while the shorter side stays >= 24 px and the init's largest circle
    >= 1 px; the 32 x 32 test scene stays at full resolution."""
    assert auto_levels((24, 24), 3.6) == 1  # 12 px would be under 24
    assert auto_levels((96, 96), 3.6) == 2  # 48 px, 1.8 px circles; 0.9 px would be too few
    assert auto_levels((96, 96), 8.0) == 3  # 48, 24 px: circles 4, 2 px
    assert auto_levels((192, 400), 10.0) == 4  # shorter side 192 -> 96 -> 48 -> 24
    assert auto_levels((47, 500), 50.0) == 1  # shorter side 47 -> 23
    assert auto_levels((512, 512), 0.9) == 1  # the init is in the dead zone already
    image, depth = scene()
    res = fit_lens(image, depth, render(image, depth, lens()), lens(), max_radius=WINDOW,
                   starts=STARTS, **EXACT)  # fmt: skip
    assert res.levels == 1
    # From one start the automatic choice is full resolution (the init is solved there anyway).
    image, depth = np.tile(image, (3, 3)), np.tile(depth, (3, 3))  # 96 x 96: two levels otherwise
    res = fit_lens(
        image, depth, render(image, depth, lens()), lens(), max_radius=WINDOW, starts=1, **EXACT
    )
    assert res.levels == 1


def test_pyramid_downsample():
    """One level down: box-averaged images, depth averaged in inverse depth (the signed circle is
    affine in 1/d, so the coarse pixel carries the mean circle), masked pixels mask their coarse
    pixel, pitch doubled."""
    rng = np.random.default_rng(0)
    image = rng.uniform(size=(5, 6, 2))  # odd height: the last row is dropped
    depth = rng.uniform(1.0, 4.0, size=(5, 6))
    depth[0, 0] = np.inf
    targets = rng.uniform(size=(2, 5, 6, 2))
    sqrt_w = np.ones((2, 5, 6, 2))
    sqrt_w[1, 3, 4, 0] = 0.0
    base = np.array([[0.05, 2.0, 1.6, 1e-4]] * 2)
    im, dep, tg, sw, b = strategies._downsample(image, depth, targets, sqrt_w, base)
    assert im.shape == (2, 3, 2) and dep.shape == (2, 3) and tg.shape == sw.shape == (2, 2, 3, 2)
    np.testing.assert_allclose(im[1, 2], image[2:4, 4:6].mean(axis=(0, 1)), rtol=1e-15)
    np.testing.assert_allclose(tg[0, 0, 1], targets[0, 0:2, 2:4].mean(axis=(0, 1)), rtol=1e-15)
    k, d_f = 5.0, 1.6  # signed circles K (1 - d_f / d): their mean is the coarse pixel's circle
    signed = k * (1 - d_f / depth[:4])
    mean = signed.reshape(2, 2, 3, 2).mean(axis=(1, 3))
    np.testing.assert_allclose(k * (1 - d_f / dep), mean, rtol=1e-13)
    assert np.isfinite(dep[0, 0])  # one pixel at infinity: 1/d averages to a finite depth
    assert np.isinf(
        strategies._downsample(image, np.full((5, 6), np.inf), targets, sqrt_w, base)[1]
    ).all()
    assert sw[1, 1, 2, 0] == 0.0 and sw[1, 1, 2, 1] == 1.0 and np.sum(sw == 0) == 1
    np.testing.assert_array_equal(b[:, 3], 2e-4)


@pytest.mark.parametrize(
    "shape, axes",
    [((9, 12), (0, 1)), ((9, 13, 3), (0, 1)), ((2, 10, 7, 3), (1, 2)), ((1, 10, 8, 1), (1, 2))],
)
def test_box2_is_the_mean_of_each_block(shape, axes):
    """The pyramid's 2 x 2 average, summed in a fixed order (`strategies._box2`): numpy's mean of
    each block to its last bit or one unit in it (numpy's own order is an implementation's)."""
    x = np.random.default_rng(4).uniform(0.1, 3.0, shape).astype(np.float32)
    a, b = axes
    h, w = shape[a] // 2 * 2, shape[b] // 2 * 2
    cut = x[(slice(None),) * a + (slice(0, h), slice(0, w))]
    view = cut.reshape(cut.shape[:a] + (h // 2, 2, w // 2, 2) + cut.shape[b + 1 :])
    box = strategies._box2(x, axes)
    assert box.dtype == np.float32
    np.testing.assert_array_max_ulp(box, view.mean(axis=(a + 1, a + 3)), maxulp=1)


@pytest.mark.parametrize(
    "pyramid, match",
    [
        (-1, "pyramid must be None"),
        (True, "pyramid must be None"),  # a bool is an int to Python, not a number of levels
        (4, r"use at most pyramid=3"),  # 32 -> 16 -> 8 -> 4 px: under the 8 px floor
    ],
)
def test_pyramid_bad_value(pyramid, match):
    # (A non-int never gets this far under the tests' type-checking hook; without it, fit_lens
    # raises the same ValueError for it.)
    image, depth = scene()
    with pytest.raises(ValueError, match=match):
        fit_lens(image, depth, image, lens(), pyramid=pyramid)


@pytest.mark.parametrize("pyramid", [1, PYRAMID], ids=["full-resolution", "pyramid"])
def test_near_far_ambiguity_is_reported(pyramid):
    """One fronto-parallel plane: a focus distance in front of it and one behind blur it alike.
    Through the pyramid, a near/far tie found on the coarse level is refined at full resolution
    too, and reported."""
    image, _ = scene()
    depth = np.full((H, W), 2.0)
    target = render(image, depth, lens(focus_distance=1.5))
    res = fit_lens(
        image,
        depth,
        target,
        lens(focus_distance=1.3),
        free=("focus_distance",),
        max_radius=WINDOW,
        starts=STARTS,
        pyramid=pyramid,
        **EXACT,
    )
    assert res.levels == pyramid
    # Both starts reach an exact fit, at different focus distances: never a silent pick.
    assert not bool(res.success) and bool(res.status == RESULTS.ambiguous)
    assert "another start converged" in res.message


# ------------------------------------------------------------------------ focus at infinity
# A scene from 2 to 12 m: a lens focused at infinity blurs every point (7.8 / d px at f/2), and a
# focus just short of the far end (11 m) is a lens whose near/far ambiguity is one-sided.
FAR_WINDOW = 8.0  # px: the largest circle below is 3.9 px (at 2 m, focused at infinity)


def far_scene(dtype=np.float64, seed=0):
    rng = np.random.default_rng(seed)
    image = rng.uniform(size=(H, W))
    depth = np.broadcast_to(2.0 + 10.0 * np.arange(W) / (W - 1), (H, W))
    return image.astype(dtype), np.array(depth, dtype)


def test_focus_coordinate_jacobian():
    """The focus coordinate `y` (`fcap / (d_f - f) = |y| + 1e-12`) passes through infinity at
    `y = 0`: the residual's Jacobian column there, at a tiny `y` and at an ordinary one is finite
    and matches float64 finite differences (one-sided at 0: `|y|` is folded with derivative +1),
    forward and reverse; in float32 it matches the float64 column."""

    def setup(dtype):
        image, depth = (x[:12, :12] for x in far_scene(dtype))
        target = np.asarray(
            render(image, depth, lens(dtype, focus_distance=np.inf), max_radius=4.0)
        )
        image, depth, targets, sqrt_w, base, _ = prepare._prepare(
            image, depth, target + 0.01, lens(dtype), None, jaxdof.DefocusModel()
        )
        lay = layout._Spec(("f_number", "focus_distance"), (), 1).layout(base, depth)
        model = residual._Model(1, 4.0, (), jaxdof.DefocusModel(), n_live=2)
        return model, (image, depth, targets, sqrt_w, lay), model.pack(base, lay)

    def column(dtype, y_focus):
        model, args, y = setup(dtype)
        y = y.at[2].set(y_focus)
        return np.asarray(jax.jit(jax.jacfwd(model))(y, args)[:, 2], np.float64), model, args, y

    model, args, _ = setup(np.float64)
    f = jax.jit(model)
    ref = {}
    for y_focus in (0.0, 1e-9, 0.3):
        col, _, _, y = column(np.float64, y_focus)
        # Second-order differences with h = 1e-5: truncation ~h^2 = 1e-10, rounding
        # ~1e-16 / h = 1e-11 (pixel values of order 1). One-sided at and next to 0, where a
        # central difference would straddle the fold (f(-h) = f(h)).
        h = 1e-5
        e = jnp.zeros_like(y).at[2].set(h)
        at = {k: np.asarray(f(y + k * e, args)) for k in (-1, 0, 1, 2)}
        if y_focus > 2 * h:
            fd = (at[1] - at[-1]) / (2 * h)
        else:
            fd = (-3 * at[0] + 4 * at[1] - at[2]) / (2 * h)
        assert np.all(np.isfinite(col)) and np.max(np.abs(col)) > 0.1
        # 1e-7 of the column's size: 1000 times the differences' error estimate above.
        np.testing.assert_allclose(col, fd, atol=1e-7 * np.max(np.abs(col)))
        grad = jax.jit(jax.grad(lambda y: jnp.sum(model(y, args) ** 2)))(y)
        assert np.all(np.isfinite(np.asarray(grad))) and float(grad[2]) != 0
        ref[y_focus] = col
    for y_focus, want in ref.items():
        col, model, args, y = column(np.float32, y_focus)
        assert y.dtype == jax.eval_shape(model, y, args).dtype == jnp.float32
        assert np.all(np.isfinite(col))
        # float32 renders to ~1e-6 of the pixel values; the column to ~1e-5 of its size.
        np.testing.assert_allclose(col, want, atol=1e-4 * np.max(np.abs(want)))


@pytest.mark.parametrize("true_focus", [np.inf, 11.0], ids=["infinity", "11m"])
@pytest.mark.parametrize("init_focus", [4.0, np.inf], ids=["from-4m", "from-infinity"])
def test_recovers_focus_at_and_near_infinity(true_focus, init_focus):
    """A lens focused at infinity, and one focused just short of the scene's far end, from
    starts on either side (4 m, inside the scene; infinity itself, with N off by 1.5x): the
    default fit recovers N and the focus (float64, noise-free). At infinity the focus power is
    0 to rounding, the focus distance has no finite standard error, and the message says so."""
    image, depth = far_scene()
    target = render(image, depth, lens(focus_distance=true_focus))
    init = lens(f_number=3.0, focus_distance=init_focus)
    res = fit_lens(image, depth, target, init, max_radius=FAR_WINDOW, **EXACT)
    assert bool(res.success), res.message
    assert abs(float(res.lens.f_number) / TRUE["f_number"] - 1) < 1e-4
    if np.isinf(true_focus):
        # The fit's farthest focus is 1e12 times the nearest depth: 5e-13 diopters.
        assert float(res.focus_power[0]) < 1e-12
        assert np.isinf(float(res.stderr["focus_distance"]))
        assert np.isfinite(float(res.focus_power_stderr))
        assert "consistent with focus at infinity" in res.message
    else:
        np.testing.assert_allclose(float(res.lens.focus_distance), true_focus, rtol=1e-4)
        assert np.isfinite(float(res.stderr["focus_distance"]))


def test_recovers_focus_at_infinity_float32():
    """The same in float32, from 30 m with N off by 1.5x (a start that used to stall at the
    bound with N = 2.84 and report convergence), with noise."""
    image, depth = far_scene(np.float32)
    rng = np.random.default_rng(5)
    clean = np.asarray(render(image, depth, lens(np.float32, focus_distance=np.inf)))
    target = (clean + 0.01 * rng.standard_normal(clean.shape)).astype(np.float32)
    init = lens(np.float32, f_number=3.0, focus_distance=30.0)
    res = fit_lens(image, depth, target, init, max_radius=FAR_WINDOW, **EXACT)
    assert bool(res.success), res.message
    se = float(res.stderr["f_number"])
    assert abs(float(res.lens.f_number) - TRUE["f_number"]) < 4 * se  # noise: within 4 sigma
    assert float(res.focus_power[0]) < 4 * float(res.focus_power_stderr)


def test_init_focused_at_infinity():
    """An init with focus_distance = inf: as a fixed field (fit N alone) and as the start of a
    free focus; the starts spread in diopters keep N where K = 0; max_circle handles it."""
    image, depth = far_scene()
    truth = lens(focus_distance=np.inf)
    target = render(image, depth, truth)
    init = lens(f_number=3.0, focus_distance=np.inf)
    res = fit_lens(image, depth, target, init, free=("f_number",), max_radius=FAR_WINDOW, **EXACT)
    assert bool(res.success), res.message
    assert np.isinf(float(res.lens.focus_distance))  # fixed: the init's
    np.testing.assert_allclose(float(res.lens.f_number), TRUE["f_number"], rtol=1e-6)
    rows = strategies.start_lenses(
        np.array([[0.05, 3.0, np.inf, PITCH]]), depth, free=("f_number", "focus_distance"), starts=4
    )
    assert np.all(np.isfinite(rows[1:])) and np.all(rows[:, 0, 1] == 3.0)
    assert np.isinf(rows[0, 0, 2])
    # Circles of a lens focused at infinity: f^2 / (2 N d p) at the nearest depth, 2 m.
    r = max_circle(np.array([0.05, 2.0, np.inf, PITCH]), depth)
    np.testing.assert_allclose(r, 0.05**2 / (2 * 2.0 * 2.0 * PITCH), rtol=1e-12)
    r = max_circle(np.array([0.05, 2.0, np.inf, PITCH]), np.array([np.inf]))
    assert r == 0.0


# ---------------------------------------------------------------------- no exception escapes


def test_focus_running_to_infinity_returns_a_result():
    """The issue's crash: depth up to 12 m, true focus 8 m, a start far beyond it with N off, the
    iterates running toward infinity (once an invalid lens and an EquinoxRuntimeError). Now
    infinity is a point of the coordinate: a result, and the lens recovered."""
    image, depth = far_scene()
    target = render(image, depth, lens(focus_distance=8.0))
    init = lens(f_number=4.0, focus_distance=60.0)
    res = fit_lens(image, depth, target, init, max_radius=FAR_WINDOW, **EXACT)
    assert bool(res.success), res.message
    np.testing.assert_allclose(float(res.lens.focus_distance), 8.0, rtol=1e-4)
    np.testing.assert_allclose(float(res.lens.f_number), TRUE["f_number"], rtol=1e-4)


class PickyDefocus(jaxdof.AbstractForwardModel):
    """The default render, with a run-time check that refuses f-numbers above `limit`."""

    limit: float = 3.0
    differentiable_in_lens: ClassVar[bool] = True

    def __call__(self, image, depth, lens, *, max_radius):
        out = render(image, depth, lens, max_radius=max_radius)
        return eqx.error_if(out, lens.f_number > self.limit, "PickyDefocus refuses f_number > 3")


def test_runtime_error_while_solving_becomes_a_failed_result():
    """A forward model whose run-time check (`equinox.error_if`) fires on an iterate: the fit
    returns a failed result naming the reason, not an exception."""
    image, depth = scene()
    target = render(image, depth, lens(f_number=3.5), max_radius=WINDOW)
    init = lens(f_number=2.5)
    res = fit_lens(
        image, depth, target, init, model=PickyDefocus(), max_radius=WINDOW, starts=STARTS
    )
    assert not bool(res.success) and bool(res.status == RESULTS.solver_failed)
    assert "EquinoxRuntimeError while solving: PickyDefocus refuses f_number > 3" in res.message
    assert float(res.lens.f_number) == 2.5  # the init: no solution to report
    assert np.isnan(float(res.stderr["f_number"])) and int(res.num_steps) == 0
    assert res.border == 6 and "FAILED" in res.summary()
    obj = json.loads(json.dumps(res.to_dict(), allow_nan=False))
    assert obj["status"] == "solver_failed" and obj["loss"] is None
    # Bad inputs are still refused before any solve.
    with pytest.raises(ValueError, match="border must be"):
        fit_lens(image, depth, target, init, model=PickyDefocus(), border="wide")


# ---------------------------------------------------------------------------- the verdict


def test_flat_start_does_not_decide_the_fit():
    """A start in the dead zone (every circle under half a pixel: zero Jacobian) "converges" at
    once; a better start that runs out of steps has the lower loss and is the one reported (its
    status says it did not converge), instead of a dead-zone refusal decided by the flat one."""
    image, depth = scene()
    target = render(image, depth, lens(), max_radius=WINDOW)
    # Starts N = 8 (circles up to 0.76 px), 16 (up to 0.38 px: flat), 4.
    init = lens(f_number=8.0)
    res = fit_lens(
        image,
        depth,
        target,
        init,
        free=("f_number",),
        max_radius=WINDOW,
        starts=3,
        max_steps=2,
        **EXACT,
    )
    assert bool(res.status == RESULTS.max_steps), res.message
    assert float(res.lens.f_number) < 8.0


def test_a_solution_in_a_flat_region_is_a_result_not_a_refusal():
    """A photo blurred by one circle everywhere, which no lens renders from a depth ramp: the
    best fit runs to a focus at the focal length (every circle about the same size), where the
    focus no longer moves the render. The photos determine the free set at the init lens and
    contradict the model at the solution (the adequacy test), so this is a failed fit
    (degenerate, said why), not the refusal a one-plane scene gets (nor a bracket focused at
    infinity, `test_degeneracy_wording_focus_at_infinity`, whose solution explains its photos).
    Seen on a ray-traced thin-poles scene fitted without the occlusion model
    (`fits/treatments.py`)."""
    rng = np.random.default_rng(0)
    image = rng.uniform(0.2, 0.8, (48, 48, 3))
    depth = np.broadcast_to(1.2 + 3.8 * np.arange(48) / 47, (48, 48))
    target = coc_filter(image, np.full((48, 48), 1.3))
    init = ThinLens(0.05, 6.0, 2.4, 1e-5)
    res = fit_lens(image, depth, target, init)
    assert not bool(res.success) and bool(res.status == RESULTS.degenerate)
    assert "though they do at the init lens" in res.message
    assert not bool(res.adequacy["adequate"])
    assert not np.isfinite(float(res.stderr["focus_distance"]))
    # one depth plane: undetermined everywhere, refused as before
    plane = np.full((48, 48), 2.0)
    with pytest.raises(ValueError, match="not determined by the data"):
        fit_lens(image, plane, render(image, plane, ThinLens(0.05, 4.0, 3.0, 1e-5)), init)


def test_degeneracy_wording_per_target_pair():
    """focal_length and f_number free per photo (not shared): each photo alone cannot separate
    them, and the message says so, naming the free set passed."""
    image, depth = scene()
    targets = [render(image, depth, lens(focus_distance=d)) for d in (1.4, 2.2)]
    inits = [lens(f_number=2.6, focus_distance=d) for d in (1.4, 2.2)]
    with pytest.raises(ValueError) as err:
        fit_lens(
            image, depth, targets, inits, free=("focal_length", "f_number"), max_radius=10.0,
            starts=STARTS, **EXACT,
        )  # fmt: skip
    text = str(err.value)
    assert "free set ('focal_length', 'f_number') (shared (), 2 target(s))" in text
    assert "cannot both be fitted from one photo (here each of the 2 photos has its own" in text


def test_degeneracy_wording_focus_at_infinity():
    """A focus bracket whose photos are all focused at infinity: there every circle is
    f^2 / (2 N d p), so f and N are not separated even with both shared; the message says why
    (and not that they cannot be fitted from one photo)."""
    image, depth = scene()
    targets = [render(image, depth, lens(focus_distance=np.inf))] * 2
    inits = [lens(focal_length=0.06, f_number=2.6, focus_distance=d) for d in (20.0, 40.0)]
    kw = dict(
        free=("focal_length", "f_number", "focus_distance"),
        shared=("focal_length", "f_number"),
        max_radius=10.0,
        starts=STARTS,
        **EXACT,
    )
    with pytest.raises(ValueError) as err:
        fit_lens(image, depth, targets, inits, **kw)
    text = str(err.value)
    assert "focus at infinity: the photos do not constrain focal_length, f_number there" in text
    assert "only through f^2 / N" in text and "from one photo" not in text
    res = fit_lens(image, depth, targets, inits, allow_degenerate=True, **kw)
    assert bool(res.status == RESULTS.degenerate) and "focus at infinity" in res.message


def test_degeneracy_wording_generic():
    """One depth plane: one circle size per photo cannot give both N and the focus; the message
    names the undetermined fields, and neither f/N-from-one-photo nor infinity."""
    image, _ = scene()
    depth = np.full((H, W), 2.0)
    target = render(image, depth, lens(focus_distance=1.5))
    with pytest.raises(ValueError) as err:
        fit_lens(
            image, depth, target, lens(f_number=2.2, focus_distance=1.45), max_radius=WINDOW,
            starts=1, **EXACT,
        )  # fmt: skip
    text = str(err.value)
    assert "the data do not determine f_number, focus_distance" in text
    assert "one depth plane" in text
    assert "from one photo" not in text and "focus at infinity" not in text
