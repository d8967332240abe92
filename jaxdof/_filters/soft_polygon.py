r"""The soft filter with a polygonal diaphragm: exact polygon-pixel overlap.

Same scatter as `soft.py`, with the disc replaced by the regular polygon of `blades` sides inscribed
in the circle of confusion (see `shape.py`):

$$w(o, r) = \frac{|\,P_r \cap \text{pixel}(o)\,|}{|P_r|},\qquad |P_r| = \tfrac{b}{2} r^2 \sin\tfrac{2\pi}{b}.$$

The overlap is computed analytically (Green's theorem over the clipped boundaries,
`shape.polygon_pixel_overlap`), so the weights sum to one (energy conserved) and are differentiable
in `radius` almost everywhere (not where a vertex or an edge passes exactly through a pixel corner
or along a pixel edge). Radii `<= 1/2` leave their pixel untouched (the polygon stays inside it).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .._custom_types import Radius
from .common import ChannelsLast, tap_offsets
from .shape import area_factor, polygon_pixel_overlap
from .taps import gather_taps


def soft_polygon_filter(
    image: ChannelsLast, radius: Radius, *, max_radius: float, blades: int, rotation: float
) -> ChannelsLast:
    """Exact-coverage scatter with a `blades`-gon aperture of circumradius `radius`."""
    dtype = image.dtype
    offsets = tap_offsets(max_radius)
    is_centre = np.all(offsets == 0, axis=-1).astype(np.float64)
    factor = area_factor(blades)

    def weight(tap, src, out):
        o, centre = tap
        (r,) = src
        big = r > 0.5
        rs = jnp.where(big, r, 1)
        area = polygon_pixel_overlap(o[1] + 0 * rs, o[0] + 0 * rs, rs, blades, rotation)
        return jnp.where(big, area / (factor * rs * rs), centre)

    return gather_taps(
        image,
        offsets,
        weight,
        per_tap=(jnp.asarray(offsets, dtype), jnp.asarray(is_centre, dtype)),
        source=(radius,),
    )
