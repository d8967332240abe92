import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from jaxdof import ThinLens, coc_radius, linearize_depth, signed_coc_radius
from jaxdof._lens import _error_if_invalid, _signed_coc_radius_from_power


LENS = ThinLens(0.05, 2.0, 3.0, 36e-3 / 6000)


def test_formula_and_seed_form():
    f, n, d_f, p = 0.05, 2.0, 3.0, 36e-3 / 6000
    d = np.array([0.5, 1.0, 2.9, 3.0, 3.1, 10.0, 1e6])
    expected = f * f / (2 * n * (d_f - f)) * np.abs(1 - d_f / d) / p
    np.testing.assert_allclose(np.asarray(coc_radius(d, LENS)), expected, rtol=1e-13)
    # The seeds' form a |s (1/f - 1/d) - 1| with a = f / 2N and the sensor at s = f d_f / (d_f - f).
    a, s = f / (2 * n), f * d_f / (d_f - f)
    np.testing.assert_allclose(
        np.asarray(coc_radius(d, LENS)),
        a * np.abs(s * (1 / f - 1 / d) - 1) / p,
        rtol=1e-12,
        atol=1e-10,
    )  # atol: the seed form rounds to ~5e-13 px at the focus plane, where ours is exactly 0


def test_sign_focus_and_infinity():
    r = signed_coc_radius(jnp.array([1.0, 3.0, 10.0, jnp.inf]), LENS)
    assert r[0] < 0 and r[1] == 0 and r[2] > 0
    assert float(r[3]) == pytest.approx(float(LENS.blur_scale))
    g = jax.grad(lambda d: coc_radius(d, LENS))(jnp.inf)
    assert g == 0.0
    # At the focus plane |.| has a kink; the derivative is the finite subgradient 0.
    assert float(jax.grad(lambda d: coc_radius(d, LENS))(3.0)) == 0.0


def test_blur_grows_with_defocus_in_diopters():
    d = 1 / np.linspace(1 / 3.0 - 0.3, 1 / 3.0 + 0.3, 50)  # symmetric in diopters about the focus
    r = np.asarray(coc_radius(jnp.asarray(d), LENS))
    dio = np.abs(1 / d - 1 / 3.0)
    assert np.all(np.diff(r[np.argsort(dio)]) >= -1e-12)


def test_grads_every_field():
    # Pixel pitch in micrometres so that one finite-difference step suits every argument.
    def f(depth, fl, n, d_f, pitch_um):
        return coc_radius(depth, ThinLens(fl, n, d_f, pitch_um * 1e-6))

    args = tuple(jnp.asarray(v) for v in (1.7, 0.05, 2.0, 3.0, 6.0))
    check_grads(f, args, order=2, modes=("fwd", "rev"), eps=1e-6)


def test_from_sensor():
    lens = ThinLens.from_sensor(0.05, 2.0, 3.0, sensor_width=0.036, image_width=6000)
    assert float(lens.pixel_pitch) == pytest.approx(6e-6)
    with pytest.raises(ValueError, match="image_width"):
        ThinLens.from_sensor(0.05, 2.0, 3.0, sensor_width=0.036, image_width=0)


_FIELDS = ("focal_length", "f_number", "focus_distance", "pixel_pitch")
_BAD = [
    (field, bad)
    for field in _FIELDS
    for bad in (0.0, -1.0, math.nan, math.inf, -math.inf)
    if not (field == "focus_distance" and bad == math.inf)  # focused at infinity: valid
]


@pytest.mark.parametrize("field,bad", _BAD)
def test_invalid_fields_named(field, bad):
    kwargs = dict(focal_length=0.05, f_number=2.0, focus_distance=3.0, pixel_pitch=6e-6)
    kwargs[field] = bad
    with pytest.raises(ValueError, match=field):
        ThinLens(**kwargs)


