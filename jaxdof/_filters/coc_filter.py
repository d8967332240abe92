"""`coc_filter`: the public entry point that checks the inputs and runs a method object."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .._custom_types import DepthLike, Image, ImageLike, RadiusLike
from .aliases import as_method
from .base import AbstractMethod
from .common import check_depth_map, check_image_and_radius, check_max_radius, is_concrete


def coc_filter(
    image: ImageLike,
    radius: RadiusLike,
    *,
    method: str | AbstractMethod = "soft",
    max_radius: float | None = None,
    normalize: bool = False,
    depth: DepthLike | None = None,
) -> Image:
    r"""Spread every pixel's light over its circle of confusion (a scatter, computed as a gather).

    $$\text{out}[p] = \sum_q \text{image}[q]\; k_{r_q}(p - q)$$

    over the source pixels `q` whose circle can reach `p` (offsets with `|p - q|_inf <=
    ceil(max_radius)`), with the kernel `k_r` of `method`, which sums to one. The reference,
    `jaxdof.Soft`, takes `k_r(o) = |disc(0, r) ∩ pixel(o)| / (pi r^2)`, the exact area of the
    output pixel covered by the source's disc (`jaxdof.circle_pixel_overlap`): antialiased, and
    conserving energy (away from the borders `sum(out) == sum(image)`).

    **Arguments:**

    - `image`: linear-light image, `(H, W)` or `(H, W, C)`, floating point.
    - `radius`: circle-of-confusion radius of each source pixel, `(H, W)`, pixels, `>= 0`.
    - `method`: how the light is spread: a method object, which holds its own options, or the
      name of a built-in one with its default options (`"soft"` is `jaxdof.Soft()`). Built in
      (each class's docstring has its model, options and sources):
        - `Soft(blades=None, rotation=0.0)` (`"soft"`, the default): the exact analytic coverage
          above, the reference; `blades` makes the diaphragm a regular polygon.
        - `Hard()` (`"hard"`): a pixel is covered when its centre is inside the disc. No gradient
          in `radius`.
        - `Supersample(samples=4, blades=None, rotation=0.0)` (`"supersample"`): coverage counted
          on `samples x samples` sub-pixel points. No gradient in `radius`.
        - `Jitter(samples=16, key=...)`: coverage estimated from `samples` random points per
          output pixel, drawn from `key` (required, so no default alias runs: `"jitter"` raises
          and says so). No gradient in `radius`.
        - `Aperture(samples=64, pattern="stratified", key=None, blades=None, rotation=0.0)`
          (`"aperture"`): the accumulation buffer, `samples` bilinear splats at lens positions of
          `pattern`; the random patterns need `key`.
        - `Layered(layers=8)` (`"layered"`): radii quantised to `layers` levels, one soft disc
          kernel each; equal to `Soft` on at most `layers` distinct radii. Gradient in `radius`
          only through the level means.
        - `Occlusion(layers=4, fill=True)` (`"occlusion"`, opt-in): depth-ordered layers
          composited with `over` (reads `depth`).
        - `Auto()` (`"auto"`): what the concrete radius map needs (`jaxdof.choose_method`),
          always `Soft`'s numbers; `Soft` itself when the radius map is traced.

      `Supersample` and `Jitter` converge to `Soft` as `samples -> infinity`: the analytic overlap
      is their limit. Subclass `jaxdof.AbstractMethod` to bring your own.
    - `max_radius`: static window size in pixels. Radii above it are clamped to it (their light
      is spread over a disc of radius `max_radius`, and the derivative with respect to the clamped
      radius is 0). `None` takes the largest radius of a concrete `radius` map: the smallest window
      the scene needs. Under `jit` it must be given.
    - `normalize`: divide by the same filter applied to an image of ones, so that pixels near the
      border, which lose light to outside the frame, keep their brightness.
    - `depth`: z-depth `(H, W)` (e.g. metres) for a method that reads it (`method.uses_depth`:
      `Occlusion`); any other method refuses it. `jaxdof.render` passes its own.

    **Returns:** the filtered image, same shape and dtype as `image`.

    On a concrete `radius` map the method's `prepare` runs first (e.g. `Auto`'s choice, `Layered`'s
    levels). Radii at or below half a pixel leave their pixel untouched (exactly the identity; the
    derivative with respect to such a radius is 0) for every built-in method except `Aperture`
    (whose bilinear splat of a sub-pixel shift blurs slightly). Linear in `image`; differentiable
    with respect to `radius` where `method.differentiable_in_radius`; `jit` with `max_radius`
    static; `vmap` over a batch.
    """
    method = as_method(method)
    if depth is not None and not method.uses_depth:
        raise ValueError(
            f"method {type(method).__name__}() does not use depth (only a method with "
            "uses_depth = True, e.g. jaxdof.Occlusion(), reads it); drop depth= or pick such a "
            "method"
        )
    # a concrete map is inspected in numpy before anything is staged into a surrounding jit
    static_radius = np.asarray(radius) if is_concrete(radius) else None
    image, radius, was_2d = check_image_and_radius(image, radius)
    if depth is not None:
        depth = check_depth_map(depth, (image.shape[0], image.shape[1]))
    max_radius = check_max_radius(max_radius, radius)
    if static_radius is None:
        # A NaN radius (possible under jit with EQX_ON_ERROR=nan or off) must not pass for a
        # sharp pixel (NaN fails `r > 1/2`, the identity test): poison its light instead, so every
        # output pixel it reaches is NaN.
        image = jnp.where(jnp.isnan(radius)[..., None], jnp.nan, image)
    radius = jnp.minimum(radius, max_radius)
    if static_radius is not None:
        method = method.prepare(np.minimum(static_radius, max_radius), max_radius)
    channels = image.shape[-1]
    if normalize:
        # filter a channel of ones alongside: the light each pixel would get from a flat field
        image = jnp.concatenate([image, jnp.ones_like(image[..., :1])], axis=-1)
    extra = {"depth": depth} if method.uses_depth else {}
    out = method(image, radius, max_radius=max_radius, **extra)
    if normalize:
        out = out[..., :channels] / out[..., channels:]
    return out[..., 0] if was_2d else out
