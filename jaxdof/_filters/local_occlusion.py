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
same weights, summed in the same order).

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

Light from hidden background (behind an occluder in the all-in-focus image) is not invented; at a
blurred foreground's edge the background that the pinhole view shows is what passes.

**Why this and not global layers (`Occlusion`).** A scene in which a floor connects the near and
the far depths has no gap in its depth histogram, so `Occlusion` renders it exactly like `Soft`
(measured on a light-field scene: every pixel equal); here every pair is decided locally, so an
object standing on a floor occludes the wall behind it. This is the scatter-as-gather with a depth
comparison of real-time depth-of-field (e.g. McGuire, "The Skylanders SWAP Force depth-of-field
shader", 2014; Jimenez, "Next generation post processing in Call of Duty: Advanced Warfare",
SIGGRAPH 2014 course), with the exact coverage weights and a planar depth prediction in place of a
raw depth comparison. `fits/occlusion_local.py` measures it against ray-traced truth.

**Gradients.** Linear in `image`; smooth in `radius` (the soft weight's derivative) and in `depth`
(through `beta`, a C1 smoothstep, and the minmod gradient, piecewise linear); plain JAX
derivatives of a checkpointed loop. **Cost.** One weight per mirror class of offsets, as the soft
filter, and per mirrored tap the depth comparison and two sums: measured 2-3x the soft filter.
"""

from __future__ import annotations

import functools as ft
from typing import ClassVar, final

import equinox as eqx
import jax.numpy as jnp
from jax import lax

from .._custom_types import DepthLike, Radius
from .base import AbstractMethod
from .common import ChannelsLast, check_depth_map, half_width, pad_rows_cols, tap_offsets
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


def local_occlusion_filter(
    image: ChannelsLast,
    radius: Radius,
    *,
    max_radius: float,
    depth: DepthLike,
    jump: float = DEFAULT_JUMP,
) -> ChannelsLast:
    """The soft scatter with per-pair occlusion (module docstring)."""
    h, w, c = image.shape
    depth = check_depth_map(depth, (h, w)).astype(image.dtype)
    offsets = tap_offsets(max_radius)
    pad = half_width(offsets)
    finite = jnp.isfinite(depth)
    u = jnp.where(finite, 1 / jnp.where(finite, depth, 1), 0)  # 0 at infinity
    gy, gx = _surface_gradient(u)
    # Inverse depths within a thousandth of the nearest's of 0 compare as at infinity: the
    # relative gap stays continuous where both the prediction and the source approach 0.
    floor = 1e-3 * lax.stop_gradient(jnp.max(u)) + jnp.finfo(image.dtype).tiny
    log_tol = jnp.log1p(jnp.asarray(jump, image.dtype))
    p_img, p_rad, p_u = (pad_rows_cols(x, pad) for x in (image, radius, u))
    zero = jnp.zeros((), jnp.int32)

    def body(k, acc, mirrors, geom):
        wgt = jnp.asarray(tap_weight(*geom, p_rad))  # the soft weight of this class, source grid
        lit = p_img * wgt[..., None]
        parts = []
        for j in range(k):
            oy, ox = mirrors[j, 0], mirrors[j, 1]
            at = (pad - oy, pad - ox)
            w_s = lax.dynamic_slice(wgt, at, (h, w))
            l_s = lax.dynamic_slice(lit, (*at, zero), (h, w, c))
            u_s = lax.dynamic_slice(p_u, at, (h, w))
            u_hat = u - gy * oy.astype(u.dtype) - gx * ox.astype(u.dtype)
            gap = 2 * (u_hat - u_s) / (jnp.abs(u_hat) + u_s + floor)
            back = _smoothstep((gap - log_tol) / log_tol)
            front = _smoothstep((-gap - log_tol) / log_tol)
            same = 1 - back - front
            parts.append(
                (
                    l_s * same[..., None],
                    w_s * same,
                    l_s * front[..., None],
                    w_s * front,
                    l_s * back[..., None],
                )
            )
        # Each class summed first, then added: the soft filter's order (`soft._shift_sum`), so
        # that with no source off its receiver's surface the sum is the soft filter's bit for bit.
        sums = [ft.reduce(lambda a, b: a + b, xs) for xs in zip(*parts)]
        return tuple(a + s for a, s in zip(acc, sums))

    img0, map0 = jnp.zeros_like(image), jnp.zeros((h, w), image.dtype)
    init = (img0, map0, img0, map0, img0)
    same, a_same, front, a_front, behind = _scan_classes(offsets, image.dtype, init, body)
    # Back to front: what lies behind the receiver's surface, under the surface, under what lies
    # in front of it; each layer lets through what its coverage leaves open.
    out = same + _transmittance(a_same)[..., None] * behind
    return front + _transmittance(a_front)[..., None] * out


@final
class LocalOcclusion(AbstractMethod):
    r"""Occlusion decided per pair of pixels from the depth around each output pixel: the soft
    scatter, with each source sorted into at-or-in-front-of or behind the receiver's surface
    (extrapolated along its inverse-depth gradient) and the two composited with `over`
    (`jaxdof/_filters/local_occlusion.py` has the math and its sources). Exactly `Soft` where no
    source lies behind its receiver's surface; differentiable in image, radius and depth.

    **Fields:**

    - `jump`: the relative depth (3 % by default, as `jaxdof.depth_edges`) beyond the receiver's
      surface from which a source starts to count as behind it (fully at twice that).
    """

    jump: float = eqx.field(static=True)

    differentiable_in_radius: ClassVar[bool] = True
    uses_depth: ClassVar[bool] = True

    def __init__(self, *, jump: float = DEFAULT_JUMP):
        if isinstance(jump, bool) or not isinstance(jump, (int, float)) or not 0 < jump <= 1:
            raise ValueError(f"jump must be a number in (0, 1], got {jump!r}")
        self.jump = float(jump)

    def spread(self, image, radius, *, max_radius, depth):
        if depth is None:
            from .soft import soft_filter

            return soft_filter(image, radius, max_radius=max_radius)
        return local_occlusion_filter(
            image, radius, max_radius=max_radius, depth=depth, jump=float(self.jump)
        )
