"""The solves of one fit, in order: the starts' coarse solve (a coarse-to-fine pyramid on the
whole frame, or on a large photo a scout and the informative tiles), then the full-resolution
multi-start solve, refitted where the window turns out too small or too large for the fitted
circles, and focus at infinity settled as a bound.

`Run` holds what the stages share; each solve is one `solve.fit_starts` stage with the window
and the border band as data.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
from collections.abc import Callable, Iterator

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._filters.common import tap_offsets
from .forward import AbstractForwardModel
from .jpeg import JpegGrid, jpeg_align
from .layout import pack, theta_floor
from .lm import bounded
from .prepare import Problem
from .residual import _Model
from .solve import default_solver, fit_starts, restate, run_stage, stage_note
from .strategies import (
    _COARSE_TOL,
    COMPILE_WORK,
    _next_starts,
    apply_border,
    distinct,
    grown_window,
    level_band,
    reductions,
    shrunk_window,
    window_of,
)
from .tiles import (
    Tiles,
    choose_tiles,
    edge_free,
    given_tiles,
    halo_of,
    jacobian_information,
    pixel_information,
    scout_factor,
    tiled_problem,
)
from .verbose import _with_verbose


# A free focus whose coordinate `y` (`|y| ~ fcap / d_f`) ends within `_NEAR_INFINITY` of 0 (a focus
# beyond 1000 times the nearest depth: circles within 1e-3 of the largest from infinity's) is
# tried at infinity as a bound (`_settle_at_infinity`): the solver cannot settle on the kink of
# `|y|` there, and may even report convergence on it (float32, tolerance 1e-5: a start stalled at
# y = 1.5e-6 with N = 2.84 instead of 2.0 "converged").
_NEAR_INFINITY = 1e-3


# The starts a fit's solves are padded to (`padded_starts`): the default fit's (the init and
# three spread in diopters), so its one-start refits reuse its compiled solve. Only where the
# photos hold at most `PAD_MAX_VALUES` values (pixels x channels x photos): the padding rows'
# share of the solver's state is carried through every step. Measured warm (default XLA level,
# this 2-core machine, one-start solves): 600 x 600 RGB (1.1e6 values, 5 steps) 1.21-1.36 s
# unpadded against 1.32-1.47 s padded to 4; the 24 MP photo's tile mosaic (620 x 620 RGB, 4
# steps; pairs in turns) 18.6 / 10.2 / 11.0 / 11.7 s against 18.8 / 12.0 / 16.3 / 17.3 s; the
# 40 x 56 test scenes (6.7e3 values) no measurable cost and one compile saved (about 15 s at
# level 0) per fit that chooses a nuisance.
STARTS_COMPILED = 4
PAD_MAX_VALUES = 2**18


# The scout's step limit (fits on tiles): its best start converged in 8 steps on the fullres
# study's 1.5 MP scene, while a start that wandered off crawled for 97 (as many as it is given).
_SCOUT_MAX_STEPS = 30


@dataclasses.dataclass(frozen=True)
class Run:
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
    # The smallest filter window the residual is compiled with (`_kept_stencil`): a refit whose
    # window shrinks reuses the compiled solve of the larger one. 0: the window itself.
    stencil: float = 0.0
    jpeg: JpegGrid | None = None  # the photos' JPEG blocks and steps (`jpeg.py`), where found

    def residual(self, window: float) -> _Model:
        """The residual function with a given filter window (compiled with `stencil`, or a
        larger window this `fit_lens` call has compiled, where that is larger: exact either way,
        the taps past a circle's reach adding 0; `_compiled_cover`)."""
        spec, targets = self.problem.spec, self.problem.args[2]
        # Any free set: the refits with a nuisance follow the fit without it.
        key = (jax.tree_util.tree_structure(self.forward), spec.luma, self.jpeg, targets.shape)
        window = _compiled_cover(max(window, self.stencil), key, targets.size)
        n_used = len(spec.used)
        return _Model(
            spec.n_targets, window, spec.nuisances, self.forward, n_used, spec.luma, self.jpeg
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
        # (A solver `race` cannot drive solves every row: no padding for it.)
        raced = isinstance(solver, optx.AbstractLeastSquaresSolver)
        n, live = len(y0s), None  # (None: the unpadded program, every row a start)
        if raced and args[2].size <= PAD_MAX_VALUES:
            y0s, live = padded_starts(np.asarray(y0s))
        solution, info = run_stage("fit_starts", fit_starts, model, solver, y0s, args, steps, live)
        # A handful of small arrays, in one go; the starts' rows without the padding.
        info = jax.device_get(info)
        info.update({k: info[k][:n] for k in _PER_START})
        return model, solution, info, args, (band, wanted)


# `fit_starts`' per-start outputs.
_PER_START = ("loss", "converged", "theta", "ys", "steps", "stopped")


def padded_starts(y0s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`y0s` `(S, P)` padded with copies of its first row to the smallest power of two of at
    least `STARTS_COMPILED` and `S` rows, and which rows are starts: the solves of one fit (from the
    caller's starts, one start from a lens found, the window's refit with one more) then share
    one compiled `fit_starts` per free set. The race never evaluates the padding, so a one-start
    refit costs what it did, less its compile."""
    n = y0s.shape[0]
    size = max(STARTS_COMPILED, 1 << max(n - 1, 0).bit_length())
    live = np.arange(size) < n
    return np.concatenate([y0s, np.repeat(y0s[:1], size - n, axis=0)]), live


# The filter windows the residual was compiled with in the enclosing `compiled_windows` block (a
# `fit_lens` call), per forward model and photo shape.
_COMPILED: contextvars.ContextVar[dict | None] = contextvars.ContextVar(
    "jaxdof_compiled_windows", default=None
)


@contextlib.contextmanager
def compiled_windows() -> Iterator[None]:
    """Inside the block, a solve reuses the compiled residual of a larger window where the taps
    that costs are too few to pay for a compile (`_compiled_cover`): a `fit_lens` call's refits
    from the lens it found (the photo's say, the nuisances) need smaller windows than its starts
    did."""
    token = _COMPILED.set({})
    try:
        yield
    finally:
        _COMPILED.reset(token)


def _compiled_cover(window: float, key: tuple, size: int) -> float:
    """The smallest window at least `window` that the residual `key` was compiled with inside
    `compiled_windows` and whose extra taps over `size` data values stay under `COMPILE_WORK`
    (as `_kept_stencil`), else `window`; recorded as compiled."""
    seen = _COMPILED.get()
    if seen is None:
        return window
    done = seen.setdefault(key, set())
    taps = len(tap_offsets(window))
    cheap = [w for w in done if w >= window and size * (len(tap_offsets(w)) - taps) <= COMPILE_WORK]
    window = min(cheap, default=window)
    done.add(window)
    return window


def solvers(solver, dtype, verbose):
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


def _level(run: Run, data, k: int, y0s, rows: np.ndarray, max_steps: int | None = None):
    """One coarse level of the starts' solve: the starts `y0s` (lens rows `rows`) solved with the
    coarse solver on `data` (`(image, depth, targets, sqrt_w, base)`, the problem box-averaged
    `2^k` times), in the user's window scaled to it or the reach of the starts' circles there.
    The layout keeps the full-resolution bound on f, so that a parameter vector means the same
    lens on every level. Returns the solution, its `info`, the level's layout and the next
    starts (`_next_starts`: their vectors and lens rows at the full-resolution pitch)."""
    p = run.problem
    im, dep, tg, sw, b = data
    layout = dataclasses.replace(p.layout, base=b.astype(p.dtype))
    window = window_of(run.forward, rows, dep, tg.shape[1:3], 2**k, run.max_radius)
    # (A level whose band would leave no pixel keeps them all; only its starts matter.)
    args = (im, dep, tg, sw, layout)
    _, solution, info, _, _ = run.solve(window, y0s, args, k, run.coarse_solver, max_steps)
    y0s, rows = _next_starts(info, p.b, y0s, p.spec, layout)
    return solution, info, layout, y0s, rows


def _with_init(y0s, rows: np.ndarray, y0_init, rows0: np.ndarray):
    """The starts with the raw init appended, to be refined at full resolution too: a coarse
    level's model error can move every start into a wrong basin with the lowest coarse loss
    (seen on a depth-steps scene with a fine texture: all four starts went to N = 17,
    d_f = 0.42 at 48 x 48, while the init converges to the truth at 96 x 96 with a quarter of
    that loss), and the full-resolution loss, not the coarse one, decides between them."""
    return np.concatenate([y0s, y0_init[:1]]), np.concatenate([rows, rows0[:1]])


def _coarse_to_fine(run: Run, rows0: np.ndarray):
    """The starts of the full-resolution solve on the whole frame: the parameter vectors `(S, P)`
    and their lens rows `(S, T, 4)`.

    The multi-start solve runs on the coarsest level, and each finer level starts from the level
    below's solution (and a near-tie alternative, if any); the last level is the full-resolution
    problem with the full tolerance (`full_resolution`), so the answer and its statistics are
    those of the full-resolution fit. With one level: the starts themselves."""
    p = run.problem
    y0_init = pack(rows0.astype(p.dtype), p.layout, p.spec.nuisances)
    if run.levels == 1:
        return y0_init, rows0
    pyramid = reductions(p, range(1, run.levels))
    y0s, rows = y0_init, rows0
    for k in range(run.levels - 1, 0, -1):
        _, _, _, y0s, rows = _level(run, pyramid[k], k, y0s, rows)
    return _with_init(y0s, rows, y0_init, rows0)


# When the border band leaves less than this share of the pixels, the starts first search for
# their basin on every pixel. Seen on small frames (24 x 24 scenes of `fits/recover.py`, band 6 px:
# a quarter of the pixels kept; a 25 x 27 photo of tests/test_downsample.py, 99 of 675 kept): from
# the same starts a third to a half of the banded fits settled in a wrong basin while reporting
# success, and every one of them converged with the band off. The border's bias is a few percent of
# the blur scale at most, far inside the right basin, so the banded solve then refines from there.
_SEARCH_ALL_BELOW = 0.5


def _search_on_every_pixel(run: Run, window: float, y0s):
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


def _kept_stencil(run: Run, window: float, smaller: float) -> Run:
    """`run` compiled at `window` for a refit at `smaller` (`Run.stencil`), where the taps the
    smaller window saves are too few to pay for a compile (`COMPILE_WORK`); else `run`."""
    saved = len(tap_offsets(window)) - len(tap_offsets(smaller))
    if run.problem.args[2].size * saved > COMPILE_WORK:
        return run
    return dataclasses.replace(run, stencil=max(window, run.stencil))


def _shrink_window(run: Run, window: float, r_final: float, info):
    """A refit with the window the solution's circles need, when that is smaller than the one
    the starts needed (`None` otherwise, or with a given `max_radius`).

    The automatic window and its border band follow the largest circle of any start (starts
    spread in diopters make large circles), so the band can leave out far more of the photo than
    the fitted lens requires: on a ray-traced slanted plane with circles under 3 px, four starts
    set a 10 px window and band, and the lowest-loss start there was 20 % off in K, while the
    4 px window of the fitted circles keeps 37 % more pixels. Every start is solved again from
    where it ended, so the larger set of pixels decides between them."""
    p = run.problem
    smaller = shrunk_window(window, r_final, p.photo, run.max_radius)
    if smaller is None:
        return None
    ys = np.where(np.isfinite(info["ys"]), info["ys"], 0).astype(np.asarray(info["ys"]).dtype)
    run = _kept_stencil(run, window, smaller)
    model, solution, info2, args, bands = run.solve(smaller, ys, p.args, 0, run.solver)
    r2 = run.forward.max_circle(np.asarray(info2["natural"], np.float64), p.d)
    if r2 > smaller:  # the refit's circles outgrow it: keep the first solve
        return None
    return run, model, solution, info2, args, bands, smaller, r2


def full_resolution(run: Run, y0s, window: float):
    """The full-resolution multi-start solve from `y0s` with `window` (`coarse_solve`'s),
    refitted (up to twice) with a larger window when the automatic one turns out too small for
    the solution's circles.

    Every refit leaves out the border band of its own window. Returns the residual model, the
    chosen solution (for `finish`), its `info`, the largest fitted circle (px), the final window
    (px), the notes, the `args` solved (weights with the band applied) and the band (px)."""
    p = run.problem
    notes = []
    y0s = _search_on_every_pixel(run, window, y0s)
    model, solution, info, args, (band, wanted) = run.solve(window, y0s, p.args, 0, run.solver)
    r_final = run.forward.max_circle(np.asarray(info["natural"], np.float64), p.d)
    for _ in range(2):
        bigger = grown_window(window, r_final, p.photo, run.max_radius)
        if bigger is None:
            break
        notes.append(
            f"the window {window:g} px was too small for the fitted circles ({r_final:.3g} px); refitted"
        )
        window = bigger
        best = int(info["best"])
        y0s = np.concatenate([info["ys"][best][None], info["ys"]], axis=0)
        model, solution, info, args, (band, wanted) = run.solve(window, y0s, p.args, 0, run.solver)
        r_final = run.forward.max_circle(np.asarray(info["natural"], np.float64), p.d)
    shrunk = _shrink_window(run, window, r_final, info)
    if shrunk is not None:
        run, model, solution, info, args, (band, wanted), window, r_final = shrunk
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


def _fine_window(run: Run, rows: np.ndarray, depth: np.ndarray | None = None) -> float:
    """The full-resolution window after coarse levels: the reach of the starts' circles over
    `depth` (default: the problem's). On tiles the raw init, when `_on_tiles` appends it as the
    last start (`run.init_last`), does not widen it: its circles (often the largest, from a
    start far off) would set the cost of every step of a large photo (24 MP, f/5.6 at 2 m for an
    f/8 truth: a 32 px window for 13 px circles). Its render is then clamped to the window;
    should it win with circles beyond it, `full_resolution` refits with a larger one.
    (Whole-frame fits keep the init's reach, as validated by the studies.)"""
    p = run.problem
    starts = rows[:-1] if run.init_last else rows
    depth = p.d if depth is None else depth
    return window_of(run.forward, starts, depth, p.photo, fixed=run.max_radius)


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


def _on_tiles(run: Run, rows0: np.ndarray, window: float, budget: int, levels: int | None):
    """A fit on tiles up to its full-resolution solve: `(run, y0s, tiles, window)`, `run` on the
    mosaic of the tiles (levels 2 with a scout solve, else 1), the starts of the
    full-resolution solve, the tiles and that solve's window (`_on_chosen`).

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
        align = jpeg_align(run.jpeg)
        given = None if run.boxes is None else given_tiles(p.photo, forward, win, run.boxes, align)
        return given or choose_tiles(p, forward, win, budget, information, align)

    q = scout_factor(p.photo, forward.max_circle(rows0, p.d), levels)  # levels 1: one start
    y0_init = pack(rows0.astype(p.dtype), p.layout, p.spec.nuisances)
    if q == 1:
        chosen = choose(window, lambda: pixel_information(p, forward, rows0))
        assert chosen is not None  # `fits_tiles` said there is room
        return _on_chosen(dataclasses.replace(run, levels=1), chosen, y0_init, rows0)
    k = q.bit_length() - 1
    scout = reductions(p, [k])[k]
    run = dataclasses.replace(run, levels=2)
    # The scout only finds the basin: a start still crawling after `_SCOUT_MAX_STEPS` (towards
    # f/300 and a focus at 0.1 m on the 1.5 MP study, 97 lockstep steps) is far behind the best.
    solution, info, layout, y0s, rows = _level(run, scout, k, y0_init, rows0, _SCOUT_MAX_STEPS)
    if _init_elsewhere(info, p, layout):
        y0s, rows = _with_init(y0s, rows, y0_init, rows0)
        run = dataclasses.replace(run, init_last=True)
    fine = _fine_window(run, rows)
    jac = solution[5]

    def information():
        return jacobian_information(jax.device_get(jac), scout[2].shape, p.spec.used), q

    # (The init's window had room for tiles; a larger fine window may not: then its halos.)
    chosen = choose(fine, information) or choose(window, information)
    assert chosen is not None
    return _on_chosen(run, chosen, y0s, rows)


def _on_chosen(run: Run, chosen: Tiles, y0s, rows: np.ndarray):
    """`_on_tiles`'s result once the tiles are `chosen`: their halos trimmed to the reach of the
    starts' circles over the tiles' own depths (they were sized for the whole scene's, which
    the tiles may not hold), `run` on their mosaic, the starts, and the full-resolution window
    over the mosaic (`_fine_window`), whether a scout or an earlier fit chose the tiles."""
    p = run.problem
    align = jpeg_align(run.jpeg)
    if run.max_radius is None:
        crops = chosen.mosaic(p.depth, p.ratio, 0, np.nan)
        reach = _fine_window(run, rows, crops[~np.isnan(crops)])
        halo = halo_of(run.forward, reach, align)
        chosen = dataclasses.replace(chosen, halo=min(halo, chosen.halo))
    tiled = tiled_problem(p, chosen)
    # A camera JPEG's blocks where every crop lies on its grid (tiles chosen here: `align`).
    on_grid = align == 8 and all(v % 8 == 0 for v in (chosen.halo, *sum(chosen.corners, ())))
    jpeg = run.jpeg.on(tiled.photo) if on_grid and run.jpeg is not None else None
    run = dataclasses.replace(run, problem=tiled, border=0, jpeg=jpeg)
    return run, y0s, chosen, _fine_window(run, rows)


def _settle_at_infinity(run: Run, window: float, solved):
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


def coarse_solve(run: Run, treatment, rows0, window: float, budget, levels, own_choice: bool):
    """The starts' solves before the full-resolution one: coarse-to-fine on the whole frame, or
    the scout and the choice of tiles (`budget` pixels). Returns `(run, treatment, y0s, chosen,
    window)`: `chosen` the tiles (`None` on the whole frame), `window` the full-resolution
    solve's. On tiles the occlusion render the fit chose itself (`own_choice`) is kept only
    where a tile holds a depth edge."""
    p = run.problem
    if budget is None:  # `run.levels` set (`_set_up`)
        y0s, rows = _coarse_to_fine(run, rows0)
        return run, treatment, y0s, None, _fine_window(run, rows) if run.levels > 1 else window
    occluding = run.forward
    chosen_here = treatment.occlusion and own_choice
    if chosen_here:
        # The scout (starts, information) runs on the soft render with the edge weight; the
        # tiles keep clear of edges where they can, and only tiles holding one need the
        # occlusion render (2-3x the soft filter's cost per step).
        run = dataclasses.replace(run, forward=dataclasses.replace(occluding, method="soft"))
    run, y0s, chosen, window = _on_tiles(run, rows0, window, budget, levels)
    if chosen_here and not edge_free(p, chosen):
        run = dataclasses.replace(run, forward=occluding)
    elif chosen_here:
        treatment = dataclasses.replace(treatment, occlusion=False, method="soft")
    return run, treatment, y0s, chosen, window
