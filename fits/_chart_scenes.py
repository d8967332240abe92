"""Ray-traced photos of a printed chart and of a chart on a monitor for `chart.py` (issue 35):
Mitsuba 3 as an independent ray tracer of the chart that `jaxdof.make_chart` draws.

- `CASES`: eight poses and lenses (tilt, distance, field of view, aperture, focus in front of,
  behind and across the chart; printed or on a monitor), and the held-out half (`HELD_OUT`),
  chosen before any fit was run.
- `render_case`: the photo (linear float32 RGB), rendered by Mitsuba's `thinlens` camera; a
  printed chart is a diffuse rectangle lit unevenly (a point light off to one side and a dim
  constant environment) before a textured wall, a monitor is an area emitter in the dark.
- `case_photo`: the photo, its 8-bit camera JPEG (`_captures_scenes.camera_jpeg`: sRGB, quality
  90, 4:2:0, read back to linear), the truth lens (`true_lens`, `lens_from_raytracer` with the
  focal length of a 36 mm wide sensor), the truth pose (`chart_pose`) and the z-depth from
  Mitsuba's depth AOV (`ray_distance_to_z`), checked against the pose (`depth_check`).
- `no_chart_photo`: the printed chart's room without the chart (calibrate must refuse it).
- `pinhole_photo`: a case rendered with a pinhole (the sharp truth, for diagnosis).

Renders are cached in `fits/.cache/chart/`, keyed by the case and a hash of the chart raster (a
changed `make_chart` renders again). Mitsuba is imported only when something has to be rendered.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math

import jax


jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from _captures_scenes import camera_jpeg  # noqa: E402
from _common import CACHE as _CACHE_ROOT, cached_npz  # noqa: E402
from _raytraced_scenes import mitsuba, texture  # noqa: E402

import jaxdof  # noqa: E402
from jaxdof import lens_from_raytracer, ray_distance_to_z  # noqa: E402


CACHE = _CACHE_ROOT / "chart"
W, H = 640, 480  # film size (px)
NEAR_CLIP = 0.01  # Mitsuba's default, passed so that the depth conversion can use it
SPP = 384  # samples per pixel of a photo (the chart's texels average over ~100-400 per pixel)
SENSOR_WIDTH = 0.036  # m: the focal length given as EXIF is a full-frame camera's, f = f_px p
EXPOSURE_PEAK = 0.9  # the photo is scaled so that its 99.5th percentile is this (linear)
PRINT_SIZE = (0.297, 0.210)  # A4 landscape (m)
DPI = 300  # the printed chart's raster


@dataclasses.dataclass(frozen=True)
class Case:
    """One photo: the chart at `distance` m straight ahead (its centre), turned `rot_y` degrees
    about the vertical axis and then `rot_x` about the horizontal one, seen by a thin lens of
    aperture radius `aperture` m focused at `focus` m (a z-distance) with a horizontal field of
    view `fov` degrees. Printed on A4 at `DPI`, or (`screen`: width px, height px, width m)
    shown on a monitor."""

    name: str
    distance: float
    rot_y: float
    rot_x: float
    fov: float
    aperture: float
    focus: float
    where: str  # the focus against the chart, in words
    screen: tuple[int, int, float] | None = None

    @property
    def monitor(self) -> bool:
        return self.screen is not None

    @property
    def size(self) -> tuple[float, float]:
        """The chart's size (m) as `make_chart` rounds it: whole raster pixels."""
        if self.screen is not None:
            nx, ny, width = self.screen
            return width, width / nx * ny
        pitch = 0.0254 / DPI
        return tuple(round(v / pitch) * pitch for v in PRINT_SIZE)  # type: ignore[return-value]


