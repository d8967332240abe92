"""`Hard`: a pixel belongs to a circle of confusion when its centre is inside it."""

from __future__ import annotations

from typing import ClassVar, final

import jax.numpy as jnp
import numpy as np
from jax import lax

from .._custom_types import Radius
from .base import AbstractMethod
from .common import ChannelsLast, window_half_width
from .taps import gather_taps


def centre_offsets(max_radius: float) -> np.ndarray:
    """Integer offsets `(n, 2)` whose pixel centre lies within `max_radius` of the origin."""
    w = window_half_width(max_radius)
    o = np.arange(-w, w + 1)
    oy, ox = np.meshgrid(o, o, indexing="ij")
    keep = oy * oy + ox * ox <= max_radius * max_radius
    return np.stack([oy[keep], ox[keep]], axis=-1).astype(np.int32)


def hard_filter(image: ChannelsLast, radius: Radius, *, max_radius: float) -> ChannelsLast:
    """Energy-preserving hard-disc scatter of `image` (H, W, C) by per-pixel radii `<= max_radius`."""
    offsets = centre_offsets(max_radius)
    d2 = (offsets.astype(np.float64) ** 2).sum(-1)
    r2 = lax.stop_gradient(radius) ** 2  # no gradient in r: say so with zeros, not noise
    # N(r) = number of offsets with |o|^2 <= r^2: a search in the sorted squared norms
    count = jnp.searchsorted(jnp.asarray(np.sort(d2), radius.dtype), r2, side="right")
    scaled = image / count.astype(image.dtype)[..., None]

    def weight(tap, src, out):
        (d2_o,) = tap
        (r2_src,) = src
        return (d2_o <= r2_src).astype(image.dtype)

    return gather_taps(
        scaled, offsets, weight, per_tap=(jnp.asarray(d2, radius.dtype),), source=(r2,)
    )


@final
class Hard(AbstractMethod):
    r"""Hard discs: a pixel belongs to a circle of confusion when its centre is inside it.

    Yu's uniform light distribution, and the 2006 paper's "simplest algorithm" (section 3.1.2):
    source `q` of radius `r` gives every pixel `p` with `|p - q| <= r` the same share of its light,

    $$\text{out}[p] = \sum_q \text{image}[q]\,\frac{[\,|p - q| \le r_q\,]}{N(r_q)},\qquad
      N(r) = \#\{o \in \mathbb{Z}^2 : |o| \le r\}.$$

    Dividing by the count `N(r)` of covered pixels (Gauss's circle problem), not by `pi r^2`, makes
    the filter conserve energy exactly; the paper's `e / (pi r^2)` does not, and its brightness
    jumps as `r` crosses the radius of a lattice point (the moiré of its figure 4). `r < 1` covers
    only the source pixel: the identity. No options.

    **Gradients:** linear in `image` (exact gradient). Piecewise constant in `radius`: the
    derivative with respect to the radius is zero almost everywhere (and the jumps are not
    differentiable), so this method cannot fit a lens (`differentiable_in_radius = False`).
    """

    differentiable_in_radius: ClassVar[bool] = False

    def spread(self, image, radius, *, max_radius, depth):
        return hard_filter(image, radius, max_radius=max_radius)
