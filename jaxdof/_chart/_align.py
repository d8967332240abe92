r"""The chart's homography refined against the photo with the fitted lens's blur.

`detect_chart` aligns the chart's raster with the photo blurred by one uniform disc, while a
tilted chart's circles grow and shrink across it: the outline comes out a few tenths of a pixel
off, and the focal length in pixels that the homography gives (hence the chart's depth and the
focus distance) by a few percent. Once a lens is fitted its render of the chart has each
pixel's own circle; aligning that render with the photo puts the corners within about a tenth
of a pixel.

Only the template's pixels around the compared ones are rendered: all of the chart's usable
pixels up to `_SAMPLES`, beyond that square patches on a grid over the chart, rendered side by
side as one mosaic.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from jaxtyping import Float
from scipy import ndimage

from .._holes import near_holes
from .._lens import ThinLens
from .._render import render
from ._detect import ChartView, _linear, _project
from ._geometry import _hom4


_STEP_PX = 1e-3  # the corners' finite-difference step (pixels)
_ITERATIONS = 20  # Levenberg-Marquardt steps at most
_STOP_PX = 1e-3  # a step that moves no corner further than this ends the search
_SAMPLES = 400_000  # chart pixels compared at most (square patches on a grid beyond)
_PATCH = 96  # the patches' side (px): a 7 x 7 grid of them holds about `_SAMPLES` pixels
# The template's pixels kept around the compared ones: the cubic spline's prefilter decays by
# 0.27 a pixel (16 px: 1e-9), and the corners move up to `_MAX_MOVE_PX`.
_SPLINE_PAD = 20
_MARGIN_PX = 2  # kept clear of the chart's outline beyond the largest circle
# `detect_chart` places the corners within about half a pixel: a move beyond this is the
# template's error (a lens far off), not the chart's, and the view is kept as it was.
_MAX_MOVE_PX = 2.0


@dataclasses.dataclass(frozen=True)
class Samples:
    """The photo pixels `align_view` compares, `(ys, xs)`, grouped by the boxes
    `(r0, r1, c0, c1)` of the template they need (`boxes[k]` holds `ys[groups[k]]`, each at
    least `_SPLINE_PAD` from the box's edges, or at the frame's)."""

    ys: np.ndarray
    xs: np.ndarray
    boxes: tuple[tuple[int, int, int, int], ...]
    groups: tuple[np.ndarray, ...]


def alignment_samples(usable: np.ndarray) -> Samples:
    """The pixels `align_view` compares: every `usable` one, in one box, where they are at most
    `_SAMPLES`; else those in a grid of `_PATCH`-pixel squares spread over the usable pixels'
    bounding box (each square its own box), so that the template is rendered around them only."""
    ys, xs = np.nonzero(usable)
    if ys.size == 0:
        return Samples(ys, xs, (), ())
    h, w = usable.shape
    lo_r, hi_r, lo_c, hi_c = int(ys.min()), int(ys.max()) + 1, int(xs.min()), int(xs.max()) + 1
    if ys.size <= _SAMPLES:
        patches = [(lo_r, hi_r, lo_c, hi_c)]
    else:
        n = math.ceil(math.sqrt(_SAMPLES / _PATCH**2))
        # (squares apart: no more of them along an axis than it holds)
        n_r, n_c = (min(n, max(1, span // _PATCH)) for span in (hi_r - lo_r, hi_c - lo_c))
        rows = np.linspace(lo_r, max(lo_r, hi_r - _PATCH), n_r).round().astype(int)
        cols = np.linspace(lo_c, max(lo_c, hi_c - _PATCH), n_c).round().astype(int)
        patches = [(int(r), int(r) + _PATCH, int(c), int(c) + _PATCH) for r in rows for c in cols]
    out_ys, out_xs, boxes, groups, count = [], [], [], [], 0
    for r0, r1, c0, c1 in patches:
        py, px = np.nonzero(usable[r0:r1, c0:c1])
        if py.size == 0:
            continue
        out_ys.append(py + r0)
        out_xs.append(px + c0)
        groups.append(np.arange(count, count + py.size))
        count += py.size
        pad = _SPLINE_PAD
        boxes.append((max(0, r0 - pad), min(h, r1 + pad), max(0, c0 - pad), min(w, c1 + pad)))
    return Samples(np.concatenate(out_ys), np.concatenate(out_xs), tuple(boxes), tuple(groups))


def render_template(
    sharp: np.ndarray, depth: np.ndarray, lens: ThinLens, boxes, reach: float
) -> list[np.ndarray]:
    """The chart as `lens` renders it (`jaxdof.render`, holes filled), on each of `boxes`
    `(r0, r1, c0, c1)`: one render of a mosaic of the boxes, each with the `reach` (px) of the
    light it sees around it, apart from the next by that much of darkness."""
    if not boxes:
        return []
    h, w = depth.shape
    m = math.ceil(reach) + 1  # (and the pixel that the circle's edge covers in part)
    heights = [r1 - r0 + 2 * m for r0, r1, _, _ in boxes]
    widths = [c1 - c0 + 2 * m for _, _, c0, c1 in boxes]
    offsets = np.concatenate([[0], np.cumsum(widths)])
    image = np.zeros((max(heights), int(offsets[-1]), *sharp.shape[2:]), np.float32)
    dmap = np.full(image.shape[:2], np.nan, np.float32)  # holes, filled by `render`
    for (r0, r1, c0, c1), at in zip(boxes, offsets[:-1]):
        a0, a1, b0, b1 = max(0, r0 - m), min(h, r1 + m), max(0, c0 - m), min(w, c1 + m)
        rows = slice(a0 - (r0 - m), a1 - (r0 - m))
        cols = slice(int(at) + b0 - (c0 - m), int(at) + b1 - (c0 - m))
        image[rows, cols] = sharp[a0:a1, b0:b1]
        dmap[rows, cols] = depth[a0:a1, b0:b1]
    out = np.asarray(render(image, dmap, lens, fill_holes=True))
    return [
        out[m : m + r1 - r0, int(at) + m : int(at) + m + c1 - c0]
        for (r0, r1, c0, c1), at in zip(boxes, offsets[:-1])
    ]


def align_view(
    photo: np.ndarray,
    view: ChartView,
    templates: list[np.ndarray],
    at: Float[np.ndarray, "3 3"],
    samples: Samples,
) -> tuple[ChartView, float]:
    r"""`(view, moved)`: `view` with the homography that best aligns the template with `photo`,
    and the largest distance (pixels) a corner of the chart's outline moved.

    **Arguments:**

    - `photo`: the photo, `(H, W)` or `(H, W, C)` (linear light, or integers in sRGB).
    - `view`: the chart as found in it (`detect_chart`).
    - `templates`: the chart as the fitted lens renders it (linear light, on any scale), through
      the homography `at` (the pose's, near `view`'s), on each of `samples.boxes`
      (`render_template`).
    - `samples`: the pixels compared (`alignment_samples` of those whose render is the chart's
      alone: each circle wholly on the chart, `usable_pixels`).

    **Method.** The unknowns are the moves `\delta` (pixels) of the outline's four corners,
    `H(\delta)` the homography through the moved corners; the template is resampled through
    `A H(\delta)^{-1}` (`A` = `at`; cubic splines) and compared with the photo after the best gain,
    quadratic across the frame, and offset (solved exactly at each `\delta`: the print's
    uneven light). Levenberg-Marquardt on the eight moves, its Jacobian by finite differences.
    Where the search does not improve the match, or moves a corner by more than 2 px (more than
    the detection's error: the template is off), `view` is returned.
    """
    h, w = np.shape(photo)[:2]
    ys, xs = samples.ys, samples.xs
    if ys.size < 64:
        return view, 0.0
    target = _linear(np.asarray(photo)[ys, xs][None])[0].astype(np.float64)  # the samples' only
    coefs = [ndimage.spline_filter(np.asarray(t, np.float64), order=3) for t in templates]
    u, v = (xs - w / 2) / w, (ys - h / 2) / w
    basis = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v])
    points = np.column_stack([xs, ys, np.ones(xs.size)])
    h0 = np.asarray(at, np.float64)
    chart, seen = view.outline_m, view.outline

    def homography(delta):
        return _hom4(chart, seen + delta.reshape(4, 2))

    def resampled(q):
        t = np.empty(q.shape[0])
        for c, (r0, _, c0, _), k in zip(coefs, samples.boxes, samples.groups):
            y, x = q[k, 1] / q[k, 2] - r0, q[k, 0] / q[k, 2] - c0
            t[k] = ndimage.map_coordinates(c, [y, x], order=3, prefilter=False, mode="nearest")
        return t

    def residual(delta):
        t = resampled(points @ (h0 @ np.linalg.inv(homography(delta))).T)
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
