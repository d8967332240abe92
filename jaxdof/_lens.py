"""Thin-lens optics: the lens parameters, the circle of confusion, and depth-buffer linearisation."""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Iterator

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
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
    return not isinstance(x, Tracer)


class ThinLens(eqx.Module):
    """An ideal thin lens in front of a pixel sensor. All lengths in metres (SI).

    **Fields:**

    - `focal_length`: focal length `f` (m).
    - `f_number`: relative aperture `N = f / D` for an aperture of diameter `D` (dimensionless).
    - `focus_distance`: distance `d_f` from the lens to the plane in focus (m), `> f`; `inf`
      (focused at infinity, the sensor in the focal plane) is allowed. See also `focus_power`.
    - `pixel_pitch`: width of one sensor pixel (m); use `ThinLens.from_sensor` to derive it from
      the sensor width.

    Fields are arrays, so a `ThinLens` is a pytree you can `jit`, `vmap` and differentiate.
    Concrete values are validated at construction (positive and finite, `focus_distance >
    focal_length`, `focus_distance = inf` allowed): `ValueError`. A lens built from traced values
    (under `jit`, `grad`, `vmap`) cannot be checked there; `jaxdof.coc_radius` then returns NaN for
    an invalid lens and `jaxdof.render` raises at run time (see "Invalid inputs" in
    `jaxdof.coc_radius`).
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
        Focused at infinity (`focus_distance = inf`) `K = 0`, as a point at infinity is sharp; the
        blur of a point at depth `d` is then `f^2 / (2 N d) / pixel_pitch`, and the single-image
        invariant is `f^2 / (2 N) / pixel_pitch` (`jaxdof.coc_radius` handles both cases). Its
        derivatives are finite there (0 with respect to `focus_distance`).
        """
        # `(f^2 / 2Np) / (d_f - f)` rather than one product in the denominator: at d_f = inf a
        # product `2 N (d_f - f) p` has an infinite tangent (dN * inf), and the quotient's
        # derivative would be inf * 0 = NaN.
        return _blur_numerator(self) / (self.focus_distance - self.focal_length)

    @property
    def focus_power(self) -> Array:
        """`u = 1 / focus_distance` (diopters, 1/m): 0 when focused at infinity.

        The coordinate in which infinity is an ordinary point: the valid lenses are exactly
        `0 <= u < 1 / f`, and the radius `r = f^2 |u - 1/d| / (2 N p (1 - f u))` is smooth in `u`
        up to and including `u = 0`. A fit that moves the focus should move `u`, not
        `focus_distance` (whose derivative at infinity, 0, times `d(1/u)/du = -inf`, is NaN).
        """
        return 1 / self.focus_distance


def _blur_numerator(lens: ThinLens) -> Array:
    """`f^2 / (2 N p)` (pixels times metres): the blur of a point at 1 m focused at infinity."""
    f = lens.focal_length
    return f * f / (2 * lens.f_number * lens.pixel_pitch)


def _check_lens_values(lens: ThinLens) -> None:
    """Raise `ValueError` for a concrete lens with a bad field; do nothing for a traced one."""
    values = {name: getattr(lens, name) for name in _FIELDS}
    if not all(_is_concrete(v) for v in values.values()):
        return
    for name, v in values.items():
        v = np.asarray(v)
        if name == "focus_distance":  # +inf is a lens focused at infinity
            ok, what = v > 0, "positive (or inf, focused at infinity)"
        else:
            ok, what = (v > 0) & np.isfinite(v), "positive and finite"
        if not np.all(ok):  # `v > 0` is False for NaN
            raise ValueError(
                f"ThinLens.{name} must be {what}, got {name}={v}. "
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
    "(a thin lens cannot focus closer than its focal length; focus_distance=inf, focused at "
    "infinity, is allowed); lengths are in metres"
)


def _lens_is_valid(lens: ThinLens) -> Array:
    """Boolean (lens batch shape): fields positive and finite (`focus_distance = inf` allowed),
    `focus_distance > f`."""
    # `d_f > f` is False for NaN and True for +inf (focused at infinity, valid); with `f` positive
    # and finite it also makes `d_f` positive.
    ok = lens.focus_distance > lens.focal_length
    for name in ("focal_length", "f_number", "pixel_pitch"):
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


# What a traced check does when it fails (`equinox.error_if`'s `on_error`), read at trace time by
# every traced check (`_error_if_invalid`, the filters' radius check): "default" (equinox's
# `EQX_ON_ERROR`, raising unless set), or "nan" inside a model that asks for no host callbacks
# (`DefocusModel.checks`).
_ON_ERROR: contextvars.ContextVar[str] = contextvars.ContextVar(
    "jaxdof_on_error", default="default"
)


