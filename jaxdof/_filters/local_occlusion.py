r"""`LocalOcclusion`: the soft scatter with occlusion decided per pair of pixels, from the depth
around each output pixel, not from the whole image's depth histogram.

The soft filter (`soft.py`) sums every source's disc of light at every output pixel `p`,
whatever stands in front of it. A real aperture does not: a surface behind the one seen at `p`
reaches `p` only through the part of the aperture that the nearer surface leaves open. Here each
source `s = p - o` is sorted, relative to the receiver `p`, into *in front of* `p`'s surface
(`F`), *on* it (`S`) or *behind* it (`B`), and the three are composited back to front with
`over`:

$$\mathrm{out}_p = F_p + t(\alpha^F_p) \bigl(S_p + t(\alpha^S_p)\, B_p\bigr), \qquad
  X_p = \sum_{s \in X} w_s I_s, \quad \alpha^X_p = \sum_{s \in X} w_s,$$

with the transmittance `t(alpha) = max(1 - alpha, 0)` (smoothed to C1 within 0.05 below 1), and

`w_s = w(o, r_s)` the soft filter's exact circle-pixel weight (`soft.tap_weight`). So a sharp foreground keeps its
edge in front of a blurred background (its own coverage at `p` is 1: the background light there is
blocked), and a blurred foreground is semi-transparent over a sharp background (where it covers
half of `p`, half of the background's light passes). Where every source lies on its receiver's
surface `F` and `B` are empty and the result is **exactly the soft filter** (bit for bit: the
same weights, summed in the same order; `S` is the whole sum less `F` and `B`, which are then 0).

**Behind which surface.** Sorting by depth alone (`z_s > z_p`) would split every receding floor
or wall, whose depth changes across any window, into a near and a far part. Instead the source's
inverse depth `u_s = 1/z_s` is compared with what the receiver's own surface would have at the
source's pixel, extrapolated along its inverse-depth gradient (inverse depth is affine in image
coordinates on any plane seen in perspective, so a plane predicts itself exactly):

$$\hat u_s = u_p - \nabla u_p \cdot o, \qquad g_s = \frac{2 (\hat u_s - u_s)}{|\hat u_s| + u_s +
  10^{-3} \max u}, \qquad \beta_s = \mathrm{smoothstep}\Bigl(\frac{g_s - \tau}{\tau}\Bigr),$$

`g_s` the relative gap (about `log(u_hat / u_s)` when small; the floor keeps it continuous where
both approach focus at infinity, `u = 0`),

`beta_s = 0` while the source is less than `tau` (relative, `jump`, default 3 %, as
`jaxdof.depth_edges`) behind that prediction, 1 beyond `2 tau`, and smooth between: the source's
weight goes to `B` with `beta_s`, to `F` with the same function of the gap the other way, and to
`S` with the rest. The gradient `\nabla u_p` is the smaller in magnitude of
the one-sided differences on each axis (minmod), so a receiver beside a depth edge extrapolates
its own surface, not the jump. A surface curved within one window, or a slope the extrapolation
misses by more than `tau`, reads as an edge (conservative: it only lets less light through).

**Fill: the surfaces that the all-in-focus image hides.** The pinhole image shows one surface per
pixel; a real aperture, seeing from beside the pinhole, also sees some of what lies behind an
occluder. Without a fill that light is missing: a dark halo around every occluder (measured on
the ray-traced scenes: 5-13 dB worse than `Occlusion` within 2 px of depth edges). Two cases, both
zero where `F` and `B` are empty, so the result stays exactly the soft filter there:

1. *The receiver's surface hidden by what is in front of it* (a background pixel beside a sharp
   foreground). The receiver's circle (radius `r_p`) reaches pixels whose sources lie in front of
   its surface; continued behind them, the surface would have sent `w(o, r_p)` from each. That
   part is filled with the mean colour of what is seen of the surface, and is as opaque:

   $$H_p = \sum_{s \in F} w(o, r_p), \qquad S_p \leftarrow S_p + H_p \frac{S_p}{\alpha^S_p},
     \qquad \alpha^S_p \leftarrow \alpha^S_p + H_p.$$

2. *The background hidden behind the receiver* (a pixel of a blurred foreground near its edge,
   whose own circles cover it only in part). What `t(alpha^S)` lets through should show the
   background behind `p`, which the pinhole image hides; the sources behind cover `p` only by
   `alpha^B`, and the rest is filled with their mean colour:

   $$B_p \leftarrow B_p + t(\alpha^B_p)\, \frac{B_p + \lambda \tilde B_p}{\alpha^B_p + \lambda
     \tilde\alpha^B_p + \epsilon}, \qquad \tilde B_p = \sum_{s \in B,\ o \in \star} w(o, r_p)\,
     I_s, \quad \tilde\alpha^B_p = \sum_{s \in B,\ o \in \star} w(o, r_p),$$

   the mean weighted by each source's own coverage of `p` plus `lambda = 0.1` times the
   receiver's circle weight, which still finds a sharp background (whose own circles reach no
   neighbour of it); the second sum runs over the taps on the axes and diagonals (`star`, the
   mirror classes of 4 offsets: the same fill to 0.1 dB, and the filter about 10 % faster than
   with every tap). `epsilon = 1e-4` fades the fill out smoothly as the last source behind stops
   counting as behind (a bounded derivative in depth).

Chosen by measurement (`fits/occlusion_local.py`, PSNR within 2 px of depth edges, mean of the 4
lenses of each tuning scene, planes / occluders, dB): no fill 20.42 / 19.86; case 1 alone
23.58 / 24.71; with case 2 filled by `B / alpha^B` alone 27.35 / 27.66 (dark where the background is
sharp); by the receiver-weighted mean alone 29.00 / 28.10; by the combination above 29.83 / 28.20
(every tap: 29.75 / 28.22); `Occlusion` 30.51 / 28.72. Case 1's colour from the receiver's own
pixel (29.43 / 27.46) or from a Gaussian of 1 px about it (29.65 / 27.86) did worse than the mean
over the circle. On the tuning scenes the fill stays 0.15-1.15 dB behind `Occlusion` in the edge
band. Held out (never tuned on): on `ground` (curved objects standing on a floor) it gains 12.9 dB
there (21.25 -> 34.13) and beats `Occlusion` (29.71) on all four lenses, by 3.1-6.4 dB; on `fgbg`
(a card before a wall, focused on either; added after every constant here was chosen) it gains
9.2 dB (15.83 -> 25.03) but stays behind `Occlusion` (26.10), by 1.9 dB where the card is sharp
and 0.2-0.3 dB where it is blurred. Where it trails, the loss sits on the side of the edge that a
fill decides (tuning planes, A = 0.1, within 2 px, this fill against `Occlusion`'s: at d_f = 1.8
the background side, 26.8 against 29.1 dB, the foreground side equal at 27.2; at d_f = 3.0, its
foreground blurred before a sharper background, the foreground side, 26.8 against 28.5): a mean
colour over the receiver's circle stands in for the hidden surface where `Occlusion` takes the
colour of the nearest visible pixel of the hidden layer. Its cost: 2.0-3.0x the soft filter at
the same window (without the fill 1.6-2.8x, `Occlusion` 5.8-11.6x; the fastest of 25 rounds timed
in turns, 2-core CPU).

**Why this and not global layers (`Occlusion`).** A scene in which a floor connects the near and
the far depths has no gap in its depth histogram, so `Occlusion` renders it exactly like `Soft`
(measured on a light-field scene: every pixel equal); here every pair is decided locally, so an
object standing on a floor occludes the wall behind it. This is the scatter-as-gather with a depth
comparison of real-time depth-of-field (e.g. McGuire, "The Skylanders SWAP Force depth-of-field
shader", 2014; Jimenez, "Next generation post processing in Call of Duty: Advanced Warfare",
SIGGRAPH 2014 course), with the exact coverage weights and a planar depth prediction in place of a
raw depth comparison. `fits/occlusion_local.py` measures it against ray-traced truth.

**Gradients.** Linear in `image` (the fills are weighted means of the image, times coverages
that do not depend on it); smooth in `radius` (the soft weight's derivative) and in `depth`
(through `beta`, a C1 smoothstep, and the minmod gradient, piecewise linear); the fills' means
divide by a coverage that is at least the receiver's own weight (case 1, with a double `where`) or
`epsilon` (case 2); plain JAX derivatives of a checkpointed loop. **Cost.** One weight per mirror
class of offsets, as the soft filter, and per mirrored tap the depth comparison and the sums of
`S + F + B`, `F`, `B` (light and coverage in one array each) and `H`, on the star taps also
`tilde B`: measured 2.0-3.0x the soft filter (1.6-2.8x without the fill).
"""

