r"""The reference scatter: each pixel's light spread with the exact circle-pixel overlap.

Computed as a gather over the integer offsets `o` of the window,

$$\text{out}[p] = \sum_o \text{image}[p - o]\, w(o, r_{p - o}), \qquad
  w(o, r) = \frac{|\,\text{disc}(0, r) \cap \text{pixel}(o)\,|}{\pi r^2}.$$

Two things make it cheap:

- **Symmetry.** A disc is symmetric under the eight reflections of the square grid, so
  `w(o, r)` is the same for the up-to-eight offsets `(±oy, ±ox), (±ox, ±oy)`. The weight is computed
  once per *canonical* offset `0 <= oy <= ox`, on the source grid, and the weighted source image is
  scattered to every mirrored offset: about one eighth of the weight evaluations, and the mirrored
  additions read the same array (`symmetric_gather`).
- **A lean per-tap formula** (`tap_area`): two square roots locate the arc's end points, and the
  thin circular segment under the chord comes from one series in the sine of the quarter
  angle that converges over the whole range, so no branch is evaluated and thrown away.

The loop over offsets is a `lax.scan` whose body is checkpointed: memory stays at a few images in
the forward pass and in reverse mode (the body is recomputed instead of storing per-offset weights).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float

from .._overlap import _c, _horner, _num_terms
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


@jax.custom_jvp
def tap_weight(ax, bx, ay, by, m, centre, r):
    """Normalised weight `m |disc(r) ∩ rect| / (pi r^2)`; exactly the identity for `r <= 1/2`.

    A disc of radius at most half a pixel centred in its pixel stays inside it, so the weight is 1 at
    the centre tap and 0 elsewhere: no 0/0 as `r -> 0`, and a zero derivative (the dead zone).
    """
    big = r > 0.5
    rs = jnp.where(big, r, 1)
    area = tap_area(ax, bx, ay, by, rs)
    return jnp.where(big, m * area / (math.pi * rs * rs), centre)


@tap_weight.defjvp
def _tap_weight_jvp(primals, tangents):
    ax, bx, ay, by, m, centre, r = primals
    big = r > 0.5
    rs = jnp.where(big, r, 1)
    area, arc = tap_area(ax, bx, ay, by, rs, with_arc=True)
    inv = m / (math.pi * rs * rs)
    w = jnp.where(big, area * inv, centre)
    # d/dr [A / (pi r^2)] = (dA/dr - 2 A / r) / (pi r^2), with dA/dr the arc length inside.
    dw = jnp.where(big, (arc - 2 * area / rs) * inv, 0)
    return w, dw * tangents[-1]


def soft_filter(
    image: Float[Array, "h w c"], radius: Float[Array, "h w"], *, max_radius: float
) -> Float[Array, "h w c"]:
    """Exact soft-coverage scatter of `image` (H, W, C) by per-pixel radii, clamped to `max_radius`."""
    offsets = tap_offsets(max_radius)
    return symmetric_gather(image, radius, offsets, tap_weight)


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


def symmetric_gather(image, radius, offsets: np.ndarray, weight_fn) -> Array:
    """The same sum as `gather`, for a weight with the disc's symmetry, one weight per mirror class.

    `out[p] = sum_o image[p - o] w(o, r[p - o])` with `w` invariant under the 8 reflections of the
    grid. For each canonical offset the weighted source `image * w(o, radius)` is formed once and
    added into a padded output at each of its (1, 4 or 8) mirrored offsets, as a scatter: the
    window `out[o : o + H, o : o + W]` is read, incremented and written back in place. Written this
    way, reverse mode is cheap too: the transpose of that in-place update is a plain slice of the
    cotangent (the transpose of the gather form, slicing a padded source, would write a mostly-zero
    padded image per mirror). A checkpointed `lax.scan` per mirror class keeps memory at a few
    images, forward and reverse.
    """
    h, w, c = image.shape
    pad = int(np.abs(offsets).max()) if offsets.size else 0
    acc = jnp.zeros((h + 2 * pad, w + 2 * pad, c), image.dtype)
    zero = jnp.zeros((), jnp.int32)
    for k, (canonical, mirrors) in mirror_classes(offsets).items():
        geometry = _offset_geometry(canonical, image.dtype)
        starts = jnp.asarray(pad + mirrors, jnp.int32)  # source (0, 0) lands at pad + o

        def body(acc, xs, k=k):
            start, geom = xs
            weighted = image * weight_fn(*geom, radius)[..., None]
            for j in range(k):  # the same weighted sources, added at each mirrored offset
                at = (start[j, 0], start[j, 1], zero)
                window = lax.dynamic_slice(acc, at, (h, w, c))
                acc = lax.dynamic_update_slice(acc, window + weighted, at)
            return acc, None

        body = jax.checkpoint(body, prevent_cse=False)
        acc, _ = lax.scan(body, acc, (starts, geometry))
    return acc[pad : pad + h, pad : pad + w]
