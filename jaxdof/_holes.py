r"""Depth as sensors give it: holes (no data) in a depth map.

A time-of-flight or stereo sensor leaves pixels without a depth (no return, an occlusion shadow
between the projector and the camera, a surface too dark or too shiny), written as NaN, 0 or a
negative value. `+inf` is not a hole: it is a depth (the sky, focus at infinity's subject).

A hole's own light still reaches the photo, within its circle of confusion, so a fit cannot
use the photo pixels within a circle's reach of a hole whatever depth it guesses there:
`fit_lens` fills the holes (so that the render runs) and leaves those photo pixels out of the
residual (a zero weight), reporting how many (`Treatment.depth_holes`, `Treatment.hole_pixels`).
`render` refuses holes unless asked to fill them (`fill_holes=True`), since what it makes of
them is a guess.
"""

from __future__ import annotations

import math

import numpy as np
from jaxtyping import ArrayLike
from scipy import ndimage

from ._corrections import edge_distance_to


def depth_holes(depth: ArrayLike) -> np.ndarray:
    """Boolean `(H, W)` mask of the pixels without a depth: NaN, 0, negative (`-inf` included);
    `+inf` is a depth (infinitely far), not a hole."""
    d = np.asarray(depth)
    with np.errstate(invalid="ignore"):
        return np.isnan(d) | (d <= 0)


def fill_depth_holes(depth: ArrayLike) -> np.ndarray:
    """The depth map with every hole (`depth_holes`) set to the depth of its nearest pixel that
    has one (Euclidean distance; exact, `scipy.ndimage.distance_transform_edt`).

    **Arguments:** `depth`: a concrete `(H, W)` z-depth map (m).

    **Returns:** a copy, the dtype kept, without holes.

    **Raises:** `ValueError` when no pixel has a depth.

    Nearest-pixel filling keeps depth edges where they are (a hole beside an edge takes the
    depth of the surface it touches). A fit does not depend on the filled values: it leaves out
    every photo pixel a hole's light reaches.
    """
    d = np.asarray(depth)
    if d.ndim != 2:
        raise ValueError(f"depth must be an (H, W) map, got shape {d.shape}")
    holes = depth_holes(d)
    return filled(d, holes) if holes.any() else d.copy()


def filled(depth: np.ndarray, holes: np.ndarray) -> np.ndarray:
    """`fill_depth_holes` for a map whose holes `depth_holes` already found (a copy)."""
    if holes.all():
        raise ValueError("depth has no data: every pixel is NaN, 0 or negative")
    d = np.array(depth, copy=True)
    # the nearest pixel's indices in int32 (half the memory of scipy's default int64: 24 MP
    # frames, 1.8 -> 1.2 s)
    found = np.empty((2, *holes.shape), np.int32)
    ndimage.distance_transform_edt(
        holes, return_distances=False, return_indices=True, indices=found
    )
    d[holes] = d[found[0][holes], found[1][holes]]
    return d


def near_holes(holes: np.ndarray, reach: float, ratio: int = 1) -> np.ndarray:
    """Photo pixels `(H / ratio, W / ratio)` within `reach` image pixels of a hole of the image
    grid `holes` `(H, W)` (a pixel whose `ratio x ratio` block holds one such image pixel)."""
    if math.ceil(reach) <= 0:  # the holes themselves (no distances needed)
        near = np.asarray(holes, bool)
    else:
        near = edge_distance_to(holes, limit=float(reach) + 1.0) <= math.ceil(reach)
    h, w = near.shape
    return np.asarray(near.reshape(h // ratio, ratio, w // ratio, ratio).any(axis=(1, 3)))
