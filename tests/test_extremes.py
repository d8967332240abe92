"""Finite where it should be, and a documented answer where it should not.

1. A grid of extreme but valid inputs (radii from 0 to 1e4 px, depths from just beyond the focal
   length to infinity, focus distances just beyond the focal length, f/1e4): values and gradients
   have no NaN or inf, in float64 and in float32.
2. Invalid inputs (NaN or negative depth, depth not beyond the focal length, focus distance not
   beyond the focal length, negative or NaN radius): `ValueError` for concrete values;
   under `jit`, NaN from the elementwise `coc_radius` / `signed_coc_radius`, and a run-time error
   (`equinox.error_if`) from `render` and `coc_filter`, also under `vmap` and `grad`.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdof import (
    ThinLens,
    circle_pixel_overlap,
    coc_filter,
    coc_radius,
    linearize_depth,
    render,
    signed_coc_radius,
)

from .helpers import METHODS, method_id


F = 0.05


def _finite(tree) -> bool:
    return all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves(tree))


# ---------------------------------------------------------------------------------------------
# 1. The grid of extremes


def _lens_grid(dtype):
    """(f, N, d_f, pitch) rows: ordinary, wide open, pinhole, focus just beyond f, far focus,
    phone-sized and telephoto lenses, tiny and huge pixels."""
    rows = [
        (F, 2.0, 3.0, 6e-6),
        (F, 0.7, 3.0, 6e-6),  # faster than any real lens: radii in the hundreds of px
        (F, 1e4, 3.0, 6e-6),  # nearly a pinhole: every radius < 1/2
        (F, 2.0, F * (1 + 1e-4), 6e-6),  # focus just beyond the focal length: K ~ 2e7 px
        (F, 2.0, 1e4, 6e-6),  # focused (almost) at infinity
        (0.004, 1.8, 0.5, 1e-6),  # phone camera
        (0.3, 4.0, 50.0, 4e-6),  # telephoto
        (F, 2.0, 3.0, 1e-4),  # huge pixels: radii < 1
    ]
    return {
        k: jnp.asarray(np.array(v), dtype)
        for k, v in zip(("focal_length", "f_number", "focus_distance", "pixel_pitch"), zip(*rows))
    }


def _depth_grid(dtype, f_min):
    """Depths from just beyond the longest focal length in the grid (0.3 m) to infinity, 3 x 4."""
    just_beyond = np.nextafter(np.asarray(f_min, dtype), np.asarray(np.inf, dtype))
    vals = [
        just_beyond,
        f_min * 1.001,
        0.5,
        1.0,
        3.0,
        3.0 * (1 + 1e-7),
        50.0,
        1e4,
        1e30,
        np.inf,
        2.0,
        7.0,
    ]
    return np.asarray(vals, dtype).reshape(3, 4)


def _grid_render_check(dtype):
    rng = np.random.default_rng(0)
    image = jnp.asarray(rng.uniform(size=(3, 4, 2)), dtype)
    lenses = _lens_grid(dtype)
    f_max = float(np.max(np.asarray(lenses["focal_length"])))
    # every depth must be beyond every lens's focal length: shift the grid past the longest one
    depth = jnp.asarray(_depth_grid(dtype, f_max), dtype)

    def loss(image, depth, fl, n, d_f, pitch):
        out = render(image, depth, ThinLens(fl, n, d_f, pitch), max_radius=4.0)
        return jnp.sum(out * out), out

    grad = jax.jit(
        jax.vmap(
            jax.grad(loss, argnums=tuple(range(6)), has_aux=True), in_axes=(None, None, 0, 0, 0, 0)
        )
    )
    grads, out = grad(image, depth, *lenses.values())
    assert out.dtype == dtype
    assert _finite(out), "render values"
    assert _finite(grads), "render gradients"
    # and the radii themselves, unclamped, are finite (inf depth included)
    r = jax.vmap(lambda fl, n, d_f, p: coc_radius(depth, ThinLens(fl, n, d_f, p)))(*lenses.values())
    assert _finite(r)
    assert float(jnp.max(r)) > 1e3  # the grid does reach enormous radii


def test_grid_render_float64():
    _grid_render_check(jnp.float64)


def test_grid_render_float32():
    _grid_render_check(jnp.float32)


RADII = [0.0, 1e-30, 1e-8, 1e-7, 0.3, 0.5, 0.5 + 1e-7, math.sqrt(0.5), 1.0, 7.5, 1e3, 1e4]


def _grid_overlap_check(dtype):
    o = np.arange(-2, 3, dtype=np.float64)
    dx, dy, r = (a.ravel() for a in np.meshgrid(o + 0.5, o, np.array(RADII), indexing="ij"))
    # add squares on the circle itself for the big radii: where float32 cancellation would bite
    dx = np.concatenate([dx, np.array(RADII) * math.sqrt(0.5)])
    dy = np.concatenate([dy, np.array(RADII) * math.sqrt(0.5)])
    r = np.concatenate([r, np.array(RADII)])
    args = tuple(jnp.asarray(a, dtype) for a in (dx, dy, r))
    area = circle_pixel_overlap(*args)
    g = jax.vmap(jax.grad(circle_pixel_overlap, argnums=(0, 1, 2)))(*args)
    assert area.dtype == dtype and _finite(area) and _finite(g)
    assert float(jnp.min(area)) >= 0 and float(jnp.max(area)) <= 1 + 1e-6  # 1e-6: float32 rounding


def test_grid_overlap_float64():
    _grid_overlap_check(jnp.float64)


def test_grid_overlap_float32():
    _grid_overlap_check(jnp.float32)


def _grid_filter_check(dtype, method):
    rng = np.random.default_rng(1)
    image = jnp.asarray(rng.uniform(size=(3, 4)), dtype)
    radius = jnp.asarray(np.array(RADII, np.float64).reshape(3, 4), dtype)

    def loss(image, radius):
        out = coc_filter(image, radius, method=method, max_radius=3.0)
        return jnp.sum(out * out), out

    (g_img, g_rad), out = jax.jit(jax.grad(loss, argnums=(0, 1), has_aux=True))(image, radius)
    assert out.dtype == dtype
    assert _finite(out) and _finite(g_img) and _finite(g_rad), method
    for shape in [(1, 1), (1, 5)]:  # degenerate frames
        g = jax.grad(lambda r, s=shape: loss(jnp.ones(s, dtype), r)[0])(jnp.full(shape, 2.2, dtype))
        assert _finite(g), (method, shape)


@pytest.mark.parametrize("method", METHODS, ids=method_id)
def test_grid_filter_float64(method):
    _grid_filter_check(jnp.float64, method)


@pytest.mark.parametrize("method", METHODS, ids=method_id)
def test_grid_filter_float32(method):
    _grid_filter_check(jnp.float32, method)


def test_linearize_depth_finite_at_the_ends():
    z = jnp.asarray([0.0, 1e-7, 0.5, 1 - 1e-7, 1.0], jnp.float32)
    g = jax.vmap(jax.grad(linearize_depth, argnums=(0, 1, 2)), in_axes=(0, None, None))(
        z, jnp.float32(0.1), jnp.float32(1000.0)
    )
    out = linearize_depth(z, 0.1, 1000.0)
    assert out.dtype == jnp.float32 and all(x.dtype == jnp.float32 for x in g)
    assert _finite(out) and _finite(g)


# ---------------------------------------------------------------------------------------------
# 2. Invalid inputs

LENS = ThinLens(F, 2.0, 3.0, 6e-6)
BAD_DEPTHS = {
    "nan": np.nan,
    "negative": -1.0,
    "zero": 0.0,
    "inside_f": 0.01,
    "at_f": F,
    "minus_inf": -np.inf,
}


@pytest.mark.parametrize("bad", list(BAD_DEPTHS))
def test_concrete_invalid_depth_raises(bad):
    depth = np.full((3, 4), 2.0)
    depth[1, 2] = BAD_DEPTHS[bad]
    for fn in (coc_radius, signed_coc_radius):
        with pytest.raises(ValueError, match="beyond the focal length"):
            fn(depth, LENS)
    # `render` names a hole (no data: NaN, 0, negative) as such, with the option that fills it
    hole = bad in ("nan", "negative", "zero", "minus_inf")
    match = "holes .NaN, 0 or negative: no data.; pass fill_holes=True" if hole else "beyond the"
    with pytest.raises(ValueError, match=match):
        render(np.ones((3, 4)), depth, LENS)


def test_traced_invalid_depth_gives_nan_from_coc_radius():
    """Elementwise functions cannot raise under jit: invalid entries are NaN, valid ones exact,
    and the derivative at an invalid entry is 0 (a masked loss keeps finite gradients)."""
    d = jnp.asarray([np.nan, -1.0, 0.0, 0.01, F, -np.inf, 2.0, np.inf])
    bad = np.arange(8) < 6
    for fn in (coc_radius, signed_coc_radius):
        r = np.asarray(jax.jit(fn)(d, LENS))
        assert np.all(np.isnan(r[bad])) and np.all(np.isfinite(r[~bad]))
        np.testing.assert_array_equal(r[~bad], np.asarray(fn(d[~bad], LENS)))
        g = jax.grad(lambda d, fn=fn: jnp.sum(jnp.where(bad, 0.0, fn(d, LENS))))(d)
        assert np.all(np.isfinite(np.asarray(g)))
        assert np.all(np.asarray(g)[bad] == 0.0)


@pytest.mark.parametrize(
    "field,value",
    [("focus_distance", 0.04), ("focus_distance", F), ("f_number", -2.0), ("pixel_pitch", 0.0)],
)
def test_traced_invalid_lens(field, value):
    kwargs = dict(focal_length=F, f_number=2.0, focus_distance=3.0, pixel_pitch=6e-6)

    def make(v):
        return ThinLens(**{**kwargs, field: v})

    with pytest.raises(ValueError, match=field):
        make(value)  # concrete: the lens refuses to exist
    r = jax.jit(lambda v: coc_radius(jnp.asarray([1.0, 3.0, 5.0]), make(v)))(value)
    assert np.all(np.isnan(np.asarray(r)))  # traced: every radius is NaN
    rend = jax.jit(
        lambda v: render(jnp.ones((3, 4)), jnp.full((3, 4), 2.0), make(v), max_radius=2.0)
    )
    with pytest.raises((RuntimeError, ValueError), match="focus_distance must exceed focal_length"):
        jax.block_until_ready(rend(value))
    assert np.all(np.isfinite(np.asarray(rend(3.0 if field == "focus_distance" else 2e-6))))


# Under `jax.jit` JAX re-raises the callback's error: a `JaxRuntimeError` (a RuntimeError) or, on
# its fast dispatch path, a `ValueError`; the message is ours either way.
RUNTIME = (RuntimeError, ValueError)


@pytest.mark.parametrize("bad", list(BAD_DEPTHS))
def test_jit_render_raises_at_run_time(bad):
    image = jnp.ones((3, 4))
    f = jax.jit(lambda d: render(image, d, LENS, max_radius=2.0))
    good = jnp.full((3, 4), 2.0)
    assert _finite(f(good))
    with pytest.raises(RUNTIME, match="beyond the focal length"):
        jax.block_until_ready(f(good.at[1, 2].set(BAD_DEPTHS[bad])))
    assert _finite(f(good))  # the compiled function is still usable afterwards


def test_jit_render_error_under_vmap_grad_and_filter_jit():
    image = jnp.ones((3, 4))
    good = jnp.full((3, 4), 2.0)
    bad = good.at[0, 0].set(0.01)
    f = lambda d: render(image, d, LENS, max_radius=2.0)
    batch = jax.jit(jax.vmap(f))
    assert batch(jnp.stack([good, 2 * good])).shape == (2, 3, 4)
    with pytest.raises(RUNTIME, match="beyond the focal length"):  # one bad element is enough
        jax.block_until_ready(batch(jnp.stack([good, bad])))
    loss = jax.jit(jax.grad(lambda d: jnp.sum(f(d) ** 2)))
    assert _finite(loss(good))
    with pytest.raises(RUNTIME, match="beyond the focal length"):  # raised in the forward pass
        jax.block_until_ready(loss(bad))
    fwd = jax.jit(lambda d: jax.jvp(f, (d,), (jnp.ones_like(d),))[1])
    with pytest.raises(RUNTIME, match="beyond the focal length"):
        jax.block_until_ready(fwd(bad))
    with pytest.raises(eqx.EquinoxRuntimeError, match="beyond the focal length"):
        jax.block_until_ready(eqx.filter_jit(f)(bad))


def test_jit_float32_render_raises():
    lens = ThinLens(*(np.float32(x) for x in (F, 2.0, 3.0, 6e-6)))
    f = jax.jit(lambda d: render(jnp.ones((3, 4), jnp.float32), d, lens, max_radius=2.0))
    assert f(jnp.full((3, 4), 2.0, jnp.float32)).dtype == jnp.float32
    with pytest.raises(RUNTIME, match="beyond the focal length"):
        jax.block_until_ready(f(jnp.full((3, 4), jnp.nan, jnp.float32)))


@pytest.mark.parametrize("method", METHODS, ids=method_id)
@pytest.mark.parametrize("bad", [-1.0, np.nan])
def test_invalid_radius(method, bad):
    radius = np.full((3, 4), 1.5)
    radius[2, 1] = bad
    with pytest.raises(ValueError, match=">= 0"):
        coc_filter(np.ones((3, 4)), radius, method=method, max_radius=2.0)
    f = jax.jit(lambda r: coc_filter(jnp.ones((3, 4)), r, method=method, max_radius=2.0))
    with pytest.raises(RUNTIME, match="radius must be >= 0"):
        jax.block_until_ready(f(jnp.asarray(radius)))


def test_nan_radius_poisons_rather_than_passing_for_sharp():
    """Under jit with the run-time check switched off, a NaN radius must not act as r <= 1/2."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent(
        """
        import jax, jax.numpy as jnp, numpy as np, jaxdof
        r = jnp.full((5, 6), 1.0).at[2, 3].set(jnp.nan)
        out = jax.jit(lambda i, r: jaxdof.coc_filter(i, r, max_radius=2.0))(jnp.ones((5, 6)), r)
        bad = np.isnan(np.asarray(out))
        assert bad[2, 3] and bad[1, 2] and not bad[0, 0], bad
        print("ok")
        """
    )
    env = {**__import__("os").environ, "EQX_ON_ERROR": "off"}
    res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert res.returncode == 0 and "ok" in res.stdout, res.stderr[-2000:]