from __future__ import annotations

import functools as ft
import math
from typing import ClassVar, final

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Bool

from .._custom_types import DepthLike, Radius
from .base import AbstractMethod
from .common import (
    ChannelsLast,
    check_bool,
    check_depth_map,
    half_width,
    pad_rows_cols,
    tap_offsets,
)
from .occlusion import DEFAULT_JUMP
from .soft import _scan_classes, tap_weight


def _minmod(a, b):
    """The one of `a`, `b` smaller in magnitude where they agree in sign, else 0."""
    return jnp.where(a * b > 0, jnp.where(jnp.abs(a) < jnp.abs(b), a, b), 0)


def _surface_gradient(u):
    """`(du/dy, du/dx)` of the inverse depth, one-sided differences combined by minmod (edges of
    the frame: the one difference there is)."""

    def along(x, axis):
        d = jnp.diff(x, axis=axis)
        zero = jnp.zeros_like(lax.slice_in_dim(d, 0, 1, axis=axis))
        back = jnp.concatenate([zero, d], axis=axis)  # u[i] - u[i-1]
        fwd = jnp.concatenate([d, zero], axis=axis)  # u[i+1] - u[i]
        n = x.shape[axis]
        idx = jnp.arange(n).reshape((-1, 1) if axis == 0 else (1, -1))
        both = _minmod(back, fwd)
        return jnp.where(idx == 0, fwd, jnp.where(idx == n - 1, back, both))

    return along(u, 0), along(u, 1)


