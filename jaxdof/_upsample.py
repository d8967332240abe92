r"""A depth map coarser than the image (a time-of-flight or stereo sensor), upsampled to it.

`upsample_depth` interpolates the sensor's depth in inverse depth where the surface is smooth and,
where a 2 x 2 cell of coarse samples spans a depth discontinuity, gives each fine pixel the depth of
the surface whose colour it has (a winner-take-all joint bilateral upsampling). `depth_ratio` says
how much coarser a depth map is than an image, or why the two do not fit together.
"""

from __future__ import annotations

import math

import numpy as np
from jaxtyping import ArrayLike

from ._corrections import depth_edges
from ._holes import depth_holes, filled


def depth_ratio(depth_shape: tuple[int, ...], image_shape: tuple[int, ...]) -> tuple[float, float]:
    """How many image pixels one depth pixel spans, `(H / h, W / w)`; `(1.0, 1.0)` when the two
    have the same resolution.

    **Arguments:** `depth_shape` `(h, w)`; `image_shape` `(H, W)` or `(H, W, C)`.

    **Returns:** the two ratios (floats `>= 1`, not necessarily integers).

    **Raises:** `ValueError`, naming both shapes, when the depth is not `(h, w)`, the image not
    `(H, W[, C])`, the depth is larger than the image along an axis, or the two frames' aspect
    ratios disagree by more than one image pixel (`|W - w H / h| > 1` or `|H - h W / w| > 1`):
    the depth map must cover the image's whole field of view, sampled on a regular grid.
    """
    shapes = f"depth {tuple(depth_shape)} and image {tuple(image_shape)}"
    if len(depth_shape) != 2 or len(image_shape) not in (2, 3):
        raise ValueError(f"{shapes}: expected a depth (h, w) and an image (H, W) or (H, W, C)")
    (h, w), (big_h, big_w) = depth_shape, image_shape[:2]
    if min(h, w, big_h, big_w) < 1:
        raise ValueError(f"{shapes}: empty")
    if h > big_h or w > big_w:
        raise ValueError(
            f"{shapes}: the depth map is larger than the image; pass the image at full "
            "resolution, or downsample the depth to the image's shape first"
        )
    if abs(big_w - w * big_h / h) > 1 + 1e-9 or abs(big_h - h * big_w / w) > 1 + 1e-9:
        raise ValueError(
            f"{shapes}: aspect ratios differ by more than one image pixel "
            f"({big_h / h:.4g}x vertically, {big_w / w:.4g}x horizontally); the depth map must "
            "cover the image's whole field of view (crop both to the same view)"
        )
    return big_h / h, big_w / w