def test_focus_inside_focal_length():
    with pytest.raises(ValueError, match="focus_distance must exceed focal_length"):
        ThinLens(0.05, 2.0, 0.04, 6e-6)


def test_lens_is_a_pytree_under_jit_and_vmap():
    lenses = jax.vmap(lambda d_f: ThinLens(0.05, 2.0, d_f, 6e-6))(jnp.array([2.0, 3.0]))
    r = jax.jit(jax.vmap(coc_radius, in_axes=(None, 0)))(jnp.array([1.0, 5.0]), lenses)
    assert r.shape == (2, 2)


def _glu_perspective(fovy_deg, aspect, near, far):
    f = 1 / math.tan(math.radians(fovy_deg) / 2)
    return np.array(
        [
            [f / aspect, 0, 0, 0],
            [0, f, 0, 0],
            [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)],
            [0, 0, -1, 0],
        ]
    )


def test_linearize_depth_inverts_glu_perspective():
    near, far = 0.1, 100.0
    proj = _glu_perspective(60.0, 4 / 3, near, far)
    z_true = np.array([0.1, 0.25, 1.0, 3.7, 42.0, 100.0])
    eye = np.stack(
        [0.3 * z_true, -0.2 * z_true, -z_true, np.ones_like(z_true)]
    )  # camera looks down -z
    clip = proj @ eye
    window_z = (clip[2] / clip[3] + 1) / 2  # glDepthRange(0, 1)
    np.testing.assert_allclose(np.asarray(linearize_depth(window_z, near, far)), z_true, rtol=1e-9)


# ---------------------------------------------------------------------------------------------
# Focus at infinity, and the accuracy of the radius at every focus distance

F, N, P = 0.05, 2.0, 6e-6
C = F * F / (2 * N * P)  # f^2 / (2 N p): the blur in px of a point at 1 m, focused at infinity
DEPTHS = np.array([0.0500001, 0.06, 0.5, 1.0, 3.0, 10.0, 1e3, 1e12, np.inf])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_focus_at_infinity_is_a_lens(dtype):
    lens = ThinLens(*(np.asarray(v, dtype) for v in (F, N, np.inf, P)))
    assert lens.focus_distance.dtype == dtype and np.isposinf(lens.focus_distance)
    assert float(lens.blur_scale) == 0.0  # a point at infinity is sharp
    assert float(lens.focus_power) == 0.0
    sensor = ThinLens.from_sensor(F, N, np.inf, sensor_width=0.036, image_width=6000)
    assert np.isposinf(sensor.focus_distance) and float(sensor.pixel_pitch) == pytest.approx(P)
    assert float(ThinLens(F, N, 4.0, P).focus_power) == 0.25  # diopters


def test_coc_at_infinity_focus():
    lens = ThinLens(F, N, np.inf, P)
    r = np.asarray(signed_coc_radius(DEPTHS, lens))
    # Every finite depth is in front of the focus plane: r = -f^2 / (2 N d p). 4 ulps: C's three
    # roundings and the division by d.
    np.testing.assert_allclose(r[:-1], -C / DEPTHS[:-1], rtol=4 * np.finfo(float).eps)
    assert r[-1] == 0.0  # a point at infinity is in focus
    np.testing.assert_array_equal(np.asarray(coc_radius(DEPTHS, lens)), np.abs(r))


