r"""The diaphragm: a disc, or a regular polygon of `blades` sides rotated by `rotation`.

A polygonal aperture of `b` blades is the regular `b`-gon **inscribed** in the circle of
confusion: its vertices lie on the circle of radius `r` at angles `rotation + 2 pi j / b`
(radians, counter-clockwise from the +x axis, y pointing down the image rows). As `b -> inf` it
tends to the disc. Its area is `(b / 2) r^2 sin(2 pi / b)`, and as a half-plane intersection it is
`{p : n_j . p <= r cos(pi / b)}` with outward normals `n_j` at angles `rotation + 2 pi (j + 1/2) / b`.

This module holds what the methods need of the shape: the horizontal extent of a row (for the
supersampled coverage), the exact area of the polygon inside a unit pixel (for the soft polygon
kernel), and an area-preserving map from the unit square to the aperture (for lens samples).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array


def unit_vertices(blades: int, rotation: float) -> np.ndarray:
    """Vertices `(b, 2)` as `(x, y)` of the unit-circumradius polygon, counter-clockwise."""
    a = rotation + 2 * np.pi * np.arange(blades) / blades
    return np.stack([np.cos(a), np.sin(a)], axis=-1)


def unit_halfplanes(blades: int, rotation: float) -> tuple[np.ndarray, float]:
    """Outward unit normals `(b, 2)` and the apothem `cos(pi / b)` of the unit polygon."""
    a = rotation + 2 * np.pi * (np.arange(blades) + 0.5) / blades
    return np.stack([np.cos(a), np.sin(a)], axis=-1), math.cos(math.pi / blades)


def area_factor(blades: int | None) -> float:
    """Area of the shape of circumradius 1: `pi` for the disc, `(b/2) sin(2 pi / b)` for a b-gon."""
    return math.pi if blades is None else 0.5 * blades * math.sin(2 * math.pi / blades)


def _lead(values: np.ndarray, like: Array) -> Array:
    """Static per-edge values `(b,)` as `(b, 1, ..., 1)` in `like`'s dtype, to broadcast against it."""
    return jnp.asarray(values, like.dtype).reshape((-1,) + (1,) * like.ndim)


def _extreme(values: Array, arg: Callable[..., Array]) -> Array:
    """The min (`arg=jnp.argmin`) or max (`jnp.argmax`) of `values` over the leading axis.

    Not `jnp.min`/`jnp.max`: their tangent divides by the count of elements equal to the result,
    recomputed in another kernel, and compiled at XLA's optimisation level 0 the two kernels can
    round `values` differently (one contracts a multiply-add into an FMA): the count is then 0 and
    the tangent inf or NaN. The element picked here carries its own tangent, with no count.
    """
    return jnp.take_along_axis(values, arg(values, axis=0)[None], axis=0)[0]


def row_extent(y: Array, r: Array, blades: int | None, rotation: float) -> tuple[Array, Array]:
    """Horizontal extent `[xl, xr]` of the shape of radius `r` on the row at height `y`.

    Empty rows give `xl > xr`. Broadcasts `y` against `r` (same rank, or scalars).
    """
    if blades is None:
        h = jnp.sqrt(jnp.maximum(r * r - y * y, 0))
        inside = y * y <= r * r
        return jnp.where(inside, -h, 1), jnp.where(inside, h, -1)
    normals, apothem = unit_halfplanes(blades, rotation)
    y, r = jnp.broadcast_arrays(y, r)
    nx, ny = normals[:, 0], normals[:, 1]
    flat = np.abs(nx) < 1e-12  # edges parallel to the rows bound the row itself, not x
    # n . (x, y) <= apothem r bounds x from one side, all edges at once (leading axis b)
    rhs = apothem * r[None] - _lead(ny, y) * y[None]
    safe_nx = _lead(np.where(flat, 1.0, nx), y)
    bound = rhs / safe_nx
    xr = jnp.min(jnp.where(_lead((nx > 0) & ~flat, y) > 0, bound, jnp.inf), axis=0)
    xl = jnp.max(jnp.where(_lead((nx < 0) & ~flat, y) > 0, bound, -jnp.inf), axis=0)
    row_ok = jnp.all(jnp.where(_lead(flat, y) > 0, rhs >= 0, True), axis=0)
    return jnp.where(row_ok, xl, 1), jnp.where(row_ok, xr, -1)


