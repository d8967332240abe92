r"""`calibrate`: the lens from photos of a chart: find the chart, solve the camera and the pose,
build the chart's all-in-focus image and depth in each photo's frame, and fit the lens with
`jaxdof.fit_lens`."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Float

from .. import _tuning
from .._exif import ExifLens
from .._fit import FitResult, fit_lens
from .._fit.solve import stage_note
from .._holes import near_holes
from .._lens import ThinLens
from .._scene import rows_of, start_circles
from ._align import align_view, alignment_samples, render_template, usable_pixels
from ._design import Chart
from ._detect import ChartView, detect_chart
from ._geometry import (
    ChartError,
    ChartPose,
    camera_matrix,
    chart_pose,
    chart_scene,
    focal_from_homographies,
    focal_stderr,
    refine_focal,
)


_MIN_TILT = 10.0  # degrees: a chart closer to facing the camera gives too little depth range
# Photos of one scene (a focus bracket): their chart corners agree, once a magnification about
# the centre (focus breathing) is taken out, within this many pixels plus this share of the
# chart's extent in the photo.
_SAME_PX, _SAME_SHARE = 2.0, 0.01
_F_NUMBER = 4.0  # the starting f-number when EXIF has none
_KEEP = 0.5  # the share of the chart's pixels that the background's band leaves at least
_GIVEN = "focal length and pixel pitch"


@dataclasses.dataclass(frozen=True)
class ChartCalibration:
    """What `calibrate` found and fitted.

    **Fields:**

    - `fit`: the `jaxdof.FitResult` of `jaxdof.fit_lens` (`fit.lens`, `fit.stderr`, ...).
    - `views`: the chart found in each photo (`ChartView`: how, the homography, its error).
    - `poses`: the chart's pose in each photo (`ChartPose`; `tilt` in degrees).
    - `camera`: the intrinsic matrix `K` (pixels) used.
    - `focal_px`: its focal length (pixels): the lens-to-sensor distance over the pixel pitch.
    - `focal_px_stderr`: its standard error (pixels): from the corners placed to
      `_tuning.CHART_CORNER_PX` where found from the homographies; from the fitted focus's where
      taken at it (the focal length and the pitch given, not the focus distance); else 0.
    - `intrinsics`: where `focal_px` came from: `"focal length and pixel pitch"` or
      `"homographies"`.
    - `init`: the starting lens (one per photo).
    - `depth_range`: the chart's nearest and farthest z-depth (m) in the first photo.
    - `aligned_px`: per photo, how far (pixels) the chart's corners moved when it was aligned
      again with the first fit's blur (`calibrate`'s `align`); empty where it was not.
    """

    fit: FitResult
    views: tuple[ChartView, ...]
    poses: tuple[ChartPose, ...]
    camera: Float[np.ndarray, "3 3"]
    focal_px: float
    focal_px_stderr: float
    intrinsics: str
    init: tuple[ThinLens, ...]
    depth_range: tuple[float, float]
    aligned_px: tuple[float, ...] = ()

    @property
    def lens(self) -> ThinLens:
        """The fitted lens (`fit.lens`)."""
        return self.fit.lens

    def to_dict(self) -> dict[str, Any]:
        """The chart's part as JSON-ready values (SI units, angles in degrees): per photo the
        markers decoded, how the chart was found, the homography's error (px), the blur and
        correlation it was refined at, the tilt and the pose; the intrinsics."""
        return {
            "focal_px": self.focal_px,
            "focal_px_stderr": self.focal_px_stderr,
            "intrinsics": self.intrinsics,
            "depth_range": list(self.depth_range),
            "aligned_px": list(self.aligned_px),
            "photos": [
                {
                    "markers": v.markers,
                    "found_by": v.method,
                    "coc_px": v.coc_px,
                    "correlation": v.correlation,
                    "inliers": v.inliers,
                    "reprojection_error_px": v.error,
                    "cover": v.cover,
                    "tilt_deg": p.tilt,
                    "distance_m": float(np.linalg.norm(p.translation)),
                    "rotation": p.rotation.tolist(),
                    "translation_m": p.translation.tolist(),
                    "homography": v.homography.tolist(),
                }
                for v, p in zip(self.views, self.poses)
            ],
        }


def calibrate(
    photos: np.ndarray | Sequence[np.ndarray],
    chart: Chart,
    image: Float[np.ndarray, "ch cw"],
    *,
    focal_length: float | int | None = None,
    pixel_pitch: float | int | None = None,
    exif: ExifLens | Sequence[ExifLens | None] | None = None,
    init: ThinLens | Sequence[ThinLens] | None = None,
    views: Sequence[ChartView] | None = None,
    align: bool = True,
    **fit_options,
) -> ChartCalibration:
    r"""Calibrate a lens from photos of a chart (`make_chart`): the chart gives the fit its
    all-in-focus image and depth map.

    **Arguments:**

    - `photos`: one photo `(H, W)`/`(H, W, C)` (linear light) or several of one scene (a focus
      bracket taken from a tripod: the chart where it was).
    - `chart`, `image`: the chart and its raster (`read_chart`).
    - `focal_length`, `pixel_pitch`: the lens's focal length and the photo's pixel pitch (m),
      where known; they override `exif`.
    - `exif`: the photos' `jaxdof.ExifLens` (one, or one per photo): focal length, f-number,
      focus distance and pixel pitch where recorded.
    - `init`: the starting lens (one, or one per photo); default from the values above.
    - `views`: the chart as already found in each photo (`detect_chart`); default: found here.
    - `align`: find the chart again in each photo with the first fit's blur and fit again
      (default); `False`: one fit, with the chart where `detect_chart` put it.
    - `fit_options`: passed to `jaxdof.fit_lens` (`free`, `shared`, `verbose`, the nuisances,
      ...): its defaults otherwise, so vignetting, registration and luma are decided from the
      photos; the exposure (gain and offset) and the illumination (its tilt across the frame)
      are fitted by default, as the chart's raster says nothing of the light on it.

    **Returns:** a `ChartCalibration`: the `FitResult` and what the chart told.

    **Method.** The homographies give the camera's focal length in pixels `f_px`, the distance
    from the lens to the sensor over the pixel pitch (`focal_from_homographies`, with square
    pixels and the principal point at the centre), unless the focal length `f` and the pitch
    `p` are known: then `f_px = s / p` with the thin lens's `s = f d / (d - f)` at the focus
    distance `d`: EXIF's, else the chart centre's distance for the first fit (the pose at
    `f_px` gives it: a fixed point) and the fitted focus distance for the fit after the
    alignment (`align`; made again where that fit's focus moves `f_px` by over
    `_tuning.CHART_REFOCUS`). Each photo's pose (`chart_pose`), the
    first photo's chart image and z-depth (`chart_scene`; off the chart: holes, left out of the
    fit with the pixels their circles reach), then `fit_lens` on the photos. The starting lens:
    EXIF's focal length, f-number and focus distance where recorded, else focus at the chart's
    median depth, f/4, and `f = 1 / (1 / s + 1 / d)` from `s = f_px p`. Only the blur scale
    (`ThinLens.blur_scale`) and the focus distance are measured from one photo; the f-number
    follows from the focal length held. The chart's depth scales with `f_px` and the blur
    cannot tell (it depends on the depths over the focus distance), so where `f_px` comes from
    the homographies the focus distance's standard error includes its relative error
    (`ChartCalibration.focal_px_stderr`). `detect_chart` aligns the chart blurred by one disc;
    with `align`, each photo's chart is aligned again with the fitted lens's render of it,
    each pixel blurred by its own circle (`align_view`: the corners to about 0.1 px), and the
    camera, the poses, the scene and the fit follow.

    **Raises:** `ChartError` (a `ValueError`, one line) when a photo does not show the chart
    usably (`detect_chart`), the chart faces the camera within 10 degrees (too little depth
    range: it says the tilt found), the photos show it in different places (not one scene), or
    the pixel pitch is unknown (give `pixel_pitch`, or `focal_length`, or a sensor width).
    """
    photos, exifs = _photos_and_exifs(photos, exif)
    shape, n = photos[0].shape, len(photos)
    found = (
        list(views) if views is not None else [detect_chart(p, chart, image=image) for p in photos]
    )
    _one_scene(found)
    f, pixel_pitch, focus = _camera(exifs[0] or ExifLens(), shape, focal_length, pixel_pitch)
    # The chart's raster holds reflectances (or a monitor's levels): the light on it, its level
    # and how it falls across the chart, is on no scale of the photo's. The exposure and the
    # illumination are fitted unless the caller says otherwise (without the illumination, a
    # ray-traced print lit from one side came back with K 62 % off, and its fit and the
    # selection's refits crawled for minutes towards that lens).
    fit_options = {"exposure": True, "illumination": True, **fit_options}
    geometry = _Geometry.of(found, f, pixel_pitch, focus)
    if pixel_pitch is None and f is None and init is None:
        raise ChartError(
            "the pixel pitch is unknown (no EXIF focal-plane resolution or 35 mm equivalent): "
            "give the sensor width or the focal length"
        )
    stage_note("building the chart's image and depth")
    sharp, depth = geometry.scene(chart, image, photos[0])
    median = float(np.nanmedian(depth))
    if init is None:
        init = [_start(e or ExifLens(), f, pixel_pitch, geometry.f_px, median) for e in exifs]
    inits = tuple(init) if isinstance(init, Sequence) else (init,) * n
    targets = photos[0] if n == 1 else np.stack(photos)
    fit = _fit_chart(sharp, depth, targets, list(inits) if n > 1 else inits[0], fit_options)
    moved: tuple[float, ...] = ()
    if align:
        found, moved, geometry, depth, fit = _aligned_fit(
            photos,
            found,
            geometry,
            chart,
            image,
            fit,
            (sharp, depth),
            (f, pixel_pitch, focus),
            fit_options,
        )
    return ChartCalibration(
        fit=_with_scale_error(fit, geometry.f_px_se / geometry.f_px),
        views=tuple(found),
        poses=tuple(geometry.poses),
        camera=geometry.camera,
        focal_px=float(geometry.f_px),
        focal_px_stderr=float(geometry.f_px_se),
        intrinsics=geometry.source,
        init=inits,
        depth_range=(float(np.nanmin(depth)), float(np.nanmax(depth))),
        aligned_px=moved,
    )


def _photos_and_exifs(photos, exif) -> tuple[list[np.ndarray], list[ExifLens | None]]:
    """`calibrate`'s photos as a list of arrays of one shape, and one EXIF entry per photo."""
    many = not (isinstance(photos, np.ndarray) and photos.ndim in (2, 3))
    photos = [np.asarray(p) for p in photos] if many else [np.asarray(photos)]
    if not photos:
        raise ValueError("calibrate needs at least one photo")
    if any(p.shape != photos[0].shape for p in photos):
        raise ValueError(f"the photos differ in shape: {[p.shape for p in photos]}")
    exifs = list(exif) if isinstance(exif, Sequence) else [exif] * len(photos)
    if len(exifs) != len(photos):
        raise ValueError(f"exif: {len(exifs)} given for {len(photos)} photos")
    return photos, exifs


