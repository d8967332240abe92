"""The textbook circle-pixel overlap that `jaxdof.circle_pixel_overlap` avoids (study only).

Kept as the comparison of `fits/stability.py` (its float32 error at every radius) and of
`tests/test_overlap.py` (the digits it loses at a large radius).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike


def textbook_overlap(dx: ArrayLike, dy: ArrayLike, r: ArrayLike) -> Array:
    r"""Area of disc(0, r) ∩ the unit square centred at `(dx, dy)`, by inclusion-exclusion.

    $$A = F(x_1, y_1) - F(x_0, y_1) - F(x_1, y_0) + F(x_0, y_0),\qquad
      F(x, y) = \int_0^x \min\!\left(y, \sqrt{r^2 - t^2}\right) dt,$$

    over the square's corners `x_{0,1} = dx -+ 1/2`, `y_{0,1} = dy -+ 1/2`, with the
    antiderivative `(t sqrt(r^2 - t^2) + r^2 asin(t / r)) / 2`. The first-quadrant form: valid for
    squares in the first quadrant (`dx, dy >= 1/2`). Its terms are `r^2`-sized and differenced, so
    float32 loses most digits at large `r` (and the arcsine's argument can round past 1: NaN);
    `jaxdof.circle_pixel_overlap` computes the same area from quantities local to the pixel.
    """
    dx, dy, r = jnp.asarray(dx), jnp.asarray(dy), jnp.asarray(r)

    def prim(t):
        return 0.5 * (t * jnp.sqrt(r * r - t * t) + r * r * jnp.arcsin(t / r))

    def big_f(x, y):
        xm = jnp.sqrt(jnp.maximum(r * r - y * y, 0))
        xa, xb = jnp.minimum(x, xm), jnp.minimum(x, r)
        return y * xa + prim(xb) - prim(xa)

    x0, x1, y0, y1 = dx - 0.5, dx + 0.5, dy - 0.5, dy + 0.5
    return big_f(x1, y1) - big_f(x0, y1) - big_f(x1, y0) + big_f(x0, y0)
