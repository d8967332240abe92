"""Pixel-footprint corrections measured against ray tracing and not adopted (study only).

`fits/raytraced.py` compares three ways to remove the extra pixel box of the post-process model
(`jaxdof.coc_filter` spreads pixel *averages*, so its blur has one box of variance `1/12 px^2` per
axis too many for circles of a pixel or more, and none for circles under half a pixel). The core
keeps the one that won, `jaxdof.footprint_prefilter` (`render(..., footprint=True)`); the other two
live here, kept for comparison and for the study's cached fits:

- `pixel_prefilter`: the image sharpened by the large-circle constant everywhere.
- `footprint_radius`: the radius changed instead of the image.

Measured in `fits/results/raytraced.md`; tested in `tests/test_raytraced.py`.
"""

from __future__ import annotations

import functools
import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike


def pixel_prefilter(image: ArrayLike) -> Array:
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
    out sharpened; the prefilter helps where circles are about 1 px or larger. Measured against
    Mitsuba (`fits/results/raytraced.md`) this sharpening of the in-focus pixels doubles the
    model's error at the true lens on a slanted plane and biases the fit;
    `jaxdof.footprint_prefilter` is this filter with a strength chosen per pixel from its circle
    (this one's `1/24` for large circles, a slight blur under half a pixel), which removes that
    bias. Kept for comparison.
    """
    x = jnp.asarray(image)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        raise ValueError(f"image must be a floating-point array, got dtype {x.dtype}")
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
    (no tracing, so it can be first called under `jit`/`vmap`). The closed form the core uses,
    differentiable in `r`, is `jaxdof.internal.kernel_variance`.
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
    is about `rho^2/4 + 1/12` for `rho >~ 1` (slightly more: the sampled kernel), adds the box a
    second time, and the filter copies circles under half a pixel without any spread. Matching the
    kernel's variance to the disc's, `Var(rho) = r^2/4`, removes both biases to second order:
    `rho ~ sqrt(r^2 - 1/3)` for large circles, `rho -> 1/2` (a copy) as `r -> 0`, and in between
    the exact inverse of the kernel's variance, tabulated from `jaxdof.circle_pixel_overlap` and
    interpolated (piecewise linear, differentiable). Use as
    `coc_filter(image, footprint_radius(coc_radius(depth, lens)))`.

    **Measured** against Mitsuba (`fits/results/raytraced.md`): it removes the few-percent
    under-estimate of the blur scale that fits with the plain model show on fronto-parallel
    planes and (with `edge_weight`) on occluders, but over-corrects by a few percent on a
    slanted plane whose image holds texture near the Nyquist frequency: a smaller disc matches
    the variance but not the shape of the transfer function at higher frequencies, and it still
    copies the circles under half a pixel. `jaxdof.footprint_prefilter` (which keeps the radius
    and corrects the image) does not over-correct there, hence the core's choice; this one is kept
    for comparison.
    """
    r = jnp.asarray(radius)
    table_r, table_var = _kernel_variance_table()
    target = r * r / 4
    small = jnp.interp(target, jnp.asarray(table_var, r.dtype), jnp.asarray(table_r, r.dtype))
    # Past the table, Var(rho) = rho^2/4 + c with c taken at the table's end (continuous there).
    c = float(table_var[-1]) - _TABLE_MAX**2 / 4
    big = jnp.sqrt(jnp.maximum(r * r - 4 * c, 0.25))
    return jnp.where(target <= table_var[-1], small, big).astype(r.dtype)
