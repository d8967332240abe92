r"""The reference scatter: each pixel's light spread with the exact circle-pixel overlap.

Computed as a gather over the integer offsets `o` of the window,

$$\text{out}[p] = \sum_o \text{image}[p - o]\, w(o, r_{p - o}), \qquad
  w(o, r) = \frac{|\,\text{disc}(0, r) \cap \text{pixel}(o)\,|}{\pi r^2}.$$

Three things make it cheap:

- **Symmetry.** A disc is symmetric under the eight reflections of the square grid, so
  `w(o, r)` is the same for the up-to-eight offsets `(±oy, ±ox), (±ox, ±oy)`. The weight is computed
  once per *canonical* offset `0 <= oy <= ox`, on the zero-padded source grid, and the weighted
  source image is read at every mirrored offset in one fused pass: about one eighth of the weight
  evaluations (`symmetric_gather`, `mirrored_scatter`).
- **A lean per-tap formula** (`tap_area`): two square roots locate the arc's end points, and the
  thin circular segment under the chord comes from one series in the sine of the quarter
  angle that converges over the whole range, so no branch is evaluated and thrown away. Each
  weight ends in a division, which XLA keeps in one fused kernel instead of re-evaluating the
  formula's tail in every consumer (each mirrored offset, each channel): the forward pass
  costs 2.8-3.4x less at R = 2-8 than with a multiply there (see `_weight_and_slope`).
- **Hand-written derivatives** (`soft_filter`): the tangent is a primitive whose transpose is a
  gather of the same shape from the padded cotangent (see the comment above `_tangent`), so
  forward and reverse mode each cost about one more pass, not a transpose that writes a padded
  image per tap.

The loops over offsets are `lax.scan`s whose bodies are checkpointed: memory stays at a few images
in the forward pass and in either mode of differentiation, whatever the window.
"""

from __future__ import annotations

import functools as ft
import math

import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.core import ShapedArray
from jax.interpreters import ad
from jaxtyping import Array

from .._custom_types import Radius
from .._overlap import _c, _horner, _num_terms
from .common import ChannelsLast, half_width, pad_rows_cols, tap_offsets


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


# With t = sin(theta / 2), theta = asin(L / 2r) <= pi/4 the half-angle of a chord of length L:
#   segment / r^2 = theta - sin(theta) cos(theta) = 16 int_0^t tau^2 sqrt(1 - tau^2) dtau
#                 = 16 t^3 sum_k b_k t^(2k) / (2k + 3),   b_k = (-1)^k binom(1/2, k),
#   arc / r      = 2 theta = 4 asin(t) = 4 t sum_k c_k t^(2k) / (2k + 1).
# t <= sin(pi/8), so both converge like 0.1465^k over the whole range: one formula, no branches.
_T2_MAX = 0.1465


def _b(k: int) -> float:
    return (-1) ** k * math.prod((0.5 - j) for j in range(k)) / math.factorial(k)


def _segment_series(dtype) -> list[float]:
    return [16 * _b(k) / (2 * k + 3) for k in range(_num_terms(dtype, _T2_MAX))]


def _arc_series(dtype) -> list[float]:
    return [4 * _c(k) / (2 * k + 1) for k in range(_num_terms(dtype, _T2_MAX))]