def test_infinity_is_the_limit_of_far_focus():
    """d_f = 1e12 m and d_f = inf: the same radii and the same gradients, to O(d / d_f)."""

    def radii(fields, depth):
        return coc_radius(depth, ThinLens(*fields))

    near, at_inf = (jnp.asarray([F, N, d_f, P]) for d_f in (1e12, np.inf))
    # Relative difference of the radii: (d - f) / (d_f - f) <= 1e3 / 1e12 for these depths.
    np.testing.assert_allclose(radii(near, DEPTHS[:-2]), radii(at_inf, DEPTHS[:-2]), rtol=2e-9)
    # At d = inf the far focus leaves K = C / d_f = 1e-10 px, at d = 1e12 it is in focus.
    np.testing.assert_allclose(radii(near, DEPTHS[-2:]), radii(at_inf, DEPTHS[-2:]), atol=2e-8)
    fields = np.array([F, N, 1.0, P])
    for d in [*DEPTHS[:-2], np.inf]:  # not d = 1e12, in focus for the finite lens
        g_near, g_inf = (np.asarray(jax.grad(radii)(x, d)) for x in (near, at_inf))
        # The sensitivities x dr/dx of f, N and p (px) agree as the radii do; dr/dd_f is
        # C (f - d) / (d d_f^2), <= 1e-22 px/m at 1e12 and exactly 0 (the limit) at inf.
        np.testing.assert_allclose(g_near * fields, g_inf * fields, rtol=2e-9, atol=2e-8)
        assert abs(g_near[2]) < 1e-20 and g_inf[2] == 0.0


def _accuracy_grid(lens_dtype):
    """(lens fields (L, 1) each, depths (L, D)): lenses from just beyond f to infinity focus."""
    f32 = np.float32
    rows = []
    for f, n, p in itertools.product([0.004, 0.05, 0.3], [0.7, 2.0, 22.0], [1e-6, 6e-6, 1e-4]):
        for d_f in [f * (1 + 1e-4), f * 1.01, 2 * f, 0.5, 3.0, 100.0, 1e4, 1e12, np.inf]:
            if d_f > f:
                rows.append((f, n, d_f, p))
    lenses = np.array(rows, f32)  # the float32 values are the exact inputs of the reference
    depths = []
    for f, _, d_f, _ in lenses:
        d = [np.nextafter(f, f32(np.inf)), f * 1.001, 0.3, 1.0, 2.9, 3.1, 50.0, 1e6, 1e30, np.inf]
        if np.isfinite(d_f):  # around the focus plane, in rounding units and in percent
            d_f = f32(d_f)
            d += [d_f, np.nextafter(d_f, f32(0)), np.nextafter(d_f, f32(np.inf)), d_f * 1.01]
            d += [d_f * 0.99, d_f * 2, d_f / 2]
        d = np.array(d, f32)
        d = np.where(d > f, d, f32(np.inf))  # pad rows to equal length with a valid depth
        depths.append(np.concatenate([d, np.full(17 - d.size, np.inf, f32)]))
    fields = [lenses[:, i : i + 1].astype(lens_dtype) for i in range(4)]
    return fields, np.stack(depths)


@pytest.mark.parametrize("lens_dtype", [np.float32, np.float64])
def test_float32_radius_within_two_rounding_units(lens_dtype):
    """Float32 radii against the exact radius of the same float32 inputs (float64 reference), over
    lenses focused from just beyond f (K ~ 1e7 px) to infinity and depths from just beyond f
    through the focus plane to infinity. Measured: at most 1.9 (float32 lens) and 1.8 (float64
    lens) units of 2^-23, relative; the textbook `K (1 - d_f/d)` had 2.1 and 1.4 at finite focus."""
    fields, depth = _accuracy_grid(lens_dtype)
    r = np.asarray(coc_radius(jnp.asarray(depth), ThinLens(*fields)))
    assert r.dtype == np.float32
    f, n, d_f, p = (x.astype(np.float64) for x in fields)
    d = depth.astype(np.float64)
    c = f * f / (2 * n * p)
    with np.errstate(invalid="ignore", divide="ignore"):  # the inf cases, replaced below
        ref = c * np.abs(d - d_f) / d / (d_f - f)  # d - d_f of float32 values: exact in float64
    ref = np.where(np.isinf(d), np.where(np.isinf(d_f), 0.0, c / (d_f - f)), ref)
    ref = np.where(np.isinf(d_f) & ~np.isinf(d), c / d, ref)
    zero = ref == 0
    assert np.all(r[zero] == 0)  # the focus plane is exactly sharp
    err = np.abs(r[~zero] - ref[~zero]) / ref[~zero] / 2.0**-23
    # 3 units: the ~8 float32 roundings of the computation (half a unit each) rarely add up
    assert err.max() <= 3.0, err.max()


