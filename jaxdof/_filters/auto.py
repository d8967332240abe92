"""`Auto`: model only what the scene needs, chosen from the concrete radius map (see `Auto`)."""

from __future__ import annotations

import logging
from typing import ClassVar, final

import numpy as np

from .. import _tuning
from .base import AbstractMethod
from .common import is_concrete, tap_offsets
from .layered import Layered
from .soft_method import Soft
from .tabulated import Tabulated, radius_levels


logger = logging.getLogger("jaxdof")


def max_layers(max_radius: float) -> int:
    """Largest number of levels for which FFT layers beat the tabulated gather at `max_radius`."""
    taps = len(tap_offsets(max_radius))
    return int(min(_tuning.MAX_LAYERS, taps // _tuning.LAYER_COST_IN_TAPS))


def distinct_levels(radius) -> int:
    """Number of distinct radii in a concrete map, all radii `<= 1/2` counted as one."""
    r = np.asarray(radius)
    return int(np.unique(np.where(r <= 0.5, 0, r)).size)


def choose_method(radius, *, max_radius: float | None = None) -> str:
    """What `Auto()` does with this radius map.

    **Arguments:**

    - `radius`: concrete circle-of-confusion radii `(H, W)`, pixels (already clamped to
      `max_radius` if one is used).
    - `max_radius`: the window in pixels; `None` takes the map's maximum.

    **Returns:** `"convolution"` (one level, one FFT convolution), `"layered"` (FFT layers, one per
    distinct radius), `"tabulated"` (the gather with looked-up weights) or `"soft"`; `"soft"` for a
    traced map.
    """
    if not is_concrete(radius):
        return "soft"
    r = np.asarray(radius)
    if max_radius is None:
        max_radius = float(r.max()) if r.size else 0.0
    n = distinct_levels(np.minimum(r, max_radius))
    blurred = n - bool(np.any(r <= 0.5))  # the identity level is copied, not convolved
    if blurred <= max_layers(max_radius):
        return "convolution" if n == 1 else "layered"
    return "tabulated" if n <= max(1.0, r.size * _tuning.TABLE_LEVELS_PER_PIXEL) else "soft"


@final
class Auto(AbstractMethod):
    r"""Model only what the scene needs, chosen from the concrete radius map: `Soft`'s numbers.

    Let `L` be the number of distinct radii (all radii `<= 1/2` count as one level, the identity)
    and `T` the number of taps of the window. Every choice gives the soft filter's result (to float
    rounding), so `Auto` is a speed choice, never an accuracy one:

    - **layered** (FFT, `Layered`): one convolution per level with the soft disc kernel, one FFT
      per level that blurs (the level of radii `<= 1/2` is copied) whatever the radius; chosen when
      those levels number at most `T / LAYER_COST_IN_TAPS`, i.e. few levels and a large window.
      With `L = 1` this is a single convolution (reported as `"convolution"`).
    - **tabulated**: the soft gather with the `L` distinct weights per offset computed once and
      looked up (`jaxdof/_filters/tabulated.py`), the cost of a gather with constant weights;
      chosen otherwise while the table is small against the image (`L <= H W / 8`).
    - **soft** (`Soft`): the gather computing each weight (smoothly varying depth: every pixel its
      own radius).

    The choice needs concrete radii (`Auto.prepare`, called by `jaxdof.coc_filter` on a concrete
    map): under `jit`/`vmap`/`grad` with a traced radius map `Auto` falls back to `Soft`
    (documented, not an error, so that `render(..., method=Auto())` can sit inside a traced fit).
    The choice is logged at INFO level on the `"jaxdof"` logger and returned by
    `jaxdof.choose_method`. No options; `differentiable_in_radius = True` (a traced radius map
    makes it `Soft`).
    """

    differentiable_in_radius: ClassVar[bool] = True

    def prepare(self, radius: np.ndarray, max_radius: float) -> AbstractMethod:
        """The method `choose_method` picks for this concrete map, itself prepared."""
        choice = choose_method(radius, max_radius=max_radius)
        logger.info("coc_filter(method=Auto()) chose %r", choice)
        if choice == "soft":
            return Soft()
        if choice == "tabulated":
            levels, index = radius_levels(radius)
            return Tabulated(levels=levels, index=index)
        layers = 1 if choice == "convolution" else distinct_levels(radius)
        return Layered(layers=layers).prepare(radius, max_radius)

    def spread(self, image, radius, *, max_radius, depth):
        """A traced radius map (`prepare` was not called): the documented fallback to `Soft`."""
        logger.info("coc_filter(method=Auto()): the radius map is traced, using Soft()")
        return Soft()(image, radius, max_radius=max_radius)
