"""A gather over integer tap offsets whose weight may read per-source and per-output maps.

`soft.gather` passes its weight function only the source radius and the soft filter's own tap
geometry. The sampled methods also need per-source quantities (an energy normaliser) and, for
jittered sampling, per-output-pixel sample positions, so they share this slightly wider loop. Same
structure: a `lax.scan` over offsets with a checkpointed body, so memory stays at a few images in
the forward pass and in reverse mode.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array

from .common import half_width, pad_rows_cols


def _slice_hw(x: Array, start: Array, h: int, w: int) -> Array:
    zero = jnp.zeros((), jnp.int32)
    return lax.dynamic_slice(x, (start[0], start[1]) + (zero,) * (x.ndim - 2), (h, w) + x.shape[2:])


def gather_taps(
    image: Array,
    offsets: np.ndarray,
    weight_fn: Callable[..., Array],
    *,
    per_tap: Sequence[Array] = (),
    source: Sequence[Array] = (),
    output: Sequence[Array] = (),
) -> Array:
    """`out[p] = sum_o image[p - o] * weight_fn(tap_o, source[p - o], output[p])`.

    **Arguments:**

    - `image`: `(H, W, C)`.
    - `offsets`: static integer offsets `(n, 2)` as `(oy, ox)`: output `p` reads source `p - o`.
    - `weight_fn(tap, src, out) -> (H, W)`: `tap` is the tuple of `per_tap[i][k]` for this offset,
      `src` the tuple of `source` maps read at the source pixels, `out` the `output` maps as given.
    - `per_tap`: arrays with leading dimension `n`, scanned alongside the offsets.
    - `source`: maps `(H, W, ...)` read at `p - o` (zero outside the frame).
    - `output`: maps `(H, W, ...)` read at `p`.
    """
    h, w, c = image.shape
    offsets = np.asarray(offsets, np.int32).reshape(-1, 2)
    pad = half_width(offsets)
    pimg = pad_rows_cols(image, pad)
    psrc = tuple(pad_rows_cols(s, pad) for s in source)
    starts = jnp.asarray(pad - offsets, jnp.int32)
    output = tuple(output)

    def body(acc, xs):
        start, tap = xs
        src_img = _slice_hw(pimg, start, h, w)
        src = tuple(_slice_hw(s, start, h, w) for s in psrc)
        wgt = weight_fn(tap, src, output)
        return acc + src_img * wgt[..., None], None

    body = jax.checkpoint(body, prevent_cse=False)
    out, _ = lax.scan(body, jnp.zeros_like(image), (starts, tuple(per_tap)))
    return out