@dataclasses.dataclass(frozen=True)
class _Geometry:
    """The camera and the chart's poses from the views: the focal length in pixels `f_px`
    (from `f` and the pitch, else the homographies, with its standard error `f_px_se`), the
    intrinsic matrix and each view's pose."""

    f_px: float
    f_px_se: float
    source: str
    camera: np.ndarray
    poses: list[ChartPose]

    @classmethod
    def of(cls, views: Sequence[ChartView], f, pitch, focus) -> _Geometry:
        shape = views[0].shape
        if f is not None and pitch is not None:
            f_px, source, f_px_se = _focal_px(views[0], f, pitch, focus), _GIVEN, 0.0
        else:
            f_px = focal_from_homographies([v.homography for v in views], shape)
            if f_px is None:
                raise ChartError(
                    "the chart faces the camera too squarely to give the focal length in "
                    f"pixels: tilt it by {_MIN_TILT:.0f} degrees or more, or give the focal "
                    "length and the pixel pitch"
                )
            f_px, source = refine_focal(views, f_px), "homographies"
            f_px_se = focal_stderr(views, _tuning.CHART_CORNER_PX)
        camera = camera_matrix(f_px, shape)
        poses = [chart_pose(*v.grid(), camera) for v in views]
        tilt = min(p.tilt for p in poses)
        if tilt < _MIN_TILT:
            raise ChartError(_facing(tilt))
        return cls(f_px, f_px_se, source, camera, poses)

    def scene(self, chart: Chart, image, photo: np.ndarray, k: int = 0):
        """`chart_scene` of view `k`, its image in as many channels as `photo` has."""
        sharp, depth = chart_scene(chart, image, self.poses[k], self.camera, photo.shape)
        if photo.ndim == 3:
            sharp = np.repeat(sharp[..., None], photo.shape[2], axis=-1)
        return sharp, depth


