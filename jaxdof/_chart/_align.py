r"""The chart's homography refined against the photo with the fitted lens's blur.

`detect_chart` aligns the chart's raster with the photo blurred by one uniform disc, while a
tilted chart's circles grow and shrink across it: the outline comes out a few tenths of a pixel
off, and the focal length in pixels that the homography gives (hence the chart's depth and the
focus distance) by a few percent. Once a lens is fitted its render of the chart has each
pixel's own circle; aligning that render with the photo puts the corners within about a tenth
of a pixel.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from jaxtyping import Float
from scipy import ndimage

from .._holes import near_holes
from ._detect import ChartView, _linear, _project
from ._geometry import _hom4


_STEP_PX = 1e-3  # the corners' finite-difference step (pixels)
_ITERATIONS = 20  # Levenberg-Marquardt steps at most
_STOP_PX = 1e-3  # a step that moves no corner further than this ends the search
_SAMPLES = 400_000  # chart pixels compared at most (a regular subsample beyond)
_MARGIN_PX = 2  # kept clear of the chart's outline beyond the largest circle
# `detect_chart` places the corners within about half a pixel: a move beyond this is the
# template's error (a lens far off), not the chart's, and the view is kept as it was.
_MAX_MOVE_PX = 2.0


def align_view(
    photo: np.ndarray,
    view: ChartView,
    template: Float[np.ndarray, "h w"],
    at: Float[np.ndarray, "3 3"],
    usable: np.ndarray,
) -> tuple[ChartView, float]:
    r"""`(view, moved)`: `view` with the homography that best aligns `template` with `photo`,
    and the largest distance (pixels) a corner of the chart's outline moved.

    **Arguments:**

    - `photo`: the photo, `(H, W)` or `(H, W, C)` (linear light, or integers in sRGB).
    - `view`: the chart as found in it (`detect_chart`).
    - `template`: the chart as the fitted lens renders it, `(H, W)` (linear light, on any
      scale), through the homography `at` (the pose's, near `view`'s).
    - `usable`: `(H, W)` bool, the pixels whose render is the chart's alone (each circle wholly
      on the chart).

    **Method.** The unknowns are the moves `\delta` (pixels) of the outline's four corners,
    `H(\delta)` the homography through the moved corners; the template is resampled through
    `A H(\delta)^{-1}` (`A` = `at`; cubic splines) and compared with the photo after the best gain,
    quadratic across the frame, and offset (solved exactly at each `\delta`: the print's
    uneven light). Levenberg-Marquardt on the eight moves, its Jacobian by finite differences.
    Where the search does not improve the match, or moves a corner by more than 2 px (more than
    the detection's error: the template is off), `view` is returned.
    """
    h, w = np.shape(photo)[:2]
    ys, xs = np.nonzero(usable)
    if ys.size < 64:
        return view, 0.0
    every = max(1, math.ceil(ys.size / _SAMPLES))
    ys, xs = ys[::every], xs[::every]
    target = _linear(np.asarray(photo)[ys, xs][None])[0].astype(np.float64)  # the samples' only
    coefs = ndimage.spline_filter(np.asarray(template, np.float64), order=3)
    u, v = (xs - w / 2) / w, (ys - h / 2) / w
    basis = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v])
    points = np.column_stack([xs, ys, np.ones(xs.size)])
    h0 = np.asarray(at, np.float64)
    chart, seen = view.outline_m, view.outline

    def homography(delta):
        return _hom4(chart, seen + delta.reshape(4, 2))

    def residual(delta):
        q = points @ (h0 @ np.linalg.inv(homography(delta))).T
        t = ndimage.map_coordinates(
            coefs, [q[:, 1] / q[:, 2], q[:, 0] / q[:, 2]], order=3, prefilter=False, mode="nearest"
        )
        a = np.column_stack([(basis * t).T, np.ones_like(t)])
        coef, *_ = np.linalg.lstsq(a, target, rcond=None)
        return a @ coef - target

    delta, r0 = np.zeros(8), residual(np.zeros(8))
    r, damping = r0, 1e-3
    for _ in range(_ITERATIONS):
        jac = np.column_stack([(residual(delta + _STEP_PX * e) - r) / _STEP_PX for e in np.eye(8)])
        g, jj = jac.T @ r, jac.T @ jac
        while damping < 1e8:
            move = -np.linalg.solve(jj + damping * np.diag(np.diag(jj)), g)
            r_new = residual(delta + move)
            if r_new @ r_new < r @ r:
                delta, r, damping = delta + move, r_new, damping / 3
                break
            damping *= 4
        else:
            break
        if np.abs(move).max() < _STOP_PX:
            break
    moved = float(np.abs(_project(homography(delta), chart) - seen).max())
    if not r @ r < r0 @ r0 or not moved <= _MAX_MOVE_PX:
        return view, 0.0
    return dataclasses.replace(view, homography=homography(delta)), moved


def usable_pixels(depth: Float[np.ndarray, "h w"], reach: float) -> np.ndarray:
    """The pixels on the chart (finite `depth`) at least `reach` plus a margin pixels inside its
    outline: their circles of confusion hold the chart's light alone."""
    return ~near_holes(~np.isfinite(depth), reach + _MARGIN_PX)