@contextlib.contextmanager
def traced_checks(on_error: str) -> Iterator[None]:
    """Within the block, traced checks do `on_error` (`"default"` or `"nan"`) on failure: `"nan"`
    needs no host callback, so the program can be kept in the persistent compilation cache."""
    token = _ON_ERROR.set(on_error)
    try:
        yield
    finally:
        _ON_ERROR.reset(token)


def traced_on_error() -> str:
    """What a traced check does on failure here (`traced_checks`)."""
    return _ON_ERROR.get()


def _error_if_invalid(depth: Array, lens: ThinLens) -> Array:
    """`depth`, with run-time checks of `depth > focal_length` and of the lens attached (NaN
    instead where `traced_checks("nan")` asks).

    `equinox.error_if` raises when the compiled computation runs (`EquinoxRuntimeError` under
    `equinox.filter_jit`; `jax.jit` re-raises it as a JAX runtime error with the same message): under `vmap` if any batch element is invalid, under `grad` in the forward
    pass. The check
    is a comparison and an `any` over the depth map plus a `lax.cond`: negligible beside a filter.
    The returned array must be used, or the check is dead code and removed. Concrete inputs are
    returned as they are (`_check_depth` has already inspected them).
    """
    if all(_is_concrete(x) for x in jax.tree_util.tree_leaves((depth, lens))):
        return depth
    bad = ~(depth > lens.focal_length.astype(depth.dtype))
    on_error = traced_on_error()
    depth = eqx.error_if(depth, bad, _DEPTH_MSG, on_error=on_error)  # pyright: ignore
    return eqx.error_if(depth, ~_lens_is_valid(lens), _LENS_MSG, on_error=on_error)  # pyright: ignore


def signed_coc_radius(depth: AnyFloatLike, lens: ThinLens) -> AnyFloat:
    r"""Signed circle-of-confusion radius in pixels: negative in front of the focus plane.

    **Arguments:**

    - `depth`: z-depth `d` of each point along the optical axis (m), any shape; `inf` is allowed.
    - `lens`: the `ThinLens`.

    **Returns:** `K (1 - d_f / d)` in pixels, with `K = f^2 / (2 N (d_f - f)) / p`; focused at
    infinity (`d_f = inf`), `-f^2 / (2 N d p)` (every finite depth is in front of the focus plane,
    and a point at infinity is sharp).

    **Derivation.** The lens images a point at depth `d` at distance `s_d = f d / (d - f)` behind
    it, and the sensor sits at `s = f d_f / (d_f - f)`, where the focus plane is sharp. The cone of
    light from the aperture (diameter `D = f / N`, radius `a = f / (2N)`) converging to `s_d`
    cuts the sensor in a disc of radius

    $$a \left| \frac{s - s_d}{s_d} \right| = a \left| s \left(\frac1f - \frac1d\right) - 1\right|,$$

    the form used by Riguer et al. (2006) and Yu (2004). Substituting `s` gives
    `a f (1 - d_f/d) / (d_f - f)`, i.e. `K (1 - d_f / d)` once divided by the pixel pitch `p`.
    The sign is that of `d - d_f`.

    **Numerics.** With `C = f^2 / (2 N p)` the radius is `C (d - d_f) / (d (d_f - f))`, computed
    as `K ((d - d_f) / d)` behind the focus plane and as `C ((d - d_f) / (d_f - f)) / d` in front
    of it. Each quotient in brackets lies in `(-1, 1)`, so no step overflows for any `d_f` or `d`
    (the textbook `K (1 - d_f/d)` is `0 * inf` at `d_f = inf` and overflows in front of a very
    distant focus), and `d - d_f` has no cancellation error near the focus plane: in float32 the
    radius is within 2 rounding units (`2^-23` relative) of the exact value on a grid of lenses and
    depths (`tests/test_lens.py`). The limits are taken exactly: `K` at `d = inf`, `-C / d` at
    `d_f = inf`, and 0 when both are infinite, with finite derivatives there (the limits': 0 with
    respect to an infinite depth or focus distance).

    Invalid inputs (depth not beyond the focal length, NaN, an invalid traced lens): as in
    `jaxdof.coc_radius`.
    """
    depth = _as_float(depth)
    _check_depth(depth, lens)
    dtype = depth.dtype  # a float64 lens does not promote a float32 scene
    lens_ok = _lens_is_valid(lens)
    valid = (depth > lens.focal_length.astype(dtype)) & lens_ok
    # Double-where: every quotient below sees harmless (finite, nonzero) values wherever its
    # result is not used (an infinite depth or focus distance, an invalid entry), so no inf * 0
    # or 0 / 0 reaches a derivative. Invalid entries are the NaN poison at the end.
    d_inf = jnp.isinf(depth)
    f_inf = lens_ok & ~jnp.isfinite(lens.focus_distance)  # +inf; jnp.isinf warns without x64
    finite_lens = lens_ok & ~f_inf
    # C, d_f - f and K = C / (d_f - f) in the lens's precision (for a float32 lens d_f - f is
    # exact near the focal length), then in the depth's.
    c = jnp.where(lens_ok, _blur_numerator(lens), 1)
    w = jnp.where(finite_lens, lens.focus_distance - lens.focal_length, 1)
    k, c, w = (c / w).astype(dtype), c.astype(dtype), w.astype(dtype)
    d_f = jnp.where(finite_lens, lens.focus_distance, 1).astype(dtype)
    d = jnp.where(valid & ~d_inf, depth, 1)
    n = d - d_f
    # Behind the focus plane K (1 - d_f/d) as the textbook has it, in front C ((d - d_f) /
    # (d_f - f)) / d: both factors in brackets lie in (-1, 1), so no step overflows.
    r = jnp.where(n >= 0, k * (n / d), c * (n / w) / d)
    r = jnp.where(d_inf, jnp.where(f_inf, 0, k), jnp.where(f_inf, -c / d, r))
    return jnp.where(valid, r, jnp.nan)


