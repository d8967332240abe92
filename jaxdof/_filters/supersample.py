r"""`Supersample`: coverage counted on `n x n` sub-pixel points (the model is in its docstring).

The count is exact integer arithmetic done row by row: on the sub-row at height `y` the aperture
spans `[xl(y), xr(y)]` and the sub-pixel columns inside it are a range of integers, so a tap costs
`O(n)`, not `O(n^2)`. For the disc the count is computed once per mirror class of offsets (up to 8
taps share it, as in the soft filter). With `blades` the aperture is the inscribed polygon (see
`shape.py`), every tap counted.

**Row spans for large discs.** A fully covered pixel holds all `n^2` sub-samples, so its weight is
`n^2 / N(r)` whatever `n`: from `SUPERSAMPLE_SPANS_MIN_RADIUS` on, those pixels are added as row spans
(`spans.py`) and only the partially covered ones are counted, `O(r)` work per source instead of
`O(r^2)`. Same counts, same numbers to rounding.
"""

from __future__ import annotations

from typing import ClassVar, final

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array

from .. import _tuning
from .._custom_types import Radius
from .base import AbstractMethod
from .common import (
    ChannelsLast,
    check_blades,
    check_int,
    check_rotation,
    tap_offsets,
    window_half_width,
)
from .shape import row_extent
from .soft import mirrored_scatter
from .spans import crossover_for, spans_filter, use_spans
from .taps import gather_taps


def _column_range(xl: Array, xr: Array, n: int) -> tuple[Array, Array]:
    """Integer range `[lo, hi]` of global sub-columns `m` with `xl <= (m + 1/2)/n - 1/2 <= xr`."""
    lo = jnp.ceil((xl + 0.5) * n - 0.5)
    hi = jnp.floor((xr + 0.5) * n - 0.5)
    return lo, hi


def _count_rows(y0: Array, c0: Array | None, r: Array, blades, rotation: float, n: int) -> Array:
    """Sub-pixel centres inside the shape of radius `r` on the `n` sub-rows of the pixel row at
    integer height `y0` (heights `y0 + (k + 1/2)/n - 1/2`), in the global sub-columns
    `c0 .. c0 + n - 1` of one pixel (`c0=None`: in any column). `y0`, `c0` and `r` broadcast.

    The sub-rows are summed one at a time, so that XLA fuses the count into one elementwise pass
    (summing an `(n, H, W)` array instead was 3.5-5x slower at 256^2, R = 8, CPU, one run).
    """
    sub = (np.arange(n) + 0.5) / n - 0.5  # float64; y0 + sub is exact for the tie tests' radii

    def row(acc, s):
        xl, xr = row_extent(y0 + s, r, blades, rotation)
        lo, hi = _column_range(xl, xr, n)
        if c0 is not None:
            lo, hi = jnp.maximum(lo, c0), jnp.minimum(hi, c0 + n - 1)
        return acc + jnp.maximum(hi - lo + 1, 0)

    shapes = [jnp.shape(y0), r.shape] + ([] if c0 is None else [jnp.shape(c0)])
    cnt = jnp.zeros(jnp.broadcast_shapes(*shapes), r.dtype)
    if n <= _tuning.UNROLL_ROWS:
        for s in sub:
            cnt = row(cnt, jnp.asarray(s, r.dtype))
        return cnt
    heights = jnp.asarray(sub, r.dtype)
    return lax.fori_loop(0, n, lambda k, acc: row(acc, heights[k]), cnt)


def supersample_filter(
    image: ChannelsLast,
    radius: Radius,
    *,
    max_radius: float,
    samples: int,
    blades: int | None = None,
    rotation: float = 0.0,
    path: str = "auto",
) -> ChannelsLast:
    """Scatter with `samples x samples` supersampled coverage; energy-preserving.

    `path` (the disc only; a polygon is always gathered): `"dense"` (a gather over every tap, one
    count per mirror class), `"spans"` (row spans for the fully covered pixels and counts on the
    boundary taps: `spans.py`), or `"auto"`: spans from `SUPERSAMPLE_SPANS_MIN_RADIUS` on.
    """
    spans = use_spans(
        path, max_radius, crossover_for(samples, _tuning.SUPERSAMPLE_SPANS_MIN_RADIUS)
    )
    n = samples
    dtype = image.dtype
    r = lax.stop_gradient(radius)  # the counts are piecewise constant in r
    offsets = tap_offsets(max_radius)
    w = window_half_width(max_radius)

    # total count N(r) over the whole window, one pixel row (its n sub-rows) per scan step
    rows = jnp.arange(-w - 1, w + 2, dtype=dtype)  # heights +-(w + 3/2) cover every disc

    def add_row(total, y0):
        return total + _count_rows(y0, None, r, blades, rotation, n), None

    total, _ = lax.scan(add_row, jnp.zeros_like(r), rows)
    small = r <= 0.5
    inv_total = jnp.where(small, 0, 1 / jnp.where(small, 1, total))

    if blades is None:
        if spans:
            return _spans(image, r, max_radius, inv_total, n)
        # the disc and the sub-pixel grid share the grid's 8 reflections
        return _mirrored(image, r, inv_total, offsets, n)

    # per tap: its pixel row, and the global sub-column range of its pixel
    row0 = offsets[:, 0].astype(np.float64)
    col0 = offsets[:, 1].astype(np.float64) * n
    is_centre = np.all(offsets == 0, axis=-1).astype(np.float64)

    def weight(tap, src, out):
        y, c0, centre = tap
        r_s, inv_s = src
        cnt = _count_rows(y, c0, r_s, blades, rotation, n)
        return jnp.where(r_s <= 0.5, centre, cnt * inv_s)

    return gather_taps(
        image,
        offsets,
        weight,
        per_tap=(jnp.asarray(row0, dtype), jnp.asarray(col0, dtype), jnp.asarray(is_centre, dtype)),
        source=(r, inv_total),
    )


