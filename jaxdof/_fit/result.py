"""The outcome of a fit: `FitResult`, its status enumeration `RESULTS`, and their wording."""

from __future__ import annotations

import math
from typing import Any

import equinox as eqx
import equinox.internal as eqxi
import jax
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._lens import ThinLens
from .layout import ALL_FIELDS, LENS_FIELDS
from .treatment import Treatment


_UNITS = {"focal_length": "m", "f_number": "", "focus_distance": "m", "gain": "", "offset": ""}


def nuisance_words(entry: dict) -> str:
    """One nuisance's decision in words (`FitResult.nuisances[name]`), with its fitted values."""
    how = "fitted" if entry.get("fitted") else "not fitted"
    values = entry.get("values") or {}
    if values:
        how += (
            " ("
            + "; ".join(f"{n} " + ", ".join(f"{v:.4g}" for v in vs) for n, vs in values.items())
            + ")"
        )
    if "chroma_detail" in entry:  # the luma comparison
        how = "compared in luma" if entry.get("fitted") else "compared in linear RGB"
        detail = entry["chroma_detail"]
        if not entry.get("forced") and math.isfinite(detail):
            how += f" (chroma detail {detail:.3g} of the luma's)"
        blocks = entry.get("jpeg") or {}
        if blocks.get("found"):
            quality = [q for q in blocks.get("quality") or () if q is not None]
            of = f", quality {'/'.join(map(str, quality))}" if quality else ""
            how += f", in its JPEG blocks to within half a step{of}"
    if entry.get("forced"):
        return f"{how} (forced)"
    if entry.get("exact"):
        return f"{how} (the fit explains the photo to its float rounding)"
    score, p = entry.get("score"), entry.get("p_value")
    if score is None or p is None or not math.isfinite(float(p)):
        return how
    why = "the photo needs it" if entry.get("chosen") else "the photo does not need it"
    gain = entry.get("explains")
    tried = (
        f"; fitted, chi2 {float(gain):.3g} lower in model-error units" if gain is not None else ""
    )
    return (
        f"{how} ({why}: score {float(score):.3g} on {entry.get('dof')} dof, p = {float(p):.2g}"
        f"{tried})"
    )


