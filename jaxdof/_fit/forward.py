r"""Forward models: what `fit_lens` fits, the photo a lens makes of a scene.

A forward model is an `equinox.Module` (so a pytree: its array fields are traced, everything else is
static and part of the compiled solve's key, so distinct models compile distinctly). The fit needs
four things from it:

- `model(image, depth, lens, *, max_radius) -> photo`: one target, a pure JAX function,
  differentiable in the lens (forward mode: Levenberg-Marquardt builds its Jacobian with JVPs);
- `differentiable_in_lens`: whether that derivative is the true one (else the fit refuses it);
- `photo_shape(image_shape)`: the photo's shape, the image's `(H, W)` divided by an integer;
- `max_circle(lenses, depth)`: the largest circle it draws (pixels), which sizes the window;
- `border_band(max_radius)`: how far (photo pixels) light travels in a render with that window,
  which sizes the band along the edges that `fit_lens` leaves out (`border="auto"`).

`DefocusModel` is the thin-lens render `jaxdof.render`, the default of `fit_lens`.
"""

import abc
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from equinox import AbstractVar
from jaxtyping import Array, Bool, Float

from .._corrections import FOOTPRINT_REACH, footprint_prefilter
from .._custom_types import DepthLike, ImageLike
from .._filters import AbstractMethod, as_method, coc_filter
from .._lens import (
    ThinLens,
    _abs,
    _check_depth,
    _error_if_invalid,
    _signed_coc_radius_from_power,
    traced_checks,
)
from .._render import _check_downsample, box_downsample
from .layout import ALL_FIELDS


def max_circle(lenses: ThinLens | np.ndarray, depth: np.ndarray) -> float:
    """The largest circle of confusion (pixels) any of `lenses` makes over `depth`, in numpy.

    **Arguments:**

    - `lenses`: a `ThinLens` (any batch shape) or lens rows `(..., 4)` of
      `(focal_length, f_number, focus_distance, pixel_pitch)` (m, -, m, m).
    - `depth`: z-depths (m), any shape; `inf` counts as a circle of `K` pixels.

    **Returns:** `max |C (u - 1/d) / (1 - f u)|` over the depths, with `C = f^2 / (2 N pitch)` and
    `u = 1 / d_f` (the focus power, 0 for `d_f = inf`): `K |1 - d_f / d|` with
    `K = f^2 / (2 N (d_f - f)) / pitch`, written so that `d_f = inf` (`K = 0`, circles
    `C / d`) and `d = inf` (a circle of `K`) need no special case. A Python float (0 for no depth).
    """
    if isinstance(lenses, ThinLens):
        lenses = np.stack([np.asarray(getattr(lenses, n), np.float64) for n in ALL_FIELDS], -1)
    inv_d = 1 / np.asarray(depth, np.float64).reshape(-1)  # 0 at infinity
    if inv_d.size == 0:
        return 0.0
    # The extremes of u - 1/d over the scene are at its nearest and farthest depths.
    ends = np.array([inv_d.min(), inv_d.max()])
    rows = np.asarray(lenses, np.float64).reshape(-1, 4)
    f, n, d_f, pitch = (rows[:, i : i + 1] for i in range(4))
    u = 1 / d_f
    r = np.abs(f * f / (2 * n * pitch) * (u - ends[None, :]) / (1 - f * u))
    return float(np.max(r, initial=0.0))


