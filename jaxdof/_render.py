"""`render`: image + depth + lens -> circle of confusion -> filter."""

from __future__ import annotations

import jax.numpy as jnp

from ._corrections import footprint_prefilter
from ._custom_types import DepthLike, Image, ImageLike
from ._filters import coc_filter
from ._lens import ThinLens, _check_depth, _error_if_invalid, coc_radius


def render(
    image: ImageLike,
    depth: DepthLike,
    lens: ThinLens,
    *,
    method: str = "soft",
    max_radius: float | None = None,
    normalize: bool = False,
    samples: int | None = None,
    key=None,
    pattern: str | None = None,
    blades: int | None = None,
    rotation: float | None = None,
    layers: int | None = None,
    fill: bool | None = None,
    footprint: bool = False,
) -> Image:
    """Render the depth of field of `lens` from an all-in-focus image and its depth map.

    `coc_filter(image, coc_radius(depth, lens), ...)`: see those two for the optics and the filter.

    **Arguments:**

    - `image`: all-in-focus linear-light image, `(H, W)` or `(H, W, C)`.
    - `depth`: z-depth along the optical axis (m), `(H, W)`, `> lens.focal_length`; `inf` allowed.
    - `lens`: the `ThinLens`.
    - `method`, `normalize`, and the method's knobs (`samples`, `key`, `pattern`, `blades`,
      `rotation`, `layers`, `fill`): as in `coc_filter`. `method="occlusion"` (opt-in) orders the
      layers by `depth`, which `render` passes to the filter itself.
    - `footprint`: opt-in pixel-footprint correction (default off): spread
      `footprint_prefilter(image, r)` instead of `image`, so that the blur of every pixel has the
      lens's variance `r^2 / 4`, also for circles under half a pixel, where the plain filter copies
      the pixel (see `jaxdof.footprint_prefilter`; measured against ray tracing in
      `fits/results/raytraced.md`).
    - `max_radius`: window size in pixels. `None` (the default) uses the smallest window that covers
      the largest circle in the scene, which needs concrete inputs; under `jit` pass a number.

    **Returns:** the defocused image, same shape as `image`.

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
    if depth.shape != image.shape[:2]:
        raise ValueError(
            f"depth must have the image's (H, W) = {image.shape[:2]}, got {depth.shape}"
        )
    if not jnp.issubdtype(depth.dtype, jnp.floating):
        raise ValueError(f"depth must be floating point (metres), got dtype {depth.dtype}")
    _check_depth(depth, lens)  # concrete: ValueError now
    depth = _error_if_invalid(depth, lens)  # traced: error at run time (equinox.error_if)
    radius = coc_radius(depth, lens).astype(jnp.result_type(image.dtype, depth.dtype))
    knobs = dict(samples=samples, key=key, pattern=pattern, blades=blades, rotation=rotation)
    if footprint:  # corrected for the radius the filter spreads (clamped to the window)
        r = radius if max_radius is None else jnp.minimum(radius, max_radius)
        image = footprint_prefilter(image, r)
    return coc_filter(
        image,
        radius,
        method=method,
        max_radius=max_radius,
        normalize=normalize,
        layers=layers,
        depth=depth if method == "occlusion" else None,
        fill=fill,
        **knobs,
    )
