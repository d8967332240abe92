r"""The soft scatter for a scene of few distinct radii: the weights looked up, not recomputed.

The soft filter spends most of its time on the exact weight `w_o(r)` of every (offset class,
source pixel) pair. A scene of `L` distinct radii (a few depth planes, a quantised depth map) has
only `L` distinct weights per offset, so they are computed once into a table `(offsets, L)` and
each pixel reads its own column by its level index:

$$\text{out}[p] = \sum_o \text{image}[p - o]\; T[o, \ell(p - o)], \qquad T[o, l] = w_o(\rho_l).$$

The table holds the soft filter's own weights (`soft.tap_weight`), so the result is the soft
filter's to rounding, depth edges included; only the cost changes, to that of a gather with
constant weights plus one table read per class. Used by `method="auto"` on a concrete radius map
(see `auto.py`); radii `<= 1/2` share one level (the identity).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .common import tap_offsets
from .soft import _pad, _scan_classes, _shift_sum, tap_weight


def radius_levels(radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(levels (L,), index (H, W) int32)` of a concrete radius map, radii `<= 1/2` merged to 0."""
    r = np.where(radius <= 0.5, 0, radius)
    levels, index = np.unique(r, return_inverse=True)
    return levels, index.reshape(r.shape).astype(np.int32)


def tabulated_filter(
    image: Float[Array, "h w c"],
    *,
    max_radius: float,
    levels: np.ndarray,
    index: np.ndarray,
) -> Float[Array, "h w c"]:
    """The soft scatter of `image` for the radius map `levels[index]` (concrete, clamped)."""
    offsets = tap_offsets(max_radius)
    pad = int(np.abs(offsets).max()) if offsets.size else 0
    rho = jnp.asarray(levels, image.dtype)
    idx = jnp.asarray(index, jnp.int32)

    def body(k, acc, mirrors, geom):
        row = tap_weight(*geom, rho)  # this offset's weight at each of the L levels
        weighted = image * jnp.take(row, idx)[..., None]
        return acc + _shift_sum(_pad(weighted, pad), mirrors, k, pad, -1, image.shape)

    return _scan_classes(offsets, image.dtype, jnp.zeros_like(image), body)
