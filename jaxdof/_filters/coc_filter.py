"""`coc_filter`: the public entry point that checks inputs and dispatches on `method`."""

from __future__ import annotations

import logging
import math
import operator

import jax
import jax.numpy as jnp
import numpy as np

from .._custom_types import DepthLike, Image, ImageLike, RadiusLike
from .aperture import PATTERNS, RANDOM_PATTERNS, aperture_filter
from .auto import choose_method, distinct_levels
from .common import check_image_and_radius, check_max_radius, is_concrete
from .hard import hard_filter
from .jitter import jitter_filter
from .layered import assign_numpy, layered_filter, level_radii, sharp_first_level
from .occlusion import occlusion_filter
from .soft_polygon import soft_polygon_filter
from .spans import exact_soft_filter
from .supersample import supersample_filter
from .tabulated import radius_levels, tabulated_filter


logger = logging.getLogger("jaxdof")

METHODS = ("soft", "hard", "supersample", "jitter", "aperture", "layered", "auto", "occlusion")

#: The keyword knobs each method uses; any other knob given to it is a `ValueError`.
KNOBS: dict[str, tuple[str, ...]] = {
    "soft": ("blades", "rotation"),
    "hard": (),
    "supersample": ("samples", "blades", "rotation"),
    "jitter": ("samples", "key"),
    "aperture": ("samples", "key", "pattern", "blades", "rotation"),
    "layered": ("layers",),
    "auto": (),
    "occlusion": ("layers", "depth", "fill"),
}

#: Defaults of the knobs left at `None`.
DEFAULTS = {
    ("supersample", "samples"): 4,
    ("jitter", "samples"): 16,
    ("aperture", "samples"): 64,
    ("aperture", "pattern"): "stratified",
    ("layered", "layers"): 8,
    ("occlusion", "layers"): 4,
    ("occlusion", "fill"): True,
}

#: Whether `d(out)/d(radius)` is the true derivative of the method's own forward model, so that a
#: lens can be fitted through it. `False`: the output is piecewise constant in the radius
#: (`hard`, `supersample`, `jitter`: zero gradient), or the gradient is shared over a level
#: (`layered`: exact only for scenes of at most `layers` depth planes). `auto` is `True` because a
#: traced radius map makes it use `soft`.
DIFFERENTIABLE_IN_RADIUS: dict[str, bool] = {
    "soft": True,
    "hard": False,
    "supersample": False,
    "jitter": False,
    "aperture": True,
    "layered": False,
    "auto": True,
    "occlusion": True,
}


def _check_int(name: str, value, lo: int, hi: int | None = None) -> int:
    try:
        if isinstance(value, bool):
            raise TypeError
        value = operator.index(value)
    except TypeError:
        raise ValueError(f"{name} must be a Python int, got {value!r}") from None
    if value < lo or (hi is not None and value > hi):
        bound = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise ValueError(f"{name} must be {bound}, got {value}")
    return value


def _check_knobs(method: str, knobs: dict) -> dict:
    given = {k: v for k, v in knobs.items() if v is not None}
    unused = sorted(set(given) - set(KNOBS[method]))
    if unused:
        uses = ", ".join(KNOBS[method]) or "no knobs"
        raise ValueError(
            f"method={method!r} does not use {', '.join(unused)} (it takes {uses}); "
            "remove the argument or pick a method that uses it"
        )
    out = {k: given.get(k, DEFAULTS.get((method, k))) for k in KNOBS[method]}
    if out.get("samples") is not None:
        hi = 64 if method == "supersample" else None  # 64 x 64 = 4096 sub-samples per pixel
        out["samples"] = _check_int("samples", out["samples"], 1, hi)
    if out.get("layers") is not None:
        out["layers"] = _check_int("layers", out["layers"], 1, 256)
    if out.get("blades") is not None:
        out["blades"] = _check_int("blades", out["blades"], 3, 1024)
    if "rotation" in out:
        rot = out["rotation"]
        if rot is None:
            out["rotation"] = 0.0
        else:
            if isinstance(rot, jax.Array) and not is_concrete(rot):
                raise ValueError(
                    "rotation must be a static Python number (radians), not a traced array"
                )
            rot = float(rot)
            if not math.isfinite(rot):
                raise ValueError(f"rotation must be finite (radians), got {rot}")
            if out.get("blades") is None and method != "aperture":
                raise ValueError(
                    f"rotation={rot} has no effect on a circular aperture with method={method!r}; "
                    "pass blades=<int >= 3> for a polygonal diaphragm, or drop rotation"
                )
            out["rotation"] = rot
    if method == "occlusion":
        if not isinstance(out["fill"], bool):
            raise ValueError(f"fill must be a Python bool, got {out['fill']!r}")
    if "pattern" in out and out["pattern"] not in PATTERNS:
        raise ValueError(f"pattern={out['pattern']!r} is not one of {PATTERNS}")
    needs_key = method == "jitter" or (method == "aperture" and out["pattern"] in RANDOM_PATTERNS)
    if "key" in out:
        key = out["key"]
        if needs_key and key is None:
            what = "jitter" if method == "jitter" else f"pattern={out['pattern']!r}"
            raise ValueError(
                f"method={method!r} with {what} draws random samples and needs an explicit "
                "key=jax.random.key(<seed>) (the same key always gives the same image)"
            )
        if key is not None and not needs_key:
            raise ValueError(
                f"pattern={out['pattern']!r} is deterministic and does not use key; drop it or "
                f"use one of the random patterns {RANDOM_PATTERNS}"
            )
        if key is not None:
            out["key"] = _check_key(key)
    return out