def _aligned_fit(
    photos, found, geometry: _Geometry, chart, image, fit: FitResult, first, camera, fit_options
):
    """The chart found again in each photo with its fitted blur (`_aligned`), the camera, poses
    and scene that follow, and the lens fitted again from `fit`'s, its focus distance moved
    with the chart's depth; `first`: the first photo's scene `(sharp, depth)`, which `fit` was
    fitted on. Returns `(views, moved, geometry, depth, fit)`."""
    stage_note("aligning the chart again with the fitted blur")
    sharp0, depth0 = first
    grey0 = sharp0[..., 0] if sharp0.ndim == 3 else sharp0
    median = float(np.nanmedian(depth0))
    aligned = [
        _aligned(p, v, geometry, chart, image, fit, k, (grey0, depth0) if k == 0 else None)
        for k, (p, v) in enumerate(zip(photos, found))
    ]
    found, moved = [a[0] for a in aligned], tuple(a[1] for a in aligned)
    targets = photos[0] if len(photos) == 1 else np.stack(photos)
    # One start and the first fit's choices: its starts found the basin, its photo chose the
    # treatment and the nuisances, and the chart moved by tenths of a pixel.
    options = {"starts": 1, **_as_decided(fit), **fit_options}

    def fit_at(geometry: _Geometry, start: FitResult, median: float):
        sharp, depth = geometry.scene(chart, image, photos[0])
        scale = float(np.nanmedian(depth)) / median
        lenses = [_lens_at(start, k, scale) for k in range(len(photos))]
        init = lenses if len(photos) > 1 else lenses[0]
        return depth, _fit_chart(sharp, depth, targets, init, options)

    geometry = _Geometry.of(found, *_focused(camera, _first_focus(fit), geometry.f_px))
    stage_note("building the aligned chart's image and depth; fitting again")
    depth, again = fit_at(geometry, fit, median)
    # `f_px` was taken at the first fit's focus (`_focused`); where the focus found now moves it
    # (a first fit far off), once more at the new one.
    if _at_fitted_focus(camera):
        refocused = _Geometry.of(found, *_focused(camera, _first_focus(again), geometry.f_px))
        if abs(refocused.f_px / geometry.f_px - 1) > _tuning.CHART_REFOCUS:
            stage_note("the focal length in pixels at the fitted focus; fitting again")
            median = float(np.nanmedian(depth))
            geometry = refocused
            depth, again = fit_at(geometry, again, median)
    return found, moved, _focus_share(geometry, camera, again), depth, _told_as(again, fit)


