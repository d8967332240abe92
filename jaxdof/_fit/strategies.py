"""`fit_lens`'s search strategies, in numpy on the host: where to start, how large a window, which
pixels to leave out along the border, and the coarse-to-fine pyramid (levels, downsampled problems,
and the starts handed from level to level)."""

from __future__ import annotations

import math

import numpy as np

from .layout import _Arr, _Layout, _Spec, theta_floor


# A solve compiled anew (a refit at a smaller window; the soft render beside the occlusion one)
# saves work per render; it pays for its compile (seconds) only where that work, over every pixel
# of every target, exceeds this (tap-pixels). A render gathers roughly 1e8-1e9 tap-pixels per
# second on one core (an estimate) and a solve takes tens of renders, so below it the saving is
# under a second, while the compile of the 40 x 56 test scenes' solve took 6-12 s (XLA level 0).
COMPILE_WORK = 3e7


# --------------------------------------------------------------------------------------------
# Starts.
# --------------------------------------------------------------------------------------------


def start_lenses(
    base: np.ndarray, depth: np.ndarray, *, free, starts: int, fcap: np.ndarray | None = None
) -> np.ndarray:
    """`fit_lens`'s starting lenses: rows `(S, T, 4)` of `(f, N, d_f, pitch)` (m, -, m, m).

    The `init` lens first (`base`, rows `(T, 4)`; `focus_distance = inf` allowed). With the focus
    distance free, the others place it evenly in diopters across the scene's depth range (both
    sides of every depth: the near/far ambiguity), keeping each target's blur scale `K` through
    `N` where that is free (an init focused at infinity has `K = 0`: then `N` is kept). With
    the focus distance fixed, `K` is spread by factors of 2 (through `N`, else `f`), keeping `f`
    under `fcap` (`(T,)`, m; default: the bound `fit_lens` uses, just under the nearest depth and
    a fixed focus distance).
    """
    base = np.asarray(base, np.float64)
    depth = np.asarray(depth, np.float64)
    if fcap is None:
        spec = _Spec(tuple(free), (), base.shape[0])
        fcap = np.asarray(spec.layout(base, depth).fcap, np.float64)
    out = [base.copy()]
    finite = depth[np.isfinite(depth)]
    f, n, d_f, pitch = (base[:, i] for i in range(4))
    k = f * f / (2 * n * (d_f - f) * pitch)  # 0 focused at infinity
    if "focus_distance" in free and finite.size:
        near, far = float(np.min(finite)), float(np.max(finite))
        if np.any(np.isinf(depth)) or far <= near * 1.01:
            far = max(far * 4, far + 1.0)
        lo, hi = 1 / far, 1 / near  # diopters
        for i in range(starts - 1):
            dpt = hi + (lo - hi) * (i + 0.5) / (starts - 1)
            s = base.copy()
            s[:, 2] = np.maximum(1 / dpt, f * 1.05)
            if "f_number" in free:
                keep_k = k > 0
                s[:, 1] = np.where(
                    keep_k, f * f / (2 * np.where(keep_k, k, 1) * (s[:, 2] - f) * pitch), n
                )
            out.append(s)
    else:
        factors = [0.5, 2.0, 0.25, 4.0, 0.125, 8.0]
        for i in range(starts - 1):
            c = factors[i % len(factors)] ** (1 + i // len(factors))
            s = base.copy()
            if "f_number" in free:
                s[:, 1] = n / c
            elif "focal_length" in free:
                s[:, 0] = np.minimum(f * math.sqrt(c), 0.9 * fcap)  # K ~ f^2 for f << d_f
            out.append(s)
    return np.stack(out)


# --------------------------------------------------------------------------------------------
# The window.
# --------------------------------------------------------------------------------------------

# Windows are rounded up to this grid so that fits of similar scenes share a compiled solve.
_WINDOWS = (2, 3, 4, 5, 6, 8, 10, 12, 16, 20, 24, 32, 40, 48, 64, 80, 96, 128, 160, 192, 256)


def window_for(radius: float, cap: float) -> float:
    """The filter window (pixels) `fit_lens` picks for circles up to `radius` pixels: headroom
    of 1.5x + 1 px, rounded up to a grid (so that similar scenes share a compiled solve), at most
    `cap` (the photo's longer side)."""
    need = 1.5 * radius + 1.0
    w = next((float(x) for x in _WINDOWS if x >= need), float(math.ceil(need)))
    return float(min(w, max(cap, 2.0)))


def window_of(
    forward, rows: np.ndarray, depth, photo, scale: int = 1, fixed: float | None = None
) -> float:
    """`fit_lens`'s window (pixels) for the lenses `rows` on a problem reduced `scale` times (a
    pyramid level, a scout) whose photo is `photo` `(H, W)`: the caller's `fixed` window (the
    same extent in the scene), else the reach of the lenses' circles over `depth` with the pitch
    `scale` times coarser (`window_for`)."""
    if fixed is not None:
        return fixed / scale
    rows = np.asarray(rows, np.float64).copy()
    rows[..., 3] = rows[..., 3] * scale
    r = forward.max_circle(rows, np.asarray(depth, np.float64))
    return window_for(r, float(max(photo[:2])))


def grown_window(window: float, r: float, photo, fixed: float | None) -> float | None:
    """The window a refit takes when the fitted circles (up to `r` px) outgrew `window` (allowed
    past the photo's side, so that the circles fit), or None: they fit, or the window is the
    caller's."""
    if fixed is not None or r <= window:
        return None
    return window_for(r, max(float(max(photo[:2])), 1.5 * r + 1.0))


def shrunk_window(window: float, r: float, photo, fixed: float | None) -> float | None:
    """The smaller window that the fitted circles (up to `r` px) need, when it is smaller than
    `window` (the starts' circles, spread in diopters, can set a far larger one), or None."""
    smaller = window_for(r, float(max(photo[:2])))
    return None if fixed is not None or smaller >= window else smaller


# --------------------------------------------------------------------------------------------
# Coarse-to-fine.
# --------------------------------------------------------------------------------------------

# The automatic pyramid stops coarsening before the image's shorter side drops under
# `_PYRAMID_MIN_SIZE` pixels (a 24 x 24 image still constrains two parameters with hundreds of
# residuals, and its window of a few pixels is not most of the image) or before the init's largest
# circle drops under `_PYRAMID_MIN_CIRCLE` pixels: circles under half a pixel render as the identity
# (the dead zone, zero gradient), and the init may overestimate K by 2x, so the coarsest level keeps
# the init's largest circle at twice the dead zone's edge. An explicit `pyramid` may go down to
# `_PYRAMID_FLOOR` pixels.
_PYRAMID_MIN_SIZE = 24
_PYRAMID_MIN_CIRCLE = 1.0
_PYRAMID_FLOOR = 8
# An alternative coarse solution is refined at the finer levels too (so that the near/far test
# sees it at full resolution) when its coarse loss is within this factor of the best one's: coarse
# losses carry the downsampling's model error, so only a generous margin keeps true ties.
_PYRAMID_TIE = 2.0
# Tolerance of the default solver on the coarse levels. A coarse level's minimum differs from the
# full-resolution one by the downsampling's model error (measured ~1-3 % in N and d_f on the
# 96 x 96 scenes of fits/recover.py), so solving it tighter than that buys nothing: the finer
# levels move the answer anyway.
_COARSE_TOL = 1e-3


def auto_levels(shape: tuple[int, int], r_init: float) -> int:
    """`fit_lens`'s automatic number of pyramid levels (1: full resolution only) for a photo of
    `shape` `(H, W)` whose init lens makes circles up to `r_init` pixels: the most halvings that
    keep the coarsest photo at least 24 px on its shorter side and the init's largest circle at
    least 1 px (twice the half-pixel dead zone)."""
    levels = 1
    side = min(shape)
    while side // 2 >= _PYRAMID_MIN_SIZE and r_init / 2**levels >= _PYRAMID_MIN_CIRCLE:
        side //= 2
        levels += 1
    return levels


def _check_pyramid(pyramid, shape: tuple[int, int]) -> int | None:
    """Validate an explicit `pyramid` (number of levels); `None` stays `None` (automatic)."""
    if pyramid is None:
        return None
    if isinstance(pyramid, bool) or not isinstance(pyramid, (int, np.integer)) or pyramid < 0:
        raise ValueError(
            f"pyramid must be None (automatic), 0 or 1 (full resolution only) or the number of "
            f"levels >= 2 as a Python int, got {pyramid!r}"
        )
    levels = max(int(pyramid), 1)
    side = min(shape) // 2 ** (levels - 1)
    if side < _PYRAMID_FLOOR:
        most = 1
        while min(shape) // 2**most >= _PYRAMID_FLOOR:
            most += 1
        raise ValueError(
            f"pyramid={pyramid} would shrink the {shape[0]} x {shape[1]} image to {side} px at its "
            f"coarsest level (under {_PYRAMID_FLOOR} px); use at most pyramid={most}, or None to "
            "choose automatically"
        )
    return levels


def _box2(x: np.ndarray, axes: tuple[int, int]) -> np.ndarray:
    """2 x 2 box average over two adjacent `axes` (H, W) of `x`, dropping an odd last row/column.

    The four pixels summed in the order in which numpy 2's `mean` over the two axes of a
    reshaped view sums them (each row's pair first; then the two pair sums where nothing
    follows the columns, else one by one), so the same values (checked bitwise against it), at
    4-5x its speed: no strided reduction (a 24 MP colour frame in 0.2 s)."""
    a, b = axes
    h, w = x.shape[a] // 2 * 2, x.shape[b] // 2 * 2
    x = x[(slice(None),) * a + (slice(0, h), slice(0, w))]
    pre = (slice(None),) * a

    def at(i: int, j: int) -> np.ndarray:
        return x[pre + (slice(i, None, 2), slice(j, None, 2))]

    if math.prod(x.shape[b + 1 :]) == 1:
        total = (at(0, 0) + at(0, 1)) + (at(1, 0) + at(1, 1))
    else:
        total = ((at(0, 0) + at(0, 1)) + at(1, 0)) + at(1, 1)
    return total / x.dtype.type(4)


def _downsample(image, depth, targets, sqrt_w, base, s: int = 1):
    """One pyramid level down: halved images, depth and weights; the pixel pitch doubled.

    With `downsample = s` (the image `s` times the targets' resolution) the image and depth are
    first cropped to `s` times the targets' even part, so that the ratio stays `s` exactly.

    - `image`, `targets`: 2 x 2 box averages, in linear light (what a sensor with twice the pitch
      records, up to the blur/averaging order, which the finer levels correct).
    - `depth`: averaged in inverse depth. The signed circle `K (1 - d_f / d)` is affine in `1 / d`,
      so the coarse pixel gets exactly the mean signed circle of its four pixels (then halved, in
      the doubled pitch's units); averaging depth itself would drag a near/far pair toward the
      far side (1 m with infinity would average to infinity). `1 / inf = 0` is kept exact.
    - weights: the harmonic mean of `w = sqrt_w^2`. For inverse-variance weights this is exactly
      (up to a constant factor 4, irrelevant to the minimiser) the inverse variance of the
      averaged target, and a masked pixel (w = 0), whose target value is arbitrary, masks the
      coarse pixel it falls in instead of leaking into its average.
    """
    h, w = targets.shape[1] // 2 * 2 * s, targets.shape[2] // 2 * 2 * s
    image, depth = image[:h, :w], depth[:h, :w]
    inv = _box2(1.0 / depth, (0, 1))  # depth > 0 everywhere (checked), inf -> 0
    with np.errstate(divide="ignore"):
        depth = (1.0 / inv).astype(depth.dtype)
    with np.errstate(divide="ignore"):
        # w >= +0, so 1 / w is inf exactly where w = 0, and 1 / inf = +0 where a masked pixel
        # masks the coarse one
        mean_inv = _box2(1.0 / (sqrt_w * sqrt_w), (1, 2))
        w_c = 1.0 / mean_inv
    base = base.copy()
    base[:, 3] = base[:, 3] * 2
    return (
        _box2(image, (0, 1)).astype(image.dtype),
        depth,
        _box2(targets, (1, 2)).astype(targets.dtype),
        np.sqrt(w_c).astype(sqrt_w.dtype),
        base,
    )


def reductions(p, ks) -> dict[int, tuple]:
    """The arrays of problem `p` (`prepare.Problem`) box-averaged `2^k` times (`_downsample`, `k`
    times), for each `k` of `ks`: `{k: (image, depth, targets, sqrt_w, base)}`; the levels
    between are not kept."""
    ks = set(ks)
    level = (p.image, p.depth, p.targets, p.sqrt_w, p.b)
    out = {0: level} if 0 in ks else {}
    for k in range(1, max(ks, default=0) + 1):
        level = _downsample(*level, p.ratio)
        if k in ks:
            out[k] = level
    return out


def _rows(theta: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Lens rows `(f, N, d_f, pitch)` `(T, 4)` from a solution's slot values `theta`
    (`layout.theta`: the focus as its power `1 / d_f`, 0 at infinity) and the pitch of `base`."""
    t = base.shape[0]
    fields = np.asarray(theta, np.float64)[: 3 * t].reshape(3, t).T.copy()
    with np.errstate(divide="ignore"):
        fields[:, 2] = 1 / fields[:, 2]
    return np.concatenate([fields, np.asarray(base, np.float64)[:, 3:4]], axis=1)


def distinct(
    a: np.ndarray, b: np.ndarray, floor: np.ndarray, slack: np.ndarray | float = 0.0
) -> bool:
    """Whether two solutions' `theta` (used slots) differ anywhere by more than
    `slack + 1e-3 max(|b|, floor)` (`floor`: `layout.theta_floor`, so that two focus powers
    near 0, both at infinity, are not told apart by their relative difference)."""
    return bool(np.any(np.abs(a - b) > slack + 1e-3 * np.maximum(np.abs(b), floor)))


def _next_starts(info, base: np.ndarray, y0s: _Arr, spec: _Spec, layout: _Layout):
    """Starts for the next finer level from a coarse level's solve: its best solution, and the
    lowest-loss converged solution at a distinct lens if its loss is within `_PYRAMID_TIE` of the
    best (a possible near/far tie that only the full-resolution test can settle). A coarse level
    whose best start did not converge hands on every start it was given, best solution first.

    Returns the parameter vectors `(S', P)` and their lens rows `(S', T, 4)` (with the pitch of
    `base`; the forward model's `max_circle` of them sizes the next window)."""
    ys, loss, converged, best = info["ys"], info["loss"], info["converged"], int(info["best"])
    theta = np.asarray(info["theta"], np.float64)
    pick = [best]
    if not converged[best]:
        out = np.concatenate([ys[best][None], np.asarray(y0s)], axis=0)
        th = np.concatenate([theta[best][None], theta], axis=0)
        return out, np.stack([_rows(t, base) for t in th])
    # The lens slots only: a near/far tie is one of lenses. The nuisances' coefficients are near
    # 0 (an offset, the light's tilt), where the coarse tolerance's scatter of one basin's
    # solutions is far beyond `distinct`'s relative margin.
    used = [i for i in spec.used if i < 3 * spec.n_targets]
    floor = np.asarray(theta_floor(layout, spec.nuisances), np.float64)[used]
    for i in np.argsort(loss):
        if i == best or not converged[i]:
            continue
        far = distinct(theta[i, used], theta[best, used], floor)
        if far and loss[i] <= _PYRAMID_TIE * loss[best] + 1e-12 * (1 + loss[best]):
            pick.append(int(i))
        break  # only the lowest-loss alternative; a worse one is no tie
    return ys[pick], np.stack([_rows(theta[i], base) for i in pick])


# --------------------------------------------------------------------------------------------
# The border.
# --------------------------------------------------------------------------------------------


def check_border(border) -> int | None:
    """Validate `fit_lens`'s `border`: `None` for the window's band (`"auto"` or `True`), else the
    band in photo pixels (`False` is 0)."""
    if border is True or (isinstance(border, str) and border == "auto"):
        return None
    if border is False:
        return 0
    if isinstance(border, (int, np.integer)) and not isinstance(border, bool) and border >= 0:
        return int(border)
    raise ValueError(
        f"border must be 'auto' (or True: leave out the band of photo pixels that light from "
        f"outside the frame reaches, the window's), False or 0 (keep every pixel), or a band "
        f"width in photo pixels as an int >= 0; got {border!r}"
    )


def border_mask(shape: tuple[int, ...], band: int) -> np.ndarray:
    """`(H, W)` 0/1 mask that is 0 within `band` pixels of the edges of a `shape` `(H, W, ...)`
    photo and 1 inside (all 0 when the band covers the frame)."""
    h, w = shape[0], shape[1]
    mask = np.zeros((h, w))
    if band == 0:
        mask[:] = 1
    elif 2 * band < min(h, w):
        mask[band : h - band, band : w - band] = 1
    return mask


def apply_border(sqrt_w: np.ndarray, band: int) -> tuple[np.ndarray, int]:
    """`sqrt_w` `(T, H, W[, C])` with the border band's weights set to 0, and the band used:
    `band`, or 0 (every pixel kept) when the band leaves no pixel with non-zero weight."""
    mask = border_mask(sqrt_w.shape[1:3], band)
    mask = mask[None, :, :, None] if sqrt_w.ndim == 4 else mask[None]
    masked = (sqrt_w * mask).astype(sqrt_w.dtype)
    if band > 0 and not np.any(masked > 0):
        return sqrt_w, 0
    return masked, band


def level_band(border: int | None, forward, window: float, level: int) -> int:
    """The band (pixels of pyramid `level`) to leave out: the forward model's reach in a render
    with that level's `window` (`border=None`, automatic), else `border` photo pixels at full
    resolution, `ceil(border / 2^level)` at the level."""
    if border is None:
        return int(forward.border_band(window))
    return -(-border // 2**level)
