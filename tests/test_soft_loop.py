"""The soft filter's fast path: the per-tap area and the grouping of offsets into mirror classes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdof._filters.common import tap_offsets
from jaxdof._filters.soft import (
    gather,
    mirror_classes,
    soft_filter,
    symmetric_gather,
    tap_area,
    tap_weight,
)
from jaxdof._overlap import _quadrant


def _canonical_rects(max_radius):
    for oy, ox in tap_offsets(max_radius):
        if 0 <= oy <= ox:
            yield max(ox - 0.5, 0.0), ox + 0.5, max(oy - 0.5, 0.0), oy + 0.5


@pytest.mark.parametrize("max_radius", [0.7, 3.0, 12.0])
def test_tap_area_matches_quadrant_float64(max_radius):
    """Same area and arc length as the overlap module's quadrant, to float64 rounding."""
    r = jnp.asarray(np.random.default_rng(0).uniform(0, max_radius, 500))
    for rect in _canonical_rects(max_radius):
        area, arc = tap_area(*(jnp.float64(v) for v in rect), r, with_arc=True)
        ref_area, ref_arc = _quadrant(*(jnp.float64(v) for v in rect), r)
        # both are sums of a few O(1) terms: a few float64 rounding units
        np.testing.assert_allclose(area, ref_area, rtol=0, atol=1e-14)
        np.testing.assert_allclose(arc, ref_arc, rtol=0, atol=1e-14)


def test_tap_area_float32_error_within_rounding_of_r():
    """float32 keeps issue 2's overlap bound, 2e-6 max(1, r) of a pixel, up to r = 1000.

    All inputs are float32 arrays, so the computation stays in float32 with x64 on (the strict
    dtype promotion of the test config would raise on any silent mix).
    """
    rng = np.random.default_rng(1)
    worst = 0.0
    for centre in (0.8, 5.0, 60.0, 999.0):
        r32 = jnp.asarray(centre + rng.uniform(-0.7, 0.7, 400), jnp.float32)
        r64 = np.asarray(r32, np.float64)
        k = int(centre)
        for oy in range(0, 3):
            for ox in (max(k - 1, oy), k, k + 1):  # squares the circle crosses
                rect = (max(ox - 0.5, 0.0), ox + 0.5, max(oy - 0.5, 0.0), oy + 0.5)
                got = tap_area(*(jnp.float32(v) for v in rect), r32)
                assert got.dtype == jnp.float32
                ref = np.asarray(_quadrant(*(jnp.float64(v) for v in rect), jnp.asarray(r64))[0])
                err = np.abs(np.asarray(got, np.float64) - ref) / np.maximum(1, r64)
                worst = max(worst, float(np.max(err)))
    assert worst <= 2e-6


@pytest.mark.parametrize("max_radius", [0.0, 1.0, 2.5, 7.0])
def test_mirror_classes_cover_every_offset_once(max_radius):
    offsets = tap_offsets(max_radius)
    seen = []
    for k, (canonical, mirrors) in mirror_classes(offsets).items():
        assert mirrors.shape == (len(canonical), k, 2)
        seen += [tuple(m) for m in mirrors.reshape(-1, 2)]
    assert sorted(seen) == sorted(tuple(o) for o in offsets)


def test_symmetric_gather_equals_plain_gather():
    rng = np.random.default_rng(2)
    image, radius = rng.uniform(size=(11, 13, 2)), rng.uniform(0, 4, (11, 13))
    offsets = tap_offsets(4.0)
    np.testing.assert_allclose(
        symmetric_gather(image, radius, offsets, tap_weight),
        gather(image, radius, offsets, tap_weight),
        rtol=0,
        atol=1e-14,  # the same terms summed in another order
    )


def test_mirror_classes_reject_an_asymmetric_set():
    with pytest.raises(ValueError, match="reflections"):
        mirror_classes(np.array([[0, 0], [0, 1]]))


def _plain_soft(image, radius, max_radius):
    """The same scatter left entirely to JAX's autodiff: the per-tap gather, no custom rules."""
    return gather(image, radius, tap_offsets(max_radius), tap_weight)


def test_hand_written_derivatives_equal_autodiff_of_the_plain_gather():
    """`soft_filter`'s tangent primitive and its transpose give JAX's own derivatives, every mode."""
    rng = np.random.default_rng(4)
    image = jnp.asarray(rng.uniform(size=(9, 10, 2)))
    radius = jnp.asarray(rng.uniform(0, 3.4, (9, 10)))
    f = lambda i, r: soft_filter(i, r, max_radius=3.4)
    g = lambda i, r: _plain_soft(i, r, 3.4)
    ti, tr = jnp.asarray(rng.normal(size=image.shape)), jnp.asarray(rng.normal(size=radius.shape))
    # forward mode (what Levenberg-Marquardt uses)
    jf, jg = jax.jvp(f, (image, radius), (ti, tr))[1], jax.jvp(g, (image, radius), (ti, tr))[1]
    # reverse mode, with respect to both inputs and to each alone
    loss = lambda fn: lambda i, r: jnp.sum(jnp.sin(fn(i, r)))
    rf = jax.grad(loss(f), argnums=(0, 1))(image, radius)
    rg = jax.grad(loss(g), argnums=(0, 1))(image, radius)
    r_only = jax.grad(loss(f), argnums=1)(image, radius)
    # linearize then transpose (optimistix's normal equations)
    _, lin = jax.linearize(f, image, radius)
    ct = jnp.asarray(rng.normal(size=image.shape))
    tf = jax.linear_transpose(lin, image, radius)(ct)
    tg = jax.vjp(g, image, radius)[1](ct)
    # second order: the primitive's own JVP (a Hessian-vector product in the radius)
    hvp = lambda fn: jax.jvp(jax.grad(lambda r: loss(fn)(image, r)), (radius,), (tr,))[1]
    # vmap of a gradient (the vprim batching rule)
    vg = jax.vmap(jax.grad(loss(f), argnums=1))(
        jnp.stack([image, 2 * image]), jnp.stack([radius] * 2)
    )
    vref = jax.grad(loss(g), argnums=1)(2 * image, radius)
    # all are sums of the same few O(1) terms in another order: float64 rounding
    for got, want in [
        (jf, jg),
        *zip(rf, rg),
        (r_only, rg[1]),
        *zip(tf, tg),
        (hvp(f), hvp(g)),
        (vg[1], vref),
    ]:
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