def _at_fitted_focus(camera) -> bool:
    """Whether `f_px` is taken at the fitted focus distance (`_focused`): the focal length and
    the pitch of `camera` `(f, pitch, focus)` given, its focus distance not."""
    f, pitch, focus = camera
    return f is not None and pitch is not None and focus is None


def _focus_share(geometry: _Geometry, camera, fit: FitResult) -> _Geometry:
    """`geometry` with the standard error of `f_px` that the fitted focus gives it, where `f_px`
    was taken at that focus (`_focused`: the focal length and the pitch given, not the focus):
    `f_px = 1 / ((1 / f - P) p)`, so `sigma(f_px) = f_px s sigma(P)` with `s = f_px p`."""
    if not _at_fitted_focus(camera):
        return geometry
    power_se = float(np.ravel(np.asarray(fit.focus_power_stderr))[0])
    if not math.isfinite(power_se):
        return geometry
    pitch = camera[1]
    se = geometry.f_px * (geometry.f_px * pitch) * power_se
    return dataclasses.replace(geometry, f_px_se=math.hypot(geometry.f_px_se, se))


def _aligned(photo, view, geometry: _Geometry, chart, image, fit: FitResult, k: int, scene=None):
    """`align_view` of photo `k` with the chart as `fit`'s lens for it renders it; `scene`: its
    `chart_scene` where already made (the first photo's, which the first fit used)."""
    sharp, depth = scene or chart_scene(
        chart, image, geometry.poses[k], geometry.camera, photo.shape
    )
    lens = jax.tree_util.tree_map(lambda x: x[k], fit.lenses)
    reach = _background_reach(depth, [lens])
    # The pixels whose light comes from the chart alone (no hole's reaches them), and the
    # template rendered around those compared only.
    samples = alignment_samples(usable_pixels(depth, reach))
    templates = render_template(sharp, depth, lens, samples.boxes, reach)
    at = geometry.poses[k].homography(geometry.camera)
    return align_view(photo, view, templates, at, samples)


