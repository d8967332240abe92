r"""`fit_lens`: checks, then the parts in order: starts, pyramid, full-resolution solve with the
window policy, statistics, and the verdict in words.

The two compiled calls per level (`solve.fit_starts`, `solve.finish`) run through
`solve.run_stage`; everything between them is numpy on the host. An error raised while they run
(a forward model's run-time check, a NaN under `jax_debug_nans`) becomes a failed `FitResult`.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import scipy.stats
from jaxtyping import ArrayLike

from .. import _tuning
from .._corrections import depth_edges
from .._filters import AbstractMethod
from .._filters.common import is_concrete
from .._lens import ThinLens
from .._upsample import upsample_depth
from .forward import AbstractForwardModel
from .layout import LENS_FIELDS, nuisance_names, pack, theta_floor
from .lm import bounded
from .photo import _LANCZOS, FRAMED, NUISANCES, canonical, chroma_detail, half_diagonal
from .prepare import (
    Problem,
    _check_names,
    _check_options,
    check_differentiable,
    forward_model,
    leave_out_holes,
    prepare_problem,
)
from .residual import _Model
from .result import RESULTS, FitResult, _degeneracy_text, code_of, degeneracy_reason, member
from .select import (
    alternatives,
    decisions,
    kept,
    nuisance_floor,
    prefers,
    refit_call,
    rounding_sigma,
    same_pixels,
    selected,
    with_nuisances,
)
from .solve import (
    default_solver,
    degenerate_at,
    finish,
    fit_starts,
    nuisance_scores,
    restate,
    run_stage,
    stage_note,
)
from .strategies import (
    _COARSE_TOL,
    _check_pyramid,
    _downsample,
    _next_starts,
    apply_border,
    auto_levels,
    check_border,
    distinct,
    level_band,
    reduced_window,
    start_lenses,
    window_for,
)
from .tiles import (
    Tiles,
    choose_tiles,
    edge_free,
    fits_tiles,
    given_tiles,
    jacobian_information,
    pixel_information,
    scout_factor,
    scout_problem,
    tile_boxes,
    tiled_problem,
    use_tiles,
)
from .treatment import check_edge_weight, treat_scene
from .verbose import _with_verbose


# Errors that running the compiled solve can raise on valid inputs: a run-time check
# (`equinox.error_if`, e.g. in a user's forward model: `EquinoxRuntimeError` under
# `equinox.filter_jit`, `JaxRuntimeError` under `jax.jit`, which is XLA's runtime error) or a NaN
# under `jax_debug_nans` (`FloatingPointError`). `fit_lens` reports them as a failed fit.
_SOLVER_ERRORS = (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError, FloatingPointError)

# A free focus whose coordinate `y` (`|y| ~ fcap / d_f`) ends within `_NEAR_INFINITY` of 0 (a focus
# beyond 1000 times the nearest depth: circles within 1e-3 of the largest from infinity's) is
# tried at infinity as a bound (`_settle_at_infinity`): the solver cannot settle on the kink of
# `|y|` there, and may even report convergence on it (float32, tolerance 1e-5: a start stalled at
# y = 1.5e-6 with N = 2.84 instead of 2.0 "converged").
_NEAR_INFINITY = 1e-3

# The scout's step limit (fits on tiles): its best start converged in 8 steps on the fullres
# study's 1.5 MP scene, while a start that wandered off crawled for 97 (as many as it is given).
_SCOUT_MAX_STEPS = 30


_SUCCESSFUL, _MAX_STEPS, _DEAD_ZONE, _DEGENERATE, _WINDOW, _AMBIGUOUS, _INCONSISTENT = (
    code_of(s)
    for s in (
        RESULTS.successful,
        RESULTS.max_steps,
        RESULTS.dead_zone,
        RESULTS.degenerate,
        RESULTS.window,
        RESULTS.ambiguous,
        RESULTS.inconsistent,
    )
)


@dataclasses.dataclass(frozen=True)
class _Run:
    """What the stages of one `fit_lens` call share (host side)."""

    problem: Problem
    forward: AbstractForwardModel
    solver: optx.AbstractLeastSquaresSolver
    coarse_solver: optx.AbstractLeastSquaresSolver
    verbose: bool | Callable[..., None]
    max_steps: int
    max_radius: float | None  # the user's window; None: automatic
    levels: int
    border: int | None  # the user's band (photo pixels); None: the window's (automatic)
    init_last: bool = False  # the last start is the raw init, outside the window's reach
    extra_band: int = 0  # photo pixels added to the band (a registration's reach)
    boxes: tuple | None = None  # the tiles' interiors where given (an earlier fit's)

    def residual(self, window: float) -> _Model:
        """The residual function with a given filter window."""
        spec = self.problem.spec
        return _Model(
            spec.n_targets, window, spec.nuisances, self.forward, len(spec.used), spec.luma
        )

    def solve(self, window: float, y0s, args, level: int, solver, max_steps: int | None = None):
        """One `fit_starts` stage at pyramid `level` (0: full resolution) with `window` (that
        level's pixels): model, solution, its `info` on the host, the `args` solved (the border
        band's weights set to 0: data, so every band shares the compiled solve), and the band
        used and the band asked for (they differ when the band would leave no pixel)."""
        model = self.residual(window)
        wanted = level_band(self.border, self.forward, window, level)
        wanted += -(-self.extra_band // 2**level)  # the registration's reach, any band
        sqrt_w, band = apply_border(args[3], wanted)
        args = (*args[:3], sqrt_w, args[4])
        tag = f"level {level} " if self.levels > 1 else ""
        solver = _with_verbose(solver, self.verbose, model, args[-1], tag)
        steps = self.max_steps if max_steps is None else min(max_steps, self.max_steps)
        solution, info = run_stage("fit_starts", fit_starts, model, solver, y0s, args, steps)
        # A handful of small arrays, in one go.
        return model, solution, jax.device_get(info), args, (band, wanted)


def _solvers(solver, dtype, verbose):
    """The full-resolution and coarse-level solvers (the default, or the user's for both)."""
    if solver is None:
        solver = default_solver(dtype)
        # A coarse level's minimum differs from the full-resolution one by the downsampling's
        # model error, so it is solved only to `_COARSE_TOL` (see `strategies.py`).
        coarse_solver = bounded(optx.LevenbergMarquardt(rtol=_COARSE_TOL, atol=_COARSE_TOL))
    else:
        coarse_solver = solver
    if verbose is not False and not hasattr(solver, "verbose"):
        raise ValueError(
            f"verbose needs a solver with a `verbose` field, got {type(solver).__name__}"
        )
    return solver, coarse_solver


def _coarse_to_fine(run: _Run, rows0: np.ndarray, window: float):
    """The starts of the full-resolution solve: the parameter vectors `(S, P)` and their lens rows
    `(S, T, 4)`.

    Coarse-to-fine: the multi-start solve runs on the coarsest level, and each finer level starts
    from the level below's solution (and a near-tie alternative, if any); the last level is the
    full-resolution problem with the full tolerance (`_full_resolution`), so the answer and its
    statistics are those of the full-resolution fit. With one level: the starts themselves.
    """
    p = run.problem
    y0_init = pack(rows0.astype(p.dtype), p.layout, p.spec.nuisances)
    if run.levels == 1:
        return y0_init, rows0
    pyr = [(p.image, p.depth, p.targets, p.sqrt_w, p.b)]
    for _ in range(run.levels - 1):
        pyr.append(_downsample(*pyr[-1], p.ratio))
    y0s, rows = y0_init, rows0  # rows: the current starts' lenses, at the full-resolution pitch
    for lev in range(run.levels - 1, 0, -1):
        im_l, dep_l, tg_l, sw_l, b_l = pyr[lev]
        # Shapes and values stay numpy; the layout keeps the full-resolution bound on f at every
        # level, so that a parameter vector means the same lens on every level.
        layout_l = dataclasses.replace(p.layout, base=b_l.astype(p.dtype))
        scale = 2.0**lev
        if run.max_radius is not None:
            win_l = window / scale  # the same extent in the scene as the full-resolution window
        else:
            win_l = reduced_window(run.forward, rows, dep_l, tg_l.shape, scale)
        args_l = (im_l, dep_l, tg_l, sw_l, layout_l)
        # (A coarse level whose band would leave no pixel keeps them all; only its starts matter.)
        _, _, info_l, _, _ = run.solve(win_l, y0s, args_l, lev, run.coarse_solver)
        y0s, rows = _next_starts(info_l, p.b, y0s, p.spec, layout_l)  # at full-resolution pitch
    # The init is refined at full resolution too: a coarse level's model error can move every
    # start into a wrong basin with the lowest coarse loss (seen on a depth-steps scene with a
    # fine texture: all four starts went to N = 17, d_f = 0.42 at 48 x 48, while the init
    # converges to the truth at 96 x 96 with a quarter of that loss), and the full-resolution
    # loss, not the coarse one, decides between them.
    y0s = np.concatenate([y0s, y0_init[:1]], axis=0)
    rows = np.concatenate([rows, rows0[:1]], axis=0)
    return y0s, rows


# When the border band leaves less than this share of the pixels, the starts first search for
# their basin on every pixel. Seen on small frames (24 x 24 scenes of `fits/recover.py`, band 6 px:
# a quarter of the pixels kept; a 25 x 27 photo of tests/test_downsample.py, 99 of 675 kept): from
# the same starts a third to a half of the banded fits settled in a wrong basin while reporting
# success, and every one of them converged with the band off. The border's bias is a few percent of
# the blur scale at most, far inside the right basin, so the banded solve then refines from there.
_SEARCH_ALL_BELOW = 0.5


def _search_on_every_pixel(run: _Run, window: float, y0s):
    """The starts, moved to the solutions of a solve on every pixel (no border band) when the band
    would leave few pixels (`_SEARCH_ALL_BELOW`); unchanged otherwise. Same compiled stage (the band
    is data), same number of starts."""
    p = run.problem
    band = level_band(run.border, run.forward, window, 0)
    kept, _ = apply_border(np.ones((1, *p.photo[:2]), np.float32), band)
    if band == 0 or kept.mean() >= _SEARCH_ALL_BELOW:
        return y0s
    _, _, info, _, _ = dataclasses.replace(run, border=0).solve(window, y0s, p.args, 0, run.solver)
    return np.where(np.isfinite(info["ys"]), info["ys"], y0s).astype(np.asarray(y0s).dtype)


def _shrink_window(run: _Run, window: float, r_final: float, info):
    """A refit with the window the solution's circles need, when that is smaller than the one
    the starts needed (`None` otherwise, or with a given `max_radius`).

    The automatic window and its border band follow the largest circle of any start (starts
    spread in diopters make large circles), so the band can leave out far more of the photo than
    the fitted lens requires: on a ray-traced slanted plane with circles under 3 px, four starts
    set a 10 px window and band, and the lowest-loss start there was 20 % off in K, while the
    4 px window of the fitted circles keeps 37 % more pixels. Every start is solved again from
    where it ended, so the larger set of pixels decides between them."""
    if run.max_radius is not None:
        return None
    p = run.problem
    smaller = window_for(r_final, float(max(p.photo)))
    if smaller >= window:
        return None
    ys = np.where(np.isfinite(info["ys"]), info["ys"], 0).astype(np.asarray(info["ys"]).dtype)
    model, solution, info2, args, bands = run.solve(smaller, ys, p.args, 0, run.solver)
    r2 = run.forward.max_circle(np.asarray(info2["natural"], np.float64), p.d)
    if r2 > smaller:  # the refit's circles outgrow it: keep the first solve
        return None
    return model, solution, info2, args, bands, smaller, r2


def _full_resolution(run: _Run, y0s, rows: np.ndarray, window: float):
    """The full-resolution multi-start solve, refitted (up to twice) with a larger window when
    the automatic one turns out too small for the solution's circles.

    Every refit leaves out the border band of its own window. Returns the residual model, the
    chosen solution (for `finish`), its `info`, the largest fitted circle (px), the final window
    (px), the notes, the `args` solved (weights with the band applied) and the band (px)."""
    p = run.problem
    cap = float(max(p.photo))
    if run.levels > 1 and run.max_radius is None:
        window = _fine_window(run, rows)
    notes = []
    y0s = _search_on_every_pixel(run, window, y0s)
    model, solution, info, args, (band, wanted) = run.solve(window, y0s, p.args, 0, run.solver)
    r_final = run.forward.max_circle(np.asarray(info["natural"], np.float64), p.d)
    for _ in range(2):
        if r_final <= window or run.max_radius is not None:
            break
        notes.append(
            f"the window {window:g} px was too small for the fitted circles ({r_final:.3g} px); refitted"
        )
        window = window_for(r_final, max(cap, 1.5 * r_final + 1.0))
        best = int(info["best"])
        y0s = np.concatenate([info["ys"][best][None], info["ys"]], axis=0)
        model, solution, info, args, (band, wanted) = run.solve(window, y0s, p.args, 0, run.solver)
        r_final = run.forward.max_circle(np.asarray(info["natural"], np.float64), p.d)
    shrunk = _shrink_window(run, window, r_final, info)
    if shrunk is not None:
        model, solution, info, args, (band, wanted), window, r_final = shrunk
    solved = _settle_at_infinity(run, window, (model, solution, info, args))
    if solved is not None:
        model, solution, info, args, note = solved
        notes.extend([note] if note else [])
        r_final = run.forward.max_circle(np.asarray(info["natural"], np.float64), p.d)
    if band != wanted:
        notes.append(
            f"the border band of {wanted} px (where light from outside the frame lands) leaves no "
            "pixel with non-zero weight: fitted with every pixel (border 0), so the pixels near "
            "the edges, which lack that light, bias the fit; use a larger image"
        )
    return model, solution, info, r_final, window, notes, args, band


def _stage(verbose, text: str) -> None:
    """Tell a `verbose` callable with a `stage` method, and an enclosing `watch_stages`, what
    `fit_lens` does outside the solver."""
    stage = getattr(verbose, "stage", None)
    if callable(stage):
        stage(text)
    stage_note(text)


def _fine_window(run: _Run, rows: np.ndarray, depth: np.ndarray | None = None) -> float:
    """The full-resolution window after coarse levels: the reach of the starts' circles over
    `depth` (default: the problem's). On tiles the raw init, when `_on_tiles` appends it as the
    last start (`run.init_last`), does not widen it: its circles (often the largest, from a
    start far off) would set the cost of every step of a large photo (24 MP, f/5.6 at 2 m for an
    f/8 truth: a 32 px window for 13 px circles). Its render is then clamped to the window;
    should it win with circles beyond it, `_full_resolution` refits with a larger one.
    (Whole-frame fits keep the init's reach, as validated by the studies.)"""
    p = run.problem
    starts = rows[:-1] if run.init_last else rows
    depth = p.d if depth is None else depth
    return window_for(run.forward.max_circle(starts, depth), float(max(p.photo)))


# A start whose scout solution lies within this share of the best one's fields (relative) is in
# the best one's basin: its raw init is not solved again at full resolution (`_init_elsewhere`).
_SAME_BASIN = 0.05


def _init_elsewhere(info, p: Problem, layout) -> bool:
    """Whether the scout solve left the init (start 0) outside the basin of its best solution
    (not converged, or a lens more than `_SAME_BASIN` away in some field), so that the raw init
    is worth a full-resolution solve of its own. `_coarse_to_fine` refines it at full resolution
    always (a coarse level's model error once sent every start to a wrong basin on a 48 x 48
    level); on a scout of a large photo whose init solution joins the best, that start only
    wanders: on the 1.5 MP scene of `fits/fullres.py` it went off to f/194 at full resolution,
    tripling the solve's steps (lockstep) and its cost per step. When the best did not converge,
    every start, the init's included, goes on anyway (`_next_starts`)."""
    best = int(info["best"])
    if not bool(info["converged"][best]):
        return False
    used = list(p.spec.used)
    theta = np.asarray(info["theta"], np.float64)[:, used]
    floor = np.asarray(theta_floor(layout, p.spec.nuisances), np.float64)[used]
    size = np.maximum(np.abs(theta[best]), floor)
    return not bool(info["converged"][0]) or distinct(
        theta[0], theta[best], floor, slack=_SAME_BASIN * size
    )


def _on_tiles(run: _Run, rows0: np.ndarray, window: float, budget: int, levels: int | None):
    """A fit on tiles up to its full-resolution solve: `(run, y0s, rows, tiles)`, `run` on the
    mosaic of the tiles (levels 2 with a scout solve, else 1), the starts of the
    full-resolution solve and their lens rows.

    The starts are solved on a scout, the whole photo box-averaged by `q` (`scout_factor`), the
    coarse level of a two-level pyramid; the information that chooses the tiles is that of the
    scout solve's best solution (its Jacobian, which the solve returns anyway), and their halos
    hold the reach of the full-resolution window (`_fine_window`). So the tiles are chosen at a
    lens near the photo's, not at the init, whose circles may be far off; and a fit compiles
    three stages (scout, full resolution, statistics). With one start, or no room to reduce the
    photo (`q = 1`), the tiles are chosen at the init (a `restate` on a reduced copy) and every
    start is solved at full resolution on them."""
    p, forward = run.problem, run.forward
    _stage(run.verbose, f"choosing tiles: {budget} of {p.photo[0] * p.photo[1]} photo pixels")

    def choose(win: float, information) -> Tiles | None:
        # An earlier fit's tiles where given and their halos fit, so that it is compared with
        # this one on the same pixels (`select.same_pixels`); else chosen here.
        given = None if run.boxes is None else given_tiles(p.photo, forward, win, run.boxes)
        return given or choose_tiles(p, forward, win, budget, information)

    q = scout_factor(p.photo, forward.max_circle(rows0, p.d), levels)  # levels 1: one start
    y0_init = pack(rows0.astype(p.dtype), p.layout, p.spec.nuisances)
    if q == 1:
        chosen = choose(window, lambda: pixel_information(p, forward, rows0))
        assert chosen is not None  # `fits_tiles` said there is room
        run = dataclasses.replace(run, problem=tiled_problem(p, chosen), border=0, levels=1)
        return run, y0_init, rows0, chosen
    (im, dep, tg, sw, b), _ = scout_problem(p, q)
    layout = dataclasses.replace(p.layout, base=b.astype(p.dtype))
    if run.max_radius is not None:
        win = run.max_radius / q  # the same extent in the scene
    else:
        win = reduced_window(forward, rows0, dep, tg.shape, q)
    run = dataclasses.replace(run, levels=2)
    level = q.bit_length() - 1
    # The scout only finds the basin: a start still crawling after `_SCOUT_MAX_STEPS` (towards
    # f/300 and a focus at 0.1 m on the 1.5 MP study, 97 lockstep steps) is far behind the best.
    _, solution, info, _, _ = run.solve(
        win, y0_init, (im, dep, tg, sw, layout), level, run.coarse_solver, _SCOUT_MAX_STEPS
    )
    y0s, rows = _next_starts(info, p.b, y0_init, p.spec, layout)  # at full-resolution pitch
    if _init_elsewhere(info, p, layout):
        # The init is refined at full resolution too (as in `_coarse_to_fine`).
        y0s = np.concatenate([y0s, y0_init[:1]], axis=0)
        rows = np.concatenate([rows, rows0[:1]], axis=0)
        run = dataclasses.replace(run, init_last=True)
    fine = window if run.max_radius is not None else _fine_window(run, rows)
    jac = solution[5]

    def information():
        return jacobian_information(jax.device_get(jac), tg.shape, p.spec.used), q

    # (The init's window had room for tiles; a larger fine window may not: then its halos.)
    chosen = choose(fine, information) or choose(window, information)
    assert chosen is not None
    if run.max_radius is None:
        # The halos were sized for circles over the whole scene's depths; the tiles hold fewer.
        crops = chosen.mosaic(p.depth, p.ratio, 0, np.nan)
        reach = _fine_window(run, rows, crops[~np.isnan(crops)])
        halo = min(int(forward.border_band(reach)), chosen.halo)
        chosen = dataclasses.replace(chosen, halo=halo)
    run = dataclasses.replace(run, problem=tiled_problem(p, chosen), border=0)
    return run, y0s, rows, chosen


def _fields_text(names, theta) -> str:
    """`name=value` for solution slots `theta` (statistical units: the focus as its power), the
    focus shown as a distance (m; `inf` at power 0)."""
    parts = []
    for n, v in zip(names, np.asarray(theta, np.float64)):
        if n.startswith("focus_distance"):
            v = np.inf if v <= 0 else 1 / v
        parts.append(f"{n}={v:.5g}")
    return ", ".join(parts)


def _settle_at_infinity(run: _Run, window: float, solved):
    """Focus at infinity as an active bound: `None`, or a better solve settled there and a note.

    Where the data pull a free focus beyond infinity (`dL/dw > 0` at `w = 0`, `layout.py`) the
    loss has a kink at `y = 0`, on which Levenberg-Marquardt cannot settle: it cycles across it,
    and the other fields stall with it (a start at infinity with the wrong `N` never leaves).
    For the starts whose focus ended near infinity (`_NEAR_INFINITY`, converged or not) this
    does what a bound-constrained method would, on the same
    compiled stage: (1) solve with those foci fixed at infinity (a layout whose focus slots
    nobody reads: data, not code); (2) the pull `dL/dw` at the best such solution with them free
    again (`restate`); (3) every pull `>= 0`: the bound is active and that is the solution, with
    its statistics taken with the focus free; else solve with the focus free from there, the data
    pulling it in. The result replaces the first solve's where its loss is lower (`_better`); so
    steps (2) and (3) run only when (1) beats the first solve.
    """
    _, _, info0, _ = solved
    p = run.problem
    src, use = np.asarray(p.layout.src), np.asarray(p.layout.use)
    slots = np.unique(src[:, 2][use[:, 2]])  # the free focus slots
    ys = np.array(info0["ys"])
    near = np.abs(ys[:, slots]) <= _NEAR_INFINITY  # (starts, slots)
    if not np.any(near):
        return None
    loss = np.where(near.any(axis=1), info0["loss"], np.inf)
    fix = slots[near[int(np.argmin(loss))]]  # those of the lowest-loss start near infinity
    fixed = use[:, 2] & np.isin(src[:, 2], fix)
    base, use_fixed = np.array(p.layout.base), use.copy()
    base[fixed, 2], use_fixed[fixed, 2] = np.inf, False
    layout = dataclasses.replace(p.layout, base=base, use=use_fixed)
    ys[:, fix] = 0
    model, solution, info, args, _ = run.solve(window, ys, (*p.args[:4], layout), 0, run.solver)
    if not _better(info, info0):
        # Settled at infinity, no start beats the first solve's best, so the bound cannot be the
        # answer; what is left is a re-solve inward from there, of starts the first solve already
        # ran. Skipping it skips compiling `restate` (2.1 s of the ray-traced pentagon's 16.8 s,
        # A = 0.03 m, d_f = 1.8 m, where a start the race stopped at 25 times the best loss
        # ended near infinity); no settle in tests/test_fit.py or the default study won that way.
        return None
    y = solution[0]
    args = (*args[:4], p.layout)  # the band applied, the focus free again
    residual, theta, jac, g = run_stage("restate", restate, model, y, args)
    pull = np.asarray(jac, np.float64)[:, fix].T @ np.asarray(residual, np.float64)
    names = ", ".join(p.spec.names[p.spec.used.index(int(k))] for k in fix)
    if np.all(pull >= 0):
        info = {**info, "natural": np.asarray(model.natural(jnp.asarray(y), p.layout))}
        solution = (y, solution[1], solution[2], residual, theta, jac, g)
        note = f"{names} fitted at infinity: the data pull it no closer (focus at infinity bounds a lens)"
    else:
        model, solution, info, args, _ = run.solve(window, info["ys"], p.args, 0, run.solver)
        note = None
    return (model, solution, info, args, note) if _better(info, info0) else None


def _better(new, old) -> bool:
    """Whether solve `new`'s best start beats `old`'s: a lower loss, or a tie (to 1e-9) that
    converged where the other did not."""
    bn, bo = int(new["best"]), int(old["best"])
    ln, lo = float(new["loss"][bn]), float(old["loss"][bo])
    tie = ln <= lo * (1 + 1e-9) and lo <= ln * (1 + 1e-9)
    converged = bool(new["converged"][bn]) and not bool(old["converged"][bo])
    return (ln < lo and not tie) or (tie and converged)


def _ambiguity(info, p: Problem) -> str | None:
    """The near/far ambiguity: another converged start at a distinct lens, with a loss the noise
    cannot tell from the best one (within ~2 sigma^2 per parameter, or rounding when noise-free).
    Returns the note naming it, or None."""
    loss, converged, best = info["loss"], info["converged"], int(info["best"])
    if len(loss) < 2:
        return None
    spec = p.spec
    used = list(spec.used)
    theta = np.asarray(info["theta"], np.float64)[:, used]
    floor = np.asarray(theta_floor(p.layout, spec.nuisances), np.float64)[used]
    sigma2 = float(info["sigma"]) ** 2
    n_p = len(used)
    floor_loss = float(jnp.finfo(p.dtype).eps) * float(
        np.sum(np.asarray(p.targets, np.float64) ** 2)
    )
    se = np.sqrt(np.maximum(np.asarray(info["variance"], np.float64), 0))
    for i in np.argsort(loss):
        if i == best or not converged[i]:
            continue
        tie = loss[i] - loss[best] <= 2.0 * sigma2 * n_p + 10 * floor_loss
        if tie and distinct(theta[i], theta[best], floor, slack=10 * se):
            alt = _fields_text(spec.names, theta[i])
            return (
                f"another start converged to {alt} with loss {loss[i]:.4g} (best {loss[best]:.4g})"
            )
    return None


def _undetermined(info, spec) -> tuple[str, ...]:
    """The free fields (without target index) whose variance at the solution is infinite."""
    var = np.asarray(info["variance"], np.float64)
    bad = {n.split("[")[0] for n, v in zip(spec.names, var) if not np.isfinite(v)}
    return tuple(n for n in (*LENS_FIELDS, "gain", "offset") if n in bad)


def _at_infinity(run: _Run, rows: np.ndarray) -> bool:
    """Whether every target's focus is at (or near) infinity: moving it to infinity changes no
    circle by more than 1 % of the largest (the circle of a point at infinity, `K`, is under 1 %
    of the largest circle in the scene)."""
    far = np.array([np.inf])
    rows = np.asarray(rows, np.float64)
    return all(
        run.forward.max_circle(r, far) <= 0.01 * run.forward.max_circle(r, run.problem.d)
        for r in rows
    )


def _infinity_notes(result: FitResult, spec) -> list[str]:
    """Notes on free focus distances consistent with infinity (power within one standard error
    of infinity's, `solve._focus_to_distance`): their `stderr` is `inf`; the power and its
    standard error say what is known."""
    if "focus_distance" not in spec.free:
        return []
    power = np.asarray(result.lenses.focus_power, np.float64).reshape(-1)
    se = np.broadcast_to(np.asarray(result.focus_power_stderr, np.float64).reshape(-1), power.shape)
    se_d = np.broadcast_to(np.asarray(result.stderr["focus_distance"]).reshape(-1), power.shape)
    d_f = np.asarray(result.lenses.focus_distance, np.float64).reshape(-1)
    ts = range(1 if "focus_distance" in spec.shared else len(power))
    notes = []
    for t in ts:
        if np.isinf(se_d[t]) and np.isfinite(se[t]):
            tag = f"[{t}]" if spec.n_targets > 1 and "focus_distance" not in spec.shared else ""
            notes.append(
                f"focus_distance{tag} = {d_f[t]:.4g} m is consistent with focus at infinity "
                f"(focus power {power[t]:.3g} +- {se[t]:.2g} dpt): it has no finite standard error"
            )
    return notes


def _tiles_note(tiles: Tiles, photo_pixels: int) -> str:
    """What the fit on tiles used, in words."""
    n = len(tiles.corners)
    return (
        f"fitted on {n} tiles of {tiles.side} x {tiles.side} px ({n * tiles.side**2} of "
        f"{photo_pixels} photo pixels), chosen for their information about the lens (halo "
        f"{tiles.halo} px; tiles=None fits the whole frame)"
    )


def _inconsistency_note(result: FitResult) -> str:
    """The adequacy test's numbers, in words, for a fit it found inconsistent."""
    a = {k: float(np.asarray(v)) for k, v in result.adequacy.items()}
    return (
        f"{a['tiles']:g} tiles of the photo disagree on the lens beyond their noise (chi2 "
        f"{a['chi2']:.4g} on {a['dof']:g} dof, p = {a['p_value']:.2g}): stderr inflated "
        f"{a['inflation']:.3g}x to their spread"
    )


# How strongly the residual's map must follow a pattern (a correlation over its cells) to name
# that pattern's cause (`_cause`), and the spread under which it is "everywhere alike".
_PATTERN = 0.5
_ALIKE = 2.0


def _cause(cells: np.ndarray, p) -> str:
    """The likely cause of a fit's inconsistency, from where its residual is large
    (`solve.residual_map`, mean squared residual per cell of the photo): growing towards the
    corners (vignetting) or towards two sides (light falling unevenly), along depth edges
    (occlusion the model does not render), or everywhere alike (the aperture's shape, the photo's encoding, noise or a lens
    the model does not know)."""
    ok = np.isfinite(cells)
    if ok.sum() < 4:
        return "too few regions fitted to say where the photo differs from the model"
    n = cells.shape[0]
    centre = (np.arange(n) + 0.5) / n - 0.5
    rho2 = np.add.outer(centre**2, centre**2)
    edges = depth_edges(p.d).astype(np.float64)
    h, w = edges.shape
    rows = (np.arange(h) * n // h)[:, None] == np.arange(n)[None, :]
    cols = (np.arange(w) * n // w)[:, None] == np.arange(n)[None, :]
    edge_share = (rows.T @ edges @ cols) / np.maximum(rows.T @ np.ones_like(edges) @ cols, 1)

    def corr(x):
        # (A region fitted exactly, a zero mean square, counts as a thousandth of the median.)
        floor = max(1e-3 * float(np.median(cells[ok])), np.finfo(np.float64).tiny)
        a, b = np.log(np.maximum(cells[ok], floor)), x[ok]
        if np.std(a) == 0 or np.std(b) == 0:
            return 0.0
        return float(np.corrcoef(a, b)[0, 1])

    radial, edgy = corr(rho2), corr(edge_share)
    # A gain tilted across the frame leaves, after the exposure's mean, a residual growing
    # towards two opposite sides: along one axis rather than towards every corner.
    across = np.broadcast_to(centre**2, (n, n))  # grows towards the left and right sides
    sideways = max(corr(across), corr(across.T))
    spread = float(np.nanmax(cells) / max(float(np.nanmedian(cells)), np.finfo(float).tiny))
    if edgy > _PATTERN and edgy >= radial:
        return (
            f"the residual is largest along depth edges (correlation {edgy:.2f}): likely "
            "occlusion the model renders differently (method=jaxdof.LocalOcclusion())"
        )
    if sideways > _PATTERN and sideways > radial:
        return (
            f"the residual grows towards two sides of the frame (correlation {sideways:.2f}): "
            "likely light that falls unevenly across the scene (illumination=True)"
        )
    if radial > _PATTERN:
        return (
            f"the residual grows towards the corners (correlation {radial:.2f}): likely "
            "vignetting (vignetting=True) or uneven illumination (illumination=True)"
        )
    if spread < _ALIKE:
        return (
            "the residual is alike over the photo: likely what every pixel shares, the "
            "aperture's shape, the photo's encoding, or noise the model does not know"
        )
    return (
        f"the residual is {spread:.3g}x its median in places without a radial or edge pattern: "
        "likely a depth map that does not match the photo there, or a misregistration"
    )


def _verdict(run: _Run, result: FitResult, info, r_final, window, notes, allow_degenerate):
    """The final status (ambiguity and window found on the host), the notes, and the
    `ValueError` for a free set the data cannot determine (unless `allow_degenerate`)."""
    p = run.problem
    spec = p.spec
    code = code_of(info["status"])
    if code == _INCONSISTENT:
        notes.append(_inconsistency_note(result))
        notes.append(_cause(np.asarray(info["residual_map"], np.float64), p))
    alt = _ambiguity(info, p) if code in (_SUCCESSFUL, _INCONSISTENT) else None
    if alt is not None:
        code = _AMBIGUOUS
        notes.append(alt)
    if r_final > window:
        code = _WINDOW if code in (_SUCCESSFUL, _INCONSISTENT) else code
        notes.append(
            f"the fitted lens makes circles up to {r_final:.3g} px but max_radius={window:g}"
        )
    if code in (_DEGENERATE, _DEAD_ZONE):
        why = (
            code,
            spec.free,
            spec.shared,
            spec.n_targets,
            _undetermined(info, spec),
            _at_infinity(run, info["natural"]),
            float(info["condition"]),
        )
        if info.get("determined_at_init", False):
            # Rank deficient at the best solution but not at the init: the fit ended where the
            # blur stops depending on a field (e.g. a focus near the focal length, where every
            # circle is about the same size), a local minimum and no property of the data.
            notes.append(
                f"the best solution lies where the photos do not determine "
                f"{', '.join(_undetermined(info, spec)) or ', '.join(spec.free)} (condition "
                f"{float(info['condition']):.3g} of the column-scaled Jacobian), though they do "
                "at the init lens, and the photo is not what the model renders there (the "
                "adequacy test fails): the fit ended in a flat region of the model, not a free "
                "set the data cannot determine; check the inputs, start from a lens nearer the "
                "truth (EXIF) or force a treatment of the scene"
            )
        elif not allow_degenerate:
            raise ValueError(_degeneracy_text(*why))
        elif code == _DEGENERATE:
            notes.append(
                f"free={spec.free}, shared={spec.shared}, {spec.n_targets} target(s): "
                + degeneracy_reason(*why)
            )
    elif code in (_SUCCESSFUL, _AMBIGUOUS, _WINDOW, _INCONSISTENT):
        notes.extend(_infinity_notes(result, spec))
    if code == _MAX_STEPS:
        notes.insert(0, f"max_steps={run.max_steps}")
    text = "; ".join(notes)
    if code == code_of(info["status"]):
        return dataclasses.replace(result, notes=text, levels=run.levels)
    return dataclasses.replace(
        result,
        status=member(code),
        success=jnp.asarray(code in (_SUCCESSFUL, _INCONSISTENT)),
        notes=text,
        levels=run.levels,
    )


def _error_reason(err: BaseException) -> str:
    """The first line of an error's message that says what went wrong: equinox's run-time error
    message (after its preamble on where the stack is), else the first non-empty line."""
    text = str(err)
    found = re.search(r"EquinoxRuntimeError: *(\S.*)", text)
    if found:
        return found.group(1).strip()
    return next((line.strip() for line in text.splitlines() if line.strip()), type(err).__name__)


def _untested(dtype) -> dict[str, jax.Array]:
    """The adequacy entry of a fit that never reached a solution: nothing tested (NaN)."""
    nan = jnp.asarray(np.nan, dtype)
    return dict(
        chi2=nan,
        dof=nan,
        p_value=nan,
        tiles=jnp.zeros((), jnp.int32),
        inflation=nan,
        spread=nan,
        adequate=jnp.asarray(False),
    )


def _failed(run: _Run, err: BaseException, window: float) -> FitResult:
    """A `FitResult` for a solve that raised `err`: the init lens(es), NaN statistics, status
    `solver_failed` and the reason in the notes."""
    p, spec = run.problem, run.problem.spec
    t, dtype = spec.n_targets, p.dtype
    nan = np.full((t,), np.nan, dtype)
    one = (lambda x: x[0]) if p.single else (lambda x: x)
    names = spec.free + nuisance_names(spec.nuisances)
    sqrt_w, band = apply_border(p.sqrt_w, level_band(run.border, run.forward, window, 0))
    live = np.any(sqrt_w > 0, axis=-1) if sqrt_w.ndim == 4 else sqrt_w > 0
    return FitResult(
        lenses=ThinLens(*(jnp.asarray(p.base[:, i]) for i in range(4))),
        stderr={name: jnp.asarray(one(nan)) for name in names},
        covariance=jnp.full((len(spec.used),) * 2, np.nan, dtype),
        gain=jnp.ones((t,), dtype),
        offset=jnp.zeros((t,), dtype),
        loss=jnp.asarray(np.nan, dtype),
        sigma=jnp.asarray(np.nan, dtype),
        num_steps=jnp.asarray(0),
        condition=jnp.asarray(np.nan, dtype),
        status=RESULTS.solver_failed,
        success=jnp.asarray(False),
        focus_power_stderr=jnp.asarray(one(nan)),
        pixels_used=jnp.asarray(int(np.sum(live)), jnp.int32),
        adequacy=_untested(dtype),
        names=spec.names,
        notes=f"{type(err).__name__} while solving: {_error_reason(err)}",
        max_radius=window,
        border=band,
        levels=run.levels,
    )


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
    exposure: bool | None = None,
    vignetting: bool | None = None,
    illumination: bool | None = None,
    registration: bool | None = None,
    luma: bool | None = None,
    starts: int | None = None,
    verbose: bool | Callable[..., None] = False,
    model: AbstractForwardModel | None = None,
    method: str | AbstractMethod | None = None,
    footprint: bool | None = None,
    pyramid: int | None = None,
    downsample: int | None = None,
    border: bool | str | int = "auto",
    tiles: str | int | bool | Sequence[tuple[int, int, int, int]] | None = "auto",
    edge_weight: bool | float | None = None,
) -> FitResult:
    r"""Recover lens parameters from defocused photos of a scene with known image and depth.

    Minimises, over the `free` lens fields (and the camera's nuisances where fitted),

    $$\sum_t \sum_p w_p \left( E\big(g_t V_t(p) L_t(p)\, W_t[\mathrm{model}(I, Z,
      \mathrm{lens}_t)]_p + o_t\big) - T_{t,p} \right)^2$$

    (linear light; `model` is `jaxdof.render` by default; `g, o` exposure, `V` vignetting, `L`
    illumination, `W` registration, `E` the luma encoding, each the identity unless fitted) with
    an optimistix least-squares solver from a few starts, in coordinates in which focus at infinity is the
    ordinary point 0 (`log N`, a logit of `f`, the focus power in diopters scaled to the scene).
    The photo pixels within a circle's reach of the frame's edge, which hold light from outside
    the frame, are left out (`border`).

    **Arguments:**

    - `image`: the all-in-focus linear-light image, `(H, W)` or `(H, W, C)`.
    - `depth`: z-depth (m), `(H, W)` or coarser (upsampled, `jaxdof.upsample_depth`); `inf` is
      infinitely far; NaN, 0 and negative are holes (filled; the photo pixels they reach are
      left out and counted in `FitResult.treatment`).
    - `targets`: the photo(s): one of the photo's shape, a sequence, or an array `(T, *photo)`.
    - `init`: a `ThinLens` (for every target) or one per target: the start, and the value of
      every field that is not free. `pixel_pitch` is always fixed.
    - `free`: the fields to fit, among `"focal_length"`, `"f_number"`, `"focus_distance"`.
    - `shared`: the free fields with one value across targets (a focus bracket:
      `shared=("focal_length", "f_number")`).
    - `solver`: an optimistix least-squares solver; default Levenberg-Marquardt that also stops
      when its next step is under a thousandth of a standard error (`jaxdof/_fit/lm.py`).
    - `max_steps`: the solver's step limit per start.
    - `weight`: per-pixel weights `>= 0` (inverse variances or a 0/1 mask), `(H, W)`,
      `(T, H, W)` or the targets' shape.
    - `max_radius`: the filter window (px, static); `None` sizes it from the starts' circles and
      refits with a larger one if the solution's circles outgrow it.
    - `allow_degenerate`: return a fit whose free fields the data cannot all determine
      (`success=False`, `inf` standard errors) instead of raising.
    - `exposure`, `vignetting`, `illumination`, `registration`: a gain and offset; a radial
      gain `1 + a rho^2 + b rho^4`; a gain tilted across the frame `1 + c_x u + c_y v` (a chart
      lit from one side); a shift and magnification (focus breathing), per target.
      `None` (default): fitted where a score test at the fit without it rejects and fitting it
      explains more than the model's error (`select.with_nuisances`); `True`/`False` force it.
      On tiles the gains are fitted only where forced, and registration not at all (it needs
      `tiles=None`).
    - `luma`: compare colour photos in their sRGB luma (a camera JPEG's colour is stored at half
      resolution); `None` decides from the photo's colour detail.
    - `starts`: the number of starts (default 4 with a free focus, else 3): `init`, then focus
      powers spread over the scene's depths, solved in lockstep (`race.py`).
    - `verbose`: `True` prints each step; a callable receives optimistix's `(name, value)` pairs
      and `lenses=("Lenses", ThinLens)`, every photo's lens at the last accepted step (traced).
    - `model`: a `jaxdof.AbstractForwardModel` (default `jaxdof.DefocusModel`); `method`,
      `footprint`, `downsample`: the default model's options (not with `model`).
    - `pyramid`: coarse-to-fine levels (`None`: automatic; `1`: full resolution only). The result
      is always the full-resolution fit's.
    - `border`: `"auto"`/`True` leaves out the band the window reaches, an int that many photo
      pixels, `False`/`0` none.
    - `tiles`: `"auto"` fits a photo of more than 2^20 pixels on 2^17 pixels of informative tiles
      (`jaxdof/_fit/tiles.py`); an int is that budget; `None`/`False` the whole frame; an
      earlier fit's `FitResult.tiles`, its pixels.
    - `edge_weight`: the weight ramping to 0 at depth edges: `None` decides, `False`, `True`, or a
      width in photo pixels.

    **Treatment.** By default the scene decides what is modelled (`jaxdof.scene_treatment`:
    occlusion and an edge weight at depth edges, the footprint correction for small circles),
    then the photo has its say (`jaxdof/_fit/select.py`): each choice, then each nuisance, is
    kept only where it explains the photo better on the same pixels. A photo from
    `jaxdof.render` comes back as its lens. `FitResult.treatment` and `FitResult.nuisances`
    report every choice and why; `method`, `footprint`, `edge_weight` and the nuisance flags
    force one.

    **Returns:** a `FitResult`. `success` says whether the lens and its standard errors can be
    trusted: converged, determined, unambiguous, and errors from the noise, or inflated to the
    spread between tiles of the photo where they disagree on the lens (status `inconsistent`,
    a model-adequacy test at level 0.01, `jaxdof.internal.adequacy`; `notes` name the likely
    cause). Otherwise `status` (a `jaxdof.RESULTS` member) and `message` say why. Errors are
    Gauss-Newton, `sigma^2 (J^T J)^{-1}`, in the focus power, so finite through infinity.

    **Raises:** `ValueError` for bad inputs (before any solve), and when the data cannot
    determine the free fields, with the reason (`focal_length` and `f_number` both free from
    one photo: blur depends on them only through `K = f^2 / (2 N (d_f - f))` and `d_f`; focus at
    infinity; every circle under half a pixel).

    Fits of many independent scenes: `jaxdof.solve_lens` under `jax.vmap`.
    """
    call = dict(locals())
    asked = {
        "exposure": exposure,
        "vignetting": vignetting,
        "illumination": illumination,
        "registration": registration,
    }
    for name, value in (*asked.items(), ("luma", luma)):
        if value not in (None, True, False):
            raise ValueError(f"{name} must be None (decide from the photo), True or False")
    for name in asked:
        del call[name]
    call["nuisances"] = canonical(k for k, v in asked.items() if v)
    call["test"] = canonical(k for k, v in asked.items() if v is None)
    call["luma"], luma_entry = _choose_luma(image, targets, luma)
    coarse = np.shape(depth)
    if len(coarse) == 2 and np.ndim(image) in (2, 3) and coarse != np.shape(image)[:2]:
        # A depth sensor coarser than the image: upsampled once, guided by the image.
        call["depth"] = upsample_depth(np.asarray(depth), np.asarray(image))
    else:
        coarse = ()
    result = _fit_treated(**call)
    # The photo's say in the treatment (`select.py`): each choice of the scene's changed in turn,
    # kept only where the photo prefers it ...
    rounding = rounding_sigma(targets, np.asarray(result.loss).dtype)
    result = _photo_says(result, call, rounding)
    # ... and in what the camera added: each nuisance fitted where a score test at the fit
    # without it rejects and it explains more than the model's error (`select.with_nuisances`),
    # the caller's choices as given ...
    decided = with_nuisances(result, call, _fit_treated, nuisance_floor(targets), asked)
    # ... and where the photo asked for one, the treatment asked again with it.
    result = _asked_again(decided, call, asked, rounding)
    if coarse and result.treatment is not None:
        treatment = dataclasses.replace(result.treatment, depth_upsampled=tuple(coarse))
        result = dataclasses.replace(result, treatment=treatment)
    return dataclasses.replace(result, nuisances={**(result.nuisances or {}), "luma": luma_entry})


def _asked_again(decided: FitResult, call: dict, asked: dict, rounding: float) -> FitResult:
    """`decided` (`select.with_nuisances`'s), or where it chose nuisances the caller did not
    give, the fit with them from its lens and the photo's say in the treatment again
    (`_photo_says`): a photo darker than the model made the footprint correction look worse
    (the ray-traced fgbg at exposure x 0.85 dropped it, focus 5 % off)."""
    on = canonical(k for k, v in (decided.nuisances or {}).items() if v.get("fitted"))
    if on == call["nuisances"]:
        return decided
    call = {**call, "nuisances": on, "test": ()}  # decided: no score tests again
    start = {"init": decided.lenses, "starts": 1, "pyramid": None}
    same = same_pixels(decided)
    try:
        again = _fit_treated(**{**call, **start, **same})
        again = _photo_says(again, {**call, **same}, rounding)
    except ValueError:
        return decided
    return decisions(again, decided, asked)


def _photo_says(result: FitResult, call: dict, rounding: float) -> FitResult:
    """The scene's treatment changed in turn (`select.alternatives`), each change kept only where
    the photo prefers it (`select.prefers`)."""
    for name, changes in alternatives(result, call):
        try:
            alt = _fit_treated(**refit_call(result, call, changes))
        except ValueError:  # e.g. the simpler model leaves the free set undetermined
            result = kept(result, name, -np.inf)
            continue
        better, chi2 = prefers(alt, result, rounding)
        result = selected(alt, result, name, chi2) if better else kept(result, name, chi2)
    return result


# An image whose chroma holds under this share of its luma's detail (`chroma_detail`) is grey.
_GREY_CHROMA = 1e-6


def _choose_luma(image, targets, luma: bool | None) -> tuple[bool, dict]:
    """Whether to compare the photos in their sRGB luma, and the decision's record: the caller's
    `luma`, else where a colour photo has lost the colour detail of the all-in-focus image (its
    `photo.chroma_detail` under `_tuning.LUMA_CHROMA` of the image's: a camera JPEG's chroma,
    stored at half resolution), in any of the photos. `chroma_detail` in the record is the
    smallest ratio."""
    arr = [np.asarray(t) for t in targets] if isinstance(targets, (list, tuple)) else None
    if arr is None:
        t = np.asarray(targets)
        arr = list(t) if t.ndim == 4 else [t]
    colour = np.ndim(image) == 3 and all(a.ndim == 3 and a.shape[-1] == 3 for a in arr)
    detail = math.nan
    if colour and luma is None:
        of_image = chroma_detail(np.asarray(image))
        # A grey image (a chart's raster in three channels) has no colour detail to lose: its
        # ratio is rounding over rounding, and says nothing.
        grey = not of_image > _GREY_CHROMA
        detail = math.nan if grey else min(chroma_detail(a) for a in arr) / of_image
    if luma is not None:
        return bool(luma), {"fitted": bool(luma), "forced": True, "chroma_detail": detail}
    on = bool(colour and detail < _tuning.LUMA_CHROMA)
    return on, {"fitted": on, "forced": False, "chroma_detail": detail}


def _fit_treated(
    image, depth, targets, init, *, free, shared, solver, max_steps, weight, max_radius,
    allow_degenerate, nuisances: tuple[str, ...], luma: bool, starts, verbose, model, method,
    footprint, pyramid, downsample, border, tiles, edge_weight, test: tuple[str, ...] = (),
    registration_reach=None, hole_reach=None,
) -> FitResult:  # fmt: skip
    """`fit_lens` with the scene's treatment (or the caller's): one fit, no selection; the score
    tests of the nuisances `test` (`photo.NUISANCES`) where it does not fit them."""
    given = dict(locals())  # the call, to refit on tiles chosen for a larger window
    run, treatment, rows0, window, budget, levels = _set_up(**given)
    p, full_pixels = run.problem, int(run.problem.photo[0] * run.problem.photo[1])
    chosen = None
    try:
        run, treatment, y0s, rows, chosen = _coarse_solve(
            run,
            treatment,
            rows0,
            window,
            budget,
            levels,
            own_choice=model is None and method is None,
        )
        p = run.problem
        model_r, solution, info, r_final, window, notes, args, used = _full_resolution(
            run, y0s, rows, window
        )
        result, stats = run_stage("finish", finish, model_r, solution, args, p.spec, p.single, used)
        info.update(jax.device_get(stats))
        # The score tests of the nuisances to decide, where the fit leaves something to explain
        # (`select.with_nuisances`); on tiles only those that do not depend on the whole frame.
        names = tuple(k for k in test if k not in p.spec.nuisances and not (chosen and k in FRAMED))
        if names and float(info["sigma"]) >= nuisance_floor(targets):
            scores = run_stage(
                "nuisance scores", nuisance_scores, model_r, solution, args, p.spec, names
            )
            info["nuisance_scores"] = jax.device_get(scores)
    except _SOLVER_ERRORS as err:
        failed = _failed(run, err, window)
        return dataclasses.replace(
            failed, treatment=dataclasses.replace(treatment, border=failed.border)
        )
    result = dataclasses.replace(
        result,
        border=used,
        treatment=dataclasses.replace(treatment, border=used),
        nuisances=_nuisance_entries(info, p.spec, p.photo, run.extra_band),
    )
    if "registration" in p.spec.nuisances:
        needed = _registration_reach(p.photo, info["nuisance_values"])
        if needed > run.extra_band:  # the fitted registration reads beyond the band: again
            return _fit_treated(**{**given, "registration_reach": needed})
    if chosen is not None:
        if window > chosen.halo:  # the halos no longer hold the window's reach: choose again
            again = tiles if run.boxes is not None else budget  # (given tiles where they fit)
            return _fit_treated(**{**given, "max_radius": window, "tiles": again})
        notes.append(_tiles_note(chosen, full_pixels))
        result = dataclasses.replace(result, tiles=chosen.boxes)
    # A rank-deficient solution that the photos contradict (the adequacy test fails there) while
    # they determine the free set at the init: a fit that ended in a flat region of the model,
    # not a free set the data cannot determine (that one is refused: a focus bracket all at
    # infinity is rank deficient only at its solution, which explains the photos).
    if (
        code_of(info["status"]) == _DEGENERATE
        and not allow_degenerate
        and not bool(result.adequacy["adequate"])
    ):
        info["determined_at_init"] = _determined_at_init(model_r, rows0, args, p)
    return _verdict(run, result, info, r_final, window, notes, allow_degenerate)


def _set_up(
    image, depth, targets, init, *, free, shared, solver, max_steps, weight, max_radius,
    nuisances, luma, starts, verbose, model, method, footprint, pyramid, downsample, border,
    tiles, edge_weight, registration_reach, hole_reach, **_,
):  # fmt: skip
    """`_fit_treated`'s checked problem and plan: `(run, treatment, rows0, window, budget,
    levels)`, the starts `rows0`, the window, the tiles' pixel budget (`None`: the whole frame)
    and the pyramid's levels (`None`: automatic)."""
    forward = forward_model(model, method=method, footprint=footprint, downsample=downsample)
    free, shared = _check_names(free, shared)
    check_edge_weight(edge_weight)
    check_differentiable(forward)
    if not is_concrete(image, depth, targets, init, weight):
        raise ValueError(
            "fit_lens needs concrete inputs (it picks starts and a window, and reports in Python); "
            "under jit/vmap use jaxdof.solve_lens with a static max_radius."
        )
    max_steps, n_starts = _check_options(max_steps, starts, verbose, max_radius, free)
    band = check_border(border)
    p = prepare_problem(image, depth, targets, init, weight, forward, free, shared, nuisances, luma)
    p, forward, treatment = treat_scene(p, forward, model, method, footprint, edge_weight)
    levels = _check_pyramid(pyramid, p.photo)
    solver, coarse_solver = _solvers(solver, p.dtype, verbose)
    rows0 = start_lenses(p.b, p.d, free=free, starts=n_starts, fcap=p.fcap)
    if max_radius is None:
        window = window_for(forward.max_circle(rows0, p.d), float(max(p.photo)))
    else:
        window = float(max_radius)
    # The photo pixels that a depth hole's light reaches: the init lens's circles and the
    # border's stencils (the border band of their window; the starts' window can be far
    # larger: starts spread in diopters make large circles).
    own = window_for(forward.max_circle(rows0[:1], p.d), float(max(p.photo)))
    if hole_reach is None:
        hole_reach = float(forward.border_band(min(own, window)))
    p, hole_pixels, hole_reach = leave_out_holes(p, hole_reach)
    if p.holes is not None:
        holes = int(p.holes.sum())
        treatment = dataclasses.replace(
            treatment, depth_holes=holes, hole_pixels=hole_pixels, hole_reach=hole_reach
        )
    budget, boxes = use_tiles(tiles, p.photo), tile_boxes(tiles)
    given = boxes is not None and given_tiles(p.photo, forward, window, boxes) is not None
    if budget is not None and not given and not fits_tiles(p.photo, forward, window, budget):
        budget = None  # too few candidate tiles (and no given ones that fit): the whole frame
    if levels is None and len(rows0) == 1:
        # From one start the init is refined at full resolution anyway (`_coarse_to_fine`), so
        # coarse levels would only add work: measured 0.5-0.7x the full-resolution fit's speed
        # (fits/recover.py).
        levels = 1
    user_window = None if max_radius is None else window
    run = _Run(
        p, forward, solver, coarse_solver, verbose, max_steps, user_window, 1, band, boxes=boxes
    )
    if "registration" in p.spec.nuisances and budget is not None:
        raise ValueError(
            "registration is fitted on the whole frame (it resamples the photo, reading pixels "
            "across it), not on tiles: pass tiles=None"
        )
    if "registration" in p.spec.nuisances:
        reach = _registration_reach(p.photo) if registration_reach is None else registration_reach
        run = dataclasses.replace(run, extra_band=reach)
    if budget is None:  # coarse-to-fine on the whole frame
        if levels is None:
            levels = auto_levels(p.photo, forward.max_circle(rows0[:1], p.d))
        run = dataclasses.replace(run, levels=levels)
    return run, treatment, rows0, window, budget, levels


def _coarse_solve(run: _Run, treatment, rows0, window: float, budget, levels, own_choice: bool):
    """The starts' solves before the full-resolution one: coarse-to-fine on the whole frame, or
    the scout and the choice of tiles (`budget` pixels). Returns `(run, treatment, y0s, rows,
    chosen)`, `chosen` the tiles (`None` on the whole frame); on tiles the occlusion render the
    fit chose itself (`own_choice`) is kept only where a tile holds a depth edge."""
    p = run.problem
    if budget is None:  # `run.levels` set (`_set_up`)
        y0s, rows = _coarse_to_fine(run, rows0, window)
        return run, treatment, y0s, rows, None
    occluding = run.forward
    chosen_here = treatment.occlusion and own_choice
    if chosen_here:
        # The scout (starts, information) runs on the soft render with the edge weight; the
        # tiles keep clear of edges where they can, and only tiles holding one need the
        # occlusion render (2-3x the soft filter's cost per step).
        run = dataclasses.replace(run, forward=dataclasses.replace(occluding, method="soft"))
    run, y0s, rows, chosen = _on_tiles(run, rows0, window, budget, levels)
    if chosen_here and not edge_free(p, chosen):
        run = dataclasses.replace(run, forward=occluding)
    elif chosen_here:
        treatment = dataclasses.replace(treatment, occlusion=False, method="soft")
    return run, treatment, y0s, rows, chosen


# The registration a fit allows for before it has one (photo pixels): a shift of up to 2 px and
# a magnification of up to 2 %, the resampling kernel's reach added (`_registration_reach`).
_REGISTRATION_SHIFT = 2.0
_REGISTRATION_MAGNIFICATION = 0.02


def _registration_reach(photo, values=None) -> int:
    """The photo pixels along the edges whose registered value reads the render past its edge
    (or its taps): `|s| + |m| R` (`R` the half diagonal) and the kernel's reach, for the fitted
    `values` of every photo, else for the largest registration allowed for before a fit."""
    r = half_diagonal(photo[0], photo[1])
    if values is None:
        shift, mag = _REGISTRATION_SHIFT, _REGISTRATION_MAGNIFICATION
    else:
        sx, sy = (np.abs(np.asarray(values[k], np.float64)) * r for k in ("shift_x", "shift_y"))
        shift = float(np.max(np.maximum(sx, sy)))
        mag = float(np.max(np.abs(np.asarray(values["magnification"], np.float64))))
    return int(math.ceil(shift + mag * r)) + _LANCZOS


def _nuisance_entries(info, spec, photo, reach: int) -> dict:
    """`FitResult.nuisances`: per nuisance of `photo.NUISANCES`, fitted or not, its values (in
    photo pixels for shifts; for the registration also the `reach` its band added) and the score
    test of it at this fit (where it was tested)."""
    scores = info.get("nuisance_scores", {})
    r = half_diagonal(photo[0], photo[1])
    out = {}
    for name, params in NUISANCES.items():
        fitted = name in spec.nuisances
        dof = len(params) * spec.n_targets
        score = float(scores[name]) if name in scores else math.nan
        entry = {
            "fitted": fitted,
            "score": score,
            "dof": dof,
            "p_value": float(scipy.stats.chi2.sf(score, dof)) if math.isfinite(score) else math.nan,
        }
        if fitted:
            entry["values"] = {
                n: [
                    float(v) * (r if n.startswith("shift") else 1.0)
                    for v in np.asarray(info["nuisance_values"][n])
                ]
                for n in params
            }
            if name == "registration":
                entry["reach"] = reach
        out[name] = entry
    return out


def _determined_at_init(model: _Model, rows0: np.ndarray, args, p) -> bool:
    """Whether the photos determine the free set at the init lens (full rank there); `False`
    also when the test itself fails (the refusal then stands)."""
    y_init = pack(rows0[:1].astype(p.dtype), args[-1], p.spec.nuisances)[0]
    try:
        return not bool(run_stage("rank at init", degenerate_at, model, y_init, args, p.spec))
    except _SOLVER_ERRORS:
        return False
