"""`coc_filter`: the public entry point that checks inputs and dispatches on `method`."""

from __future__ import annotations

import jax.numpy as jnp

from .._custom_types import Image, ImageLike, RadiusLike
from .common import check_image_and_radius, check_max_radius
from .soft import soft_filter


METHODS = ("soft",)


def coc_filter(
    image: ImageLike,
    radius: RadiusLike,
    *,
    method: str = "soft",
    max_radius: float | None = None,
    normalize: bool = False,
) -> Image:
    r"""Spread every pixel's light uniformly over its circle of confusion (a scatter, as a gather).

    $$\text{out}[p] = \sum_q \text{image}[q]\; \frac{|\,\text{disc}(q, r_q) \cap \text{pixel}(p)\,|}
      {\pi r_q^2}$$

    over the source pixels `q` whose disc can reach `p` (offsets with `|p - q|_inf <=
    ceil(max_radius)`, corners the disc cannot reach dropped). Each weight is the exact area of the
    output pixel covered by the source's disc (`jaxdof.circle_pixel_overlap`), so the filter is
    antialiased and conserves energy: away from the borders `sum(out) == sum(image)`.

    **Arguments:**

    - `image`: linear-light image, `(H, W)` or `(H, W, C)`, floating point.
    - `radius`: circle-of-confusion radius of each source pixel, `(H, W)`, pixels, `>= 0`.
    - `method`: `"soft"` (the exact analytic coverage).
    - `max_radius`: static window size in pixels. Radii above it are clamped to it (their light
      is spread over a disc of radius `max_radius`, and the derivative with respect to the clamped
      radius is 0). `None` takes the largest radius of a concrete `radius` map: the smallest window
      the scene needs. Under `jit` it must be given.
    - `normalize`: divide by the same filter applied to an image of ones, so that pixels near the
      border, which lose light to outside the frame, keep their brightness.

    **Returns:** the filtered image, same shape and dtype as `image`.

    Radii at or below half a pixel leave their pixel untouched (exactly the identity; the
    derivative with respect to such a radius is 0). Differentiable with respect to `image` and
    `radius` in forward and reverse mode; `jit` with `max_radius` static; `vmap` over a batch.
    """
    if method not in METHODS:
        raise ValueError(f"{method=} is not one of {METHODS}")
    image, radius, was_2d = check_image_and_radius(image, radius)
    max_radius = check_max_radius(max_radius, radius)
    radius = jnp.minimum(radius, max_radius)
    channels = image.shape[-1]
    if normalize:  # filter a channel of ones alongside: the light each pixel would get from a flat field
        image = jnp.concatenate([image, jnp.ones_like(image[..., :1])], axis=-1)
    out = soft_filter(image, radius, max_radius=max_radius)
    if normalize:
        out = out[..., :channels] / out[..., channels:]
    return out[..., 0] if was_2d else out
