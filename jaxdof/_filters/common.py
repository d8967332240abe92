"""What every filter method shares: input checks, the window a scene needs, and the tap offsets."""

from __future__ import annotations

import math
import operator

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Float

from .. import _tuning
from .._lens import traced_on_error


#: The image a method and its kernel filter: channels last, `(H, W, C)` (`jaxdof.coc_filter` adds
#: the axis to a 2-D image). Beside `_custom_types.Radius`, in every kernel's signature.
ChannelsLast = Float[Array, "h w c"]


def is_concrete(*xs) -> bool:
    """True when no argument is a tracer, i.e. its values can be inspected in Python."""
    return not any(isinstance(x, Tracer) for x in jax.tree_util.tree_leaves(xs))


def window_half_width(max_radius: float) -> int:
    """Half-width `W` of the square window that a disc of radius `max_radius` can reach.

    The pixel at integer offset `k` along an axis is touched when its near edge `k - 1/2` is closer
    than the radius, so `W = ceil(R + 1/2) - 1` (never more than `ceil(R)`, the bound in the docs).
    """
    return max(math.ceil(max_radius + 0.5) - 1, 0)


def half_width(offsets: np.ndarray) -> int:
    """The largest `|offset|` along either axis: the zero padding a gather over `offsets` reads."""
    return int(np.abs(offsets).max()) if offsets.size else 0


def pad_rows_cols(x: ArrayLike, pad: int) -> Array:
    """`x` (rows and columns leading, any trailing axes) with a zero border of `pad` pixels."""
    return jnp.pad(x, ((pad, pad), (pad, pad)) + ((0, 0),) * (jnp.ndim(x) - 2))


def tap_offsets(max_radius: float) -> np.ndarray:
    """Integer offsets `(oy, ox)` of the pixels a disc of radius `max_radius` overlaps, `(n, 2)`.

    The window's corners that the disc cannot reach are dropped (about a fifth of the taps).
    """
    w = window_half_width(max_radius)
    o = np.arange(-w, w + 1)
    oy, ox = np.meshgrid(o, o, indexing="ij")
    near = np.hypot(np.maximum(np.abs(oy) - 0.5, 0), np.maximum(np.abs(ox) - 0.5, 0))
    keep = (near < max_radius) | ((oy == 0) & (ox == 0))
    return np.stack([oy[keep], ox[keep]], axis=-1).astype(np.int32)


def check_max_radius(max_radius, radius) -> float:
    """Resolve `max_radius`: a given Python number, or the largest radius of a concrete map."""
    if max_radius is None:
        if not is_concrete(radius):
            raise ValueError(
                "max_radius=None sizes the filter window from the largest circle in the scene, "
                "which needs concrete values; under jit/vmap/grad pass max_radius=<float> (pixels) "
                "as a static Python number."
            )
        r = np.asarray(radius)
        return float(np.max(r)) if r.size else 0.0
    if isinstance(max_radius, jax.Array) and not is_concrete(max_radius):
        raise ValueError(
            "max_radius must be a static Python number (it sizes the window), not a traced array"
        )
    max_radius = float(max_radius)
    if not math.isfinite(max_radius) or max_radius < 0:
        raise ValueError(f"max_radius must be a finite number >= 0 (pixels), got {max_radius}")
    return max_radius


RADIUS_MSG = "radius must be >= 0 pixels everywhere (found a negative or NaN value)"


