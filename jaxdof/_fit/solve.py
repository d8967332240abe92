r"""The pure solve (jit/vmap-able), its statistics, and `solve_lens`.

**Statistics.** With `J` the Jacobian of the weighted residuals at the solution,
`cov = sigma^2 (J^T J)^{-1}` with `sigma^2 = SSR / (n - p)` (Gauss-Newton; `n` residuals with
non-zero weight, `p` free parameters), mapped from the solver's coordinates by the chain rule to
`(f, N, u)`, `u = 1 / d_f` the focus power (diopters), which is smooth through focus at infinity
(`u = 0`), and from there to the focus distance: `se(d_f) = se(u) / u^2`, and `inf` where the
power is within one standard error of 0 (the data cannot rule out focus at infinity, so no
finite interval holds the distance). For Gaussian pixel noise these are the asymptotic
(Cramér-Rao) errors. A free set the data cannot determine shows as a rank-deficient
column-scaled Jacobian.

**Model adequacy.** Every fit then tests, from the same residual and Jacobian, whether
independent tiles of the photo agree on one lens beyond their noise (`adequacy.py`: Chow's test
in score form, each tile also allowed its own exposure); when they do not, the status is
`inconsistent` and the covariance is inflated to the spread between the tiles.

`fit_lens` runs two compiled stages per level, `fit_starts` (every start, raced, and the
Jacobians at the best) and `finish` (statistics and the `FitResult`), through `run_stage`, which
`record_stages` can time; settling a focus at infinity adds a `fit_starts` and a `restate`.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import time
from collections.abc import Callable, Iterator, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, ArrayLike

from .. import _traced
from .._filters import AbstractMethod
from .._lens import ThinLens
from .adequacy import adequacy, rounding_noise
from .forward import AbstractForwardModel
from .layout import _W_MIN, _Spec, nuisance_names, theta_floor
from .linalg import thin_svd
from .lm import LevenbergMarquardt
from .photo import NUISANCES, camera, canonical, half_diagonal
from .prepare import _check_names, _prepare, check_differentiable, forward_model, luma_targets
from .race import accepted_point, race, tie_margin
from .residual import _Model
from .result import RESULTS, FitResult
from .strategies import border_mask, check_border, level_band


def _default_tol(dtype) -> float:
    # Steps in the log coordinates below these are at the rounding floor of the residual: in
    # float32 the iterates jitter at ~1e-6 (a residual of ~1e-7 per pixel moved by a Jacobian of
    # order 1), so 1e-5 terminates reliably while leaving errors far under 1e-3; float64 goes to 1e-8.
    return 1e-5 if jnp.dtype(dtype) == jnp.float32 else 1e-8


# Bates & Watts' relative offset under which a solve stops (`lm.py`): its next Gauss-Newton step
# would move it by less than 1e-3 sqrt(p) standard errors (their recommended value). Measured on
# the four scenes of `fits/recover.py` (210 default fits, sigma 0.001-0.03): converged fits moved
# by at most 3.7e-3 standard errors against the 1e-8 step test alone; 40 noise-free fits unchanged
# bit for bit (the offset does not fall without noise).
_OFFSET_TOL = 1e-3


def default_solver(dtype) -> optx.AbstractLeastSquaresSolver:
    """The default solver for data of `dtype`: `lm.LevenbergMarquardt` (optimistix's, also
    stopping on the relative offset `_OFFSET_TOL`) with the step tolerance `_default_tol(dtype)`."""
    tol = _default_tol(dtype)
    return LevenbergMarquardt(rtol=tol, atol=tol, offset_tol=_OFFSET_TOL, rank_tol=_rank_tol(dtype))


def _rank_tol(dtype) -> float:
    # Relative singular-value threshold of the column-scaled Jacobian. An exact degeneracy (f and N
    # from one photo) leaves s_min / s_max at the rounding level of the Jacobian: measured 2.2e-16
    # in float64 and 1.9e-7 in float32 (32x32 slanted-plane scene). Determined problems stay far
    # above: 0.65 for (N, d_f) from one photo, 1.5e-3 for f and N from a three-photo focus bracket
    # (the worst conditioned case we support). The threshold sits between: ~15x the float32
    # rounding level, and sqrt(eps) in float64.
    return 3e-6 if jnp.dtype(dtype) == jnp.float32 else 1.5e-8


def _statistics(residual, jac, g, theta, floor, n, used: tuple[int, ...]) -> dict[str, Array]:
    """Loss, residual sigma, covariance in statistical units, conditioning: from the full Jacobian.

    `jac` `(n_res, P)` is d residual / d y, `g` `(P, P)` is d theta / d y, `theta` `(P,)` the
    slots' values in their statistical units (`layout.theta`: m, -, diopters, gain, offset) and
    `floor` `(P,)` their scales near 0 (`layout.theta_floor`); `used` are the slots that are free.
    Works on tracers (`solve_lens` under vmap) and on concrete arrays.
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
    _, s, vt = thin_svd(jac / safe[None, :])
    good = s > _rank_tol(dtype) * s[0]
    inv_s2 = jnp.where(good, 1 / jnp.where(good, s * s, 1), 0)
    cov_y = sigma2 * ((vt.T * inv_s2[None, :]) @ vt) / safe[:, None] / safe[None, :]
    cov = g @ cov_y @ g.T  # chain rule: y (log / logit / focus coordinates) -> (f, N, u)
    # A parameter that moves along a null direction (or has a zero column) is undetermined. The
    # test is in each field's own units: with f and N free from one photo, the null direction moves
    # the focus coordinate too (it holds fcap / (d_f - f)), yet the focus itself stays put and
    # keeps its (estimable) standard error. A focus power is measured against the nearest
    # depth's power where it is smaller (at infinity it is 0, and any movement relative to it is
    # infinite).
    v_null = jnp.where(good[:, None], 0, vt).T / safe[:, None]  # (p, k) null vectors in y
    size = jnp.maximum(jnp.abs(theta[idx]), floor[idx].astype(dtype))
    moved = jnp.abs(g @ v_null) / size[:, None]
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


