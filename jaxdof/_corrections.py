"""Treatments measured against ray-traced truth (see `fits/raytraced.py`).

- `edge_weight`: a fit weight that leaves out the pixels near depth edges, where an image with
  one depth per pixel cannot know what a real aperture sees around a foreground object.
- `pixel_prefilter`: undoes the pixel footprint of the all-in-focus image before it is spread, so
  that small circles are not blurred by one pixel more than a real lens blurs them.
"""

from __future__ import annotations

import functools
import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from ._custom_types import Image, ImageLike


def depth_edges(depth: ArrayLike, *, jump: float = 0.03) -> np.ndarray:
    """Boolean `(H, W)` mask of the pixels on either side of a depth discontinuity.

    A pair of 4-neighbours is an edge when their z-depths differ by more than `jump` relative to
    the nearer one (`|d_p - d_q| / min(d_p, d_q) > jump`). A smooth surface, even a steeply slanted
    one, changes depth by well under 3% per pixel at any ordinary resolution, so the default marks
    occlusion boundaries only. Infinite depths (sky) count as far.
    """
    d = np.asarray(depth, np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth must be an (H, W) map, got shape {d.shape}")
    if not (jump > 0):
        raise ValueError(f"jump must be a positive relative depth difference, got {jump}")
    edges = np.zeros(d.shape, bool)
    for axis in (0, 1):
        a = np.moveaxis(d, axis, 0)
        lo, hi = a[:-1], a[1:]
        with np.errstate(invalid="ignore"):  # inf - inf: both sky, no edge
            rel = np.abs(lo - hi) / np.minimum(lo, hi)
        step = np.nan_to_num(rel, nan=0.0, posinf=np.inf) > jump
        e = np.moveaxis(edges, axis, 0)
        e[:-1] |= step
        e[1:] |= step
    return edges


def edge_distance(depth: ArrayLike, *, jump: float = 0.03, limit: float = 64.0) -> np.ndarray:
    """Euclidean distance (px) from every pixel to the nearest `depth_edges` pixel, capped at `limit`.

    Exact within the cap (brute force over the offsets of a disc of radius `limit`); `limit`
    everywhere when the scene has no depth edge.
    """
    edges = depth_edges(depth, jump=jump)
    h, w = edges.shape
    out = np.full((h, w), float(limit))
    if not edges.any():
        return out
    rmax = int(math.ceil(limit))
    ys, xs = np.nonzero(edges)
    # Few edge pixels: scatter their distance discs; cost ~ (#edge px) * limit^2, fine for fits.
    dy, dx = np.mgrid[-rmax : rmax + 1, -rmax : rmax + 1]
    dist = np.sqrt(dy * dy + dx * dx)
    keep = dist < limit
    dy, dx, dist = dy[keep], dx[keep], dist[keep]
    for y, x in zip(ys, xs):
        yy, xx = y + dy, x + dx
        ok = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
        np.minimum.at(out, (yy[ok], xx[ok]), dist[ok])
    return out


def edge_weight(depth: ArrayLike, *, width: float, jump: float = 0.03) -> np.ndarray:
    r"""A fit weight `(H, W)` in `[0, 1]` that leaves out pixels within `width` px of a depth edge.

    **Arguments:**

    - `depth`: z-depth `(H, W)` (any unit).
    - `width`: how far from an edge the post-process model is not trusted (px): use the largest
      circle of confusion expected near the edges (e.g. that of the starting lens), since a real
      aperture mixes foreground and background within one circle of the edge.
    - `jump`: relative depth step that counts as an edge (see `depth_edges`).

    **Returns:** `clip(distance_to_edge / width, 0, 1)^2`: zero on the edge, one from `width` px
    away; all ones when the scene has no depth edge (then it changes nothing). Pass it to
    `jaxdof.fit_lens(..., weight=...)`.

    **Why.** At an occlusion edge a real lens sees around the foreground object: the blurred
    background behind a sharp foreground edge is built from background the pinhole image never
    saw, and a defocused foreground edge is semi-transparent over the background (the partial
    occlusion of Lee, Eisemann and Seidel 2009, "Depth-of-field rendering with multiview
    synthesis"). Neither is in an image with one depth per pixel, so the fit should
    not try to explain those pixels with the lens.
    """
    if not (width > 0 and math.isfinite(width)):
        raise ValueError(f"width must be a positive number of pixels, got {width}")
    dist = edge_distance(depth, jump=jump, limit=float(width))
    return np.clip(dist / width, 0.0, 1.0) ** 2


def pixel_prefilter(image: ImageLike) -> Image:
    r"""Sharpen an all-in-focus image by one pixel footprint (a box of width 1 px), approximately.

    **Arguments:** `image`, `(H, W)` or `(H, W, C)`, linear light.

    **Returns:** `image - (\Delta_x + \Delta_y) image / 24`, with `\Delta` the discrete second
    difference along each axis (edge pixels repeated), same shape and dtype.

    **Why.** A pixel value is the average of the scene over the pixel's square, `L * box`.
    `jaxdof.coc_filter` spreads each value over a disc and integrates the disc over the receiving
    pixels, which is a second box: the model is `L * box * disc * box`, while a real lens gives
    `L * disc * box`. The extra box adds `1/12 px^2` of variance per axis; for a circle of radius
    `r` (variance `r^2/4` per axis) the fitted radius comes out near `sqrt(r^2 - 1/3)`: 18% short
    at 1 px, 4% at 2 px. The box's transfer function is `sinc(w/2) = 1 - w^2/24 + O(w^4)`, so to
    second order its inverse is `1 - \partial^2/24` per axis, and `\Delta` approximates
    `\partial^2` to the same order. The prefilter is exact for the variance (the second moment of
    the 5-tap kernel is `-1/12` per axis) and slightly amplifies texture at the Nyquist
    frequency (gain `1 + 1/3` there).

    In-focus pixels (circles under half a pixel) are copied by the filter, not spread, so they come
    out sharpened; the prefilter helps where circles are about 1 px or larger.
    """
    x = jnp.asarray(image)
    if x.ndim not in (2, 3):
        raise ValueError(f"image must be (H, W) or (H, W, C), got shape {x.shape}")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        raise ValueError(f"image must be floating point (linear light), got dtype {x.dtype}")
    pad = [(1, 1), (1, 1)] + [(0, 0)] * (x.ndim - 2)
    p = jnp.pad(x, pad, mode="edge")
    lap = p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:] - 4 * x
    return x - lap / 24


