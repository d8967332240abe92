"""`render`: image + depth + lens -> circle of confusion -> filter (-> the photo's pixels)."""

from __future__ import annotations

import functools
import logging
import math
from typing import ClassVar, final

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array

from . import _tuning
from ._corrections import FOOTPRINT_REACH, footprint_prefilter
from ._custom_types import DepthLike, Image, ImageLike
from ._filters import (
    AbstractMethod,
    Aperture,
    Auto,
    Hard,
    Layered,
    Soft,
    Supersample,
    as_method,
    coc_filter,
)
from ._filters.common import check_max_radius, is_concrete
from ._holes import depth_holes, filled
from ._lens import ThinLens, _check_depth, _error_if_invalid, coc_radius
from ._scene import OCCLUSION_METHOD, scene_treatment


logger = logging.getLogger("jaxdof")


def render(
    image: ImageLike,
    depth: DepthLike,
    lens: ThinLens,
    *,
    method: str | AbstractMethod = "soft",
    max_radius: float | None = None,
    normalize: bool = False,
    footprint: bool | None = None,
    downsample: int = 1,
    band_rows: int | None = None,
    fill_holes: bool = False,
) -> Image:
    r"""Render the depth of field of `lens` from an all-in-focus image and its depth map.

    `coc_filter(image, coc_radius(depth, lens), ...)`: see those two for the optics and the filter.

    **Arguments:**

    - `image`: all-in-focus linear-light image, `(H, W)` or `(H, W, C)`.
    - `depth`: z-depth along the optical axis (m), `(H, W)`, `> lens.focal_length`; `inf` allowed.
    - `lens`: the `ThinLens`.
    - `method`: a method object (`jaxdof.Soft()`, `jaxdof.Aperture(pattern="ring")`, a subclass
      of `jaxdof.AbstractMethod` of your own) or a built-in's name, as in `coc_filter`. A method
      that reads depth (`method.uses_depth`: `jaxdof.Occlusion`, opt-in) gets `depth` from
      `render` itself. `"auto"` (`jaxdof.Auto()`) models what the scene needs, by the rules
      `jaxdof.fit_lens` uses (`jaxdof.scene_treatment` says what it chose, also logged at INFO on
      the `"jaxdof"` logger): `jaxdof.LocalOcclusion` where depth edges meet circles over half a
      pixel, the footprint correction where the median circle is under 40 px (unless
      `footprint` is given), and otherwise the fastest filter with `soft`'s numbers. It needs a
      concrete depth map and lens: under `jit`/`vmap`/`grad` it renders `soft` (no footprint
      correction unless asked), and with `band_rows` it cannot render occlusion (logged as a
      warning). The default `"soft"` renders exactly what it is asked, the same under `jit` as
      outside it; `jaxdof.fit_lens`'s default call recovers the lens of its photos (the photo
      decides whether the scene's footprint correction and occlusion render stay in the fit).
    - `normalize`: as in `coc_filter`: divide by the same render of an image of ones, so that the
      pixels within a circle of the frame's edge, whose light partly leaves the frame, keep
      their brightness. Which border treatment when: `normalize=True` for a picture whose
      edges should look right. For fitting a lens to a real photo, neither the default (those
      pixels lack the light that reaches them from scene points outside the frame: zeros in
      its place) nor the renormalisation (the light inside the frame, rescaled) is that
      light, so leave the band out of the comparison instead: `jaxdof.fit_lens` does by
      default (`border="auto"`: the `ceil(max_radius)` photo pixels along every edge).
    - `footprint`: the pixel-footprint correction (`None`, the default: off, except with
      `method="auto"`, where the scene decides; `True`/`False` force it): spread
      `footprint_prefilter(image, r)` instead of `image`, so that the blur of every pixel has the
      lens's variance `r^2 / 4`, also for circles under half a pixel, where the plain filter copies
      the pixel, and, for circles under 3 px, the lens's transfer function at high frequencies to
      a least-squares fit (see `jaxdof.footprint_prefilter`; measured against ray tracing in
      `fits/results/raytraced.md` and `fits/results/footprint_order.md`).
    - `downsample`: the image and depth map are `s = downsample` times the photo's resolution in
      each axis (a pixel-shift or higher-resolution capture of the all-in-focus scene; the lens's
      `pixel_pitch` stays the photo's). The scatter runs at that resolution, with circles of
      `s r` input pixels, and its `s x s` blocks are averaged into the photo's pixels: what a
      sensor with `s` times the pitch records. Default 1 (same resolution). Why: a pixel of the
      all-in-focus image is already an average over its area, and a photo's blur of circles of a
      pixel or two depends on detail inside that area, which no filter of the averages can know;
      against ray tracing (`fits/results/raytraced.md`) a 2x input recovers most of it.
    - `max_radius`: window size in the photo's pixels (the lens's `pixel_pitch`). `None` (the
      default) uses the smallest window that covers the largest circle in the scene, which needs
      concrete inputs; under `jit` pass a number.
    - `band_rows`: `None` (the default) filters the whole frame at once. An int `>= 1` renders
      bands of that many photo rows one after another, each from its own rows and a halo of
      `h` input rows on either side (see **Bands** below), and gives the same pixels (bitwise
      for most methods; within a few float roundings where a band orders or fuses its additions
      differently: `Aperture`'s splats, a polygonal `Soft`, the footprint correction with
      `downsample`) in a fraction of the memory: the filter's working memory scales with the
      rows it filters (`jaxdof.internal.estimate_memory`). Concrete inputs only (a loop on the
      host, which frees each band's arrays before the next, and compiles each band shape once),
      and not for a method whose output at a pixel depends on pixels beyond the window
      (`Occlusion`'s depth layers and `Jitter`'s per-pixel pattern choice are drawn over the
      whole frame): `ValueError` for those.

    - `fill_holes`: a depth map with holes (NaN, 0 or negative: no data, as depth sensors leave
      them; `inf` is a depth) is refused with a `ValueError` unless this is `True`, which fills
      each hole with its nearest pixel's depth (`jaxdof.fill_depth_holes`; concrete depth only).
      What the render makes of a hole is a guess; `fit_lens` fills them itself and leaves the
      photo pixels they reach out of the fit.

    **Returns:** the defocused image, `image`'s shape (each spatial axis divided by `downsample`).

    **Invalid inputs** (NaN or negative depth, depth not beyond the focal length, a lens with a
    non-positive field or `focus_distance <= focal_length`): concrete values raise `ValueError`
    before any work. Traced values (under `jit`, `grad`, `vmap`) are checked with
    `equinox.error_if`: the compiled computation raises an error with the same message when it
    runs (`EquinoxRuntimeError` under `equinox.filter_jit`, which also shows where; under
    `jax.jit` JAX re-raises it as its own runtime error), under `vmap` if any batch element is
    invalid, under `grad` in the forward pass. With `EQX_ON_ERROR=nan` the output is NaN (equinox
    makes the checked array NaN); with `off` there is no check, and a NaN radius still poisons
    every output pixel its light reaches. The check is a comparison and a reduction over the
    depth map (one pass; the filter makes one per tap).

    **Bands** (`band_rows`). With the window `R` (photo pixels) and `s = downsample`, the filter
    reads, for an output pixel `p`, only the sources `q` with `|p - q|_inf <= W(sR)` input
    pixels, where `W(x) = ceil(x + 1/2) - 1 <= ceil(x)` is the half-width of the window a disc of
    radius `x` reaches (`Aperture`'s bilinear splats reach one pixel more, and `footprint`'s
    stencils read `FOOTPRINT_REACH = 2` more). So the photo rows `[a, b)`, input rows `[sa, sb)`, are
    exactly the rows `[sa - lo, sb - lo)` of the render of the input rows `[lo, hi)` with

    $$lo = \max(sa - h, 0),\quad hi = \min(sb + h, H),\quad
      h = s \left\lceil \frac{\lceil sR \rceil + 1 + 2\,[\text{footprint}]}{s} \right\rceil$$

    (`H` the input's height; `h` a multiple of `s` so that the `s x s` blocks stay aligned): every
    source that reaches them is inside, and where the band stops at row 0 or `H` it stops where
    the frame does, so the light that leaves the frame (and, with `normalize`, the flat field's)
    is the same. What a method decides from the whole frame is decided once, on the whole frame:
    the window (`R` from the largest circle when `None`), and `method.prepare` (`Auto`'s choice,
    `Layered`'s levels), whose per-pixel maps are then cut to each band. The bands are
    `band_rows` high, the last one moved up to end at the frame's bottom (it overlaps the one
    before it), so that at most two band shapes are compiled.
    """
    s = _check_downsample(downsample, np.shape(image))
    method = as_method(method)
    rows = _check_band_rows(band_rows)
    # circles and window in the input's pixels, s times smaller than the photo's
    window = None if max_radius is None else max_radius * s
    bands = rows is not None and rows * s < np.shape(image)[0]
    if bands:  # kept as they are (a numpy array stays on the host): each band is converted alone
        image, depth = (x if isinstance(x, jax.Array) else np.asarray(x) for x in (image, depth))
    else:
        image, depth = jnp.asarray(image), jnp.asarray(depth)
    depth = _holes_filled(depth, fill_holes)
    _check_inputs(image, depth, lens)
    method, footprint = _scene_choice(method, depth, lens, s, footprint, bands)
    options = dict(method=method, normalize=normalize, footprint=footprint, s=s)
    if bands:
        assert rows is not None
        return _render_bands(image, depth, lens, rows, window=window, **options)
    image, depth = jnp.asarray(image), jnp.asarray(depth)  # already arrays (for the types)
    radius = _checked_circles(image, depth, lens, s)
    return _filter(image, depth, radius, window=window, **options)


