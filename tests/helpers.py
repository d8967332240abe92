"""Shared references and scenes for the tests: slow, obviously-correct float64 numpy code."""

import mpmath
import numpy as np


def overlap_by_integration(dx: float, dy: float, r: float) -> float:
    """Area of disc(0, r) ∩ unit square at (dx, dy) by 30-digit quadrature of the column heights.

    Independent of the library: integrates `len({y in [y0, y1] : x^2 + y^2 <= r^2})` over x with
    mpmath's tanh-sinh rule, split at the kinks where the circle crosses y0 and y1.
    """
    with mpmath.workdps(30):
        dx, dy, r = mpmath.mpf(dx), mpmath.mpf(dy), mpmath.mpf(r)
        x0, x1 = max(dx - 0.5, -r), min(dx + 0.5, r)
        if x1 <= x0:
            return 0.0
        y0, y1 = dy - 0.5, dy + 0.5

        def column(x):
            h = mpmath.sqrt(max(r * r - x * x, 0))
            return max(min(y1, h) - max(y0, -h), 0)

        kinks = []
        for y in (y0, y1):
            if abs(y) < r:
                xm = mpmath.sqrt(r * r - y * y)
                kinks += [k for k in (-xm, xm) if x0 < k < x1]
        return float(mpmath.quad(column, [x0, *sorted(set(kinks)), x1]))


def scatter_reference(image: np.ndarray, radius: np.ndarray, overlap) -> np.ndarray:
    """Literal scatter loop over source pixels: each spreads `image[q] * overlap / (pi r^2)`.

    `overlap(dx, dy, r)` is a vectorised float64 area function. Radii <= 1/2 stay in their pixel.
    """
    image = np.asarray(image, np.float64)
    squeeze = image.ndim == 2
    if squeeze:
        image = image[..., None]
    h, w, _ = image.shape
    out = np.zeros_like(image)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    for qy in range(h):
        for qx in range(w):
            r = float(radius[qy, qx])
            if r <= 0.5:
                out[qy, qx] += image[qy, qx]
                continue
            wgt = np.asarray(overlap(xx - qx, yy - qy, r)) / (np.pi * r * r)
            out += wgt[..., None] * image[qy, qx]
    return out[..., 0] if squeeze else out


def step_scene(h: int = 24, w: int = 28, seed: int = 0):
    """A random texture with a radius map of depth steps (0 .. 20 px) and a smooth ramp."""
    rng = np.random.default_rng(seed)
    image = rng.uniform(size=(h, w, 3))
    radius = np.where(np.arange(w)[None, :] < w // 2, 0.0, 7.3) + np.zeros((h, 1))
    radius[h // 2 :, :] = np.linspace(0.0, 20.0, w)[None, :]
    return image, radius