def _signed_coc_radius_from_power(
    depth: AnyFloatLike,
    focal_length: AnyFloatLike,
    f_number: AnyFloatLike,
    focus_power: AnyFloatLike,
    pixel_pitch: AnyFloatLike,
) -> AnyFloat:
    r"""`jaxdof.signed_coc_radius` with the focus given by its power `u = 1 / d_f` (diopters).

    For fits that move the focus in diopters, where infinity (`u = 0`) is an ordinary point:
    `r = C (u - 1/d) / (1 - f u)` with `C = f^2 / (2 N p)` is smooth in `u` on `[0, 1/f)`, and its
    derivatives are exact there, `u = 0` included. Building `ThinLens(..., 1 / u, ...)` instead
    differentiates through `d_f = 1/u`: at `u = 0` reverse mode gives `0 * inf = NaN` and forward
    mode 0 (the true derivative of the signed radius is `C (1 - f/d)`), and in float32 `d_f^2`
    overflows below `u ~ 1e-19`.

    No concrete checks: entries with `depth <= f` (or NaN), `u < 0`, `f u >= 1` or a field not
    positive and finite are NaN, with derivative 0 with respect to the depth. Same dtype rules as
    `signed_coc_radius` (computed in the depth's precision). Accuracy: the absolute error is a
    few rounding units of `C max(u, 1/d) / (1 - f u)` (the subtraction `u - 1/d` cancels near the
    focus plane, where the radius is small), and `1 - f u` loses `log2(1 / (1 - f u))` bits as
    the focus approaches the focal length; `signed_coc_radius`, given `d_f`, has neither loss.
    """
    depth = _as_float(depth)
    dtype = depth.dtype
    f, u = jnp.asarray(focal_length), jnp.asarray(focus_power)
    n, p = jnp.asarray(f_number), jnp.asarray(pixel_pitch)
    g = 1 - f * u
    lens_ok = (u >= 0) & (g > 0) & (f > 0) & jnp.isfinite(f) & (n > 0) & jnp.isfinite(n)
    lens_ok = lens_ok & (p > 0) & jnp.isfinite(p)
    valid = (depth > f.astype(dtype)) & lens_ok
    # Double-where, as in `signed_coc_radius`: harmless values wherever the result is not used.
    c = jnp.where(lens_ok, f * f / (2 * n * p) / jnp.where(lens_ok, g, 1), 1).astype(dtype)
    u = jnp.where(lens_ok, u, 0).astype(dtype)
    inv_d = 1 / jnp.where(valid, depth, 1)  # 0 at depth = inf, derivative -1/d^2 = 0 there
    return jnp.where(valid, c * (u - inv_d), jnp.nan)


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
    included) and a valid lens (fields positive and finite, `focus_distance > focal_length`;
    `focus_distance = inf` is a lens focused at infinity, where `r = f^2 / (2 N d p)`).

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
    z, near, far = _as_float(zbuf), jnp.asarray(near), jnp.asarray(far)
    return near * far / (far - z * (far - near))
