r"""`fit_lens`'s multi-start solve: every start in lockstep, and a start stopped once its pace
shows it cannot catch up with one that has converged.

**Why.** The starts of a fit are solved together (one compiled solve; `solve.fit_starts`), so
the solve lasts as long as its slowest start. A start that leaves its basin early can go on for
the whole step budget while losing almost nothing: on the ray-traced `texture` scene (A = 0.1,
d_f = 3 m) one of four starts overshot on its first step to 8.6 times its f-number, where the
circles are under a pixel, and crawled towards `d_f -> f`, `N -> 83` for all 100 steps, its loss
falling 0.1-0.3 % per step at 45 times the loss the other three had converged to by step 46. The
fit reported the converged lens, after twice the steps.

**The rule.** After each step, with `L*` the lowest loss among the starts that have converged, a
start still running is stopped (its status: out of steps, not converged) when it has run at
least `window` steps and

$$L_s(t) - \frac{L_s(t - w) - L_s(t)}{w} \, (T - t) \; > \; L^* + \Delta,$$

`L_s(t)` its loss at its last accepted point after step `t`, `w = window`, `T` the step budget,
and `Delta` the margin within which `_pick_best` counts two losses as tied (`tie_margin`): at the
pace of its last `w` steps it would end the budget above the converged start, so it can neither
become the reported start nor tie with it (the near/far ambiguity test reads only converged
starts). A start that stopped this way is never the reported one, since its loss is above `L*`.
Losses decelerate under Levenberg-Marquardt, so the straight-line projection promises a start
more than it will reach; the rule errs on the side of running. It can cut a start that stalls on
a plateau and would then fall steeply; `fits/raytraced_default.py` (48 ray-traced lenses) and
`fits/recover.py` (noisy synthetic fits) measured no reported lens changed by it.

The driver is optimistix's iterative loop (`init`, then `step` and `terminate` until done, then
`postprocess`) over all starts at once, with the pace test between steps. Each step advances
the running starts one at a time (a `lax.cond` per start), so a start that has converged or
stopped costs nothing while the others run (a vmapped step would compute every start for as
long as the slowest one runs). It needs the residual at each start's accepted point, which the
Gauss-Newton family (Levenberg-Marquardt, Dogleg, Gauss-Newton) keeps in its state; for other
solvers `race` returns None and the caller solves the starts independently.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Bool, Float


# Steps over which a running start's pace is measured. Long enough to span a few rejected
# Levenberg-Marquardt steps (which leave the loss unchanged), short against the budget.
PACE_WINDOW = 10


def tie_margin(lowest, n, p: int, floor):
    """The loss above `lowest` within which another start ties with it: `2 sigma^2` per free
    parameter, `sigma^2 = 2 lowest / (n - p)` estimated from the lowest loss (`n` residuals, `p`
    parameters), plus `floor` for rounding. Shared by `solve._pick_best` and the race."""
    sigma2 = 2 * lowest / jnp.maximum(n - p, 1)
    return 2.0 * sigma2 * p + floor


def cannot_catch_up(before, loss, steps_left, window: int, target):
    """Whether a start whose loss went from `before` to `loss` over its last `window` steps ends
    its `steps_left` steps above `target` at that pace (the straight line of the module
    docstring)."""
    pace = (before - loss) / window
    return loss - pace * steps_left > target


def _accepted_residual(state) -> Array | None:
    """The residual at the last accepted point, where the solver's state keeps one (the
    Gauss-Newton family's `f_info`), else None."""
    f_info = getattr(state, "f_info", None)
    residual = getattr(f_info, "residual", None)
    return residual if isinstance(residual, jax.Array) else None


def accepted_point(state) -> tuple[Array, Array] | None:
    """The residual and the Jacobian (as a matrix) at the solver's last accepted point, or None
    (`solve._outcome` reads the Jacobian there)."""
    residual = _accepted_residual(state)
    op = getattr(getattr(state, "f_info", None), "jac", None)
    if residual is None or not isinstance(op, lx.AbstractLinearOperator):
        return None
    return residual, op.as_matrix()