def _sqrt0(x: Array) -> Array:
    """`sqrt(max(x, 0))` whose derivatives of every order stay finite (0) at and below 0."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1)), 0)


def tap_area(ax, bx, ay, by, r, *, with_arc: bool = False):
    r"""Area (and arc length inside) of `disc(0, r) ∩ [ax, bx] x [ay, by]`, first quadrant.

    The same decomposition as `jaxdof._overlap._quadrant` (full columns, a trapezoid under the
    chord, the circular segment between chord and arc; all local to the rectangle, so float32 keeps
    a few rounding units of `r`), arranged to cost less per tap:

    - The arc enters the rectangle at `u`: on the top edge `(sqrt(r^2 - ay'^2), by)` when the
      top-left corner is inside the disc, else on the left edge `(ax, sqrt(r^2 - ax^2))`; it leaves
      at `v`: on the bottom edge when the bottom-right corner is outside, else on the right edge.
      Choosing the radicand before the square root takes two roots instead of four.
    - The segment `r^2 (theta - sin theta cos theta)`, `sin theta = L / 2r`, is one series in
      `t = sin(theta / 2)`, valid for every chord a unit rectangle can hold.

    `r^2 - x^2` is always formed as `(r - x)(r + x)` so that no `r^2` is differenced.
    """
    dtype = r.dtype
    t_a = (r - ax) * (r + ax)
    t_b = (r - bx) * (r + bx)
    t_c = (r - ay) * (r + ay)
    t_d = (r - by) * (r + by)
    zero = jnp.zeros((), dtype)
    # Entry point u = (ux, uy): the top-left corner (ax, by) is inside iff ax^2 < r^2 - by^2.
    top = ax * ax < t_d
    root_u = _sqrt0(jnp.where(top, t_d, t_a))
    ux = jnp.where(top, jnp.minimum(root_u, bx), ax)
    uy = jnp.where(top, by, root_u)
    # Exit point v = (vx, vy): the bottom-right corner (bx, ay) is outside iff r^2 - ay^2 < bx^2.
    bottom = t_c < bx * bx
    root_v = _sqrt0(jnp.where(bottom, t_c, t_b))
    vx = jnp.where(bottom, jnp.maximum(root_v, ax), bx)
    vy = jnp.where(bottom, ay, root_v)
    width = jnp.maximum(vx - ux, zero)  # no width, no arc
    dh = jnp.where(width > 0, uy - vy, zero)
    # s = L / 2r and t^2 = sin^2(theta/2) = s^2 / (2 (1 + sqrt(1 - s^2))), all without the chord.
    pos = r > 0
    inv_r = 1 / jnp.where(pos, r, 1)
    s2 = jnp.where(pos, (width * width + dh * dh) * (inv_r * inv_r / 4), zero)
    s2 = jnp.minimum(s2, 0.5)  # a quarter circle at most; guards rounding above it
    t2 = s2 / (2 * (1 + jnp.sqrt(1 - s2)))
    t = _sqrt0(t2)
    segment = (r * r) * (t2 * t) * _horner(t2, _segment_series(dtype))
    area = (by - ay) * (ux - ax) + width * ((uy - ay) + (vy - ay)) / 2 + segment
    if not with_arc:
        return area
    arc = r * t * _horner(t2, _arc_series(dtype))
    return area, arc


def _weight_and_slope(ax, bx, ay, by, m, centre, r, *, with_slope: bool):
    """`w = m |disc(r) ∩ rect| / (pi r^2)` and, if asked, `dw/dr`; identity and 0 for `r <= 1/2`."""
    big = r > 0.5
    rs = jnp.where(big, r, 1)
    # Each weight ends in a division, on purpose: XLA does not copy a division into the consumers
    # that read it (the mirrored shifts, every channel), so the weight is computed once per pixel
    # and class. Ending in a multiply by a precomputed 1 / (pi r^2) let XLA re-evaluate the whole
    # tail of `tap_area` in every consumer (the forward pass 2.8-3.4x slower at R = 2-8).
    disc = (math.pi / m) * (rs * rs)
    if not with_slope:
        return jnp.where(big, tap_area(ax, bx, ay, by, rs) / disc, centre)
    area, arc = tap_area(ax, bx, ay, by, rs, with_arc=True)
    w = jnp.where(big, area / disc, centre)
    # d/dr [A / (pi r^2)] = A' / (pi r^2) - 2 w / r, with A' = dA/dr the arc length inside. Written
    # with `w`, not `area`, so that the area's tail is evaluated once (in `w`), not again in `dw`.
    return w, jnp.where(big, arc / disc - 2 * w / rs, 0)


@jax.custom_jvp
def tap_weight(ax, bx, ay, by, m, centre, r):
    """Normalised weight `m |disc(r) ∩ rect| / (pi r^2)`; exactly the identity for `r <= 1/2`.

    A disc of radius at most half a pixel centred in its pixel stays inside it, so the weight is 1 at
    the centre tap and 0 elsewhere: no 0/0 as `r -> 0`, and a zero derivative (the dead zone).
    """
    return _weight_and_slope(ax, bx, ay, by, m, centre, r, with_slope=False)


@tap_weight.defjvp
def _tap_weight_jvp(primals, tangents):
    w, dw = _weight_and_slope(*primals, with_slope=True)
    return w, dw * tangents[-1]


def gather(image, radius, offsets: np.ndarray, weight_fn) -> Array:
    """`out[p] = sum_o image[p - o] * weight_fn(*geometry(o), r[p - o])` as a checkpointed scan."""
    h, w, c = image.shape
    pad = half_width(offsets)
    pimg, prad = pad_rows_cols(image, pad), pad_rows_cols(radius, pad)
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


def mirror_classes(offsets: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Group `offsets` (a set closed under the grid's 8 reflections) by canonical representative.

    Returns `{k: (canonical (n, 2), mirrors (n, k, 2))}` for `k` in 1 (the centre), 4 (on an axis or
    a diagonal) and 8 (elsewhere): the canonical offsets `0 <= oy <= ox` and their distinct images.
    """
    present = {(int(y), int(x)) for y, x in offsets}
    classes: dict[int, tuple[list, list]] = {}
    for y, x in sorted(present):
        if not 0 <= y <= x:
            continue
        images = sorted(
            {(sy * p, sx * q) for p, q in ((y, x), (x, y)) for sy in (1, -1) for sx in (1, -1)}
        )
        if not present.issuperset(images):
            raise ValueError(f"offsets are not closed under the grid's reflections at {(y, x)}")
        canonical, mirrors = classes.setdefault(len(images), ([], []))
        canonical.append((y, x))
        mirrors.append(images)
    return {
        k: (np.asarray(c, np.int32), np.asarray(m, np.int32))
        for k, (c, m) in sorted(classes.items())
    }


