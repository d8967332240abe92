r"""Lens calibration: recover focal length, f-number and focus distance from defocused photos.

`fit_lens` solves the nonlinear least-squares problem

$$\min_\theta \sum_t \sum_p w_p \left( P_t\big(\mathrm{render}(I, Z, \mathrm{lens}_t(\theta))\big)_p
  - T_{t,p} \right)^2$$

over the free lens fields `theta`, `P_t` what the camera adds where the photo needs it (an
exposure gain and offset, vignetting, a registration per target; the luma of a camera JPEG:
`photo.py`, compared in its blocks: `jpeg.py`), with an optimistix least-squares solver (Levenberg-Marquardt by default), from a few
starting points spread over the scene's depth range. It is the only package that imports
optimistix. `render` is the forward model, `jaxdof.DefocusModel` unless another
`jaxdof.AbstractForwardModel` is given.

**What a single image can determine.** The circle of confusion of a point at depth `d` is
`r = K |1 - d_f / d|` pixels with `K = f^2 / (2 N (d_f - f)) / p` (`jaxdof.coc_radius`), so one
photo determines `K` and `d_f` but not `f` and `N` separately: any `(f, N)` with the same `K` (and
`d_f`) renders the same image. `fit_lens` finds such a degeneracy from the rank of the
column-scaled Jacobian at the best solution and refuses it (`ValueError`, with the reason) unless
asked not to. A focus
bracket (several photos with different focus distances through the same `f` and `N`) separates
them: `K_t \propto 1 / (d_{f,t} - f)` varies across the bracket in a way that depends on `f`.

**Coordinates.** The solver works in unconstrained coordinates, so every iterate is a physical lens:
`log N`, a bounded logit of `f` (`f` under the nearest depth and a fixed focus distance), and for
the focus `fcap / (d_f - f) = |y| + 1e-12`, the focus power scaled to the scene, in which focus at
infinity is the ordinary point `y = 0` (`layout.py`; `fit_lens` treats it as a bound the data may
press against). The statistics are computed in `(f, N, 1 / d_f)` and mapped to each field's own
units (metres, or dimensionless for `N`); a focus consistent with infinity has an infinite
standard error in metres and a finite one in diopters (`FitResult.focus_power_stderr`).

**The border.** Photo pixels within a circle's reach of the frame's edge receive light from outside
it, which the image lacks; `fit_lens` leaves that band out of the residual by default (a zero
weight, `border`).

**The parts**, lower to higher (the data path: coordinates -> render -> residual -> solve ->
statistics -> the orchestration's choices):

- `layout.py`: the parameter layout (`_Spec`, `_Layout`) and the unconstrained coordinates;
- `forward.py`: the forward models (`AbstractForwardModel`, `DefocusModel`) and `max_circle`;
- `photo.py`: what the camera adds to the render (exposure, vignetting, registration, luma);
- `jpeg.py`: a camera JPEG's luma compared in its 8 x 8 blocks to within half a step, and its
  quantisation table found from the decoded photo;
- `residual.py`: the residual function (`_Model`) with its Jacobian-materialising JVP rule;
- `linalg.py`: the small dense decompositions of the statistics (thin SVD, pseudo-inverse);
- `lm.py`: the default solver, Levenberg-Marquardt that stops at the noise level;
- `race.py`: the multi-start solve, every start in lockstep, a slow start stopped;
- `adequacy.py`: the model-adequacy test between tiles of the residual;
- `result.py`: `FitResult`, the status enumeration `RESULTS`, and the wording;
- `prepare.py`: input checks and conversion;
- `solve.py`: the pure solve, statistics, the compiled stages and `solve_lens`;
- `strategies.py`: starts, windows, the border band, the coarse-to-fine pyramid;
- `tiles.py`: the informative tiles of a large photo, and a fit's memory estimate;
- `treatment.py`: what the scene needs modelled (occlusion, edge weight, footprint): `Treatment`;
- `verbose.py`: the solver's `verbose` callable, with the lenses each step reached;
- `path.py`: one fit's solves in order: the starts' coarse solve (a pyramid, or a scout and
  tiles), the full-resolution solve and its window refits, focus at infinity as a bound;
- `verdict.py`: the status and the notes in words, and the result of a solve that raised;
- `select.py`: the photo's say in the treatment and in the camera's nuisances;
- `fit.py`: `fit_lens`, which orchestrates them.

**For studies and the CLI**: `auto_levels` (the automatic pyramid rule), `max_circle` (the
largest circle of lenses over a depth map), `start_lenses` (fit_lens's starts), `record_stages`
(time the compiled stages of `fit_lens` calls without patching; these four are re-exported by
`jaxdof.internal`), `window_for` (the window rule of `strategies.py`'s window policy), `watch_stages` (tell a caller each stage
as it runs: the CLI's progress), `run_stage`, `fit_starts`, `restate` and `finish` (the stages).
"""

from .fit import fit_lens as fit_lens
from .forward import (
    AbstractForwardModel as AbstractForwardModel,
    DefocusModel as DefocusModel,
    max_circle as max_circle,
)
from .result import RESULTS as RESULTS, FitResult as FitResult
from .solve import (
    finish as finish,
    fit_starts as fit_starts,
    record_stages as record_stages,
    restate as restate,
    run_stage as run_stage,
    solve_lens as solve_lens,
    watch_stages as watch_stages,
)
from .strategies import (
    auto_levels as auto_levels,
    start_lenses as start_lenses,
    window_for as window_for,
)
from .treatment import Treatment as Treatment, choose_treatment as choose_treatment