def _statistics_at(residual, jac, g, theta, args, spec: _Spec) -> dict[str, Array]:
    """`_statistics` with the floors and the residual count of the solve's `args`."""
    _, _, targets, sqrt_w, layout = args
    floor = theta_floor(layout, spec.nuisances)
    return _statistics(residual, jac, g, theta, floor, _n_residuals(targets, sqrt_w), spec.used)


def _exposure_columns(residual, args) -> tuple[Array, Array]:
    """`sqrt(w)` at the targets' shape, and the derivatives of the residual with respect to a
    gain and an offset per target, `(n, 2 T)`: `sqrt(w) model_t` and `sqrt(w)` on target `t`'s
    pixels, 0 elsewhere."""
    _, _, targets, sqrt_w, _ = args
    shape = targets.shape
    sw = jnp.broadcast_to(sqrt_w, shape).astype(residual.dtype)
    pred = residual.reshape(shape) + sw * targets  # sqrt(w) * model
    t = shape[0]
    which = jnp.arange(t).reshape((t,) + (1,) * (len(shape) - 1))
    extra = [jnp.where(which == i, x, 0).reshape(-1) for i in range(t) for x in (pred, sw)]
    return sw, jnp.stack(extra, axis=1)


def _check_model(residual, jac, args, spec: _Spec, band: int) -> dict[str, Array]:
    """The model-adequacy test (`adequacy.adequacy`) at the solution: tiles of the region inside
    the border `band`, every target and channel of a tile together; each tile may also have its
    own gain and offset per target (the prediction and the weight as `extra` columns), so that
    photometric model error (vignetting, uneven exposure) shows too; the noise kept above the
    targets' rounding level."""
    _, _, targets, sqrt_w, _ = args
    shape = targets.shape
    sw, extra = _exposure_columns(residual, args)
    return adequacy(
        residual,
        jac,
        shape,
        sw > 0,
        used=spec.used,
        extra=extra,
        band=band,
        noise_floor=rounding_noise(sw * targets, sw > 0),
    )


def _options(model: _Model, args) -> dict:
    """The optimistix `options` of every solve: each residual's rounding, from which
    `lm.LevenbergMarquardt` tells when a step can no longer be told from the loss's noise."""
    return dict(rounding=model.rounding(args))


