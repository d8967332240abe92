r"""The reference scatter: each pixel's light spread with the exact circle-pixel overlap.

Computed as a gather over the integer offsets `o` of the window,

$$\text{out}[p] = \sum_o \text{image}[p - o]\, w(o, r_{p - o}), \qquad
  w(o, r) = \frac{|\,\text{disc}(0, r) \cap \text{pixel}(o)\,|}{\pi r^2},$$

as a `lax.scan` over offsets whose body is checkpointed: memory stays at a few images in the
forward pass and in reverse mode (the body is recomputed instead of storing per-offset weights).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float

from .._overlap import _quadrant
from .common import tap_offsets


def _offset_geometry(offsets: np.ndarray, dtype) -> tuple[Array, ...]:
    """Per-offset first-quadrant rectangle `[ax, bx] x [ay, by]` and multiplicity `m`.

    By symmetry the pixel at integer offset `o` covers the same area as the first-quadrant rectangle
    `[|ox| - 1/2, |ox| + 1/2]`, except that a pixel on an axis straddles it: there the area is twice
    that of its half `[0, 1/2]`. One quadrant evaluation per tap instead of four.
    """
    oy, ox = offsets[:, 0].astype(np.float64), offsets[:, 1].astype(np.float64)
    ax, ay = np.maximum(np.abs(ox) - 0.5, 0), np.maximum(np.abs(oy) - 0.5, 0)
    bx, by = np.abs(ox) + 0.5, np.abs(oy) + 0.5
    m = np.where(ox == 0, 2.0, 1.0) * np.where(oy == 0, 2.0, 1.0)
    centre = ((ox == 0) & (oy == 0)).astype(np.float64)
    return tuple(jnp.asarray(v, dtype) for v in (ax, bx, ay, by, m, centre))


@jax.custom_jvp
def tap_weight(ax, bx, ay, by, m, centre, r):
    """Normalised weight `m |disc(r) ∩ rect| / (pi r^2)`; exactly the identity for `r <= 1/2`.

    A disc of radius at most half a pixel centred in its pixel stays inside it, so the weight is 1 at
    the centre tap and 0 elsewhere: no 0/0 as `r -> 0`, and a zero derivative (the dead zone).
    """
    return _tap_weight_and_derivative(ax, bx, ay, by, m, centre, r)[0]


def _tap_weight_and_derivative(ax, bx, ay, by, m, centre, r):
    area, arc = _quadrant(ax, bx, ay, by, r)
    big = r > 0.5
    rs = jnp.where(big, r, 1)
    inv = 1 / (math.pi * rs * rs)
    w = jnp.where(big, m * area * inv, centre)
    dw = jnp.where(big, m * (arc - 2 * area / rs) * inv, 0)
    return w, dw


@tap_weight.defjvp
def _tap_weight_jvp(primals, tangents):
    w, dw = _tap_weight_and_derivative(*primals)
    return w, dw * tangents[-1]


def soft_filter(
    image: Float[Array, "h w c"], radius: Float[Array, "h w"], *, max_radius: float
) -> Float[Array, "h w c"]:
    """Exact soft-coverage scatter of `image` (H, W, C) by per-pixel radii, clamped to `max_radius`."""
    offsets = tap_offsets(max_radius)
    return gather(image, radius, offsets, tap_weight)


def gather(image, radius, offsets: np.ndarray, weight_fn) -> Array:
    """`out[p] = sum_o image[p - o] * weight_fn(*geometry(o), r[p - o])` as a checkpointed scan."""
    h, w, c = image.shape
    pad = int(np.abs(offsets).max()) if offsets.size else 0
    pimg = jnp.pad(image, ((pad, pad), (pad, pad), (0, 0)))
    prad = jnp.pad(radius, ((pad, pad), (pad, pad)))
    geometry = _offset_geometry(offsets, image.dtype)
    starts = jnp.asarray(pad - offsets, jnp.int32)
    zero = jnp.zeros((), jnp.int32)

    def body(acc, xs):
        start, geom = xs
        src = lax.dynamic_slice(pimg, (start[0], start[1], zero), (h, w, c))
        r = lax.dynamic_slice(prad, (start[0], start[1]), (h, w))
        wgt = weight_fn(*geom, r)
        return acc + src * wgt[..., None], None

    body = jax.checkpoint(body, prevent_cse=False)
    out, _ = lax.scan(body, jnp.zeros_like(image), (starts, geometry))
    return out