# Circles of confusion over the chart (px, A f_px |1/d_f - 1/z| at its nearest and farthest
# pixel) are in `coc_range`; the designs aim at about 1-15 px. Screens: 24" (1920x1080), 15.6"
# (1920x1080) and 27" (2560x1440), 16:9.
CASES = (
    Case("print_front", 0.8, 35.0, 0.0, 40.0, 0.012, 0.6, "in front"),
    Case("print_behind", 1.0, -30.0, 15.0, 40.0, 0.015, 1.6, "behind"),
    Case("print_steep", 0.5, 60.0, 0.0, 50.0, 0.008, 0.55, "across"),
    Case("monitor_front", 1.2, 40.0, 0.0, 30.0, 0.015, 0.9, "in front", (1920, 1080, 0.527)),
    Case("print_cross", 0.6, 55.0, 0.0, 40.0, 0.015, 0.6, "across"),
    Case("print_far", 2.5, 45.0, 0.0, 12.0, 0.03, 2.0, "in front"),
    Case("monitor_cross", 0.7, 25.0, 30.0, 40.0, 0.02, 0.7, "across", (1920, 1080, 0.344)),
    Case("monitor_far", 2.8, -35.0, -10.0, 20.0, 0.03, 3.5, "behind", (2560, 1440, 0.597)),
)
CASE = {c.name: c for c in CASES}
# The held-out half, chosen with the cases and before any fit: never used to tune anything in
# jaxdof (its chart detector, starts, tolerances); report it apart. Each half has a focus in
# front of, behind and across the chart, and a monitor.
HELD_OUT = ("print_cross", "print_far", "monitor_cross", "monitor_far")
TUNING = tuple(c.name for c in CASES if c.name not in HELD_OUT)


def f_px(case: Case) -> float:
    """The focal length in pixels of the case's field of view."""
    return (W / 2) / math.tan(math.radians(case.fov) / 2)


def focal_length(case: Case) -> float:
    """The focal length (m) an EXIF block would give: a `SENSOR_WIDTH` wide sensor imaged to
    `W` px, `f = f_px SENSOR_WIDTH / W` (the pitch of the equivalent lens is then
    `SENSOR_WIDTH / W` up to the factor `s / f = d_f / (d_f - f)`)."""
    return f_px(case) * SENSOR_WIDTH / W


def true_lens(case: Case) -> jaxdof.ThinLens:
    """The `ThinLens` that blurs as the case's Mitsuba thin lens (`lens_from_raytracer`)."""
    return lens_from_raytracer(
        case.aperture,
        case.focus,
        fov_x_deg=case.fov,
        image_width=W,
        focal_length=focal_length(case),
    )


# ----------------------------------------------------------------------------- the chart


def chart_and_image(case: Case):
    """`(chart, image)`: `jaxdof.make_chart` for the case (A4 printed, or the monitor's
    screen), cached in memory (a 300 dpi dead-leaves raster takes seconds)."""
    if case.screen not in _CHARTS:
        if case.screen is None:
            out = jaxdof.make_chart(width_m=PRINT_SIZE[0], height_m=PRINT_SIZE[1], dpi=DPI)
        else:
            nx, ny, width = case.screen
            out = jaxdof.make_chart(monitor=True, screen_px=(nx, ny), screen_width_m=width)
        chart = out[0]
        if max(abs(chart.width_m - case.size[0]), abs(chart.height_m - case.size[1])) > 1e-9:
            raise ValueError(
                f"{case.name}: chart {chart.width_m} x {chart.height_m} m, case {case.size}"
            )
        _CHARTS[case.screen] = out
    return _CHARTS[case.screen]


_CHARTS: dict = {}


def raster_hash(image) -> str:
    return hashlib.sha256(np.ascontiguousarray(image, np.float32).tobytes()).hexdigest()[:10]


# ----------------------------------------------------------------------------- geometry


def _chart_to_world(mi, case: Case):
    """The rectangle's `to_world`: local `[-1, 1]^2` scaled to the chart's half-sizes, turned to
    face the camera (Mitsuba's camera looks along +z with +x to the image's left and +y up),
    then by `rot_x` and `rot_y`, then moved to `(0, 0, distance)`."""
    T = mi.ScalarTransform4f
    w, h = case.size
    return (
        T()
        .translate([0.0, 0.0, case.distance])
        .rotate([0, 1, 0], case.rot_y)
        .rotate([1, 0, 0], case.rot_x)
        .rotate([0, 1, 0], 180.0)
        .scale([w / 2, h / 2, 1.0])
    )


