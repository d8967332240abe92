"""The row-span path of the soft filter (`jaxdof/_filters/spans.py`) against the dense gather."""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxdof
from jaxdof._filters.soft import soft_filter
from jaxdof._filters.spans import (
    TAPS,
    crossover_for,
    exact_soft_filter,
    in_jacobian,
    spans_filter,
)
from jaxdof.internal import tuning

from .helpers import scatter_reference, step_scene


SPANS_MIN_RADIUS = tuning.SPANS_MIN_RADIUS


@functools.partial(jax.jit, static_argnames="max_radius")
def fast(image, radius, *, max_radius):
    """The span path, jitted: one compile per shape instead of an eager scan per call."""
    return spans_filter(image, radius, max_radius=max_radius)


@functools.partial(jax.jit, static_argnames="max_radius")
def dense(image, radius, *, max_radius):
    return soft_filter(image, radius, max_radius=max_radius)


def special_radii(shape, max_radius, seed):
    """Random radii in [0, R] salted with the values where the geometry switches."""
    rng = np.random.default_rng(seed)
    r = rng.uniform(0, max_radius, shape)
    salt = [0.0, 0.25, 0.5, 0.5 + 1e-12, 0.6, math.sqrt(0.5), 1.0, 1.5, 2.0, 2.5, 3.0]
    salt += [max_radius, max_radius - 0.5, math.floor(max_radius), max_radius / math.sqrt(2)]
    flat = r.reshape(-1)
    idx = rng.choice(flat.size, size=len(salt), replace=False)
    flat[idx] = np.minimum(salt, max_radius)
    return flat.reshape(shape)


def test_two_taps_cover_the_boundary():
    """The module's claim: past a side row's (cap column's) start, at most 2 pixels are partial.

    Exhaustive over the rows of every radius on a fine grid up to 400 px, in float64 numpy,
    written independently of the module: pixel (j, k) is touched when its nearest point is inside
    the circle and fully covered when its farthest corner is.
    """
    radii = np.concatenate(
        [np.linspace(0.5, 60, 6000), np.linspace(60, 400, 1500), np.arange(1, 801) / 2 + 1e-9]
    )
    worst = 0
    for r in radii:
        n = int(r) + 3
        k = np.arange(n)[:, None]
        j = np.arange(n)[None, :]
        full = (j + 0.5) ** 2 + (k + 0.5) ** 2 <= r * r
        touched = np.maximum(j - 0.5, 0) ** 2 + np.maximum(k - 0.5, 0) ** 2 < r * r
        a = np.where(full.any(1), (full * j).max(1), -1)  # last full pixel of row k
        b = np.where(touched.any(1), (touched * j).max(1), -1)  # last touched pixel of row k
        ks = k[:, 0]
        side = b - np.maximum(a + 1, ks) + 1  # side row k starts at max(a + 1, k)
        cap = b - np.maximum(a + 1, ks + 1) + 1  # cap column k starts at max(a + 1, k + 1)
        worst = max(worst, side.max(), cap.max())
    assert worst == TAPS


@pytest.mark.parametrize("max_radius", [0.7, 2.5, 9.0])
def test_equals_dense_gather(max_radius):
    rng = np.random.default_rng(1)
    image = jnp.asarray(rng.uniform(size=(19, 23, 2)))
    radius = jnp.asarray(special_radii((19, 23), max_radius, seed=2))
    got = fast(image, radius, max_radius=max_radius)
    want = dense(image, radius, max_radius=max_radius)
    # float64: both sum the same exact areas in a different order, a few rounding units apart
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_equals_scatter_reference_on_depth_steps():
    image, radius = step_scene(16, 18, seed=3)  # radii 0 .. 20, with steps
    max_radius = 6.5
    radius = np.minimum(radius, max_radius)  # the reference does not clamp
    got = fast(jnp.asarray(image), jnp.asarray(radius), max_radius=max_radius)
    want = scatter_reference(image, radius, jaxdof.circle_pixel_overlap)
    # issue 2's float64 goal: 1e-10 of the image's range (here [0, 1])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-10)