def check_image_and_radius(image, radius) -> tuple[Array, Array, bool]:
    """Validate shapes and dtypes; return `(image (H, W, C), radius (H, W), was_2d)` in one dtype.

    Radii must be `>= 0` and not NaN: concrete values raise `ValueError`; traced ones are checked
    at run time by `equinox.error_if` (a comparison and a reduction over the map).
    """
    image = jnp.asarray(image)
    radius = jnp.asarray(radius)
    if image.ndim not in (2, 3):
        raise ValueError(f"image must have shape (H, W) or (H, W, C), got shape {image.shape}")
    for name, x in (("image", image), ("radius", radius)):
        if not jnp.issubdtype(x.dtype, jnp.floating):
            raise ValueError(
                f"{name} must be a floating-point array (linear light / pixels), got dtype "
                f"{x.dtype}; convert it first, e.g. {name}.astype(numpy.float32)"
            )
    if radius.shape != image.shape[:2]:
        raise ValueError(
            f"radius must have the image's (H, W) = {image.shape[:2]}, got shape {radius.shape}"
        )
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f"image must have at least one pixel, got shape {image.shape}")
    dtype = jnp.result_type(image.dtype, radius.dtype)
    if is_concrete(radius):
        r = np.asarray(radius)
        if np.any(np.isnan(r)) or np.any(r < 0):
            raise ValueError(RADIUS_MSG)
    else:
        # Under jit/grad/vmap: an error with the same message when the computation runs (if any
        # batch element is bad under vmap; in the forward pass under grad). The returned radius
        # must be used for the check to survive dead-code elimination.
        # `~(r >= 0)`: NaN fails too
        radius = eqx.error_if(radius, ~(radius >= 0), RADIUS_MSG, on_error=traced_on_error())  # pyright: ignore
    was_2d = image.ndim == 2
    if was_2d:
        image = image[..., None]
    return image.astype(dtype), radius.astype(dtype), was_2d


def check_depth_map(depth, shape: tuple[int, int]) -> Array:
    """`depth` as a floating-point `(H, W)` array for a method that reads it; `ValueError` else."""
    depth = jnp.asarray(depth)
    if depth.shape != tuple(shape) or not jnp.issubdtype(depth.dtype, jnp.floating):
        raise ValueError(
            f"depth must be a floating-point (H, W) = {tuple(shape)} map (z-depth, e.g. metres), "
            f"got shape {depth.shape} and dtype {depth.dtype}"
        )
    return depth


def unique_with_index(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(sorted distinct values (L,), index map int32 of values' shape)`, as `np.unique` with
    `return_inverse=True`, without its argsort when the values are few."""
    uniq = np.unique(values)
    return uniq, level_index(values, uniq)


def level_index(values: np.ndarray, uniq: np.ndarray) -> np.ndarray:
    """Position of every entry of `values` in `uniq = np.unique(values)`, int32, `values`' shape."""
    if uniq.size > _tuning.COMPARE_MAX_LEVELS:
        inverse = np.unique(values, return_inverse=True)[1]
        return inverse.reshape(values.shape).astype(np.int32)
    index = np.zeros(values.shape, np.int32)
    for v in uniq[:-1]:  # a value's position = how many distinct values lie below it
        index += values > v
    return index


# Checks of the methods' options (shared by the method classes): `ValueError`s that name the option
# and say what it must be.


def check_int(name: str, value, lo: int, hi: int | None = None) -> int:
    """`value` as a Python int in `[lo, hi]` (`hi=None`: no upper bound); bools are refused."""
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


def check_blades(blades) -> int | None:
    """The number of diaphragm blades: `None` (a circular aperture) or an int in `[3, 1024]`."""
    return None if blades is None else check_int("blades", blades, 3, 1024)


def check_rotation(rotation, blades: int | None, owner: str) -> float:
    """The diaphragm's rotation (radians) as a static finite float.

    `owner` (e.g. `"Soft"`) names a method whose disc has no orientation: there a non-zero
    rotation without `blades` is refused, since it would silently do nothing.
    """
    if isinstance(rotation, jax.Array) and not is_concrete(rotation):
        raise ValueError("rotation must be a static Python number (radians), not a traced array")
    rotation = float(rotation)
    if not math.isfinite(rotation):
        raise ValueError(f"rotation must be finite (radians), got {rotation}")
    if rotation != 0 and blades is None and owner:
        raise ValueError(
            f"rotation={rotation} has no effect on a circular aperture with {owner}(); pass "
            "blades=<int >= 3> for a polygonal diaphragm, or drop rotation"
        )
    return rotation


def check_bool(name: str, value) -> bool:
    """`value` as a Python bool (not merely truthy)."""
    if not isinstance(value, bool):
        raise ValueError(f"{name} must be a Python bool, got {value!r}")
    return value


def check_key(key, what: str, how: str) -> Array:
    """A single `jax.random` key: a typed key (`jax.random.key`) or a raw `uint32[2]`
    (`jax.random.PRNGKey`). `what` names the method that needs it and `how` is the call that
    gives it one, for the message when it is missing."""
    if key is None:
        raise ValueError(
            f"{what} draws random samples and needs an explicit key: pass e.g. {how} (the same "
            "key always gives the same image)"
        )
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
