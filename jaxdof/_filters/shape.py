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


def row_extent(y: Array, r: Array, blades: int | None, rotation: float) -> tuple[Array, Array]:
    """Horizontal extent `[xl, xr]` of the shape of radius `r` on the row at height `y`.

    Empty rows give `xl > xr`. Broadcasts `y` against `r`.
    """
    if blades is None:
        h = jnp.sqrt(jnp.maximum(r * r - y * y, 0))
        inside = y * y <= r * r
        return jnp.where(inside, -h, 1), jnp.where(inside, h, -1)
    normals, apothem = unit_halfplanes(blades, rotation)
    xl = jnp.full(jnp.broadcast_shapes(y.shape, r.shape), -jnp.inf, y.dtype)
    xr = jnp.full_like(xl, jnp.inf)
    for nx, ny in normals:  # n . (x, y) <= apothem r bounds x from one side (or the row itself)
        rhs = apothem * r - ny * y
        if abs(nx) < 1e-12:
            xr = jnp.where(rhs >= 0, xr, -jnp.inf)
        elif nx > 0:
            xr = jnp.minimum(xr, rhs / nx)
        else:
            xl = jnp.maximum(xl, rhs / nx)
    return xl, xr


def polygon_pixel_overlap(ox: Array, oy: Array, r: Array, blades: int, rotation: float) -> Array:
    r"""Exact area of (polygon of circumradius `r` at the origin) ∩ (unit pixel centred at `(ox, oy)`).

    By Green's theorem the area of the intersection of two convex regions is
    $\tfrac12\oint (x\,dy - y\,dx)$ along its boundary, which is the part of the polygon's boundary
    inside the pixel plus the part of the pixel's boundary inside the polygon. Each straight piece
    is a segment clipped by half-planes (Liang-Barsky / Cyrus-Beck), so the area is a fixed-size,
    branch-free computation, differentiable almost everywhere (the polygon's vertices are linear in
    `r`). Coordinates are taken relative to the pixel centre so that the cross products stay of
    order 1 and float32 keeps its precision at large radii.
    """
    verts = unit_vertices(blades, rotation)
    normals, apothem = unit_halfplanes(blades, rotation)
    total = jnp.zeros(jnp.broadcast_shapes(ox.shape, oy.shape, r.shape), r.dtype)
    # A polygon edge lying along a pixel edge (same outward normal) must be counted once: the
    # polygon's copy is kept (inclusive, with this tolerance) and the pixel's dropped (strict).
    tol = 16 * float(jnp.finfo(r.dtype).eps) * (1 + r)

    def clip_piece(ax, ay, bx, by, lo, hi):
        # contribution 1/2 cross(p(t0), p(t1)) of the segment a + t (b - a), t in [lo, hi]
        ok = hi > lo
        lo, hi = jnp.where(ok, lo, 0), jnp.where(ok, hi, 0)
        px, py = ax + lo * (bx - ax), ay + lo * (by - ay)
        qx, qy = ax + hi * (bx - ax), ay + hi * (by - ay)
        return jnp.where(ok, 0.5 * (px * qy - qx * py), 0)

    # the polygon's edges, clipped to the pixel [-1/2, 1/2]^2 (pixel-centred coordinates)
    for j in range(blades):
        (ux, uy), (vx, vy) = verts[j], verts[(j + 1) % blades]
        ax, ay, bx, by = ux * r - ox, uy * r - oy, vx * r - ox, vy * r - oy
        lo, hi = jnp.zeros_like(total), jnp.ones_like(total)
        for p0, d, unit_d in ((ax, bx - ax, vx - ux), (ay, by - ay, vy - uy)):
            if abs(unit_d) < 1e-12:  # edge parallel to this axis (decided on the static shape)
                inside = jnp.abs(p0) <= 0.5 + tol
                lo, hi = jnp.where(inside, lo, 1), jnp.where(inside, hi, 0)
                continue
            t1, t2 = (-0.5 - p0) / d, (0.5 - p0) / d  # -1/2 <= p0 + t d <= 1/2
            lo, hi = jnp.maximum(lo, jnp.minimum(t1, t2)), jnp.minimum(hi, jnp.maximum(t1, t2))
        total = total + clip_piece(ax, ay, bx, by, lo, hi)

    # the pixel's edges (counter-clockwise), clipped to the polygon n . p <= apothem r
    corners = ((-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5))
    edge_normals = ((0.0, -1.0), (1.0, 0.0), (0.0, 1.0), (-1.0, 0.0))
    for k in range(4):
        (ax, ay), (bx, by) = corners[k], corners[(k + 1) % 4]
        lo, hi = jnp.zeros_like(total), jnp.ones_like(total)
        for nx, ny in normals:
            # n . (a + o + t (b - a)) <= apothem r, in the polygon's frame (pixel at o)
            c0 = nx * (ax + ox) + ny * (ay + oy) - apothem * r
            d = nx * (bx - ax) + ny * (by - ay)
            if abs(d) < 1e-12:
                same = nx * edge_normals[k][0] + ny * edge_normals[k][1] > 0
                keep = c0 < -tol if same else c0 <= 0
                hi = jnp.where(keep, hi, 0)
            elif d > 0:
                hi = jnp.minimum(hi, -c0 / d)
            else:
                lo = jnp.maximum(lo, -c0 / d)
        a_x, a_y = jnp.full_like(total, ax), jnp.full_like(total, ay)
        total = total + clip_piece(
            a_x, a_y, jnp.full_like(total, bx), jnp.full_like(total, by), lo, hi
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