def upsample_depth(
    depth: ArrayLike, image: ArrayLike, *, jump: float = 0.03, sigma_color: float = 0.1
) -> np.ndarray:
    r"""A z-depth map `(h, w)` upsampled to the image's resolution `(H, W)`, guided by the image
    at depth discontinuities.

    **Arguments:**

    - `depth`: z-depth `(h, w)` (m), coarser than the image or the same shape. NaN, 0 and
      negative values are holes (no data); `+inf` is infinitely far (the sky).
    - `image`: the all-in-focus image `(H, W)` or `(H, W, C)`, linear light, any scale, over the
      same field of view: depth pixel `i` covers image rows `[i H / h, (i + 1) H / h)` (as a
      resize of the whole frame; the ratio need not be an integer, `depth_ratio`).
    - `jump`: the relative depth step that counts as a discontinuity (`depth_edges`' `jump`).
    - `sigma_color`: the colour difference worth one coarse pixel of distance when choosing a
      surface, in units of `sqrt(image / mean(image))` per channel.

    **Returns:** z-depth `(H, W)` (m), float32 for a float32 `depth`, float64 otherwise; `inf`
    where the sky is, NaN on the image pixels whose depth pixel is a hole (the fit leaves them
    out), finite elsewhere. At the same resolution, a copy of `depth`, unchanged (holes as given).

    **Raises:** `ValueError` (`depth_ratio`) when the shapes do not fit together.

    **Method.** With `q = 1 / d` (a plane is linear in the image in `q`; the sky is `q = 0`)
    and `(u, v)` an image pixel's centre in depth-pixel coordinates, `u = (y + 1/2) h / H - 1/2`,
    the four depth samples around it form a cell. Where the cell lies on one surface, `q` is
    interpolated bilinearly (exact on a plane; linearly extrapolated within the outermost half
    depth pixel). A cell spans a discontinuity when one of its samples is on a `depth_edges` jump
    (found on the depth map, holes filled with their nearest sample) and its sorted `q` have a
    relative gap above `jump`, or when it mixes sky and a finite depth. The largest gap splits
    it into a near and a far surface; the pixel belongs to the surface of the sample `s` that
    minimises the joint bilateral cost

    $$\|c_p - \bar c_s\|^2 / \sigma_c^2 + |x_p - x_s|^2,$$

    `c_p` the pixel's colour, `\bar c_s` the mean colour of the image pixels sample `s` covers
    (both as `sqrt(image / mean)`), `|x_p - x_s|` in depth pixels, and takes the mean of that
    surface's samples in the cell, each continued to the pixel along its surface's slope (the
    smaller one-sided difference, zero where the two differ in sign) and weighted bilinearly:
    a plane stays exact up to its edge. This is the joint bilateral
    upsampling of Kopf, Cohen, Lischinski and Uyttendaele (2007, "Joint bilateral upsampling",
    ACM TOG 26(3)) restricted to the cell, with the winner-take-all of Yang, Yang, Davis and
    Nistér (2007, "Spatial-depth super resolution for range images", CVPR) in place of the
    weighted mean: a mean of two surfaces' depths is a depth on neither (a flying pixel), and the
    choice costs colour only on the cells at a discontinuity.

    **Holes.** An image pixel whose depth pixel is a hole is NaN; none other is. Its neighbours
    interpolate towards the hole with the hole's nearest sample in its place (`fill_depth_holes`).
    """
    d = np.asarray(depth)
    img = np.asarray(image)
    dtype = np.float32 if d.dtype == np.float32 else np.float64
    ratio = depth_ratio(d.shape, img.shape)
    if not (jump > 0):
        raise ValueError(f"jump must be a positive relative depth difference, got {jump}")
    if not (sigma_color > 0 and math.isfinite(sigma_color)):
        raise ValueError(f"sigma_color must be a positive number, got {sigma_color}")
    d = d.astype(dtype)
    if ratio == (1.0, 1.0):
        return d.copy()
    if img.ndim == 2:
        img = img[..., None]
    (h, w), (big_h, big_w) = d.shape, img.shape[:2]
    holes = depth_holes(d)
    if holes.all():
        return np.full((big_h, big_w), np.nan, dtype)
    if holes.any():
        d = filled(d, holes)
    with np.errstate(divide="ignore"):
        q = (1 / d).astype(dtype)  # the sky at 0

    (i0, i1, ty, own_y), (j0, j1, tx, own_x) = _axis(h, big_h, dtype), _axis(w, big_w, dtype)
    rows = q[i0] * (1 - ty)[:, None] + q[i1] * ty[:, None]  # (H, w)
    out = rows[:, j0] * (1 - tx) + rows[:, j1] * tx  # (H, W)

    near, split = _cells(d, q, jump)  # per cell (i0, j0): a discontinuity, and where it splits
    ys, xs = np.nonzero(near[i0][:, j0])
    if ys.size:
        guide = _footprint_means(img, own_y, own_x, near)
        out[ys, xs] = _guided(
            q, img, guide, split, (ys, xs), (i0, i1, ty), (j0, j1, tx), sigma_color
        )

    np.maximum(out, 0, out=out)  # (a plane extrapolated past its horizon is sky)
    with np.errstate(divide="ignore"):
        out = 1 / out
    if holes.any():
        out[holes[own_y][:, own_x]] = np.nan
    return out


