r"""What the camera does to the render before it is a photo: the nuisances and the encoding.

A fit compares photo `t` with

$$P_t(x) = E\Big(g_t\,V_t(x)\,L_t(x)\,\big[\mathcal{W}_t\,\mathrm{render}_t\big](x) + o_t\Big),$$

each part the identity at its null value, and each fitted only where the photo needs it
(`select.with_nuisances`):

- **exposure** (`gain` `g_t`, 1; `offset` `o_t`, 0): a shutter, ISO or aperture change between
  the shots, a black level;
- **vignetting** (`vignetting_r2` `a_t`, `vignetting_r4` `b_t`, 0): a radial gain
  `V_t = 1 + a_t rho^2 + b_t rho^4`, `rho` the distance from the frame's centre over its half
  diagonal (1 in the corners), low order as natural `cos^4` falloff is
  (`1 - 2 tan^2 + 3 tan^4 ...`); with the gain, `V_t(0) = 1`;
- **illumination** (`illumination_x`, `illumination_y` `c_t`, 0): a gain that tilts across the
  frame, `L_t = 1 + c_x u + c_y v` (`u, v` from the frame's centre over its half diagonal): a
  chart lit from one side (the all-in-focus image of a chart is its raster, evenly lit), or a
  light that changed between the shots;
- **registration** (`shift_x`, `shift_y`, `magnification` `m_t`, 0): photo pixel `x` sees the
  render at `c + (x - c - s_t) / (1 + m_t)` (`c` the frame's centre): a tripod that moved a
  fraction of a pixel, and focus breathing (a focus change scales the image). Shifts are in
  units of the half diagonal (the same number on every pyramid level), reported in photo
  pixels. The render is resampled with the separable Lanczos kernel of order 6 (12 taps;
  Duchon 1979; weights normalised to sum to 1, so it is the identity at integer positions and
  keeps a uniform image uniform): a sinusoid of up to a quarter of the sampling rate shifted
  by 0.1-0.5 px comes out within 0.34 % of its amplitude (order 3: 2.3 %; 0.35 cycles/px: 1.9 %
  against 14 %), where bilinear or cubic interpolation would blur the fine detail of the
  in-focus parts, which a fit would take for defocus.
- **encoding** `E`: with `luma`, the sRGB-encoded luma `Y' = 0.299 R' + 0.587 G' + 0.114 B'`
  (ITU-R BT.601, what JPEG's YCbCr keeps at full resolution; `R' = srgb(R)`, IEC 61966-2-1),
  one channel: a camera JPEG stores colour at half resolution (4:2:0), so only its luma holds
  the full-resolution blur; compared in the file's 8 x 8 blocks to within half a quantisation
  step where the photo's coefficients show its table (`jpeg.py`). Without, the linear photo
  itself.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


#: The nuisances in their order in the parameter vector, and their parameters (per photo).
NUISANCES: dict[str, tuple[str, ...]] = {
    "exposure": ("gain", "offset"),
    "vignetting": ("vignetting_r2", "vignetting_r4"),
    "illumination": ("illumination_x", "illumination_y"),
    "registration": ("shift_x", "shift_y", "magnification"),
}
#: Each parameter's null value (the camera adds nothing).
NULL = {"gain": 1.0}
#: The Lanczos kernel's order `a`: taps at offsets `-a + 1 .. a` from the floor of the source
#: position.
_LANCZOS = 6
_TAPS = np.arange(-_LANCZOS + 1, _LANCZOS + 1)
_LUMA = (0.299, 0.587, 0.114)


# The nuisances that depend on where a pixel is in the whole frame: not tested on tiles (a fit
# on tiles fits the gains where asked, with each pixel's place in the frame, `_Layout.frame_vu`).
FRAMED = frozenset({"vignetting", "illumination", "registration"})


def canonical(nuisances) -> tuple[str, ...]:
    """The nuisances named, in `NUISANCES` order; a `ValueError` for an unknown name."""
    nuisances = set(nuisances)
    unknown = nuisances - set(NUISANCES)
    if unknown:
        raise ValueError(f"unknown nuisance(s) {sorted(unknown)}; known: {list(NUISANCES)}")
    return tuple(n for n in NUISANCES if n in nuisances)


def half_diagonal(h: int, w: int) -> float:
    """Half the frame's diagonal (pixels): the unit of `frame`'s coordinates."""
    return 0.5 * float(np.hypot(h, w))


def frame(h: int, w: int, dtype) -> tuple[Array, Array, float]:
    """Pixel centres `(v (h,), u (w,))` in units of the half diagonal from the frame's centre,
    and the half diagonal `R` (pixels)."""
    r = half_diagonal(h, w)
    v = (jnp.arange(h, dtype=dtype) + 0.5 - h / 2) / r
    u = (jnp.arange(w, dtype=dtype) + 0.5 - w / 2) / r
    return v, u, r


def _lanczos(frac: Array, taps: Array) -> Array:
    """`sinc(x) sinc(x / a)` at `x = frac - taps` on `|x| < a`, 0 outside: continuous with a
    continuous derivative. `sin(pi x) = (-1)^taps sin(pi frac)` is taken from the fraction, so
    that at `frac = 0` every tap but the centre's is exactly 0 (the identity, bit for bit)."""
    x = frac[:, None] - taps[None, :]
    sign = jnp.where(taps % 2 == 0, 1.0, -1.0).astype(frac.dtype)
    safe = jnp.where(x == 0, 1, x)  # no 0/0 in the branch `where` drops (its gradient is kept)
    s1 = sign[None, :] * jnp.sin(jnp.pi * frac)[:, None] / (jnp.pi * safe)
    a = _LANCZOS
    s3 = jnp.sin(jnp.pi * safe / a) / (jnp.pi * safe / a)
    return jnp.where(x == 0, 1, jnp.where(jnp.abs(x) < a, s1 * s3, 0))