def _check_key(key):
    key = jnp.asarray(key) if not isinstance(key, jax.Array) else key
    if jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        if key.shape != ():
            raise ValueError(f"key must be a single PRNG key, got a key array of shape {key.shape}")
        return key
    if key.dtype != jnp.uint32 or key.shape != (2,):
        raise ValueError(
            f"key must be a jax.random key (jax.random.key(seed) or jax.random.PRNGKey(seed)), got "
            f"an array of dtype {key.dtype} and shape {key.shape}"
        )
    return key


def coc_filter(
    image: ImageLike,
    radius: RadiusLike,
    *,
    method: str = "soft",
    max_radius: float | None = None,
    normalize: bool = False,
    samples: int | None = None,
    key=None,
    pattern: str | None = None,
    blades: int | None = None,
    rotation: float | None = None,
    layers: int | None = None,
    depth: DepthLike | None = None,
    fill: bool | None = None,
) -> Image:
    r"""Spread every pixel's light uniformly over its circle of confusion (a scatter, as a gather).

    $$\text{out}[p] = \sum_q \text{image}[q]\; \frac{|\,\text{disc}(q, r_q) \cap \text{pixel}(p)\,|}
      {\pi r_q^2}$$

    over the source pixels `q` whose disc can reach `p` (offsets with `|p - q|_inf <=
    ceil(max_radius)`, corners the disc cannot reach dropped). Each weight is the exact area of the
    output pixel covered by the source's disc (`jaxdof.circle_pixel_overlap`), so the filter is
    antialiased and conserves energy: away from the borders `sum(out) == sum(image)`.

    **Arguments:**

    - `image`: linear-light image, `(H, W)` or `(H, W, C)`, floating point.
    - `radius`: circle-of-confusion radius of each source pixel, `(H, W)`, pixels, `>= 0`.
    - `method`: how the coverage is computed (the seeds' family; see `jaxdof/_filters/<name>.py`):
        - `"soft"`: the exact analytic coverage above, the reference. Below `max_radius = 12`
          (`spans.SPANS_MIN_RADIUS`, the measured crossover) a gather over the window's offsets,
          one weight per mirror class (`soft.py`); from there on the same sum by row spans of fully
          covered pixels plus the analytic boundary pixels, whose cost grows linearly in the radius
          (`spans.py`). Both give the same numbers to rounding.
        - `"hard"`: a pixel belongs to a disc when its centre is inside; normalised by the count
          of covered pixels (energy exact). No gradient in `radius`.
        - `"supersample"`: coverage counted on `samples x samples` sub-pixel points (default 4),
          normalised by the total count (energy exact). No gradient in `radius`.
        - `"jitter"`: coverage estimated from `samples` stratified random points per output pixel
          (default 16; 16 point sets drawn from `key`, one picked at random per pixel); an
          unbiased estimate of `"soft"` (energy exact in expectation). No gradient in `radius`.
        - `"aperture"`: the accumulation buffer: mean of `samples` (default 64) bilinear
          forward splats at `q + u_k r_q` for lens samples `u_k` from `pattern` (`"ring"`,
          `"stratified"` (default), `"jittered"`, `"disc"`, `"weighted_disc"`; the random ones need
          `key`). Differentiable in `radius`.
        - `"layered"`: radii quantised to `layers` levels (default 8), each level blurred by one
          soft disc kernel (by FFT for large windows, by a direct sum with the levels' weights
          looked up for small ones); equal to `"soft"` when the map has at most `layers` distinct
          radii. Gradient in `radius` only through the level means.
        - `"auto"`: what the concrete radius map needs (`choose_method`): FFT layers for a few
          distinct radii and a large window, the soft gather with its weights tabulated per
          distinct radius (`tabulated.py`) for a few hundred levels, the soft filter otherwise;
          always the soft filter's result. Falls back to `"soft"` when the radius map is traced
          (under `jit`/`grad` in `radius`).
        - `"occlusion"` (opt-in): the pixels are split into at most `layers` (default 4) layers
          at relative gaps of more than 3% in `depth` (`(H, W)`, positive z-depth, e.g. metres;
          `jaxdof.render` passes its own; without it the frame is one layer); each layer (with
          `fill=True`, the default, extended behind nearer layers by its nearest visible colour)
          is blurred by the soft scatter and the layers are composited back to front with `over`
          (`jaxdof/_filters/occlusion.py`). Exactly `"soft"` when `depth` has no such gap.
          Differentiable in `image` and `radius`, not in `depth`.

      `supersample` and `jitter` converge to `soft` as `samples -> infinity`: the analytic overlap is
      their limit.
    - `max_radius`: static window size in pixels. Radii above it are clamped to it (their light
      is spread over a disc of radius `max_radius`, and the derivative with respect to the clamped
      radius is 0). `None` takes the largest radius of a concrete `radius` map: the smallest window
      the scene needs. Under `jit` it must be given.
    - `normalize`: divide by the same filter applied to an image of ones, so that pixels near the
      border, which lose light to outside the frame, keep their brightness.
    - `samples`, `key`, `pattern`, `blades`, `rotation`, `layers`, `depth`, `fill`: the methods'
      knobs (keyword only; a knob given to a method that does not use it is a `ValueError`). `blades` (int `>= 3`)
      makes the diaphragm the regular polygon inscribed in the circle of confusion, turned by
      `rotation` radians (for `"soft"`, `"supersample"` and `"aperture"`).

    **Returns:** the filtered image, same shape and dtype as `image`.

    Radii at or below half a pixel leave their pixel untouched (exactly the identity; the
    derivative with respect to such a radius is 0) for every method except `"aperture"` (whose
    bilinear splat of a sub-pixel shift blurs slightly). Linear in `image`; differentiable with
    respect to `radius` where `DIFFERENTIABLE_IN_RADIUS[method]`; `jit` with `max_radius` static;
    `vmap` over a batch.
    """
    if method not in METHODS:
        raise ValueError(f"{method=} is not one of {METHODS}")
    knobs = _check_knobs(
        method,
        dict(
            samples=samples,
            key=key,
            pattern=pattern,
            blades=blades,
            rotation=rotation,
            layers=layers,
            depth=depth,
            fill=fill,
        ),
    )
    # a concrete map is inspected in numpy before anything is staged into a surrounding jit
    static_radius = np.asarray(radius) if is_concrete(radius) else None
    image, radius, was_2d = check_image_and_radius(image, radius)
    max_radius = check_max_radius(max_radius, radius)
    if static_radius is None:
        # A NaN radius (possible under jit with EQX_ON_ERROR=nan or off) must not pass for a
        # sharp pixel (NaN fails `r > 1/2`, the identity test): poison its light instead, so every
        # output pixel it reaches is NaN.
        image = jnp.where(jnp.isnan(radius)[..., None], jnp.nan, image)
    radius = jnp.minimum(radius, max_radius)
    if static_radius is not None:
        static_radius = np.minimum(static_radius, max_radius)
    if method == "auto":
        method, knobs = _resolve_auto(static_radius, max_radius)
    if method == "layered" and static_radius is not None:
        assignment = assign_numpy(static_radius, knobs["layers"])
        sharp = sharp_first_level(static_radius, assignment)
        levels = level_radii(static_radius, assignment, knobs["layers"])
        knobs = {**knobs, "assignment": assignment, "sharp_level": sharp, "static_levels": levels}
    channels = image.shape[-1]
    if normalize:
        # filter a channel of ones alongside: the light each pixel would get from a flat field
        image = jnp.concatenate([image, jnp.ones_like(image[..., :1])], axis=-1)
    out = _dispatch(method, image, radius, max_radius, knobs)
    if normalize:
        out = out[..., :channels] / out[..., channels:]
    return out[..., 0] if was_2d else out


