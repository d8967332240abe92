r"""The filter-method family: an abstract base that every method (built in or a user's) subclasses.

A method is an `equinox.Module` that holds and validates its own options (as diffrax's solvers
do): `jaxdof.Soft()`, `jaxdof.Aperture(pattern="ring", samples=32)`, or a user's subclass. It maps
an image and a per-pixel circle-of-confusion radius to the scattered image:

$$\text{out}[p] = \sum_q \text{image}[q]\, k_{r_q}(p - q)$$

with a kernel `k_r` that integrates to one (energy conserving). `jaxdof.coc_filter` checks the
inputs, resolves the window and calls `method.prepare` (on a concrete radius map) and then the
method itself on a channels-last image: `AbstractMethod.__call__`, which runs the subclass's
`spread`.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any, ClassVar

import equinox as eqx
import numpy as np

from .._custom_types import Depth, Radius
from .common import ChannelsLast


class AbstractMethod(eqx.Module):
    """How a circle of confusion spreads a pixel's light. Subclass it to bring your own.

    A subclass says about itself:

    - `differentiable_in_radius` (class variable): whether `d(out)/d(radius)` is the true
      derivative of the method's own forward model, so that a lens can be fitted through it
      (`jaxdof.fit_lens` refuses a method for which it is `False`).
    - `uses_depth` (class variable, default `False`): whether the method reads the depth map
      (occlusion ordering); `jaxdof.render` then passes it.
    - `local` (class variable, default `True`): whether every output pixel depends only on the
      inputs within the window around it, so that `jaxdof.render(..., band_rows=)` may render
      the frame in bands; `False` for a method that decides from the whole frame (`Jitter`'s
      per-pixel sample patterns are drawn over the frame's shape). A method that `uses_depth` is
      rendered whole too (its depth ordering may be global, as `Occlusion`'s layers are).
    - `prepare(radius, max_radius)`: optional precomputation on a *concrete* radius map (numpy),
      e.g. radius levels or the choice of a kernel; returns the method to call (default: itself).
      Not called when the radius is traced (under `jit`/`grad`), so the method must work without
      it.
    - `spread(image, radius, *, max_radius, depth)`: the filter, on `image` `(H, W, C)` and
      `radius` `(H, W)` (pixels, already clamped to `max_radius`), returning `(H, W, C)`. It must be
      a pure JAX function of its array arguments (jit, vmap, grad). `depth` (`(H, W)`) is `None`
      unless the method `uses_depth`. A method is called as `method(image, radius, *, max_radius,
      depth=None)`: `__call__`, defined here once (the signature and its types), runs `spread`.

    Options are fields: arrays (a random key) as leaves, Python ints and strings that shape the
    computation as `eqx.field(static=True)`. Checks of the options belong in `__check_init__` or
    `__init__` (`ValueError` naming the option and the fix). A method whose fields are exactly its
    kernel's keyword options passes them on as `**self._options()`. `jaxdof.coc_filter`,
    `jaxdof.render` and `jaxdof.render_batch` take an instance, or a built-in's name (`as_method`:
    `"soft"` is `Soft()`).
    """

    differentiable_in_radius: ClassVar[bool]
    uses_depth: ClassVar[bool] = False
    local: ClassVar[bool] = True

    def prepare(self, radius: np.ndarray, max_radius: float) -> AbstractMethod:
        """Precompute on a concrete radius map `(H, W)` (pixels, clamped to `max_radius`)."""
        del radius, max_radius
        return self

    def __call__(
        self, image: ChannelsLast, radius: Radius, *, max_radius: float, depth: Depth | None = None
    ) -> ChannelsLast:
        """Spread every pixel of `image` over its circle of radius `radius` (pixels): `spread`, with
        `depth` passed on only to a method that `uses_depth` (`None` to any other)."""
        depth = depth if self.uses_depth else None
        return self.spread(image, radius, max_radius=max_radius, depth=depth)

    @abc.abstractmethod
    def spread(
        self, image: ChannelsLast, radius: Radius, *, max_radius: float, depth: Depth | None
    ) -> ChannelsLast:
        """The filter itself (see the class docstring); called by `__call__`."""

    def _options(self) -> dict[str, Any]:
        """The method's fields by name: its kernel's keyword options, each named once (a field)."""
        return {field.name: getattr(self, field.name) for field in dataclasses.fields(self)}