def race(
    model: Callable[[Array, Any], Array],
    solver: optx.AbstractLeastSquaresSolver,
    y0s: Float[Array, "S P"],
    args,
    max_steps: int,
    tie: tuple[Any, Any, Any],
    options: dict | None = None,
    window: int = PACE_WINDOW,
    live: Bool[Array, " S"] | None = None,
):
    """Solve from every start `y0s` in lockstep, stopping a start that cannot catch up (module
    docstring). `model(y, args)` is the residual (`residual._Model`); `tie` is `(n, p, floor)`
    of `tie_margin`; `options` go to the solver (as `optimistix.least_squares`'s). `live`: the
    rows of `y0s` that are starts (default every row); the others only pad the batch to a shape
    compiled once for fits of fewer starts, and are never evaluated (their result: diverged).

    Returns `(ys, result, num_steps, states, stopped)`: per start its solution, optimistix result,
    steps taken, final solver state and whether the pace rule stopped it; None where the solver
    keeps no residual in its state."""
    if not isinstance(solver, optx.AbstractLeastSquaresSolver):
        return None
    fn = eqx.filter_closure_convert(lambda y, a: (model(y, a), None), y0s[0], args)
    f_struct = jax.eval_shape(model, y0s[0], args)
    options = {} if options is None else options
    tags: frozenset = frozenset()

    init = lambda y: solver.init(fn, y, args, options, f_struct, None, tags)

    def step(y, state):
        y, state, _ = solver.step(fn, y, args, options, state, tags)
        done, result = solver.terminate(fn, y, args, options, state, tags)
        finite = jnp.all(jnp.isfinite(y))
        return y, state, done, optx.RESULTS.where(finite, result, optx.RESULTS.nonfinite)

    n_starts = y0s.shape[0]
    if live is None:  # every row a start: the batch's initial states in one vmapped call
        dynamic0, static = eqx.partition(eqx.filter_vmap(init)(y0s), eqx.is_array)
        live, rows, n_live = jnp.ones(n_starts, bool), jnp.arange(n_starts), n_starts
    else:
        live = jnp.asarray(live, bool)
        rows, n_live = _live_rows(live)
        dynamic0, static = _initial_states(init, y0s, rows, n_live)
    state0 = eqx.combine(dynamic0, static)
    if _accepted_residual(state0) is None:
        return None
    done0, result0 = eqx.filter_vmap(lambda y, s: solver.terminate(fn, y, args, options, s, tags))(
        y0s, state0
    )
    result0 = eqx.filter_vmap(
        lambda m, r: optx.RESULTS.where(m, r, optx.RESULTS.nonlinear_divergence)
    )(live, result0)

    def cond(carry):
        _, _, _, running, _, _, _, t = carry
        return jnp.any(running) & (t < max_steps)

    def body(carry):
        ys, dynamic, result, running, stopped, steps, history, t = carry
        done = jnp.zeros(n_starts, bool)
        ys, dynamic, done, result = jax.lax.fori_loop(
            0, n_live, _one_at_a_time(step, static, running, rows), (ys, dynamic, done, result)
        )
        steps = steps + running.astype(steps.dtype)
        t = t + 1
        loss = _accepted_loss(eqx.combine(dynamic, static))
        ok = result == optx.RESULTS.successful
        running = running & ~done & ok
        stop, history = _pace(running, stopped, ok, loss, history, t, max_steps, window, tie)
        return ys, dynamic, result, running & ~stop, stopped | stop, steps, history, t

    running0 = ~done0 & (result0 == optx.RESULTS.successful)
    history0 = jnp.full((window, n_starts), jnp.inf, jnp.result_type(float))
    stopped0, steps0 = jnp.zeros(n_starts, bool), jnp.zeros(n_starts, jnp.int32)
    carry = (y0s, dynamic0, result0, running0, stopped0, steps0, history0, jnp.array(0, jnp.int32))
    ys, dynamic, result, running, stopped, steps, _, _ = jax.lax.while_loop(cond, body, carry)
    state = eqx.combine(dynamic, static)
    # Out of budget: still running at the end, or stopped by the pace rule.
    out_of_steps = (running | stopped) & (result == optx.RESULTS.successful)
    result = eqx.filter_vmap(
        lambda m, r: optx.RESULTS.where(m, optx.RESULTS.nonlinear_max_steps_reached, r)
    )(out_of_steps, result)
    post = lambda y, st, r: solver.postprocess(fn, y, None, args, options, st, tags, r)[0]
    return eqx.filter_vmap(post)(ys, state, result), result, steps, state, stopped


