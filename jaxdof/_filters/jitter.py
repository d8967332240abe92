r"""`Jitter`: `n` random sample points per output pixel (the model is in its docstring).

**A precomputed set of patterns.** The paper found generating random numbers per pixel costly
"unless using a precomputed set of numbers"; so `key` draws `PATTERNS` (16) Latin hypercubes once,
and every output pixel uses one of them, picked at random (also from `key`, so no period shows).
For a tap at offset `o` and pattern `j` the squared distances `|o + s_{j,k}|^2` are then known
before the image is seen, and the hit count of a source of radius `r` is their number below `r^2`:
`n` comparisons against the pattern's precomputed row, fetched in one look-up per tap (up to
`COMPARE_ALL_MAX` points), or beyond that a binary search in the sorted row, `log2(n) + 1`
look-ups. Same estimate, same expectation.

**Row spans for large windows.** Every point of a fully covered pixel hits, so there the estimate
is exact: `1 / (pi r^2)`, the soft filter's weight. From `JITTER_SPANS_MIN_RADIUS` on, those pixels
are added as row spans and only the partially covered ones count hits (`spans.py`, whose boundary
taps take a per-output-pixel weight for this): `O(r)` work per source instead of `O(r^2)`.
"""

from __future__ import annotations

import contextlib
import math
from typing import ClassVar, final

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from .. import _tuning
from .._custom_types import Radius
from .base import AbstractMethod
from .common import ChannelsLast, check_int, check_key, is_concrete, tap_offsets
from .spans import crossover_for, spans_filter, spans_layout, use_spans
from .taps import gather_taps


#: Latin hypercubes drawn per key; each output pixel uses one, picked at random.
PATTERNS = 16


def jitter_points(key: Array, count: int, samples: int, dtype) -> Float[Array, "count n 2"]:
    """`count` Latin hypercubes of `samples` points `(dy, dx)` in `[-1/2, 1/2)^2`."""
    ky, kx, kp = jax.random.split(key, 3)
    strata = jnp.arange(samples, dtype=dtype)[None]
    uy = jax.random.uniform(ky, (count, samples), dtype)
    ux = jax.random.uniform(kx, (count, samples), dtype)
    perm = jnp.argsort(jax.random.uniform(kp, (count, samples), dtype), axis=-1)
    dy = (strata + uy) / samples - 0.5
    dx = (perm.astype(dtype) + ux) / samples - 0.5
    return jnp.stack([dy, dx], axis=-1)


def hit_thresholds(points: Float[Array, "p n 2"], offsets: np.ndarray) -> Float[Array, "taps p m"]:
    """Per tap and pattern, the squared distances `|o + s|^2`, sorted; beyond `COMPARE_ALL_MAX`
    points padded with `inf` to `m = 2^ceil(log2 n)`, the binary search's length."""
    o = jnp.asarray(offsets, points.dtype)
    d2 = jnp.sort(((o[:, None, None, :] + points[None]) ** 2).sum(-1), axis=-1)
    n = points.shape[1]
    m = n if n <= _tuning.COMPARE_ALL_MAX else 1 << (n - 1).bit_length()
    return jnp.pad(d2, ((0, 0), (0, 0), (0, m - n)), constant_values=jnp.inf)


def count_below(
    rows: Float[Array, "k m"], pattern: Int[Array, "*b"], r2: Array
) -> Int[Array, "*b"]:
    """`#{k : rows[pattern, k] <= r2}` elementwise, for rows ascending (`r2` broadcast against
    `pattern`'s shape).

    Up to `COMPARE_ALL_MAX` thresholds per row: one gather of the pattern's whole row and `m`
    comparisons; beyond it, a branchless binary search over the flattened rows (`log2 m + 1`
    dependent single-element gathers, fewer comparisons).
    """
    m = rows.shape[1]
    if m <= _tuning.COMPARE_ALL_MAX:
        below = rows.at[pattern].get(mode="promise_in_bounds") <= r2[..., None]
        return below.sum(-1, dtype=pattern.dtype)
    assert m & (m - 1) == 0, "the binary search needs rows of a power-of-two length"
    flat, base = rows.reshape(-1), pattern * m
    idx = jnp.zeros_like(base)
    step = m // 2
    while step >= 1:  # invariant: flat[base + idx - 1] <= r2 (or idx = 0)
        idx = jnp.where(flat[base + idx + step - 1] <= r2, idx + step, idx)
        step //= 2
    return idx + (flat[base + idx] <= r2).astype(idx.dtype)