def _holes_filled(depth, fill_holes: bool):
    """The depth map with its holes filled (`fill_holes`), or a `ValueError` naming the option
    when it has holes and that was not asked; traced depth as it is."""
    if not is_concrete(depth) or np.ndim(depth) != 2:
        return depth
    holes = depth_holes(depth)
    if not holes.any():
        return depth
    if not fill_holes:
        raise ValueError(
            f"depth has {int(holes.sum())} holes (NaN, 0 or negative: no data); pass "
            "fill_holes=True to fill each from its nearest pixel (jaxdof render --fill-holes)"
        )
    out = filled(np.asarray(depth), holes)
    return out if isinstance(depth, np.ndarray) else jnp.asarray(out)


def _scene_choice(method, depth, lens: ThinLens, s: int, footprint, bands: bool):
    """`(method, footprint)` to render with. `Auto` on a concrete depth map and lens: the scene's
    treatment (`jaxdof.scene_treatment`, `fit_lens`'s rules), logged; otherwise the method as
    given and the footprint correction as asked (`None`: off)."""
    if not isinstance(method, Auto) or not is_concrete(depth, lens):
        return method, bool(footprint)
    treatment = scene_treatment(depth, lens, downsample=s, footprint=footprint)
    occlusion = treatment.occlusion and not bands
    words = _treatment_words(treatment, occlusion)
    if treatment.occlusion and bands:  # LocalOcclusion reads depth beyond the band's halo
        words += f"; not occlusion ({treatment.edge_pixels} edge pixels), which bands cannot render"
        logger.warning(
            "render(method='auto', band_rows=...): the scene's depth edges call for occlusion "
            "(%d edge pixels), which bands cannot render; rendered without it",
            treatment.edge_pixels,
        )
    # `treatment`: the words, for a caller's handler (the CLI prints them)
    logger.info("render(method='auto'): %s", words, extra={"treatment": words})
    return (as_method(OCCLUSION_METHOD) if occlusion else method), treatment.footprint


