r"""The exact soft scatter at a cost linear in the blur radius: row spans plus boundary taps.

The soft filter (`jaxdof/_filters/soft.py`) computes

$$\text{out}[p] = \sum_q \text{image}[q]\, \frac{A(p - q, r_q)}{\pi r_q^2}, \qquad
  A(o, r) = |\,\text{disc}(0, r) \cap \text{pixel}(o)\,|,$$

as a gather over every offset of the window: about `pi R^2` exact areas per pixel. But almost all
of a large disc's pixels are *fully* covered, `A = 1`, and only the `O(r)` pixels its circle
crosses need the analytic area. This module splits each source's footprint accordingly and
computes the same sum (to rounding) in scatter form:

- **Interior: row spans.** Pixel `(j, k)` (column, row offset) is fully covered iff its far
  corner is inside, `(|j| + 1/2)^2 + (|k| + 1/2)^2 <= r^2`; in row `k` that is the span
  `|j| <= a_k(r)`. A source adds `v_q = image[q] / (pi r_q^2)` to that span by two marks in a
  difference array, `D[q_y + k, q_x - a_k] += v_q` and `D[q_y + k, q_x + a_k + 1] -= v_q`, and one
  cumulative sum along `x` at the end turns the marks into spans: `O(1)` per source per row.
- **Boundary: the partially covered pixels, split by the diagonals.** A pixel with
  `|k| <= |j|` (the left and right "sides" of the disc, where the circle is steeper than 45
  degrees) is taken from its row: in row `k` these are `j = ±(j_0 + t)`,
  `j_0 = max(a_k + 1, |k|)`, `t < J`. A pixel with `|k| > |j|` (the top and bottom "caps") is
  taken from its column the same way (the disc is symmetric under transposition), starting at
  `max(a_j + 1, |j| + 1)`. Each pixel of the footprint lies in exactly one of {row span, side,
  cap}, so nothing is counted twice or missed. Because the side pixels of a row lie where the
  circle is at least as steep as the diagonal, the circle crosses at most `J = 2` partial pixels
  there per side (checked exhaustively in the tests for every radius on a fine grid up to 400 px);
  taps past the circle have area 0 and cost only their slot. Each tap's weight is the exact
  `tap_weight` of the soft filter (same float32-stable area formula, same analytic derivative), and
  is added directly (a scatter, one pixel per update).
- **Consistency at the seams.** "Fully covered" is decided by one predicate, symmetric in `j`
  and `k` and exact in floating point (`(j + 1/2)^2` and their sum are exact for offsets below
  ~2000 px), so the row view of the interior and the column view of the caps always agree on
  which pixels are interior. Which side of the predicate a nearly fully covered pixel falls on
  does not matter: its exact area is 1 up to rounding either way.
- **Sharp pixels.** Sources with `r <= 1/2` are the identity, as in the soft filter.

**Derivatives.** The span `a_k(r)` is piecewise constant in `r`; it switches exactly where a pixel
becomes fully covered, where the pixel's weight is `1 / (pi r^2)` from both sides, so the output is
continuous in `r` and its derivative is that of `v_q` plus that of the boundary taps (analytic,
from `tap_weight`), correct everywhere except on those switching radii (a measure-zero set).
Everything is `lax.scatter_add`, elementwise arithmetic and one `cumsum`: forward and reverse
mode, `jit`, `vmap`.

**Cost model.** With `R = max_radius`, one checkpointed `lax.scan` step per row offset
`m = 0 .. ceil(R + 1/2) - 1` does, for every source at once: the span `a_m` (a square root), and
scatters of 4 span marks (rows `±m`, both ends); the steps up to the diagonal
(`m <= ~R / sqrt(2)`) also evaluate 4 exact weights (`J = 2` side taps, `J = 2` cap taps) and
scatter 16 boundary pixels (`J` taps x 2 sides x rows `±m`, and the same for the caps in columns
`±m`). Per source that is about `4 R + 16 R / sqrt(2) ~ 15 R` scattered pixels (C channels each)
and `2.8 R` exact areas, against the dense gather's `pi R^2` taps (an eighth of them evaluated,
by symmetry): linear in `R`. The buffers are flat `(padded pixels, C)` arrays so each update
carries one index. The price is the scatter's per-update cost (an index formed at run time,
about 5-10 ns per pixel of 3 channels on the CPU measured), which the dense gather, adding whole
shifted images at static offsets, does not pay; hence the crossover `SPANS_MIN_RADIUS`. Memory
is two padded image-sized buffers plus the step's temporaries, independent of `R`, forward and
reverse (the scan body is recomputed in the backward pass, not stored).

**Precision.** The running sum along a row adds and removes each span's value once, so its
rounding error grows with the row's length rather than with the window. Measured in float32
against the float64 result (uniform image in [0, 1], radii uniform in [0, R]): 8e-7 on a
16 x 2048 image at R = 32 (the dense gather: 1.3e-6); `tests/test_spans.py` checks 96 x 96 at
R = 40 against the float32 accuracy goal, 2e-5 of the image's range.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import math
from collections.abc import Callable, Iterator
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Float

from .. import _tuning
from .._custom_types import Radius
from .common import ChannelsLast, window_half_width
from .soft import soft_filter, tap_weight


#: Partial pixels per row (side) or column (cap) half beyond the span: 2 always suffices (see the
#: module docstring; `tests/test_spans.py::test_two_taps_cover_the_boundary` checks it).
TAPS = 2


PATHS = ("auto", "dense", "spans")


def use_spans(path: str, max_radius: float, crossover: float) -> bool:
    """Whether a filter with a dense and a row-span path takes the spans: `path="spans"`, or
    `"auto"` from its measured `crossover` radius on; `"dense"` never. Another `path` is an error."""
    if path not in PATHS:
        raise ValueError(f"{path=} is not one of {PATHS}")
    return path == "spans" or (path == "auto" and max_radius >= crossover)


def crossover_for(samples: int, table: dict[int | float, float]) -> float:
    """The crossover radius for `samples` from a table `{samples: radius}` (keys ascending, the last
    `inf`): the entry of the first key `>= samples`."""
    return next(r for n, r in table.items() if samples <= n)


# Set while a Jacobian of renders is traced (`in_jacobian`).
_IN_JACOBIAN: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "jaxdof_in_jacobian", default=False
)


@contextlib.contextmanager
def in_jacobian() -> Iterator[None]:
    """Trace the soft filters inside the block as parts of a Jacobian (a few forward-mode tangents
    sharing one primal, as `fit_lens`'s residual builds it): `exact_soft_filter` then takes the
    crossover measured there, `SPANS_MIN_RADIUS_JACOBIAN` by the number of channels, where the
    dense gather's tangents (every tap's area derivative) cost far more than the spans' (only the
    boundary taps move with the radius)."""
    token = _IN_JACOBIAN.set(True)
    try:
        yield
    finally:
        _IN_JACOBIAN.reset(token)


def exact_soft_filter(
    image: ChannelsLast, radius: Radius, *, max_radius: float, path: str = "auto"
) -> ChannelsLast:
    """The exact soft scatter by the dense gather or by row spans, whichever is faster.

    `path="auto"` picks spans when `max_radius >= SPANS_MIN_RADIUS` (traced `in_jacobian`:
    `SPANS_MIN_RADIUS_JACOBIAN` for the image's channels); `"dense"` and `"spans"` force one
    (the tests and benchmarks compare them). Both give the same numbers up to rounding.
    """
    crossover = _tuning.SPANS_MIN_RADIUS
    if _IN_JACOBIAN.get():
        crossover = crossover_for(image.shape[-1], _tuning.SPANS_MIN_RADIUS_JACOBIAN)
    if use_spans(path, max_radius, crossover):
        return spans_filter(image, radius, max_radius=max_radius)
    return soft_filter(image, radius, max_radius=max_radius)


def spans_filter(
    image: ChannelsLast,
    radius: Radius,
    *,
    max_radius: float,
    partial: Callable[[Array, Array, Array], Array] | None = None,
    interior: Float[Array, "h w"] | None = None,
) -> ChannelsLast:
    """The soft filter's exact scatter by row spans and boundary taps (module docstring).

    Same contract as `jaxdof._filters.soft.soft_filter`: `image` (H, W, C), `radius` (H, W) in
    pixels, already clamped to `max_radius` (static); radii `<= 1/2` are the identity.

    `partial(target, dy, dx) -> (T, H, W)`: another weight for the boundary taps (the pixels not
    fully covered), given for the `T` taps of a step at once: each source's output pixel as an
    index into the flat padded buffers (layout of `spans_layout`; out of range for a dropped
    duplicate) and the offset `(dy, dx)` from source to output pixel. It must be 0 for radii
    `<= 1/2`. `jitter` and `supersample` use this: their estimates are exact on fully covered
    pixels. `interior` (H, W): the weight of a fully covered pixel of each source, `1 / (pi r^2)`
    if not given (`supersample`: `n^2 / N(r)`, all sub-samples over its normaliser).
    """
    h, w, c = image.shape
    dtype = image.dtype
    wh = window_half_width(max_radius)
    if wh == 0:  # every disc fits inside its own pixel
        return image
    pad, hp, wp = spans_layout(h, w, max_radius)

    big = radius > 0.5
    rs = jnp.where(big, radius, 1)
    if interior is None:
        interior = 1 / (math.pi * rs * rs)
    sharp = jnp.where(big[..., None], jnp.zeros((), dtype), image)  # the identity part
    # Buffers are flat (padded pixels, C): one index per update, pixel (y, x) at y * wp + x.
    rows = (jnp.arange(h, dtype=jnp.int32) + pad) * wp
    disc = _Discs(
        image=image,
        radius=radius,
        big=big,
        # The integer geometry depends on r only through comparisons: no gradient through it.
        rr=lax.stop_gradient(rs * rs),
        v=image * jnp.where(big, interior, 0)[..., None],
        base=rows[:, None] + (jnp.arange(w, dtype=jnp.int32) + pad)[None, :],
        wp=wp,
        skip=2 * hp * wp,  # an index past the end: the update is dropped
        wh=wh,
        partial=partial,
    )
    # Rows past the diagonal hold no side pixels and their columns no cap pixels: the pixel
    # (m, m) is touched only while 2 (m - 1/2)^2 < r^2, a cap pixel (m, m + 1) only while
    # (m - 1/2)^2 + (m + 1/2)^2 < r^2. Past it, only spans.
    diag = min(wh, math.ceil(max_radius / math.sqrt(2) + 0.5) - 1)
    carry = (jnp.zeros((hp * wp, c), dtype), jnp.zeros((hp * wp, c), dtype))
    carry = _scan(functools.partial(_boundary_step, disc), carry, 0, diag)
    carry = _scan(functools.partial(_spans_step, disc), carry, diag + 1, wh)
    boundary, marks = (b.reshape(hp, wp, c) for b in carry)
    out = boundary + jnp.cumsum(marks, axis=1)
    return out[pad : pad + h, pad : pad + w] + sharp


class _Discs(NamedTuple):
    """Every source's disc, as each step of `spans_filter`'s scan reads it (all `(H, W)` maps of
    the sources but `image` and `v`, `(H, W, C)`)."""

    image: Array
    radius: Array  # pixels, clamped to `max_radius`
    big: Array  # `radius > 1/2`: not the identity
    rr: Array  # `r^2` (1 for the identity), no gradient: the integer geometry's only input
    v: Array  # `image * interior`: what a fully covered pixel receives
    base: Array  # each source's index in the flat padded buffers (layout of `spans_layout`)
    wp: int  # padded row length: one row down is `+ wp`
    skip: int  # an index past the end of the buffers: the update is dropped
    wh: int  # the window's half-width: no span is longer
    partial: Callable[[Array, Array, Array], Array] | None  # see `spans_filter`

    def full(self, jf, kk):
        """Pixel (j, k), `j, k >= 0`, is fully covered; `kk = (k + 1/2)^2`. Exact, symmetric."""
        half = jnp.asarray(0.5, self.image.dtype)
        return (jf + half) * (jf + half) + kk <= self.rr

    def span(self, mf):
        """`a_m`: the largest `j` with pixel (j, m) fully covered, -1 if none; float (H, W)."""
        dtype = self.image.dtype
        half, zero, one = jnp.asarray(0.5, dtype), jnp.zeros((), dtype), jnp.ones((), dtype)
        kk = (mf + half) * (mf + half)
        a = jnp.floor(jnp.sqrt(jnp.maximum(self.rr - kk, zero)) - half)
        # the square root's rounding, corrected by the exact predicate
        a = jnp.where(self.full(a + 1, kk), a + 1, a)
        a = jnp.where((a >= 0) & ~self.full(a, kk), a - 1, a)
        return jnp.minimum(jnp.where(self.big, a, -one), jnp.asarray(self.wh, dtype))

    def weight(self, jf, kf):
        """Exact normalised weight of pixel (j, k) (float maps, `j, k >= 0`), by `tap_weight`."""
        dtype = self.image.dtype
        half, zero, one = jnp.asarray(0.5, dtype), jnp.zeros((), dtype), jnp.ones((), dtype)
        two = jnp.asarray(2, dtype)
        ax, ay = jnp.maximum(jf - half, zero), jnp.maximum(kf - half, zero)
        mult = jnp.where(jf == 0, two, one) * jnp.where(kf == 0, two, one)
        nothing = jnp.zeros_like(self.radius)
        wgt = tap_weight(ax, jf + half, ay, kf + half, mult, nothing, self.radius)
        assert isinstance(wgt, Array)  # without `with_arc`, one array
        return wgt


def _add(buf: Array, idx: Array, upd: Array) -> Array:
    # Out-of-range indices are dropped: that is how a duplicate (row -0, column -0, the centre
    # pixel on the left side) is skipped. Every other index is inside the padding.
    return buf.at[idx].add(upd, mode="drop")


def _spans_step(disc: _Discs, carry, m):
    """Row spans of rows +m and -m (row 0 once): two marks per row."""
    boundary, marks = carry
    a = disc.span(m.astype(disc.image.dtype))
    ai = a.astype(jnp.int32)
    val = disc.v * (a >= 0).astype(disc.image.dtype)[..., None]
    twin = jnp.where(m == 0, disc.skip, 0)  # row -0 is row +0: send it out of the buffer
    for row in (disc.base + m * disc.wp, disc.base - m * disc.wp + twin):
        marks = _add(marks, row - ai, val)
        marks = _add(marks, row + ai + 1, -val)
    return (boundary, marks), a


def _boundary_step(disc: _Discs, carry, m):
    """Spans, then the partial pixels of rows +-m (sides) and columns +-m (caps)."""
    (boundary, marks), a = _spans_step(disc, carry, m)
    taps = _boundary_taps(disc, a, m)
    if disc.partial is None:  # the soft weight is shared by the mirrored pixels
        for target, _, _, upd in taps:
            boundary = _add(boundary, target, upd)
    else:  # one weight per pixel, all of the step's taps at once (a smaller program)
        target, dy, dx = (jnp.stack([tap[i] for tap in taps]) for i in range(3))
        wgt = disc.partial(target, dy, dx)
        boundary = _add(boundary, target, disc.image[None] * wgt[..., None])
    return (boundary, marks), None


def _boundary_taps(disc: _Discs, a: Array, m: Array) -> list:
    """`(target, dy, dx, weighted source or None)` of every boundary pixel of rows +-m (sides)
    and columns +-m (caps), given the span `a = a_m`; the soft weighted source (shared by the
    mirrored pixels) only without `partial`."""
    base, wp, skip = disc.base, disc.wp, disc.skip
    mf = m.astype(disc.image.dtype)
    mm = jnp.full_like(a, mf)
    twin = jnp.where(m == 0, skip, 0)
    j0 = jnp.maximum(a + 1, mf)  # sides: j = +-(j0 + t), t < TAPS, in rows +-m
    k0 = jnp.maximum(a + 1, mf + 1)  # caps: k = +-(k0 + t), in columns +-m
    taps = []
    for t in range(TAPS):
        j = j0 + t
        ji = j.astype(jnp.int32)
        side = None if disc.partial else disc.image * disc.weight(j, mm)[..., None]
        centre = jnp.where(ji == 0, skip, 0)  # (0, 0) is on the right side only
        for sy, row in ((1, base + m * wp), (-1, base - m * wp + twin)):
            taps += [(row + ji, sy * mm, j, side), (row - ji + centre, sy * mm, -j, side)]
        k = k0 + t
        ki = k.astype(jnp.int32) * wp
        cap = None if disc.partial else disc.image * disc.weight(mm, k)[..., None]
        for sx, col in ((1, base + m), (-1, base - m + twin)):  # column -0 is column +0
            taps += [(col + ki, k, sx * mm, cap), (col - ki, -k, sx * mm, cap)]
    return taps


def _scan(step, carry, lo: int, hi: int):
    """`step` over the row offsets `lo .. hi`, checkpointed: the body is recomputed in the
    backward pass, not stored."""
    if hi < lo:
        return carry
    body = jax.checkpoint(lambda cr, m: (step(cr, m)[0], None), prevent_cse=False)
    return lax.scan(body, carry, jnp.arange(lo, hi + 1, dtype=jnp.int32))[0]


def spans_layout(h: int, w: int, max_radius: float) -> tuple[int, int, int]:
    """`(pad, hp, wp)`: the flat buffers hold pixel `(y, x)` of the frame at `(y + pad) * wp + x +
    pad`, with `hp x wp` padded pixels; every mark and tap lands inside."""
    pad = window_half_width(max_radius) + TAPS
    return pad, h + 2 * pad, w + 2 * pad + 1


__all__ = ["exact_soft_filter", "spans_filter"]
