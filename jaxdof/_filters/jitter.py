r"""Jittered coverage: `n` random sample points per output pixel, from an explicit `jax.random` key.

The 2006 paper's irregular alternative to the `n x n` grid: each output pixel `p` tests `n` points
`p + s_{p,k}` against every circle of confusion. The points are stratified jitter (a Latin
hypercube: one point in each of `n` horizontal and `n` vertical strips of the pixel, paired by a
random permutation), a cheap approximation to the Poisson-disk distribution the paper cites.
Source `q` of radius `r` gives pixel `p`

$$w(p, q) = \frac{1}{\pi r_q^2}\cdot\frac{1}{n}\sum_{k=1}^{n} [\,|p + s_{p,k} - q| \le r_q\,],$$

the paper's `e / (pi r^2)` times the estimated covered fraction of the pixel. Because the points
are uniform in the pixel, `E[w] = area(disc ∩ pixel) / (pi r^2)`: **an unbiased estimate of the soft
filter's weight**, which is its `n -> infinity` limit (error `O(n^-1/2)` for independent points, faster
for the stratified ones). Energy is conserved in expectation, not exactly. Radii `<= 1/2` leave
their pixel untouched, as in the soft filter.

The same `key` always gives the same points and the same image (`normalize=True` reuses them for the
flat field).

**Gradients:** linear in `image`. The coverage is a step function of the radius, so the radius is
held constant (`stop_gradient`): `DIFFERENTIABLE_IN_RADIUS["jitter"]` is `False`.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float

from .common import tap_offsets
from .taps import gather_taps


def jitter_points(key: Array, shape: tuple[int, int], samples: int, dtype) -> Array:
    """Latin-hypercube points `(H, W, n, 2)` as `(dy, dx)` in `[-1/2, 1/2)^2`, one set per pixel."""
    ky, kx, kp = jax.random.split(key, 3)
    h, w = shape
    strata = jnp.arange(samples, dtype=dtype)[None, None]
    uy = jax.random.uniform(ky, (h, w, samples), dtype)
    ux = jax.random.uniform(kx, (h, w, samples), dtype)
    perm = jnp.argsort(jax.random.uniform(kp, (h, w, samples), dtype), axis=-1)
    dy = (strata + uy) / samples - 0.5
    dx = (perm.astype(dtype) + ux) / samples - 0.5
    return jnp.stack([dy, dx], axis=-1)


def jitter_filter(
    image: Float[Array, "h w c"],
    radius: Float[Array, "h w"],
    *,
    max_radius: float,
    samples: int,
    key: Array,
) -> Float[Array, "h w c"]:
    """Scatter with coverage estimated from `samples` jittered points per output pixel."""
    dtype = image.dtype
    r = lax.stop_gradient(radius)
    pts = jitter_points(key, r.shape, samples, dtype)
    offsets = tap_offsets(max_radius)
    small = r <= 0.5
    inv_area = jnp.where(small, 0, 1 / (math.pi * jnp.where(small, 1, r) ** 2 * samples))
    is_centre = np.all(offsets == 0, axis=-1).astype(np.float64)

    def weight(tap, src, out):
        o, centre = tap
        r_s, inv_s = src
        (p,) = out
        # the output pixel's points relative to the source centre: o + s
        d2 = (p[..., 0] + o[0]) ** 2 + (p[..., 1] + o[1]) ** 2
        hits = (d2 <= (r_s * r_s)[..., None]).astype(dtype).sum(-1)
        return jnp.where(r_s <= 0.5, centre, hits * inv_s)

    return gather_taps(
        image,
        offsets,
        weight,
        per_tap=(jnp.asarray(offsets, dtype), jnp.asarray(is_centre, dtype)),
        source=(r, inv_area),
        output=(pts,),
    )
