r"""Informative tiles: fit a large photo on a few full-resolution tiles chosen by what they tell
about the lens.

Most pixels of a photo say little about the lens (flat regions; pixels whose circle barely moves
with the parameters), and the cost of a fit grows with the pixels rendered. For a photo above
`TILES_ABOVE` pixels `fit_lens` fits on tiles instead:

1. **Information.** The photo, image, depth and weights are box-averaged (the pyramid's
   `_downsample`) until the longer side is at most `SCOUT_SIDE` px, and the Jacobian `J` of the
   weighted residual with respect to the free parameters is evaluated there at the `init` lens
   (one compiled `restate`: `P` forward-mode passes over a small image). Each candidate tile's
   Fisher information is the sum of `J_p J_p^T` over its pixels (every target and channel),
   times the area ratio: the information the full-resolution pixels of the tile carry about the
   parameters, up to the noise variance, which is common to all tiles.
2. **Choice.** Candidates are the cells of a grid of `side x side` photo pixels (`SIDE`, or
   twice the halo where that is more) inside the band
   that light from outside the frame reaches (each tile with its halo must lie in the frame).
   A tile whose crop (interior and halo) holds a depth edge (`jaxdof.depth_edges`) is left out
   while enough others remain, whatever the forward model: a post-process model explains light
   blocked at an edge only approximately (the hidden surfaces are guessed), and those pixels bias
   the lens; with no edge in the tiles `fit_lens` fits them without its occlusion treatment
   (the soft filter, 2-3x cheaper). From the rest the tiles are
   picked greedily for D-optimality: each step adds the tile that most increases
   `log det(M + I_k)`, `M` the information chosen so far (plus a ridge of `1e-9` of the
   candidates' mean trace, so that the first tiles fill the directions one by one). This favours
   tiles that determine what the others do not (other depths, other circle sizes), not just the
   most textured ones, until `budget` interior pixels are chosen.
3. **Mosaic.** The tiles, each with a halo of the window's reach (`forward.border_band`), are laid
   side by side in one image (rows of crops). Light from a neighbour in the mosaic reaches only
   into a tile's halo, and the halo has weight 0 (the border rule, per tile), so the residual of
   every interior pixel is exactly that of the full-frame fit. The fit then runs unchanged on the
   mosaic: its pyramid, starts, window policy, statistics and adequacy test (whose tiles then
   cover groups of photo tiles: independent parts of the photo).

4. **At a lens near the photo's.** The starts are first solved on a scout, the whole photo
   box-averaged until its longer side is at most `SCOUT_SIDE` px (`scout_factor`); the tiles are
   chosen from the information at the scout's best solution (its Jacobian, which that solve
   returns), with halos of the full-resolution window's reach over the chosen tiles' depths, and
   the full-resolution solve starts from the scout's solution (`path._on_tiles`). Information at
   a lens near the photo's chooses better tiles than at a start far off: on the 1.5 MP scene of
   `fits/fullres.py` (init f/5.6 at 2 m, truth f/2.8 at 3 m), 2^17 pixels of tiles chosen at the
   init gave standard errors 4.8x (N) and 3.3x (d_f) the whole frame's, chosen at a coarse
   solution 2.4x and 2.8x. A fit compiles three stages (scout, full resolution, statistics): that
   fit took 15-18 s in a fresh `jaxdof fit`, against 30 s with a pyramid on tiles chosen twice.
   With one start, or a photo that needs no reduction, the tiles are chosen at the `init`.

The standard errors are those of the pixels used; `FitResult.tiles` lists the tiles
`(row, column, height, width)` of their interiors in photo pixels.

Source: D-optimal subset selection (Kiefer and Wolfowitz 1959; greedy D-optimal designs, e.g.
Atkinson, Donev and Tobias, "Optimum Experimental Designs, with SAS", 2007, ch. 12).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from .. import _tuning
from .._corrections import depth_edges
from .layout import pack
from .photo import frame
from .prepare import Problem, scene_edges
from .residual import _Model
from .solve import restate, run_stage
from .strategies import auto_levels, reductions, window_of


#: Photos with more pixels than this are fitted on tiles by default (`tiles="auto"`).
TILES_ABOVE = 1 << 20
#: The default budget: interior pixels of all tiles together (per target).
BUDGET = 1 << 17
#: The smallest interior side of a tile (photo pixels); it is at least twice the halo (the
#: window's reach), so that the interiors are at least a quarter of the pixels rendered.
SIDE = 32
#: The longer side (pixels) of the reduced photo on which the information is computed.
SCOUT_SIDE = 512


@dataclasses.dataclass(frozen=True)
class Tiles:
    """Chosen tiles: interiors' top-left corners `(row, column)` (photo pixels), their `side`,
    the `halo` around each (photo pixels), and the photo's `(H, W)`."""

    corners: tuple[tuple[int, int], ...]
    side: int
    halo: int
    photo: tuple[int, int]

    @property
    def boxes(self) -> tuple[tuple[int, int, int, int], ...]:
        """`(row, column, height, width)` of every interior (photo pixels)."""
        return tuple((r, c, self.side, self.side) for r, c in self.corners)

    @property
    def cols(self) -> int:
        return math.ceil(math.sqrt(len(self.corners)))

    def mosaic(self, x: np.ndarray, s: int, axis: int, fill) -> np.ndarray:
        """The crops (interior and halo) of `x` laid out in rows of `cols`: `x`'s spatial axes
        at `axis, axis + 1` are `s` times the photo's (the image with `downsample = s`)."""
        crop = (self.side + 2 * self.halo) * s
        n, cols = len(self.corners), self.cols
        rows = math.ceil(n / cols)
        shape = list(x.shape)
        shape[axis], shape[axis + 1] = rows * crop, cols * crop
        out = np.full(shape, fill, x.dtype)
        for i, (r, c) in enumerate(self.corners):
            r0, c0 = (r - self.halo) * s, (c - self.halo) * s
            src = [slice(None)] * x.ndim
            src[axis], src[axis + 1] = slice(r0, r0 + crop), slice(c0, c0 + crop)
            dst = [slice(None)] * x.ndim
            rr, cc = divmod(i, cols)
            dst[axis] = slice(rr * crop, (rr + 1) * crop)
            dst[axis + 1] = slice(cc * crop, (cc + 1) * crop)
            out[tuple(dst)] = x[tuple(src)]
        return out

    def interior_mask(self) -> np.ndarray:
        """`(H_m, W_m)` of the mosaic (photo pixels): 1 in the interiors, 0 in halos and gaps."""
        crop = self.side + 2 * self.halo
        one = np.zeros((crop, crop))
        one[self.halo : self.halo + self.side, self.halo : self.halo + self.side] = 1
        ones = np.broadcast_to(one, (len(self.corners), crop, crop))
        cols, n = self.cols, len(self.corners)
        rows = math.ceil(n / cols)
        out = np.zeros((rows * crop, cols * crop))
        for i in range(n):
            rr, cc = divmod(i, cols)
            out[rr * crop : (rr + 1) * crop, cc * crop : (cc + 1) * crop] = ones[i]
        return out


