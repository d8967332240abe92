r"""`fit_lens`: checks, the scene's treatment, then the parts in order (`path.py`: the starts'
coarse solve and the full-resolution solve; `solve.finish`: the statistics; `verdict.py`: the
status in words), and the photo's say in the treatment and the camera's nuisances (`select.py`).

The compiled calls (`solve.fit_starts`, `solve.finish`, ...) run through `solve.run_stage`;
everything between them is numpy on the host. An error raised while they run (a forward model's
run-time check, a NaN under `jax_debug_nans`) becomes a failed `FitResult` (`verdict.failed`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import numpy as np
import optimistix as optx
import scipy.special
from jaxtyping import ArrayLike

from .. import _tuning
from .._filters import AbstractMethod
from .._filters.common import is_concrete
from .._lens import ThinLens
from .._upsample import upsample_depth
from .forward import AbstractForwardModel
from .jpeg import jpeg_align, jpeg_grid
from .layout import pack
from .path import Run, coarse_solve, compiled_windows, full_resolution, solvers
from .photo import _LANCZOS, FRAMED, NUISANCES, canonical, chroma_detail, half_diagonal
from .prepare import (
    _check_names,
    _check_options,
    check_differentiable,
    forward_model,
    leave_out_holes,
    prepare_problem,
    prepared_once,
)
from .residual import _Model
from .result import RESULTS, FitResult, code_of
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
from .solve import degenerate_at, finish, nuisance_scores, run_stage
from .strategies import _check_pyramid, auto_levels, check_border, start_lenses, window_of
from .tiles import fits_tiles, given_tiles, tile_boxes, use_tiles
from .treatment import check_edge_weight, shared_render, treat_scene
from .verdict import failed, tiles_note, verdict


# Errors that running the compiled solve can raise on valid inputs: a run-time check
# (`equinox.error_if`, e.g. in a user's forward model: `EquinoxRuntimeError` under
# `equinox.filter_jit`, `JaxRuntimeError` under `jax.jit`, which is XLA's runtime error) or a NaN
# under `jax_debug_nans` (`FloatingPointError`). `fit_lens` reports them as a failed fit.
_SOLVER_ERRORS = (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError, FloatingPointError)


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
    jpeg: bool | ArrayLike | None = None,
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
    - `jpeg`: with the luma, compare in the JPEG file's 8 x 8 blocks to within half its
      quantisation steps (`jaxdof/_fit/jpeg.py`): `None` where the photo's coefficients lie on
      a quantisation lattice, `False` never, `True` required, or the file's luma table (64
      steps, row-major, as Pillow's `Image.quantization[0]`; the photo read whole).
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
    call["jpeg"], luma_entry["jpeg"] = jpeg_grid(targets, call["luma"], jpeg)
    # The render is the fit's to choose (the photo's say refits with another): on a small photo
    # the soft and occlusion renders then share one compiled solve (`treatment.shared_render`).
    call["own_render"] = model is None and method is None
    coarse = np.shape(depth)
    if len(coarse) == 2 and np.ndim(image) in (2, 3) and coarse != np.shape(image)[:2]:
        # A depth sensor coarser than the image: upsampled once, guided by the image.
        call["depth"] = upsample_depth(np.asarray(depth), np.asarray(image))
    else:
        coarse = ()
    # The refits below prepare the same arrays once, and reuse the compiled residual of a larger
    # window where that is cheap.
    with prepared_once(), compiled_windows():
        result = _fit_treated(**call)
        # The photo's say in the treatment (`select.py`): each choice of the scene's changed in
        # turn, kept only where the photo prefers it ...
        rounding = rounding_sigma(targets, np.asarray(result.loss).dtype)
        result = _photo_says(result, call, rounding)
        # ... and in what the camera added: each nuisance fitted where a score test at the fit
        # without it rejects and it explains more than the model's error
        # (`select.with_nuisances`), the caller's choices as given ...
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
        # A grey image (a chart's raster in three channels) has no colour detail to lose: its
        # ratio is rounding over rounding, and says nothing (equal channels: known without it).
        img = np.asarray(image)
        equal = np.array_equal(img[..., 0], img[..., 1]) and np.array_equal(
            img[..., 1], img[..., 2]
        )
        of_image = 0.0 if equal else chroma_detail(img)
        grey = not of_image > _GREY_CHROMA
        detail = math.nan if grey else min(chroma_detail(a) for a in arr) / of_image
    if luma is not None:
        return bool(luma), {"fitted": bool(luma), "forced": True, "chroma_detail": detail}
    on = bool(colour and detail < _tuning.LUMA_CHROMA)
    return on, {"fitted": on, "forced": False, "chroma_detail": detail}


def _fit_treated(**call) -> FitResult:
    """`fit_lens` with the scene's treatment (or the caller's): one fit, no selection; the score
    tests of the nuisances `call["test"]` (`photo.NUISANCES`) where it does not fit them. Fitted
    again where the fit finds it needs more room (`_fit_once`)."""
    while True:
        out = _fit_once(call)
        if isinstance(out, FitResult):
            return out
        call = {**call, **out}


def _fit_once(call: dict) -> FitResult | dict:
    """One fit of `call` (`fit_lens`'s, as `_set_up` takes it), or the changes to fit again
    with: a fitted registration that reads beyond the band allowed for it, or tiles whose halos
    no longer hold the fitted window (chosen again for it)."""
    run, treatment, rows0, window, budget, levels = _set_up(**call)
    p, full_pixels = run.problem, int(run.problem.photo[0] * run.problem.photo[1])
    chosen = None
    try:
        run, treatment, y0s, chosen, window = coarse_solve(
            run,
            treatment,
            rows0,
            window,
            budget,
            levels,
            own_choice=call["model"] is None and call["method"] is None,
        )
        p = run.problem
        model_r, solution, info, r_final, window, notes, args, used = full_resolution(
            run, y0s, window
        )
        statistical = model_r.statistical()  # one compiled `finish` for every render and window
        result, stats = run_stage(
            "finish", finish, statistical, solution, args, p.spec, p.single, used
        )
        info.update(jax.device_get(stats))
        # The score tests of the nuisances to decide, where the fit leaves something to explain
        # (`select.with_nuisances`); on tiles only those that do not depend on the whole frame.
        test = call.get("test", ())
        names = tuple(k for k in test if k not in p.spec.nuisances and not (chosen and k in FRAMED))
        if names and float(info["sigma"]) >= nuisance_floor(call["targets"]):
            scores = run_stage(
                "nuisance scores", nuisance_scores, model_r, solution, args, p.spec, names
            )
            info["nuisance_scores"] = jax.device_get(scores)
    except _SOLVER_ERRORS as err:
        out = failed(run, err, window)
        return dataclasses.replace(out, treatment=dataclasses.replace(treatment, border=out.border))
    result = dataclasses.replace(
        result,
        max_radius=window,  # (`finish` saw the statistical model, which has no window)
        border=used,
        treatment=dataclasses.replace(treatment, border=used),
        nuisances=_nuisance_entries(info, p.spec, p.photo, run.extra_band),
    )
    if "registration" in p.spec.nuisances:
        needed = _registration_reach(p.photo, info["nuisance_values"])
        if needed > run.extra_band:  # the fitted registration reads beyond the band: again
            return {"registration_reach": needed}
    if chosen is not None:
        if window > chosen.halo:  # the halos no longer hold the window's reach: choose again
            again = call["tiles"] if run.boxes is not None else budget  # (given ones if they fit)
            return {"max_radius": window, "tiles": again}
        notes.append(tiles_note(chosen, full_pixels))
        result = dataclasses.replace(result, tiles=chosen.boxes)
    # A rank-deficient solution that the photos contradict (the adequacy test fails there) while
    # they determine the free set at the init: a fit that ended in a flat region of the model,
    # not a free set the data cannot determine (that one is refused: a focus bracket all at
    # infinity is rank deficient only at its solution, which explains the photos).
    if (
        code_of(info["status"]) == code_of(RESULTS.degenerate)
        and not call["allow_degenerate"]
        and not bool(result.adequacy["adequate"])
    ):
        info["determined_at_init"] = _determined_at_init(model_r, rows0, args, p)
    return verdict(run, result, info, r_final, window, notes, call["allow_degenerate"])


def _set_up(
    image, depth, targets, init, *, free, shared, solver, max_steps, weight, max_radius,
    nuisances, luma, starts, verbose, model, method, footprint, pyramid, downsample, border,
    tiles, edge_weight, registration_reach=None, hole_reach=None, own_render=False, jpeg=None,
    **_,
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
    solver, coarse_solver = solvers(solver, p.dtype, verbose)
    rows0 = start_lenses(p.b, p.d, free=free, starts=n_starts, fcap=p.fcap)
    fixed = None if max_radius is None else float(max_radius)
    window = window_of(forward, rows0, p.d, p.photo, fixed=fixed)
    if own_render:
        forward = shared_render(forward, p, window)
    # The photo pixels that a depth hole's light reaches: the init lens's circles and the
    # border's stencils (the border band of their window; the starts' window can be far
    # larger: starts spread in diopters make large circles).
    own = window_of(forward, rows0[:1], p.d, p.photo)
    if hole_reach is None:
        hole_reach = float(forward.border_band(min(own, window)))
    p, hole_pixels, hole_reach = leave_out_holes(p, hole_reach)
    if p.holes is not None:
        holes = int(p.holes.sum())
        treatment = dataclasses.replace(
            treatment, depth_holes=holes, hole_pixels=hole_pixels, hole_reach=hole_reach
        )
    budget, boxes, align = use_tiles(tiles, p.photo), tile_boxes(tiles), jpeg_align(jpeg)
    given = boxes is not None and given_tiles(p.photo, forward, window, boxes, align) is not None
    if budget is not None and not given and not fits_tiles(p.photo, forward, window, budget, align):
        budget = None  # too few candidate tiles (and no given ones that fit): the whole frame
    if levels is None and len(rows0) == 1:
        # From one start the init is refined at full resolution anyway (`_coarse_to_fine`), so
        # coarse levels would only add work: measured 0.5-0.7x the full-resolution fit's speed
        # (fits/recover.py).
        levels = 1
    run = Run(p, forward, solver, coarse_solver, verbose, max_steps, fixed, 1, band)
    run = dataclasses.replace(run, boxes=boxes, jpeg=jpeg)
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
            "p_value": float(scipy.special.chdtrc(dof, score))
            if math.isfinite(score)
            else math.nan,
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