def jitter_filter(
    image: ChannelsLast,
    radius: Radius,
    *,
    max_radius: float,
    samples: int,
    key: Array,
    path: str = "auto",
) -> ChannelsLast:
    """Scatter with coverage estimated from `samples` jittered points per output pixel.

    `path`: `"dense"` (a gather over every tap), `"spans"` (row spans for the fully covered pixels,
    where every point hits, and counts only on the boundary taps: `spans.py`), or `"auto"`: spans
    from `JITTER_SPANS_MIN_RADIUS` on. The same counts either way (the numbers agree to rounding).
    """
    spans = use_spans(path, max_radius, crossover_for(samples, _tuning.JITTER_SPANS_MIN_RADIUS))
    dtype = image.dtype
    r = lax.stop_gradient(radius)
    small = r <= 0.5
    inv_area = jnp.where(small, 0, 1 / (math.pi * jnp.where(small, 1, r) ** 2 * samples))
    pad, _, _ = spans_layout(r.shape[0], r.shape[1], max_radius)
    # spans: every offset the boundary taps reach (a square of half-width `pad`); dense: the window
    offsets = _square(pad) if spans else tap_offsets(max_radius)
    # A concrete key (the usual case, also when closed over under jit) makes the thresholds and the
    # pattern choice compile-time constants: the precomputed set. A traced key builds them per call.
    with jax.ensure_compile_time_eval() if is_concrete(key) else contextlib.nullcontext():
        k_points, k_choice = jax.random.split(key)
        table = hit_thresholds(jitter_points(k_points, PATTERNS, samples, dtype), offsets)
        choice = jax.random.randint(k_choice, r.shape, 0, PATTERNS, jnp.int32)
    if spans:
        # the square's offsets outside the window are never hit, as in the dense gather
        outside = np.ones((2 * pad + 1,) * 2, bool)
        reach = tap_offsets(max_radius) + pad
        outside[reach[:, 0], reach[:, 1]] = False
        table = jnp.where(jnp.asarray(outside.reshape(-1, 1, 1)), jnp.inf, table)
        return _jitter_spans(image, r, max_radius, inv_area, table, choice)
    is_centre = np.all(offsets == 0, axis=-1).astype(np.float64)

    def weight(tap, src, out):
        row, centre = tap
        r_s, inv_s = src
        (pattern,) = out
        hits = count_below(row, pattern, r_s * r_s)
        return jnp.where(r_s <= 0.5, centre, hits.astype(dtype) * inv_s)

    return gather_taps(
        image,
        offsets,
        weight,
        per_tap=(table, jnp.asarray(is_centre, dtype)),
        source=(r, inv_area),
        output=(choice,),
    )


def _square(half: int) -> np.ndarray:
    """Every integer offset `(oy, ox)` with `|oy|, |ox| <= half`, row-major, `(n, 2)` int32."""
    o = np.arange(-half, half + 1)
    return np.stack(np.meshgrid(o, o, indexing="ij"), -1).reshape(-1, 2).astype(np.int32)


def _jitter_spans(image, r, max_radius, inv_area, table, choice):
    """The jittered scatter by row spans: a fully covered pixel gets all `n` hits (`1 / (pi r^2)`,
    the spans' weight); the boundary taps count the hits of their output pixel's pattern.
    `table`: `hit_thresholds` over `_square(pad)`."""
    h, w, _ = image.shape
    pad, hp, wp = spans_layout(h, w, max_radius)
    choice_flat = jnp.zeros((hp, wp), jnp.int32).at[pad : pad + h, pad : pad + w].set(choice)
    choice_flat = choice_flat.reshape(-1)
    r2 = r * r
    side = 2 * pad + 1
    rows = table.reshape(-1, table.shape[-1])  # one row per (tap, pattern) pair

    def partial(target, dy, dx):
        pattern = jnp.take(choice_flat, target, mode="clip")  # a dropped duplicate: any pattern
        tap = (dy + pad).astype(jnp.int32) * side + (dx + pad).astype(jnp.int32)
        hits = count_below(rows, tap * PATTERNS + pattern, r2[None])  # (taps, H, W)
        return hits.astype(r.dtype) * inv_area[None]

    return spans_filter(image, r, max_radius=max_radius, partial=partial)


@final
class Jitter(AbstractMethod):
    r"""Jittered coverage: `n` random points per output pixel, drawn from a `jax.random` key.

    The 2006 paper's irregular alternative to the `n x n` grid of `Supersample`: each output pixel
    `p` tests `n` points `p + s_{p,k}` against every circle of confusion. The points are stratified
    jitter (a Latin hypercube: one point in each of `n` horizontal and `n` vertical strips of the
    pixel, paired by a random permutation), a cheap approximation to the Poisson-disk distribution
    the paper cites. Source `q` of radius `r` gives pixel `p`

    $$w(p, q) = \frac{1}{\pi r_q^2}\cdot\frac{1}{n}\sum_{k=1}^{n} [\,|p + s_{p,k} - q| \le r_q\,],$$

    the paper's `e / (pi r^2)` times the estimated covered fraction of the pixel. Because the points
    are uniform in the pixel, `E[w] = area(disc ∩ pixel) / (pi r^2)`: **an unbiased estimate of the
    weight of `Soft`**, which is its `n -> infinity` limit (error `O(n^-1/2)` for independent
    points, faster for the stratified ones). Energy is conserved in expectation, not exactly. Radii
    `<= 1/2` leave their pixel untouched, as in the soft filter. The points are 16 Latin hypercubes
    drawn from `key`, one picked at random (also from `key`) for each output pixel: the paper's
    "precomputed set of numbers". The same `key` always gives the same points and the same image
    (`normalize=True` reuses them for the flat field).

    **Fields:**

    - `samples`: `n`, the points per output pixel, an int `>= 1` (default 16).
    - `key`: the `jax.random` key the points are drawn from (`jax.random.key(seed)` or
      `jax.random.PRNGKey(seed)`); required. An array leaf: a key given under `jit` is traced
      (the points are then drawn at run time, not at compile time).

    **Gradients:** linear in `image`. The coverage is a step function of the radius, so the radius
    is held constant (`stop_gradient`): `differentiable_in_radius = False`.
    """

    samples: int = eqx.field(static=True)
    key: PRNGKeyArray

    differentiable_in_radius: ClassVar[bool] = False
    local: ClassVar[bool] = False  # each pixel's pattern is drawn over the frame's shape

    def __init__(self, *, samples: int = 16, key: ArrayLike | None = None):
        self.samples = check_int("samples", samples, 1)
        self.key = check_key(key, "Jitter()", "jaxdof.Jitter(key=jax.random.key(0))")

    def spread(self, image, radius, *, max_radius, depth):
        return jitter_filter(image, radius, max_radius=max_radius, **self._options())
