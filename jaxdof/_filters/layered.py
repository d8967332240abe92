r"""`Layered`: one soft disc kernel per radius level (the model is in its docstring).

The convolutions run in one of two ways, chosen by cost (`direct_is_cheaper`; `path=` forces one):

- **FFT**, for large windows: on a frame padded by the window's half-width `W` (a tap that wraps
  around either end lands in the zeros), rounded up to a 5-smooth length: `L` forward FFTs of the
  masked image, one product per level, the sum, one inverse FFT. Cost `O(L H W log(H W))`,
  independent of the radius except through the padding.
- **direct**, for small windows: the same sum as a gather over the `T` taps, each source pixel's
  weight looked up from the `(T, L)` table of its level's disc weights (`tabulated.py`, the soft
  filter's own weights). Cost `O(T H W)` with a look-up that grows with `L`.

On a concrete radius map `Layered.prepare` assigns the levels in numpy once (`assign_numpy`,
`level_radii`, `sharp_first_level`), so that neither the level search nor the kernels' spectra
enter the compiled graph; a traced map is assigned inside it (`assign_levels`).
"""

from __future__ import annotations

import math
from typing import ClassVar, final

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float, Int

from .. import _tuning
from .._custom_types import Radius
from .._overlap import circle_pixel_overlap
from .base import AbstractMethod
from .common import ChannelsLast, check_int, level_index, tap_offsets, window_half_width
from .tabulated import tabulated_filter


def assign_levels(
    radius: Radius, layers: int, assignment: np.ndarray | None = None
) -> tuple[Array, Array]:
    """Level index `(H, W)` int32 and level radius `(L,)` for each of `layers` levels.

    Exact levels when the (in-focus-merged) map has at most `layers` distinct values, else equal
    bins over its range. The level radius is the mean of its pixels' radii (differentiable); empty
    levels get radius 0. `assignment`: the index map already computed in numpy by
    `assign_numpy` from a concrete map (then no search for the levels enters the compiled graph).
    """
    r = jnp.where(radius <= 0.5, 0, radius)  # all of these are the identity: one level
    if assignment is not None:
        idx = jnp.asarray(assignment, jnp.int32)
        # counted in numpy: a segment sum over a constant map would be constant-folded by XLA,
        # which takes seconds on a megapixel
        counts = jnp.asarray(np.bincount(assignment.reshape(-1), minlength=layers), r.dtype)
    else:
        idx = _assign_traced(lax.stop_gradient(r), layers)
        counts = jax.ops.segment_sum(jnp.ones_like(r).reshape(-1), idx.reshape(-1), layers)
    # The mean as (a pixel's radius) + mean(deviation from it): a float32 sum of ~1e5 equal radii
    # drifts by ~1e-4 relative, which moved a 6 px disc enough to err by 1.5e-4 of the image;
    # the deviations of an exact level are exactly zero. Same value and derivative (1/count each).
    flat_idx = idx.reshape(-1)
    ref = lax.stop_gradient(jax.ops.segment_max(r.reshape(-1), flat_idx, num_segments=layers))
    ref = jnp.where(counts > 0, ref, 0)
    dev = jax.ops.segment_sum((r - ref[idx]).reshape(-1), flat_idx, num_segments=layers)
    levels = ref + dev / jnp.where(counts > 0, counts, 1)
    return idx, levels


def assign_numpy(radius: np.ndarray, layers: int) -> np.ndarray:
    """`assign_levels`' index map for a concrete radius map, in numpy."""
    r = np.where(radius <= 0.5, 0, radius)
    uniq = np.unique(r)
    if uniq.size <= layers:  # exact levels (the index map only here: binning needs none)
        return level_index(r, uniq)
    sharp = uniq[0] == 0 and layers > 1  # the identity keeps level 0 to itself
    lo, hi = (uniq[1] if sharp else uniq[0]), uniq[-1]
    bins = layers - sharp
    span = hi - lo if hi > lo else 1
    idx = np.clip(np.floor((r - lo) / span * bins), 0, bins - 1) + sharp
    return np.where(sharp & (r == 0), 0, idx).astype(np.int32)