def _json_value(v):
    if isinstance(v, float):
        return _json_float(v)
    if isinstance(v, dict):
        return {k: _json_value(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_value(x) for x in v]
    return v


def _json_nuisances(nuisances: dict | None) -> dict | None:
    if nuisances is None:
        return None
    out = {}
    for name, entry in nuisances.items():
        out[name] = _json_value(entry)
        out[name]["text"] = nuisance_words(entry)
    return out


class RESULTS(eqxi.Enumeration):  # pyright: ignore
    """The status of a lens fit (`FitResult.status`), an enumeration as `optimistix.RESULTS`:
    compare with `==` (`result.status == jaxdof.RESULTS.degenerate`, traced, per batch element
    under `vmap`) and read the message with `jaxdof.RESULTS[result.status]`.

    - `successful`: converged to a determined, unambiguous lens.
    - `max_steps`: the solver did not converge within `max_steps`.
    - `solver_failed`: non-finite values, a failed linear solve, or an error raised while the
      compiled solve ran (e.g. a forward model's run-time check; `fit_lens` names it).
    - `dead_zone`: every circle is under half a pixel, where the render ignores the lens.
    - `degenerate`: the data do not determine every free field (a rank-deficient Jacobian).
    - `window`: the fitted circles outgrow the given filter window (`max_radius`).
    - `ambiguous`: distinct lenses fit equally well (e.g. the near/far ambiguity).
    - `inconsistent`: the solve converged, but the photo is not fully explained by the model: parts
      of it pull towards different lenses beyond their noise (the model-adequacy test,
      `FitResult.adequacy`); the standard errors are inflated to the spread between the parts,
      and with them the lens can be used (`success` is `True`).

    `window` and `ambiguous` are found by `fit_lens` only (`solve_lens` has one start and a fixed
    window).
    """

    successful = "converged"
    max_steps = "did not converge within max_steps: increase max_steps, or start from a closer init"
    solver_failed = (
        "the solver failed (non-finite values, a failed linear solve, or an error raised while "
        "it ran): check the inputs and weights for NaN or inf, or start from a closer init"
    )
    dead_zone = (
        "every circle is under half a pixel (of confusion): the render does not depend on the lens "
        "(zero Jacobian). Start from a lens with more blur (a smaller f_number, or a focus "
        "distance farther from the scene), or check that the targets are really defocused"
    )
    degenerate = (
        "the free parameters are not determined by the data (rank-deficient Jacobian; fit_lens's "
        "notes say which and why). Common causes: focal_length and f_number both free from one "
        "photo (the blur depends on the lens only through K = f^2 / (2 N (d_f - f)) and d_f: fix "
        "one from EXIF, or fit a focus bracket with shared=('focal_length', 'f_number')), a focus "
        "at infinity, or a scene of one depth plane"
    )
    window = (
        "the fitted circles exceed the filter window (max_radius): the model was clamped; pass a "
        "larger max_radius"
    )
    ambiguous = (
        "several distinct lenses fit the data equally well (e.g. the near/far ambiguity): add a "
        "photo at another focus distance, or fix the focus distance"
    )
    inconsistent = (
        "the photo is not fully explained by the model: tiles of it pull towards different lenses "
        "beyond their noise (a model-adequacy test), so the standard errors are inflated to the "
        "spread between the tiles, which covers the bias of what the model lacks; the lens with "
        "these errors can be used; the notes say where the photo differs from the model and "
        "the likely cause"
    )


# The members in the order of their codes (an Enumeration numbers its members as they are defined).
_NAMES = (
    "successful",
    "max_steps",
    "solver_failed",
    "dead_zone",
    "degenerate",
    "window",
    "ambiguous",
    "inconsistent",
)
_MEMBERS = tuple(getattr(RESULTS, name) for name in _NAMES)


def code_of(status: RESULTS) -> int:
    """The integer code of a concrete, unbatched status (its position in `RESULTS`)."""
    return int(np.asarray(status._value))


def member(code: int) -> RESULTS:
    """The `RESULTS` member with integer code `code`."""
    return _MEMBERS[code]


assert len(RESULTS) == len(_NAMES) and all(code_of(m) == i for i, m in enumerate(_MEMBERS))


def degeneracy_reason(
    code: int, free, shared, n_t: int, undetermined, at_infinity: bool, condition: float
) -> str:
    """Why the data do not determine the free set, in words, with the fix.

    `undetermined`: the free fields (names without target index) with no finite standard error;
    `at_infinity`: every photo's focus is at (or near) infinity at the solution. The reasons, in
    order: every circle under half a pixel (a dead zone); `focal_length` and `f_number` both free
    from one photo (or a bracket that does not share both, so that some photo has its own pair);
    a focus at infinity, where every circle is `f^2 / (2 N d p)`; otherwise a generic statement
    naming the undetermined fields.
    """
    if _NAMES[code] == "dead_zone":
        return (
            "every circle is under half a pixel at the solution, where the render does not depend "
            "on the lens (zero Jacobian): the photo looks in focus everywhere to this model. Start "
            "from a lens with more blur (a smaller f_number or a closer/farther focus distance), "
            "or check that the targets are really defocused"
        )
    pair = ("focal_length", "f_number")
    names = ", ".join(undetermined) if undetermined else ", ".join(free)
    if all(n in free for n in pair) and (n_t == 1 or not all(n in shared for n in pair)):
        alone = "" if n_t == 1 else f" (here each of the {n_t} photos has its own: shared={shared})"
        return (
            "focal_length and f_number cannot both be fitted from one photo" + alone + ": from a "
            "single photo the circle of confusion depends on the lens only through "
            "K = f^2 / (2 N (d_f - f)) and the focus distance d_f. Fixes: fix one of them from the "
            "EXIF data (drop it from free), or fit a focus bracket: several photos with different "
            "focus distances, free=('focal_length', 'f_number', 'focus_distance'), "
            "shared=('focal_length', 'f_number')"
        )
    if at_infinity:
        through = (
            ", which depends on focal_length and f_number only through f^2 / N"
            if all(n in undetermined for n in pair)
            else ""
        )
        return (
            f"focus at infinity: the photo{'s' if n_t > 1 else ''} do{'' if n_t > 1 else 'es'} "
            f"not constrain {names} there: focused at (or near) infinity every circle is "
            f"f^2 / (2 N d p) at depth d (p the pixel pitch){through}, and a farther focus "
            "changes nothing the photo shows. Fixes: fix one of the undetermined fields (EXIF), "
            "or add a photo focused inside the scene's depth range"
        )
    return (
        f"the data do not determine {names} (condition number {condition:.3g} of the "
        "column-scaled Jacobian): the photos constrain fewer combinations of the lens than there "
        "are free fields (e.g. a scene of one depth plane gives one circle size per photo, or a "
        "bracket's photos share one focus distance). Fixes: drop a field from free (set it from "
        "EXIF), add photos at other focus distances, or use a scene with more depth range"
    )


def _degeneracy_text(code: int, free, shared, n_t: int, undetermined, at_infinity, condition):
    """`fit_lens`'s `ValueError` for a dead zone or a degenerate free set: causes and fixes."""
    why = degeneracy_reason(code, free, shared, n_t, undetermined, at_infinity, condition)
    if _NAMES[code] == "dead_zone":
        head = "fit_lens: "
    else:
        head = (
            f"fit_lens: the free set {free} (shared {shared}, {n_t} target(s)) is not determined "
            "by the data: "
        )
    return head + why + ". Pass allow_degenerate=True to get the (non-unique) fit anyway."


def _json_float(v) -> float | None:
    """A JSON number: the shortest decimal that round-trips the value's own precision (0.085, not
    0.08500000089406967 for a float32 value); `None` for NaN and inf."""
    v = np.asarray(v)
    if not np.isfinite(v):
        return None
    return float(str(v.item() if v.dtype == np.float64 else np.float32(v)))


class FitResult(eqx.Module):
    """The outcome of `jaxdof.fit_lens` (and of `jaxdof.solve_lens`).

    **Fields:**

    - `lenses`: the fitted `ThinLens`, one per target (fields of shape `(T,)`).
    - `stderr`: standard error of each free field in its own units (metres for lengths, plain
      number for the f-number; `gain`, `offset` with `exposure=True`): a scalar for a single
      target, else an array `(T,)` (a shared field repeats its value).
      `inf` marks a field that the data do not determine (only with `allow_degenerate=True`),
      and a focus distance consistent with infinity (its power within one standard error of 0:
      no finite interval holds the distance; `focus_power_stderr` is finite).
    - `focus_power_stderr`: standard error (diopters, 1/m) of the focus power `1 / d_f`
      (`focus_power`), the coordinate the statistics are computed in: finite through focus at
      infinity. Shaped as a `stderr` entry; NaN when the focus distance is not free.
    - `covariance`: covariance of the free parameters in their own units, `(p, p)`, in the order of
      `names` (e.g. `("f_number", "focus_distance")`, or `"focus_distance[1]"` per target); the
      row and column of a focus distance consistent with infinity are NaN.
    - `names`: the name of each row of `covariance`.
    - `gain`, `offset`: exposure per target (1 and 0 unless `exposure=True`), `(T,)`.
    - `loss`: `0.5 * sum(residual^2)` at the solution.
    - `sigma`: the residual standard deviation `sqrt(SSR / (n - p))` used to scale `covariance`.
    - `num_steps`: solver steps taken by the chosen start.
    - `condition`: condition number of the column-scaled Jacobian at the solution.
    - `status`: a `jaxdof.RESULTS` member (traced; one per batch element under `vmap`), e.g.
      `result.status == jaxdof.RESULTS.successful`.
    - `success`: `True` when the lens and its standard errors can be trusted: the fit converged to
      a determined, unambiguous lens, with errors from the noise, or (status `inconsistent`)
      inflated to the spread between tiles of the photo that disagree beyond their noise.
    - `notes`: `fit_lens`'s explanations in words (refits, the competing lens, ...); `""` if none.
    - `max_radius`: the filter window (pixels) the fit used (at full resolution).
    - `pixels_used`: the number of photo pixels (over targets, rows and columns) with non-zero
      weight in the residual at full resolution: the border band and `weight=0` left out.
    - `border`: the width (photo pixels) of the band along the edges left out of the residual
      (0: every pixel kept; see `fit_lens`'s `border`).
    - `adequacy`: the model-adequacy test at the solution (`jaxdof.internal.adequacy`: do
      independent tiles of the photo agree on one lens, beyond their noise?), a dict of arrays:
      `chi2`, `dof`, `p_value`, `tiles` (tiles with information), `adequate` (`p_value >= 0.01`,
      or too few degrees of freedom to test), `inflation` (`>= 1`; 1 unless the test fires).
      When it fires the status is `inconsistent` (unless another failure came first) and
      `stderr`, `focus_power_stderr` and `covariance` are already multiplied by `inflation`
      (`inflation^2`): see `stderr_kind`.
    - `levels`: pyramid levels `fit_lens` solved on (1: full resolution only; see its `pyramid`).
    - `tiles`: the photo tiles fitted, `(row, column, height, width)` of each (photo pixels), when
      `fit_lens` fitted on informative tiles (see its `tiles`); `()`: the whole frame.
    - `treatment`: what `fit_lens` chose to model and leave out for this scene (occlusion, edge
      weight, footprint, border; a `jaxdof.Treatment`, `str()` says it in words); `None` from
      `solve_lens`, which models what it is given.
    - `nuisances`: what `fit_lens` decided about what the camera adds (`"exposure"`,
      `"vignetting"`, `"illumination"`, `"registration"`, per photo): `{"fitted", "forced",
      "chosen", "score", "dof", "p_value", "explains"}`: the score test at the fit without it and, where that
      rejected, by how much fitting it lowered the chi-square in units of the model's error
      (`select.explained`; `chosen`: kept), and `"values"` where fitted (shifts in photo
      pixels); and `"luma"`: whether the photos were compared in their
      luma, with the colour detail that decided it, and `"jpeg"`: whether in their JPEG blocks
      (`found`, `origin`, `quality`: the IJG quality the table matched). `None` from
      `solve_lens`.

    `message` is the status's message and the notes; `stderr_kind` says what the standard errors
    measure (`"noise"`, or `"tile spread"` when inflated); `lens` is the first target's lens;
    `focus_power` the focus power `1 / d_f` per target (diopters, 0 at infinity); `summary()`
    formats everything as a table and `to_dict()` as JSON-ready numbers.
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
    status: RESULTS
    success: Bool[Array, ""]
    focus_power_stderr: Float[Array, "*t"]
    pixels_used: Int[Array, ""]
    adequacy: dict[str, Array]
    names: tuple[str, ...] = eqx.field(static=True)
    notes: str = eqx.field(static=True, default="")
    max_radius: float = eqx.field(static=True, default=0.0)
    border: int = eqx.field(static=True, default=0)
    levels: int = eqx.field(static=True, default=1)
    tiles: tuple[tuple[int, int, int, int], ...] = eqx.field(static=True, default=())
    treatment: Treatment | None = eqx.field(static=True, default=None)
    nuisances: dict | None = eqx.field(static=True, default=None)

    @property
    def lens(self) -> ThinLens:
        """The first target's lens."""
        return jax.tree_util.tree_map(lambda x: x[0], self.lenses)

    @property
    def focus_power(self) -> Array:
        """The focus power `1 / focus_distance` of every target (diopters, 1/m; 0 at infinity)."""
        return self.lenses.focus_power

    @property
    def message(self) -> str:
        """What happened, in words: the status's message, then the notes. For one fit: index a
        batch first (`jax.tree_util.tree_map(lambda x: x[i], result).message`)."""
        self._check_one("message")
        text = RESULTS[self.status]
        return f"{text}; {self.notes}" if self.notes else text

    @property
    def stderr_kind(self) -> str:
        """What the standard errors measure: `"noise"` (Gauss-Newton, the pixel noise only: the
        model explained the photo) or `"tile spread"` (the adequacy test fired, and they are
        inflated to the spread between the photo's tiles). For one fit."""
        self._check_one("stderr_kind")
        return "noise" if float(self.adequacy["inflation"]) == 1.0 else "tile spread"

    def _adequacy_text(self) -> str:
        a = {k: float(np.asarray(v)) for k, v in self.adequacy.items()}
        verdict = "consistent" if a["adequate"] else "INCONSISTENT"
        text = (
            f"adequacy: {verdict} (chi2 {a['chi2']:.4g} on {a['dof']:g} dof, p = "
            f"{a['p_value']:.3g}, {a['tiles']:g} tiles)"
        )
        if self.stderr_kind == "noise":
            return text + "; stderr: noise"
        return text + f"; stderr: tile spread (noise x {a['inflation']:.3g})"

    def _check_one(self, what: str) -> None:
        if np.ndim(self.success) != 0:
            raise ValueError(
                f"FitResult.{what} describes one fit, but this result holds a batch of shape "
                f"{np.shape(self.success)} (from vmap or fit_batch): take one first, "
                "e.g. jax.tree_util.tree_map(lambda x: x[i], result)"
            )

    def summary(self) -> str:
        """A human-readable table of the fitted lens(es), standard errors and fit statistics."""
        lines = [f"fit_lens: {'success' if bool(self.success) else 'FAILED'}: {self.message}"]
        n_t = int(np.shape(self.lenses.focal_length)[0])
        for t in range(n_t):
            lens = ThinLens(*(np.asarray(getattr(self.lenses, n))[t] for n in ALL_FIELDS))
            lines.append(f"target {t}:" if n_t > 1 else "lens:")
            for name in LENS_FIELDS:
                value = float(getattr(lens, name))
                if name in self.stderr:
                    se = float(np.reshape(np.asarray(self.stderr[name]), -1)[t if n_t > 1 else 0])
                    lines.append(f"  {name:15s} {value:.6g} +- {se:.2g} {_UNITS[name]}".rstrip())
                else:
                    lines.append(f"  {name:15s} {value:.6g} {_UNITS[name]} (fixed)".rstrip())
            if "focus_distance" in self.stderr:
                se = float(np.reshape(np.asarray(self.focus_power_stderr), -1)[t if n_t > 1 else 0])
                lines.append(
                    f"  {'focus power':15s} {float(lens.focus_power):.6g} +- {se:.2g} dpt "
                    "(1 / focus_distance)"
                )
            lines.append(f"  {'K (blur scale)':15s} {float(lens.blur_scale):.6g} px")
        for name, entry in (self.nuisances or {}).items():
            lines.append(f"{name}: {nuisance_words(entry)}")
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
            f"window {self.max_radius:g} px, pixels used {int(self.pixels_used)} "
            f"(border {self.border} px)"
        )
        lines.append(self._adequacy_text())
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        """The fit as a JSON-ready dict (`json.dumps(result.to_dict())`), SI units.

        Keys: the first target's lens (`focal_length`, `f_number`, `focus_distance`,
        `pixel_pitch`, m) and its `stderr` (free fields only); `lenses`, one dict per target with
        its own `stderr`, `focus_power` (diopters) and `focus_power_stderr`; `success`, `status`
        (the `RESULTS` member's name), `message`, `steps`, `loss`, `sigma`, `condition`,
        `max_radius` (px), `pixels_used`, `border` (px), `levels`, `tiles`, `treatment` (`Treatment.to_dict()`, with `text` the
        words; `None` from `solve_lens`), `adequacy` (the test's
        numbers, `adequate` a bool), `stderr_kind`, `names`, `covariance` (rows
        and columns in the order of `names`), `gain` and `offset` (per target). Numbers are the
        shortest decimals that round-trip the arrays' precision; NaN and inf become `None`.
        For one fit (index a batch first).
        """
        self._check_one("to_dict")
        n_t = int(np.shape(self.lenses.focal_length)[0])
        per_target = []
        for t in range(n_t):
            lens = {n: _json_float(np.asarray(getattr(self.lenses, n))[t]) for n in ALL_FIELDS}
            err = {}
            for name, v in self.stderr.items():
                v = np.asarray(v)
                err[name] = _json_float(v if v.ndim == 0 else v.reshape(-1)[min(t, v.size - 1)])
            power = np.asarray(self.lenses.focus_power).reshape(-1)[t]
            se_power = np.asarray(self.focus_power_stderr).reshape(-1)
            extra = {
                "focus_power": _json_float(power),
                "focus_power_stderr": _json_float(se_power[min(t, se_power.size - 1)]),
            }
            per_target.append({**lens, "stderr": err, **extra})
        return {
            **per_target[0],
            "success": bool(self.success),
            "status": _NAMES[code_of(self.status)],
            "message": self.message,
            "steps": int(self.num_steps),
            "loss": _json_float(self.loss),
            "sigma": _json_float(self.sigma),
            "condition": _json_float(self.condition),
            "max_radius": float(self.max_radius),
            "pixels_used": int(self.pixels_used),
            "border": int(self.border),
            "levels": int(self.levels),
            "tiles": [list(box) for box in self.tiles],
            "treatment": None if self.treatment is None else self.treatment.to_dict(),
            "nuisances": _json_nuisances(self.nuisances),
            "adequacy": {
                k: bool(v) if k == "adequate" else _json_float(v) for k, v in self.adequacy.items()
            },
            "stderr_kind": self.stderr_kind,
            "names": list(self.names),
            "covariance": [[_json_float(x) for x in row] for row in np.asarray(self.covariance)],
            "gain": [_json_float(x) for x in np.asarray(self.gain)],
            "offset": [_json_float(x) for x in np.asarray(self.offset)],
            "lenses": per_target,
        }
