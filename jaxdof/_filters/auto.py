r"""`"auto"`: model only what the scene needs, chosen from the concrete radius map.

- one radius everywhere (radii `<= 1/2` count as one level, the identity): **one convolution**
  with the soft disc kernel (the layered filter with `L = 1`);
- a few distinct radii, when `L` FFT layers cost less than the soft gather's taps (see
  `max_layers`): the **layered** filter with exactly those levels, which equals the soft filter;
- otherwise the **soft** gather.

All three give the soft filter's result (to float rounding), so `"auto"` is a speed choice, never an
accuracy one. The choice needs concrete radii: under `jit`/`vmap`/`grad` with a traced radius map
`"auto"` falls back to `"soft"` (documented, not an error, so that `render(..., method="auto")` can
sit inside a traced fit). The choice is logged at INFO level on the `"jaxdof"` logger and returned by
`choose_method`.
"""

from __future__ import annotations

import logging

import numpy as np

from .common import is_concrete, tap_offsets


logger = logging.getLogger("jaxdof")

# Cost of one FFT layer relative to one soft-gather tap over the same image, measured on CPU: at
# 128 x 128 x 3 float32, max radius 8 (201 taps), a layer costs ~12-15 taps; at 32 x 32 x 3
# (fits/tradeoff.py --quick) ~50 taps (8 layers 2.9 ms against soft 1.4 ms), because a small frame
# leaves the per-layer overhead uncovered. The larger figure is used, so that "auto" picks layers
# only where they win on small frames too (on large frames it then gives away some speed).
LAYER_COST_IN_TAPS = 48.0
#: Never more layers than this (memory: the padded spectra are accumulated one level at a time, but
#: the assignment sorts the map once per call).
MAX_LAYERS = 32


def max_layers(max_radius: float) -> int:
    """Largest number of levels for which the layered filter beats the soft gather at `max_radius`."""
    taps = len(tap_offsets(max_radius))
    return int(min(MAX_LAYERS, max(1, taps // LAYER_COST_IN_TAPS)))


def distinct_levels(radius) -> int:
    """Number of distinct radii in a concrete map, all radii `<= 1/2` counted as one."""
    r = np.asarray(radius)
    return int(np.unique(np.where(r <= 0.5, 0, r)).size)


def choose_method(radius, *, max_radius: float | None = None) -> str:
    """What `method="auto"` does with this radius map: `"convolution"`, `"layered"` or `"soft"`.

    **Arguments:**

    - `radius`: concrete circle-of-confusion radii `(H, W)`, pixels (already clamped to
      `max_radius` if one is used).
    - `max_radius`: the window in pixels; `None` takes the map's maximum.

    **Returns:** `"convolution"` (one level: the layered filter with `layers=1`), `"layered"` (with
    `layers=distinct_levels(radius)`), or `"soft"`; `"soft"` for a traced map.
    """
    if not is_concrete(radius):
        return "soft"
    r = np.asarray(radius)
    if max_radius is None:
        max_radius = float(r.max()) if r.size else 0.0
    n = distinct_levels(np.minimum(r, max_radius))
    if n == 1:
        return "convolution"
    return "layered" if n <= max_layers(max_radius) else "soft"
