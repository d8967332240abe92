r"""What a scene needs modelled, decided from its depth map and a lens: `Treatment`.

A photo differs from the thin-lens render of its all-in-focus image in three places, each with a
treatment that `jaxdof.fit_lens` (and `jaxdof.render(method="auto")`) turns on only where the
scene needs it, by a measured rule (`jaxdof/_tuning.py`, `fits/treatments.py`):

- **Depth edges that matter.** Within a circle of an occlusion edge a real aperture sees around the
  foreground (hidden background behind a sharp foreground, a semi-transparent blurred one), which
  an image with one depth per pixel lacks. An edge *matters* when a pixel on it
  (`jaxdof.depth_edges`: a relative depth step over 3 % between 4-neighbours, so a floor or a
  slanted wall is no edge) or a neighbour has a circle over half a pixel at the lens: below that
  the render copies the pixel (the dead zone) and no light crosses the edge. When such edges touch
  more than `EDGE_MIN_SHARE` of the pixels (within the circle of one of them), the model renders
  occlusion (`OCCLUSION_METHOD`, `jaxdof.LocalOcclusion`), and a fit's weight ramps to 0 towards
  them (`jaxdof.edge_weight` with the width of the largest circle on them, plus a pixel) unless
  that would leave less than `EDGE_KEEP_MIN` of the weight, where the edges are the scene.
- **Small circles.** Spreading a pinhole pixel (itself a box average) with the circle-pixel
  overlap adds one pixel footprint too many, a blur variance of `1/6 px^2` against the lens's
  `r^2 / 2` (both axes), so `K` comes out short by about `1 / (6 r^2)` (relative): 1.9 % at
  `r = 3`, 1e-4 at 40 px. The footprint correction (`jaxdof.footprint_prefilter`) is on when
  the lens's median circle over the pixels is under `FOOTPRINT_BELOW` px (40): a bias a fit of a
  large photo can detect, at a cost of a few percent of the fit.
- **The border** (a fit's only): always left out (`fit_lens`'s `border`, decided with the window).
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np

from . import _tuning
from ._corrections import depth_edges, edge_distance_to
from ._filters.occlusion import DEFAULT_JUMP


# The rules' thresholds, with their measurements: `jaxdof/_tuning.py` (`TREATMENT_*`).
FOOTPRINT_BELOW = _tuning.TREATMENT_FOOTPRINT_BELOW
EDGE_MIN_SHARE = _tuning.TREATMENT_EDGE_MIN_SHARE
EDGE_KEEP_MIN = _tuning.TREATMENT_EDGE_KEEP_MIN
#: A circle (px) that spreads light off its pixel: the dead zone's edge.
_DEAD_ZONE = 0.5
#: The default model's method where occlusion matters: the per-pair local occlusion with the
#: hidden surfaces filled, chosen over the global layers of `Occlusion` by `fits/occlusion_local.py`
#: (within 2 px of edges 0.5-0.7 dB behind it on the tuning scenes, 4.4 dB ahead on the held-out
#: floor scene, where no global depth gap exists; at 2-3x the soft filter's cost against 6-11x).
OCCLUSION_METHOD = "local_occlusion"


@dataclasses.dataclass(frozen=True)
class Treatment:
    """What `fit_lens` (or `render(method="auto")`) did to the scene, and why (`FitResult.treatment`).

    - `method`: the default forward model's filter method (`"soft"`, `"local_occlusion"`, or the
      caller's `method=`, by its alias or class name); `"model"` for a caller's forward model.
    - `occlusion`: the forward model renders occlusion at depth edges.
    - `edge_pixels`: depth-edge pixels whose starting circle exceeds half a pixel (image grid).
    - `edge_share`: the share of the fitted pixels within a starting circle of such an edge.
    - `edge_weight`: the width (px) of the edge weight's ramp; 0 when off.
    - `footprint`: the pixel-footprint correction is on.
    - `median_circle`: the starting lens's median circle over the fitted pixels (photo px).
    - `border`: the band along the frame's edges left out (photo px; set after the fit).
    - `forced`: the choices the caller made (`"occlusion"`, `"footprint"`, `"edge_weight"`);
      the rest were chosen by the rules above.
    - `depth_holes`: image pixels without a depth (NaN, 0, negative; filled for the render) and
      `hole_pixels`: the photo pixels within `hole_reach` photo px of them (the starting lens's
      circle), left out of the fit; a refit that the photo compares leaves out the same ones.
    - `depth_upsampled`: the shape of a coarser depth map `fit_lens` upsampled to the image
      (`jaxdof.upsample_depth`); `()` when it had the image's.
    - `selected`: what the photo said of the scene's choices (a fit's only; `jaxdof/_fit/select.py`):
      e.g. `"footprint off: better by chi2 812"` where the fit without it explains the photo
      better, `"occlusion off: not better (chi2 -62)"` where it does not.
    """

    method: str = "soft"
    occlusion: bool = False
    edge_pixels: int = 0
    edge_share: float = 0.0
    edge_weight: float = 0.0
    footprint: bool = False
    median_circle: float = 0.0
    border: int = 0
    forced: tuple[str, ...] = ()
    selected: tuple[str, ...] = ()
    depth_holes: int = 0
    hole_pixels: int = 0
    hole_reach: float = 0.0
    depth_upsampled: tuple[int, ...] = ()

    def __str__(self) -> str:
        parts = []
        if self.occlusion:
            parts.append(f"occlusion ({self.edge_pixels} edge pixels)")
        if self.edge_weight > 0:
            parts.append(f"edge weight {self.edge_weight:.3g} px")
        if self.footprint:
            parts.append("footprint")
        parts.append(f"border {self.border} px")
        if self.depth_holes:
            parts.append(
                f"{self.depth_holes} depth holes filled ({self.hole_pixels} photo px near them "
                "left out)"
            )
        if self.depth_upsampled:
            h, w = self.depth_upsampled
            parts.append(f"depth upsampled from {h}x{w}")
        text = ", ".join(parts)
        text = f"{text} (forced: {', '.join(self.forced)})" if self.forced else text
        return f"{text}; photo: {', '.join(self.selected)}" if self.selected else text

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        return {
            **d,
            "forced": list(self.forced),
            "selected": list(self.selected),
            "text": str(self),
        }


def rows_of(lenses) -> np.ndarray:
    """The concrete lenses `lenses` (`jaxdof.ThinLens`, scalar fields) as rows `(T, 4)` of
    `(f, N, d_f, pitch)`, float64, as `start_circles` takes them."""
    fields = ("focal_length", "f_number", "focus_distance", "pixel_pitch")
    return np.array([[float(np.asarray(getattr(n, k))) for k in fields] for n in lenses])


def start_circles(lens_rows: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """The largest circle (pixels of the lens's pitch) over lens rows `(T, 4)` of
    `(f, N, d_f, pitch)` at every pixel of `depth` (float32; focus at infinity included, as
    `forward.max_circle`)."""
    inv_d = 1 / np.asarray(depth, np.float32)
    out = np.zeros(inv_d.shape, np.float32)
    step = np.empty_like(out)
    for f, n, d_f, pitch in np.asarray(lens_rows, np.float64).reshape(-1, 4):
        u = 0.0 if math.isinf(d_f) else 1.0 / d_f
        c = f * f / (2 * n * pitch) / (1 - f * u)  # > 0
        # |c (u - 1/d)|, in place (a 24 MP frame's temporaries cost more than the arithmetic)
        np.subtract(np.float32(u), inv_d, out=step)
        np.abs(step, out=step)
        step *= np.float32(c)
        np.maximum(out, step, out=out)
    return out


def choose_treatment(
    depth: np.ndarray,
    init_rows: np.ndarray,
    fitted: np.ndarray,
    ratio: int,
    *,
    occlusion: bool | None,
    footprint: bool | None,
    edge_weight: bool | float | None,
    edges: np.ndarray | None = None,
) -> tuple[Treatment, np.ndarray | None]:
    """The treatment of a scene and the edge weight on the image grid (`None`: no edge weight).

    **Arguments:**

    - `depth`: z-depth `(H, W)` of the image (m).
    - `init_rows`: the starting lens per target, `(T, 4)` of `(f, N, d_f, pitch)`, the pitch of
      the photo's pixels; a pixel's circle is the largest over the targets.
    - `fitted`: `(H / ratio, W / ratio)` bool, the photo pixels with weight (before the border).
    - `ratio`: the image's pixels per photo pixel along an axis (`downsample`).
    - `occlusion`, `footprint`, `edge_weight`: the caller's forced choices, `None` to decide
      (`edge_weight` may be a width in photo px).
    - `edges`: `depth_edges(depth)` where known (not modified), else found here.
    """
    forced = tuple(
        name
        for name, v in (
            ("occlusion", occlusion),
            ("footprint", footprint),
            ("edge_weight", edge_weight),
        )
        if v is not None
    )
    r = start_circles(init_rows, depth)
    r = r * ratio if ratio != 1 else r  # image pixels
    fitted_img = np.repeat(np.repeat(fitted, ratio, 0), ratio, 1) if ratio != 1 else fitted
    median = float(np.median(r[fitted_img])) / ratio if fitted_img.any() else 0.0
    # An edge pixel matters when it or a neighbour across the edge spreads light off its pixel:
    # the largest circle of its 3 x 3 neighbourhood (the frame's edge pixels repeated).
    edges = depth_edges(depth, jump=DEFAULT_JUMP) if edges is None else edges.copy()
    rows, cols = np.nonzero(edges)
    h, w = r.shape
    around = np.zeros(rows.shape, np.float32)
    for di, dj in itertools.product((-1, 0, 1), repeat=2):
        around = np.maximum(around, r[np.clip(rows + di, 0, h - 1), np.clip(cols + dj, 0, w - 1)])
    dead = ~(around > _DEAD_ZONE * ratio)
    edges[rows[dead], cols[dead]] = False
    n_edges = int(rows.size - dead.sum())
    reach = float(around[~dead].max()) + 1.0 if n_edges else 0.0
    dist = edge_distance_to(edges, limit=max(reach, 1.0))
    near = dist < reach
    share = float(np.mean(near[fitted_img])) if fitted_img.any() else 0.0
    matters = share > EDGE_MIN_SHARE
    weight = None
    width = 0.0
    want_weight = matters if edge_weight is None else bool(edge_weight)
    if want_weight and n_edges:
        width = reach if edge_weight in (None, True) else float(edge_weight) * ratio
        # the distances above serve when the width is the reach (the automatic width)
        d_w = dist if width <= max(reach, 1.0) else edge_distance_to(edges, limit=width)
        weight = np.clip(d_w / width, 0.0, 1.0) ** 2
        kept = float(np.mean(weight[fitted_img])) if fitted_img.any() else 0.0
        if edge_weight is None and kept < EDGE_KEEP_MIN:
            weight, width = None, 0.0
    treatment = Treatment(
        occlusion=matters if occlusion is None else bool(occlusion),
        edge_pixels=n_edges,
        edge_share=share,
        edge_weight=width / ratio,
        footprint=(median < FOOTPRINT_BELOW) if footprint is None else bool(footprint),
        median_circle=median,
        forced=forced,
    )
    return treatment, weight


def scene_treatment(
    depth, lens, *, downsample: int = 1, footprint: bool | None = None
) -> Treatment:
    """What `jaxdof.render(..., method="auto")` models for `lens` on this depth map: the rules
    above over every pixel of the frame (`fit_lens` applies them to its fitted pixels and its
    starting lens).

    **Arguments:**

    - `depth`: concrete z-depth `(H, W)` (m).
    - `lens`: a concrete `jaxdof.ThinLens` (`pixel_pitch` the photo's).
    - `downsample`: the image's pixels per photo pixel along an axis, as in `render`.
    - `footprint`: `None` decides by the rule; a bool forces it (reported in `forced`).

    **Returns:** a `Treatment` (`occlusion`, `footprint`, the edge statistics; `edge_weight` and
    `border` are a fit's and stay 0). Its `method` is the filter method `render` uses:
    `"local_occlusion"` where the edges matter, else `"auto"` (the fastest equivalent of `soft`).
    """
    depth = np.asarray(depth)
    s = int(downsample)
    fitted = np.ones((depth.shape[0] // s, depth.shape[1] // s), bool)
    treatment, _ = choose_treatment(
        depth,
        rows_of([lens]),
        fitted,
        s,
        occlusion=None,
        footprint=footprint,
        edge_weight=False,
    )
    method = OCCLUSION_METHOD if treatment.occlusion else "auto"
    forced = tuple(name for name in treatment.forced if name != "edge_weight")  # a fit's only
    return dataclasses.replace(treatment, method=method, forced=forced)