def _first_focus(fit: FitResult) -> float:
    return float(np.ravel(np.asarray(fit.lenses.focus_distance))[0])


def _focused(camera, focus_fit: float, f_px: float):
    """`camera`'s `(f, pitch, focus)` with the focus distance `focus_fit` that the first photo's
    fit found, where the focal length and the pitch are given and the focus distance is not:
    the image distance `s = 1 / (1 / f - P)` (`P`: the focus power), hence `f_px = s / p`, is
    the lens's at its focus, not at the chart's centre. The fitted power is on the scale of the
    depth map made with `f_px`, and the depth scales with it: the fixed point of
    `P = P_fit f_px / f_px(P)`, each pass shrinking the error by about `f P`."""
    f, pitch, _ = camera
    power = 1 / focus_fit
    if not _at_fitted_focus(camera) or not 0 <= power < 0.5 / f:
        return camera
    p = power
    for _ in range(8):
        p = power * f_px * pitch * (1 / f - p)
    return f, pitch, (math.inf if p <= 0 else 1 / p)


def _as_decided(fit: FitResult) -> dict:
    """The `fit_lens` options that treat the scene and the camera as `fit` decided: the filter
    method, the footprint correction, the edge weight and each nuisance fitted or not."""
    t = fit.treatment
    if t is None:
        return {}
    # (`FitResult.nuisances`: one entry per `fit_lens` switch, the luma's included)
    nuisances = {k: bool(v.get("fitted")) for k, v in (fit.nuisances or {}).items()}
    scene = {
        "method": t.method if t.occlusion else "soft",
        "footprint": t.footprint,
        "edge_weight": t.edge_weight if t.edge_weight > 0 else False,
    }
    return {
        **(scene if t.method != "model" else {}),  # (a caller's forward model: its own)
        **nuisances,
    }


def _told_as(fit: FitResult, first: FitResult) -> FitResult:
    """`fit`, made with `first`'s choices (`_as_decided`), reporting them as `first` made them:
    the treatment's forced and selected choices, and each nuisance's entry (its score test, and
    whether the caller forced it) with `fit`'s values."""
    t, t0 = fit.treatment, first.treatment
    if t is None or t0 is None:
        return fit
    kept = ("values", "reach")
    nuisances = {
        k: {**(first.nuisances or {}).get(k, v), **{n: x for n, x in v.items() if n in kept}}
        for k, v in (fit.nuisances or {}).items()
    }
    treatment = dataclasses.replace(t, forced=t0.forced, selected=t0.selected)
    return dataclasses.replace(fit, treatment=treatment, nuisances=nuisances)


