"""`Occlusion`: depth-ordered layers, each blurred on its own, composited with `over`."""

from __future__ import annotations

import math
from typing import ClassVar, final

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Bool, Int

from .._custom_types import Depth, DepthLike, Radius
from .base import AbstractMethod
from .common import ChannelsLast, check_bool, check_depth_map, check_int
from .soft import soft_filter


#: Default relative depth gap that separates two layers (as `jaxdof.depth_edges`' default jump).
DEFAULT_JUMP = 0.03


def depth_layers(depth: Depth, layers: int, jump: float = DEFAULT_JUMP) -> Array:
    """Layer index `(H, W)` int32, `0` nearest, cut at the `layers - 1` largest relative depth gaps.

    Sort the log-depths of all pixels; a gap between consecutive values larger than
    `log(1 + jump)` is a candidate boundary; the `layers - 1` largest candidates are used. A
    pixel's layer is the number of used boundaries at or below its log-depth. Works on traced
    depth (a sort and a `top_k`); piecewise constant, so it carries no gradient.
    """
    depth = lax.stop_gradient(depth)
    finite_max = jnp.finfo(depth.dtype).max
    u = jnp.log(jnp.minimum(depth, finite_max)).reshape(-1)  # inf -> the largest float: farthest
    n = u.size
    k = min(layers - 1, n - 1)
    if k <= 0:
        return jnp.zeros(depth.shape, jnp.int32)
    s = jnp.sort(u)
    gaps = s[1:] - s[:-1]
    size, at = lax.top_k(gaps, k)
    used = size > math.log1p(jump)
    # boundary value: the first log-depth beyond the gap; unused ones never count
    bound = jnp.where(used, s[at + 1], jnp.inf)
    idx = jnp.sum(u[:, None] >= bound[None, :], axis=-1)
    return idx.reshape(depth.shape).astype(jnp.int32)