def _scan_classes(offsets: np.ndarray, dtype, carry, body):
    """Fold `body(k, carry, mirrors (k, 2), geometry)` over the canonical offsets of each class.

    One checkpointed `lax.scan` per class size `k` (1, 4, 8): memory stays at a few images whatever
    the window, in the forward pass and when the loop is differentiated.
    """
    for k, (canonical, mirrors) in mirror_classes(offsets).items():
        xs = (jnp.asarray(mirrors, jnp.int32), _offset_geometry(canonical, dtype))

        def step(carry, xs, k=k):
            return body(k, carry, *xs), None

        carry, _ = lax.scan(jax.checkpoint(step, prevent_cse=False), carry, xs)
    return carry


def _shift_sum(padded, mirrors, k: int, pad: int, sign: int, shape) -> Array:
    """`sum_j padded[pad + sign * o_j + p]` over the `k` mirrored offsets `o_j`, for every `p`.

    With `padded` the zero-padded `x`: `sign = -1` gives the scatter `sum_j x[p - o_j]`, `sign = +1`
    its adjoint `sum_j x[p + o_j]`. Both read one padded array, `k` slices fused into one pass.
    """
    zero = jnp.zeros((), jnp.int32)
    total = None
    for j in range(k):
        at = (pad + sign * mirrors[j, 0], pad + sign * mirrors[j, 1], zero)
        piece = lax.dynamic_slice(padded, at, shape)
        total = piece if total is None else total + piece
    assert total is not None, "a mirror class has at least one offset"
    return total


def mirrored_scatter(source, offsets: np.ndarray, shape, dtype, inputs: tuple) -> Array:
    """`out[p] = sum_o x_o[p - o]` with `x_o = source(geometry(o), *padded inputs)`.

    `source` forms, on the zero-padded `inputs` (the halo is the window's half-width), the array
    that every offset of one mirror class scatters (e.g. the weighted image); it is formed once per
    class and read at each mirrored offset (`_shift_sum`). `shape` is the output's `(H, W, C)`.
    """
    pad = half_width(offsets)
    padded = tuple(pad_rows_cols(x, pad) for x in inputs)

    def body(k, acc, mirrors, geom):
        return acc + _shift_sum(source(geom, *padded), mirrors, k, pad, -1, shape)

    return _scan_classes(offsets, dtype, jnp.zeros(shape, dtype), body)


def symmetric_gather(image, radius, offsets: np.ndarray, weight_fn) -> Array:
    """The same sum as `gather`, for a weight with the disc's symmetry, one weight per mirror class.

    `out[p] = sum_o image[p - o] w(o, r[p - o])` with `w` invariant under the 8 reflections of the
    grid. For each canonical offset the weighted source `image * w(o, radius)` is formed once, on the
    source grid, and read at each of its (1, 4 or 8) mirrored offsets.
    """

    def weighted(geom, image, radius):
        return image * weight_fn(*geom, radius)[..., None]

    return mirrored_scatter(weighted, offsets, image.shape, image.dtype, (image, radius))


# The soft filter with hand-written derivatives.
#
# The scatter is linear in the image and smooth in the radius, so its tangent is
#   T(dI, dr) = sum_o S_o(dI * w_o(r) + I * dr * w_o'(r)),   (S_o x)[p] = x[p - o],
# and, as the offsets of a mirror class are closed under negation, its adjoint is a gather of the
# same shape from the cotangent, padded once:
#   dI* = sum_o w_o(r) S_o^T ct,   dr* = sum_o w_o'(r) <I, S_o^T ct>_channels,   S_o^T = S_{-o}.
# Left to JAX, the transpose of the padded-slice loop would write a zero-padded image per mirrored
# tap. The tangent is therefore a primitive whose transpose rule is that gather: forward mode
# (`jvp`, `linearize`: what Levenberg-Marquardt uses) and reverse mode both cost about one more
# filter pass, vmap works through equinox's vprim, and higher derivatives are JAX's own through
# `_tangent` (correct, not tuned).


