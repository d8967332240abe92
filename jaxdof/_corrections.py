"""Treatments measured against ray-traced truth (see `fits/raytraced.py`).

- `edge_weight`: a fit weight that leaves out the pixels near depth edges, where an image with
  one depth per pixel cannot know what a real aperture sees around a foreground object.
- `footprint_prefilter`: corrects the all-in-focus image, pixel by pixel for its own circle, so
  that spreading it with the overlap kernel has the blur of a real lens: its variance exactly (it
  removes the one pixel footprint too many for large circles and blurs the circles under half a
  pixel, which the filter copies, by as much as the lens does), and its transfer function at high
  frequencies to a least-squares fit for circles under 3 px (`_footprint_table.py`).
- `edge_distance`, `kernel_variance`: their parts (the distance to a depth edge, the filter's
  kernel variance), re-exported by `jaxdof.internal`.

The candidates that lost to `footprint_prefilter` (`pixel_prefilter`, `footprint_radius`) are
study-only code in `fits/_footprint_candidates.py`.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike
from scipy import interpolate

from . import _footprint_table
from ._custom_types import Image, ImageLike, RadiusLike


#: `depth_edges`: a step is a jump when it differs from both surfaces' own steps beside it by more
#: than this many times the larger of them (a plane's steps grow by a constant ratio, a crease
#: continues one side).
EDGE_SLOPE = 2.0


def depth_edges(depth: ArrayLike, *, jump: float = 0.03, slope: float = EDGE_SLOPE) -> np.ndarray:
    """Boolean `(H, W)` mask of the pixels on either side of a depth discontinuity.

    A pair of 4-neighbours `(p, q)` along a row or a column, with step `D = d_q - d_p`, is an
    edge when its step is both

    - large: `|D| > jump min(d_p, d_q)` (3 % by default), and
    - a jump, which neither surface beside it continues into, in depth and in inverse depth
      alike: for `v = d` and for `v = 1/d`, with `s_l` and `s_r` the steps of the surfaces on
      either side (each the smaller of the steps one and two pixels out: `v_p - v_{p-1}`,
      `v_{p-1} - v_{p-2}` on the left; beyond the frame the pair's own, so that within two
      pixels of the frame's edge, which a fit leaves out anyway, nothing is an edge),
      `|D_v - s_l|` and `|D_v - s_r|` both exceed `slope max(|s_l|, |s_r|)` (`slope` 2 by
      default).

    A plane, however steep (a floor at a grazing angle, up to its horizon), is linear in inverse
    depth, a synthetic ramp in depth: either continues into the pair from both sides; where two
    surfaces meet (a floor and a wall) the crease continues one of them: none of these is an
    edge. An occlusion boundary continues neither, also when the depth map spreads it over two
    pixels (antialiased or upsampled) and around a structure one or two pixels wide (a pole, a
    branch): one of the steps one and two out is the surface's. Infinite depths
    (sky) count as far. A jump on a surface that itself changes depth several times over within
    a few pixels can be missed (1 to 6 m over 8 px, a jump from 3.1 to 8.2 m).
    """
    d = np.asarray(depth)
    # float32 stays float32 (a 3 % test needs no more; a 24 MP map in float64 would make ~1 GB
    # of temporaries); other types become float64.
    d = d if d.dtype == np.float32 else d.astype(np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth must be an (H, W) map, got shape {d.shape}")
    if not (jump > 0):
        raise ValueError(f"jump must be a positive relative depth difference, got {jump}")
    if not (slope >= 1):
        raise ValueError(f"slope must be a ratio of steps >= 1, got {slope}")
    edges = np.zeros(d.shape, bool)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        for x, e in ((d, edges), (d.T, edges.T)):
            # inf - inf (within the sky) is NaN, which compares False: no edge.
            large = np.abs(np.diff(x, axis=0)) > jump * np.minimum(x[:-1], x[1:])
            # The continuation test only where the step is large: few pairs of a real map.
            rows, cols = np.nonzero(large)
            jumps = _uncontinued(_steps_around(x, rows, cols), slope)
            jumps &= _uncontinued(_steps_around(x, rows, cols, inverse=True), slope)
            e[rows[jumps], cols[jumps]] = True
            e[rows[jumps] + 1, cols[jumps]] = True
    return edges


def _steps_around(x: np.ndarray, rows: np.ndarray, cols: np.ndarray, inverse=False) -> np.ndarray:
    """`(5, n)`: the steps `v[i + k + 1] - v[i + k]` along axis 0 of `v = x` (or `1 / x`, the sky
    at 0) for `k = -2 .. 2` around the pairs `(rows, cols)` (the pair `(i, i + 1)` at `k = 0`),
    the pair's own beyond the frame; NaN steps as 0."""
    last = x.shape[0] - 2  # the last step's index
    at = rows[None] + np.arange(-2, 3)[:, None]  # (5, n) step indices
    i = np.clip(at, 0, last)
    a, b = x[i + 1, cols], x[i, cols]
    out = np.nan_to_num(1 / a - 1 / b if inverse else a - b, nan=0.0, posinf=np.inf, neginf=-np.inf)
    return np.where((at < 0) | (at > last), out[2][None], out)


def _uncontinued(steps: np.ndarray, slope: float) -> np.ndarray:
    """Whether each pair's step (`steps[2]`, of `_steps_around`) differs from the surface's step
    on its left and on its right by more than `slope` times the larger of them. A side's step is
    the smaller (in magnitude) of the steps one and two out (left: `steps[1]`, `steps[0]`;
    right: `steps[3]`, `steps[4]`), so that the far side of a structure one or two pixels wide,
    or the second half of a jump spread over two pixels, does not count as the surface; beyond
    the frame the pair's own step stands in (no evidence of a jump)."""

    def side(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.where(np.abs(a) <= np.abs(b), a, b)

    own = steps[2]
    s_l, s_r = side(steps[1], steps[0]), side(steps[3], steps[4])
    tol = slope * np.maximum(np.abs(s_l), np.abs(s_r))
    return (np.abs(own - s_l) > tol) & (np.abs(own - s_r) > tol)


def edge_distance(depth: ArrayLike, *, jump: float = 0.03, limit: float = 64.0) -> np.ndarray:
    """Euclidean distance (px) from every pixel to the nearest `depth_edges` pixel, capped at `limit`.

    Exact (`edge_distance_to`); `limit` everywhere when the scene has no depth edge.
    """
    return edge_distance_to(depth_edges(depth, jump=jump), limit=limit)


def edge_distance_to(edges: np.ndarray, *, limit: float) -> np.ndarray:
    """Euclidean distance (px, pixel centre to pixel centre) from every pixel to the nearest `True`
    pixel of the `(H, W)` mask `edges`, capped at `limit`; float32.

    The exact Euclidean distance transform of Felzenszwalb and Huttenlocher ("Distance
    transforms of sampled functions", 2012), as OpenCV's `distanceTransform` with
    `DIST_MASK_PRECISE` computes it: linear in the pixels, in float32 (a 24 MP frame in 0.4 s,
    where `scipy.ndimage.distance_transform_edt`'s float64 took 3-7 s).
    """
    import cv2  # (as the chart's modules: not at `import jaxdof`)

    edges = np.asarray(edges, bool)
    if not edges.any():
        return np.full(edges.shape, float(limit), np.float32)
    far = np.ascontiguousarray(~edges, np.uint8)  # the transform measures to its zeros
    dist = cv2.distanceTransform(far, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.minimum(dist, np.float32(limit))


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


def _checked_image(image: ImageLike) -> jax.Array:
    """The image `(H, W[, C])` as a floating-point array, or a ValueError naming the problem."""
    x = jnp.asarray(image)
    if x.ndim not in (2, 3):
        raise ValueError(f"image must be (H, W) or (H, W, C), got shape {x.shape}")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        raise ValueError(f"image must be floating point (linear light), got dtype {x.dtype}")
    return x


def _dxx(a: jax.Array) -> jax.Array:
    """Second difference along rows (axis 0), one row shorter at either end."""
    return a[:-2] - 2 * a[1:-1] + a[2:]


def _dyy(a: jax.Array) -> jax.Array:
    """Second difference along columns (axis 1), one column shorter at either end."""
    return a[:, :-2] - 2 * a[:, 1:-1] + a[:, 2:]


def _laplacian(p: jax.Array) -> jax.Array:
    """The 5-point Laplacian of the interior of `p` (one ring smaller on every side)."""
    return _dxx(p)[:, 1:-1] + _dyy(p)[1:-1]


def _edge_padded(x: jax.Array, width: int) -> jax.Array:
    return jnp.pad(x, [(width, width), (width, width)] + [(0, 0)] * (x.ndim - 2), mode="edge")


def _image_and_laplacian(image: ImageLike) -> tuple[jax.Array, jax.Array]:
    """The checked image `(H, W[, C])` and its 5-point discrete Laplacian (edge pixels repeated)."""
    x = _checked_image(image)
    return x, _laplacian(_edge_padded(x, 1))


# How far (pixels, along a row or column) `footprint_prefilter` reads: its biharmonic term reaches
# two neighbours. A render with the correction receives light from that much farther.
FOOTPRINT_REACH = 2


def _stencils(x: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The 5-point Laplacian, its square (13 points) and the mixed difference `d_xx d_yy` (9 points)
    of `x` `(H, W[, C])`, edge pixels repeated (the Laplacian is `_image_and_laplacian`'s)."""
    p = _edge_padded(x, FOOTPRINT_REACH)
    lap = _laplacian(p)  # (H + 2, W + 2): one ring beyond the frame
    return lap[1:-1, 1:-1], _laplacian(lap), _dxx(_dyy(p))[1:-1, 1:-1]


@jax.custom_jvp
def _chord_area(u):
    """`u sqrt(1 - u^2) + asin(u)` for `u` in `[0, 1]`: the disc area left of `x = u r`, over `r^2`,
    less `pi/2`. Its derivative `2 sqrt(1 - u^2)` is finite at `u = 1`, where the two terms' own
    derivatives are infinite and would give `inf - inf` under autodiff."""
    return u * jnp.sqrt(1 - u * u) + jnp.arcsin(u)


@_chord_area.defjvp
def _chord_area_jvp(primals, tangents):
    (u,), (du,) = primals, tangents
    return _chord_area(u), 2 * jnp.sqrt(1 - u * u) * du


# Columns summed exactly: the kernel variance is exact for radii up to this + 1/2 px, and the
# correction is held at its value there beyond (it has settled to ~1/12 px^2 by then; see below).
_VARIANCE_COLUMNS = 24


def kernel_variance(radius: ArrayLike, *, max_radius: float | None = None) -> jax.Array:
    r"""Per-axis variance (px^2) of `jaxdof.coc_filter`'s discrete kernel `overlap(o, r) / (pi r^2)`.

    **Arguments:** `radius` (px), any shape, `>= 0`; `max_radius` (static, optional): a bound on
    `radius` (the filter's window), which sums only the columns a circle that size reaches (the
    same numbers, `O(max_radius)` work per pixel instead of `O(24)`).

    **Returns:** `Var(r) = sum_o o_x^2 overlap(o, r) / (pi r^2)`, same shape. Summing the overlap
    over a column of pixels `o_x = k` gives the disc's area between `x = k - 1/2` and `k + 1/2`, so

    $$\mathrm{Var}(r) = \frac{2}{\pi} \sum_{k \ge 1} k^2
      \left[g\!\left(\min(\tfrac{k + 1/2}{r}, 1)\right) - g\!\left(\min(\tfrac{k - 1/2}{r}, 1)\right)\right],
      \qquad g(u) = u\sqrt{1 - u^2} + \arcsin u,$$

    exact (closed form) for `r <= 24.5`, zero for `r <= 1/2` (the disc stays in its pixel and the
    filter copies it), continuously differentiable in `r`. It is about `r^2/4 + 1/12` (the disc's
    variance plus one pixel box), with a sampling wiggle of a few hundredths of a px^2 at small `r`.
    Beyond 24.5 px it returns `r^2/4 + (Var(24.5) - 24.5^2/4)`.
    """
    r = jnp.asarray(radius)
    n = _VARIANCE_COLUMNS
    if max_radius is not None:  # columns beyond the largest circle add g(1) - g(1) = 0
        n = max(1, min(n, math.ceil(float(max_radius) + 0.5)))
    rc = jnp.minimum(r, n + 0.5)
    # Under 1/2 px every term is zero; the floor keeps 1/r finite (and its derivative) at r = 0.
    rs = jnp.maximum(rc, 0.25)[..., None]
    # g at the column boundaries k + 1/2, k = 0..n, once each (a boundary ends one column and
    # starts the next).
    b = jnp.arange(n + 1, dtype=rs.dtype).reshape((1,) * r.ndim + (-1,)) + 0.5
    g = _chord_area(jnp.minimum(b / rs, 1.0))
    k = jnp.arange(1, n + 1, dtype=rs.dtype).reshape((1,) * r.ndim + (-1,))
    var_c = (2 / jnp.pi) * jnp.sum(k * k * (g[..., 1:] - g[..., :-1]), axis=-1)
    return var_c + (r * r - rc * rc) / 4


# The correction's coefficient c(r) = (Var(r) - r^2/4) / 2, tabulated with its derivative and
# interpolated by cubic Hermite segments (C^1, like Var): one table look-up per pixel instead of
# `kernel_variance`'s 2 (n + 1) chord areas (n up to 24). Var grows like (r - k - 1/2)^(3/2) past
# each column boundary k + 1/2, so within each unit interval the nodes sit at k + 1/2 + (j/M)^2:
# dense where that singular term is, and an error of order 1/M^3 everywhere (measured below).
_TABLE_PER_PX = 128


def _chord_area_np(u: np.ndarray) -> np.ndarray:
    return u * np.sqrt(1 - u * u) + np.arcsin(u)


def _coefficient_table() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The nodes `r`, `c(r)` and `c'(r)` (float64 numpy: the closed form of `kernel_variance` and
    its derivative), from 1/2 to `_VARIANCE_COLUMNS + 1/2` px."""
    n, m = _VARIANCE_COLUMNS, _TABLE_PER_PX
    within = (np.arange(m) / m) ** 2
    r = np.append((np.arange(n)[:, None] + 0.5 + within[None, :]).ravel(), n + 0.5)[:, None]
    b = np.arange(n + 1)[None, :] + 0.5
    u = np.minimum(b / r, 1.0)
    g = _chord_area_np(u)
    dg = np.where(b < r, 2 * np.sqrt(1 - u * u) * (-b / (r * r)), 0.0)  # d g(u(r)) / dr
    k2 = (np.arange(1, n + 1) ** 2)[None, :]
    var = (2 / np.pi) * np.sum(k2 * (g[:, 1:] - g[:, :-1]), axis=1)
    dvar = (2 / np.pi) * np.sum(k2 * (dg[:, 1:] - dg[:, :-1]), axis=1)
    r = r[:, 0]
    return r, (var - r * r / 4) / 2, (dvar - r / 2) / 2


_R_TABLE, _C_TABLE, _DC_TABLE = _coefficient_table()


def footprint_coefficient(radius: ArrayLike) -> jax.Array:
    r"""The footprint correction's coefficient `c(r) = (Var(r) - r^2/4) / 2` (px^2), see
    `footprint_prefilter`; `Var` is `kernel_variance`.

    **Arguments:** `radius` (px), any shape, `>= 0`. **Returns:** `c(r)`, same shape and dtype.

    `-r^2/8` under half a pixel (`Var = 0`: the filter copies the pixel); from 1/2 to 24.5 px a
    cubic Hermite interpolant of the closed form and its derivative, on 128 nodes per pixel placed
    at `k + 1/2 + (j/128)^2` (`Var` has a `(r - k - 1/2)^{3/2}` term past each column boundary,
    which quadratic spacing resolves); constant beyond (`Var - r^2/4` is held there). Continuously
    differentiable, as `Var` is; one table look-up per pixel instead of up to 50 chord areas.
    """
    r = jnp.asarray(radius)
    dtype = r.dtype if jnp.issubdtype(r.dtype, jnp.floating) else jnp.result_type(float)
    r = r.astype(dtype)
    n, m = _VARIANCE_COLUMNS, _TABLE_PER_PX
    rc = jnp.clip(r, 0.5, n + 0.5)
    # The segment is chosen outside autodiff; within it the cubic is differentiable in r.
    x = jax.lax.stop_gradient(rc) - 0.5
    k = jnp.clip(jnp.floor(x), 0, n - 1)
    j = jnp.clip(jnp.floor(m * jnp.sqrt(jnp.maximum(x - k, 0.0))), 0, m - 1)
    i = (k * m + j).astype(jnp.int32)
    nodes = jnp.asarray(_R_TABLE, dtype)
    c_tab, dc_tab = jnp.asarray(_C_TABLE, dtype), jnp.asarray(_DC_TABLE, dtype)
    r0, r1 = nodes[i], nodes[i + 1]
    h = r1 - r0
    inside = _hermite((rc - r0) / h, h, c_tab, dc_tab, i)
    return jnp.where(r < 0.5, -r * r / 8, inside)


def _hermite(t, h, values, slopes, i):
    """The cubic Hermite segment `i` of a table (`values` and `slopes` at its nodes, segments of
    width `h`) at the fraction `t` in `[0, 1]` of the segment."""
    t2 = t * t
    t3 = t2 * t
    ends = (2 * t3 - 3 * t2 + 1) * values[i] + (3 * t2 - 2 * t3) * values[i + 1]
    return ends + h * ((t3 - 2 * t2 + t) * slopes[i] + (t3 - t2) * slopes[i + 1])


_C2 = np.asarray(_footprint_table.C2, np.float64)
_C3 = np.asarray(_footprint_table.C3, np.float64)


def _spline_slopes(values: np.ndarray) -> np.ndarray:
    # The slopes of the cubic spline through the nodes (twice continuously differentiable), flat
    # at both ends: c_2 and c_3 are even in r (~ r^2 at 0) and tapered flat to 0 at 3 px.
    r = np.arange(values.shape[0]) * _footprint_table.R_STEP
    spline = interpolate.CubicSpline(r, values, bc_type="clamped")
    return spline.derivative()(r)


_DC2, _DC3 = _spline_slopes(_C2), _spline_slopes(_C3)


def fourth_order_coefficients(radius: ArrayLike) -> tuple[jax.Array, jax.Array]:
    r"""The footprint correction's fourth-order coefficients `(c_2(r), c_3(r))` (px^4), see
    `footprint_prefilter` and `jaxdof/_footprint_table.py` (how they are fitted).

    **Arguments:** `radius` (px), any shape, `>= 0`. **Returns:** two arrays of its shape and
    floating dtype: the cubic splines through the tables' nodes (every 0.01 px), twice
    continuously differentiable in `r`, and 0 from 3 px on.
    """
    r = jnp.asarray(radius)
    dtype = r.dtype if jnp.issubdtype(r.dtype, jnp.floating) else jnp.result_type(float)
    r = r.astype(dtype)
    step = _footprint_table.R_STEP
    n = _C2.shape[0] - 1
    rc = jnp.clip(r, 0.0, n * step)
    # The segment is chosen outside autodiff; within it the cubic is differentiable in r.
    i = jnp.clip(jnp.floor(jax.lax.stop_gradient(rc) / step), 0, n - 1).astype(jnp.int32)
    t = rc / step - i.astype(dtype)

    def interp(values, slopes):
        return _hermite(t, step, jnp.asarray(values, dtype), jnp.asarray(slopes, dtype), i)

    return interp(_C2, _DC2), interp(_C3, _DC3)


def footprint_prefilter(image: ImageLike, radius: RadiusLike) -> Image:
    r"""Correct an all-in-focus image for the pixel footprint, pixel by pixel for its own circle.

    **Arguments:**

    - `image`: all-in-focus image `(H, W)` or `(H, W, C)`, linear light (pixel averages).
    - `radius`: the circle of confusion of each pixel `(H, W)` (px, `>= 0`), the same radius that
      is then given to `jaxdof.coc_filter`.

    **Returns:** per pixel,

    $$x - c_1(r)\,\Delta x + c_2(r)\,\Delta^2 x + c_3(r)\,\partial_{xx}\partial_{yy} x,
      \qquad c_1(r) = \tfrac12 \left( \mathrm{Var}(r) - \tfrac{r^2}{4} \right),$$

    `Var` the filter's kernel variance (`kernel_variance`; `c_1` is read from a table of it,
    `footprint_coefficient`), `Delta` the 5-point discrete Laplacian, `d_xx`, `d_yy` second
    differences (edge pixels repeated; the result reads up to `FOOTPRINT_REACH = 2` pixels away),
    and `c_2`, `c_3` the fourth-order terms (`fourth_order_coefficients`, below); same shape and
    dtype. Use as
    `coc_filter(footprint_prefilter(image, r), r)` with `r = coc_radius(depth, lens)`.

    **Why.** A pixel of the all-in-focus image is the scene averaged over the pixel, `L * box`; a
    pixel of the real (or ray-traced) photo is `L * disc_r * box`. `coc_filter` spreads each pixel
    with its overlap kernel, whose per-axis variance is `Var(r)`, while the lens adds only the
    disc's `r^2/4`: about `1/12 px^2` too much (one more box) for `r >~ 1`, and `-r^2/4` (nothing
    instead of a little blur) for `r <= 1/2`, where the filter copies the pixel. A filter whose
    transfer function is `1 - v w^2/2 + O(w^4)` per axis has variance `v`, and the 5-point
    Laplacian's is `-w_x^2 - w_y^2 + O(w^4)`; so `1 - c Laplacian` has variance `-2c` per axis,
    and with `c(r)` above the corrected image spread by the kernel has the lens's variance `r^2/4`
    exactly, for every radius: it sharpens by about one box (`c -> 1/24`, the study-only
    `pixel_prefilter` of `fits/_footprint_candidates.py`) where circles are large and blurs by `r^2/4` where they are
    under half a pixel. Unlike that study's `footprint_radius` (a smaller radius instead) it
    keeps the kernel (the disc's shape) and makes the render depend on the lens in the dead zone,
    so a fit sees the focus plane's small circles.

    **Fourth order.** Matching the second moment leaves the transfer function off the lens's at
    high frequencies: at `r = 0.8` px the kernel with the second-order correction alone passes
    0.58 of the Nyquist frequency along a row where the disc passes 0.39 (the overlap kernel is
    square where the disc is round), which biases fits on finely textured scenes (a blur scale 13-14 % short on the ray-traced `texture` scene with circles
    under 1.5 px). `c_2` and `c_3` change neither the light nor the variance (`Delta^2` and
    `d_xx d_yy` have zero sum and zero second moment); they are fitted per radius to the disc's
    transfer function over the band `|w| <= pi` by least squares, and are zero from 3 px on, where
    the kernel is already close (`jaxdof/_footprint_table.py` says how, with the errors).

    Differentiable in `image` and `radius` (`Var` and the tables' interpolants are continuously
    differentiable). `c_2` and `c_3` follow the pixel grid: their third derivative in `r` reaches
    ~500 px^-3 near 2-3 px, so a finite-difference check of the radius (or depth) gradient needs
    steps of ~1e-5 px or less to match it to 1e-6. The stencils mix neighbours across depth edges.
    Measured against Mitsuba in `fits/results/raytraced.md`.
    """
    x = _checked_image(image)
    r = jnp.asarray(radius)
    if r.shape != x.shape[:2]:
        raise ValueError(
            f"radius must be one circle per pixel, shape {x.shape[:2]}, got {r.shape}; "
            "pass coc_radius(depth, lens) for the image's depth map"
        )
    r = r.astype(x.dtype)
    c1, c2, c3 = footprint_coefficient(r), *fourth_order_coefficients(r)
    if x.ndim == 3:
        c1, c2, c3 = c1[..., None], c2[..., None], c3[..., None]
    lap, bilap, mixed = _stencils(x)
    return x - c1 * lap + c2 * bilap + c3 * mixed