def _resample(img: Array, pos: Array, axis: int) -> Array:
    """`img` `(H, W, C)` read at source positions `pos` (pixels, centres at integers) along
    `axis` (0 rows, 1 columns) with normalised Lanczos weights; taps past the edge repeat the
    edge pixel (the border band leaves those photo pixels out of the fit)."""
    n = img.shape[axis]
    base = jnp.floor(jax.lax.stop_gradient(pos))
    taps = jnp.asarray(_TAPS, pos.dtype)
    idx = base[:, None] + taps[None, :]
    wts = _lanczos(pos - base, taps)
    wts = wts / jnp.sum(wts, axis=1, keepdims=True)
    idx = jnp.clip(idx, 0, n - 1).astype(jnp.int32)
    taken = jnp.take(img, idx, axis=axis)  # axis 0: (o, k, W, C); axis 1: (H, o, k, C)
    if axis == 0:
        return jnp.einsum("ok,okwc->owc", wts.astype(img.dtype), taken)
    return jnp.einsum("ok,hokc->hoc", wts.astype(img.dtype), taken)


def register(img: Float[Array, "h w c"], shift_x, shift_y, magnification) -> Array:
    """The photo of a camera whose image is `img` magnified by `1 + m` about the frame's centre
    and shifted by `(shift_x, shift_y)` (half diagonals): pixel `x` reads `img` at
    `c + (x - c - s) / (1 + m)`. Separable, as the map is, one axis at a time."""
    h, w = img.shape[:2]
    v, u, r = frame(h, w, img.dtype)
    # Each pixel's index plus its displacement `-(s + m x) / (1 + m)` (half diagonals, times
    # `R` in pixels): exactly the index at the null values, so the identity is exact there.
    rows = jnp.arange(h, dtype=img.dtype) - (shift_y + magnification * v) / (1 + magnification) * r
    cols = jnp.arange(w, dtype=img.dtype) - (shift_x + magnification * u) / (1 + magnification) * r
    return _resample(_resample(img, rows, 0), cols, 1)


def _places(h: int, w: int, dtype, frame_vu=None) -> tuple[Array, Array]:
    """Each pixel's `(v, u)` in the frame (half diagonals from its centre), broadcastable to
    `(h, w)`: from `frame`, or `frame_vu` `(2, h, w)` (a mosaic of tiles)."""
    if frame_vu is not None:
        return frame_vu[0].astype(dtype), frame_vu[1].astype(dtype)
    v, u, _ = frame(h, w, dtype)
    return v[:, None], u[None, :]


def vignette(h: int, w: int, a2, a4, dtype, frame_vu=None) -> Float[Array, "h w 1"]:
    """The radial gain `1 + a2 rho^2 + a4 rho^4` (`rho` over the half diagonal)."""
    v, u = _places(h, w, dtype, frame_vu)
    rho2 = v**2 + u**2
    return (1 + a2 * rho2 + a4 * rho2 * rho2)[..., None]


def illuminate(h: int, w: int, cx, cy, dtype, frame_vu=None) -> Float[Array, "h w 1"]:
    """The tilted gain `1 + cx u + cy v` (`u, v` over the half diagonal, 0 at the centre)."""
    v, u = _places(h, w, dtype, frame_vu)
    return (1 + cx * u + cy * v)[..., None]


def srgb_encode(x: Array) -> Array:
    """The sRGB transfer curve (IEC 61966-2-1), extended linearly below 0 and by its power law
    above 1; its derivative is finite everywhere."""
    return _srgb(x, jnp)