class AbstractForwardModel(eqx.Module):
    """The forward model of a lens fit: the photo a lens makes of an all-in-focus image and its
    depth map. Subclass it to fit through a render of your own (pass `model=` to
    `jaxdof.fit_lens` / `jaxdof.solve_lens`).

    A subclass provides:

    - `__call__(image, depth, lens, *, max_radius)`: the photo of one target. `image` is
      `(H, W)` or `(H, W, C)` linear light, `depth` `(H, W)` z-depths (m), `lens` a scalar
      `ThinLens`, `max_radius` the window (a static Python float, the photo's pixels) beyond which
      circles may be clamped. A pure JAX function of its array arguments (jit, vmap, forward and
      reverse mode), returning `photo_shape(image.shape)`.
    - `differentiable_in_lens`: a field, class variable or property; whether the photo's derivative
      with respect to the lens is the true derivative of this model (`fit_lens` refuses `False`).

    and may override:

    - `photo_shape(image_shape)`: default the image's shape. A photo at a coarser resolution than
      the image must divide its `(H, W)` by one integer (the coarse-to-fine pyramid keeps it).
    - `max_circle(lenses, depth)`: the largest circle (the photo's pixels) the model draws for any of
      `lenses` (rows `(..., 4)` of `(f, N, d_f, pitch)`; `d_f = inf` is focus at infinity) over
      `depth`, in numpy; default the thin lens's circle of confusion (`jaxdof.coc_radius`).
      `fit_lens` sizes its window from it.
    - `border_band(max_radius)`: the farthest (photo pixels, along a row or column) a source
      pixel's light lands in a render with window `max_radius`; default `ceil(max_radius)`.
      The photo pixels that close to an edge receive light from outside the frame, which the
      image lacks: `fit_lens` leaves them out (its `border="auto"`).

    **Derivatives near focus at infinity.** `fit_lens` moves the focus through infinity, handing
    the model lenses with `focus_distance` up to `1e12` times the nearest depth. A model that
    computes its circles from `focus_distance` (`jaxdof.coc_radius` does) differentiates
    `d_f` there, which costs about `eps * d_f / d` relative accuracy (`eps` the dtype's rounding
    unit): negligible in float64 and for a focus inside the scene, but the Jacobian degrades in
    float32 from `d_f ~ 1e4 d` on. Compute the circles from `lens.focus_power` (`1 / d_f`) to
    keep them exact, as `DefocusModel` does.

    Everything in the model that is not an array (strings, flags, ints) is static: two models
    that differ in one compile two solves; equal models share one.
    """

    differentiable_in_lens: AbstractVar[bool]

    @abc.abstractmethod
    def __call__(
        self, image: ImageLike, depth: DepthLike, lens: ThinLens, *, max_radius: float
    ) -> Float[Array, "hp wp *c"]:
        """The photo of `image` (`(H, W[, C])`) at `depth` (`(H, W)`, m) through `lens`."""

    def photo_shape(self, image_shape: tuple[int, ...]) -> tuple[int, ...]:
        """The shape of the photo rendered from an image of `image_shape` (`(H, W[, C])`)."""
        return tuple(image_shape)

    def max_circle(self, lenses: ThinLens | np.ndarray, depth: np.ndarray) -> float:
        """The largest circle (the photo's pixels) of any of `lenses` over `depth` (numpy)."""
        return max_circle(lenses, depth)

    def border_band(self, max_radius: float) -> int:
        """How far (photo pixels) light travels in a render with window `max_radius` (pixels):
        `ceil(max_radius)`, the reach of a disc clamped to the window."""
        return math.ceil(max_radius)