def polygon_pixel_overlap(ox: Array, oy: Array, r: Array, blades: int, rotation: float) -> Array:
    r"""Exact area of (polygon of circumradius `r` at the origin) ∩ (unit pixel centred at `(ox, oy)`).

    By Green's theorem the area of the intersection of two convex regions is
    $\tfrac12\oint (x\,dy - y\,dx)$ along its boundary, which is the part of the polygon's boundary
    inside the pixel plus the part of the pixel's boundary inside the polygon. Each straight piece
    is a segment clipped by half-planes (Liang-Barsky / Cyrus-Beck), so the area is a fixed-size,
    branch-free computation, vectorised over the edges, differentiable almost everywhere (the
    polygon's vertices are linear in `r`). Coordinates are taken relative to the pixel centre so
    that the cross products stay of order 1 and float32 keeps its precision at large radii.
    """
    ox, oy, r = jnp.broadcast_arrays(ox, oy, r)
    verts = unit_vertices(blades, rotation)
    normals, apothem = unit_halfplanes(blades, rotation)
    # A polygon edge lying along a pixel edge (same outward normal) must be counted once: the
    # polygon's copy is kept (inclusive, with this tolerance) and the pixel's dropped (strict).
    tol = 16 * float(jnp.finfo(r.dtype).eps) * (1 + r)

    def piece(ax, ay, bx, by, lo, hi):
        # 1/2 cross(p(lo), p(hi)) of the segment a + t (b - a), t in [lo, hi], summed over edges
        ok = hi > lo
        lo, hi = jnp.where(ok, lo, 0), jnp.where(ok, hi, 0)
        px, py = ax + lo * (bx - ax), ay + lo * (by - ay)
        qx, qy = ax + hi * (bx - ax), ay + hi * (by - ay)
        return jnp.sum(jnp.where(ok, 0.5 * (px * qy - qx * py), 0), axis=0)

    # the polygon's edges (leading axis b), clipped to the pixel [-1/2, 1/2]^2, pixel-centred
    u, v = verts, np.roll(verts, -1, axis=0)
    ax, ay = _lead(u[:, 0], r) * r[None] - ox[None], _lead(u[:, 1], r) * r[None] - oy[None]
    bx, by = _lead(v[:, 0], r) * r[None] - ox[None], _lead(v[:, 1], r) * r[None] - oy[None]
    lo, hi = jnp.zeros_like(ax), jnp.ones_like(ax)
    for p0, q0, unit_d in ((ax, bx, v[:, 0] - u[:, 0]), (ay, by, v[:, 1] - u[:, 1])):
        par = np.abs(unit_d) < 1e-12  # edge parallel to this axis (decided on the static shape)
        d = jnp.where(_lead(par, r) > 0, 1, q0 - p0)
        t1, t2 = (-0.5 - p0) / d, (0.5 - p0) / d  # -1/2 <= p0 + t d <= 1/2
        inside = jnp.abs(p0) <= 0.5 + tol[None]
        lo = jnp.where(
            _lead(par, r) > 0, jnp.where(inside, lo, 1), jnp.maximum(lo, jnp.minimum(t1, t2))
        )
        hi = jnp.where(
            _lead(par, r) > 0, jnp.where(inside, hi, 0), jnp.minimum(hi, jnp.maximum(t1, t2))
        )
    total = piece(ax, ay, bx, by, lo, hi)

    # the pixel's edges (counter-clockwise), clipped to the polygon n . p <= apothem r (axis b)
    corners = ((-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5))
    edge_normals = ((0.0, -1.0), (1.0, 0.0), (0.0, 1.0), (-1.0, 0.0))
    nx, ny = _lead(normals[:, 0], r), _lead(normals[:, 1], r)
    for k in range(4):
        (cx, cy), (dx, dy) = corners[k], corners[(k + 1) % 4]
        c0 = nx * (cx + ox[None]) + ny * (cy + oy[None]) - apothem * r[None]
        d = normals[:, 0] * (dx - cx) + normals[:, 1] * (dy - cy)  # static, (b,)
        par = np.abs(d) < 1e-12
        same = normals @ np.asarray(edge_normals[k]) > 0
        keep = jnp.where(_lead(same, r) > 0, c0 < -tol[None], c0 <= 0)
        t = -c0 / _lead(np.where(par, 1.0, d), r)
        hi_k = _extreme(jnp.where(_lead(~par & (d > 0), r) > 0, t, 1), jnp.argmin)
        lo_k = _extreme(jnp.where(_lead(~par & (d < 0), r) > 0, t, 0), jnp.argmax)
        alive = jnp.all(jnp.where(_lead(par, r) > 0, keep, True), axis=0)
        hi_k = jnp.where(alive, jnp.minimum(hi_k, 1), 0)
        lo_k = jnp.maximum(lo_k, 0)
        full = jnp.ones_like(r)
        total = total + piece(
            (cx * full)[None],
            (cy * full)[None],
            (dx * full)[None],
            (dy * full)[None],
            lo_k[None],
            hi_k[None],
        )
    return total


def map_to_aperture(s: Array, t: Array, blades: int | None, rotation: float) -> Array:
    """Area-preserving map of `(s, t)` in `[0, 1]^2` onto the unit aperture; returns `(n, 2)` `(x, y)`.

    Disc: polar `rho = sqrt(s)`, `phi = rotation + 2 pi t`. Polygon: `t` picks one of the `b`
    congruent triangles (centre, `V_j`, `V_{j+1}`) and the point is `sqrt(s) ((1 - t') V_j + t' V_{j+1})`
    with `t' = b t - j`; both maps have constant Jacobian, so uniform `(s, t)` gives uniform
    points, and `s` is the fraction of the aperture's area inside the point's "radius".
    """
    rho = jnp.sqrt(s)
    if blades is None:
        phi = rotation + 2 * jnp.pi * t
        return jnp.stack([rho * jnp.cos(phi), rho * jnp.sin(phi)], axis=-1)
    verts = jnp.asarray(unit_vertices(blades, rotation), s.dtype)
    bt = blades * t
    j = jnp.clip(jnp.floor(bt), 0, blades - 1).astype(jnp.int32)
    tp = (bt - j.astype(s.dtype))[:, None]
    p = (1 - tp) * verts[j] + tp * verts[(j + 1) % blades]
    return rho[:, None] * p
