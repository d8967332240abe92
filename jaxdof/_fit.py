r"""Lens calibration: recover focal length, f-number and focus distance from defocused photos.

`fit_lens` solves the nonlinear least-squares problem

$$\min_\theta \sum_t \sum_p w_p \left( g_t\,\mathrm{render}(I, Z, \mathrm{lens}_t(\theta))_p + o_t
  - T_{t,p} \right)^2$$

over the free lens fields `theta` (and, optionally, an exposure gain `g_t` and offset `o_t` per
target), with an optimistix least-squares solver (Levenberg-Marquardt by default), from a few
starting points spread over the scene's depth range. It is the only module that imports optimistix.

**What a single image can determine.** The circle of confusion of a point at depth `d` is
`r = K |1 - d_f / d|` pixels with `K = f^2 / (2 N (d_f - f)) / p` (`jaxdof.coc_radius`), so one
photo determines `K` and `d_f` but not `f` and `N` separately: any `(f, N)` with the same `K` (and
`d_f`) renders the same image. `fit_lens` finds such a degeneracy from the rank of the
column-scaled Jacobian at the solution and refuses it (`ValueError`) unless asked not to. A focus
bracket (several photos with different focus distances through the same `f` and `N`) separates
them: `K_t \propto 1 / (d_{f,t} - f)` varies across the bracket in a way that depends on `f`.

**Coordinates.** The solver works in unconstrained coordinates, so every iterate is a physical lens:
`log N`, `log f` (or `logit(f / d_f)` when the focus distance is held fixed, keeping `f < d_f`), and
`log(d_f - f)` for the focus distance. Results and standard errors are mapped back to each field's
own units (metres, or dimensionless for `N`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._filters.coc_filter import DIFFERENTIABLE_IN_RADIUS
from ._filters.common import is_concrete
from ._lens import ThinLens
from ._render import _check_downsample, render


LENS_FIELDS = ("focal_length", "f_number", "focus_distance")
_ALL_FIELDS = ("focal_length", "f_number", "focus_distance", "pixel_pitch")
_UNITS = {"focal_length": "m", "f_number": "", "focus_distance": "m", "gain": "", "offset": ""}

# Status codes of a fit (FitResult.status).
CONVERGED = 0
MAX_STEPS = 1
SOLVER_FAILED = 2
DEAD_ZONE = 3
DEGENERATE = 4
WINDOW = 5
AMBIGUOUS = 6
_STATUS_TEXT = {
    CONVERGED: "converged",
    MAX_STEPS: "did not converge within max_steps",
    SOLVER_FAILED: "the solver failed (non-finite values or a failed linear solve)",
    DEAD_ZONE: "every circle of confusion is under half a pixel: the render does not depend on the lens",
    DEGENERATE: "the free parameters are not all determined by the data (rank-deficient Jacobian)",
    WINDOW: "the fitted circles exceed the filter window (max_radius): the model was clamped",
    AMBIGUOUS: "several distinct lenses fit the data equally well (e.g. the near/far ambiguity)",
}


def _default_tol(dtype) -> float:
    # Steps in the log coordinates below these are at the rounding floor of the residual: in
    # float32 the iterates jitter at ~1e-6 (a residual of ~1e-7 per pixel moved by a Jacobian of
    # order 1), so 1e-5 terminates reliably while leaving errors far under 1e-3; float64 goes to 1e-8.
    return 1e-5 if jnp.dtype(dtype) == jnp.float32 else 1e-8


# --------------------------------------------------------------------------------------------
# The model: parameter vector <-> lenses, and the residual.
# --------------------------------------------------------------------------------------------

# Unconstrained coordinates are clipped to this range before they are mapped to a lens, so that no
# iterate overflows to an infinite or zero field (exp(40) ~ 2e17 is far outside any real lens).
_CLIP = 40.0


class _Layout(eqx.Module):
    """Which entry of the parameter vector drives which lens field of which target: data, not code.

    Keeping this in arrays (passed through `args`) means every free/shared choice with the same
    number of targets, number of free parameters, image shape and window runs the same compiled
    solve.

    - `base`: `(T, 4)` init values of `(f, N, d_f, pitch)`, used for the fields that are not free.
    - `src`: `(T, 3)` index into `y` of the coordinate of `(f, N, d_f)` for each target.
    - `use`: `(T, 3)` whether that field is free (else `base` is used).
    - `fcap`: `(T,)` upper bound on the focal length (metres): just under the nearest depth and,
      with the focus distance fixed, under the focus distance.
    - `live`: `(p,)` the slots of `y` that some field reads (the free parameters): the only
      Jacobian columns that are not zero by construction, so the only ones computed.
    """

    # numpy arrays in `fit_lens` (built without device calls), jax arrays under jit.
    base: Float[ArrayLike, "t 4"]
    src: Int[ArrayLike, "t 3"]
    use: Bool[ArrayLike, "t 3"]
    fcap: Float[ArrayLike, " t"]
    live: Int[ArrayLike, " p"]


class _Model(eqx.Module):
    r"""The residual function for optimistix, and the maps between `y` and lenses.

    `y` holds `3 T` lens coordinates, field-major (`y[j T + t]` is field `j` of target `t`:
    `logit(f / fcap)`, `log N`, `log(d_f - f)`), then with `exposure` `T` gains and `T` offsets.
    A shared field reads slot `j T` for every target; fixed fields read `base`; unread slots have
    zero Jacobian columns: they are neither differentiated (`n_live`) nor in the statistics.
    """

    n_targets: int = eqx.field(static=True)
    max_radius: float = eqx.field(static=True)
    exposure: bool = eqx.field(static=True)
    method: str = eqx.field(static=True, default="soft")
    # The number of live slots (`_Layout.live`); None: differentiate every slot.
    n_live: int | None = eqx.field(static=True, default=None)
    footprint: bool = eqx.field(static=True, default=False)
    # The image and depth are `downsample` times the targets' resolution (`render`'s).
    downsample: int = eqx.field(static=True, default=1)

    def natural(self, y: Float[Array, " P"], layout: _Layout) -> Float[Array, "t 4"]:
        """Lens fields `(f, N, d_f, pitch)` of every target."""
        y = jnp.where(jnp.isfinite(y), jnp.clip(y, -_CLIP, _CLIP), 0)
        u = y[layout.src]
        base = layout.base
        f = jnp.where(layout.use[:, 0], layout.fcap * jax.nn.sigmoid(u[:, 0]), base[:, 0])
        n = jnp.where(layout.use[:, 1], jnp.exp(u[:, 1]), base[:, 1])
        d_f = jnp.where(layout.use[:, 2], f + jnp.exp(u[:, 2]), base[:, 2])
        return jnp.stack([f, n, d_f, base[:, 3]], axis=-1)

    def exposure_params(self, y: Float[Array, " P"]) -> tuple[Array, Array]:
        """Gain and offset per target (ones and zeros without `exposure`)."""
        t = self.n_targets
        if not self.exposure:
            return jnp.ones(t, y.dtype), jnp.zeros(t, y.dtype)
        return y[3 * t : 4 * t], y[4 * t : 5 * t]

    def pack(self, params: Float[ArrayLike, "*s t 4"], layout: _Layout) -> Float[ArrayLike, "*s P"]:
        """Inverse of `natural` (a shared field takes the first target's value).

        Works on numpy arrays too (in numpy: `fit_lens` packs its starts without device calls),
        and on a leading batch of starts.
        """
        xp = np if isinstance(params, np.ndarray) else jnp
        f, n, d_f = params[..., 0], params[..., 1], params[..., 2]
        coords = [xp.log(f) - xp.log(layout.fcap - f), xp.log(n), xp.log(d_f - f)]
        if self.exposure:
            coords += [xp.ones_like(f), xp.zeros_like(f)]
        return xp.concatenate(coords, axis=-1)

    def theta(self, y: Float[Array, " P"], layout: _Layout) -> Float[Array, " P"]:
        """The value of every slot in its field's own units (m, f-number, gain, offset)."""
        p = self.natural(y, layout)
        out = [p[:, 0], p[:, 1], p[:, 2]]
        if self.exposure:
            out += list(self.exposure_params(y))
        return jnp.concatenate(out)

    def lenses(self, y, layout: _Layout) -> ThinLens:
        p = self.natural(y, layout)
        return ThinLens(p[:, 0], p[:, 1], p[:, 2], p[:, 3])

    def predict(self, y, args) -> Array:
        """Rendered targets `(T, H, W[, C])` for parameters `y`."""
        image, depth, _, _, layout = args
        lenses = self.lenses(y, layout)
        gain, offset = self.exposure_params(y)

        def one(lens, g, o):
            return (
                g
                * render(
                    image,
                    depth,
                    lens,
                    method=self.method,
                    max_radius=self.max_radius,
                    footprint=self.footprint,
                    downsample=self.downsample,
                )
                + o
            )

        return jax.vmap(one)(lenses, gain, offset)

    def __call__(self, y, args) -> Array:
        """Weighted residuals, flattened: `sqrt(w) * (model - target)`.

        A non-finite `y` (a failed step) gives NaN residuals, which the solver rejects, rather than
        a lens that the render's run-time checks would refuse. Differentiating this with respect
        to `y` builds the whole Jacobian once per point (see `_residuals_jvp`).
        """
        return _residuals(self, y, args)

    def residuals(self, y, args) -> Array:
        """`__call__` without the Jacobian-materialising JVP rule (the plain forward model)."""
        _, _, targets, sqrt_w, _ = args
        # The solver may carry `y` in a wider dtype than the data (see `_solve`): the model runs
        # in the data's precision and the residuals are handed back in the solver's dtype.
        y_dtype = y.dtype
        y = y.astype(targets.dtype)
        r = ((self.predict(y, args) - targets) * sqrt_w).reshape(-1)
        return jnp.where(jnp.all(jnp.isfinite(y)), r, jnp.nan).astype(y_dtype)


# The residual with a JVP rule that materialises the Jacobian. Optimistix's Gauss-Newton family
# linearises the residual at every trial point and then applies the linearisation several times per
# step (the damped solve materialises it column by column, the trust-region test applies it again),
# each application re-running the render's tangent computation. With `P` (a handful of) parameters
# and many residuals it is cheaper to build the `(n, P)` Jacobian once per point, as `P` JVPs that
# share one primal evaluation, and let every later application be a small matrix product. The
# derivative is the same; only where it is evaluated changes. Measured on a 24 x 24 scene of
# `fits/recover.py` (two free fields, 20 LM steps either way): 1.5-1.9x less time per solve.
@partial(jax.custom_jvp, nondiff_argnums=(0,))
def _residuals(model: _Model, y, args):
    return model.residuals(y, args)


def _residuals_jvp(model: _Model, primals, tangents):
    y, args = primals
    y_dot, args_dot = tangents
    # Only the live slots: the others are read by no field, so their columns are exactly zero.
    live = jnp.arange(y.shape[0]) if model.n_live is None else jnp.asarray(args[-1].live)
    basis = jax.nn.one_hot(live, y.shape[0], dtype=y.dtype)

    def column(t):
        return jax.jvp(lambda y_: model.residuals(y_, args), (y,), (t,))

    if isinstance(y_dot, SymbolicZero):  # differentiated with respect to the data only
        r = model.residuals(y, args)
        out = jnp.zeros_like(r)
    else:
        r, jac = jax.vmap(column, out_axes=(None, 1))(basis)
        out = jac @ y_dot[live]
    # Derivatives with respect to the data (e.g. implicit differentiation of a fit with respect to
    # the image) are rare: a plain JVP through the render, only for the inputs that carry one.
    is_zero = lambda t: isinstance(t, SymbolicZero)  # noqa: E731
    a_leaves, a_def = jax.tree_util.tree_flatten(args)
    d_leaves = jax.tree_util.tree_leaves(args_dot, is_leaf=is_zero)
    live = [i for i, t in enumerate(d_leaves) if not is_zero(t)]
    if live:

        def of_data(*xs):
            leaves = list(a_leaves)
            for i, x in zip(live, xs):
                leaves[i] = x
            return model.residuals(y, jax.tree_util.tree_unflatten(a_def, leaves))

        _, extra = jax.jvp(
            of_data, tuple(a_leaves[i] for i in live), tuple(d_leaves[i] for i in live)
        )
        out = out + extra
    return r, out


_residuals.defjvp(_residuals_jvp, symbolic_zeros=True)


class _Spec:
    """Python-side description of a fit: free/shared fields, targets, exposure -> slots and names."""

    def __init__(self, free, shared, n_targets: int, exposure: bool):
        self.free, self.shared, self.n_targets, self.exposure = free, shared, n_targets, exposure
        used, names = [], []
        multi = n_targets > 1
        for j, name in enumerate(LENS_FIELDS):
            if name not in free:
                continue
            ts = [0] if name in shared else range(n_targets)
            for t in ts:
                used.append(j * n_targets + t)
                names.append(name if (name in shared or not multi) else f"{name}[{t}]")
        if exposure:
            for k, name in ((3, "gain"), (4, "offset")):
                for t in range(n_targets):
                    used.append(k * n_targets + t)
                    names.append(f"{name}[{t}]" if multi else name)
        self.used, self.names = tuple(used), tuple(names)

    # A spec is static data of the compiled fit: equal specs must share one compilation.
    def _key(self):
        return (self.free, self.shared, self.n_targets, self.exposure)

    def __eq__(self, other):
        return isinstance(other, _Spec) and self._key() == other._key()

    def __hash__(self):
        return hash(self._key())

    def layout(self, base, depth) -> _Layout:
        """The `_Layout` of this fit: in numpy for numpy `base` and `depth` (no device calls),
        else in jax (works on tracers)."""
        xp = np if isinstance(base, np.ndarray) and isinstance(depth, np.ndarray) else jnp
        t = self.n_targets
        shared = np.array([n in self.shared for n in LENS_FIELDS])
        use = np.broadcast_to(np.array([n in self.free for n in LENS_FIELDS]), (t, 3))
        src = np.arange(3)[None, :] * t + np.where(shared[None, :], 0, np.arange(t)[:, None])
        cap = xp.broadcast_to(xp.min(depth).astype(base.dtype), (t,))
        if "focus_distance" not in self.free:
            cap = xp.minimum(cap, base[:, 2])
        # Everything at infinity and the focus distance free: no bound from the scene.
        cap = xp.where(xp.isfinite(cap), cap, 1e3 * base[:, 0])
        # Just under the bound: a focal length equal to the nearest depth is not a lens for it.
        cap = (cap * (1 - 1e-3)).astype(base.dtype)
        return _Layout(
            base=base,
            src=xp.asarray(src, np.int32),
            use=xp.asarray(use),
            fcap=cap,
            live=xp.asarray(np.array(self.used, np.int32)),
        )


# --------------------------------------------------------------------------------------------
# The result.
# --------------------------------------------------------------------------------------------


class FitResult(eqx.Module):
    """The outcome of `jaxdof.fit_lens`.

    **Fields:**

    - `lenses`: the fitted `ThinLens`, one per target (fields of shape `(T,)`).
    - `stderr`: standard error of each free field in its own units (metres for lengths, plain
      number for the f-number; `gain`, `offset` with `exposure=True`): a scalar for a single
      target, else an array `(T,)` (a shared field repeats its value).
      `inf` marks a field that the data do not determine (only with `allow_degenerate=True`).
    - `covariance`: covariance of the free parameters in their own units, `(p, p)`, in the order of
      `names` (e.g. `("f_number", "focus_distance")`, or `"focus_distance[1]"` per target).
    - `names`: the name of each row of `covariance`.
    - `gain`, `offset`: exposure per target (1 and 0 unless `exposure=True`), `(T,)`.
    - `loss`: `0.5 * sum(residual^2)` at the solution.
    - `sigma`: the residual standard deviation `sqrt(SSR / (n - p))` used to scale `covariance`.
    - `num_steps`: solver steps taken by the chosen start.
    - `condition`: condition number of the column-scaled Jacobian at the solution.
    - `status`: an integer code (0 converged; see `message`).
    - `success`: `True` when the fit converged to a determined, unambiguous lens.
    - `message`: what happened, in words.
    - `max_radius`: the filter window (pixels) the fit used (at full resolution).
    - `levels`: pyramid levels `fit_lens` solved on (1: full resolution only; see its `pyramid`).

    `lens` is the first target's lens; `summary()` formats everything as a table.
    """

    lenses: ThinLens
    stderr: dict[str, Array]
    covariance: Float[Array, "p p"]
    gain: Float[Array, " t"]
    offset: Float[Array, " t"]
    loss: Float[Array, ""]
    sigma: Float[Array, ""]
    num_steps: Int[Array, ""]
    condition: Float[Array, ""]
    status: Int[Array, ""]
    success: Bool[Array, ""]
    names: tuple[str, ...] = eqx.field(static=True)
    message: str = eqx.field(static=True, default="")
    max_radius: float = eqx.field(static=True, default=0.0)
    levels: int = eqx.field(static=True, default=1)

    @property
    def lens(self) -> ThinLens:
        """The first target's lens."""
        return jax.tree_util.tree_map(lambda x: x[0], self.lenses)

    def summary(self) -> str:
        """A human-readable table of the fitted lens(es), standard errors and fit statistics."""
        lines = [f"fit_lens: {'success' if bool(self.success) else 'FAILED'}: {self.message}"]
        n_t = int(np.shape(self.lenses.focal_length)[0])
        for t in range(n_t):
            lens = ThinLens(*(np.asarray(getattr(self.lenses, n))[t] for n in _ALL_FIELDS))
            head = f"target {t}:" if n_t > 1 else "lens:"
            lines.append(head)
            for name in LENS_FIELDS:
                value = float(getattr(lens, name))
                if name in self.stderr:
                    se = float(np.reshape(np.asarray(self.stderr[name]), -1)[t if n_t > 1 else 0])
                    lines.append(f"  {name:15s} {value:.6g} +- {se:.2g} {_UNITS[name]}".rstrip())
                else:
                    lines.append(f"  {name:15s} {value:.6g} {_UNITS[name]} (fixed)".rstrip())
            k = float(lens.blur_scale)
            lines.append(f"  {'K (blur scale)':15s} {k:.6g} px")
        for name in ("gain", "offset"):
            if name in self.stderr:
                vals = np.atleast_1d(np.asarray(getattr(self, name)))
                ses = np.atleast_1d(np.asarray(self.stderr[name]))
                lines.append(
                    f"{name}: " + ", ".join(f"{v:.5g} +- {s:.2g}" for v, s in zip(vals, ses))
                )
        lines.append(
            f"loss {float(self.loss):.4g}, residual sigma {float(self.sigma):.3g}, "
            f"steps {int(self.num_steps)}, condition {float(self.condition):.3g}, "
            f"window {self.max_radius:g} px"
        )
        return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# The pure solve (jit/vmap-able) and its statistics.
# --------------------------------------------------------------------------------------------


def _rank_tol(dtype) -> float:
    # Relative singular-value threshold of the column-scaled Jacobian. An exact degeneracy (f and N
    # from one photo) leaves s_min / s_max at the rounding level of the Jacobian: measured 2.2e-16
    # in float64 and 1.9e-7 in float32 (32x32 slanted-plane scene). Determined problems stay far
    # above: 0.65 for (N, d_f) from one photo, 1.5e-3 for f and N from a three-photo focus bracket
    # (the worst conditioned case we support). The threshold sits between: ~15x the float32
    # rounding level, and sqrt(eps) in float64.
    return 3e-6 if jnp.dtype(dtype) == jnp.float32 else 1.5e-8


def _statistics(residual, jac, g, theta, n, used: tuple[int, ...]) -> dict[str, Array]:
    """Loss, residual sigma, covariance in natural units, conditioning: from the full Jacobian.

    `jac` `(n_res, P)` is d residual / d y, `g` `(P, P)` is d theta / d y, `theta` `(P,)` the
    slots' values in their own units; `used` are the slots that are free. Works on tracers (`solve_lens` under vmap) and on concrete arrays.
    """
    idx = jnp.asarray(used)
    jac = jac[:, idx]
    g = g[idx][:, idx]
    dtype = residual.dtype
    p = len(used)
    ssr = jnp.sum(residual * residual)
    sigma2 = ssr / jnp.maximum(n - p, 1)
    scale = jnp.sqrt(jnp.sum(jac * jac, axis=0))
    safe = jnp.where(scale > 0, scale, 1)
    # Column scaling makes the rank test independent of the units of each coordinate.
    _, s, vt = jnp.linalg.svd(jac / safe[None, :], full_matrices=False)
    good = s > _rank_tol(dtype) * s[0]
    inv_s2 = jnp.where(good, 1 / jnp.where(good, s * s, 1), 0)
    cov_y = sigma2 * ((vt.T * inv_s2[None, :]) @ vt) / safe[:, None] / safe[None, :]
    cov = g @ cov_y @ g.T  # chain rule: y (log / logit coordinates) -> each field's own units
    # A parameter that moves along a null direction (or has a zero column) is undetermined. The
    # test is in each field's own units: with f and N free from one photo, the null direction moves
    # log(d_f - f) too, yet d_f itself stays put and keeps its (estimable) standard error.
    v_null = jnp.where(good[:, None], 0, vt).T / safe[:, None]  # (p, k) null vectors in y
    moved = jnp.abs(g @ v_null) / jnp.maximum(jnp.abs(theta[idx]), jnp.finfo(dtype).tiny)[:, None]
    moved = jnp.max(moved, axis=1)
    undetermined = (moved > 1e-3 * jnp.max(moved)) & ~jnp.all(good) | (scale == 0)
    var = jnp.where(undetermined, jnp.inf, jnp.diag(cov))
    smin = s[-1]
    condition = jnp.where(smin > 0, s[0] / jnp.where(smin > 0, smin, 1), jnp.inf)
    return dict(
        loss=0.5 * ssr,
        sigma=jnp.sqrt(sigma2),
        covariance=cov,
        variance=var,
        condition=condition,
        degenerate=~jnp.all(good) | jnp.any(scale == 0),
        jac_zero=jnp.all(scale == 0),
    )


def _solve(model: _Model, solver, y0, args, max_steps: int):
    """One least-squares solve from `y0`: solution, status, steps, residual and slot values. Pure."""
    # optimistix 0.1.0's Levenberg-Marquardt builds its damping term in JAX's default float dtype,
    # so float32 parameters under `jax_enable_x64` fail its structure check ("Vector and operator
    # structures do not match"). Carrying `y` in the default dtype and casting it to the data's
    # dtype inside the residual avoids that; the model itself runs in the data's precision.
    sol = optx.least_squares(
        model, solver, y0.astype(jnp.result_type(float)), args, max_steps=max_steps, throw=False
    )
    y = sol.value.astype(y0.dtype)
    dtype = args[2].dtype  # the data's
    kept = _solver_point(sol)
    if kept is None:
        residual, jac = model(y, args), None  # in the data's dtype again, since `y` is
    else:
        residual, jac = kept[0].astype(dtype), kept[1].astype(dtype)
    ok = sol.result == optx.RESULTS.successful
    maxed = sol.result == optx.RESULTS.nonlinear_max_steps_reached
    status = jnp.where(ok, CONVERGED, jnp.where(maxed, MAX_STEPS, SOLVER_FAILED))
    status = jnp.where(ok & ~jnp.all(jnp.isfinite(residual)), SOLVER_FAILED, status)
    return y, status, sol.stats["num_steps"], residual, model.theta(y, args[-1]), jac


def _solver_point(sol):
    """The residual and Jacobian at the solution, as the solver last evaluated them, or None.

    The Gauss-Newton family (Levenberg-Marquardt, Dogleg, Gauss-Newton) keeps the residual and
    the linearisation at its last accepted point, which is the returned solution; with the JVP
    rule of `_residuals` that linearisation is the materialised Jacobian times a vector, so reading
    it back as a matrix costs `P` small products instead of a render and `P` tangent passes (a
    tenth to a third of a whole fit, depending on its number of steps). Other solvers: None, and
    the caller evaluates both.
    """
    f_info = getattr(sol.state, "f_info", None)
    residual = getattr(f_info, "residual", None)
    op = getattr(f_info, "jac", None)
    if not isinstance(op, lx.AbstractLinearOperator) or not isinstance(residual, jax.Array):
        return None
    return residual, op.as_matrix()


def _jacobians(model: _Model, y, args, jac=None):
    """d residual / d y `(n, P)` by forward mode (P passes; few parameters, many residuals),
    unless given, and d theta / d y `(P, P)`."""
    if jac is None:
        jac = jax.jacfwd(model)(y, args).astype(args[2].dtype)
    return jac, jax.jacfwd(model.theta)(y, args[-1])


def _n_residuals(targets, sqrt_w):
    return jnp.sum(jnp.broadcast_to(sqrt_w, targets.shape) > 0).astype(targets.dtype)


@eqx.filter_jit
def _fit_starts(model: _Model, solver, y0s, args, max_steps: int):
    """The solve of `fit_lens` as one compiled call, shared by the free/shared sets with the same
    number of free parameters.

    Solves from every start at once (vmapped), picks the best (converged first, then the lowest
    loss), and evaluates the Jacobians there. The free set is data (`args[-1]`, the layout), not
    part of the compiled code; `_finish` (small, compiled per free set) does the statistics.
    """
    ys, status, num_steps, residual, theta, jacs = eqx.filter_vmap(
        _solve, in_axes=(None, None, 0, None, None)
    )(model, solver, y0s, args, max_steps)
    loss = 0.5 * jnp.sum(jnp.square(residual.astype(jnp.result_type(float))), axis=-1)
    loss = jnp.where(jnp.isfinite(loss), loss, jnp.inf)
    converged = status == CONVERGED
    best = jnp.lexsort((loss, (~converged).astype(jnp.int32)))[0]
    y = ys[best]
    jac, g = _jacobians(model, y, args, None if jacs is None else jacs[best])
    # A non-finite Jacobian at the solution makes its statistics meaningless: a failed solve.
    status_best = jnp.where(jnp.all(jnp.isfinite(jac)), status[best], SOLVER_FAILED)
    solution = (y, status_best, num_steps[best], residual[best], theta[best], jac, g)
    info = dict(
        best=best,
        loss=loss,
        converged=converged,
        theta=theta,
        natural=model.natural(y, args[-1]),
        ys=ys,
    )
    return solution, info


@eqx.filter_jit
def _finish(model: _Model, solution, args, spec: _Spec, single: bool):
    """Statistics, status and the `FitResult` (without its message) at the chosen solution, and
    the few numbers `fit_lens` reads in Python to word the message."""
    y, status, num_steps, residual, theta, jac, g = solution
    _, _, targets, sqrt_w, layout = args
    stats = _statistics(residual, jac, g, theta, _n_residuals(targets, sqrt_w), spec.used)
    result = _assemble(spec, model, y, status, num_steps, stats, layout, single)
    info = dict(
        status=result.status,
        condition=stats["condition"],
        sigma=stats["sigma"],
        variance=stats["variance"],
    )
    return result, info


@eqx.filter_jit
def _solve_one(model: _Model, solver, y0, args, max_steps: int, spec: _Spec, single: bool):
    """`solve_lens`'s numerics: one solve, its Jacobian, statistics and status (one compiled call
    when `solve_lens` runs eagerly; inlined into the caller's trace under jit/vmap)."""
    y, status, num_steps, residual, theta, jac = _solve(model, solver, y0, args, max_steps)
    jac, g = _jacobians(model, y, args, jac)
    status = jnp.where((status == CONVERGED) & ~jnp.all(jnp.isfinite(jac)), SOLVER_FAILED, status)
    _, _, targets, sqrt_w, layout = args
    stats = _statistics(residual, jac, g, theta, _n_residuals(targets, sqrt_w), spec.used)
    return _assemble(spec, model, y, status, num_steps, stats, layout, single)


def _assemble(spec: _Spec, model: _Model, y, status, num_steps, stats, layout, single) -> FitResult:
    """Build a FitResult from the raw solve outputs (works on tracers)."""
    var = stats["variance"]
    stderr: dict[str, Array] = {}
    for name in spec.free + (("gain", "offset") if spec.exposure else ()):
        idx = [i for i, nm in enumerate(spec.names) if nm.split("[")[0] == name]
        se = jnp.sqrt(var[jnp.asarray(idx)])
        se = jnp.broadcast_to(se, (spec.n_targets,))  # a shared field repeats its one value
        stderr[name] = se[0] if single else se
    gain, offset = model.exposure_params(y)
    status = jnp.where(
        (status == CONVERGED) & stats["jac_zero"],
        DEAD_ZONE,
        jnp.where((status == CONVERGED) & stats["degenerate"], DEGENERATE, status),
    )
    return FitResult(
        lenses=model.lenses(y, layout),
        stderr=stderr,
        covariance=stats["covariance"],
        gain=gain,
        offset=offset,
        loss=stats["loss"],
        sigma=stats["sigma"],
        num_steps=jnp.asarray(num_steps),
        condition=stats["condition"],
        status=jnp.asarray(status),
        success=status == CONVERGED,
        names=spec.names,
        message="",
        max_radius=model.max_radius,
    )


# --------------------------------------------------------------------------------------------
# Input handling.
# --------------------------------------------------------------------------------------------


def _check_method(method: str) -> None:
    if not DIFFERENTIABLE_IN_RADIUS.get(method, False):
        usable = tuple(m for m, ok in DIFFERENTIABLE_IN_RADIUS.items() if ok)
        raise ValueError(
            f"{method=} cannot drive a fit: its output has no useful derivative with respect to the "
            f"circle radii (or it is unknown); use one of {usable}"
        )


def _check_names(free, shared) -> tuple[tuple[str, ...], tuple[str, ...]]:
    if isinstance(free, str):
        free = (free,)
    if isinstance(shared, str):
        shared = (shared,)
    free, shared = tuple(free), tuple(shared)
    for name in free:
        if name == "pixel_pitch":
            raise ValueError(
                "pixel_pitch cannot be fitted: it scales every circle of confusion exactly as "
                "1/K does, so it is indistinguishable from the other fields. Set it from the "
                "sensor width (ThinLens.from_sensor) and fit the others."
            )
        if name not in LENS_FIELDS:
            raise ValueError(f"free must name fields among {LENS_FIELDS}, got {name!r}")
    if not free:
        raise ValueError(f"free must name at least one field among {LENS_FIELDS}")
    if len(set(free)) != len(free):
        raise ValueError(f"free names a field twice: {free}")
    for name in shared:
        if name not in free:
            raise ValueError(
                f"shared must be a subset of free (a fixed field keeps its init value in every "
                f"target anyway), got shared={shared}, free={free}"
            )
    free = tuple(n for n in LENS_FIELDS if n in free)
    shared = tuple(n for n in LENS_FIELDS if n in shared)
    return free, shared


def _prepare(image, depth, targets, init, weight, xp=jnp, downsample: int = 1):
    """Validate and convert inputs: arrays in one float dtype, targets `(T, ...)`, base `(T, 4)`.

    With `downsample = s` the targets (and weights) have the photo's shape, the image's with each
    spatial axis divided by `s`.

    `xp=np` (concrete inputs only) does it all in numpy, without a device call per operation; the
    dtypes are jax's either way (`float64` becomes `float32` without `jax_enable_x64`).
    """
    image = _asarray(xp, image)
    depth = _asarray(xp, depth)
    if image.ndim not in (2, 3):
        raise ValueError(f"image must have shape (H, W) or (H, W, C), got {image.shape}")
    if depth.shape != image.shape[:2]:
        raise ValueError(
            f"depth must have the image's (H, W) = {image.shape[:2]}, got {depth.shape}"
        )
    s = _check_downsample(downsample, image.shape)
    # The photo's shape: the image's, or with `downsample` its spatial axes divided by `s`.
    photo = (image.shape[0] // s, image.shape[1] // s, *image.shape[2:])
    of = "the image's shape" if s == 1 else f"the image's shape divided by downsample={s}"
    single = not isinstance(targets, (list, tuple))
    if single:
        targets = _asarray(xp, targets)
        if targets.shape == photo:
            targets = targets[None]
            single = True
        elif targets.shape[1:] == photo:
            single = False
        else:
            raise ValueError(
                f"targets must be one image of {of} {photo}, a sequence of them, or an array "
                f"(T, *{photo}); got shape {targets.shape}"
            )
    else:
        if len(targets) == 0:
            raise ValueError("targets is an empty sequence; pass at least one photo")
        targets = [_asarray(xp, t) for t in targets]
        for i, t in enumerate(targets):
            if t.shape != photo:
                raise ValueError(
                    f"targets[{i}] has shape {t.shape}; every target must have {of} "
                    f"{photo} (same scene, same framing)"
                )
        targets = xp.stack(targets)
    for name, x in (("image", image), ("depth", depth), ("targets", targets)):
        if not jnp.issubdtype(x.dtype, jnp.floating):
            raise ValueError(
                f"{name} must be floating point (linear light / metres), got dtype {x.dtype}; "
                f"convert it first, e.g. {name}.astype(numpy.float32)"
            )
    dtype = jnp.result_type(image.dtype, targets.dtype)
    n_t = targets.shape[0]

    if isinstance(init, ThinLens):
        inits = [init]
    elif isinstance(init, (list, tuple)) and all(isinstance(x, ThinLens) for x in init):
        inits = list(init)
    else:
        raise ValueError(
            f"init must be a ThinLens or a sequence of them, got {type(init).__name__}"
        )
    fields = [[_asarray(xp, getattr(x, name)) for name in _ALL_FIELDS] for x in inits]
    if len(inits) == 1 and all(v.ndim == 1 for v in fields[0]) and fields[0][0].shape[0] == n_t:
        base = xp.stack(fields[0], axis=-1)  # one batched ThinLens with a (T,) axis
    else:
        for x in fields:
            if any(v.ndim != 0 for v in x):
                raise ValueError(
                    "init must be scalar ThinLens(es) (one, or one per target) or one ThinLens "
                    f"with fields of shape (T,) = ({n_t},)"
                )
        base = xp.stack([xp.stack(x) for x in fields])
        if base.shape[0] == 1:
            base = xp.broadcast_to(base, (n_t, 4))
        elif base.shape[0] != n_t:
            raise ValueError(
                f"init has {base.shape[0]} lenses but there are {n_t} targets; pass one or {n_t}"
            )
    base = base.astype(dtype)

    # The weight is always materialised at the targets' shape, so that weighted and unweighted
    # fits share one compiled solve.
    if weight is None:
        sqrt_w = xp.ones(targets.shape, dtype)
    else:
        weight = _asarray(xp, weight)
        shape_ok = weight.shape in (photo[:2], (n_t, *photo[:2]), photo, targets.shape)
        if not shape_ok:
            raise ValueError(
                f"weight must have the targets' pixels: shape (H, W) = {photo[:2]}, (T, H, W), "
                f"{photo} or {targets.shape}; got {weight.shape}"
            )
        if is_concrete(weight):
            w = np.asarray(weight)
            if np.any(~np.isfinite(w)) or np.any(w < 0):
                raise ValueError("weight must be finite and >= 0 (0 masks a pixel out)")
            if not np.any(w > 0):
                raise ValueError("weight is zero everywhere: nothing left to fit")
        colour = targets.ndim == 4
        if weight.shape == photo[:2]:
            weight = weight[None, ..., None] if colour else weight[None]
        elif weight.shape == (n_t, *photo[:2]):
            weight = weight[..., None] if colour else weight
        elif weight.shape == photo:
            weight = weight[None]
        sqrt_w = xp.broadcast_to(xp.sqrt(weight.astype(dtype)), targets.shape)
    return image.astype(dtype), depth.astype(dtype), targets.astype(dtype), sqrt_w, base, single


def _asarray(xp, x):
    """`jnp.asarray`, or its numpy twin keeping jax's dtype rules (`float64` -> `float32` without
    x64), so that both paths of `_prepare` see the same dtypes and say the same in messages."""
    if xp is jnp:
        return jnp.asarray(x)
    x = np.asarray(x)
    return x.astype(jax.dtypes.canonicalize_dtype(x.dtype), copy=False)


def _max_coc(params: np.ndarray, depth: np.ndarray) -> float:
    """Largest circle (pixels) over the finite and infinite depths for each lens row (f, N, d_f, p)."""
    finite = depth[np.isfinite(depth)]
    has_inf = bool(np.any(np.isinf(depth)))
    out = 0.0
    for f, n, d_f, pitch in np.asarray(params, np.float64).reshape(-1, 4):
        k = f * f / (2 * n * (d_f - f) * pitch)
        defocus = np.abs(1 - d_f / finite) if finite.size else np.zeros(1)
        m = np.max(defocus, initial=0.0)
        if has_inf:
            m = max(m, 1.0)
        out = max(out, float(k * m))
    return out


# Windows are rounded up to this grid so that fits of similar scenes share a compiled solve.
_WINDOWS = (2, 3, 4, 5, 6, 8, 10, 12, 16, 20, 24, 32, 40, 48, 64, 80, 96, 128, 160, 192, 256)


def _window(radius: float, cap: float) -> float:
    """A window with headroom (1.5x + 1 px) over `radius`, on the grid, at most `cap`."""
    need = 1.5 * radius + 1.0
    w = next((float(x) for x in _WINDOWS if x >= need), float(math.ceil(need)))
    return float(min(w, max(cap, 2.0)))


# Coarse-to-fine. The automatic pyramid stops coarsening before the image's shorter side drops
# under `_PYRAMID_MIN_SIZE` pixels (a 24 x 24 image still constrains two parameters with hundreds
# of residuals, and its window of a few pixels is not most of the image) or before the init's
# largest circle drops under `_PYRAMID_MIN_CIRCLE` pixels: circles under half a pixel render as the
# identity (the dead zone, zero gradient), and the init may overestimate K by 2x, so the coarsest
# level keeps the init's largest circle at twice the dead zone's edge. An explicit `pyramid` may go
# down to `_PYRAMID_FLOOR` pixels.
_PYRAMID_MIN_SIZE = 24
_PYRAMID_MIN_CIRCLE = 1.0
_PYRAMID_FLOOR = 8
# An alternative coarse solution is refined at the finer levels too (so that the near/far test
# sees it at full resolution) when its coarse loss is within this factor of the best one's: coarse
# losses carry the downsampling's model error, so only a generous margin keeps true ties.
_PYRAMID_TIE = 2.0
# Tolerance of the default solver on the coarse levels (see `fit_lens`).
_COARSE_TOL = 1e-3


def _auto_levels(shape: tuple[int, int], r_init: float) -> int:
    """Number of pyramid levels (1: full resolution only) for an image of `shape` whose init lens
    makes circles up to `r_init` pixels: the most halvings that keep the coarsest image at least
    `_PYRAMID_MIN_SIZE` px on its shorter side and the init's largest circle `_PYRAMID_MIN_CIRCLE` px."""
    levels = 1
    side = min(shape)
    while side // 2 >= _PYRAMID_MIN_SIZE and r_init / 2**levels >= _PYRAMID_MIN_CIRCLE:
        side //= 2
        levels += 1
    return levels


def _check_pyramid(pyramid, shape: tuple[int, int]) -> int | None:
    """Validate an explicit `pyramid` (number of levels); `None` stays `None` (automatic)."""
    if pyramid is None:
        return None
    if isinstance(pyramid, bool) or not isinstance(pyramid, (int, np.integer)) or pyramid < 0:
        raise ValueError(
            f"pyramid must be None (automatic), 0 or 1 (full resolution only) or the number of "
            f"levels >= 2 as a Python int, got {pyramid!r}"
        )
    levels = max(int(pyramid), 1)
    side = min(shape) // 2 ** (levels - 1)
    if side < _PYRAMID_FLOOR:
        most = 1
        while min(shape) // 2**most >= _PYRAMID_FLOOR:
            most += 1
        raise ValueError(
            f"pyramid={pyramid} would shrink the {shape[0]} x {shape[1]} image to {side} px at its "
            f"coarsest level (under {_PYRAMID_FLOOR} px); use at most pyramid={most}, or None to "
            "choose automatically"
        )
    return levels


def _box2(x: np.ndarray, axes: tuple[int, int]) -> np.ndarray:
    """2 x 2 box average over two adjacent `axes` (H, W) of `x`, dropping an odd last row/column."""
    a, b = axes
    h, w = x.shape[a] // 2 * 2, x.shape[b] // 2 * 2
    x = x[(slice(None),) * a + (slice(0, h), slice(0, w))]
    shape = x.shape[:a] + (h // 2, 2, w // 2, 2) + x.shape[b + 1 :]
    return x.reshape(shape).mean(axis=(a + 1, a + 3))


def _downsample(image, depth, targets, sqrt_w, base, s: int = 1):
    """One pyramid level down: halved images, depth and weights; the pixel pitch doubled.

    With `downsample = s` (the image `s` times the targets' resolution) the image and depth are
    first cropped to `s` times the targets' even part, so that the ratio stays `s` exactly.

    - `image`, `targets`: 2 x 2 box averages, in linear light (what a sensor with twice the pitch
      records, up to the blur/averaging order, which the finer levels correct).
    - `depth`: averaged in inverse depth. The signed circle `K (1 - d_f / d)` is affine in `1 / d`,
      so the coarse pixel gets exactly the mean signed circle of its four pixels (then halved, in
      the doubled pitch's units); averaging depth itself would drag a near/far pair toward the
      far side (1 m with infinity would average to infinity). `1 / inf = 0` is kept exact.
    - weights: the harmonic mean of `w = sqrt_w^2`. For inverse-variance weights this is exactly
      (up to a constant factor 4, irrelevant to the minimiser) the inverse variance of the
      averaged target, and a masked pixel (w = 0), whose target value is arbitrary, masks the
      coarse pixel it falls in instead of leaking into its average.
    """
    h, w = targets.shape[1] // 2 * 2 * s, targets.shape[2] // 2 * 2 * s
    image, depth = image[:h, :w], depth[:h, :w]
    inv = _box2(1.0 / depth, (0, 1))  # depth > 0 everywhere (checked), inf -> 0
    with np.errstate(divide="ignore"):
        depth = (1.0 / inv).astype(depth.dtype)
    w = sqrt_w * sqrt_w
    with np.errstate(divide="ignore"):
        inv_w = np.where(w > 0, 1.0 / np.where(w > 0, w, 1), np.inf)
        mean_inv = _box2(inv_w, (1, 2))
        w_c = np.where(np.isfinite(mean_inv), 1.0 / mean_inv, 0.0)
    base = base.copy()
    base[:, 3] = base[:, 3] * 2
    return (
        _box2(image, (0, 1)).astype(image.dtype),
        depth,
        _box2(targets, (1, 2)).astype(targets.dtype),
        np.sqrt(w_c).astype(sqrt_w.dtype),
        base,
    )


def _rows(theta: np.ndarray, base: np.ndarray) -> np.ndarray:
    """Lens rows `(f, N, d_f, pitch)` `(T, 4)` from a solution's slot values `theta` (`_Model.theta`)
    and the pitch of `base`."""
    t = base.shape[0]
    fields = np.asarray(theta, np.float64)[: 3 * t].reshape(3, t).T
    return np.concatenate([fields, np.asarray(base, np.float64)[:, 3:4]], axis=1)


def _next_starts(info, base: np.ndarray, y0s: np.ndarray, spec: _Spec):
    """Starts for the next finer level from a coarse level's solve: its best solution, and the
    lowest-loss converged solution at a distinct lens if its loss is within `_PYRAMID_TIE` of the
    best (a possible near/far tie that only the full-resolution test can settle). A coarse level
    whose best start did not converge hands on every start it was given, best solution first.

    Returns the parameter vectors `(S', P)` and their lens rows `(S', T, 4)` (with the pitch of
    `base`; `_max_coc` of them sizes the next window)."""
    ys, loss, converged, best = info["ys"], info["loss"], info["converged"], int(info["best"])
    theta = np.asarray(info["theta"], np.float64)
    pick = [best]
    if not converged[best]:
        out = np.concatenate([ys[best][None], np.asarray(y0s)], axis=0)
        th = np.concatenate([theta[best][None], theta], axis=0)
        return out, np.stack([_rows(t, base) for t in th])
    used = list(spec.used)
    for i in np.argsort(loss):
        if i == best or not converged[i]:
            continue
        far = np.any(np.abs(theta[i, used] - theta[best, used]) > 1e-3 * np.abs(theta[best, used]))
        if far and loss[i] <= _PYRAMID_TIE * loss[best] + 1e-12 * (1 + loss[best]):
            pick.append(int(i))
        break  # only the lowest-loss alternative; a worse one is no tie
    return ys[pick], np.stack([_rows(theta[i], base) for i in pick])


def _with_verbose(solver, verbose, model: _Model, layout: _Layout, tag: str):
    """`solver` with its `verbose` set as `fit_lens`'s `verbose` asks (unchanged for `False`)."""
    if verbose is False:
        return solver
    fn = verbose if callable(verbose) else _verbose_printer(model, layout, tag)
    return eqx.tree_at(lambda s: s.verbose, solver, fn)


def _start_params(
    base: np.ndarray, free, n_starts: int, depth: np.ndarray, fcap: np.ndarray
) -> np.ndarray:
    """`(S, T, 4)` starting lenses.

    The `init` lens first. With the focus distance free, the others place it evenly in diopters
    across the scene's depth range (both sides of every depth: the near/far ambiguity), keeping
    each target's blur scale `K` through `N` (or `f`) where that is free. With the focus distance
    fixed, `K` is spread by factors of 2 (through `N`, else `f`).
    """
    starts = [base.copy()]
    finite = depth[np.isfinite(depth)]
    f, n, d_f, pitch = (base[:, i] for i in range(4))
    k = f * f / (2 * n * (d_f - f) * pitch)
    if "focus_distance" in free and finite.size:
        near, far = float(np.min(finite)), float(np.max(finite))
        if np.any(np.isinf(depth)) or far <= near * 1.01:
            far = max(far * 4, far + 1.0)
        lo, hi = 1 / far, 1 / near  # diopters
        for i in range(n_starts - 1):
            dpt = hi + (lo - hi) * (i + 0.5) / (n_starts - 1)
            s = base.copy()
            s[:, 2] = np.maximum(1 / dpt, f * 1.05)
            if "f_number" in free:
                s[:, 1] = f * f / (2 * k * (s[:, 2] - f) * pitch)
            starts.append(s)
    else:
        factors = [0.5, 2.0, 0.25, 4.0, 0.125, 8.0]
        for i in range(n_starts - 1):
            c = factors[i % len(factors)] ** (1 + i // len(factors))
            s = base.copy()
            if "f_number" in free:
                s[:, 1] = n / c
            elif "focal_length" in free:
                s[:, 0] = np.minimum(f * math.sqrt(c), 0.9 * fcap)  # K ~ f^2 for f << d_f
            starts.append(s)
    return np.stack(starts)


def _verbose_printer(model: _Model, layout: _Layout, level: str = ""):
    """An optimistix `verbose` callable that prints step, loss and the current lens (prefixed by
    `level`, the pyramid level, when coarse-to-fine)."""
    layout = jax.tree_util.tree_map(np.asarray, layout)

    def show(step, loss, y):
        ys = np.asarray(y).reshape(-1, np.shape(y)[-1])
        steps, losses = np.reshape(step, -1), np.reshape(loss, -1)
        for i, yi in enumerate(ys):
            rows = np.asarray(
                model.natural(jnp.asarray(yi), jax.tree_util.tree_map(jnp.asarray, layout))
            )
            parts = []
            for t, (f, n, d_f, _) in enumerate(rows):
                tag = f"[{t}]" if model.n_targets > 1 else ""
                parts.append(f"f{tag}={f * 1e3:.5g} mm N{tag}={n:.5g} d_f{tag}={d_f:.6g} m")
            head = level + (f"start {i} " if len(ys) > 1 else "")
            st = int(steps[min(i, len(steps) - 1)])
            ls = float(losses[min(i, len(losses) - 1)])
            print(f"{head}step {st}: loss {ls:.6g}  " + "  ".join(parts), flush=True)

    def verbose(**kwargs):
        jax.debug.callback(
            show,
            kwargs["num_steps"][1],
            kwargs["loss_last_accepted_step"][1],
            kwargs["y_last_accepted_step"][1],
        )

    return verbose


# --------------------------------------------------------------------------------------------
# Public API.
# --------------------------------------------------------------------------------------------


def solve_lens(
    image: ArrayLike,
    depth: ArrayLike,
    targets: ArrayLike,
    init: ThinLens,
    *,
    max_radius: float,
    free: Sequence[str] = ("focus_distance", "f_number"),
    shared: Sequence[str] = (),
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 100,
    weight: ArrayLike | None = None,
    exposure: bool = False,
    method: str = "soft",
    footprint: bool = False,
    downsample: int = 1,
) -> FitResult:
    """The pure core of `fit_lens`: one solve from `init`, with no checks that need values.

    Use it to fit many independent scenes with `jax.vmap` (one compilation for the batch), e.g.
    `jax.jit(jax.vmap(lambda im, z, t: solve_lens(im, z, t, init, max_radius=8.0)))`. Arguments
    are as in `fit_lens`, except that `max_radius` (pixels) is required and static, only `init`
    is tried (no multi-start), and nothing is raised: read `.status` / `.success` (a degenerate
    free set gives `status == 4`, circles all under half a pixel `status == 3`). Circles above
    `max_radius` are clamped and not detected here; `message` is empty.
    """
    free, shared = _check_names(free, shared)
    _check_method(method)
    image, depth, targets, sqrt_w, base, single = _prepare(
        image, depth, targets, init, weight, downsample=downsample
    )
    spec = _Spec(free, shared, targets.shape[0], bool(exposure))
    t = targets.shape[0]
    layout = spec.layout(base, depth)
    model = _Model(
        t, float(max_radius), bool(exposure), method, len(spec.used), bool(footprint), downsample
    )
    if solver is None:
        tol = _default_tol(image.dtype)
        solver = optx.LevenbergMarquardt(rtol=tol, atol=tol)
    args = (image, depth, targets, sqrt_w, layout)
    y0 = model.pack(base, layout)
    return _solve_one(model, solver, y0, args, int(max_steps), spec, single)


def fit_lens(
    image: ArrayLike,
    depth: ArrayLike,
    targets: ArrayLike | Sequence[ArrayLike],
    init: ThinLens | Sequence[ThinLens],
    *,
    free: Sequence[str] = ("focus_distance", "f_number"),
    shared: Sequence[str] = (),
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 100,
    weight: ArrayLike | None = None,
    max_radius: float | None = None,
    allow_degenerate: bool = False,
    exposure: bool = False,
    starts: int | None = None,
    verbose: bool | Callable[..., None] = False,
    method: str = "soft",
    footprint: bool = False,
    pyramid: int | None = None,
    downsample: int = 1,
) -> FitResult:
    r"""Recover lens parameters from defocused photos of a scene with known image and depth.

    Minimises `sum w (gain_t * render(image, depth, lens_t) + offset_t - targets[t])^2` (linear
    light) over the `free` lens fields with an optimistix least-squares solver, from a few starts,
    and reports the best fit with standard errors.

    **Arguments:**

    - `image`: the all-in-focus linear-light image, `(H, W)` or `(H, W, C)`.
    - `depth`: z-depth of every pixel (m), `(H, W)`, beyond the focal length; `inf` allowed.
    - `targets`: the defocused photo(s): one image like `image`, a sequence of them, or an array
      `(T, *image.shape)`.
    - `init`: a `ThinLens` (used for every target) or one per target: the start, and the value of
      every field that is not free. Its `pixel_pitch` is always fixed.
    - `free`: the fields to fit, among `"focal_length"`, `"f_number"`, `"focus_distance"`.
    - `shared`: the free fields that take one value across all targets (a focus bracket:
      `shared=("focal_length", "f_number")`, with `focus_distance` free per target).
    - `solver`: any optimistix least-squares solver; default
      `optx.LevenbergMarquardt(rtol=tol, atol=tol)` with `tol = 1e-8` (float64) or `1e-5`
      (float32): steps in the log coordinates below that are at float32's rounding floor.
    - `max_steps`: solver step limit per start.
    - `weight`: optional per-pixel weight `>= 0` (an inverse variance, or a 0/1 mask), `(H, W)`,
      `(T, H, W)`, or the image's/targets' shape.
    - `max_radius`: the filter window (pixels, static). `None` picks one with headroom over the
      circles of every start and refits with a larger one if the solution's circles outgrow it.
      Circles above the window are clamped (see `jaxdof.coc_filter`), so a given value must
      exceed the true largest circle.
    - `allow_degenerate`: return a fit whose free fields the data cannot all determine (with
      `success=False` and `inf` standard errors for the undetermined fields) instead of raising.
    - `exposure`: also fit a gain and an offset per target (nuisance parameters).
    - `starts`: number of starting points (default 4 when the focus distance is free, else 3): the
      `init` lens, then focus distances spread evenly in diopters over the scene's depth range
      (keeping `K` through `N` where possible), which covers the near/far ambiguity; with the focus
      distance fixed, `K` spread by factors of 2. All starts run as one vmapped solve.
    - `verbose`: `True` prints step, loss and the current lens of every start while solving; a
      callable is passed to the optimistix solver as its `verbose` (it receives `(name, value)`
      pairs, with `y` in the solver's coordinates).
    - `method`: the `jaxdof.render` method of the forward model (default `"soft"`, the exact
      coverage); it must be differentiable with respect to the radius.
    - `footprint`: the forward model's opt-in pixel-footprint correction (`jaxdof.render`'s
      `footprint`): default off. It removes the blur-scale bias of a few percent at circles of
      1-3 px on ray-traced photos (`fits/results/raytraced.md`).
    - `downsample`: the image and depth are this many times the targets' resolution in each axis
      (`jaxdof.render`'s `downsample`): targets and weights have the photo's pixels, the window
      and the circles are in them too. Default 1. An all-in-focus image at 2x the photo's
      resolution (a pixel-shift capture, or a longer focal length stitched) carries the detail
      inside each photo pixel that blur of circles of a pixel or two depends on: the fix for the
      smallest blur scales in `fits/results/raytraced.md`. Each render costs about `s^2` times more.
    - `pyramid`: coarse-to-fine levels (a Python int; `None`: automatic; `0` or `1`: full
      resolution only). Level `l` halves the images `l` times (2 x 2 box averages in linear light;
      depth averaged in inverse depth, weights by their harmonic mean) and doubles the pixel pitch
      (so every circle, and the window, halves). The starts are solved on the coarsest level,
      where a render costs `4^-l` of the full one; every finer level starts from the solution of
      the level below (and a near-tie alternative), the full-resolution level also from `init`
      itself (a coarse level's model error can favour a wrong basin; the full-resolution loss
      decides), and the last is the full-resolution problem with the full tolerance, so
      the result (lens, standard errors, statistics) is the full-resolution fit's, to solver
      tolerance. `None` halves while the shorter side stays at least 24 px and the `init` lens's
      largest circle at least 1 px (twice the half-pixel dead zone, where the render ignores the
      lens), and stays at full resolution with `starts=1` (the init is solved there anyway).
      `FitResult.levels` says how many levels ran; `num_steps` counts full-resolution steps only.

    **Returns:** a `FitResult`. `success` is `False`, with the reason in `message`, when the best
    start did not converge, when distinct lenses fit equally well, when the circles outgrow a given
    window, or (with `allow_degenerate`) when the free set is not determined.

    **Raises:** `ValueError` for bad inputs, and when the data cannot determine the free fields
    (the column-scaled Jacobian at the solution is rank deficient): from one photo, blur depends on
    the lens only through `K = f^2 / (2 N (d_f - f))` and `d_f`, so `focal_length` and `f_number`
    cannot both be free; also when every circle is under half a pixel (the render does not depend
    on the lens at all, a zero Jacobian).

    **Statistics.** With `J` the Jacobian of the weighted residuals at the solution,
    `cov = sigma^2 (J^T J)^{-1}` with `sigma^2 = SSR / (n - p)` (Gauss-Newton; `n` residuals with
    non-zero weight, `p` free parameters), mapped from the solver's coordinates to each field's
    units by the chain rule. For Gaussian pixel noise these are the asymptotic (Cramér-Rao) errors.
    Fits of many independent scenes: `jaxdof.solve_lens` under `jax.vmap`.
    """
    free, shared = _check_names(free, shared)
    _check_method(method)
    if not is_concrete(image, depth, targets, init, weight):
        raise ValueError(
            "fit_lens needs concrete inputs (it picks starts and a window, and reports in Python); "
            "under jit/vmap use jaxdof.solve_lens with a static max_radius."
        )
    # Checks and set-up in numpy on the host: two compiled calls per fit (`_fit_starts`, `_finish`)
    # and one transfer of a few small results back, not one device call per array operation.
    image, depth, targets, sqrt_w, base, single = _prepare(
        image, depth, targets, init, weight, xp=np, downsample=downsample
    )
    downsample = int(downsample)  # checked by `_prepare` against the image's shape
    photo = targets.shape[1:3]
    d = np.asarray(depth, np.float64)
    b = np.asarray(base, np.float64)
    for name, x in (("image", image), ("targets", targets)):
        if not np.all(np.isfinite(x)):
            raise ValueError(
                f"{name} contains NaN or inf; mask such pixels with weight=0 and set them to 0"
            )
    if np.any(np.isnan(d)) or not np.all(d > b[:, 0].max()):
        raise ValueError(
            f"depth must exceed the focal length everywhere (metres; found min depth {np.nanmin(d)} m "
            f"or NaN, focal length {b[:, 0].max()} m)"
        )
    n_t = targets.shape[0]
    if int(max_steps) < 1:
        raise ValueError(f"max_steps must be a positive integer, got {max_steps}")
    if starts is None:
        starts = 4 if "focus_distance" in free else 3
    if int(starts) < 1:
        raise ValueError(f"starts must be >= 1, got {starts}")
    if verbose is not False and verbose is not True and not callable(verbose):
        raise ValueError(f"verbose must be a bool or a callable, got {verbose!r}")
    levels = _check_pyramid(pyramid, photo)

    dtype = image.dtype
    spec = _Spec(free, shared, n_t, bool(exposure))
    layout = spec.layout(base, depth)
    fcap = np.asarray(layout.fcap, np.float64)
    if np.any(b[:, 0] >= fcap):
        raise ValueError(
            "init.focal_length must be below the nearest depth (and the focus distance): "
            f"got {b[:, 0]} m against a bound of {fcap} m"
        )
    coarse_solver = solver
    if solver is None:
        tol = _default_tol(dtype)
        solver = optx.LevenbergMarquardt(rtol=tol, atol=tol)
        # A coarse level's minimum differs from the full-resolution one by the downsampling's
        # model error (measured ~1-3 % in N and d_f on the 96 x 96 scenes of fits/recover.py),
        # so solving it tighter than that buys nothing: the finer levels move the answer anyway.
        coarse_solver = optx.LevenbergMarquardt(rtol=_COARSE_TOL, atol=_COARSE_TOL)
    if verbose is not False and not hasattr(solver, "verbose"):
        raise ValueError(
            f"verbose needs a solver with a `verbose` field, got {type(solver).__name__}"
        )
    cap = float(max(photo))
    start_params = _start_params(b, free, int(starts), d, fcap)
    user_window = max_radius is not None
    if user_window:
        window = float(max_radius)
        if not math.isfinite(window) or window < 0:
            raise ValueError(f"max_radius must be a finite number >= 0 (pixels), got {max_radius}")
    else:
        window = _window(_max_coc(start_params, d), cap)

    def model_at(window: float) -> _Model:  # the forward model with a given filter window
        return _Model(
            n_t, window, bool(exposure), method, len(spec.used), bool(footprint), downsample
        )

    # Coarse-to-fine: the multi-start solve runs on the coarsest level, and each finer level
    # starts from the level below's solution (and a near-tie alternative, if any); the last level
    # is the full-resolution problem with the full tolerance, so the answer and its statistics are
    # those of the full-resolution fit.
    if levels is None:
        # From one start the init is refined at full resolution anyway (below), so coarse levels
        # would only add work: measured 0.5-0.7x the full-resolution fit's speed (fits/recover.py).
        one = len(start_params) == 1
        levels = 1 if one else _auto_levels(photo, _max_coc(start_params[:1], d))
    pyr = [(image, depth, targets, sqrt_w, b)]
    for _ in range(levels - 1):
        pyr.append(_downsample(*pyr[-1], downsample))
    # Shapes and values stay numpy; the layout keeps the full-resolution bound on f at every
    # level, so that a parameter vector means the same lens on every level.
    layouts = [layout] + [dataclasses.replace(layout, base=lv[4].astype(dtype)) for lv in pyr[1:]]
    y0s = y0_init = model_at(window).pack(start_params.astype(dtype), layout)
    notes = []
    rows = start_params  # (S, T, 4) the current starts' lenses, at the full-resolution pitch
    for lev in range(levels - 1, 0, -1):
        im_l, dep_l, tg_l, sw_l, _ = pyr[lev]
        d_l = np.asarray(dep_l, np.float64)
        scale = 2.0**lev
        if user_window:
            win_l = window / scale  # the same extent in the scene as the full-resolution window
        else:
            rows_l = np.asarray(rows, np.float64).copy()
            rows_l[..., 3] = rows_l[..., 3] * scale
            win_l = _window(_max_coc(rows_l, d_l), float(max(tg_l.shape[1:3])))
        model_l = model_at(win_l)
        solver_l = _with_verbose(coarse_solver, verbose, model_l, layouts[lev], f"level {lev} ")
        args_l = (im_l, dep_l, tg_l, sw_l, layouts[lev])
        _, info_l = _fit_starts(model_l, solver_l, y0s, args_l, int(max_steps))
        info_l = jax.device_get(info_l)
        y0s, rows = _next_starts(info_l, b, y0s, spec)  # rows at full-resolution pitch
    if levels > 1:
        # The init is refined at full resolution too: a coarse level's model error can move every
        # start into a wrong basin with the lowest coarse loss (seen on a depth-steps scene with a
        # fine texture: all four starts went to N = 17, d_f = 0.42 at 48 x 48, while the init
        # converges to the truth at 96 x 96 with a quarter of that loss), and the full-resolution
        # loss, not the coarse one, decides between them.
        y0s = np.concatenate([y0s, y0_init[:1]], axis=0)
        rows = np.concatenate([rows, start_params[:1]], axis=0)

    args = (image, depth, targets, sqrt_w, layout)
    if levels > 1 and not user_window:
        window = _window(_max_coc(rows, d), cap)
    for _ in range(3):
        model = model_at(window)
        fit_solver = _with_verbose(solver, verbose, model, layout, "level 0 " if levels > 1 else "")
        solution, info = _fit_starts(model, fit_solver, y0s, args, int(max_steps))
        info = jax.device_get(info)  # a handful of small arrays, in one go
        loss, converged, best = info["loss"], info["converged"], int(info["best"])
        r_final = _max_coc(np.asarray(info["natural"], np.float64), d)
        if r_final <= window or user_window:
            break
        notes.append(
            f"the window {window:g} px was too small for the fitted circles ({r_final:.3g} px); refitted"
        )
        window = _window(r_final, max(cap, 1.5 * r_final + 1.0))
        y0s = np.concatenate([info["ys"][best][None], info["ys"]], axis=0)

    result, stats = _finish(model, solution, args, spec, bool(single))
    info.update(jax.device_get(stats))
    code = int(info["status"])
    # The near/far ambiguity: another converged start at a distinct lens, with a loss the noise
    # cannot tell from the best one (within ~2 sigma^2 per parameter, or rounding when noise-free).
    theta = np.asarray(info["theta"], np.float64)[:, list(spec.used)]
    if code == CONVERGED and len(loss) > 1:
        sigma2 = float(info["sigma"]) ** 2
        p = len(spec.used)
        floor = float(jnp.finfo(dtype).eps) * float(np.sum(np.asarray(targets, np.float64) ** 2))
        se = np.sqrt(np.maximum(np.asarray(info["variance"], np.float64), 0))
        for i in np.argsort(loss):
            if i == best or not converged[i]:
                continue
            tie = loss[i] - loss[best] <= 2.0 * sigma2 * p + 10 * floor
            far = np.any(np.abs(theta[i] - theta[best]) > 10 * se + 1e-3 * np.abs(theta[best]))
            if tie and far:
                code = AMBIGUOUS
                alt = ", ".join(f"{n}={v:.5g}" for n, v in zip(spec.names, theta[i]))
                notes.append(
                    f"another start converged to {alt} with loss {loss[i]:.4g} (best {loss[best]:.4g}); "
                    "add a photo at another focus distance, or fix the focus distance"
                )
                break

    if r_final > window:
        code = WINDOW if code == CONVERGED else code
        notes.append(
            f"the fitted lens makes circles up to {r_final:.3g} px but max_radius={window:g}: "
            "pass a larger max_radius"
        )

    msg = _STATUS_TEXT[code]
    if code in (DEGENERATE, DEAD_ZONE):
        explain = _degeneracy_text(code, free, shared, n_t, float(info["condition"]))
        if not allow_degenerate:
            raise ValueError(explain)
        msg = explain
    if code == MAX_STEPS:
        msg += f" ({max_steps}); increase max_steps or give a closer init"
    if notes:
        msg += "; " + "; ".join(notes)
    if code == int(info["status"]):
        return dataclasses.replace(result, message=msg, levels=levels)
    return dataclasses.replace(
        result,
        status=jnp.asarray(code),
        success=jnp.asarray(code == CONVERGED),
        message=msg,
        levels=levels,
    )


def _degeneracy_text(code, free, shared, n_t, condition) -> str:
    if code == DEAD_ZONE:
        return (
            "fit_lens: every circle of confusion is under half a pixel at the solution, where the "
            "render does not depend on the lens (zero Jacobian): the photo looks in focus "
            "everywhere to this model. Start from a lens with more blur (a smaller f_number or a "
            "closer/farther focus distance), check that the targets are really defocused, or "
            "pass allow_degenerate=True to get this fit anyway."
        )
    return (
        f"fit_lens: the free set {free} (shared {shared}, {n_t} target(s)) is not determined by the "
        f"data: the column-scaled Jacobian at the solution is rank deficient (condition number "
        f"{condition:.3g}). From a single photo the circle of confusion depends on the lens only "
        "through K = f^2 / (2 N (d_f - f)) and the focus distance d_f, so focal_length and f_number "
        "cannot both be fitted. Fixes: fix one of them from the EXIF data (drop it from free), or "
        "fit a focus bracket: several photos with different focus distances, "
        "free=('focal_length', 'f_number', 'focus_distance'), shared=('focal_length', 'f_number'). "
        "Pass allow_degenerate=True to get the (non-unique) fit anyway."
    )
