r"""The photo's say in the treatment: `fit_lens` keeps a treatment the scene chose only where the
photo prefers it.

The scene's rules (`jaxdof/_scene.py`) choose, from the depth map and the starting lens, the
footprint correction where circles are small and the occlusion render where depth edges matter.
Those rules know what a camera records; they cannot know what made *this* photo. A photo made by
`jaxdof.render` with its default options (the plain `soft` scatter), by another simulator, or by
a camera whose all-in-focus image was itself prefiltered, may be explained better without them,
and fitting it with them biases the lens (the README's example: 3.6 % in `K`).

**The rule.** After the fit with the scene's treatment `T0`, each choice the scene made (and the
caller did not force) is dropped in turn, as a likelihood comparison between two models with the
same free parameters: the fit without it `T1` is solved from `T0`'s lens (one start, the same edge
weight and border band, so the same pixels), and replaces `T0` when

$$\Delta\chi^2 = \frac{n\,(m_0 - m_1)}{\sigma^2} > \texttt{SELECT\_CHI2}$$

with `m = 2 L / n` the mean squared weighted residual over the `n` residuals fitted and
`sigma^2` the smaller of the two fits' residual variances (the noise, as nearly as either model
sees it), at least the float rounding's (`rounding_sigma`): where both fits are down to the
rounding, the photo cannot tell them apart and the scene's choice stays. With equal numbers of parameters the information criteria (AIC, BIC) all reduce to
comparing the losses; the margin keeps the scene's choice where the photo cannot tell the two
apart (then their lenses agree to within their errors anyway), so a wrong switch needs the noise
to favour the wrong model by `sqrt(SELECT_CHI2)` standard deviations of the difference.
The occlusion render is tried first (off where the scene chose it, on where the depth map has
edges that the starting lens's circles did not make matter), then the footprint; the result says
what was tried and what the photo chose (`Treatment.selected`).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .. import _tuning
from .._corrections import FOOTPRINT_REACH, depth_edges
from .._scene import OCCLUSION_METHOD
from .result import RESULTS, FitResult, code_of
from .tiles import edges_near


#: The chi-square margin by which the photo must prefer a simpler treatment (module docstring).
SELECT_CHI2 = _tuning.SELECT_CHI2
#: The level of the score test that turns a nuisance on (`with_nuisances`).
SELECT_ALPHA = _tuning.SELECT_ALPHA

# Statuses whose lens is worth comparing: a converged fit, whatever its verdict.
_COMPARABLE = ("successful", "inconsistent", "ambiguous", "window")


def alternatives(result: FitResult, call: dict) -> list[tuple[str, dict]]:
    """The other treatments to try after `result` (the scene's), as `(label, changes to the
    call)`, each only where the caller did not force that choice, and only for the default
    forward model: the occlusion render off where the scene chose it, or on where the depth map
    has edges the starting lens did not make matter (the photo's lens may: the scene's rule at
    the start is not its rule at the truth); then the footprint correction off where the scene
    chose it."""
    t = result.treatment
    if t is None or call.get("model") is not None or _status(result) not in _COMPARABLE:
        return []
    # The occlusion render first: where it is wrong its error is the larger, and it would
    # muddle the footprint's comparison (a soft render with the footprint correction, circles
    # of 30 px: with occlusion still on, the fit without the footprint won by chi2 11.5).
    out = []
    if call.get("method") is None:
        if t.occlusion:
            out.append(("occlusion off", {"method": "soft"}))
        elif _edges_read(result, call):
            out.append(("occlusion on", {"method": OCCLUSION_METHOD}))
    if t.footprint and call.get("footprint") is None:
        out.append(("footprint off", {"footprint": False}))
    return out


def _edges_read(result: FitResult, call: dict) -> bool:
    """Whether `result`'s pixels can see a depth edge, where alone the occlusion render differs
    from the soft one: anywhere on the whole frame; on tiles, within twice the fitted window of
    one (the refit's window, from `result`'s lens, with room for its circles to grow): on tiles
    clear of every edge the refit would render the same image."""
    depth = np.asarray(call["depth"])
    if not result.tiles:
        return bool(depth_edges(depth).any())
    boxes = np.asarray(result.tiles, np.int64)
    reach = 2 * math.ceil(float(np.asarray(result.max_radius))) + FOOTPRINT_REACH
    corners = [(int(r), int(c)) for r, c in boxes[:, :2]]
    return edges_near(depth, int(call.get("downsample") or 1), corners, int(boxes[0, 2]), reach)


def refit_call(result: FitResult, call: dict, changes: dict) -> dict:
    """The call of an alternative fit: the same edge weight and border band (so the same pixels),
    the treatment's other choices as `result` made them; from `result`'s lens with one start
    where `result` succeeded, else from the caller's starts (a model that does not explain the
    photo may have led its fit astray: a soft render of circles under a pixel fitted with the
    footprint correction ended at 4.5 times the f-number, where the soft render is in its
    dead zone)."""
    return _from(result, {**call, **_as_chosen(result, call), **changes})


def _as_chosen(result: FitResult, call: dict) -> dict:
    """The options that make a fit treat the scene as `result` did."""
    t = result.treatment
    assert t is not None
    same = same_pixels(result)
    # The band as the caller's: without the registration's reach, which a fit adds to it.
    reach = same.get("registration_reach", 0)
    keep = {
        "footprint": t.footprint,
        "method": t.method if t.occlusion else "soft",
        "edge_weight": t.edge_weight if t.edge_weight > 0 else False,
        "border": int(result.border) - reach if call.get("border") is not False else False,
        **same,
    }
    if call.get("method") is not None:
        keep["method"] = call["method"]
    return keep


def same_pixels(result: FitResult) -> dict:
    """The options that make a refit fit `result`'s pixels: its tiles (chosen at its own lens or
    scout, which a refit's differ from), the reach of its registration and of its depth holes
    (each set by the starting lens), where it has them; the band is `_as_chosen`'s."""
    out: dict = {}
    if result.tiles:
        out["tiles"] = tuple(tuple(int(v) for v in box) for box in result.tiles)
    reach = (result.nuisances or {}).get("registration", {}).get("reach")
    if reach is not None:
        out["registration_reach"] = int(reach)
    t = result.treatment
    if t is not None and t.depth_holes:
        out["hole_reach"] = float(t.hole_reach)
    return out


def nuisance_floor(targets) -> float:
    """The residual standard deviation under which no nuisance is tested: float32's rounding of
    the photos (`rounding_sigma`). A photo holds at most float32's digits (a camera's 16 bits, or
    a float32 render); a float64 fit of a render stops at the solver's tolerance, far above
    float64's rounding, and leaves no camera's nuisance to find."""
    return rounding_sigma(targets, np.float32)


def prefers(alt: FitResult, incumbent: FitResult, rounding: float) -> tuple[bool, float]:
    """Whether the photo prefers `alt` to `incumbent` (module docstring), and the chi-square
    difference `Delta chi^2` (positive: `alt` fits better). `rounding`: the residual standard
    deviation that the data's float rounding alone leaves (`rounding_sigma`), the floor of the
    noise: where both fits are down to it, the photo cannot tell them apart."""
    if _status(alt) not in _COMPARABLE:
        return False, -math.inf
    n0, n1 = _residuals(incumbent), _residuals(alt)
    l0, l1 = float(np.asarray(incumbent.loss)), float(np.asarray(alt.loss))
    if not (np.isfinite(l0) and np.isfinite(l1)) or min(n0, n1) <= 0:
        return False, -math.inf
    m0, m1 = 2 * l0 / n0, 2 * l1 / n1
    s0, s1 = (float(np.asarray(r.sigma)) ** 2 for r in (incumbent, alt))
    sigma2 = max(min(s0, s1), rounding**2, np.finfo(np.float64).tiny)
    chi2 = min(n0, n1) * (m0 - m1) / sigma2
    return bool(chi2 > SELECT_CHI2 and max(s0, s1) > rounding**2), chi2


def rounding_sigma(targets, dtype) -> float:
    """The residual standard deviation that float rounding alone leaves on photos `targets`:
    `16 eps rms(T)` (a float32 render of the true lens matches its own photo to about
    `0.7 eps rms(T)`; the margin covers the longer sums of the occlusion renders)."""
    # Per photo and without a float64 copy (a 24 MP photo is 600 MB in float64); one digit is
    # all a floor needs.
    photos = targets if isinstance(targets, (list, tuple)) else [targets]
    flat = [np.ravel(np.asarray(x)) for x in photos]
    total = sum(float(np.vdot(x, x)) for x in flat)
    return 16 * float(np.finfo(dtype).eps) * math.sqrt(total / sum(x.size for x in flat))


def selected(alt: FitResult, incumbent: FitResult, label: str, chi2: float) -> FitResult:
    """`alt`, with its treatment saying that the photo chose it over `incumbent`'s, and the
    incumbent's near/far ambiguity (a property of the data, which the one-start refit cannot see)
    carried over."""
    t_alt, t0 = alt.treatment, incumbent.treatment
    assert t_alt is not None and t0 is not None
    treatment = dataclasses.replace(
        t_alt,
        edge_pixels=t0.edge_pixels,
        edge_share=t0.edge_share,
        median_circle=t0.median_circle,
        forced=t0.forced,
        selected=(*t0.selected, f"{label}: better by chi2 {chi2:.3g}"),
    )
    out = dataclasses.replace(alt, treatment=treatment, levels=incumbent.levels)
    if _status(incumbent) == "ambiguous" and _status(alt) == "successful":
        out = dataclasses.replace(
            out, status=RESULTS.ambiguous, success=np.asarray(False), notes=incumbent.notes
        )
    return out


def kept(incumbent: FitResult, label: str, chi2: float) -> FitResult:
    """`incumbent`, its treatment saying that the photo did not prefer `label` (`chi2`: how much
    better that fit was, negative where it was worse; `-inf` where it could not be fitted)."""
    t0 = incumbent.treatment
    assert t0 is not None
    how = f"chi2 {chi2:+.3g}" if math.isfinite(chi2) else "no fit"
    treatment = dataclasses.replace(t0, selected=(*t0.selected, f"{label}: not better ({how})"))
    return dataclasses.replace(incumbent, treatment=treatment)


def with_nuisances(
    result: FitResult, call: dict, fit, floor: float, asked: dict[str, bool | None]
) -> FitResult:
    """The fit with what the camera added (`photo.NUISANCES`) where the photo needs it (`fit`:
    `fit_lens`'s single-treatment fit; `asked`: the caller's choice per nuisance, `None` to
    decide).

    **The rule.** At a fit without a nuisance, the score (Lagrange multiplier) statistic of its
    parameters (`solve.nuisance_scores`, chi-square with `q T` degrees of freedom where the
    photo has none of it; no refit) is tested at level `SELECT_ALPHA`. Where it rejects, the
    fit with the nuisance is solved (from the lens found) and kept where it lowers the
    chi-square by more than `SELECT_CHI2` in units of the model error (residual variance times
    the tiles' inflation squared, the smaller of the two fits', `explained`): a real photo rejects any model
    at its noise level (a ray-traced photo asked for a registration of 0.01 px), and a
    nuisance must explain more than what the model already lacks.
    Forward selection: the most significant rejection first, the others tested again at the
    fit kept, until none is left. A score test keeps the default fit's cost where the photo
    asks for nothing (Rao 1948, Buse 1982)."""
    entries = {k: dict(v) for k, v in (result.nuisances or {}).items()}
    for name, value in asked.items():
        entries.setdefault(name, {"fitted": bool(value)})
        entries[name].update(forced=value is not None, chosen=False)
    tried: set[str] = set()
    for _ in range(len(asked)):
        # A fit down to the float rounding (a render of the photo's own lens) leaves nothing
        # for a nuisance to explain, and its residual is the rounding, which is proportional to
        # the values, so along the gain column: no test there (`nuisance_floor`).
        if float(np.asarray(result.sigma)) < floor:
            for name in asked:
                entries[name]["exact"] = not entries[name].get("chosen")
            break
        candidates = [
            k
            for k, value in asked.items()
            if value is None
            and k not in tried
            and not entries[k].get("fitted")
            and entries[k].get("p_value", math.nan) < SELECT_ALPHA
        ]
        if not candidates:
            break
        # The most significant first: the smallest p-value, then the largest score per dof.
        pick = min(
            candidates,
            key=lambda k: (entries[k]["p_value"], -entries[k]["score"] / entries[k]["dof"]),
        )
        tried.add(pick)
        on = tuple(k for k in asked if entries[k].get("fitted") or k == pick)
        failed = _status(result) == "other"
        # From the lens found; where the fit without it failed (a misregistration can drive it
        # into a flat region), from the caller's starts.
        start = {} if failed else {"init": result.lenses, "starts": 1, "pyramid": None}
        try:
            refit = fit(**{**call, **_as_chosen(result, call), **start, "nuisances": on})
        except ValueError:
            continue
        base = result if failed else _on_pixels_of(refit, result, call, fit, start)
        if base is None:
            continue
        gain = explained(refit, base)
        entries[pick]["explains"] = gain
        ok = _status(refit) in ("successful", "inconsistent")
        if not ok or not (failed or gain > SELECT_CHI2):
            continue
        t0, t1 = result.treatment, refit.treatment
        assert t0 is not None and t1 is not None
        treatment = dataclasses.replace(t1, forced=t0.forced, selected=t0.selected)
        chosen = {k for k in asked if entries[k].get("chosen")} | {pick}
        tested = {k: dict(v) for k, v in (refit.nuisances or {}).items()}
        for name, value in asked.items():
            tested[name].update(forced=value is not None, chosen=name in chosen)
            if name in chosen or name in tried:  # the test that chose it, at the fit without it
                keep = ("score", "dof", "p_value", "explains")
                tested[name].update({k: entries[name][k] for k in keep if k in entries[name]})
        result, entries = dataclasses.replace(refit, treatment=treatment), tested
        call = {**call, "nuisances": on}
    return dataclasses.replace(result, nuisances=entries)


def _on_pixels_of(refit: FitResult, result: FitResult, call: dict, fit, start: dict):
    """`result` (the fit without the nuisance), on `refit`'s pixels: the registration's reach
    leaves edge pixels out, whose misfit may differ, so where they differ the fit again with
    `refit`'s band (a weight: the same programs). `None` where that fit is refused."""
    if _residuals(refit) == _residuals(result):
        return result
    try:
        base = fit(**{**call, **_as_chosen(result, call), **start, "border": refit.border})
    except ValueError:
        return None
    return base if _status(base) in ("successful", "inconsistent") else result


def decisions(final: FitResult, decided: FitResult, asked: dict[str, bool | None]) -> FitResult:
    """`final` (a fit with the nuisances `decided` chose) reporting the tests that decided them
    (`with_nuisances`): each nuisance's values from `final`, its test from `decided`."""
    entries = {k: dict(v) for k, v in (final.nuisances or {}).items()}
    test = ("forced", "chosen", "score", "dof", "p_value", "explains", "exact")
    for name in asked:
        old = (decided.nuisances or {}).get(name, {})
        entries[name] = {**entries.get(name, {}), **{k: old[k] for k in test if k in old}}
    return dataclasses.replace(final, nuisances=entries)


def explained(refit: FitResult, base: FitResult) -> float:
    """How much of `base`'s misfit `refit` explains: the chi-square difference on the same pixels
    (as `prefers`) in units of the model error, a fit's residual variance times the square of its
    tiles' inflation (1 where its tiles agree), the smaller of the two fits' (as `prefers` takes
    the smaller noise): where the nuisance is what the model lacked, the fit without it has its
    tiles disagree because of it, and its model error would divide the gain by the misfit the
    nuisance removes."""
    n0, n1 = _residuals(base), _residuals(refit)
    l0, l1 = float(np.asarray(base.loss)), float(np.asarray(refit.loss))
    if not (np.isfinite(l0) and np.isfinite(l1)) or min(n0, n1) <= 0:
        return -math.inf
    sigma2 = max(min(_model_error(base), _model_error(refit)), np.finfo(np.float64).tiny)
    return min(n0, n1) * (2 * l0 / n0 - 2 * l1 / n1) / sigma2


def _model_error(result: FitResult) -> float:
    """The residual variance times the square of the tiles' inflation (`math.inf` if unknown)."""
    inflation = float(np.asarray((result.adequacy or {}).get("inflation", math.nan)))
    inflation = inflation if math.isfinite(inflation) else 1.0
    sigma2 = float(np.asarray(result.sigma)) ** 2 * inflation**2
    return sigma2 if math.isfinite(sigma2) else math.inf


def _from(result: FitResult, call: dict) -> dict:
    """`call` started from `result`'s lens with one start where `result` succeeded."""
    if _status(result) != "successful":
        return call
    return {**call, "init": result.lenses, "starts": 1, "pyramid": None}


def _status(result: FitResult) -> str:
    code = code_of(result.status)
    return next((n for n in _COMPARABLE if code == code_of(getattr(RESULTS, n))), "other")


def _residuals(result: FitResult) -> int:
    """The photo pixels fitted: with the mean square per pixel, `n (m0 - m1)` is the difference
    of the sums of squares on the same pixels, whatever the channels."""
    return int(np.asarray(result.pixels_used))