def test_identity_for_sharp_pixels():
    rng = np.random.default_rng(4)
    image = jnp.asarray(rng.uniform(size=(9, 11, 3)))
    radius = jnp.asarray(rng.uniform(0, 0.5, (9, 11)))
    for max_radius in (0.5, 3.0):  # a window of one pixel, and a wide one with nothing to spread
        got = fast(image, radius, max_radius=max_radius)
        np.testing.assert_array_equal(got, image)


@pytest.mark.parametrize("max_radius", [3.0, 12.5])
def test_conserves_energy(max_radius):
    """Light placed at least `max_radius + 1` px from the border stays in the frame, all of it."""
    rng = np.random.default_rng(5)
    n, margin = 40, math.ceil(max_radius) + 1
    image = np.zeros((n, n, 1))
    image[margin:-margin, margin:-margin] = rng.uniform(size=(n - 2 * margin, n - 2 * margin, 1))
    radius = special_radii((n, n), max_radius, seed=6)
    out = fast(jnp.asarray(image), jnp.asarray(radius), max_radius=max_radius)
    # float64 sums of ~1e3 terms of size <= 1
    np.testing.assert_allclose(float(out.sum()), image.sum(), rtol=1e-12)


def test_float32_large_radius():
    """R = 40 on 96 x 96 in float32 against the float64 dense gather: issue 2's 2e-5 of the range."""
    rng = np.random.default_rng(7)
    image = rng.uniform(size=(96, 96, 1))
    radius = special_radii((96, 96), 40.0, seed=8)
    want = dense(jnp.asarray(image), jnp.asarray(radius), max_radius=40.0)
    got = fast(jnp.asarray(image, jnp.float32), jnp.asarray(radius, jnp.float32), max_radius=40.0)
    assert got.dtype == jnp.float32
    err = float(jnp.max(jnp.abs(got.astype(jnp.float64) - want)))
    assert err <= 2e-5 * (image.max() - image.min()), err


def test_float32_mode_matches_dense(tmp_path):
    """With x64 off (every array float32, int32 indices), the two paths agree to float32.

    The session runs with x64 on, so this runs in a subprocess under JAX's default config (with
    the session's strict dtype and rank promotion and jaxtyping checks), and prints the largest
    difference."""
    import os
    import subprocess
    import sys
    import textwrap

    rng = np.random.default_rng(9)
    image = rng.uniform(size=(40, 44, 3)).astype(np.float32)
    radius = special_radii((40, 44), 17.0, seed=10).astype(np.float32)
    np.savez(tmp_path / "scene.npz", image=image, radius=radius)
    code = textwrap.dedent(
        """
        import sys
        from jaxtyping import install_import_hook
        with install_import_hook("jaxdof", "beartype.beartype"):
            import jax, jax.numpy as jnp, numpy as np
            from jaxdof._filters.soft import soft_filter
            from jaxdof._filters.spans import spans_filter
        assert not jax.config.jax_enable_x64 and jnp.arange(2).dtype == jnp.int32
        data = np.load(sys.argv[1])
        image, radius = jnp.asarray(data["image"]), jnp.asarray(data["radius"])
        assert image.dtype == radius.dtype == jnp.float32
        run = lambda f: jax.jit(f, static_argnames="max_radius")(image, radius, max_radius=17.0)
        got, want = run(spans_filter), run(soft_filter)
        assert got.dtype == want.dtype == jnp.float32, (got.dtype, want.dtype)
        print("max_abs_diff", float(jnp.max(jnp.abs(got - want))))
        """
    )
    env = {
        **os.environ,
        "JAX_ENABLE_X64": "0",
        "JAX_NUMPY_DTYPE_PROMOTION": "strict",
        "JAX_NUMPY_RANK_PROMOTION": "raise",
    }
    res = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path / "scene.npz")],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-4000:]
    name, err = res.stdout.split()[-2:]
    assert name == "max_abs_diff", res.stdout[-2000:]
    # both float32: each within a few 1e-6 of the exact sum (issue 2's bound is 2e-5)
    assert float(err) <= 2e-5, err