def use_tiles(tiles, photo: tuple[int, ...]) -> int | None:
    """The pixel budget of a fit on tiles, or None for the whole frame: `tiles` is `"auto"`
    (tiles with `BUDGET` when the photo has more than `TILES_ABOVE` pixels), `None`/`False`
    (the whole frame), a positive int (a budget of interior pixels) or an earlier fit's tiles
    (`FitResult.tiles`, `tile_boxes`: their interiors' pixels; `()`, a whole-frame fit's, is
    the whole frame)."""
    if tiles is None or tiles is False:
        return None
    if _as_boxes(tiles):  # an earlier fit's, `()` a whole-frame fit's
        boxes = tile_boxes(tiles)
        return None if boxes is None else sum(h * w for _, _, h, w in boxes)
    if isinstance(tiles, str):
        if tiles != "auto":
            raise ValueError(f"tiles must be 'auto', None/False or a pixel budget, got {tiles!r}")
        return BUDGET if photo[0] * photo[1] > TILES_ABOVE else None
    if isinstance(tiles, bool) or not isinstance(tiles, (int, np.integer)) or tiles <= 0:
        raise ValueError(
            f"tiles must be 'auto', None/False or a positive pixel budget, got {tiles!r}"
        )
    return int(tiles)


def _as_boxes(tiles) -> bool:
    """Whether `tiles` is a sequence of boxes (or none), not a `use_tiles` choice."""
    return isinstance(tiles, (tuple, list)) or (isinstance(tiles, np.ndarray) and tiles.ndim == 2)