class DefocusModel(AbstractForwardModel):
    """The thin-lens depth-of-field render `jaxdof.render`: the default forward model of
    `jaxdof.fit_lens` and `jaxdof.solve_lens`.

    **Fields** (all static; as in `jaxdof.render`):

    - `method`: how a circle spreads a pixel's light (default `"soft"`, the exact coverage). Its
      output must be differentiable with respect to the circle radii to drive a fit
      (`differentiable_in_radius`; `fit_lens` refuses the others).
    - `footprint`: the opt-in pixel-footprint correction (default off; `fit_lens` turns it on where
      small circles dominate): it removes the blur-scale bias of a few percent at circles of 1-3 px
      on ray-traced photos, and of up to 14 % on finely textured ones with circles under 1.5 px
      (`fits/results/raytraced.md`, `fits/results/footprint_order.md`). A scalar boolean array
      chooses at run time (`jax.lax.cond`), so that renders with and without it share one
      compiled program: `fit_lens` passes one, and tries the correction on and off at the cost
      of one compile.
    - `downsample`: the image and depth are this many times the photo's resolution in each axis
      (a pixel-shift capture, say): the photo is the image's `(H, W)` divided by it. Default 1.
      Each render costs about `downsample^2` times more.
    - `normalize`: as in `jaxdof.render` (default off).
    - `checks`: traced lenses and depths are checked when the render runs, and an invalid one
      (`depth <= focal_length`, a non-positive f-number) raises, as in `jaxdof.render` (default);
      `False`: the render is NaN there instead. Raising needs a host callback, and a program
      with one is not kept in the persistent compilation cache (`jaxdof.enable_compilation_cache`):
      `fit_lens` builds its own model with `checks=False`, since its coordinates keep every
      lens valid (and a NaN render fails the step, not the fit).

    The photo is `jaxdof.render`'s to rounding, with one difference in how it is computed: the
    circles come from the lens's focus power `u = 1 / d_f`, `r = |C (u - 1/d) / (1 - f u)|`
    (`C = f^2 / (2 N p)`), rather than from `d_f`, so that its derivatives stay exact as the focus
    moves to infinity (where `d_f`'s are `0 * inf`), which the fit's focus coordinate passes
    through; see `jaxdof.AbstractForwardModel`.

    A final class: for another render, subclass `jaxdof.AbstractForwardModel`.
    """

    method: str | AbstractMethod = "soft"
    footprint: bool | Bool[Array, ""] = False
    downsample: int = 1
    normalize: bool = False
    checks: bool = True

    def __check_init__(self):
        _check_downsample(self.downsample, ())
        as_method(self.method)  # an unknown method is refused here, not at the first render

    @property
    def differentiable_in_lens(self) -> bool:
        """Whether the method's output is differentiable in the circle radii (hence the lens)."""
        return bool(as_method(self.method).differentiable_in_radius)

    def __call__(
        self, image: ImageLike, depth: DepthLike, lens: ThinLens, *, max_radius: float
    ) -> Float[Array, "hp wp *c"]:
        """`jaxdof.render(image, depth, lens, max_radius=max_radius, ...)` with this model's
        options, its circles computed from the focus power (see the class docstring)."""
        image, depth = jnp.asarray(image), jnp.asarray(depth)
        s = _check_downsample(self.downsample, image.shape)
        method = as_method(self.method)
        _check_depth(depth, lens)  # concrete: ValueError now; traced: checked at run time
        with traced_checks("default" if self.checks else "nan"):  # this call's traced checks
            depth = _error_if_invalid(depth, lens)
            radius = _abs(
                _signed_coc_radius_from_power(
                    depth, lens.focal_length, lens.f_number, lens.focus_power, lens.pixel_pitch
                )
            ).astype(jnp.result_type(image.dtype, depth.dtype))
            # From here on as `jaxdof.render`: circles and window in the input's pixels.
            radius, window = radius * s, max_radius * s
            if isinstance(self.footprint, bool):
                if self.footprint:
                    image = footprint_prefilter(image, jnp.minimum(radius, window))
            else:  # chosen at run time: one program, only the chosen branch runs
                image = jax.lax.cond(
                    self.footprint,
                    lambda im: footprint_prefilter(im, jnp.minimum(radius, window)),
                    lambda im: im,
                    image,
                )
            out = coc_filter(
                image,
                radius,
                method=method,
                max_radius=window,
                normalize=self.normalize,
                depth=depth if method.uses_depth else None,
            )
        return box_downsample(out, s)

    def border_band(self, max_radius: float) -> int:
        """How far (photo pixels) light travels: `ceil(s R)` input pixels for a window of `R`
        photo pixels with `downsample = s` (`FOOTPRINT_REACH = 2` more with `footprint`, whose
        stencils read two neighbours), that is `ceil(ceil(s R) / s) = ceil(R)` photo pixels
        without it."""
        s = int(self.downsample)
        return math.ceil((math.ceil(s * max_radius) + FOOTPRINT_REACH * bool(self.footprint)) / s)

    def photo_shape(self, image_shape: tuple[int, ...]) -> tuple[int, ...]:
        """The image's shape with `(H, W)` divided by `downsample` (checked to divide them)."""
        s = _check_downsample(self.downsample, image_shape)
        return (image_shape[0] // s, image_shape[1] // s, *image_shape[2:])
