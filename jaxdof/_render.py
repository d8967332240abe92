"""`render`: image + depth + lens -> circle of confusion -> filter (-> the photo's pixels)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ._corrections import footprint_prefilter
from ._custom_types import DepthLike, Image, ImageLike
from ._filters import AbstractMethod, as_method, coc_filter
from ._lens import ThinLens, _check_depth, _error_if_invalid, coc_radius


def render(
    image: ImageLike,
    depth: DepthLike,
    lens: ThinLens,
    *,
    method: str | AbstractMethod = "soft",
    max_radius: float | None = None,
    normalize: bool = False,
    footprint: bool = False,
    downsample: int = 1,
) -> Image:
    """Render the depth of field of `lens` from an all-in-focus image and its depth map.

    `coc_filter(image, coc_radius(depth, lens), ...)`: see those two for the optics and the filter.

    **Arguments:**

    - `image`: all-in-focus linear-light image, `(H, W)` or `(H, W, C)`.
    - `depth`: z-depth along the optical axis (m), `(H, W)`, `> lens.focal_length`; `inf` allowed.
    - `lens`: the `ThinLens`.
    - `method`: a method object (`jaxdof.Soft()`, `jaxdof.Aperture(pattern="ring")`, a subclass
      of `jaxdof.AbstractMethod` of your own) or a built-in's name, as in `coc_filter`. A method
      that reads depth (`method.uses_depth`: `jaxdof.Occlusion`, opt-in) gets `depth` from
      `render` itself.
    - `normalize`: as in `coc_filter`: divide by the same render of an image of ones, so that the
      pixels within a circle of the frame's edge, whose light partly leaves the frame, keep
      their brightness. Which border treatment when: `normalize=True` for a picture whose
      edges should look right. For fitting a lens to a real photo, neither the default (those
      pixels lack the light that reaches them from scene points outside the frame: zeros in
      its place) nor the renormalisation (the light inside the frame, rescaled) is that
      light, so leave the band out of the comparison instead: `jaxdof.fit_lens` does by
      default (`border="auto"`: the `ceil(max_radius)` photo pixels along every edge).
    - `footprint`: opt-in pixel-footprint correction (default off): spread
      `footprint_prefilter(image, r)` instead of `image`, so that the blur of every pixel has the
      lens's variance `r^2 / 4`, also for circles under half a pixel, where the plain filter copies
      the pixel (see `jaxdof.footprint_prefilter`; measured against ray tracing in
      `fits/results/raytraced.md`).
    - `downsample`: the image and depth map are `s = downsample` times the photo's resolution in
      each axis (a pixel-shift or higher-resolution capture of the all-in-focus scene; the lens's
      `pixel_pitch` stays the photo's). The scatter runs at that resolution, with circles of
      `s r` input pixels, and its `s x s` blocks are averaged into the photo's pixels: what a
      sensor with `s` times the pitch records. Default 1 (same resolution). Why: a pixel of the
      all-in-focus image is already an average over its area, and a photo's blur of circles of a
      pixel or two depends on detail inside that area, which no filter of the averages can know;
      against ray tracing (`fits/results/raytraced.md`) a 2x input recovers most of it.
    - `max_radius`: window size in the photo's pixels (the lens's `pixel_pitch`). `None` (the
      default) uses the smallest window that covers the largest circle in the scene, which needs
      concrete inputs; under `jit` pass a number.

    **Returns:** the defocused image, `image`'s shape (each spatial axis divided by `downsample`).

    **Invalid inputs** (NaN or negative depth, depth not beyond the focal length, a lens with a
    non-positive field or `focus_distance <= focal_length`): concrete values raise `ValueError`
    before any work. Traced values (under `jit`, `grad`, `vmap`) are checked with
    `equinox.error_if`: the compiled computation raises an error with the same message when it
    runs (`EquinoxRuntimeError` under `equinox.filter_jit`, which also shows where; under
    `jax.jit` JAX re-raises it as its own runtime error), under `vmap` if any batch element is
    invalid, under `grad` in the forward pass. With `EQX_ON_ERROR=nan` the output is NaN (equinox
    makes the checked array NaN); with `off` there is no check, and a NaN radius still poisons
    every output pixel its light reaches. The check is a comparison and a reduction over the
    depth map (one pass; the filter makes one per tap).
    """
    depth = jnp.asarray(depth)
    image = jnp.asarray(image)
    s = _check_downsample(downsample, image.shape)
    method = as_method(method)
    if depth.shape != image.shape[:2]:
        raise ValueError(
            f"depth must have the image's (H, W) = {image.shape[:2]}, got {depth.shape}"
        )
    if not jnp.issubdtype(depth.dtype, jnp.floating):
        raise ValueError(f"depth must be floating point (metres), got dtype {depth.dtype}")
    _check_depth(depth, lens)  # concrete: ValueError now
    depth = _error_if_invalid(depth, lens)  # traced: error at run time (equinox.error_if)
    radius = coc_radius(depth, lens).astype(jnp.result_type(image.dtype, depth.dtype))
    if s > 1:  # circles and window in the input's pixels, s times smaller than the photo's
        radius = radius * s
        max_radius = None if max_radius is None else max_radius * s
    if footprint:  # corrected for the radius the filter spreads (clamped to the window)
        r = radius if max_radius is None else jnp.minimum(radius, max_radius)
        image = footprint_prefilter(image, r)
    out = coc_filter(
        image,
        radius,
        method=method,
        max_radius=max_radius,
        normalize=normalize,
        depth=depth if method.uses_depth else None,
    )
    return box_downsample(out, s)


def _check_downsample(downsample, shape: tuple[int, ...]) -> int:
    """`downsample` as an int, checked against the input's `(H, W, ...)` shape."""
    if isinstance(downsample, bool) or not isinstance(downsample, (int, np.integer)):
        raise ValueError(f"downsample must be a Python int >= 1, got {downsample!r}")
    s = int(downsample)
    if s < 1:
        raise ValueError(f"downsample must be >= 1, got {s}")
    h, w = (tuple(shape) + (0, 0))[:2]  # fewer than 2 axes: refused by the callers' own checks
    if h % s or w % s:
        raise ValueError(
            f"downsample={s} needs an image whose height and width are multiples of {s}, got "
            f"{h} x {w}; crop it to {h - h % s} x {w - w % s}"
        )
    return s


def box_downsample(x: Array, s: int) -> Array:
    """Means of the `s x s` blocks of `x` `(s h, s w, ...)` -> `(h, w, ...)`: a sensor with `s`
    times the pitch (linear light). `s = 1` returns `x`."""
    if s == 1:
        return x
    h, w = x.shape[0] // s, x.shape[1] // s
    return x.reshape(h, s, w, s, *x.shape[2:]).mean(axis=(1, 3))