@pytest.mark.parametrize(
    "depth,focus",
    [(1.7, 3.0), (5.0, 3.0), (0.07, 0.0501), (2.0, 1e4), (0.3, 1.2)],
    ids=["front", "behind", "focus_near_f", "far_focus", "close_up"],
)
def test_grads_lens_fields_float64(depth, focus):
    # Pixel pitch in micrometres so that one finite-difference step suits every argument; the
    # focus distance in units of its own value, for the same reason.
    def f(fl, n, d_f_rel, pitch_um):
        return coc_radius(depth, ThinLens(fl, n, d_f_rel * focus, pitch_um * 1e-6))

    args = tuple(jnp.asarray(v) for v in (0.05, 2.0, 1.0, 6.0))
    # eps 1e-7 keeps f and d_f from crossing (0.0501 - 0.05 = 1e-4); check_grads' own float64
    # tolerances (1e-5 relative) cover the central differences' O(eps^2) error
    check_grads(f, args, order=2, modes=("fwd", "rev"), eps=1e-7)


@pytest.mark.parametrize("depth", [0.06, 1.7, 40.0])
def test_grads_at_infinity_focus(depth):
    """At d_f = inf: check_grads for depth, f, N, p (d_f itself cannot be stepped past inf), and
    jax.grad, jvp and the Hessian finite, with dr/dd_f = 0, the limit of C (d - f) / (d d_f^2)."""

    def r(d, fl, n, d_f, pitch_um):
        return coc_radius(d, ThinLens(fl, n, d_f, pitch_um * 1e-6))

    args = tuple(jnp.asarray(v) for v in (depth, F, N, np.inf, 6.0))
    check_grads(
        lambda d, fl, n, p: r(d, fl, n, np.inf, p),
        (args[0], args[1], args[2], args[4]),
        order=2,
        modes=("fwd", "rev"),
        eps=1e-7,
    )
    g = jax.grad(r, argnums=range(5))(*args)
    expected = (-C / depth**2, F / (N * P * depth), -C / (N * depth), 0.0, -C / (6.0 * depth))
    np.testing.assert_allclose(np.asarray(g), expected, rtol=1e-14)
    tangent = jax.jvp(r, args, tuple(jnp.ones_like(a) for a in args))[1]
    np.testing.assert_allclose(tangent, sum(expected), rtol=1e-13)
    hess = jax.hessian(r, argnums=range(5))(*args)
    assert all(np.all(np.isfinite(np.asarray(h))) for h in jax.tree_util.tree_leaves(hess))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_gradients_finite_at_every_infinity(dtype):
    """d and d_f finite or infinite, in every combination, in both precisions: finite gradients
    (0 with respect to an infinite depth or focus distance)."""

    def r(d, fl, n, d_f, p):
        return coc_radius(d, ThinLens(fl, n, d_f, p))

    for d, d_f in itertools.product([0.5, 3.0, np.inf], [3.0, np.inf]):
        args = tuple(jnp.asarray(v, dtype) for v in (d, F, N, d_f, P))
        g = np.asarray(jax.jit(jax.grad(r, argnums=range(5)))(*args))
        assert np.all(np.isfinite(g)), (d, d_f, g)
        if np.isinf(d):
            assert g[0] == 0.0
        if np.isinf(d_f):
            assert g[3] == 0.0
        if np.isinf(d) and np.isinf(d_f):
            assert np.all(g == 0.0)  # a point at infinity stays in focus