def chart_pose(case: Case) -> tuple[np.ndarray, np.ndarray]:
    """`(R, t)`: the chart's pose in the camera frame x right, y down, z forward (metres), so
    that the chart point `(x, y)` (chart coordinates: x right, y down from its top left corner)
    is at `R @ [x, y, 0] + t`. Computed without Mitsuba (the same rotations as
    `_chart_to_world`), and checked against it by `depth_check`."""
    w, h = case.size

    def rot(axis, deg):
        c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
        if axis == "y":
            return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])

    # The chart's raster is given to Mitsuba upside down (`np.flipud`) so that its row 0 is at
    # local y = +1 (the top): local (2x/w - 1, 1 - 2y/h); the 180 deg turn about y makes that
    # world (w/2 - x, h/2 - y), i.e. camera (x - w/2, y - h/2) before the pose's rotations.
    flip = np.diag([-1.0, -1.0, 1.0])  # Mitsuba world (x left, y up) <-> camera (x right, y down)
    r_world = rot("y", case.rot_y) @ rot("x", case.rot_x)
    r = flip @ r_world @ flip
    t = r @ np.array([-w / 2, -h / 2, 0.0]) + np.array([0.0, 0.0, case.distance])
    return r, t


def chart_corners_px(case: Case) -> np.ndarray:
    """`(4, 2)` the chart's corners in the photo (column, row; pixel centres at half-integers),
    top left, top right, bottom right, bottom left."""
    r, t = chart_pose(case)
    w, h = case.size
    pts = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], float) @ r.T + t
    fp = f_px(case)
    return np.stack([W / 2 + fp * pts[:, 0] / pts[:, 2], H / 2 + fp * pts[:, 1] / pts[:, 2]], -1)


def chart_z(case: Case) -> np.ndarray:
    """`(H, W)` the z-depth of the chart at every pixel centre whose ray hits it (NaN elsewhere),
    from the pose alone: the ray `(x_n, y_n, 1)` meets the chart's plane at `z = n.t / n.(x_n,
    y_n, 1)`."""
    r, t = chart_pose(case)
    w, h = case.size
    fp = f_px(case)
    xn = (np.arange(W) + 0.5 - W / 2) / fp
    yn = (np.arange(H) + 0.5 - H / 2) / fp
    ray = np.stack(np.broadcast_arrays(xn[None, :], yn[:, None], 1.0), -1)
    n = r[:, 2]
    z = (n @ t) / (ray @ n)
    p = ray * z[..., None] - t  # the hit, relative to the chart's corner, in chart axes
    cx, cy = p @ r[:, 0], p @ r[:, 1]
    inside = (cx >= 0) & (cx <= w) & (cy >= 0) & (cy <= h) & (z > 0)
    return np.where(inside, z, np.nan)


def coc_range(case: Case) -> tuple[float, float]:
    """The smallest and largest circle of confusion over the chart (px): `A f_px |1/d_f - 1/z|`
    over its pixels (0 where the focus plane crosses it)."""
    z = chart_z(case)
    r = case.aperture * f_px(case) * np.abs(1 / case.focus - 1 / z[np.isfinite(z)])
    return float(r.min()), float(r.max())


# ----------------------------------------------------------------------------- Mitsuba scenes


def _sensor(mi, case: Case, kind: str, spp: int) -> dict:
    """Mitsuba's camera at the origin looking along +z, the case's field of view, a box filter
    (each pixel the average over its square); the depth pass takes one unjittered sample at the
    pixel centre (as `_raytraced_scenes._sensor`)."""
    depth_pass = kind == "depth"
    sensor = {
        "type": "perspective" if depth_pass else kind,
        "fov": case.fov,
        "fov_axis": "x",
        "near_clip": NEAR_CLIP,
        "to_world": mi.ScalarTransform4f().look_at(
            origin=[0, 0, 0], target=[0, 0, 1], up=[0, 1, 0]
        ),
        "film": {
            "type": "hdrfilm",
            "width": W,
            "height": H,
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
            "sample_border": False,
        },
        "sampler": {"type": "stratified", "sample_count": 1, "jitter": False}
        if depth_pass
        else {"type": "independent", "sample_count": spp},
    }
    if kind == "thinlens":
        sensor.update(aperture_radius=case.aperture, focus_distance=case.focus)
    return sensor


