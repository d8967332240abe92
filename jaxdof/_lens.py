"""Thin-lens optics: the lens parameters, the circle of confusion, and depth-buffer linearisation."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._custom_types import AnyFloat, AnyFloatLike


_FIELDS = ("focal_length", "f_number", "focus_distance", "pixel_pitch")


def _as_float(x: ArrayLike) -> Array:
    """Converter for lens fields: keep floating arrays as they are, make anything else float."""
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


class ThinLens(eqx.Module):
    """An ideal thin lens in front of a pixel sensor. All lengths in metres (SI).

    **Fields:**

    - `focal_length`: focal length `f` (m).
    - `f_number`: relative aperture `N = f / D` for an aperture of diameter `D` (dimensionless).
    - `focus_distance`: distance `d_f` from the lens to the plane in focus (m), `> f`.
    - `pixel_pitch`: width of one sensor pixel (m); use `ThinLens.from_sensor` to derive it from
      the sensor width.

    Fields are arrays, so a `ThinLens` is a pytree you can `jit`, `vmap` and differentiate.
    Concrete values are validated at construction (positive and finite, `focus_distance >
    focal_length`): `ValueError`. A lens built from traced values (under `jit`, `grad`, `vmap`)
    cannot be checked there; `jaxdof.coc_radius` then returns NaN for an invalid lens and
    `jaxdof.render` raises at run time (see "Invalid inputs" in `jaxdof.coc_radius`).
    """

    focal_length: Float[Array, "*batch"] = eqx.field(converter=_as_float)
    f_number: Float[Array, "*batch"] = eqx.field(converter=_as_float)
    focus_distance: Float[Array, "*batch"] = eqx.field(converter=_as_float)
    pixel_pitch: Float[Array, "*batch"] = eqx.field(converter=_as_float)

    def __check_init__(self):
        _check_lens_values(self)

    @classmethod
    def from_sensor(
        cls,
        focal_length: AnyFloatLike,
        f_number: AnyFloatLike,
        focus_distance: AnyFloatLike,
        *,
        sensor_width: AnyFloatLike,
        image_width: int,
    ) -> ThinLens:
        """Build a lens whose pixel pitch is `sensor_width / image_width` (metres, pixels)."""
        if int(image_width) != image_width or image_width < 1:
            raise ValueError(
                f"image_width must be a positive integer number of pixels, got {image_width}"
            )
        return cls(
            focal_length, f_number, focus_distance, _as_float(sensor_width) / int(image_width)
        )

    @property
    def blur_scale(self) -> Array:
        """`K = f^2 / (2 N (d_f - f)) / pixel_pitch`: the CoC radius in pixels of a point at infinity.

        From a single image the blur depends on the lens only through `K` and `focus_distance`.
        """
        f = self.focal_length
        return f * f / (2 * self.f_number * (self.focus_distance - f) * self.pixel_pitch)


def _check_lens_values(lens: ThinLens) -> None:
    """Raise `ValueError` for a concrete lens with a bad field; do nothing for a traced one."""
    values = {name: getattr(lens, name) for name in _FIELDS}
    if not all(_is_concrete(v) for v in values.values()):
        return
    for name, v in values.items():
        v = np.asarray(v)
        if not np.all(np.isfinite(v)) or not np.all(v > 0):
            raise ValueError(
                f"ThinLens.{name} must be positive and finite, got {name}={v}. "
                "Lengths are in metres (50 mm is 0.05)."
            )
    f, d_f = np.asarray(values["focal_length"]), np.asarray(values["focus_distance"])
    if not np.all(d_f > f):
        raise ValueError(
            f"ThinLens.focus_distance must exceed focal_length (a thin lens cannot focus closer "
            f"than its focal length), got focus_distance={d_f} m <= focal_length={f} m."
        )


# The messages are shared by the concrete checks (`ValueError`) and the run-time checks under jit
# (`equinox.error_if`), so a user sees the same words either way.
_DEPTH_MSG = (
    "depth must be beyond the focal length everywhere (metres; NaN, negative and depths <= "
    "focal_length cannot be imaged)"
)
_LENS_MSG = (
    "ThinLens fields must be positive and finite and focus_distance must exceed focal_length "
    "(a thin lens cannot focus closer than its focal length); lengths are in metres"
)


def _lens_is_valid(lens: ThinLens) -> Array:
    """Boolean (lens batch shape): every field positive and finite, `focus_distance > f`."""
    ok = lens.focus_distance > lens.focal_length
    for name in _FIELDS:
        v = getattr(lens, name)
        ok = ok & (v > 0) & jnp.isfinite(v)
    return ok


def _check_depth(depth: Array, lens: ThinLens) -> None:
    """`ValueError` for concrete depths not beyond the focal length (NaN included) or a bad lens."""
    _check_lens_values(lens)
    if _is_concrete(depth) and _is_concrete(lens.focal_length):
        d, f = np.broadcast_arrays(np.asarray(depth), np.asarray(lens.focal_length))
        bad = ~(d > f)  # rather than `d <= f`: NaN fails it too
        if np.any(bad):
            raise ValueError(
                f"{_DEPTH_MSG}: {np.count_nonzero(bad)} of {bad.size} values are not, e.g. "
                f"depth={d[bad][0]} m with focal_length={f[bad][0]} m"
            )


def _error_if_invalid(depth: Array, lens: ThinLens) -> Array:
    """`depth`, with run-time checks of `depth > focal_length` and of the lens attached.

    `equinox.error_if` raises when the compiled computation runs (`EquinoxRuntimeError` under
    `equinox.filter_jit`; `jax.jit` re-raises it as a JAX runtime error with the same message): under `vmap` if any batch element is invalid, under `grad` in the forward
    pass. The check
    is a comparison and an `any` over the depth map plus a `lax.cond`: negligible beside a filter.
    The returned array must be used, or the check is dead code and removed. Concrete inputs are
    returned as they are (`_check_depth` has already inspected them).
    """
    if all(_is_concrete(x) for x in jax.tree_util.tree_leaves((depth, lens))):
        return depth
    depth = eqx.error_if(depth, ~(depth > lens.focal_length.astype(depth.dtype)), _DEPTH_MSG)
    return eqx.error_if(depth, ~_lens_is_valid(lens), _LENS_MSG)


def signed_coc_radius(depth: AnyFloatLike, lens: ThinLens) -> AnyFloat:
    r"""Signed circle-of-confusion radius in pixels: negative in front of the focus plane.

    **Arguments:**

    - `depth`: z-depth `d` of each point along the optical axis (m), any shape; `inf` is allowed.
    - `lens`: the `ThinLens`.

    **Returns:** `K (1 - d_f / d)` in pixels, with `K = f^2 / (2 N (d_f - f)) / p`.

    **Derivation.** The lens images a point at depth `d` at distance `s_d = f d / (d - f)` behind
    it, and the sensor sits at `s = f d_f / (d_f - f)`, where the focus plane is sharp. The cone of
    light from the aperture (diameter `D = f / N`, radius `a = f / (2N)`) converging to `s_d`
    cuts the sensor in a disc of radius

    $$a \left| \frac{s - s_d}{s_d} \right| = a \left| s \left(\frac1f - \frac1d\right) - 1\right|,$$

    the form used by Riguer et al. (2006) and Yu (2004). Substituting `s` gives
    `a f (1 - d_f/d) / (d_f - f)`, i.e. `K (1 - d_f / d)` once divided by the pixel pitch `p`.
    The sign is that of `d - d_f`. It is computed as `(d - d_f) / d` (no cancellation near the
    focus plane) and as `1` at `d = inf`, with finite derivatives there.

    Invalid inputs (depth not beyond the focal length, NaN, an invalid traced lens): as in
    `jaxdof.coc_radius`.
    """
    depth = _as_float(depth)
    _check_depth(depth, lens)
    # Compute in the depth's precision (a float64 lens does not promote a float32 scene).
    d_f = lens.focus_distance.astype(depth.dtype)
    valid = (depth > lens.focal_length.astype(depth.dtype)) & _lens_is_valid(lens)
    inf = jnp.isinf(depth)
    # Double-where: the unused branch sees a harmless depth, so d/d(depth) is finite (zero) at
    # inf and at invalid entries, whose value is the NaN poison below.
    safe = jnp.where(inf | ~valid, 1.0, depth)
    defocus = jnp.where(inf, 1.0, (safe - d_f) / safe)
    return jnp.where(valid, lens.blur_scale.astype(depth.dtype) * defocus, jnp.nan)


@jax.custom_jvp
def _abs(x: Array) -> Array:
    """`|x|` with derivative `sign(x)`, i.e. the symmetric subgradient 0 at the kink."""
    return jnp.abs(x)


@_abs.defjvp
def _abs_jvp(primals, tangents):
    (x,), (t,) = primals, tangents
    return jnp.abs(x), jnp.sign(x) * t


def coc_radius(depth: AnyFloatLike, lens: ThinLens) -> AnyFloat:
    r"""Circle-of-confusion radius in pixels, `r = f^2 / (2 N (d_f - f)) * |1 - d_f/d| / p`.

    The absolute value of `jaxdof.signed_coc_radius` (see there for the derivation). At the focus
    plane, where `|.|` has a kink, the derivative is defined as the symmetric subgradient `0`
    (JAX's own `abs` would give `+1`, favouring one side of the focus plane).

    **Invalid inputs.** Valid inputs are `depth > focal_length` (points the lens can image, `inf`
    included) and a valid lens (fields positive and finite, `focus_distance > focal_length`).

    - Concrete values: `ValueError` naming the problem (NaN, negative and `depth <= focal_length`
      alike). This inspects the values on the host, i.e. waits for them.
    - Traced values (under `jit`, `grad`, `vmap`): no error can be raised from this elementwise
      function; invalid entries are NaN (the whole map for an invalid lens), so the poison shows
      in any loss built on them. At an invalid depth the derivative is 0, never NaN, so a loss
      that masks such pixels out keeps finite gradients. `jaxdof.render` instead raises at run time (`equinox.error_if`).
    """
    return _abs(signed_coc_radius(depth, lens))


def linearize_depth(zbuf: AnyFloatLike, near: AnyFloatLike, far: AnyFloatLike) -> AnyFloat:
    r"""OpenGL window-space depth in `[0, 1]` to eye-space z-depth in metres.

    For a perspective projection with clip planes `near < far` (the `gluPerspective` /
    `glFrustum` convention), window depth `z` maps back to the distance along the optical axis

    $$Z = \frac{n f}{f - z (f - n)},$$

    so `z = 0` gives `near` and `z = 1` gives `far` (Yu, "Depth of field implementation with
    OpenGL"). Units of `near`, `far` are those of the result.
    """
    z = _as_float(zbuf)
    return near * far / (far - z * (far - near))