def _assign_traced(r: Array, layers: int) -> Array:
    # The first `layers` distinct values in increasing order, each the smallest value above the one
    # before (the maximum once they run out): `layers` reductions over the map instead of a sort,
    # which on CPU cost ~15x the FFTs of the whole filter (256^2: 14 ms of 21).
    lo, hi = jnp.min(r), jnp.max(r)

    def next_value(prev, _):
        value = jnp.min(jnp.where(r > prev, r, hi))
        return value, value

    _, rest = lax.scan(next_value, lo, None, length=layers - 1)
    uniq = jnp.concatenate([lo[None], rest])
    exact = uniq[-1] >= hi  # at most `layers` distinct values
    exact_idx = jnp.sum(r[..., None] > uniq[None, None], axis=-1)  # position among the levels
    # binned: radii <= 1/2 (now 0) keep level 0 when present, the rest share the other levels
    sharp = (lo == 0) & (layers > 1)
    lo = jnp.where(sharp, uniq[min(1, layers - 1)], lo)  # the smallest radius above 1/2
    shift = sharp.astype(r.dtype)
    bins = layers - shift
    span = jnp.where(hi > lo, hi - lo, 1)
    bin_idx = jnp.clip(jnp.floor((r - lo) / span * bins), 0, bins - 1) + shift
    bin_idx = jnp.where(sharp & (r == 0), 0, bin_idx).astype(exact_idx.dtype)
    return jnp.where(exact, exact_idx, bin_idx).astype(jnp.int32)


def disc_kernels(levels: Float[Array, " l"], half_width: int) -> Float[Array, "l k k"]:
    """Soft disc kernels `(L, 2W+1, 2W+1)`, the same weights as the soft filter's taps."""
    o = jnp.arange(-half_width, half_width + 1, dtype=levels.dtype)
    oy, ox = o[None, :, None], o[None, None, :]
    rho = levels[:, None, None]
    big = rho > 0.5
    rs = jnp.where(big, rho, 1)
    area = circle_pixel_overlap(ox + 0 * oy, oy + 0 * ox, rs + 0 * ox + 0 * oy)
    delta = ((oy == 0) & (ox == 0)).astype(levels.dtype)
    return jnp.where(big, area / (math.pi * rs * rs), delta)


def direct_is_cheaper(max_radius: float, layers: int, n_conv: int) -> bool:
    """Whether the direct sum (`layers` table levels) beats `n_conv` FFT levels at `max_radius`."""
    taps = len(tap_offsets(max_radius))
    return taps * (1 + layers / 5) < _tuning.FFT_LEVEL_COST_IN_TAPS * n_conv


def fft_length(n: int) -> int:
    """The smallest `m >= n` whose prime factors are 2, 3 and 5 (fast FFT lengths)."""
    m = n
    while True:
        k = m
        for p in (2, 3, 5):
            while k % p == 0:
                k //= p
        if k == 1:
            return m
        m += 1