def _treatment_words(treatment, occlusion: bool) -> str:
    words = [f"occlusion ({treatment.edge_pixels} edge pixels)"] if occlusion else []
    words += ["footprint"] if treatment.footprint else []
    return ", ".join(words) or "plain (no depth edge that matters, large circles)"


def _check_inputs(image, depth, lens: ThinLens) -> None:
    """`render`'s checks of the depth map: its shape and type, and (concrete) its values."""
    if depth.shape != image.shape[:2]:
        raise ValueError(
            f"depth must have the image's (H, W) = {image.shape[:2]}, got {depth.shape}"
        )
    if not jnp.issubdtype(depth.dtype, jnp.floating):
        raise ValueError(f"depth must be floating point (metres), got dtype {depth.dtype}")
    _check_depth(jnp.asarray(depth), lens)  # concrete: ValueError now


def _circles(image: Array, depth: Array, lens: ThinLens, s: int) -> Array:
    """The circle of every input pixel, in input pixels (`s` per photo pixel)."""
    radius = coc_radius(depth, lens).astype(jnp.result_type(image.dtype, depth.dtype))
    return radius * s if s > 1 else radius


@functools.partial(jax.jit, static_argnums=3)
def _checked_circles(image: Array, depth: Array, lens: ThinLens, s: int) -> Array:
    """`_circles` after `_error_if_invalid`, one compiled program: eager, their two dozen
    array operations would each compile on a process's first call (a second or more)."""
    return _circles(image, _error_if_invalid(depth, lens), lens, s)