def _resolve_auto(radius: np.ndarray | None, max_radius: float) -> tuple[str, dict]:
    if radius is None:  # traced: the documented fallback to the exact gather
        logger.info("coc_filter(method='auto'): the radius map is traced, using 'soft'")
        return "soft", {"blades": None, "rotation": 0.0}
    choice = choose_method(radius, max_radius=max_radius)
    logger.info("coc_filter(method='auto') chose %r", choice)
    if choice == "soft":
        return "soft", {"blades": None, "rotation": 0.0}
    if choice == "tabulated":
        levels, index = radius_levels(radius)
        return "tabulated", {"levels": levels, "index": index}
    return "layered", {"layers": 1 if choice == "convolution" else distinct_levels(radius)}


def _dispatch(method: str, image, radius, max_radius: float, knobs: dict):
    if method == "tabulated":  # only from "auto", on a concrete radius map
        return tabulated_filter(image, max_radius=max_radius, **knobs)
    if method == "soft":
        if knobs["blades"] is None:
            # the dense gather, or row spans from SPANS_MIN_RADIUS on (same numbers, faster)
            return exact_soft_filter(image, radius, max_radius=max_radius)
        return soft_polygon_filter(image, radius, max_radius=max_radius, **knobs)
    if method == "hard":
        return hard_filter(image, radius, max_radius=max_radius)
    if method == "supersample":
        return supersample_filter(image, radius, max_radius=max_radius, **knobs)
    if method == "jitter":
        return jitter_filter(image, radius, max_radius=max_radius, **knobs)
    if method == "aperture":
        return aperture_filter(image, radius, max_radius=max_radius, **knobs)
    if method == "layered":
        return layered_filter(image, radius, max_radius=max_radius, **knobs)
    if method == "occlusion":
        return occlusion_filter(image, radius, max_radius=max_radius, **knobs)
    raise AssertionError(method)