def _solve(model: _Model, solver, y0, args, max_steps: int):
    """One least-squares solve from `y0`: solution, status, steps, residual and slot values. Pure."""
    # optimistix 0.1.0's Levenberg-Marquardt builds its damping term in JAX's default float dtype,
    # so float32 parameters under `jax_enable_x64` fail its structure check ("Vector and operator
    # structures do not match"). Carrying `y` in the default dtype and casting it to the data's
    # dtype inside the residual avoids that; the model itself runs in the data's precision.
    y0_wide = y0.astype(jnp.result_type(float))
    sol = optx.least_squares(
        model, solver, y0_wide, args, _options(model, args), max_steps=max_steps, throw=False
    )
    return _outcome(
        model, sol.value.astype(y0.dtype), sol.result, sol.stats["num_steps"], sol.state, args
    )


def _outcome(model: _Model, y, result, num_steps, state, args):
    """A solve's solution `y`, its `jaxdof.RESULTS` status (from the optimistix `result`), steps,
    residual and slot values, and its Jacobian where the solver's `state` keeps one at its last
    accepted point, which is the returned solution (`race.accepted_point`): with the JVP rule of
    `residual._residuals` that linearisation is the materialised Jacobian times a vector, so
    reading it back as a matrix costs `P` small products instead of a render and `P` tangent
    passes (a tenth to a third of a whole fit, depending on its number of steps). Other solvers:
    None, and the caller evaluates it."""
    dtype = args[2].dtype  # the data's
    kept = accepted_point(state)
    if kept is None:
        residual, jac = model(y, args), None  # in the data's dtype again, since `y` is
    else:
        residual, jac = kept[0].astype(dtype), kept[1].astype(dtype)
    ok = result == optx.RESULTS.successful
    maxed = result == optx.RESULTS.nonlinear_max_steps_reached
    status = RESULTS.where(
        ok,
        RESULTS.successful,
        RESULTS.where(maxed, RESULTS.max_steps, RESULTS.solver_failed),
    )
    status = RESULTS.where(ok & ~jnp.all(jnp.isfinite(residual)), RESULTS.solver_failed, status)
    return y, status, num_steps, residual, model.theta(y, args[-1]), jac


def _jacobians(model: _Model, y, args, jac=None):
    """d residual / d y `(n, P)` by forward mode (P passes; few parameters, many residuals),
    unless given, and d theta / d y `(P, P)`."""
    if jac is None:
        jac = jax.jacfwd(model)(y, args).astype(args[2].dtype)
    return jac, jax.jacfwd(model.theta)(y, args[-1])


def _n_residuals(targets, sqrt_w):
    return jnp.sum(jnp.broadcast_to(sqrt_w, targets.shape) > 0).astype(targets.dtype)


def _n_pixels(targets, sqrt_w) -> Array:
    """Pixels (over targets, rows, columns) with a non-zero weight in some channel."""
    live = jnp.broadcast_to(sqrt_w, targets.shape) > 0
    return jnp.sum(jnp.any(live, axis=-1) if targets.ndim == 4 else live).astype(jnp.int32)


def _pick_best(loss, converged, n, p: int, floor):
    """The start whose solution `fit_lens` reports: a converged one among those whose loss is a
    statistical tie with the lowest (within `2 sigma^2` per parameter, `sigma^2` estimated from
    the lowest loss, or `floor` for rounding), else the lowest loss, converged or not.

    So a start that stopped early in a flat region (a dead zone, a plateau, where the solver
    "converges" at once) never beats a lower-loss start that merely ran out of steps: the best
    solution decides the verdict (degenerate or not), and its status says it did not converge.
    """
    lowest = jnp.min(loss)
    tie = loss <= lowest + tie_margin(lowest, n, p, floor)
    return jnp.lexsort((loss, (~(converged & tie)).astype(jnp.int32)))[0]