def _axis(n: int, big_n: int, dtype) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For each of `big_n` image pixels along an axis of `n` depth pixels: the two depth samples
    that bracket its centre (`i0`, `i1 = i0 + 1`, extrapolating at the ends), its linear weight
    `t` of `i1`, and the depth pixel that contains its centre."""
    centre = (np.arange(big_n) + 0.5) * (n / big_n)
    own = np.minimum(centre.astype(np.intp), n - 1)
    i0 = np.clip(np.floor(centre - 0.5).astype(np.intp), 0, max(n - 2, 0))
    i1 = np.minimum(i0 + 1, n - 1)
    t = np.where(i1 > i0, centre - 0.5 - i0, 0.0).astype(dtype)
    return i0, i1, t, own


def _cells(d: np.ndarray, q: np.ndarray, jump: float) -> tuple[np.ndarray, np.ndarray]:
    """For each cell `(i0, j0)` of 2 x 2 samples (as `_axis` indexes them): whether it spans a
    discontinuity, and the `q` between its near and far surfaces."""
    # Padded by repeating the frame's samples, so that a jump next to the frame's edge is found.
    edges = depth_edges(np.pad(d, 2, mode="edge"), jump=jump)[2:-2, 2:-2]

    def corners(a: np.ndarray) -> np.ndarray:
        a = np.pad(a, [(0, int(a.shape[0] == 1)), (0, int(a.shape[1] == 1))], mode="edge")
        return np.stack([a[:-1, :-1], a[1:, :-1], a[:-1, 1:], a[1:, 1:]], axis=-1)

    s = np.sort(corners(q), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        gap = np.where(s[..., 1:] > 0, 1 - s[..., :-1] / s[..., 1:], 0.0)
    k = np.argmax(gap, axis=-1)[..., None]
    largest = np.take_along_axis(gap, k, -1)[..., 0]
    split = 0.5 * (np.take_along_axis(s, k, -1) + np.take_along_axis(s, k + 1, -1))[..., 0]
    sky = (s[..., 0] == 0) & (s[..., -1] > 0)
    near = (corners(edges).any(axis=-1) & (largest > jump / (1 + jump))) | sky
    return near, split


def _footprint_means(
    img: np.ndarray, own_y: np.ndarray, own_x: np.ndarray, cells: np.ndarray
) -> np.ndarray:
    """The mean colour `(h, w, C)` of the image pixels whose centre each depth pixel covers, for
    the depth pixels at a corner of a `cells` cell (zero elsewhere: no other is read)."""
    h, w = own_y[-1] + 1, own_x[-1] + 1
    need = np.zeros((h, w), bool)
    ch, cw = cells.shape
    for dy in (0, min(1, h - 1)):
        for dx in (0, min(1, w - 1)):
            need[dy : dy + ch, dx : dx + cw] |= cells
    ri, rj = np.nonzero(need)

    def block(own: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        start = np.searchsorted(own, np.arange(own[-1] + 2))  # each depth pixel's first, and end
        count = np.diff(start)
        k = np.arange(count.max())
        return np.minimum(start[r][:, None] + k, own.size - 1), k < count[r][:, None], count[r]

    (ys, in_y, ny), (xs, in_x, nx) = block(own_y, ri), block(own_x, rj)
    inside = (in_y[:, :, None] & in_x[:, None, :])[..., None]
    sums = np.sum(np.where(inside, img[ys[:, :, None], xs[:, None, :]], 0), axis=(1, 2))
    guide = np.zeros((h, w, img.shape[-1]), np.result_type(img.dtype, np.float32))
    guide[ri, rj] = sums / (ny * nx)[:, None]
    return guide


def _guided(
    q: np.ndarray,
    img: np.ndarray,
    guide: np.ndarray,
    split: np.ndarray,
    fine: tuple[np.ndarray, np.ndarray],
    y_axis: tuple[np.ndarray, np.ndarray, np.ndarray],
    x_axis: tuple[np.ndarray, np.ndarray, np.ndarray],
    sigma_color: float,
) -> np.ndarray:
    """`q` at the image pixels `fine` of cells at a discontinuity: the surface of the sample with
    the least joint bilateral cost, interpolated over that surface's samples of the cell."""
    (i0, i1, ty), (j0, j1, tx) = y_axis, x_axis
    ys, xs = fine
    a0, a1, b0, b1 = i0[ys], i1[ys], j0[xs], j1[xs]
    ri = np.stack([a0, a1, a0, a1])  # (4, N): the cell's samples, in `_cells`' order
    rj = np.stack([b0, b0, b1, b1])
    level = float(np.mean(img, dtype=np.float64))
    level = level if level > 0 and math.isfinite(level) else 1.0

    def colour(c: np.ndarray) -> np.ndarray:
        return np.sqrt(np.maximum(np.nan_to_num(c, nan=0.0, posinf=0.0), 0.0) / level)

    diff = colour(guide[ri, rj]) - colour(img[ys, xs])[None]
    uy = (ys + 0.5) * (q.shape[0] / img.shape[0]) - 0.5
    ux = (xs + 0.5) * (q.shape[1] / img.shape[1]) - 0.5
    cost = np.sum(diff * diff, axis=-1) / sigma_color**2 + (uy - ri) ** 2 + (ux - rj) ** 2
    best = np.argmin(cost, axis=0)[None]

    samples = q[ri, rj]
    side = samples > split[a0, b0]  # True: the near surface
    mine = side == np.take_along_axis(side, best, 0)
    # Each sample continued along its own surface's slope to the pixel, so that a plane stays
    # exact up to the discontinuity.
    gy, gx = _slope(q, 0), _slope(q, 1)
    samples = samples + gy[ri, rj] * (uy - ri) + gx[ri, rj] * (ux - rj)
    # Bilinear weights within the cell (no extrapolation across a discontinuity); the floor keeps
    # a sample the pixel sits on the far edge from out of a zero sum.
    wy = np.clip(ty[ys], 0, 1)
    wx = np.clip(tx[xs], 0, 1)
    weight = np.stack([(1 - wy) * (1 - wx), wy * (1 - wx), (1 - wy) * wx, wy * wx]) + 1e-3
    weight = np.where(mine, weight, 0)
    return np.sum(weight * samples, axis=0) / np.sum(weight, axis=0)


def _slope(q: np.ndarray, axis: int) -> np.ndarray:
    """The slope of `q` along `axis` at each sample on its own surface: the smaller (in
    magnitude) of the differences to the two neighbours, zero where they differ in sign (a
    structure one sample wide) and at the frame's edge (minmod)."""
    step = np.diff(q, axis=axis)
    pad = [(0, 0), (0, 0)]
    pad[axis] = (1, 0)
    back = np.pad(step, pad)  # q[i] - q[i - 1], zero before the first
    pad[axis] = (0, 1)
    ahead = np.pad(step, pad)  # q[i + 1] - q[i], zero after the last
    return np.where(back * ahead > 0, np.where(np.abs(back) < np.abs(ahead), back, ahead), 0.0)