def _weighted_sum(filt):
    return lambda w, i, r: jnp.sum(w * filt(i, r, max_radius=3.7))


# jitted once for both gradient tests (same shapes, same static max_radius)
_grad_spans = jax.jit(jax.grad(_weighted_sum(spans_filter), argnums=(1, 2)))
_grad_dense = jax.jit(jax.grad(_weighted_sum(soft_filter), argnums=(1, 2)))


def test_gradients():
    """Forward and reverse, float64, w.r.t. image and radius, radii inside (0.5, R)."""
    rng = np.random.default_rng(11)
    image = jnp.asarray(rng.uniform(size=(7, 8, 2)))
    # strictly inside (1/2, R): the clamp and the dead zone are kinks of the model itself
    radius = jnp.asarray(rng.uniform(0.6, 3.6, (7, 8)))
    weights = jnp.asarray(rng.normal(size=(7, 8, 2)))
    f = jax.jit(functools.partial(_weighted_sum(spans_filter), weights))
    # eps 1e-4 in float64: central differences accurate to ~1e-8, far inside the default tolerance
    check_grads(f, (image, radius), order=1, modes=("fwd", "rev"), eps=1e-4)
    # and the same numbers as the dense gather's analytic derivative
    for a, b in zip(_grad_spans(weights, image, radius), _grad_dense(weights, image, radius)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)


def test_gradients_finite_at_the_extremes():
    """r = 0, r = 1/2 (the identity's edge), r = R (the clamp) and the switching radii."""
    rng = np.random.default_rng(12)
    image = jnp.asarray(rng.uniform(size=(7, 8, 2)))
    weights = jnp.asarray(rng.normal(size=(7, 8, 2)))
    radius = jnp.asarray(special_radii((7, 8), 3.7, seed=12))
    spans_grads = _grad_spans(weights, image, radius)
    for a, b in zip(spans_grads, _grad_dense(weights, image, radius)):
        assert bool(jnp.all(jnp.isfinite(a)))
        # one-sided kinks agree too: both paths use the same tap derivative
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)


def test_jit_and_vmap_equal_eager():
    rng = np.random.default_rng(13)
    images = jnp.asarray(rng.uniform(size=(2, 12, 13, 3)))
    radii = jnp.asarray(rng.uniform(0, 5, (2, 12, 13)))
    f = lambda i, r: spans_filter(i, r, max_radius=5.0)  # noqa: E731
    eager = f(images[1], radii[1])
    jitted = jnp.stack([jax.jit(f)(i, r) for i, r in zip(images, radii)])
    # jit and eager run the same operations; XLA may fuse them differently (a few ulp)
    np.testing.assert_allclose(jitted[1], eager, rtol=0, atol=1e-14)
    np.testing.assert_allclose(jax.jit(jax.vmap(f))(images, radii), jitted, rtol=0, atol=1e-14)


def _takes_spans(f, *args) -> bool:
    """Whether `f` runs the row-span path: only it builds its rows by a cumulative sum."""
    return "cumsum" in str(jax.make_jaxpr(f)(*args))


def test_coc_filter_dispatch():
    """`Soft()` takes the span path from `SPANS_MIN_RADIUS` on, the dense gather below."""
    rng = np.random.default_rng(14)
    image = rng.uniform(size=(10, 10))
    radius = rng.uniform(0, 3, (10, 10))
    assert _takes_spans(
        lambda i, r: exact_soft_filter(i[..., None], r, max_radius=5.0, path="spans"), image, radius
    )
    assert not _takes_spans(
        lambda i, r: exact_soft_filter(i[..., None], r, max_radius=5.0, path="dense"), image, radius
    )
    below = max(SPANS_MIN_RADIUS - 1, 0.0)
    assert not _takes_spans(lambda i, r: jaxdof.coc_filter(i, r, max_radius=below), image, radius)
    f = lambda i, r: jaxdof.coc_filter(i, r, max_radius=SPANS_MIN_RADIUS)
    assert _takes_spans(f, image, radius)
    with tuning.override(SPANS_MIN_RADIUS=4.0):  # the rule, not a fixed radius, decides
        assert _takes_spans(lambda i, r: jaxdof.coc_filter(i, r, max_radius=5.0), image, radius)
    out = jax.jit(f)(image, radius)
    want = dense(jnp.asarray(image)[..., None], jnp.asarray(radius), max_radius=SPANS_MIN_RADIUS)
    want = want[..., 0]
    np.testing.assert_allclose(out, want, rtol=0, atol=1e-12)