def tile_boxes(tiles) -> tuple[tuple[int, int, int, int], ...] | None:
    """`tiles` as an earlier fit's interiors, `(row, column, side, side)` each (`FitResult.tiles`),
    or None where it is not a sequence of them (a `use_tiles` choice: `"auto"`, a budget,
    `None`; or `()`, a whole-frame fit's); `ValueError` for boxes that are not squares of one
    side at non-negative corners."""
    if not _as_boxes(tiles) or len(tiles) == 0:
        return None
    boxes: list[tuple[int, int, int, int]] = []
    for box in tiles:
        values = tuple(int(v) for v in np.ravel(box))
        if len(values) != 4 or min(values) < 0 or values[2] != values[3] or values[2] < 1:
            raise ValueError(f"tiles: {box!r} is not (row, column, side, side) of a square")
        boxes.append((values[0], values[1], values[2], values[3]))
    if len({b[2] for b in boxes}) != 1:
        raise ValueError("tiles: the boxes differ in side; tiles are of one side")
    return tuple(boxes)


def halo_of(forward, window: float, align: int = 1) -> int:
    """A tile's halo (photo pixels): the band `window`'s circles reach
    (`forward.border_band`), rounded up to a multiple of `align` (8: on a JPEG's grid)."""
    return -(-int(forward.border_band(window)) // align) * align


def given_tiles(
    photo: tuple[int, ...], forward, window: float, boxes, align: int = 1
) -> Tiles | None:
    """`Tiles` with the interiors `boxes` (`tile_boxes`) and halos of `window`'s reach (a
    multiple of `align`, as `_grid`'s), or None where a halo would leave the frame (a larger
    window than the one they were chosen for)."""
    hh, ww = photo[:2]
    halo, side = halo_of(forward, window, align), boxes[0][2]
    corners = tuple((r, c) for r, c, _, _ in boxes)
    inside = all(
        halo <= r and r + side + halo <= hh and halo <= c and c + side + halo <= ww
        for r, c in corners
    )
    return Tiles(corners, side, halo, (int(hh), int(ww))) if inside else None


def estimate_fit_memory(
    image_shape: tuple[int, ...], photo_shape: tuple[int, ...], targets: int, budget: int | None
) -> int:
    """Bytes `fit_lens` needs besides its inputs, from measured bytes per pixel
    (`jaxdof.internal.tuning.FIT_MEMORY`, with its provenance): `fixed + frame n + fitted m T`,
    `n` the image's pixels, `T` photos of `m` pixels rendered each: the photo's, or on tiles
    (`budget` pixels, `use_tiles`) at most `4 budget` (every tile at least twice its halo: its
    crop at most twice its side). For planning: measured peaks were 0.68-0.97 of it."""
    table = _tuning.FIT_MEMORY
    n = int(image_shape[0]) * int(image_shape[1])
    m = int(photo_shape[0]) * int(photo_shape[1]) if budget is None else 4 * int(budget)
    return int(table["fixed"] + table["frame"] * n + table["fitted"] * m * int(targets))


def scout_factor(photo: tuple[int, int], r_starts: float, levels: int | None) -> int:
    """The reduction `q` (a power of two) of the scout on which a fit on tiles solves its starts:
    `2^(L-1)` for `levels = L` (the `pyramid` option); else the least that brings the longer side
    to at most `SCOUT_SIDE` px, with the pyramid's limits (`auto_levels`): the shorter side at
    least 24 px and the starts' largest circle, `r_starts` (px), at least 1 px (twice the
    half-pixel dead zone). `1`: no scout solve.

    The starts' circles, not the init's alone as for a whole-frame pyramid: the starts spread
    in f-number and focus, and a scout solve needs some of them to make circles it can see; on
    the 1.5 MP scene of `fits/fullres.py` the init's rule gave a 500 x 750 scout with an 12 px
    window (127 s of solve), the starts' a 250 x 375 one with 8 px (5 s)."""
    if levels is not None:
        return 2 ** (levels - 1)
    q = 2 ** (auto_levels(photo, r_starts) - 1)
    while q > 1 and max(photo) / (q // 2) <= SCOUT_SIDE:
        q //= 2
    return q


def jacobian_information(jac, shape: tuple[int, ...], used) -> np.ndarray:
    """`(h, w, P, P)`: each pixel's Fisher information about the free parameters (unit noise)
    from the Jacobian `(n, P_all)` of the weighted residuals of targets of `shape` `(T, h, w)`
    or `(T, h, w, C)`; `used` are the free columns."""
    jac = np.asarray(jac, np.float64)[:, list(used)]
    t, h, w = shape[:3]
    jac = jac.reshape(t, h, w, -1, jac.shape[-1])  # (T, h, w, C, P)
    return np.einsum("thwci,thwcj->hwij", jac, jac)


def pixel_information(p: Problem, forward, rows0: np.ndarray) -> tuple[np.ndarray, int]:
    """`(h, w, P, P)`: each reduced pixel's Fisher information about the free parameters (in the
    solver's coordinates, unit noise) at the first lens of `rows0`, on the photo box-averaged
    until its longer side is at most `SCOUT_SIDE` px, and
    the reduction factor (tiles chosen at the init: `path._on_tiles` without a scout solve)."""
    k = 0  # box-averaged until the longer side is at most `SCOUT_SIDE` px
    while max(p.targets.shape[1:3]) // 2**k > SCOUT_SIDE:
        k += 1
    (im, dep, tg, sw, b), q = reductions(p, [k])[k], 2**k
    layout = dataclasses.replace(p.layout, base=b.astype(p.dtype))
    window = window_of(forward, rows0[:1], dep, tg.shape[1:3], q)
    spec = p.spec
    model = _Model(spec.n_targets, window, spec.nuisances, forward, len(spec.used), spec.luma)
    y0 = pack(rows0[:1].astype(p.dtype), p.layout, spec.nuisances)[0]
    _, _, jac, _ = run_stage("restate", restate, model, y0, (im, dep, tg, sw, layout))
    return jacobian_information(jac, tg.shape, spec.used), q


def _box_sums(x: np.ndarray, size: int, starts_r, starts_c, dtype=None) -> np.ndarray:
    """Sums of `x` (`(H, W, ...)`) over the `size x size` boxes with top-left corners at every
    pair of `starts_r` x `starts_c` (an integral image, accumulated in `dtype`)."""
    c = np.cumsum(np.cumsum(x, axis=0, dtype=dtype), axis=1, dtype=dtype)
    c = np.pad(c, [(1, 0), (1, 0)] + [(0, 0)] * (x.ndim - 2))
    r0, c0 = np.asarray(starts_r)[:, None], np.asarray(starts_c)[None, :]
    r1, c1 = r0 + size, c0 + size
    return c[r1, c1] - c[r0, c1] - c[r1, c0] + c[r0, c0]


def _grid(photo: tuple[int, ...], forward, window: float, budget: int, align: int = 1):
    """The candidate tiles for halos of `window`'s reach: `(halo, side, want, rows, columns)`
    (the corners' rows and columns), or None with fewer than twice the tiles wanted. With
    `align` 8 the halo is a multiple of 8 (sides are already), so every corner lies on a camera
    JPEG's 8 x 8 grid, in the frame and in the mosaic (`jpeg.py`)."""
    hh, ww = photo[:2]
    halo = halo_of(forward, window, align)
    # At least twice the halo, so that interiors are at least a quarter of the pixels rendered.
    side = max(SIDE, -(-2 * halo // 8) * 8)
    want = max(1, budget // (side * side))
    starts_r = np.arange(halo, hh - halo - side + 1, side)
    starts_c = np.arange(halo, ww - halo - side + 1, side)
    if len(starts_r) * len(starts_c) < 2 * want:
        return None
    return halo, side, want, starts_r, starts_c


def fits_tiles(photo: tuple[int, ...], forward, window: float, budget: int, align: int = 1) -> bool:
    """Whether a photo of shape `photo` holds enough candidate tiles (`choose_tiles`) for
    `budget` pixels with halos of `window`'s reach (a multiple of `align`)."""
    return _grid(photo, forward, window, budget, align) is not None


def choose_tiles(
    p: Problem,
    forward,
    window: float,
    budget: int,
    information: Callable[[], tuple],
    align: int = 1,
) -> Tiles | None:
    """The tiles of a fit on `budget` interior pixels with halos of `window`'s reach (module
    docstring), or None when the photo holds too few candidates to be worth it (fewer than twice
    the tiles wanted). `information()` gives the reduced pixels' information and their factor
    `q` (`pixel_information`, or `jacobian_information` of a scout solve); it is called only
    when there are enough candidates."""
    grid = _grid(p.photo, forward, window, budget, align)
    if grid is None:
        return None
    halo, side, want, starts_r, starts_c = grid
    info, q = information()
    # Each candidate's information: the reduced pixels under it (side / q per axis, at least 1),
    # times q^2 (the full-resolution pixels each reduced one stands for).
    k = max(side // q, 1)
    hq, wq = info.shape[:2]
    rq = np.minimum(starts_r // q, hq - k)
    cq = np.minimum(starts_c // q, wq - k)
    cand = _box_sums(info, k, rq, cq) * (side * side / (k * k))  # (nr, nc, P, P)
    usable = np.ones(cand.shape[:2], bool)
    edges = scene_edges(p.depth)
    s = p.ratio
    crop = (side + 2 * halo) * s
    # int32 counts: a 24 MP frame's integral image in 96 MB, not float64's 192 MB per copy
    n_edge = _box_sums(edges, crop, (starts_r - halo) * s, (starts_c - halo) * s, np.int32)
    if np.sum(n_edge == 0) >= want:
        usable = n_edge == 0
    corners = [(int(r), int(c)) for r in starts_r for c in starts_c]
    mats = cand.reshape(-1, *cand.shape[2:])
    keep = usable.reshape(-1)
    chosen = _greedy_d_optimal(mats, keep, want)
    picked = sorted(corners[i] for i in chosen)
    return Tiles(tuple(picked), side, halo, (int(p.photo[0]), int(p.photo[1])))


def edge_free(p, chosen: Tiles) -> bool:
    """Whether no chosen tile's crop (interior and halo) holds a depth edge."""
    return not edges_near(p.depth, p.ratio, chosen.corners, chosen.side, chosen.halo)


def edges_near(depth: np.ndarray, ratio: int, corners, side: int, reach: int) -> bool:
    """Whether a depth edge lies within `reach` photo pixels of a tile (`corners`, `side`: photo
    pixels; `depth` at `ratio` image pixels per photo pixel), each crop clipped to the frame:
    only there can an occlusion render differ from the soft one on the tiles."""
    for r, c in corners:
        r0, c0 = max(r - reach, 0) * ratio, max(c - reach, 0) * ratio
        r1, c1 = (r + side + reach) * ratio, (c + side + reach) * ratio
        if depth_edges(depth[r0:r1, c0:c1]).any():
            return True
    return False


def _greedy_d_optimal(mats: np.ndarray, keep: np.ndarray, want: int) -> list[int]:
    """Indices of `want` matrices among `mats` `(K, P, P)` (those with `keep`), added one at a
    time, each maximising `log det` of the running sum plus a small ridge."""
    n_p = mats.shape[-1]
    trace = np.trace(mats, axis1=1, axis2=2)
    ridge = 1e-9 * max(float(np.mean(trace[keep])) if keep.any() else 0.0, 1e-300)
    m = ridge * np.eye(n_p)
    free = keep.copy()
    chosen: list[int] = []
    for _ in range(min(want, int(keep.sum()))):
        _, logdet = np.linalg.slogdet(m[None] + mats)
        logdet = np.where(free, logdet, -np.inf)
        i = int(np.argmax(logdet))
        chosen.append(i)
        free[i] = False
        m = m + mats[i]
    return chosen


def tiled_problem(p: Problem, tiles: Tiles) -> Problem:
    """`p` on the mosaic of `tiles`: image and depth crops (at `downsample`'s resolution),
    target crops, and weights that are the user's times 1 in the interiors (0 in the halos)."""
    s = p.ratio
    far = float(np.max(p.depth[np.isfinite(p.depth)])) if np.isfinite(p.depth).any() else 1.0
    image = tiles.mosaic(p.image, s, 0, 0)
    depth = tiles.mosaic(p.depth, s, 0, far)
    targets = tiles.mosaic(p.targets, 1, 1, 0)
    sqrt_w = tiles.mosaic(np.broadcast_to(p.sqrt_w, p.targets.shape), 1, 1, 0)
    mask = tiles.interior_mask()
    mask = mask[None, :, :, None] if sqrt_w.ndim == 4 else mask[None]
    sqrt_w = (sqrt_w * mask).astype(p.sqrt_w.dtype)
    # Each mosaic pixel's place in the whole frame, for the gains that depend on it.
    v, u, _ = frame(*p.photo, p.dtype)
    places = np.stack(np.broadcast_arrays(np.asarray(v)[:, None], np.asarray(u)[None, :]))
    frame_vu = tiles.mosaic(places, 1, 1, 0).astype(p.dtype)
    return dataclasses.replace(
        p,
        image=image,
        depth=depth,
        targets=targets,
        sqrt_w=sqrt_w,
        d=np.asarray(depth, np.float64),
        layout=dataclasses.replace(p.layout, frame_vu=frame_vu),
    )