def _background_reach(depth, lenses: Sequence[ThinLens]) -> float:
    """How far (px) light from off the chart (holes in `depth`) reaches into the photo: there
    the depth is unknown, and a background behind the chart blurs at most as a point at
    infinity does, by the blur scale `K` (`ThinLens.blur_scale`, `r -> K` as `d -> inf`); the
    chart's own circles where they are larger (`r = K |1 - d_f / d|`, near the camera)."""
    near = float(np.nanmin(depth))
    # on the host: a few scalars, not eager device calls
    return float(start_circles(rows_of(lenses), np.array([near, np.inf])).max())


def _fit_chart(sharp, depth, targets, init, fit_options: dict) -> FitResult:
    """`fit_lens` on the chart's scene with the light from off the chart left out
    (`_off_chart`), its band counted in the treatment's `hole_pixels` and `hole_reach`."""
    lenses = list(init) if isinstance(init, Sequence) else [init]
    options, band, reach = _off_chart(fit_options, depth, lenses)
    fit = fit_lens(sharp, depth, targets, init, **options)
    t = fit.treatment
    if t is None:
        return fit
    wider = dataclasses.replace(
        t, hole_pixels=max(t.hole_pixels, band), hole_reach=max(t.hole_reach, reach)
    )
    return dataclasses.replace(fit, treatment=wider)


def _off_chart(fit_options: dict, depth, lenses: Sequence[ThinLens]) -> tuple[dict, int, float]:
    """`(options, band, reach)`: `fit_options` with the photo pixels within `reach` of the
    chart's outline weighted 0 (times the caller's `weight`), and how many of them are on the
    chart. `reach` is that of light from off the chart (`_background_reach`): `fit_lens` leaves
    out the pixels its circles on the chart reach from a hole, and the background's, beyond the
    chart, are larger; halved while it would leave under half the chart's pixels."""
    on = np.isfinite(depth)
    reach = _background_reach(depth, lenses)
    near = near_holes(~on, reach)
    while reach >= 1 and np.sum(on & ~near) < _KEEP * np.sum(on):
        reach /= 2
        near = near_holes(~on, reach)
    weight = (~near).astype(np.float32)
    if fit_options.get("weight") is not None:
        weight = weight * np.asarray(fit_options["weight"], np.float32)
    return {**fit_options, "weight": weight}, int(np.sum(near & on)), reach


def _lens_at(fit: FitResult, k: int, scale: float) -> ThinLens:
    """Photo `k`'s fitted lens with its focus distance scaled by `scale` (the chart's depth
    moved so): the blur, which depends on depth over focus distance, stays."""
    lens = jax.tree_util.tree_map(lambda x: float(x[k]), fit.lenses)
    return ThinLens(lens.focal_length, lens.f_number, lens.focus_distance * scale, lens.pixel_pitch)


def _camera(exif: ExifLens, shape, focal_length, pixel_pitch):
    """`(f, pitch, focus)`: the focal length and the pixel pitch, the caller's else EXIF's (the
    pitch from its sensor width), and EXIF's focus distance where it is usable (finite, beyond
    `f`); `None` where unknown."""
    h, w = shape[:2]
    f = focal_length if focal_length is not None else exif.focal_length
    if pixel_pitch is None:
        width = exif.sensor_width(w, h)
        pixel_pitch = None if width is None else width / w
    focus = exif.focus_distance
    usable = focus is not None and math.isfinite(focus) and (f is None or focus > f)
    return f, pixel_pitch, focus if usable else None