@eqx.filter_jit
def fit_starts(model: _Model, solver, y0s, args, max_steps: int, live=None):
    """`fit_lens`'s solve at one pyramid level as one compiled call, shared by the free/shared
    sets with the same number of free parameters.

    Solves from every start `y0s` `(S, P)` at once (`race.race`: in lockstep, a start that cannot
    catch up with a converged one stopped; independent vmapped solves for a solver that keeps no
    residual in its state), picks the best (`_pick_best`: a converged start tied with the lowest
    loss, else the lowest loss), and evaluates the Jacobians there. The free set is data
    (`args[-1]`, the layout), not part of the compiled code; `finish` (small, compiled per free
    set) does the statistics. Returns the chosen `solution` (for
    `finish`) and `info`, the few arrays `fit_lens` reads in Python (`best`, per-start `loss`,
    `converged`, `theta`, `ys`, `steps`, `stopped` by the race; `natural` at the best).
    `live` `(S,)`: the rows of `y0s` that are starts, the others padding (`path.Run.solve`: one
    compiled solve for fits of up to as many starts); never reported, never the best.
    """
    _, _, targets, sqrt_w, layout = args
    eps = float(jnp.finfo(targets.dtype).eps)  # a Python float: no float32 x float64 mix
    floor = 10 * eps * jnp.sum(jnp.square(targets * sqrt_w).astype(jnp.result_type(float)))
    n = _n_residuals(targets, sqrt_w).astype(floor.dtype)
    p = jnp.asarray(layout.live).shape[0]
    y0s_wide = y0s.astype(jnp.result_type(float))  # as in `_solve`
    tie = (n, p, floor)
    raced = race(model, solver, y0s_wide, args, max_steps, tie, _options(model, args), live=live)
    if raced is None:
        stopped = jnp.zeros(y0s.shape[0], bool)
        ys, status, num_steps, residual, theta, jacs = eqx.filter_vmap(
            _solve, in_axes=(None, None, 0, None, None)
        )(model, solver, y0s, args, max_steps)
    else:
        ys, result, steps, states, stopped = raced
        ys, status, num_steps, residual, theta, jacs = eqx.filter_vmap(
            lambda y, r, k, s: _outcome(model, y.astype(y0s.dtype), r, k, s, args)
        )(ys, result, steps, states)
    loss = 0.5 * jnp.sum(jnp.square(residual.astype(jnp.result_type(float))), axis=-1)
    live = jnp.ones(y0s.shape[0], bool) if live is None else jnp.asarray(live, bool)
    loss = jnp.where(jnp.isfinite(loss) & live, loss, jnp.inf)
    converged = (status == RESULTS.successful) & live
    best = _pick_best(loss, converged, n, p, floor)
    y = ys[best]
    jac, g = _jacobians(model, y, args, None if jacs is None else jacs[best])
    # A non-finite Jacobian at the solution makes its statistics meaningless: a failed solve.
    status_best = jax.tree_util.tree_map(lambda s: s[best], status)
    status_best = RESULTS.where(jnp.all(jnp.isfinite(jac)), status_best, RESULTS.solver_failed)
    solution = (y, status_best, num_steps[best], residual[best], theta[best], jac, g)
    info = dict(
        best=best,
        loss=loss,
        converged=converged,
        theta=theta,
        natural=model.natural(y, layout),
        ys=ys,
        steps=num_steps,
        stopped=stopped,
        tie=tie_margin(loss[best], n, p, floor),  # the loss another start ties within
    )
    return solution, info


@eqx.filter_jit
def degenerate_at(model: _Model, y, args, spec: _Spec):
    """`_statistics`' rank test at a point `y` (no solve): whether the photos leave a free field
    undetermined there. `fit_lens` asks it at the init lens when the best solution is rank
    deficient, to tell a free set the data cannot determine (rank deficient everywhere) from a
    solution that ended where the blur stops depending on a field (a local minimum)."""
    residual, theta, jac, g = restate(model, y, args)
    stats = _statistics_at(residual, jac, g, theta, args, spec)
    return stats["degenerate"]


@eqx.filter_jit
def restate(model: _Model, y, args):
    """The residual, slot values and Jacobians at a given point `y` (no solve): what
    `fit_starts` hands `finish` for its best start, for a point found otherwise (`fit_lens`
    settling a focus at infinity with another layout). Also a compiled stage."""
    residual = model(y, args)
    jac, g = _jacobians(model, y, args, None)
    return residual, model.theta(y, args[-1]), jac, g