_TABLE_MAX = 6.0  # beyond, the kernel variance is rho^2/4 + c, c continued from the table's end


@functools.cache
def _kernel_variance_table() -> tuple[np.ndarray, np.ndarray]:
    """Per-axis variance (px^2) of the filter's discrete kernel `overlap(o, r) / (pi r^2)` vs `r`.

    Summing `o_x^2` times the disc area over each pixel column `o_x` is integrating `round(x)^2`
    over the disc: `Var(r) = sum_k k^2 [F(x)]_{k-1/2}^{k+1/2} / (pi r^2)` with the chord integral
    `F(x) = x sqrt(r^2 - x^2) + r^2 asin(x / r)` clipped to `[-r, r]`. Exact, in float64 numpy
    (no tracing, so it can be first called under `jit`/`vmap`).
    """
    r = np.linspace(0.5, _TABLE_MAX, 551)[:, None]
    k = np.arange(0.0, math.ceil(_TABLE_MAX) + 1)[None, :]

    def chord_integral(x):
        x = np.clip(x, -r, r)
        return x * np.sqrt(np.maximum(r * r - x * x, 0.0)) + r * r * np.arcsin(x / r)

    columns = chord_integral(k + 0.5) - chord_integral(k - 0.5)
    columns[:, 1:] *= 2  # columns k and -k
    var = (k * k * columns).sum(axis=1) / (np.pi * r[:, 0] ** 2)
    var[0] = 0.0  # r = 1/2: the disc lies inside its pixel and the filter copies it
    return r[:, 0], var


def footprint_radius(radius: ArrayLike):
    r"""Circle-of-confusion radius -> the radius to give `jaxdof.coc_filter` for a pixel-averaged image.

    **Arguments:** `radius`, the lens's circle of confusion (px), any shape.

    **Returns:** `rho(radius)`, same shape: the filter radius whose discrete kernel
    `overlap(o, rho) / (pi rho^2)` has the per-axis variance `radius^2 / 4` of the lens's disc.

    **Why.** The all-in-focus image already holds pixel averages (`L * box`); the ray-traced or
    real photo is `L * disc * box`. Spreading the averages with the overlap kernel, whose variance
    is about `rho^2/4 + 1/12` for `rho >~ 1` (slightly more: the sampled kernel), adds the box a second time, and the filter copies
    circles under half a pixel without any spread. Matching the kernel's variance to the disc's,
    `Var(rho) = r^2/4`, removes both biases to second order: `rho ~ sqrt(r^2 - 1/3)` for large
    circles, `rho -> 1/2` (a copy) as `r -> 0`, and in between the exact inverse of the kernel's
    variance, tabulated from `jaxdof.circle_pixel_overlap` and interpolated (piecewise linear,
    differentiable). Use as `coc_filter(image, footprint_radius(coc_radius(depth, lens)))`.

    **Measured** against Mitsuba (`fits/results/raytraced.md`): it removes the few-percent
    under-estimate of the blur scale that fits with the plain model show on fronto-parallel
    planes and (with `edge_weight`) on occluders, but over-corrects by a few percent on a
    slanted plane whose image holds texture near the Nyquist frequency, where the pixel values
    are not samples of a smooth `L * box`. Hence opt-in.
    """
    r = jnp.asarray(radius)
    table_r, table_var = _kernel_variance_table()
    target = r * r / 4
    small = jnp.interp(target, jnp.asarray(table_var, r.dtype), jnp.asarray(table_r, r.dtype))
    # Past the table, Var(rho) = rho^2/4 + c with c taken at the table's end (continuous there).
    c = float(table_var[-1]) - _TABLE_MAX**2 / 4
    big = jnp.sqrt(jnp.maximum(r * r - 4 * c, 0.25))
    return jnp.where(target <= table_var[-1], small, big).astype(r.dtype)
