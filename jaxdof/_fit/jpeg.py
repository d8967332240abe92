r"""A camera JPEG's luma compared in the file's own terms: its 8 x 8 block DCT, to within half a
quantisation step.

A JPEG stores each 8 x 8 block of the luma `Y'` (0-255, `photo.luma`) as its orthonormal 2-D
DCT-II coefficients, each rounded to a multiple of its step `Q_uv`, the file's quantisation table
(ITU-T T.81, Annexes A and K). The decoded photo therefore gives each coefficient only to within
half a step: every value in `[c - Q/2, c + Q/2]` writes the same file. A pixel residual takes
that rounding for signal: the small fine-detail coefficients of the parts in focus are rounded to
0, which looks like blur (the ray-traced fgbg at quality 90 fitted its focus 2.4 % long). Here
the residual of a block is the DCT of render minus photo, less its part within half a step,

$$r = \sqrt{w} \odot \mathrm{DCT}_8^{-1}\big(d - \mathrm{clip}(d, -Q/2, Q/2)\big),\qquad
  d = \mathrm{DCT}_8(\hat Y' - Y'),$$

the render less the photo the file could hold that is nearest to it: 0 wherever the render
encodes to the file's values, so the fit sees what the file holds (the "consistent set" of JPEG
decoding: A. Zakhor, "Iterative procedures for reduction of blocking effects in transform image
coding", IEEE Trans. CSVT 2 (1992) 91-95; Y. Yang, N. Galatsanos and A. Katsaggelos, IEEE Trans.
CSVT 3 (1993) 421-432). The transform is orthonormal: with every `Q = 0` this is the pixel
residual, and in an evenly weighted block its sum of squares is that of the coefficients beyond
half a step. Back in pixels, a weight still weighs a pixel: a depth edge's ramp, the border band,
a hole. (Weighting each block in its coefficients by its smallest weight instead left out most of
the ray-traced `thin` scene, whose edges cross nearly every block: focus 10 % short; keeping
the pixel residual in unevenly weighted blocks kept the bias near `fgbg`'s edge: 2.1 % long.)

**The table from the photo alone** (`estimate`): coefficient `uv` of a decoded JPEG lies on the
lattice `Q_uv Z`, blurred by the decoder's rounding (about 0.35 levels). For each step `q` the
coherence `mean cos(2 pi c / q)` over the coefficients outside the zero bin (`|c| >= q/2`) is
near 1 on the lattice or a divisor of it and near 0 off it; the step is the `q` of the highest
coherence (ties to the larger), accepted where it clears `max(0.5, 3 / sqrt(n))`. A photo that
was never a JPEG has no lattice: its coherences are noise of size `1 / sqrt(n)`. Entries the
photo leaves undetermined (every coefficient in the zero bin, or steps too small to tell from the
rounding) are the standard (IJG) table at the quality that matches the determined ones, where
one does; else the largest step determined at no higher order `u + v` (tables rise with
frequency), or 1. Source for the approach: Z. Fan and R. de Queiroz, "Identification of bitmap
compression history: JPEG detection and quantizer estimation", IEEE Trans. Image Processing 12
(2003) 230-235.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float

from .photo import _luma


#: The standard luminance table (ITU-T T.81 Annex K.1), scaled by the quality as the IJG library
#: (and Pillow, and most cameras' firmware) scales it.
_ANNEX_K = np.array(
    [
        [16, 11, 10, 16, 24, 40, 51, 61],
        [12, 12, 14, 19, 26, 58, 60, 55],
        [14, 13, 16, 24, 40, 57, 69, 56],
        [14, 17, 22, 29, 51, 87, 80, 62],
        [18, 22, 37, 56, 68, 109, 103, 77],
        [24, 35, 55, 64, 81, 104, 113, 92],
        [49, 64, 78, 87, 103, 121, 120, 101],
        [72, 92, 95, 98, 112, 100, 103, 99],
    ]
)
# The estimator's bounds: the largest step tried (the Annex K table at quality 50 and above has
# none larger than 121), the fewest coefficients outside the zero bin a step is judged on, the
# coherence a step must reach, the determined entries a photo needs to be taken for a JPEG, and
# the blocks read at most (spread over the frame).
_MAX_STEP = 128
_MIN_COUNT = 16
_COHERENCE = 0.5
_MIN_ENTRIES = 8
_MAX_BLOCKS = 2048
# Luma levels within which a block's pixels count as clipped (0 or 255): clipping moves a block
# off the lattice.
_CLIP_MARGIN = 1.0


def ijg_table(quality: int) -> np.ndarray:
    """The IJG library's luminance table at `quality` (1-100): Annex K scaled by `5000 / q`
    below 50 and by `200 - 2 q` above, rounded, in `[1, 255]` (libjpeg's `jpeg_set_quality`)."""
    scale = 5000 // quality if quality < 50 else 200 - 2 * quality
    return np.clip((_ANNEX_K * scale + 50) // 100, 1, 255)


def dct_matrix(dtype=np.float64) -> np.ndarray:
    """The orthonormal 8-point DCT-II `D` (`D @ D.T = I`): a block's coefficients are `D B D^T`."""
    k = np.arange(8)
    d = np.cos(np.pi * (2 * k[None, :] + 1) * k[:, None] / 16) * np.sqrt(2 / 8)
    d[0] /= np.sqrt(2)
    return d.astype(dtype)


@dataclasses.dataclass(frozen=True)
class JpegGrid:
    """Where a photo's 8 x 8 blocks lie and each target's quantisation table: a static part of
    the residual (hashable), so the compiled solve is keyed on it.

    - `tables`: per target, the 64 steps in row-major order (luma levels, 0-255 scale);
    - `origin`: `(row, column)` of the first block's top-left pixel, each in `0..7`;
    - `shape`: `(H, W)` of the photo the grid belongs to (the residual applies it only there).
    """

    tables: tuple[tuple[float, ...], ...]
    origin: tuple[int, int]
    shape: tuple[int, int]

    def on(self, shape: tuple[int, int]) -> JpegGrid:
        """The grid of a mosaic of `shape` cut from the photo on its grid (`tiles.py`)."""
        return dataclasses.replace(self, shape=(int(shape[0]), int(shape[1])))

    def steps(self, dtype) -> Float[Array, "t 1 8 1 8"]:
        """The tables, broadcastable over blocks `(T, by, 8, bx, 8)`."""
        q = np.asarray(self.tables, np.float64).reshape(-1, 1, 8, 1, 8)
        return jnp.asarray(q, dtype)

    def residual(
        self,
        pred: Float[Array, "t h w 1"],
        targets: Float[Array, "t h w 1"],
        sqrt_w: Float[Array, "*#s"],
    ) -> Float[Array, "t h w 1"]:
        """`sqrt(w)` times the render less the photo the file could hold nearest to it: per
        block, the DCT of `pred - targets` less its part within half a step, back in pixels
        (luma, `[0, 1]`). The transform is orthonormal, so an evenly weighted block's sum of
        squares is that of its coefficients beyond half a step; a weight still weighs a pixel
        (a depth edge's ramp, the border band, a hole). A block the file clipped (the photo's
        luma at 0 or 255: off the lattice) and the pixels outside whole blocks keep the plain
        difference."""
        t, h, w = targets.shape[:3]
        oy, ox = self.origin
        by, bx = (h - oy) // 8, (w - ox) // 8
        sl = (slice(None), slice(oy, oy + 8 * by), slice(ox, ox + 8 * bx))

        def blocks(x):
            return x[sl][..., 0].reshape(t, by, 8, bx, 8)

        diff = pred - targets
        d = blocks(diff)
        m = jnp.asarray(dct_matrix(), d.dtype)
        c = jnp.einsum("uk,tikjl,vl->tiujv", m, 255 * d, m)
        half = 0.5 * self.steps(d.dtype)
        # The render less the file-consistent photo nearest to it, back in pixels.
        e = jnp.einsum("uk,tiujv,vl->tikjl", m, c - jnp.clip(c, -half, half), m) / 255
        # A block the file clipped (0 or 255 in the luma) is off its lattice: pixels there.
        y = 255 * lax.stop_gradient(blocks(targets))
        inside = (jnp.min(y, axis=(2, 4), keepdims=True) > _CLIP_MARGIN) & (
            jnp.max(y, axis=(2, 4), keepdims=True) < 255 - _CLIP_MARGIN
        )
        e = jnp.where(inside, e, d)
        diff = diff.at[sl].set(e.reshape(t, 8 * by, 8 * bx)[..., None])
        return diff * jnp.broadcast_to(sqrt_w, targets.shape)


def _coefficients(photo: np.ndarray, origin: tuple[int, int], keep: int, encode) -> np.ndarray:
    """The block DCT coefficients `(n, 64)` (row-major `uv`) of one photo `(H, W[, C])` on the
    grid at `origin`, its luma `encode(pixels)` (0-1) read only in about `keep` whole blocks
    spread evenly over it (a 24 MP photo is not encoded whole), without the blocks that touch 0
    or 255 (clipped: off the lattice)."""
    oy, ox = origin
    h, w = photo.shape[:2]
    by, bx = (h - oy) // 8, (w - ox) // 8
    n = np.unique(np.linspace(0, by * bx - 1, min(keep, by * bx)).astype(np.int64))
    i, j = np.divmod(n, bx)
    k = np.arange(8)
    rows = oy + 8 * i[:, None, None] + k[None, :, None]
    cols = ox + 8 * j[:, None, None] + k[None, None, :]
    b = 255 * np.asarray(encode(photo[rows, cols]), np.float64)  # (n, 8, 8)
    lo, hi = b.min(axis=(1, 2)), b.max(axis=(1, 2))
    b = b[(lo > _CLIP_MARGIN) & (hi < 255 - _CLIP_MARGIN)]
    m = dct_matrix()
    return np.einsum("uk,nkl,vl->nuv", m, b, m).reshape(-1, 64)


def _steps(c: np.ndarray, max_step: int = _MAX_STEP) -> np.ndarray:
    """Each entry's step (0 where undetermined), from the coefficients `(n, 64)`."""
    q = np.arange(1, max_step + 1, dtype=np.float64)
    steps = np.zeros(64)
    for k in range(64):
        ck = c[:, k]
        outside = np.abs(ck)[:, None] >= q[None, :] / 2  # (n, q): outside the zero bin
        count = outside.sum(axis=0)
        coherence = np.where(outside, np.cos(2 * np.pi * ck[:, None] / q[None, :]), 0).sum(0)
        coherence = np.where(count >= _MIN_COUNT, coherence / np.maximum(count, 1), -np.inf)
        # The highest coherence, ties (the step's divisors, at the rounding) to the larger.
        i = len(q) - 1 - int(np.argmax(coherence[::-1]))
        top, n = coherence[i], count[i]
        if q[i] >= 2 and top >= max(_COHERENCE, 3 / np.sqrt(max(n, 1))):
            steps[k] = q[i]
    return steps


def _filled(steps: np.ndarray) -> tuple[np.ndarray, int | None]:
    """The table with its undetermined entries filled (module docstring), and the IJG quality
    that matched, if one did."""
    known = steps > 0
    matches = [(np.sum(ijg_table(q).reshape(-1)[known] == steps[known]), q) for q in range(1, 101)]
    hits, quality = max(matches)
    if hits >= 0.9 * known.sum():
        return np.where(known, steps, ijg_table(quality).reshape(-1)), quality
    order = (np.arange(64) // 8) + (np.arange(64) % 8)
    filled = steps.copy()
    for k in np.flatnonzero(~known):
        below = known & (order <= order[k])
        filled[k] = steps[below].max() if below.any() else 1.0
    return filled, None


def estimate(photos: np.ndarray, encode=None) -> tuple[JpegGrid | None, dict]:
    """The grid and tables of photos `(T, H, W[, C])` decoded from JPEG files, and a record of
    what was found; `None` for a photo with too few steps on a lattice (not a JPEG, or one
    resampled since). `encode` maps pixels `(..., C)` to the file's luma `(...)` in `[0, 1]`
    (`photo.luma` of linear RGB); `None`: `photos` `(T, H, W)` are that luma. One table per photo;
    the grid at `(0, 0)` (a whole file) is tried first, then every other origin (a crop)."""
    if encode is None:
        photos, encode = np.asarray(photos)[..., None], lambda x: x[..., 0]
    t, h, w = photos.shape[:3]
    record: dict = {"found": False}
    if h < 16 or w < 16:
        return None, record

    def found(origin, keep):
        tables = [_steps(_coefficients(photos[i], origin, keep, encode)) for i in range(t)]
        return tables if all(np.sum(s >= 2) >= _MIN_ENTRIES for s in tables) else None

    origin, tables = (0, 0), found((0, 0), _MAX_BLOCKS)
    if tables is None:
        # Another origin: judged on a few blocks each, the winner on all of them.
        others = [(oy, ox) for oy in range(8) for ox in range(8) if (oy, ox) != (0, 0)]
        score = [np.sum(_steps(_coefficients(photos[0], o, 128, encode), 48) >= 2) for o in others]
        origin = others[int(np.argmax(score))]
        tables = found(origin, _MAX_BLOCKS) if max(score) >= _MIN_ENTRIES else None
    if tables is None:
        return None, record
    filled, qualities = zip(*(_filled(s) for s in tables))
    grid = JpegGrid(tuple(tuple(map(float, f)) for f in filled), origin, (h, w))
    record = {
        "found": True,
        "origin": origin,
        "quality": list(qualities),
        "determined": [int(np.sum(s > 0)) for s in tables],
    }
    return grid, record


def jpeg_align(grid: JpegGrid | None) -> int:
    """The alignment of a fit's tiles: 8 for a JPEG grid at `(0, 0)` (the tiles then lie on its
    blocks, `tiles._grid`), else 1."""
    return 8 if grid is not None and grid.origin == (0, 0) else 1


def from_table(table, t: int, shape: tuple[int, int]) -> JpegGrid:
    """The grid of `t` photos of `shape` read whole from JPEG files of the luma table `table`
    (64 steps, row-major, as Pillow's `quantization[0]`); a `ValueError` for another table."""
    q = np.asarray(table, np.float64).reshape(-1)
    if q.size != 64 or not np.all(np.isfinite(q)) or np.any(q < 1):
        raise ValueError(
            f"jpeg must be None, True, False or a quantisation table of 64 steps >= 1 "
            f"(row-major, e.g. PIL's Image.quantization[0]); got {q.size} values"
        )
    return JpegGrid((tuple(map(float, q)),) * t, (0, 0), shape)


def jpeg_grid(targets, on: bool, jpeg) -> tuple[JpegGrid | None, dict]:
    """`fit_lens`'s `jpeg`: the photos' grid and the decision's record, for photos compared in
    their luma (`on`): the caller's table, else `estimate`d (`None` for `jpeg=False`, and for
    photos not compared in their luma, which a `jpeg` other than `None` refuses)."""
    if jpeg is False:
        return None, {"found": False, "forced": True}
    if not on:
        if jpeg is not None:
            raise ValueError("jpeg compares the photos' luma: it needs colour photos (luma)")
        return None, {"found": False, "forced": False}
    photos = _stacked(targets)
    if jpeg is None or jpeg is True:
        grid, record = estimate(photos, lambda x: _luma(np.asarray(x, np.float64), np)[..., 0])
        if grid is None and jpeg is True:
            raise ValueError(
                "jpeg=True: the photos' luma has no JPEG quantisation lattice (not decoded from a "
                "JPEG file, or resized since); pass the file's table, or jpeg=None"
            )
        return grid, {**record, "forced": jpeg is True}
    grid = from_table(jpeg, photos.shape[0], photos.shape[1:3])
    return grid, {"found": True, "origin": (0, 0), "quality": None, "forced": True}


def _stacked(targets) -> np.ndarray:
    """The targets as one array `(T, *photo)`."""
    if isinstance(targets, (list, tuple)):
        return np.stack([np.asarray(t, np.float32) for t in targets])
    t = np.asarray(targets, np.float32)
    return t if t.ndim == 4 else t[None]