def _with_scale_error(fit: FitResult, rel: float) -> FitResult:
    """`fit` with the focus distance's standard error (and its power's) widened by a relative
    error `rel` of the chart's depth: the depth map scales with the focal length in pixels, and
    the blur, which depends on the ratio of the depths to the focus distance, cannot tell; the
    covariance stays the fit's."""
    if rel == 0 or "focus_distance" not in fit.stderr:
        return fit
    se0, power0 = jnp.asarray(fit.stderr["focus_distance"]), jnp.asarray(fit.focus_power_stderr)
    d = jnp.ravel(jnp.asarray(fit.lenses.focus_distance))
    d = (d if d.size == se0.size else d[:1]).reshape(se0.shape)  # one per photo, or shared
    se = jnp.hypot(se0, rel * d)
    power = jnp.hypot(power0, rel / d.reshape(power0.shape))
    return dataclasses.replace(
        fit, stderr={**fit.stderr, "focus_distance": se}, focus_power_stderr=power
    )


def _start(
    exif: ExifLens, f: float | None, pitch: float | None, f_px: float, median: float
) -> ThinLens:
    """The starting lens: EXIF's f-number and focus distance, else f/4 focused at the chart's
    median depth; the focal length `f`, else the thin lens's `1 / (1 / s + 1 / d)` with
    `s = f_px p`; the pitch `p`, else `s / f_px` with `s` the image distance of `f` at `d`."""
    if f is None:
        assert pitch is not None  # `calibrate` has checked
        f = 1 / (1 / (f_px * pitch) + 1 / median)
    if pitch is None:
        pitch = _pitch(f, f_px, median)
    d = exif.focus_distance
    d = d if d is not None and d > f else median
    return ThinLens(f, exif.f_number or _F_NUMBER, d, pitch)


def _facing(tilt: float) -> str:
    return (
        f"the chart faces the camera within {tilt:.1f} degrees (tilt it by {_MIN_TILT:.0f} or "
        "more about a vertical or horizontal axis, so its depth varies across the frame)"
    )


def _focal_px(view: ChartView, f: float, pitch: float, focus: float | None) -> float:
    """`s / p` with the thin lens's image distance `s = f d / (d - f)` at the focus distance `d`:
    given, else the z-depth of the chart's centre, found from the pose at `s / p`, which depends on
    it: a fixed point (`ds / s = -f / (d - f) dd / d`, so each pass shrinks the error by about
    `f / d`; starting from `s = f`, a lens focused at infinity, puts the chart about
    `f / d` too near and `s` as much too short)."""
    if focus is not None:
        return 1 / ((1 / f - 1 / focus) * pitch)  # focus may be infinite
    points, pixels = view.grid()
    f_px = f / pitch
    for _ in range(8):
        pose = chart_pose(points, pixels, camera_matrix(f_px, view.shape))
        d = max(float(pose.translation[2] + pose.rotation[2, :2] @ points.mean(0)), 2 * f)
        f_px, last = f * d / (d - f) / pitch, f_px
        if abs(f_px - last) <= 1e-9 * f_px:
            break
    return f_px


def _pitch(f: float, f_px: float, d: float) -> float:
    """The pixel pitch of a camera of focal length `f` focused at `d` with `f_px`."""
    return f * d / (d - f) / f_px


def _one_scene(views: list[ChartView]) -> None:
    """`ChartError` unless the chart is where it was in every photo (a magnification about the
    centre aside)."""
    if len(views) < 2:
        return
    ref = views[0]
    h, w = ref.shape
    centre = np.array([(w - 1) / 2, (h - 1) / 2])
    corners = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    pts = ref.grid(2)[0]
    lo, hi = pts.min(0), pts.max(0)
    outline = lo + corners * (hi - lo)

    def project(v):
        p = np.column_stack([outline, np.ones(4)]) @ v.homography.T
        return p[:, :2] / p[:, 2:] - centre

    a = project(ref)
    extent = float(np.linalg.norm(a.max(0) - a.min(0)))
    for k, v in enumerate(views[1:], start=1):
        b = project(v)
        scale = float(np.sum(a * b) / np.sum(a * a))
        off = float(np.abs(b - scale * a).max())
        if off > _SAME_PX + _SAME_SHARE * extent:
            raise ChartError(
                f"photo {k + 1} shows the chart {off:.0f} px from where photo 1 does: the photos "
                "must be of one scene (a focus bracket from a tripod); calibrate each on its own"
            )
