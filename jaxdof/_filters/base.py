r"""The filter-method family: an abstract base that every method (built in or a user's) subclasses.

A method is an `equinox.Module` that holds and validates its own options (as diffrax's solvers
do): `jaxdof.Soft()`, `jaxdof.Aperture(pattern="ring", samples=32)`, or a user's subclass. It maps
an image and a per-pixel circle-of-confusion radius to the scattered image:

$$\text{out}[p] = \sum_q \text{image}[q]\, k_{r_q}(p - q)$$

with a kernel `k_r` that integrates to one (energy conserving). `jaxdof.coc_filter` checks the
inputs, resolves the window and calls `method.prepare` (on a concrete radius map) and then the
method itself on a channels-last image.
"""

from __future__ import annotations

import abc
from typing import ClassVar

import equinox as eqx
import numpy as np
from jaxtyping import Array, Float


class AbstractMethod(eqx.Module):
    """How a circle of confusion spreads a pixel's light. Subclass it to bring your own.

    A subclass says about itself:

    - `differentiable_in_radius` (class variable): whether `d(out)/d(radius)` is the true
      derivative of the method's own forward model, so that a lens can be fitted through it
      (`jaxdof.fit_lens` refuses a method for which it is `False`).
    - `uses_depth` (class variable, default `False`): whether the method reads the depth map
      (occlusion ordering); `jaxdof.render` then passes it.
    - `prepare(radius, max_radius)`: optional precomputation on a *concrete* radius map (numpy),
      e.g. radius levels or the choice of a kernel; returns the method to call (default: itself).
      Not called when the radius is traced (under `jit`/`grad`), so `__call__` must work without it.
    - `__call__(image, radius, *, max_radius, depth)`: the filter, on `image` `(H, W, C)` and
      `radius` `(H, W)` (pixels, already clamped to `max_radius`), returning `(H, W, C)`. It must be
      a pure JAX function of its array arguments (jit, vmap, grad). `depth` (`(H, W)`) is passed
      only to a method with `uses_depth`.

    Options are fields: arrays (a random key) as leaves, Python ints and strings that shape the
    computation as `eqx.field(static=True)`. Checks of the options belong in `__check_init__` or
    `__init__` (`ValueError` naming the option and the fix). `jaxdof.coc_filter`, `jaxdof.render`
    and `jaxdof.render_batch` take an instance, or a built-in's name (`as_method`: `"soft"` is
    `Soft()`).
    """

    differentiable_in_radius: ClassVar[bool]
    uses_depth: ClassVar[bool] = False

    def prepare(self, radius: np.ndarray, max_radius: float) -> AbstractMethod:
        """Precompute on a concrete radius map `(H, W)` (pixels, clamped to `max_radius`)."""
        del radius, max_radius
        return self

    @abc.abstractmethod
    def __call__(
        self,
        image: Float[Array, "h w c"],
        radius: Float[Array, "h w"],
        *,
        max_radius: float,
        depth: Float[Array, "h w"] | None = None,
    ) -> Float[Array, "h w c"]:
        """Spread every pixel of `image` over its circle of radius `radius` (pixels)."""