def _bitmap(mi, image) -> dict:
    """The chart's raster as a linear (`raw`) bilinear bitmap texture, upside down (Mitsuba's
    rectangle puts the raster's row 0 at local y = -1)."""
    data = np.ascontiguousarray(np.flipud(np.asarray(image, np.float32)))
    return {"type": "bitmap", "bitmap": mi.Bitmap(data), "raw": True, "filter_type": "bilinear"}


def light_position(case: Case) -> np.ndarray:
    """The printed chart's point light (Mitsuba world coordinates: x to the image's left, y up):
    0.9 m from the chart's centre, in front of it (along its normal), above it and to its left
    as the camera sees it: the light falls off by about a factor two across the chart."""
    mi = mitsuba()
    to_world = _chart_to_world(mi, case)
    n = np.array(to_world @ mi.ScalarNormal3f(0, 0, 1), np.float64)
    n /= np.linalg.norm(n)
    up = np.array([0.0, 1.0, 0.0])
    side = np.array([1.0, 0.0, 0.0])
    side -= (side @ n) * n
    d = 0.9 * n + 0.6 * up + 0.5 * side / np.linalg.norm(side)
    return np.array([0.0, 0.0, case.distance]) + 0.9 * d / np.linalg.norm(d)


def _room(mi, case: Case) -> dict:
    """The printed chart's surroundings: a wall 0.6 m behind the chart, diffuse with a muted
    texture (reflectance 0.2-0.45, repeating every 1.2 m), a warm point light
    (`light_position`), and a dim constant environment."""
    T = mi.ScalarTransform4f
    z_wall = case.distance + 0.6
    half = z_wall * math.tan(math.radians(case.fov) / 2) * 1.6 + 0.3
    tex = texture(7)
    wall_tex = (0.2 + 0.25 * (0.6 * tex.mean(-1, keepdims=True) + 0.4 * tex)).astype(np.float32)
    return {
        "wall": {
            "type": "rectangle",
            "to_world": T()
            .translate([0, 0, z_wall])
            .rotate([0, 1, 0], 180.0)
            .scale([half, half, 1]),
            "bsdf": {
                "type": "diffuse",
                "reflectance": {
                    "type": "bitmap",
                    "bitmap": mi.Bitmap(wall_tex),
                    "raw": True,
                    "to_uv": mi.ScalarTransform3f().scale([2 * half / 1.2, 2 * half / 1.2]),
                },
            },
        },
        "light": {
            "type": "point",
            "position": light_position(case).tolist(),
            "intensity": {"type": "rgb", "value": [1.0, 0.9, 0.75]},
        },
        "ambient": {"type": "constant", "radiance": {"type": "rgb", "value": 0.04}},
    }


def scene_dict(mi, case: Case, image, kind: str, spp: int, chart: bool = True) -> dict:
    """The Mitsuba scene of a case: its camera (`kind`: thinlens, perspective or depth), the
    chart (unless `chart=False`) and, for a printed chart, its room."""
    scene = {
        "type": "scene",
        "integrator": {"type": "aov", "aovs": "dd.y:depth"}
        if kind == "depth"
        else {"type": "path", "max_depth": 2 if case.monitor else 3},
        "sensor": _sensor(mi, case, kind, spp),
    }
    if not case.monitor:
        scene.update(_room(mi, case))
    if chart:
        rect = {"type": "rectangle", "to_world": _chart_to_world(mi, case)}
        if case.monitor:
            rect["bsdf"] = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}}
            rect["emitter"] = {"type": "area", "radiance": _bitmap(mi, image)}
        else:
            rect["bsdf"] = {"type": "diffuse", "reflectance": _bitmap(mi, image)}
        scene["chart"] = rect
    return scene


def render_case(case: Case, image, kind: str = "thinlens", spp: int = SPP, chart=True, seed=0):
    """One Mitsuba render of a case (linear RGB float32; for `kind="depth"` the ray distance,
    `inf` where nothing is hit)."""
    mi = mitsuba()
    scene = mi.load_dict(scene_dict(mi, case, image, kind, spp, chart))
    img = np.array(mi.render(scene, seed=seed), dtype=np.float32)
    if kind == "depth":
        img = img[..., 0]
        img[img <= 0] = np.inf
    return img


def _key(case: Case, image, what: str) -> str:
    return f"{case.name}_{what}_{raster_hash(image)}"