def layered_filter(
    image: ChannelsLast,
    radius: Radius,
    *,
    max_radius: float,
    layers: int,
    assignment: np.ndarray | None = None,
    sharp_level: bool = False,
    static_levels: np.ndarray | None = None,
    path: str = "auto",
) -> ChannelsLast:
    """Sum over `layers` radius levels of (masked image) * (soft disc kernel).

    By FFT or by the direct sum, whichever `direct_is_cheaper` says (`path="fft"` / `"direct"`
    forces one; the result is the same to rounding).

    `sharp_level=True` (known from a concrete map, see `sharp_first_level`): level 0 holds only
    radii `<= 1/2`, whose kernel is the identity, so its pixels are copied instead of convolved:
    one FFT layer fewer. `static_levels` (with `assignment`, from `level_radii` on a concrete map):
    the levels' radii, so that the kernels' spectra are built once, at compile time.
    """
    if path not in ("auto", "fft", "direct"):
        raise ValueError(f"path must be 'auto', 'fft' or 'direct', got {path!r}")
    first = int(sharp_level)  # the first level that needs a convolution
    n_conv = layers - first
    if static_levels is None:
        idx, levels = assign_levels(radius, layers, assignment)
    else:  # a concrete map: index and radii known in numpy (no radius gradient to keep)
        idx, levels = jnp.asarray(assignment, jnp.int32), static_levels
    if path == "direct" or (path == "auto" and direct_is_cheaper(max_radius, layers, n_conv)):
        # the same sum, each level's disc weights looked up per tap (the soft gather's weights)
        return tabulated_filter(image, max_radius=max_radius, levels=levels, index=idx)

    h, w, c = image.shape
    dtype = image.dtype
    half = window_half_width(max_radius)
    # `W` zeros past the image suffice: a tap wrapping around either end lands in them. At least the
    # kernel's `2W + 1`, rounded up to a 5-smooth FFT length.
    hp, wp = (fft_length(max(n + half, 2 * half + 1)) for n in (h, w))

    def kernel_spectra(levels):
        kernels = disc_kernels(levels[first:], half)  # (L - first, k, k)
        # centred at index 0 with negative offsets wrapped: circular = linear conv on the padding
        kpad = jnp.zeros((n_conv, hp, wp), dtype)
        kpad = kpad.at[:, : 2 * half + 1, : 2 * half + 1].set(kernels)
        return jnp.fft.rfft2(jnp.roll(kpad, (-half, -half), axis=(1, 2)))  # (L, hp, wp//2+1)

    if static_levels is None:
        kf = kernel_spectra(levels)
    else:  # the spectra are compile-time constants
        with jax.ensure_compile_time_eval():
            kf = kernel_spectra(jnp.asarray(levels, dtype))
    chw = jnp.moveaxis(image, -1, 0)  # FFTs over the last two axes run ~2x faster on CPU

    def add_level(acc, level, kf_l):
        layer = chw * (idx == level).astype(dtype)[None]
        return acc + jnp.fft.rfft2(layer, s=(hp, wp)) * kf_l[None]

    acc = jnp.zeros((c, hp, wp // 2 + 1), kf.dtype)
    if n_conv <= _tuning.UNROLL_LEVELS:  # straight-line code: XLA overlaps the levels' FFTs
        for j in range(n_conv):
            acc = add_level(acc, first + j, kf[j])
    else:  # one level's spectrum live at a time
        acc, _ = lax.scan(
            lambda a, xs: (add_level(a, *xs), None),
            acc,
            (jnp.arange(first, layers, dtype=jnp.int32), kf),
        )
    out = jnp.moveaxis(jnp.fft.irfft2(acc, s=(hp, wp)), 0, -1)[:h, :w].astype(dtype)
    if sharp_level:
        out = out + image * (idx == 0).astype(dtype)[..., None]
    return out


def level_radii(radius: np.ndarray, assignment: np.ndarray, layers: int) -> np.ndarray:
    """`assign_levels`' level radii for a concrete map, in float64 numpy: the mean radius of each
    level's pixels (radii `<= 1/2` as 0), 0 for an empty level."""
    r = np.where(radius <= 0.5, 0, radius).astype(np.float64).reshape(-1)
    flat = assignment.reshape(-1)
    counts = np.bincount(flat, minlength=layers)
    sums = np.bincount(flat, weights=r, minlength=layers)
    return np.where(counts > 0, sums / np.maximum(counts, 1), 0.0)


def sharp_first_level(radius: np.ndarray, assignment: np.ndarray) -> bool:
    """True when level 0 of `assignment` is non-empty and holds only radii `<= 1/2` (identity)."""
    in_first = assignment == 0
    return bool(in_first.any() and np.all(radius[in_first] <= 0.5))


@final
class Layered(AbstractMethod):
    r"""Layered convolution: quantise the radius map into `L` levels and blur each by one kernel.

    The scatter of the soft filter is linear in the sources, so splitting the image by radius,

    $$\text{out} = \sum_{l=1}^{L} K_{\rho_l} * (\text{image} \cdot M_l),\qquad
      K_\rho(o) = \frac{|\,\text{disc}(0, \rho) \cap \text{pixel}(o)\,|}{\pi \rho^2},$$

    with masks `M_l` (the pixels assigned to level `l`) and one space-invariant soft disc kernel
    per level, is **the same scatter as `Soft`** whenever every pixel's radius equals its level's
    `rho_l`. With at most `L` distinct radii the levels are those radii and the result equals the
    soft filter everywhere, depth edges included: the scatter formulation has no occlusion, so a
    layer boundary is not special (occlusion-aware compositing is `Occlusion`'s business). Radii
    `<= 1/2` all act as the identity and share one level.

    With more than `L` distinct radii the pixels at radius `<= 1/2` (sharp: the identity) keep a
    level of their own, the range of the others is cut into equal bins for the remaining levels,
    and each bin is blurred with the **mean radius of its pixels**; the error is that of a radius
    off by up to half a bin width, and sharp pixels stay sharp.

    Each level is blurred by FFT in large windows and by a direct sum with the levels' weights
    looked up in small ones, whichever costs less (`jaxdof/_filters/layered.py`); the two agree to
    rounding.

    **Fields:**

    - `layers`: `L`, the number of radius levels, an int in `[1, 256]` (default 8).

    **Gradients:** linear in `image` (exact). In `radius`, the assignment to levels is piecewise
    constant and the gradient flows only through the level means: each pixel receives the average
    derivative of its level. That is exact for a lens fitted to a scene of at most `L` depth planes
    (every pixel of a plane moves together), and an approximation otherwise:
    `differentiable_in_radius = False` (per-pixel radius gradients are not those of the scatter).
    """

    layers: int = eqx.field(static=True)

    differentiable_in_radius: ClassVar[bool] = False

    def __init__(self, *, layers: int = 8):
        self.layers = check_int("layers", layers, 1, 256)

    def prepare(self, radius: np.ndarray, max_radius: float) -> AbstractMethod:
        """Assign the levels of a concrete radius map in numpy (index map, level radii, whether
        level 0 holds only sharp pixels): `_LayeredLevels`, whose kernels are compile-time
        constants."""
        del max_radius
        assignment = assign_numpy(radius, self.layers)
        return _LayeredLevels(
            layers=self.layers,
            assignment=assignment,
            sharp_level=sharp_first_level(radius, assignment),
            static_levels=level_radii(radius, assignment, self.layers),
        )

    def spread(self, image, radius, *, max_radius, depth):
        """The traced radius map: levels searched and averaged inside the computation."""
        return layered_filter(image, radius, max_radius=max_radius, **self._options())


@final
class _LayeredLevels(AbstractMethod):
    """`Layered` prepared on a concrete radius map: its levels, assigned once in numpy.

    `assignment` (`(H, W)` int32) indexes `static_levels` (`(L,)`, pixels; the mean radius of each
    level's pixels, radii `<= 1/2` as 0); `sharp_level`: level 0 holds only radii `<= 1/2` and is
    copied instead of convolved. The fields are `layered_filter`'s options of those names. The
    `radius` passed at the call is not read again (it is the map these were computed from), so
    there is no radius gradient.
    """

    layers: int = eqx.field(static=True)
    assignment: Int[np.ndarray, "h w"]
    sharp_level: bool = eqx.field(static=True)
    static_levels: Float[np.ndarray, " l"]

    differentiable_in_radius: ClassVar[bool] = False

    def spread(self, image, radius, *, max_radius, depth):
        return layered_filter(image, radius, max_radius=max_radius, **self._options())