def _mirrored(image, r, inv_total, offsets: np.ndarray, n: int) -> Array:
    """The same scatter for a circular aperture, one count per mirror class of offsets.

    The sub-pixel centres are symmetric under the grid's reflections, and so is the disc: the count
    of the pixel at `(oy, ox)` is that of `(|oy|, |ox|)` and of `(|ox|, |oy|)`. As in the soft
    filter, the weighted source is formed once per class and read at each mirrored offset.
    """

    def source(geom, image, r, inv):
        _, bx, _, by, _, centre = geom
        oy, ox = by - 0.5, bx - 0.5  # the class's canonical offset, 0 <= oy <= ox
        cnt = _count_rows(oy, ox * n, r, None, 0.0, n)
        return image * jnp.where(r <= 0.5, centre, cnt * inv)[..., None]

    return mirrored_scatter(source, offsets, image.shape, image.dtype, (image, r, inv_total))


def _spans(image, r, max_radius: float, inv_total, n: int) -> Array:
    """The same scatter by row spans: a fully covered pixel holds all `n^2` sub-samples (weight
    `n^2 / N(r)`), the boundary taps count theirs."""

    def partial(target, dy, dx):  # (taps, H, W) offsets from each source to its boundary pixels
        cnt = _count_rows(dy, dx * n, r[None], None, 0.0, n)
        return cnt * inv_total[None]

    return spans_filter(
        image, r, max_radius=max_radius, partial=partial, interior=n * n * inv_total
    )


@final
class Supersample(AbstractMethod):
    r"""Supersampled coverage: the fraction of `n x n` sub-pixel points inside the circle.

    The 2006 paper's antialiasing (section 3.1.2): subdivide every pixel into `n x n` sub-pixels
    and count those whose centres fall in the disc. Pixel `p` receives from source `q` of radius `r`

    $$w_n(p - q, r) = \frac{c_n(p - q, r)}{\sum_o c_n(o, r)},\qquad
      c_n(o, r) = \#\{(i, j) \in [0, n)^2 : |o + s_{ij}| \le r\},\quad
      s_{ij} = \left(\tfrac{j + 1/2}{n} - \tfrac12,\ \tfrac{i + 1/2}{n} - \tfrac12\right).$$

    Normalising by the total count (not by `pi r^2 n^2`) conserves energy exactly. `n = 1` is the
    hard disc. **The analytic overlap is the `n -> infinity` limit**: `c_n(o, r) / n^2` is a
    midpoint rule for the area of `disc(0, r) ∩ pixel(o)`, which converges to it at rate `O(1/n)`
    on the pixels the circle crosses, and `sum_o c_n / n^2 -> pi r^2`; so `w_n -> area / (pi r^2)`,
    the weight of `Soft` (tested in `tests/test_methods.py`). Radii `<= 1/2` leave their pixel
    untouched, as in the soft filter.

    **Fields:**

    - `samples`: `n`, the sub-pixel points per axis, an int in `[1, 64]` (default 4: 16 points per
      pixel; 64 x 64 = 4096 is the most).
    - `blades`: `None` (a circular aperture, the default) or the number of diaphragm blades, an
      int in `[3, 1024]`: the regular polygon inscribed in the circle of confusion (see `Soft`).
    - `rotation`: the polygon's rotation in radians (default 0); only with `blades`.

    **Gradients:** linear in `image`. Piecewise constant in `radius` (zero derivative almost
    everywhere): `differentiable_in_radius = False`.
    """

    samples: int = eqx.field(static=True)
    blades: int | None = eqx.field(static=True)
    rotation: float = eqx.field(static=True)

    differentiable_in_radius: ClassVar[bool] = False

    def __init__(self, *, samples: int = 4, blades: int | None = None, rotation: float = 0.0):
        self.samples = check_int("samples", samples, 1, 64)  # 64 x 64 = 4096 sub-samples a pixel
        self.blades = check_blades(blades)
        self.rotation = check_rotation(rotation, self.blades, "Supersample")

    def spread(self, image, radius, *, max_radius, depth):
        return supersample_filter(image, radius, max_radius=max_radius, **self._options())