def _tangent(image, radius, d_image, d_radius, *, max_radius: float) -> Array:
    """`T(dI, dr)`: one pass per canonical offset computing `w` and `w'` together."""

    def source(geom, image, radius, d_image, d_radius):
        w, dw = _weight_and_slope(*geom, radius, with_slope=True)  # pyright: ignore[reportCallIssue]
        return d_image * w[..., None] + image * (dw * d_radius)[..., None]

    inputs = (image, radius, d_image, d_radius)
    return mirrored_scatter(source, tap_offsets(max_radius), image.shape, image.dtype, inputs)


def _adjoint(image, radius, cotangent, *, max_radius: float) -> tuple[Array, Array]:
    """`(dI*, dr*)`, the adjoint of `T` applied to `cotangent`.

    `dr* = sum_c I_c sum_o w_o' (S_o^T ct)_c`: the loop accumulates `sum_o w_o' S_o^T ct` per
    channel and the channel sum with the image is taken once after it; summing over the (short,
    innermost) channel axis inside the loop cost more than the rest of the adjoint.
    """
    offsets = tap_offsets(max_radius)
    pad = half_width(offsets)
    padded = pad_rows_cols(cotangent, pad)

    def body(k, acc, mirrors, geom):
        d_image, d_slope = acc
        w, dw = _weight_and_slope(*geom, radius, with_slope=True)  # pyright: ignore[reportCallIssue]
        g = _shift_sum(padded, mirrors, k, pad, +1, image.shape)
        return d_image + g * w[..., None], d_slope + g * dw[..., None]

    init = (jnp.zeros_like(image), jnp.zeros_like(image))
    d_image, d_slope = _scan_classes(offsets, image.dtype, init, body)
    return d_image, jnp.sum(image * d_slope, axis=-1)


def _tangent_impl(image, radius, d_image, d_radius, *, max_radius):
    return [_tangent(image, radius, d_image, d_radius, max_radius=max_radius)]


def _tangent_abstract_eval(image, radius, d_image, d_radius, *, max_radius):
    return [ShapedArray(image.shape, image.dtype)]


def _materialise(tangent, primal):
    return jnp.zeros(primal.shape, primal.dtype) if type(tangent) is ad.Zero else tangent


def _tangent_jvp(primals, tangents, *, max_radius):
    tangents = tuple(_materialise(t, p) for t, p in zip(tangents, primals))
    out, d_out = jax.jvp(ft.partial(_tangent, max_radius=max_radius), tuple(primals), tangents)
    return [out], [d_out]


def _tangent_transpose(cts, image, radius, d_image, d_radius, *, max_radius):
    (ct,) = cts
    if ad.is_undefined_primal(image) or ad.is_undefined_primal(radius):
        raise ValueError("the soft filter's tangent is linear in (d_image, d_radius) only")
    if ct is None:
        return [None, None, None, None]
    ct_image, ct_radius = _adjoint(image, radius, ct, max_radius=max_radius)
    return [
        None,
        None,
        ct_image if ad.is_undefined_primal(d_image) else None,
        ct_radius if ad.is_undefined_primal(d_radius) else None,
    ]


_soft_tangent_p = eqxi.create_vprim(
    "jaxdof_soft_tangent", _tangent_impl, _tangent_abstract_eval, _tangent_jvp, _tangent_transpose
)


@ft.partial(jax.custom_jvp, nondiff_argnums=(2,))
def _soft(image, radius, max_radius: float):
    return symmetric_gather(image, radius, tap_offsets(max_radius), tap_weight)


@_soft.defjvp
def _soft_jvp(max_radius, primals, tangents):
    image, radius = primals
    d_image, d_radius = tangents
    (d_out,) = _soft_tangent_p.bind(image, radius, d_image, d_radius, max_radius=max_radius)
    return _soft(image, radius, max_radius), d_out


def soft_filter(image: ChannelsLast, radius: Radius, *, max_radius: float) -> ChannelsLast:
    """Exact soft-coverage scatter of `image` (H, W, C) by per-pixel radii, clamped to `max_radius`.

    Forward mode and reverse mode each cost about one more pass of the same shape as the filter
    (see `_soft_tangent_p` above).
    """
    return _soft(image, radius, float(max_radius))