def test_traced_focus_distance_validity():
    """Under jit: inf focus gives finite radii, -inf, NaN, 0 and <= f give NaN (no error can be
    raised from the elementwise function), and the run-time check of `render` passes inf."""
    depth = jnp.asarray([0.5, 3.0, jnp.inf])
    radii = jax.jit(lambda d_f: coc_radius(depth, ThinLens(F, N, d_f, P)))
    np.testing.assert_allclose(radii(jnp.inf), [C / 0.5, C / 3.0, 0.0], rtol=1e-15)
    for bad in (-jnp.inf, jnp.nan, 0.0, -3.0, F):
        assert np.all(np.isnan(np.asarray(radii(bad)))), bad
    checked = jax.jit(lambda d_f: _error_if_invalid(depth, ThinLens(F, N, d_f, P)))
    np.testing.assert_array_equal(checked(jnp.inf), depth)
    with pytest.raises((RuntimeError, ValueError), match="focus_distance must exceed"):
        jax.block_until_ready(checked(-jnp.inf))


def test_inf_focus_in_a_lens_batch():
    lenses = jax.vmap(lambda d_f: ThinLens(F, N, d_f, P))(jnp.array([3.0, jnp.inf]))
    r = jax.jit(jax.vmap(coc_radius, in_axes=(None, 0)))(jnp.array([1.0, 5.0, jnp.inf]), lenses)
    expected = [
        np.asarray(coc_radius(jnp.array([1.0, 5.0, jnp.inf]), ThinLens(F, N, x, P)))
        for x in (3.0, np.inf)
    ]
    np.testing.assert_allclose(np.asarray(r), np.stack(expected), rtol=1e-15)


def test_radius_from_focus_power():
    """The diopter form `C (u - 1/d) / (1 - f u)` agrees with `signed_coc_radius` and is
    differentiable in `u` at `u = 0` (focus at infinity), where `ThinLens(..., 1/u)` is not."""
    for d_f in (0.06, 0.3, 3.0, 1e4, np.inf):
        a = _signed_coc_radius_from_power(DEPTHS, F, N, 1 / d_f, P)
        b = signed_coc_radius(DEPTHS, ThinLens(F, N, d_f, P))
        # absolute: the power form's u - 1/d cancels near the focus plane; its 1 - f u loses
        # log2(d_f / (d_f - f)) bits, 2.6 bits at d_f = 0.06
        np.testing.assert_allclose(a, b, rtol=1e-14, atol=1e-14 * C / F)

    def r(u, d):
        return _signed_coc_radius_from_power(d, F, N, u, P)

    for d in (0.5, 3.0, np.inf):
        g = jax.grad(r)(0.0, d)
        np.testing.assert_allclose(g, C * (1 - F / d), rtol=1e-15)  # d/du (u - 1/d) / (1 - f u)
        check_grads(lambda u, d=d: r(u, d), (jnp.asarray(2.0),), order=2, modes=("fwd", "rev"))
    assert np.isnan(
        float(jax.grad(lambda u: signed_coc_radius(3.0, ThinLens(F, N, 1 / u, P)))(0.0))
    )
    bad = jnp.asarray([-1e-3, 1 / F, 30.0, jnp.nan])
    assert np.all(np.isnan(np.asarray(_signed_coc_radius_from_power(1.0, F, N, bad, P))))


def test_infinity_focus_float32():
    lens = ThinLens(*(np.float32(x) for x in (F, N, np.inf, P)))
    assert lens.focus_distance.dtype == jnp.float32
    depth = jnp.asarray([0.06, 3.0, jnp.inf], jnp.float32)
    r = coc_radius(depth, lens)
    assert r.dtype == jnp.float32
    np.testing.assert_allclose(r, [C / 0.06, C / 3.0, 0.0], rtol=3e-7)
    g = jax.grad(lambda lens: jnp.sum(coc_radius(depth, lens)))(lens)
    assert all(np.isfinite(x) for x in jax.tree_util.tree_leaves(g)) and g.focus_distance == 0