# The transmittance `1 - alpha` meets 0 at full coverage in a cubic over `alpha` in
# `[1 - 2 _KNEE, 1]` (value and slope continuous at both ends, 0 with slope 0 at 1): C1, so that
# forward and reverse derivatives agree where a coverage sums to 1 up to rounding (the kink of
# `max(1 - alpha, 0)` there let the rematerialised reverse pass take the other branch: 3e-4
# apart in `check_grads`), and still exactly 0 where a surface covers the pixel wholly.
_KNEE = 0.025


def _transmittance(alpha):
    """`max(1 - alpha, 0)`, smoothed within `2 _KNEE` below full coverage."""
    x = jnp.clip(1 - alpha, 0, 2 * _KNEE)
    cubic = x * x / _KNEE - x * x * x / (4 * _KNEE * _KNEE)
    return jnp.where(alpha <= 1 - 2 * _KNEE, 1 - alpha, cubic)


def _smoothstep(t):
    t = jnp.clip(t, 0, 1)
    return t * t * (3 - 2 * t)


def _mean(total, weight):
    """`total / weight` (a weighted mean), 0 where `weight` is not positive; the double `where`
    keeps the derivative finite there."""
    ok = weight > 0
    return jnp.where(ok, total / jnp.where(ok, weight, 1), 0)


# The hidden background's colour: the mean of the sources behind the receiver, weighted by their
# own circles' coverage of it plus this times the receiver's circle weight (`w(o, r_p)`), which
# still reaches a sharp background (whose own circles reach no neighbour).
_FILL_RECEIVER = 0.1
# Added to that mean's weight: the fill fades out smoothly as the last source behind the receiver
# stops counting as behind (a bounded derivative in depth, where a plain quotient's grows without
# bound), and is exactly 0 where no source is behind.
_FILL_FLOOR = 1e-4
# The receiver-weighted part of that mean is summed over the mirror classes of 4 offsets only, the
# taps on the axes and the diagonals (8 directions): the same fill to 0.1 dB on the study's tuning
# scenes, and the whole filter about 10 % faster than with every tap.
_STAR = 4