def _filter(image, depth, radius, *, method, window, normalize, footprint, s) -> Array:
    """`render` after the circles (input pixels): the footprint correction, `coc_filter` and the
    `s x s` block means. `window`: the window in input pixels (`None`: the largest circle)."""
    if footprint:  # corrected for the radius the filter spreads (clamped to the window)
        r = radius if window is None else jnp.minimum(radius, window)
        image = footprint_prefilter(image, r)
    out = coc_filter(
        image,
        radius,
        method=method,
        max_radius=window,
        normalize=normalize,
        depth=depth if method.uses_depth else None,
    )
    return box_downsample(out, s)


# one band shape, one compilation: `coc_filter`'s kernels otherwise build their loops anew on
# every eager call (their compilation costs about as much as a megapixel band's filtering)
_filter_jit = eqx.filter_jit(_filter)


def _check_band_rows(band_rows) -> int | None:
    """`band_rows` as an int `>= 1`, or `None`."""
    if band_rows is None:
        return None
    if isinstance(band_rows, bool) or not isinstance(band_rows, (int, np.integer)):
        raise ValueError(f"band_rows must be None or a Python int >= 1, got {band_rows!r}")
    if band_rows < 1:
        raise ValueError(f"band_rows must be >= 1 (photo rows per band), got {band_rows}")
    return int(band_rows)


def band_halo(window: float, *, downsample: int = 1, footprint: bool = False) -> int:
    """The halo `h` (input rows) above and below a band that makes it exact (`render`'s
    **Bands**): `ceil(s R) + 1` (+2 with `footprint`, `FOOTPRINT_REACH`), rounded up to a multiple of `s`.

    - `window`: the filter window `R` in photo pixels (`max_radius`, or the largest circle).
    """
    s = int(downsample)
    reach = math.ceil(s * float(window)) + 1 + FOOTPRINT_REACH * bool(footprint)
    return s * math.ceil(reach / s)


def band_starts(photo_rows: int, band_rows: int) -> list[int]:
    """The first photo row of each band: every `band_rows`, the last band moved up to end at
    `photo_rows` (one band when it covers the frame)."""
    if band_rows >= photo_rows:
        return [0]
    return [*range(0, photo_rows - band_rows, band_rows), photo_rows - band_rows]


