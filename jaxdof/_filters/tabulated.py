r"""The soft scatter for a scene of few distinct radii: the weights looked up, not recomputed.

The soft filter spends most of its time on the exact weight `w_o(r)` of every (offset class,
source pixel) pair. A scene of `L` distinct radii (a few depth planes, a quantised depth map) has
only `L` distinct weights per offset, so they are computed once into a table `(offsets, L)` and
each pixel reads its own column by its level index:

$$\text{out}[p] = \sum_o \text{image}[p - o]\; T[o, \ell(p - o)], \qquad T[o, l] = w_o(\rho_l).$$

The table holds the soft filter's own weights (`soft.tap_weight`), so the result is the soft
filter's to rounding, depth edges included; only the cost changes, to that of a gather with
constant weights plus one table read per class (for windows of at most 25 taps the class loop is
written out rather than scanned). `Tabulated` is what `Auto` runs on a concrete radius map of
repeated radii (see `auto.py`); radii `<= 1/2` share one level (the identity).
"""

from __future__ import annotations

from typing import ClassVar, final

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from .. import _tuning
from .base import AbstractMethod
from .common import ChannelsLast, half_width, pad_rows_cols, tap_offsets, unique_with_index
from .soft import _offset_geometry, mirror_classes, mirrored_scatter, tap_weight


def radius_levels(radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(levels (L,), index (H, W) int32)` of a concrete radius map, radii `<= 1/2` merged to 0."""
    return unique_with_index(np.where(radius <= 0.5, 0, radius))


def _look_up(row: Array, idx: Array) -> Array:
    """`row[idx]` for a short table `row` (L,) and an index map `idx` (H, W)."""
    if row.shape[0] > _tuning.SELECT_MAX_LEVELS:
        return jnp.take(row, idx)
    out = jnp.broadcast_to(row[0], idx.shape)
    for level in range(1, row.shape[0]):
        out = jnp.where(idx == level, row[level], out)
    return out


def tabulated_filter(
    image: ChannelsLast,
    *,
    max_radius: float,
    levels: Float[ArrayLike, " l"],
    index: Int[ArrayLike, "h w"],
) -> ChannelsLast:
    """The soft scatter of `image` for the radius map `levels[index]` (clamped to `max_radius`).

    Concrete levels and index from `auto`; traced ones from `layered` (its direct path), whose
    radius gradient flows through the levels.
    """
    rho = jnp.asarray(levels, image.dtype)
    offsets = tap_offsets(max_radius)
    idx = jnp.asarray(index, jnp.int32)
    if len(offsets) <= _tuning.FUSED_MAX_TAPS:
        return _classes_written_out(image, rho, idx, offsets)

    def weighted(geom, image, idx):
        row = tap_weight(*geom, rho)  # this offset's weight at each of the L levels
        assert isinstance(row, Array)  # without `with_arc`, one array
        return image * _look_up(row, idx)[..., None]

    return mirrored_scatter(weighted, offsets, image.shape, image.dtype, (image, idx))


def _classes_written_out(image, rho, idx, offsets: np.ndarray) -> Array:
    """The same sum, the class loop written out: each class's weighted source is formed once (one
    look-up per class, not per tap) and read at each of its mirrored offsets.

    Channels first inside: XLA fuses the whole sum into one loop, which vectorises along the image
    rows instead of the 3 channels (R = 2, three levels, RGB float32, CPU, one run: 0.5x the time
    at 48^2, 0.56x at 256^2, 1.1x at 1024^2 against channels last).
    """
    h, w, _ = image.shape
    pad = half_width(offsets)
    pimg = jnp.pad(jnp.moveaxis(image, -1, 0), ((0, 0), (pad, pad), (pad, pad)))
    pidx = pad_rows_cols(idx, pad)
    out = jnp.zeros((image.shape[-1], h, w), image.dtype)
    for canonical, mirrors in mirror_classes(offsets).values():
        geometry = _offset_geometry(canonical, image.dtype)
        for n, images in enumerate(mirrors):
            row = tap_weight(*(g[n] for g in geometry), rho)
            assert isinstance(row, Array)  # without `with_arc`, one array
            source = pimg * _look_up(row, pidx)[None]
            for oy, ox in images:
                out = out + source[:, pad - oy : pad - oy + h, pad - ox : pad - ox + w]
    return jnp.moveaxis(out, 0, -1)


@final
class Tabulated(AbstractMethod):
    """The soft scatter of the radius map `levels[index]`, its weights looked up per level.

    What `Auto.prepare` returns for a concrete map of repeated radii (not exported: it is built
    from the map, `Tabulated(*radius_levels(radius))`). The result is `Soft`'s to rounding.

    **Fields:**

    - `levels`: the distinct radii `(L,)`, pixels (radii `<= 1/2` merged into one level, 0).
    - `index`: each pixel's level `(H, W)`, int.

    The `radius` passed at the call is not read (it is the map these were computed from), so there
    is no radius gradient: `differentiable_in_radius = False`.
    """

    levels: Float[ArrayLike, " l"]
    index: Int[ArrayLike, "h w"]

    differentiable_in_radius: ClassVar[bool] = False

    def spread(self, image, radius, *, max_radius, depth):
        return tabulated_filter(image, max_radius=max_radius, **self._options())