def local_occlusion_filter(
    image: ChannelsLast,
    radius: Radius,
    *,
    max_radius: float,
    depth: DepthLike,
    jump: float = DEFAULT_JUMP,
    fill: bool = True,
    occlude: bool | Array = True,
) -> ChannelsLast:
    """The soft scatter with per-pair occlusion, and with `fill` the hidden surfaces filled
    (module docstring). `occlude` False (a Python bool or a scalar boolean array, chosen at run
    time) puts every source on its receiver's surface: the soft filter, bit for bit."""
    h, w, c = image.shape
    dtype = image.dtype
    depth = check_depth_map(depth, (h, w)).astype(dtype)
    offsets = tap_offsets(max_radius)
    pad = half_width(offsets)
    finite = jnp.isfinite(depth)
    u = jnp.where(finite, 1 / jnp.where(finite, depth, 1), 0)  # 0 at infinity
    gy, gx = _surface_gradient(u)
    # Inverse depths within a thousandth of the nearest's of 0 compare as at infinity: the
    # relative gap stays continuous where both the prediction and the source approach 0.
    floor = 1e-3 * lax.stop_gradient(jnp.max(u)) + jnp.finfo(dtype).tiny
    inv_tol = 1 / math.log1p(jump)
    if not (isinstance(occlude, bool) and occlude):
        # 0: every relative gap is 0, so no source leaves its receiver's surface (F = B = 0).
        inv_tol = inv_tol * jnp.asarray(occlude).astype(dtype)
    p_rad, p_u = (pad_rows_cols(x, pad) for x in (radius, u))
    # The colour with a channel of ones (0 outside the frame: no source there): weighted, the
    # light and the coverage in one array (one sum for both, the cheaper for it).
    p_one = pad_rows_cols(jnp.concatenate([image, jnp.ones((h, w, 1), dtype)], -1), pad)
    zero = jnp.zeros((), jnp.int32)

    def body(k, acc, mirrors, geom):
        wgt = jnp.asarray(tap_weight(*geom, p_rad))  # the soft weight of this class, source grid
        lit = p_one * wgt[..., None]  # (light, coverage) of each source
        star = fill and k == _STAR
        parts = []
        for j in range(k):
            oy, ox = mirrors[j, 0], mirrors[j, 1]
            at = (pad - oy, pad - ox)
            l_s = lax.dynamic_slice(lit, (*at, zero), (h, w, c + 1))
            u_s = lax.dynamic_slice(p_u, at, (h, w))
            u_hat = u - gy * oy.astype(dtype) - gx * ox.astype(dtype)
            # the relative gap in units of the tolerance
            gap = (u_hat - u_s) * (2 * inv_tol) / (jnp.abs(u_hat) + u_s + floor)
            off = _smoothstep(jnp.abs(gap) - 1)  # off the receiver's surface
            back = jnp.where(gap > 0, off, 0)
            front = off - back
            part = [l_s, l_s * front[..., None], l_s * back[..., None]]
            if fill:
                part.append(front)
            if star:
                part.append(lax.dynamic_slice(p_one, (*at, zero), (h, w, c + 1)) * back[..., None])
            parts.append(part)
        # Each class summed first, then added: the soft filter's order (`soft._shift_sum`), so
        # that with no source off its receiver's surface the sum is the soft filter's bit for bit.
        sums = [ft.reduce(lambda a, b: a + b, xs) for xs in zip(*parts)]
        if fill:
            w_recv = lax.dynamic_slice(wgt, (pad, pad), (h, w))  # the receiver's radius
            sums[3] = sums[3] * w_recv
            sums.append(sums.pop() * w_recv[..., None] if star else jnp.zeros((), dtype))
        return tuple(a + s for a, s in zip(acc, sums))

    lit0, map0 = jnp.zeros((h, w, c + 1), dtype), jnp.zeros((h, w), dtype)
    init = (lit0, lit0, lit0) + ((map0, lit0) if fill else ())
    return _composite(list(_scan_classes(offsets, dtype, init, body)), c, fill)