def nearest_seed(seed: Bool[Array, "h w"]) -> tuple[Int[Array, "h w"], Int[Array, "h w"]]:
    """Row and column of (approximately) the nearest `True` pixel of `seed`, for every pixel.

    Jump flooding (G. Rong and T.-S. Tan, "Jump flooding in GPU with applications to Voronoi
    diagram and distance transform", I3D 2006): each pass looks at the 8 neighbours at a step `s`,
    halving `s` from the largest power of two below the image size down to 1, then one more pass at
    1 (the "1+JFA" variant, which removes most of its rare errors). Seeds map to themselves.
    Pixels with no seed anywhere get `-1`.
    """
    h, w = seed.shape
    yy, xx = jnp.meshgrid(
        jnp.arange(h, dtype=jnp.int32), jnp.arange(w, dtype=jnp.int32), indexing="ij"
    )
    none = jnp.full((h, w), -1, jnp.int32)
    by, bx = jnp.where(seed, yy, none), jnp.where(seed, xx, none)
    big = jnp.iinfo(jnp.int32).max
    steps = []
    s = 1 << (max(h, w) - 1).bit_length() - 1 if max(h, w) > 1 else 1
    while s >= 1:
        steps.append(s)
        s //= 2
    steps.append(1)
    pad = steps[0]
    unit = jnp.asarray([(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], jnp.int32)

    def one_pass(carry, s):
        # Every candidate is read from the previous pass's map (one loop body, compiled once: an
        # unrolled chain of shifted selects makes XLA's fusion recompute it and compile for
        # minutes).
        by, bx = carry
        py = jnp.pad(by, pad, constant_values=-1)
        px = jnp.pad(bx, pad, constant_values=-1)

        def candidate(o):
            at = (pad + o[0] * s, pad + o[1] * s)
            cy = lax.dynamic_slice(py, at, (h, w))
            cx = lax.dynamic_slice(px, at, (h, w))
            d = jnp.where(cy >= 0, (cy - yy) ** 2 + (cx - xx) ** 2, big)
            return cy, cx, d

        cy, cx, d = jax.vmap(candidate)(unit)  # (9, h, w); the centre (0, 0) keeps the current
        k = jnp.argmin(d, axis=0)[None]
        pick = lambda a: jnp.take_along_axis(a, k, axis=0)[0]
        return (pick(cy), pick(cx)), None

    (by, bx), _ = lax.scan(one_pass, (by, bx), jnp.asarray(steps, jnp.int32))
    return by, bx


def _layer_sources(image, radius, layer, layers: int, fill: bool):
    """Per layer: mask `(L, H, W)`, colour `(L, H, W, C)`, radius `(L, H, W)` of its sources."""
    ids = jnp.arange(layers, dtype=jnp.int32)
    if not fill:
        masks = (layer[None] == ids[:, None, None]).astype(image.dtype)
        return masks, None, None
    h, w, c = image.shape
    flat_img, flat_r, flat_l = image.reshape(h * w, c), radius.reshape(-1), layer.reshape(-1)

    def one(k):
        by, bx = nearest_seed(layer >= k)  # layer k and every farther one
        found = by >= 0
        at = jnp.where(found, by * w + bx, 0).reshape(-1)
        mask = (found.reshape(-1) & (flat_l[at] == k)).astype(image.dtype)
        return mask.reshape(h, w), flat_img[at].reshape(h, w, c), flat_r[at].reshape(h, w)

    return jax.vmap(one)(ids)


def occlusion_filter(
    image: ChannelsLast,
    radius: Radius,
    *,
    max_radius: float,
    depth: DepthLike | None,
    layers: int,
    fill: bool,
    jump: float = DEFAULT_JUMP,
) -> ChannelsLast:
    """Depth-ordered layered soft scatter, composited back to front (see the module docstring)."""
    h, w, c = image.shape
    if depth is None or layers == 1:
        # no depth order known (or asked for): one layer, which is exactly the soft scatter
        return soft_filter(image, radius, max_radius=max_radius)
    depth = check_depth_map(depth, (h, w)).astype(image.dtype)
    layer = depth_layers(depth, layers, jump)
    masks, colours, radii = _layer_sources(image, radius, layer, layers, fill)
    if fill:
        assert colours is not None and radii is not None  # what `fill` makes
        stacked = jnp.concatenate([colours * masks[..., None], masks[..., None]], axis=-1)
        blurred = jax.vmap(lambda x, r: soft_filter(x, r, max_radius=max_radius))(stacked, radii)
    else:
        # every layer blurs its own pixels with their own radii: one scatter of L (C + 1) channels
        stacked = jnp.concatenate([image[None] * masks[..., None], masks[..., None]], axis=-1)
        chans = jnp.moveaxis(stacked, 0, 2).reshape(h, w, layers * (c + 1))
        blurred = soft_filter(chans, radius, max_radius=max_radius)
        blurred = jnp.moveaxis(blurred.reshape(h, w, layers, c + 1), 2, 0)
    premult, alpha = blurred[..., :c], blurred[..., c]
    out = jnp.zeros_like(image)
    for k in reversed(range(layers)):  # farthest first
        transmit = jnp.clip(1 - alpha[k], 0, 1)
        out = premult[k] + transmit[..., None] * out
    return out


@final
class Occlusion(AbstractMethod):
    r"""Occlusion-aware scatter: depth-ordered layers, each blurred alone, composited with `over`.

    The layers split at gaps in the *whole image's* depths: where a floor or a receding wall joins
    the near and the far depths there is no gap, and this renders exactly as `Soft`. Occlusion
    decided around each pixel is `LocalOcclusion` (`"local_occlusion"`), which `fit_lens` uses.

    The soft scatter (`Soft`) adds every pixel's disc of light to the output, whatever lies in front
    of it. A real aperture does not: light from a far surface is blocked by a nearer one, and around
    a nearer object's edge the aperture sees background that the all-in-focus (pinhole) image hides.
    This method models both, in the manner of layered bokeh renderers (Kraus & Strengert 2007,
    "Depth-of-Field Rendering by Pyramidal Image Processing", Computer Graphics Forum 26(3); Lee,
    Kim & Choi 2009, "Depth-of-field rendering with multiview synthesis", ACM TOG 28(5)):

    1. **Layers at depth gaps.** The pixels are split into at most `L` layers where the sorted
       log-depths jump by more than `log(1 + jump)` (a relative depth gap of `jump`, default 3%, the
       same threshold as `jaxdof.depth_edges`): the `L - 1` largest such gaps are the boundaries. A
       scene without such a gap (one plane, a slanted plane, any continuous surface) is one layer,
       and the method is then **exactly the soft filter** (the option stays off where there is
       nothing to occlude). Layer `0` is the nearest.
    2. **Hidden background** (`fill=True`). Layer `l` is extended behind every nearer layer: a
       hidden pixel `p` takes the colour and radius of its nearest pixel `q(p)` among the pixels of
       layer `l` *and farther*, and belongs to the extension of layer `l` when that pixel is of
       layer `l`. The nearest pixel is found by jump flooding (Rong & Tan 2006), exact up to rare
       one-pixel mismatches. With `fill=False` each layer holds only its visible pixels.
    3. **Blur each layer** with the soft scatter of its own per-pixel radii, premultiplied colour
       and coverage alike:

       $$P_l = \mathcal{S}_{r_l}[\,m_l\, c_l\,], \qquad \alpha_l = \mathcal{S}_{r_l}[\,m_l\,],$$

       with `S_r` the soft scatter (`jaxdof/_filters/soft.py`), `m_l` the layer's (extended) mask,
       `c_l` and `r_l` the colour and radius of `q(p)` (the pixel itself where it is visible).
    4. **Composite from back to front**,
       `out = P_0 + (1 - alpha_0)(P_1 + (1 - alpha_1)(P_2 + ...))`, with each transmittance
       `1 - alpha` clipped to `[0, 1]` (inside a layer whose radius varies the scattered coverage
       can exceed 1 by a little).

    What the model gets right and wrong: a sharp foreground edge stays sharp in front of a blurred
    background (the plain scatter spreads background light over it); a defocused foreground edge
    becomes partly transparent and shows the (filled) background behind it, as a real aperture sees.
    The filled background is a guess (the nearest visible colour, streaked inwards), so what the
    aperture sees behind an occluder is only approximated; a continuous surface split across two
    layers (only where a >= `jump` gap separates them in depth, i.e. never within a smooth surface)
    would be composited as two objects.

    **Gradients.** Linear in `image` (every step above is a gather, a scatter or a product with
    masks that do not depend on it). In `radius` the per-pixel soft scatter's exact derivative (the
    layers and the nearest-pixel map depend only on `depth`). In `depth` the output is piecewise
    constant (the layering is a discrete choice; `stop_gradient`): through `jaxdof.render` the depth
    still acts through the radius. So a lens can be fitted through it
    (`differentiable_in_radius = True`).

    **Cost.** With `fill=True` one soft scatter of `C + 1` channels per layer (the radius of a
    hidden pixel differs per layer): about `L` times the soft filter. With `fill=False` one scatter
    of `L (C + 1)` channels.

    **Fields:**

    - `layers`: `L`, the most depth layers, an int in `[1, 256]` (default 4). `1` is the soft
      filter.
    - `fill`: extend each layer behind the nearer ones (step 2; default `True`).

    Opt-in: `uses_depth = True`, so `jaxdof.render` passes its depth map; `jaxdof.coc_filter` takes
    it as `depth=` (`(H, W)`, positive z-depth, e.g. metres; without it the frame is one layer, the
    soft filter). Differentiable in `image` and `radius`, not in `depth`.
    """

    layers: int = eqx.field(static=True)
    fill: bool = eqx.field(static=True)

    differentiable_in_radius: ClassVar[bool] = True
    uses_depth: ClassVar[bool] = True

    def __init__(self, *, layers: int = 4, fill: bool = True):
        self.layers = check_int("layers", layers, 1, 256)
        self.fill = check_bool("fill", fill)

    def spread(self, image, radius, *, max_radius, depth):
        return occlusion_filter(
            image, radius, max_radius=max_radius, depth=depth, **self._options()
        )
