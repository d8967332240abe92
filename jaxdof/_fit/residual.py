r"""The residual function handed to optimistix, with a JVP rule that materialises the Jacobian.

$$r(y) = \sqrt{w} \odot \left( P_t\big(\mathrm{model}(I, Z, \mathrm{lens}_t(y))\big) - T_t \right)$$

flattened over targets `t` and pixels, with `lens_t(y)` the coordinates of `layout.py` and `P_t`
what the camera adds, its fitted nuisances and the encoding (`photo.camera`).
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, Float

from .._filters.spans import in_jacobian
from .._lens import ThinLens
from . import layout as coords
from .forward import AbstractForwardModel
from .jpeg import JpegGrid
from .layout import _Arr, _Layout
from .photo import camera


class _NoRender(AbstractForwardModel):
    """The forward model of a `_Model` that only maps `y` to lenses and nuisances
    (`_Model.statistical`): it renders nothing."""

    differentiable_in_lens: bool = eqx.field(default=False, static=True)

    def __call__(self, image, depth, lens, *, max_radius):
        raise TypeError("a statistical model renders nothing (`_Model.statistical`)")


class _Model(eqx.Module):
    r"""The residual function for optimistix, and the maps between `y` and lenses.

    `y` holds `3 T` lens coordinates, field-major (`y[j T + t]` is field `j` of target `t`:
    `logit(f / fcap)`, `log N`, and the focus `y` with `fcap / (d_f - f) = |y| + 1e-12`, 0 at
    infinity; see `layout.py`), then `T` slots per parameter of each fitted nuisance
    (`photo.NUISANCES`, in that order). With `luma`, the photos are compared in their sRGB luma,
    and with `jpeg` in its blocks' DCT to within half a quantisation step (`jpeg.JpegGrid`).
    A shared field reads slot `j T` for every target; fixed fields read `base`; unread slots have
    zero Jacobian columns: they are neither differentiated (`n_live`) nor in the statistics.

    `forward` is the forward model (a pytree: its arrays are traced, the rest is static), so the
    compiled solve is keyed on it.
    """

    n_targets: int = eqx.field(static=True)
    max_radius: float = eqx.field(static=True)
    nuisances: tuple[str, ...] = eqx.field(static=True)
    forward: AbstractForwardModel
    # The number of live slots (`_Layout.live`); None: differentiate every slot.
    n_live: int | None = eqx.field(static=True, default=None)
    luma: bool = eqx.field(static=True, default=False)
    # A camera JPEG's blocks and steps (`jpeg.py`): the luma compared in the file's terms, on
    # the photo (or tile mosaic) the grid belongs to; a pyramid level's: pixel by pixel.
    jpeg: JpegGrid | None = eqx.field(static=True, default=None)

    def natural(self, y: Float[Array, " P"], layout: _Layout) -> Float[Array, "t 4"]:
        """Lens fields `(f, N, d_f, pitch)` of every target."""
        return coords.natural(y, layout)

    def exposure_params(self, y: Float[Array, " P"]) -> tuple[Array, Array]:
        """Gain and offset per target (ones and zeros without the exposure nuisance)."""
        return coords.exposure_params(y, self.n_targets, self.nuisances)

    def nuisance_params(self, y: Float[Array, " P"]) -> dict[str, Array]:
        """Every nuisance parameter per target (the unfitted ones at their null)."""
        return coords.nuisance_params(y, self.n_targets, self.nuisances)

    def pack(self, params: Float[_Arr, "*s t 4"], layout: _Layout) -> Float[_Arr, "*s P"]:
        """Inverse of `natural` (numpy or jax; a leading batch of starts allowed)."""
        return coords.pack(params, layout, self.nuisances)

    def theta(self, y: Float[Array, " P"], layout: _Layout) -> Float[Array, " P"]:
        """The value of every slot in its statistical units (m, f-number, focus power in
        diopters, gain, offset)."""
        return coords.theta(y, layout, self.nuisances)

    def lenses(self, y: Float[Array, " P"], layout: _Layout) -> ThinLens:
        """The lens of every target, a `ThinLens` with fields `(T,)`."""
        return coords.lenses(y, layout)

    def statistical(self) -> _Model:
        """This model without its forward model and window: what the statistics need (the maps
        from `y` to lenses and nuisances), so that they compile once for every forward model and
        window of one free set (the photo's say refits with another render)."""
        return _Model(self.n_targets, 0.0, self.nuisances, _NoRender(), self.n_live, self.luma)

    def render(self, y, args) -> Array:
        """The forward model's renders `(T, H, W[, C])` at the lenses of `y` (no nuisance)."""
        image, depth, _, _, layout = args

        def one(lens):
            return self.forward(image, depth, lens, max_radius=self.max_radius)

        return jax.vmap(one)(self.lenses(y, layout))

    def rounding(self, args) -> Array:
        """Each residual's own rounding `(n,)`, `eps |sqrt(w) T|` in the data's precision: a render
        rounds at about the size of the target it matches. The default solver stops where a step's
        predicted decrease is under the rounding this puts on the loss (`lm.loss_rounding`)."""
        _, _, targets, sqrt_w, _ = args
        eps = float(jnp.finfo(targets.dtype).eps)  # a Python float: no float32 x float64 mix
        return (eps * jnp.abs(jnp.broadcast_to(sqrt_w, targets.shape) * targets)).reshape(-1)

    def __call__(self, y, args) -> Array:
        """Weighted residuals, flattened: `sqrt(w) * (model - target)`.

        A non-finite `y` (a failed step) gives NaN residuals, which the solver rejects, rather than
        a lens that the render's run-time checks would refuse. Differentiating this with respect
        to `y` builds the whole Jacobian once per point (see `_residuals_jvp`).
        """
        dynamic, static = eqx.partition(self, eqx.is_array)
        return _residuals(static, dynamic, y, args)

    def residuals(self, y, args) -> Array:
        """`__call__` without the Jacobian-materialising JVP rule (the plain forward model)."""
        return self.from_render(self.render(y.astype(args[2].dtype), args), y, args)

    def from_render(self, raw, y, args) -> Array:
        """`residuals` from the renders `raw` at `y`'s lenses: what the camera adds, less the
        targets, weighted."""
        _, _, targets, sqrt_w, layout = args
        # The solver may carry `y` in a wider dtype than the data (see `solve._solve`): the model
        # runs in the data's precision and the residuals are handed back in the solver's dtype.
        y_dtype = y.dtype
        y = y.astype(targets.dtype)
        pred = camera(raw, self.nuisance_params(y), self.nuisances, self.luma, layout.frame_vu)
        grid = self.jpeg
        if grid is not None and targets.shape[1:3] == grid.shape:
            r = grid.residual(pred, targets, sqrt_w).reshape(-1)
        else:
            r = ((pred - targets) * sqrt_w).reshape(-1)
        return jnp.where(jnp.all(jnp.isfinite(y)), r, jnp.nan).astype(y_dtype)

    def live(self, y, args) -> Array:
        """The slots of `y` that some field reads (`_Layout.live`; every slot without `n_live`):
        the others' Jacobian columns are 0 by construction."""
        return jnp.arange(y.shape[0]) if self.n_live is None else jnp.asarray(args[-1].live)

    def jacobian(self, y, args) -> tuple[Array, Array]:
        """The residuals and their Jacobian `(n, p)` in the live slots (`_Layout.live`), as `p`
        JVPs that share one primal evaluation. The render depends on the lens slots alone, so
        it is differentiated along those only; the nuisances' columns (which come after them,
        `layout._Spec`) go through what the camera adds to the one render: a chart fit with
        exposure and illumination renders 2 tangents, not 6."""
        basis = jax.nn.one_hot(self.live(y, args), y.shape[0], dtype=y.dtype)
        n_lens = basis.shape[0] - self.n_targets * len(coords.nuisance_names(self.nuisances))
        if n_lens == basis.shape[0]:
            column = lambda t: jax.jvp(lambda y_: self.residuals(y_, args), (y,), (t,))  # noqa: E731
            with in_jacobian():  # the soft filter's crossover for Jacobians
                return jax.vmap(column, out_axes=(None, 1))(basis)
        render = lambda y_: self.render(y_.astype(args[2].dtype), args)  # noqa: E731
        with in_jacobian():
            raw, d_raw = jax.vmap(lambda t: jax.jvp(render, (y,), (t,)), out_axes=(None, 0))(
                basis[:n_lens]
            )
        camera_jvp = lambda t, d: jax.jvp(  # noqa: E731
            lambda raw_, y_: self.from_render(raw_, y_, args), (raw, y), (d, t)
        )
        r, lens = jax.vmap(camera_jvp, out_axes=(None, 1))(basis[:n_lens], d_raw)
        nuisance = jax.vmap(
            lambda t: jax.jvp(lambda y_: self.from_render(raw, y_, args), (y,), (t,))[1],
            out_axes=1,
        )(basis[n_lens:])
        return r, jnp.concatenate([lens, nuisance], axis=1)


# The residual with a JVP rule that materialises the Jacobian. Optimistix's Gauss-Newton family
# linearises the residual at every trial point and then applies the linearisation several times per
# step (the damped solve materialises it column by column, the trust-region test applies it again),
# each application re-running the render's tangent computation. With `P` (a handful of) parameters
# and many residuals it is cheaper to build the `(n, P)` Jacobian once per point, as `P` JVPs that
# share one primal evaluation, and let every later application be a small matrix product. The
# derivative is the same; only where it is evaluated changes. Measured on a 24 x 24 scene of
# `fits/recover.py` (two free fields, 20 LM steps either way): 1.5-1.9x less time per solve.
#
# The model's arrays (`dynamic`, e.g. a forward model's key or kernel) are primal inputs like the
# data, so that they may be traced; the rest of it (`static`) is the non-differentiable argument.
@partial(jax.custom_jvp, nondiff_argnums=(0,))
def _residuals(static: _Model, dynamic: _Model, y, args):
    return eqx.combine(dynamic, static).residuals(y, args)


def _residuals_jvp(static: _Model, primals, tangents):
    dynamic, y, args = primals
    dynamic_dot, y_dot, args_dot = tangents
    model = eqx.combine(dynamic, static)
    if isinstance(y_dot, SymbolicZero):  # differentiated with respect to the data only
        r = model.residuals(y, args)
        out = jnp.zeros_like(r)
    else:
        r, jac = model.jacobian(y, args)
        out = jac @ y_dot[model.live(y, args)]
    # Derivatives with respect to the data (e.g. implicit differentiation of a fit with respect to
    # the image) or the model's arrays are rare: a plain JVP through the render, only for the
    # inputs that carry one.
    is_zero = lambda t: isinstance(t, SymbolicZero)  # noqa: E731
    a_leaves, a_def = jax.tree_util.tree_flatten((dynamic, args))
    d_leaves = jax.tree_util.tree_leaves((dynamic_dot, args_dot), is_leaf=is_zero)
    live = [i for i, t in enumerate(d_leaves) if not is_zero(t)]
    if live:

        def of_data(*xs):
            leaves = list(a_leaves)
            for i, x in zip(live, xs):
                leaves[i] = x
            dynamic_, args_ = jax.tree_util.tree_unflatten(a_def, leaves)
            return eqx.combine(dynamic_, static).residuals(y, args_)

        _, extra = jax.jvp(
            of_data, tuple(a_leaves[i] for i in live), tuple(d_leaves[i] for i in live)
        )
        out = out + extra
    return r, out


_residuals.defjvp(_residuals_jvp, symbolic_zeros=True)