def test_forced_paths_and_bad_path():
    rng = np.random.default_rng(15)
    image = jnp.asarray(rng.uniform(size=(8, 9, 1)))
    radius = jnp.asarray(rng.uniform(0, 2, (8, 9)))
    f = jax.jit(exact_soft_filter, static_argnames=("max_radius", "path"))
    np.testing.assert_allclose(
        f(image, radius, max_radius=2.0, path="dense"),
        f(image, radius, max_radius=2.0, path="spans"),
        rtol=0,
        atol=1e-13,  # float64, the same exact areas summed in another order
    )
    with pytest.raises(ValueError, match="path="):
        exact_soft_filter(image, radius, max_radius=2.0, path="fast")


def test_dispatch_inside_a_jacobian():
    """Traced `in_jacobian` (a fit's residual Jacobian), the soft filter takes spans from
    `SPANS_MIN_RADIUS_JACOBIAN` for the image's channels on; outside, the forward crossover."""
    rng = np.random.default_rng(16)
    radius = rng.uniform(0, 3, (10, 10))
    table = tuning.SPANS_MIN_RADIUS_JACOBIAN
    for channels in (1, 3):
        image = rng.uniform(size=(10, 10, channels))
        at = crossover_for(channels, table)
        f = lambda i, r, w: exact_soft_filter(i, r, max_radius=w)  # noqa: E731
        for window in (at - 1, at):
            with in_jacobian():
                inside = _takes_spans(functools.partial(f, w=window), image, radius)
            outside = _takes_spans(functools.partial(f, w=window), image, radius)
            assert inside == (window >= at)
            assert outside == (window >= SPANS_MIN_RADIUS)
    assert crossover_for(1, table) < SPANS_MIN_RADIUS  # spans win there far earlier


def test_fit_residual_jacobian_takes_spans_and_matches_dense():
    """The fit's residual (`_fit.residual._Model`, its Jacobian-building JVP rule) on a grey
    photo with a window past the Jacobian's crossover: its Jacobian comes from the spans path and
    equals the dense gather's to rounding (float64)."""
    from jaxdof._fit.layout import _Spec
    from jaxdof._fit.residual import _Model

    window = float(crossover_for(1, tuning.SPANS_MIN_RADIUS_JACOBIAN))
    assert window < SPANS_MIN_RADIUS
    image = jnp.asarray(step_scene(40, 40)[0][..., :1])
    depth = jnp.asarray(np.linspace(1.0, 10.0, 40)[None, :].repeat(40, 0))
    base = np.array([[0.05, 2.0, 1.5, 4e-5]])  # circles up to ~9 px
    spec = _Spec(("focus_distance", "f_number"), (), 1)
    layout = spec.layout(base, np.asarray(depth))
    targets = jnp.zeros((1, *image.shape), jnp.float64)
    args = (image, depth, targets, jnp.ones_like(targets), layout)
    model = _Model(1, window, (), jaxdof.DefocusModel(checks=False), len(spec.used))
    y = jnp.asarray(model.pack(base, layout))
    jac = jax.jit(jax.jacfwd(model))
    assert "cumsum" in str(jax.make_jaxpr(jax.jacfwd(model))(y, args))
    with tuning.override(SPANS_MIN_RADIUS_JACOBIAN={math.inf: math.inf}):
        dense_jac = jax.jit(jax.jacfwd(model))(y, args)
        assert "cumsum" not in str(jax.make_jaxpr(jax.jacfwd(model))(y, args))
    out = jac(y, args)
    assert np.max(np.abs(out)) > 0
    np.testing.assert_allclose(out, dense_jac, rtol=0, atol=1e-12 * float(np.max(np.abs(out))))