def exposure(photo) -> float:
    """The factor that brings the photo's 99.5th percentile to `EXPOSURE_PEAK`."""
    return EXPOSURE_PEAK / float(np.quantile(photo, 0.995))


# ----------------------------------------------------------------------------- the cases' data


@dataclasses.dataclass
class CaseData:
    """A case's renders and truth."""

    case: Case
    chart: object  # jaxdof's Chart
    image: np.ndarray  # the chart's raster (reflectance or the monitor's radiance)
    photo: np.ndarray  # linear RGB float32, exposed (`exposure`)
    jpeg: np.ndarray  # the photo through `camera_jpeg`, linear RGB float32
    jpeg_path: object  # its file
    lens: jaxdof.ThinLens
    pose: tuple[np.ndarray, np.ndarray]  # (R, t), `chart_pose`
    z: np.ndarray  # (H, W) z-depth, Mitsuba's depth AOV through `ray_distance_to_z`
    render_seconds: float
    clipped: float  # share of the photo's values above 1 (clipped in the JPEG)


def case_photo(case: Case) -> CaseData:
    """Render (or load from the cache) a case's photo and depth; make its JPEG."""
    chart, image = chart_and_image(case)
    raw, secs = cached_npz(
        CACHE / f"{_key(case, image, 'thin')}.npz",
        lambda: render_case(case, image),
        verb="rendered",
    )
    dist, secs_d = cached_npz(
        CACHE / f"{_key(case, image, 'depth')}.npz",
        lambda: render_case(case, image, "depth"),
        verb="rendered",
    )
    photo = (raw * exposure(raw)).astype(np.float32)
    path = CACHE / "jpeg" / f"{_key(case, image, 'thin')}.jpg"
    jpeg, clipped = camera_jpeg(photo, path)
    z = np.asarray(ray_distance_to_z(dist, fov_x_deg=case.fov, near_clip=NEAR_CLIP))
    return CaseData(
        case=case,
        chart=chart,
        image=np.asarray(image, np.float32),
        photo=photo,
        jpeg=np.asarray(jpeg, np.float32),
        jpeg_path=path,
        lens=true_lens(case),
        pose=chart_pose(case),
        z=z,
        render_seconds=secs + secs_d,
        clipped=clipped,
    )


def pinhole_photo(case: Case, spp: int = 128) -> np.ndarray:
    """The case seen through a pinhole (every depth sharp), exposed as its photo is."""
    _, image = chart_and_image(case)
    raw, _ = cached_npz(
        CACHE / f"{_key(case, image, 'thin')}.npz", lambda: render_case(case, image)
    )
    pin, _ = cached_npz(
        CACHE / f"{_key(case, image, f'pinhole{spp}')}.npz",
        lambda: render_case(case, image, "perspective", spp),
        verb="rendered",
    )
    return (pin * exposure(raw)).astype(np.float32)


NO_CHART = CASE["print_front"]  # the room of this case, its lens, without the chart


def no_chart_photo():
    """`(photo, jpeg path)`: `NO_CHART`'s room and lens without the chart (exposed on its own)."""
    raw, _ = cached_npz(
        CACHE / "no_chart_thin.npz",
        lambda: render_case(NO_CHART, None, chart=False),
        verb="rendered",
    )
    photo = (raw * exposure(raw)).astype(np.float32)
    path = CACHE / "jpeg" / "no_chart.jpg"
    camera_jpeg(photo, path)
    return photo, path


def depth_check(data: CaseData) -> dict:
    """Mitsuba's z-depth against the pose's (`chart_z`) on the chart's pixels away from its
    outline (2 px): the largest relative difference, and the share of pixels the two call chart
    that disagree (a wrong pose or raster orientation shows here)."""
    from scipy.ndimage import binary_erosion

    zc = chart_z(data.case)
    on = np.isfinite(zc)
    inner = binary_erosion(on, iterations=2)
    rel = np.abs(data.z[inner] / zc[inner] - 1)
    # the chart's pixels by Mitsuba: the wall is at distance + 0.6 m, the chart nearer than
    # distance + 0.5 m; the monitor's room is empty
    seen = np.isfinite(data.z) & (data.z < data.case.distance + 0.5)
    return dict(max_rel_z=float(rel.max()), chart_px=int(on.sum()), off=int((seen != on).sum()))
