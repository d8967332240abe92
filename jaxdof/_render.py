"""`render`: image + depth + lens -> circle of confusion -> filter."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ._custom_types import DepthLike, Image, ImageLike
from ._filters import coc_filter
from ._filters.common import is_concrete
from ._lens import ThinLens, coc_radius


def render(
    image: ImageLike,
    depth: DepthLike,
    lens: ThinLens,
    *,
    method: str = "soft",
    max_radius: float | None = None,
    normalize: bool = False,
) -> Image:
    """Render the depth of field of `lens` from an all-in-focus image and its depth map.

    `coc_filter(image, coc_radius(depth, lens), ...)`: see those two for the optics and the filter.

    **Arguments:**

    - `image`: all-in-focus linear-light image, `(H, W)` or `(H, W, C)`.
    - `depth`: z-depth along the optical axis (m), `(H, W)`, `> lens.focal_length`; `inf` allowed.
    - `lens`: the `ThinLens`.
    - `method`, `normalize`: as in `coc_filter`.
    - `max_radius`: window size in pixels. `None` (the default) uses the smallest window that covers
      the largest circle in the scene, which needs concrete inputs; under `jit` pass a number.

    **Returns:** the defocused image, same shape as `image`.

    Concrete depths are checked: NaN, or not beyond the focal length, raise `ValueError`.
    """
    depth = jnp.asarray(depth)
    image = jnp.asarray(image)
    if depth.shape != image.shape[:2]:
        raise ValueError(
            f"depth must have the image's (H, W) = {image.shape[:2]}, got {depth.shape}"
        )
    if not jnp.issubdtype(depth.dtype, jnp.floating):
        raise ValueError(f"depth must be floating point (metres), got dtype {depth.dtype}")
    if is_concrete(depth, lens.focal_length):
        d, f = np.asarray(depth), np.asarray(lens.focal_length)
        if np.any(np.isnan(d)) or np.any(d <= f):
            raise ValueError(
                "depth must be beyond the focal length everywhere (metres; NaN, negative and "
                f"depths <= focal_length={f} m cannot be imaged)"
            )
    radius = coc_radius(depth, lens).astype(jnp.result_type(image.dtype, depth.dtype))
    return coc_filter(image, radius, method=method, max_radius=max_radius, normalize=normalize)