def _render_bands(image, depth, lens: ThinLens, rows: int, *, method, window, s, **options):
    """`_filter` band by band (`render`'s **Bands**): the same pixels.

    Nothing of the frame's size is made beyond the output and, for a method that prepares on the
    radius map (`Auto`, `Layered`), that map: each band's circles are computed on the band (the
    same numbers, elementwise), and a first pass over the bands finds the largest circle."""
    if not is_concrete(image, depth, lens):
        raise ValueError(
            "band_rows needs concrete inputs (the bands are a loop on the host); under "
            "jit/vmap/grad render the whole frame (band_rows=None)"
        )
    if _needs_whole_frame(method):
        raise ValueError(
            f"method {type(method).__name__}() reads the depth map or decides from the whole frame "
            "(depth layers, per-pixel random patterns), which bands do not support: render the "
            "whole frame (band_rows=None), or reduce the frame (downsample, a crop)"
        )
    h_in = image.shape[0]

    def circles(lo: int, hi: int) -> Array:
        return _checked_circles(jnp.asarray(image[lo:hi]), jnp.asarray(depth[lo:hi]), lens, s)

    # The whole frame's window and method choices, as coc_filter makes them on the whole frame.
    prepares = type(method).prepare is not AbstractMethod.prepare
    r_full = np.empty(image.shape[:2], np.dtype(circles(0, 1).dtype)) if prepares else None
    if window is None or prepares:
        largest = 0.0
        for lo in range(0, h_in, rows * s):
            r = np.asarray(circles(lo, min(lo + rows * s, h_in)))
            largest = max(largest, float(np.max(r)))
            if r_full is not None:
                r_full[lo : lo + r.shape[0]] = r
        window = largest if window is None else window
    window = check_max_radius(window, None)
    prepared = method if r_full is None else method.prepare(np.minimum(r_full, window), window)
    halo = band_halo(window / s, downsample=s, footprint=options["footprint"])
    photo_rows = h_in // s
    # Compiled once per band shape; a method prepared into numpy maps (`Layered`'s levels: its
    # kernels' compile-time constants, which a compiled band would trace) runs eagerly.
    host = any(isinstance(x, np.ndarray) for x in jax.tree_util.tree_leaves(prepared))
    filt = _filter if host else _filter_jit
    out = None
    starts = band_starts(photo_rows, rows)
    for k, a in enumerate(starts):
        b = min(a + rows, photo_rows)
        lo, hi = max(s * a - halo, 0), min(s * b + halo, h_in)
        part = filt(
            jnp.asarray(image[lo:hi]),
            jnp.asarray(depth[lo:hi]),
            circles(lo, hi) if r_full is None else jnp.asarray(r_full[lo:hi]),
            method=_Prepared(_cut_rows(prepared, image.shape, lo, hi)),
            window=window,
            s=s,
            **options,
        )
        part = part[(s * a - lo) // s : (s * b - lo) // s]
        if out is None:
            out = jnp.zeros((photo_rows, *part.shape[1:]), part.dtype)
        out = _put_rows(out, part, jnp.int32(a))
        del part  # this band's arrays go before the next band's are made
        # for a progress display (the `jaxdof` CLI's): `record.band` is `(done, of)`
        logger.debug(
            "render: band %d of %d done", k + 1, len(starts), extra={"band": (k + 1, len(starts))}
        )
    assert out is not None
    return out


@functools.partial(jax.jit, donate_argnums=0)
def _put_rows(out: Array, part: Array, row: Array) -> Array:
    """`out` with `part` written from row `row` on, in place (`out`'s buffer is donated: the
    frame's output exists once, not once more per band or as a copy of a host array)."""
    return lax.dynamic_update_slice(out, part, (row,) + (jnp.zeros_like(row),) * (out.ndim - 1))


def estimate_memory(
    shape: tuple[int, ...],
    max_radius: float,
    method: str | AbstractMethod = "soft",
    *,
    downsample: int = 1,
    normalize: bool = False,
    footprint: bool = False,
    band_rows: int | None = None,
    dtype=np.float32,
) -> int:
    r"""Bytes `jaxdof.render` needs on top of its inputs, estimated from measured bytes per pixel.

    **Arguments:**

    - `shape`: the image's shape, `(H, W)` or `(H, W, C)` (input pixels).
    - `max_radius`: the window (photo pixels): the largest circle, or `render`'s `max_radius`.
    - `method`, `downsample`, `normalize`, `footprint`: as in `render`.
    - `band_rows`: as in `render`: `None` for the whole frame, else one band of that many photo
      rows with its halo (`band_halo`), and what a banded render holds of the whole frame.
    - `dtype`: the arrays' float type (`float32` unless x64 is on: twice the bytes for float64).

    **Returns:** bytes, about

    $$F + \frac{q}{4} \left( n \left(b_{\text{method}} + c\,(C - 3) + u\,[\text{normalize}] +
      f\,[\text{footprint}]\right) \right)$$

    for the whole frame, with `n = H W` input pixels, `C` channels, `q` the dtype's bytes and the
    constants `F` (`fixed`), `b`, `c`, `u`, `f` of `jaxdof.internal.tuning.RENDER_MEMORY`
    (measured peak resident memory of renders at 1.5, 6 and 24 MP, with their provenance). In
    bands, `F` is `band_fixed`, `n` one band's input rows with their halo (`band_halo`) times
    `W`, scaled by the kind's `band_scale` (a compiled band needs less than the eager whole
    frame), plus `band_frame` per pixel of the whole frame (the output) and, for a method that
    prepares on the whole frame's circles, that map. For planning (the `jaxdof` CLI picks its
    band height from it): the constants are rounded up from the measurements, so measured peaks
    were below it (0.8-0.9 of it).
    """
    table = _tuning.RENDER_MEMORY
    s = _check_downsample(downsample, tuple(shape))
    h, w = shape[:2]
    channels = shape[2] if len(shape) > 2 else 1
    rows = _check_band_rows(band_rows)
    window = s * float(max_radius)
    kind = _memory_kind(as_method(method), window)
    per_pixel = (
        table["per_pixel"][kind]
        + table["per_channel"] * (channels - 3)
        + table["normalize"] * bool(normalize)
        + table["footprint"] * bool(footprint)
    )
    scale = np.dtype(dtype).itemsize / 4
    frame = h * w
    if rows is None or rows * s >= h:
        return int(table["fixed"] + scale * per_pixel * frame)
    band = min(s * rows + 2 * band_halo(float(max_radius), downsample=s, footprint=footprint), h)
    prepares = type(as_method(method)).prepare is not AbstractMethod.prepare
    held = table["band_frame"] + 4 * prepares  # the output, and the radius map to prepare on
    work = table["band_scale"].get(kind, table["band_scale"]["other"]) * per_pixel * band * w
    return int(table["band_fixed"] + scale * (work + held * frame))


def _memory_kind(method: AbstractMethod, window: float) -> str:
    """`RENDER_MEMORY`'s row for `method` with a window of `window` input pixels."""
    if isinstance(method, Soft):
        if method.blades is not None:
            return "soft_polygon"
        return "soft_spans" if window >= _tuning.SPANS_MIN_RADIUS else "soft"
    # the measured rows of the built-in methods; a method of your own gets the largest ("other")
    kinds = {
        Hard: "hard",
        Supersample: "supersample",
        Aperture: "aperture",
        Layered: "layered",
        Auto: "auto",
    }
    return next((kind for cls, kind in kinds.items() if isinstance(method, cls)), "other")


def _needs_whole_frame(method: str | AbstractMethod) -> bool:
    """Whether `method` decides from the whole frame, so that bands would change its pixels:
    one that is not `local` (`Jitter`) or reads depth (`Occlusion`: its depth layers are cut at
    the largest depth gaps of all pixels); see `AbstractMethod`."""
    method = as_method(method)
    return method.uses_depth or not method.local


def _cut_rows(method: AbstractMethod, shape: tuple[int, ...], lo: int, hi: int):
    """`method` with every per-pixel array leaf (leading axes the frame's `(H, W)`, e.g.
    `Layered`'s level assignment) cut to the rows `[lo, hi)`; other leaves as they are."""

    def cut(x):
        return x[lo:hi] if np.shape(x)[:2] == tuple(shape[:2]) else x

    return jax.tree_util.tree_map(cut, method)


@final
class _Prepared(AbstractMethod):
    """A method prepared on the whole frame, run on one band of it: `coc_filter` calls `prepare`
    again on the band's radius map, which must not redo the whole frame's choices."""

    inner: AbstractMethod

    differentiable_in_radius: ClassVar[bool] = False  # concrete inputs only (`_render_bands`)

    def prepare(self, radius: np.ndarray, max_radius: float) -> AbstractMethod:
        del radius, max_radius
        return self

    def spread(self, image, radius, *, max_radius, depth):
        return self.inner(image, radius, max_radius=max_radius, depth=depth)


def _check_downsample(downsample, shape: tuple[int, ...]) -> int:
    """`downsample` as an int, checked against the input's `(H, W, ...)` shape."""
    if isinstance(downsample, bool) or not isinstance(downsample, (int, np.integer)):
        raise ValueError(f"downsample must be a Python int >= 1, got {downsample!r}")
    s = int(downsample)
    if s < 1:
        raise ValueError(f"downsample must be >= 1, got {s}")
    h, w = (tuple(shape) + (0, 0))[:2]  # fewer than 2 axes: refused by the callers' own checks
    if h % s or w % s:
        raise ValueError(
            f"downsample={s} needs an image whose height and width are multiples of {s}, got "
            f"{h} x {w}; crop it to {h - h % s} x {w - w % s}"
        )
    return s


def box_downsample(x: Array, s: int) -> Array:
    """Means of the `s x s` blocks of `x` `(s h, s w, ...)` -> `(h, w, ...)`: a sensor with `s`
    times the pitch (linear light). `s = 1` returns `x`."""
    if s == 1:
        return x
    h, w = x.shape[0] // s, x.shape[1] // s
    return x.reshape(h, s, w, s, *x.shape[2:]).mean(axis=(1, 3))