def _composite(sums: list, c: int, fill: bool):
    """`local_occlusion_filter`'s output from its sums over the window (light and coverage of
    all sources, of those in front of and behind the receiver's surface; with `fill`, the
    hidden share of the receiver's circle and the sources around it): the layers composited
    back to front."""
    (total, a_total), (front, a_front), (behind, a_behind) = (
        (x[..., :c], x[..., c]) for x in sums[:3]
    )
    # On the receiver's surface: all but what lies off it (exactly the soft sum where none does).
    same, a_same = total - front - behind, a_total - a_front - a_behind
    if fill:
        hidden, around = sums[3], sums[4]
        # 1. The receiver's surface hidden behind the sources in front of it (their pixels' part
        # of the receiver's circle): the mean colour of what is seen of it, as opaque as the rest.
        same = same + hidden[..., None] * _mean(same, a_same[..., None])
        a_same = a_same + hidden
        # 2. The background hidden behind the receiver (the pinhole image shows the receiver
        # there): where the sources behind cover the receiver only in part, the mean colour of
        # those sources fills the rest.
        fill_sum = behind + _FILL_RECEIVER * around[..., :c]
        fill_weight = a_behind + _FILL_RECEIVER * around[..., c] + _FILL_FLOOR
        filled = fill_sum / fill_weight[..., None]
        behind = behind + _transmittance(a_behind)[..., None] * filled
    # Back to front: what lies behind the receiver's surface, under the surface, under what lies
    # in front of it; each layer lets through what its coverage leaves open.
    out = same + _transmittance(a_same)[..., None] * behind
    return front + _transmittance(a_front)[..., None] * out


@final
class LocalOcclusion(AbstractMethod):
    r"""Occlusion decided per pair of pixels from the depth around each output pixel: the soft
    scatter, with each source sorted into in front of, on or behind the receiver's surface
    (extrapolated along its inverse-depth gradient), the three composited with `over`, and the
    surfaces that the all-in-focus image hides filled from what is seen of them
    (`jaxdof/_filters/local_occlusion.py` has the math, its sources and what it measured).
    Exactly `Soft` where no source leaves its receiver's surface; differentiable in image, radius
    and depth.

    **Fields:**

    - `jump`: the relative depth (3 % by default, as `jaxdof.depth_edges`) beyond the receiver's
      surface from which a source starts to count as behind it (fully at twice that).
    - `fill`: fill the hidden surfaces (default `True`); `False` composites only the light that
      the all-in-focus image shows (dark halos beside occluders; kept for the study).
    - `occlude`: `False` puts every source on its receiver's surface, which renders `Soft` bit
      for bit at this method's cost; a scalar boolean array chooses at run time, so that the
      occlusion render and the soft one share a compiled program (`fit_lens` tries both on a
      small photo with depth edges at the cost of one compile). Default `True`.
    """

    jump: float = eqx.field(static=True)
    fill: bool = eqx.field(static=True)
    occlude: bool | Bool[Array, ""]

    differentiable_in_radius: ClassVar[bool] = True
    uses_depth: ClassVar[bool] = True

    def __init__(
        self, *, jump: float = DEFAULT_JUMP, fill: bool = True, occlude: bool | Array = True
    ):
        if isinstance(jump, bool) or not isinstance(jump, (int, float)) or not 0 < jump <= 1:
            raise ValueError(f"jump must be a number in (0, 1], got {jump!r}")
        self.jump = float(jump)
        self.fill = check_bool("fill", fill)
        if isinstance(occlude, bool):
            self.occlude = occlude
        else:  # a scalar boolean array (traced or not): chosen at run time
            arr = occlude if isinstance(occlude, jax.Array) else np.asarray(occlude)
            if arr.shape != () or arr.dtype != bool:
                raise ValueError(
                    f"occlude must be a bool or a scalar boolean array, got {occlude!r}"
                )
            self.occlude = jnp.asarray(arr)

    def spread(self, image, radius, *, max_radius, depth):
        if depth is None:
            from .soft import soft_filter

            return soft_filter(image, radius, max_radius=max_radius)
        return local_occlusion_filter(
            image,
            radius,
            max_radius=max_radius,
            depth=depth,
            jump=self.jump,
            fill=self.fill,
            occlude=self.occlude,
        )
