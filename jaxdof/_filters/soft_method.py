r"""`Soft`, the reference method: which of the exact soft kernels runs.

The disc by the dense gather (`soft.py`) or by row spans (`spans.py`, from `SPANS_MIN_RADIUS` on),
a polygonal diaphragm by the exact polygon-pixel overlap (`soft_polygon.py`). Its own module
because `spans.py` builds on `soft.py`.
"""

from __future__ import annotations

from typing import ClassVar, final

import equinox as eqx

from .base import AbstractMethod
from .common import check_blades, check_rotation
from .soft_polygon import soft_polygon_filter
from .spans import exact_soft_filter


@final
class Soft(AbstractMethod):
    r"""The exact soft coverage: every pixel's light spread uniformly over its circle of confusion.

    $$\text{out}[p] = \sum_q \text{image}[q]\; \frac{|\,\text{disc}(q, r_q) \cap
      \text{pixel}(p)\,|}{\pi r_q^2}$$

    over the source pixels `q` whose disc can reach `p`. Each weight is the exact area of the output
    pixel covered by the source's disc (`jaxdof.circle_pixel_overlap`), so the filter is antialiased
    and conserves energy, and it is differentiable in the radius with the area's analytic
    derivative. The reference that the other methods approximate: `Supersample` and `Jitter`
    converge to it as `samples -> infinity`, `Layered` equals it on at most `layers` distinct
    radii, `Auto` always gives its numbers. Radii `<= 1/2` are exactly the identity (derivative 0).

    Below `max_radius = 40` (`jaxdof/_tuning.py: SPANS_MIN_RADIUS`, the measured crossover) it is a gather over
    the window's offsets, one weight per mirror class (`jaxdof/_filters/soft.py`); from there on the
    same sum by row spans of fully covered pixels plus the analytic boundary pixels, whose cost grows
    linearly in the radius (`jaxdof/_filters/spans.py`). Both give the same numbers to rounding.
    Inside `fit_lens`'s Jacobian the spans start earlier for a one-channel image
    (`SPANS_MIN_RADIUS_JACOBIAN`: their tangents move only the boundary taps).

    With `blades`, the disc is replaced by the regular polygon of `b = blades` sides inscribed in
    the circle of confusion, its vertices at angles `rotation + 2 pi j / b` (radians,
    counter-clockwise from the +x axis, y pointing down the image rows):

    $$w(o, r) = \frac{|\,P_r \cap \text{pixel}(o)\,|}{|P_r|},\qquad
      |P_r| = \tfrac{b}{2} r^2 \sin\tfrac{2\pi}{b},$$

    the overlap computed analytically (Green's theorem over the clipped boundaries,
    `jaxdof/_filters/shape.py`): energy conserved, differentiable in `radius` almost everywhere
    (not where a vertex or an edge passes exactly through a pixel corner or along a pixel edge).

    **Fields:**

    - `blades`: `None` (a circular aperture, the default) or the number of diaphragm blades, an int
      in `[3, 1024]`.
    - `rotation`: the polygon's rotation in radians (default 0); only with `blades`.

    `differentiable_in_radius = True`.
    """

    blades: int | None = eqx.field(static=True)
    rotation: float = eqx.field(static=True)

    differentiable_in_radius: ClassVar[bool] = True

    def __init__(self, *, blades: int | None = None, rotation: float = 0.0):
        self.blades = check_blades(blades)
        self.rotation = check_rotation(rotation, self.blades, "Soft")

    def spread(self, image, radius, *, max_radius, depth):
        if self.blades is None:
            # the dense gather, or row spans from SPANS_MIN_RADIUS on (same numbers, faster)
            return exact_soft_filter(image, radius, max_radius=max_radius)
        return soft_polygon_filter(image, radius, max_radius=max_radius, **self._options())