def _live_rows(live) -> tuple[Array, Array]:
    """The indices of the live rows first (in order), and how many there are: the loops over the
    starts run over those only, so a padding row costs nothing per step."""
    return jnp.argsort(~live, stable=True), jnp.sum(live)


def _initial_states(init, y0s, rows, n_live):
    """The solver's initial state of every live start (`rows[:n_live]`, `_live_rows`; `init`, one
    start at a time), zeros in the padding rows: `(dynamic, static)` as `equinox.partition` splits
    a batch of states."""
    struct = eqx.filter_eval_shape(init, y0s[0])
    is_leaf = lambda x: isinstance(x, jax.ShapeDtypeStruct)  # noqa: E731
    dynamic, static = eqx.partition(struct, is_leaf)
    zeros = jax.tree_util.tree_map(
        lambda x: jnp.zeros((y0s.shape[0], *x.shape), x.dtype), dynamic, is_leaf=is_leaf
    )

    def one(k, dyn):
        s = rows[k]
        new = eqx.partition(init(y0s[s]), eqx.is_array)[0]
        return jax.tree_util.tree_map(lambda x, v: x.at[s].set(v), dyn, new)

    return jax.lax.fori_loop(0, n_live, one, zeros), static


def _one_at_a_time(step, static, running, rows):
    """The loop body that steps live start `rows[k]` (`_live_rows`) where it is still running,
    one start at a time: a start that has stopped costs nothing (a vmapped step computes every
    start, converged or not, as long as the slowest one runs). The carry is `(ys, dynamic states,
    done, result)`."""

    def advance(k, c):
        s = rows[k]

        def go(c):
            ys, dynamic, _, _ = c
            state = eqx.combine(jax.tree_util.tree_map(lambda x: x[s], dynamic), static)
            y, state, d, r = step(ys[s], state)
            new = (y, eqx.partition(state, eqx.is_array)[0], d, r)
            return jax.tree_util.tree_map(lambda x, v: x.at[s].set(v), c, new)

        return jax.lax.cond(running[s], go, lambda c: c, c)

    return advance


def _accepted_loss(state) -> Float[Array, " S"]:
    """Each start's loss at its last accepted step (in the default float dtype)."""
    r = _accepted_residual(state)
    assert r is not None  # checked on the initial state; the state's type does not change
    r = r.astype(jnp.result_type(float))
    return 0.5 * jnp.sum(r * r, axis=-1)


def _pace(running, stopped, ok, loss, history, t, max_steps: int, window: int, tie):
    """The pace rule after step `t`: which running starts to stop (they cannot reach the best
    converged loss plus the tie margin in the steps left), and the loss history with this step's.
    `history[t % window]` holds the loss after step `t - window` (step 0 is the dummy before the
    first evaluation, hence `t > window`)."""
    converged = ~running & ~stopped & ok
    best = jnp.min(jnp.where(converged, loss, jnp.inf))
    slot = t % window
    target = best + tie_margin(best, *tie)
    behind = cannot_catch_up(
        history[slot], loss, (max_steps - t).astype(loss.dtype), window, target
    )
    stop = running & (t > window) & jnp.isfinite(best) & behind
    return stop, history.at[slot].set(loss)