@eqx.filter_jit
def finish(model: _Model, solution, args, spec: _Spec, single: bool, band: int):
    """Statistics, the adequacy test, status and the `FitResult` (without its notes and border
    width) at the chosen solution, and the few numbers `fit_lens` reads in Python to word the
    message. `args` are the solve's, with the weights it used (the border `band` applied)."""
    y, status, num_steps, residual, theta, jac, g = solution
    stats = _statistics_at(residual, jac, g, theta, args, spec)
    check = _check_model(residual, jac, args, spec, band)
    result = _assemble(spec, model, (y, status, num_steps, theta), stats, check, args, single)
    info = dict(
        status=result.status,
        condition=stats["condition"],
        sigma=stats["sigma"],
        variance=stats["variance"],
        nuisance_values=model.nuisance_params(y),
        residual_map=residual_map(residual, args),
    )
    return result, info


def residual_map(residual, args, cells: int = 8) -> Array:
    """The mean squared weighted residual in each of `cells x cells` regions of the photo (all
    targets and channels together), `(cells, cells)`; NaN where nothing is fitted. Where the
    tiles disagree, its pattern says what the model lacks (`verdict._cause`)."""
    _, _, targets, sqrt_w, _ = args
    shape = targets.shape
    live = (jnp.broadcast_to(sqrt_w, shape) > 0).astype(residual.dtype)
    r2 = jnp.square(residual.reshape(shape))
    axes = (0, 3) if len(shape) == 4 else (0,)
    r2, live = jnp.sum(r2, axis=axes), jnp.sum(live, axis=axes)
    rows = jax.nn.one_hot(jnp.arange(shape[1]) * cells // shape[1], cells, dtype=r2.dtype).T
    cols = jax.nn.one_hot(jnp.arange(shape[2]) * cells // shape[2], cells, dtype=r2.dtype).T
    total, count = rows @ r2 @ cols.T, rows @ live @ cols.T
    return jnp.where(count > 0, total / jnp.where(count > 0, count, 1), jnp.nan)


def nuisance_columns(model: _Model, y, args, which=tuple(NUISANCES)) -> dict[str, Array]:
    """For every nuisance of `which` the fit lacks, the derivatives of the weighted residual with
    respect to its parameters at their null values, `(n, q T)`: from one render (no refit),
    through `photo.camera` only."""
    _, _, targets, sqrt_w, layout = args
    y = y.astype(targets.dtype)
    raw = model.render(y, args)
    params = model.nuisance_params(y)
    out = {}
    for name in NUISANCES:
        if name in model.nuisances or name not in which:
            continue
        on = canonical((*model.nuisances, name))
        names = NUISANCES[name]

        def r(v, names=names, on=on):
            p = {**params, **{n: v[i] for i, n in enumerate(names)}}
            pred = camera(raw, p, on, model.luma, layout.frame_vu)
            return ((pred - targets) * sqrt_w).reshape(-1)

        v0 = jnp.stack([params[n] for n in names])
        out[name] = jax.jacfwd(r)(v0).reshape(-1, v0.size)
    return out


@eqx.filter_jit
def nuisance_scores(model: _Model, solution, args, spec: _Spec, names: tuple[str, ...]):
    """`score_statistic` of each nuisance of `names` (of `photo.NUISANCES`) that the fit at
    `solution` (`fit_starts`'s) lacks, `{name: score}`. Chi-square with `q T` degrees of freedom
    (`q` the nuisance's parameters) where the photo has none of it. A compiled stage of its own,
    run only where a nuisance is to be decided: an exact fit or a caller's choice skips it."""
    y, _, _, residual, _, jac, _ = solution
    columns = nuisance_columns(model, y, args, names)
    return {k: score_statistic(residual, jac, c, args, spec) for k, c in columns.items()}


def score_statistic(residual, jac, extra, args, spec: _Spec) -> Array:
    r"""The score (Lagrange multiplier) statistic for nuisance columns `extra` `(n, q)` (the
    derivatives of the residual with respect to parameters the fit lacks, at their null) at a
    fit without them: `LM = ||P_X r||^2 / sigma^2`, `P_X` the projection onto the columns of the
    fitted parameters' Jacobian and `extra`, `sigma^2 = ||r||^2 / (n - p)`. Where the photo
    has none of that nuisance it is chi-square with `q` degrees of freedom (Rao 1948; Buse 1982,
    "The likelihood ratio, Wald, and Lagrange multiplier tests"), and it needs no refit."""
    _, _, targets, sqrt_w, _ = args
    sw = jnp.broadcast_to(sqrt_w, targets.shape)
    x = jnp.concatenate([jac[:, jnp.asarray(spec.used)], extra.astype(jac.dtype)], axis=1)
    r = residual.astype(x.dtype)
    # Scaled columns: a gain column is O(1), an offset O(1), a lens column anything.
    norms = jnp.sqrt(jnp.sum(jnp.square(x), axis=0))
    xs = x / jnp.where(norms > 0, norms, 1)[None, :]
    beta = jnp.linalg.lstsq(xs, r)[0]
    fitted = xs @ beta
    n = jnp.sum(sw > 0).astype(r.dtype)
    sigma2 = (r @ r) / jnp.maximum(n - len(spec.used), 1)
    return ((fitted @ fitted) / jnp.maximum(sigma2, jnp.finfo(r.dtype).tiny)).astype(residual.dtype)


@eqx.filter_jit
def _solve_one(
    model: _Model, solver, y0, args, max_steps: int, spec: _Spec, single: bool, band: int
):
    """`solve_lens`'s numerics: one solve, its Jacobian, statistics, adequacy test and status
    (one compiled call when `solve_lens` runs eagerly; inlined into the caller's trace under
    jit/vmap)."""
    y, status, num_steps, residual, theta, jac = _solve(model, solver, y0, args, max_steps)
    jac, g = _jacobians(model, y, args, jac)
    bad_jac = (status == RESULTS.successful) & ~jnp.all(jnp.isfinite(jac))
    status = RESULTS.where(bad_jac, RESULTS.solver_failed, status)
    stats = _statistics_at(residual, jac, g, theta, args, spec)
    check = _check_model(residual, jac, args, spec, band)
    return _assemble(spec, model, (y, status, num_steps, theta), stats, check, args, single)


def _focus_to_distance(spec: _Spec, y, theta, var, cov):
    """Variances and covariance in `(f, N, u)` (`u = 1 / d_f`, diopters) to `(f, N, d_f)`.

    `d_f = 1 / u`, so `se(d_f) = se(u) / u^2` by the chain rule, except where the power is
    within one standard error of infinity's: the interval reaches focus at infinity, and no
    finite interval holds the distance: `inf` (and NaN covariance entries). The power is
    counted above the floor of the coordinate (`layout._W_MIN`: `y = 0` is infinity, though the
    lens there is `1e12 fcap` away). Returns `(variance, covariance, se(u))`.
    """
    idx = jnp.asarray(spec.used)
    u = theta[idx]
    focus = jnp.asarray([nm.split("[")[0] == "focus_distance" for nm in spec.names])
    se_u = jnp.sqrt(var)
    y_abs = jnp.abs(y[idx]).astype(u.dtype)
    above = y_abs / (y_abs + _W_MIN)  # the share of the focus coordinate above its floor
    at_inf = focus & (u * above <= se_u)
    safe_u = jnp.where(focus & ~at_inf, u, 1)
    s = jnp.where(at_inf, jnp.nan, jnp.where(focus, -1 / (safe_u * safe_u), 1))
    var_out = jnp.where(at_inf, jnp.inf, var * s * s)
    return var_out, cov * s[:, None] * s[None, :], se_u


def _assemble(spec: _Spec, model: _Model, point, stats, check, args, single) -> FitResult:
    """Build a FitResult from the raw solve outputs (works on tracers). `point` is the solution
    `(y, status, num_steps, theta)`, `args` the solve's (weights with the border band applied;
    the caller sets `border`, a static field, so that it is no part of the compiled code). The
    adequacy test's (`check`, `_check_model`) `inflation` multiplies the covariance (its square) before it is mapped to the
    fields' units, so every derived error (`K`, the focus distance from its power) inherits it."""
    y, status, num_steps, theta = point
    _, _, targets, sqrt_w, layout = args
    s2 = jnp.square(check["inflation"]).astype(stats["covariance"].dtype)
    var, covariance, se_u = _focus_to_distance(
        spec, y, theta, stats["variance"] * s2, stats["covariance"] * s2
    )
    stderr: dict[str, Array] = {}
    # Shifts are fitted in half diagonals and reported in photo pixels.
    r = half_diagonal(targets.shape[1], targets.shape[2])
    for name in spec.free + nuisance_names(spec.nuisances):
        idx = [i for i, nm in enumerate(spec.names) if nm.split("[")[0] == name]
        unit = r if name.startswith("shift") else 1.0
        se = jnp.broadcast_to(unit * jnp.sqrt(var[jnp.asarray(idx)]), (spec.n_targets,))
        stderr[name] = se[0] if single else se  # a shared field repeats its one value
    idx = [i for i, nm in enumerate(spec.names) if nm.split("[")[0] == "focus_distance"]
    se_power = jnp.broadcast_to(
        se_u[jnp.asarray(idx)] if idx else jnp.asarray(jnp.nan, se_u.dtype), (spec.n_targets,)
    )
    gain, offset = model.exposure_params(y)
    ok = status == RESULTS.successful
    status = RESULTS.where(ok & ~check["adequate"], RESULTS.inconsistent, status)
    status = RESULTS.where(
        ok & stats["jac_zero"],
        RESULTS.dead_zone,
        RESULTS.where(ok & stats["degenerate"], RESULTS.degenerate, status),
    )
    return FitResult(
        lenses=model.lenses(y, layout),
        stderr=stderr,
        covariance=covariance,
        gain=gain,
        offset=offset,
        loss=stats["loss"],
        sigma=stats["sigma"],
        num_steps=jnp.asarray(num_steps),
        condition=stats["condition"],
        status=status,
        # An inconsistent fit's lens and its (inflated) errors can be used: success.
        success=(status == RESULTS.successful) | (status == RESULTS.inconsistent),
        focus_power_stderr=se_power[0] if single else se_power,
        pixels_used=_n_pixels(targets, sqrt_w),
        adequacy=check,
        names=spec.names,
        max_radius=model.max_radius,
    )


# ---------------------------------------------------------------------------------------------
# Timing the compiled stages, without patching.
# ---------------------------------------------------------------------------------------------

_STAGE_LOG: contextvars.ContextVar[list | None] = contextvars.ContextVar(
    "jaxdof_fit_stage_log", default=None
)


@contextlib.contextmanager
def record_stages() -> Iterator[list[tuple[str, float]]]:
    """Time the compiled stages of every `fit_lens` call inside the block.

    `with record_stages() as log: fit_lens(...)` appends `(stage, seconds)` to `log` for every
    compiled call (`"fit_starts"` per pyramid level and window, `"fit_starts"` and `"restate"`
    when a focus is settled at infinity, then `"finish"`, and `"nuisance scores"` where a nuisance
    is to be decided), each timed up to
    its results being ready (`jax.block_until_ready`); `fit_lens` reads those results on the host
    right after anyway, so the timing does not change the fit's own wall time. The rest of a warm
    `fit_lens` call (checks, set-up, wording) is its total time minus their sum.
    """
    log: list[tuple[str, float]] = []
    token = _STAGE_LOG.set(log)
    try:
        yield log
    finally:
        _STAGE_LOG.reset(token)


_STAGE_WATCH: contextvars.ContextVar[Callable[[str, float | None], None] | None] = (
    contextvars.ContextVar("jaxdof_fit_stage_watch", default=None)
)


@contextlib.contextmanager
def watch_stages(watch: Callable[[str, float | None], None]) -> Iterator[None]:
    """Tell `watch` about every stage of the `fit_lens` calls inside the block: `watch(name,
    None)` as a compiled stage starts (or `fit_lens` starts work outside the solver, named by
    what it does: `"choosing tiles ..."`), `watch(name, seconds)` as a compiled stage ends.

    What the command line shows while it fits: unlike a `verbose` callable, which runs inside
    the compiled solve through a host callback, it leaves the programs free of callbacks, so
    they can be kept in the persistent compilation cache (`jaxdof.enable_compilation_cache`).
    """
    token = _STAGE_WATCH.set(watch)
    try:
        yield
    finally:
        _STAGE_WATCH.reset(token)


def stage_note(text: str) -> None:
    """Tell an enclosing `watch_stages` what `fit_lens` does outside the compiled stages."""
    watch = _STAGE_WATCH.get()
    if watch is not None:
        watch(text, None)


def run_stage(name: str, stage: Callable, *args):
    """`stage(*args)`: one compiled stage of `fit_lens` (`fit_starts` or `finish`), timed into
    the log of an enclosing `record_stages` and told to an enclosing `watch_stages` (if any)
    under `name`."""
    log, watch = _STAGE_LOG.get(), _STAGE_WATCH.get()
    if log is None and watch is None:
        return _traced.call(stage, *args)
    if watch is not None:
        watch(name, None)
    t = time.perf_counter()
    out = jax.block_until_ready(_traced.call(stage, *args))
    seconds = time.perf_counter() - t
    if log is not None:
        log.append((name, seconds))
    if watch is not None:
        watch(name, seconds)
    return out


# ---------------------------------------------------------------------------------------------
# The pure entry point.
# ---------------------------------------------------------------------------------------------


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
    vignetting: bool = False,
    illumination: bool = False,
    registration: bool = False,
    luma: bool = False,
    model: AbstractForwardModel | None = None,
    method: str | AbstractMethod | None = None,
    footprint: bool | None = None,
    downsample: int | None = None,
    border: bool | str | int = "auto",
) -> FitResult:
    """The pure core of `fit_lens`: one solve from `init`, with no checks that need values.

    Use it to fit many independent scenes with `jax.vmap` (one compilation for the batch), e.g.
    `jax.jit(jax.vmap(lambda im, z, t: solve_lens(im, z, t, init, max_radius=8.0)))`. Arguments
    are as in `fit_lens` (`model`, or the default model's `method`, `footprint`, `downsample`),
    except that `max_radius` (pixels) is required and static, only `init` is tried (no
    multi-start), the nuisances (`exposure`, `vignetting`, `illumination`, `registration`) and
    `luma` are fitted as given (`False` by default: no score test, no selection; a registration's reach
    is not added to the band), and nothing is raised: read `.status` / `.success` (per scene under `vmap`; a
    degenerate free set gives `status == jaxdof.RESULTS.degenerate`, circles all under half a
    pixel `jaxdof.RESULTS.dead_zone`). Circles above `max_radius` are clamped and not detected
    here; `notes` is empty, `message` the status's message. A focus that the data pull beyond
    infinity is not settled there as `fit_lens` does (one solve, no active-set step): the solver
    can stall next to it (`status == jaxdof.RESULTS.max_steps`); and an error raised while the
    solve runs (a forward model's run-time check) is raised, not reported.

    `border` as in `fit_lens`: by default the band of `forward.border_band(max_radius)` photo
    pixels along the edges (`ceil(max_radius)` for the default model) is left out of the
    residual, since its pixels receive light from outside the frame; here the band is decided
    from the shapes alone (it falls back to no band only when it covers the whole photo; weights
    that leave no pixel inside it are not detected under `jit`). `FitResult.border` and
    `pixels_used` say what was used.
    """
    forward = forward_model(model, method=method, footprint=footprint, downsample=downsample)
    free, shared = _check_names(free, shared)
    check_differentiable(forward)
    band = level_band(check_border(border), forward, float(max_radius), 0)
    image, depth, targets, sqrt_w, base, single = _prepare(
        image, depth, targets, init, weight, forward
    )
    mask = border_mask(targets.shape[1:3], band)
    if not mask.any():  # the band covers the photo: keep every pixel rather than none
        band, mask = 0, border_mask(targets.shape[1:3], 0)
    mask = mask[None, :, :, None] if targets.ndim == 4 else mask[None]
    sqrt_w = sqrt_w * jnp.asarray(mask, sqrt_w.dtype)
    on = {
        "exposure": exposure,
        "vignetting": vignetting,
        "illumination": illumination,
        "registration": registration,
    }
    spec = _Spec(free, shared, targets.shape[0], canonical(k for k, v in on.items() if v), luma)
    if spec.luma:
        targets, sqrt_w = luma_targets(targets, sqrt_w)
    layout = spec.layout(base, depth)
    residual = _Model(
        targets.shape[0], float(max_radius), spec.nuisances, forward, len(spec.used), spec.luma
    )
    if solver is None:
        solver = default_solver(image.dtype)
    args = (image, depth, targets, sqrt_w, layout)
    y0 = residual.pack(base, layout)
    result = _solve_one(residual, solver, y0, args, int(max_steps), spec, single, band)
    return dataclasses.replace(result, border=band)
