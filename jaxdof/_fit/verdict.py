"""A fit's verdict: its status on the host (an ambiguity between starts, a window too small, a
free set the data cannot determine), its notes in words (the adequacy test's numbers and the
likely cause from the pattern of the residual, focus consistent with infinity, the tiles used),
and the `FitResult` of a solve that raised.
"""

from __future__ import annotations

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np

from .._corrections import depth_edges
from .._lens import ThinLens
from .layout import LENS_FIELDS, nuisance_names, theta_floor
from .path import Run
from .prepare import Problem
from .result import RESULTS, FitResult, _degeneracy_text, code_of, degeneracy_reason, member
from .strategies import apply_border, distinct, level_band
from .tiles import Tiles


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


def _fields_text(names, theta) -> str:
    """`name=value` for solution slots `theta` (statistical units: the focus as its power), the
    focus shown as a distance (m; `inf` at power 0)."""
    parts = []
    for n, v in zip(names, np.asarray(theta, np.float64)):
        if n.startswith("focus_distance"):
            v = np.inf if v <= 0 else 1 / v
        parts.append(f"{n}={v:.5g}")
    return ", ".join(parts)


def _ambiguity(info, p: Problem) -> str | None:
    """The near/far ambiguity: another converged start at a distinct lens (beyond 10 standard
    errors), with a loss the noise cannot tell from the best one's (`race.tie_margin`, the rule
    that picks the best). Returns the note naming it, or None."""
    loss, converged, best = info["loss"], info["converged"], int(info["best"])
    if len(loss) < 2:
        return None
    spec = p.spec
    used = list(spec.used)
    theta = np.asarray(info["theta"], np.float64)[:, used]
    floor = np.asarray(theta_floor(p.layout, spec.nuisances), np.float64)[used]
    se = np.sqrt(np.maximum(np.asarray(info["variance"], np.float64), 0))
    for i in np.argsort(loss):
        if i == best or not converged[i]:
            continue
        tie = loss[i] - loss[best] <= float(info["tie"])
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


def _at_infinity(run: Run, rows: np.ndarray) -> bool:
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


def tiles_note(tiles: Tiles, photo_pixels: int) -> str:
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
    # Against the median of the cells with a residual (a camera JPEG's blocks leave cells at 0
    # where the render encodes to the file's values).
    some = cells[ok & (cells > 0)]
    spread = float(np.max(some) / np.median(some)) if some.size else 1.0
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


def verdict(run: Run, result: FitResult, info, r_final, window, notes, allow_degenerate):
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


def failed(run: Run, err: BaseException, window: float) -> FitResult:
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