def _srgb(x, xp):
    """`srgb_encode` in `xp` (`np` on the host, in `x`'s precision)."""
    hi = xp.maximum(x, 0.0031308)  # keeps the power's argument (and its derivative) finite
    return xp.where(x <= 0.0031308, 12.92 * x, 1.055 * hi ** (1 / 2.4) - 0.055)


def luma(x: Float[Array, "*s 3"]) -> Float[Array, "*s 1"]:
    """The sRGB-encoded luma `Y'` (BT.601 weights) of linear RGB, keeping a channel axis."""
    return _luma(x, jnp)


def _luma(x, xp):
    """`luma` in `xp` (`np` on the host, in `x`'s precision: a JPEG's table, `jpeg.estimate`)."""
    e = _srgb(x, xp)
    return (_LUMA[0] * e[..., :1] + _LUMA[1] * e[..., 1:2] + _LUMA[2] * e[..., 2:3]).astype(x.dtype)


def camera(
    raw: Float[Array, "t h w *c"],
    params: dict[str, Array],
    nuisances: tuple[str, ...],
    is_luma: bool,
    frame_vu: Float[Array, "2 h w"] | None = None,
) -> Array:
    """The photos `(T, H, W[, C])` (one channel with `luma`) from the renders `raw`, with the
    fitted `nuisances`' parameters `params` (name -> `(T,)`); every other part at its null.
    `frame_vu`: each pixel's place in the frame, where `raw` is a mosaic of tiles."""
    grey = raw.ndim == 3
    x = raw[..., None] if grey else raw
    _, h, w, _ = x.shape

    def one(img, p):
        if "registration" in nuisances:
            img = register(img, p["shift_x"], p["shift_y"], p["magnification"])
        if "vignetting" in nuisances:
            a2, a4 = p["vignetting_r2"], p["vignetting_r4"]
            img = img * vignette(h, w, a2, a4, img.dtype, frame_vu)
        if "illumination" in nuisances:
            cx, cy = p["illumination_x"], p["illumination_y"]
            img = img * illuminate(h, w, cx, cy, img.dtype, frame_vu)
        if "exposure" in nuisances:
            img = p["gain"] * img + p["offset"]
        return img

    names = [n for k in nuisances for n in NUISANCES[k]]
    x = jax.vmap(one)(x, {n: params[n] for n in names}) if names else x
    if is_luma:
        return luma(x)
    return x[..., 0] if grey else x


# Rows per band of `chroma_detail` (temporaries of a few MB at 6000 px wide), and the pixels it
# reads at most: beyond, every k-th band (a ratio of energies needs no more to be decided).
_CHROMA_BAND = 256
_CHROMA_PIXELS = 4_000_000


def chroma_detail(photo: np.ndarray) -> float:
    r"""How much colour detail at the pixel scale a colour photo has, relative to its luma's:
    the energy of the second differences `[1, -2, 1]` (both axes) of the sRGB-encoded chroma
    `Cb, Cr` over that of the luma `Y'`. A camera JPEG's chroma, stored at half resolution and
    interpolated, has almost none (measured in `fits/captures.py`); a linear or 4:4:4 photo keeps
    its scene's colour detail and its noise (white noise in R, G, B puts about 0.9 of the luma's
    energy in each chroma channel). `nan` for a grey photo. In float32, summed in float64; over
    bands of rows spread across the frame, about `_CHROMA_PIXELS` of its pixels."""
    x = np.asarray(photo)
    if x.ndim != 3 or x.shape[-1] != 3 or min(x.shape[:2]) < 3:
        return float("nan")
    to_ycc = np.array([_LUMA, (-0.168736, -0.331264, 0.5), (0.5, -0.418688, -0.081312)], np.float32)
    sums = np.zeros(3)  # Y', Cb, Cr
    # In bands of rows, each with the two rows below it for the vertical differences (a 24 MP
    # photo at once: temporaries of gigabytes).
    b = _CHROMA_BAND
    every = max(1, math.ceil(x.shape[0] * x.shape[1] / _CHROMA_PIXELS))
    for r0 in range(0, x.shape[0], b * every):
        c = _srgb(x[r0 : r0 + b + 2].astype(np.float32, copy=False), np) @ to_ycc.T  # (rows, W, 3)
        d2x = c[:b, :-2] - 2 * c[:b, 1:-1] + c[:b, 2:]
        d2y = c[:-2] - 2 * c[1:-1] + c[2:]
        for d in (d2x, d2y):
            sums += np.einsum("hwc,hwc->c", d, d, dtype=np.float64)
    if sums[0] <= 0:
        return float("nan")
    return float((sums[1] + sums[2]) / sums[0])
