"""The calibration chart: its design and files, finding it in a photo, its plane in the camera,
its scene (image and depth), and `calibrate` end to end, on small synthetic photos: the chart
warped by a known pose and blurred by `jaxdof.render`."""

import dataclasses
import math

import numpy as np
import pytest
from scipy import ndimage

import jaxdof
from jaxdof._chart._geometry import (
    _footprint,
    _halve,
    camera_matrix,
    chart_pose,
    focal_from_homographies,
)


SHAPE = (240, 320)
F_PX = 380.0  # the camera's focal length in pixels (lens-to-sensor distance / pitch)
FOCAL = 0.025  # m


def _rotation(ax: float, ay: float) -> np.ndarray:
    """A tilt of `ax` degrees about the camera's x axis, then `ay` about its y axis."""
    a, b = math.radians(ax), math.radians(ay)
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    return ry @ rx


def _pose(chart, ax, ay, distance) -> jaxdof.ChartPose:
    """The chart's centre on the optical axis at `distance` (m), tilted by `ax`, `ay` degrees."""
    r = _rotation(ax, ay)
    centre = np.array([chart.width_m / 2, chart.height_m / 2, 0])
    return jaxdof.ChartPose(r, np.array([0, 0, distance]) - r @ centre)


def _lens(f_number, focus):
    """A thin lens whose image distance at `focus` is `F_PX` pixels."""
    s = FOCAL * focus / (focus - FOCAL)
    return jaxdof.ThinLens(FOCAL, f_number, focus, s / F_PX)


def _photo(scene, lens, noise=0.0, seed=0):
    sharp, depth = scene
    filled = jaxdof.fill_depth_holes(depth).astype(np.float32)
    photo = np.asarray(jaxdof.render(sharp, filled, lens))
    if noise:
        photo = photo + np.random.default_rng(seed).normal(0, noise, photo.shape)
    return photo.astype(np.float32)


@pytest.fixture(scope="module")
def chart():
    return jaxdof.make_chart(dpi=40, seed=1, marker_fraction=0.2)


@pytest.fixture(scope="module")
def tilted(chart):
    """The chart tilted by about 38 degrees, 0.45 m away: pose, camera, scene."""
    pose = _pose(chart[0], 15, 35, 0.45)
    camera = camera_matrix(F_PX, SHAPE)
    return pose, camera, jaxdof.chart_scene(*chart, pose, camera, SHAPE)


# ----------------------------------------------------------------------------------------------
# Design and files


def test_design_is_deterministic(chart):
    c, raster = chart
    c2, raster2 = jaxdof.make_chart(dpi=40, seed=1, marker_fraction=0.2)
    assert np.array_equal(raster, raster2) and raster.dtype == np.float32
    assert sorted(c.markers) == sorted(c2.markers)
    other, raster3 = jaxdof.make_chart(dpi=40, seed=2, marker_fraction=0.2)
    assert not np.array_equal(raster, raster3)
    assert set(other.markers) != set(c.markers)  # the ids tell the charts apart
    # reflectances clear of black crush and clipping
    assert 0.049 < raster.min() and raster.max() < 0.951
    assert raster.shape == (c.texture_px[1], c.texture_px[0])
    assert c.width_m == pytest.approx(0.297, abs=1e-3) and c.height_m == pytest.approx(
        0.21, abs=1e-3
    )
    for corners in c.markers.values():  # OpenCV's order: clockwise from the top-left
        assert corners.shape == (4, 2)
        assert corners[1, 0] > corners[0, 0] and corners[2, 1] > corners[1, 1]
        assert np.all(corners >= 0) and np.all(corners[:, 0] <= c.width_m)


def test_texture_has_energy_at_every_scale(chart):
    """The dead-leaves texture's power spectrum falls as a power law, without holes: the power
    in each octave of frequency is within a factor 100 of a 1/f^2 fit's."""
    _, raster = chart
    h, w = raster.shape
    crop = raster[h // 4 : 3 * h // 4, w // 4 : 3 * w // 4]
    spec = np.abs(np.fft.fft2(crop - crop.mean())) ** 2
    fy, fx = np.meshgrid(
        np.fft.fftfreq(crop.shape[0]), np.fft.fftfreq(crop.shape[1]), indexing="ij"
    )
    f = np.hypot(fx, fy)
    bands = [(2.0**-k / 2, 2.0 ** -(k - 1) / 2) for k in range(1, 6)]
    power = np.array([spec[(f >= a) & (f < b)].mean() for a, b in bands])
    centre = np.array([math.sqrt(a * b) for a, b in bands])
    slope = np.polyfit(np.log(centre), np.log(power), 1)[0]
    assert -3.5 < slope < -1.5
    assert np.all(power > 0)


def test_files_round_trip(chart, tmp_path):
    c, raster = chart
    paths = jaxdof.write_chart(tmp_path / "c", c, raster)
    assert [p.name for p in paths] == ["c.png", "c.pdf", "c.json"]
    c2, raster2 = jaxdof.read_chart(tmp_path / "c.json")
    assert np.array_equal(raster, raster2)
    assert c2.markers.keys() == c.markers.keys()
    assert all(np.allclose(c2.markers[i], c.markers[i]) for i in c.markers)
    assert np.allclose(c2.frame, c.frame) and c2.frame_width_m == c.frame_width_m
    # the raster drawn again from the sidecar's parameters alone (for `detect_chart` without it)
    from jaxdof._chart._design import raster_of

    assert np.array_equal(raster_of(dataclasses.replace(c2)), raster)
    assert (c2.width_m, c2.texture_px, c2.seed, c2.dictionary) == (
        c.width_m,
        c.texture_px,
        c.seed,
        c.dictionary,
    )
    with pytest.raises(ValueError, match="exists; pass overwrite=True"):
        jaxdof.write_chart(tmp_path / "c", c, raster)
    jaxdof.write_chart(tmp_path / "c", c, raster, overwrite=True)
    # another PNG under the sidecar's name
    other = jaxdof.make_chart(dpi=40, seed=5, marker_fraction=0.2)
    jaxdof.write_chart(tmp_path / "d", *other)
    (tmp_path / "c.png").write_bytes((tmp_path / "d.png").read_bytes())
    with pytest.raises(ValueError, match=r"c\.png: its SHA-256 differs"):
        jaxdof.read_chart(tmp_path / "c.json")
    (tmp_path / "x.json").write_text("{}")
    with pytest.raises(ValueError, match="not a jaxdof chart sidecar"):
        jaxdof.read_chart(tmp_path / "x.json")


def test_monitor_chart(tmp_path):
    c, raster = jaxdof.make_chart(monitor=True, screen_px=(320, 200), screen_width_m=0.3, seed=4)
    from jaxdof._chart._design import raster_of

    assert np.array_equal(raster_of(dataclasses.replace(c)), raster)
    assert c.monitor and c.texture_px == (320, 200) and raster.shape == (200, 320)
    assert c.width_m == pytest.approx(0.3) and c.height_m == pytest.approx(0.3 * 200 / 320)
    paths = jaxdof.write_chart(tmp_path / "m", c, raster)
    assert [p.name for p in paths] == ["m.png", "m.json"]  # no PDF: shown from the PNG
    with pytest.raises(ValueError, match="screen_px"):
        jaxdof.make_chart(monitor=True)


# ----------------------------------------------------------------------------------------------
# Geometry


def test_intrinsics_and_pose_from_exact_points(chart, tilted):
    """The focal length and the pose from the exact projections of the marker corners."""
    c, _ = chart
    pose, camera, _ = tilted
    g = pose.homography(camera)
    assert focal_from_homographies([g], SHAPE) == pytest.approx(F_PX, rel=1e-9)
    points = c.marker_points(sorted(c.markers)).reshape(-1, 2)
    pix = np.column_stack([points, np.ones(len(points))]) @ g.T
    pix = pix[:, :2] / pix[:, 2:]
    from jaxdof._chart._geometry import chart_pose

    found = chart_pose(points, pix, camera)
    assert np.allclose(found.rotation, pose.rotation, atol=1e-7)
    assert np.allclose(found.translation, pose.translation, atol=1e-7)
    assert found.tilt == pytest.approx(pose.tilt) and 30 < pose.tilt < 45
    # facing the camera: no focal length from the homography
    facing = _pose(c, 0, 0, 0.45)
    assert focal_from_homographies([facing.homography(camera)], SHAPE) is None


def test_focal_stderr_matches_the_scatter_of_noisy_corners(chart, tilted):
    """`focal_stderr`: the focal length's standard error from corners off by 0.5 px is the
    scatter of `focal_from_homographies` over 400 such outlines, to 15 % (the draw's own error
    is 3.5 %)."""
    import cv2

    from jaxdof._chart._geometry import focal_stderr

    c, _ = chart
    pose, camera, _ = tilted
    g = pose.homography(camera)
    w, h = c.width_m, c.height_m
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], float)
    pix = np.column_stack([corners, np.ones(4)]) @ g.T
    pix = pix[:, :2] / pix[:, 2:]
    view = jaxdof.ChartView(
        ids=np.zeros(0, int),
        corners=np.zeros((0, 4, 2)),
        points=np.zeros((0, 4, 2)),
        homography=g,
        error=0.0,
        inliers=4,
        shape=SHAPE,
        cover=0.5,
        size_m=(w, h),
    )
    se = focal_stderr([view], 0.5)
    rng = np.random.default_rng(0)
    draws = []
    for _ in range(400):
        noisy = (pix + rng.normal(0, 0.5, pix.shape)).astype(np.float32)
        hom = cv2.getPerspectiveTransform(corners.astype(np.float32), noisy).astype(np.float64)
        draws.append(focal_from_homographies([hom], SHAPE))
    assert 0 < se < 0.2 * F_PX
    assert float(np.std(draws)) == pytest.approx(se, rel=0.15)


def test_depth_is_the_plane(chart, tilted):
    """Every depth on the chart is the z of the chart's point seen there; off it, NaN."""
    c, _ = chart
    pose, camera, (_, depth) = tilted
    on = ~np.isnan(depth)
    assert 0.2 < on.mean() < 0.9
    rows, cols = np.nonzero(on)
    g_inv = np.linalg.inv(pose.homography(camera))
    p = np.stack([cols, rows, np.ones_like(cols)]).astype(float)
    q = g_inv @ p
    x, y = q[0] / q[2], q[1] / q[2]
    assert np.all((x > 0) & (x < c.width_m) & (y > 0) & (y < c.height_m))
    xyz = pose.rotation @ np.stack([x, y, np.zeros_like(x)]) + pose.translation[:, None]
    assert np.allclose(depth[on], xyz[2], rtol=1e-6)
    # a pixel off the chart: its centre maps outside
    rows, cols = np.nonzero(~on)
    q = g_inv @ np.stack([cols, rows, np.ones_like(cols)]).astype(float)
    x, y = q[0] / q[2], q[1] / q[2]
    inside = (x > 0.01) & (x < c.width_m - 0.01) & (y > 0.01) & (y < c.height_m - 0.01)
    assert not np.any(inside)


def test_scene_is_the_footprint(chart, tilted):
    """The chart's image is each pixel's mean of the raster: against 16 x 16 bilinear samples
    of the raster itself, per pixel."""
    c, raster = chart
    pose, camera, (sharp, depth) = tilted
    g_inv = np.linalg.inv(pose.homography(camera))
    u = np.arange(SHAPE[1], dtype=float)
    v = np.arange(100, 140, dtype=float)
    ref = _footprint(raster, 0, g_inv, u, v, 16, *c.pitch)
    on = ~np.isnan(depth[100:140])
    diff = np.abs(sharp[100:140] - ref)[on]
    # the raster's texels are 0.76 photo pixels here: mip level 0, 2 x 2 samples
    assert diff.mean() < 0.01 and diff.max() < 0.08


def test_footprint_samples_as_map_coordinates(chart, tilted):
    """`_footprint`'s bilinear samples are `scipy.ndimage.map_coordinates`' (order 1, mode
    "nearest"), at a mip level and with the raster's edge in reach."""
    c, raster = chart
    pose, camera, _ = tilted
    g_inv = np.linalg.inv(pose.homography(camera))
    u, v, s = np.arange(SHAPE[1], dtype=float), np.arange(0, 240, 7, dtype=float), 3
    level = _halve(raster)
    got = _footprint(level, 1, g_inv, u, v, s, *c.pitch)
    offsets = (np.arange(s) + 0.5) / s - 0.5
    uu, vv = np.meshgrid((u[None] + offsets[:, None]).ravel(), (v[None] + offsets[:, None]).ravel())
    q = g_inv @ np.stack([uu.ravel(), vv.ravel(), np.ones(uu.size)])
    col, row = q[0] / q[2] / c.pitch[0] / 2 - 0.5, q[1] / q[2] / c.pitch[1] / 2 - 0.5
    assert col.min() < 0 < level.shape[1] < col.max()  # beyond the raster on both sides
    samples = ndimage.map_coordinates(level.astype(np.float64), [row, col], order=1, mode="nearest")
    ref = samples.reshape(s, v.size, s, u.size).mean(axis=(0, 2))
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6)


def test_scene_minified(chart):
    """A chart far away (many raster pixels per photo pixel): the mip level's footprint agrees
    with fine sampling of the raster."""
    c, raster = chart
    pose = _pose(c, 10, 40, 2.0)  # texels about 0.17 photo pixels
    camera = camera_matrix(F_PX, SHAPE)
    sharp, depth = jaxdof.chart_scene(c, raster, pose, camera, SHAPE)
    g_inv = np.linalg.inv(pose.homography(camera))
    v = np.arange(110, 130, dtype=float)
    ref = _footprint(raster, 0, g_inv, np.arange(SHAPE[1], dtype=float), v, 16, *c.pitch)
    on = ~np.isnan(depth[110:130])
    diff = np.abs(sharp[110:130] - ref)[on]
    assert on.sum() > 200 and diff.mean() < 0.02


# ----------------------------------------------------------------------------------------------
# Detection


def _outline_error(view, truth, points) -> float:
    """The largest distance (px) between the view's and the truth's images of `points` (m)."""

    def project(h):
        p = np.column_stack([points, np.ones(len(points))]) @ h.T
        return p[:, :2] / p[:, 2:]

    return float(np.abs(project(view.homography) - project(truth)).max())


def test_design_has_a_frame(chart):
    """A dark band around the markers and the texture, a white zone outside it."""
    c, raster = chart
    band = round(c.frame_width_m / c.pitch[0])
    (x0, y0), (x1, y1) = np.round(c.frame[[0, 2]] / c.pitch).astype(int)
    assert band >= 0.08 * min(raster.shape)
    assert np.all(raster[y0 : y0 + band, x0:x1] < 0.06)  # the band: black
    assert np.all(raster[y0 + 2 : y1 - 2, x0 : x0 + band] < 0.06)
    assert np.all(raster[:y0, :] > 0.94) and np.all(raster[:, x1:] > 0.94)  # white outside
    for corners in c.markers.values():  # the markers inside the band
        assert np.all(corners >= c.frame[0] + c.frame_width_m)
        assert np.all(corners <= c.frame[2] - c.frame_width_m)


# Defocused photos: 480 x 360 pixels, the chart about 300 px wide, seen through a camera of
# focal length 570 px, blurred by a uniform disc (a thin lens's circle of confusion).
WIDE = (360, 480)
F_WIDE = 570.0


def _disc(diameter):
    r = diameter / 2
    n = int(math.ceil(r)) + 1
    off = (np.arange(8) + 0.5) / 8 - 0.5
    y, x = np.mgrid[-n : n + 1, -n : n + 1].astype(float)
    k = ((x[..., None, None] + off[:, None]) ** 2 + (y[..., None, None] + off) ** 2 <= r * r).mean(
        axis=(-1, -2)
    )
    return (k / k.sum()).astype(np.float32)


def _defocused(c, raster, pose, coc, seed=0):
    """An 8-bit sRGB photo of the chart at `pose` before a mottled wall, lit unevenly (a gain
    from 0.6 to 1.3 across), blurred by a disc of `coc` px, with noise; and the true
    homography."""
    import cv2

    camera = camera_matrix(F_WIDE, WIDE)
    sharp, depth = jaxdof.chart_scene(c, raster, pose, camera, WIDE)
    rng = np.random.default_rng(seed)
    wall = cv2.GaussianBlur(rng.uniform(0, 1, WIDE).astype(np.float32), (0, 0), 6)
    wall = 0.05 + 0.5 * (wall - wall.min()) / np.ptp(wall)
    img = np.where(np.isnan(depth), wall, sharp).astype(np.float32)
    img = img * np.linspace(0.6, 1.3, WIDE[1], dtype=np.float32)
    img = cv2.filter2D(img, -1, _disc(coc), borderType=cv2.BORDER_REFLECT)
    img = np.clip(img + rng.normal(0, 0.003, WIDE), 0, 1)
    codes = np.round(jaxdof._io.linear_to_srgb(img) * 255).astype(np.uint8)
    return codes, pose.homography(camera)


def _rolled(c, ax, ay, roll, distance):
    """`_pose`, then turned by `roll` degrees about the optical axis."""
    pose = _pose(c, ax, ay, distance)
    a = math.radians(roll)
    rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    return jaxdof.ChartPose(rz @ pose.rotation, rz @ pose.translation)


@pytest.fixture(scope="module")
def wide_chart():
    return jaxdof.make_chart(dpi=50, seed=7)


@pytest.mark.parametrize(
    "ax, ay, roll, distance, coc",
    [
        (0, 25, 0, 0.62, 15.0),  # circles wider than the markers' cells: none decoded
        (10, -40, 90, 0.62, 9.0),  # a quarter turn: the texture says which way round
        (0, 60, 180, 0.5, 15.0),  # steep and upside down
        (-30, 35, 270, 0.6, 4.0),
    ],
)
def test_detect_defocused(wide_chart, ax, ay, roll, distance, coc):
    """Circles of 4-15 px on a chart about 300 px wide at tilts of 25-60 degrees, turned any way
    round: the frame's outline, the orientation from the texture, the homography refined against
    the photo: the chart's corners within half a pixel of the truth, the blur measured."""
    c, raster = wide_chart
    pose = _rolled(c, ax, ay, roll, distance)
    photo, truth = _defocused(c, raster, pose, coc)
    view = jaxdof.detect_chart(photo, c)
    assert 24 < pose.tilt < 61
    assert view.method == "outline" and view.shape == WIDE
    assert _outline_error(view, truth, c.corners) < 0.5
    assert view.coc_px == pytest.approx(coc, rel=0.15)
    assert view.correlation > 0.95
    # the pose from the refined homography's grid
    points, pixels = view.grid()
    assert points.shape == pixels.shape == (25, 2)


def test_detect_reduces_large_photos(wide_chart, monkeypatch):
    """A photo larger than the working size: the frame found and the homography refined on the
    photo reduced (here by 2), mapped back to the photo's pixels."""
    from jaxdof._chart import _detect

    c, raster = wide_chart
    pose = _rolled(c, 10, 45, 200, 0.6)
    photo, truth = _defocused(c, raster, pose, 10.0)
    monkeypatch.setattr(_detect, "_WORK_PIXELS", 50_000)
    view = jaxdof.detect_chart(photo, c)
    assert view.method == "outline" and view.shape == WIDE
    assert _outline_error(view, truth, c.corners) < 1.0  # half a reduced pixel
    assert view.coc_px == pytest.approx(10.0, rel=0.15)


def test_refinement_converges(wide_chart):
    """The photometric refinement from a start 1.5 px off at the corners: within 0.2 px of the
    truth over the frame."""
    from jaxdof._chart._detect import _linear, _refine, _Template

    c, raster = wide_chart
    pose = _rolled(c, 15, 40, 30, 0.62)
    photo, truth = _defocused(c, raster, pose, 8.0, seed=3)
    frame = c.frame
    p = np.column_stack([frame, np.ones(4)]) @ truth.T
    off = np.array([[1.5, -1.0], [-1.0, -1.5], [1.0, 1.5], [-1.5, 1.0]])
    import cv2

    start = cv2.getPerspectiveTransform(
        frame.astype(np.float32), (p[:, :2] / p[:, 2:] + off).astype(np.float32)
    )
    light = _linear(photo)
    hom, coc, corr = _refine(light, _Template(c, raster, start, light.shape), start)
    view = jaxdof.ChartView(
        np.zeros(0, int), np.zeros((0, 4, 2)), np.zeros((0, 4, 2)), hom, 0.0, 0, WIDE, 0.5
    )
    assert _outline_error(view, truth, frame) < 0.2
    assert coc == pytest.approx(8.0, rel=0.15) and corr > 0.95


def _exact_view(c, homography) -> jaxdof.ChartView:
    return jaxdof.ChartView(
        np.zeros(0, int),
        np.zeros((0, 4, 2)),
        np.zeros((0, 4, 2)),
        homography,
        0.0,
        0,
        SHAPE,
        0.5,
        size_m=(c.width_m, c.height_m),
    )


@pytest.mark.parametrize("patches", [False, True])
def test_align_with_the_lens_blur(chart, tilted, monkeypatch, patches):
    """A photo from `jaxdof.render` (f/1.4 focused at 0.55 m: circles 0-3.7 px across the chart)
    and a homography whose corners are 0.4-0.6 px off: aligned with the lens's render of the
    chart, each pixel blurred by its own circle, the corners come within 0.1 px of the truth and
    the focal length in pixels from the homography within 1 %. Also where the chart has more
    pixels than are compared (`patches`: a grid of squares, the template rendered on them
    alone), whose template is the render of the whole frame there."""
    import cv2

    from jaxdof._chart import _align
    from jaxdof._chart._align import align_view, alignment_samples, render_template, usable_pixels

    if patches:
        monkeypatch.setattr(_align, "_SAMPLES", 4000)
        monkeypatch.setattr(_align, "_PATCH", 24)
    c, raster = chart
    pose, camera, scene = tilted
    lens = _lens(1.4, 0.55)
    photo = _photo(scene, lens, noise=0.002)
    truth = pose.homography(camera)
    seen = np.column_stack([c.corners, np.ones(4)]) @ truth.T
    off = np.array([[0.5, -0.3], [-0.4, -0.5], [0.3, 0.5], [-0.5, 0.4]])
    start = cv2.getPerspectiveTransform(
        c.corners.astype(np.float32), (seen[:, :2] / seen[:, 2:] + off).astype(np.float32)
    ).astype(np.float64)
    view = _exact_view(c, start)
    at = chart_pose(*view.grid(), camera)
    sharp, depth = jaxdof.chart_scene(c, raster, at, camera, SHAPE)
    reach = float(np.nanmax(np.asarray(jaxdof.coc_radius(jaxdof.fill_depth_holes(depth), lens))))
    samples = alignment_samples(usable_pixels(depth, reach))
    templates = render_template(sharp, depth, lens, samples.boxes, reach)
    assert 4 < len(templates) <= 9 if patches else len(templates) == 1
    assert samples.ys.size < 4000 if patches else samples.ys.size > 8000
    whole = np.asarray(jaxdof.render(sharp, depth, lens, fill_holes=True))
    for (r0, _, c0, _), t, k in zip(samples.boxes, templates, samples.groups):
        np.testing.assert_allclose(
            t[samples.ys[k] - r0, samples.xs[k] - c0],
            whole[samples.ys[k], samples.xs[k]],
            rtol=1e-5,
            atol=1e-6,
        )
    at_h = at.homography(camera)
    aligned, moved = align_view(photo, view, templates, at_h, samples)
    assert _outline_error(view, truth, c.corners) > 0.5
    assert _outline_error(aligned, truth, c.corners) < 0.1
    assert 0.4 < moved < 0.8
    f_px = focal_from_homographies([aligned.homography], SHAPE)
    assert f_px == pytest.approx(F_PX, rel=0.01)


@pytest.mark.parametrize("focus", [0.45, 0.6, math.inf])
def test_focal_px_from_the_focal_length(chart, tilted, focus):
    """With the focal length and the pitch given, the focal length in pixels is the image
    distance's at the focus distance: at the chart's centre's distance without one (the pose
    found at that distance: a fixed point, from `f / p` about 6 % short here), then at the
    focus distance the first fit found, on the scale of the depth it was found with."""
    from jaxdof._chart._calibrate import _focal_px, _focused

    c, _ = chart
    pose, camera, _ = tilted
    view = _exact_view(c, pose.homography(camera))
    points = view.grid()[0]
    centre = float(pose.translation[2] + pose.rotation[2, :2] @ points.mean(0))
    pitch = FOCAL * centre / (centre - FOCAL) / F_PX  # the chart's centre in focus
    assert _focal_px(view, FOCAL, pitch, None) == pytest.approx(F_PX, rel=1e-4)
    # a lens focused at `focus`; its depth map made with f_px at the centre's distance is
    # `scale` too deep, and so is the focus distance fitted on it
    truth = 1 / ((1 / FOCAL - 1 / focus) * pitch)
    scale = F_PX / truth
    f, p, found = _focused((FOCAL, pitch, None), focus * scale, F_PX)
    assert (f, p) == (FOCAL, pitch)
    assert 1 / found == pytest.approx(1 / focus, abs=1e-6)
    assert _focal_px(view, FOCAL, pitch, found) == pytest.approx(truth, rel=1e-6)
    # EXIF's focus distance stays
    assert _focused((FOCAL, pitch, 0.7), focus * scale, F_PX) == (FOCAL, pitch, 0.7)


@pytest.mark.parametrize("f_number, focus", [(16.0, 0.45), (2.0, 0.5), (1.4, 0.55)])
def test_detect_blurred(chart, tilted, f_number, focus):
    """Photos from `jaxdof.render` (circles up to 0.2, 2.2 and 3.7 px here; cells of 7 px): by
    the markers where 4 are decoded, else by the frame; the chart's corners within half a pixel
    of the truth's."""
    c, raster = chart
    pose, camera, scene = tilted
    photo = _photo(scene, _lens(f_number, focus), noise=0.002)
    view = jaxdof.detect_chart(photo, c)
    assert view.shape == SHAPE and view.error < 2.0
    assert view.method == ("markers" if view.markers >= 4 else "outline")
    assert _outline_error(view, pose.homography(camera), c.corners) < 0.5


def test_detect_errors(chart, tilted):
    c, raster = chart
    pose, camera, scene = tilted
    photo = _photo(scene, _lens(16.0, 0.45))
    noise = np.random.default_rng(0).uniform(0.1, 0.9, SHAPE).astype(np.float32)
    with pytest.raises(jaxdof.ChartError, match="no chart found"):
        jaxdof.detect_chart(noise, c)
    # another chart's sidecar: its ids differ
    other, _ = jaxdof.make_chart(dpi=40, seed=2, marker_fraction=0.2)
    with pytest.raises(jaxdof.ChartError, match="of this chart's .*is the sidecar"):
        jaxdof.detect_chart(photo, other)
    # most markers hidden: the frame, oriented by the markers left
    view = jaxdof.detect_chart(photo, c)
    hidden = photo.copy()
    for corners in view.corners[2:]:
        lo, hi = corners.min(0).astype(int) - 3, corners.max(0).astype(int) + 4
        hidden[lo[1] : hi[1], lo[0] : hi[0]] = 0.5
    found = jaxdof.detect_chart(hidden, c)
    assert found.method == "outline" and found.markers == 2
    assert _outline_error(found, pose.homography(camera), c.corners) < 0.5
    # ... and the frame's corner hidden too
    u, v = np.round(view.outline[0]).astype(int)
    hidden[max(0, v - 30) : v + 30, max(0, u - 30) : u + 30] = 0.5
    with pytest.raises(jaxdof.ChartError, match=r"2 of the chart's \d+ markers found, 4 needed"):
        jaxdof.detect_chart(hidden, c)


def test_detect_another_charts_frame(wide_chart):
    """A defocused photo of another chart (no marker decoded): its frame is found, but its
    inside does not match this chart's."""
    c, raster = wide_chart
    other, other_raster = jaxdof.make_chart(dpi=50, seed=8)
    photo, _ = _defocused(other, other_raster, _rolled(other, 0, 35, 0, 0.62), 12.0)
    with pytest.raises(jaxdof.ChartError, match="does not match this chart's"):
        jaxdof.detect_chart(photo, c)
    with pytest.raises(jaxdof.ChartError, match="does not match this chart's"):
        jaxdof.detect_chart(photo, c, image=raster)


def test_detect_without_frame_needs_markers(wide_chart):
    """A chart of an older sidecar (no frame): the markers alone, as before."""
    c, raster = wide_chart
    legacy = dataclasses.replace(c, frame=None, frame_width_m=0.0)
    photo, _ = _defocused(c, raster, _rolled(c, 0, 35, 0, 0.62), 12.0)
    with pytest.raises(jaxdof.ChartError, match="no chart found"):
        jaxdof.detect_chart(photo, legacy, image=raster)


# ----------------------------------------------------------------------------------------------
# Calibration


def test_calibrate_refuses_a_chart_facing_the_camera(chart):
    c, raster = chart
    pose = _pose(c, 3, 4, 0.5)
    camera = camera_matrix(F_PX, SHAPE)
    photo = _photo(jaxdof.chart_scene(c, raster, pose, camera, SHAPE), _lens(16.0, 0.5))
    s = FOCAL * 0.5 / (0.5 - FOCAL)
    with pytest.raises(jaxdof.ChartError, match=r"faces the camera within \d\.\d degrees"):
        jaxdof.calibrate(photo, c, raster, focal_length=FOCAL, pixel_pitch=s / F_PX)
    # f_px from the homography: too weak to solve, or a tilt under 10 degrees
    with pytest.raises(jaxdof.ChartError, match="too squarely|faces the camera within"):
        jaxdof.calibrate(photo, c, raster, pixel_pitch=s / F_PX)


def test_calibrate_refuses_photos_of_two_scenes(chart, tilted):
    c, raster = chart
    _, camera, scene = tilted
    moved = jaxdof.chart_scene(c, raster, _pose(c, -15, 30, 0.45), camera, SHAPE)
    photos = [_photo(scene, _lens(16.0, 0.45)), _photo(moved, _lens(16.0, 0.45))]
    with pytest.raises(jaxdof.ChartError, match="photo 2 shows the chart .* from where photo 1"):
        jaxdof.calibrate(photos, c, raster, pixel_pitch=1e-5)


def test_calibrate_needs_a_pitch(chart, tilted):
    c, raster = chart
    photo = _photo(tilted[2], _lens(16.0, 0.45))
    with pytest.raises(jaxdof.ChartError, match="pixel pitch is unknown"):
        jaxdof.calibrate(photo, c, raster)


def test_off_chart_light_is_left_out(tilted):
    """The photo pixels within the blur scale `K` (the circle of a background at infinity) of
    the chart's outline get weight 0, times the caller's weight; a band that would leave under
    half the chart is halved until it does not."""
    from jaxdof._chart._calibrate import _off_chart

    _, _, (_, depth) = tilted
    holes = np.isnan(depth)
    lens = _lens(2.0, 0.45)
    k = float(lens.blur_scale)
    assert 5 < k < 20
    given = np.full(depth.shape, 2.0, np.float32)
    options, band, reach = _off_chart({"weight": given, "starts": 1}, depth, [lens])
    assert reach == pytest.approx(k)
    weight = options["weight"]
    distance = ndimage.distance_transform_edt(~holes)
    assert np.all(weight[distance <= math.floor(k)] == 0)
    assert np.all(weight[distance > math.ceil(k) + 1] == 2.0)
    assert band == np.sum((weight == 0) & ~holes) > 0
    # a lens whose band would cover the chart: the band shrinks, half the chart stays
    wide = _lens(0.25, 0.45)  # K 42 px
    assert np.sum(distance > float(wide.blur_scale)) < 0.5 * np.sum(~holes)
    kept = _off_chart({}, depth, [wide])[0]["weight"]
    assert 0.5 <= kept.sum() / np.sum(~holes) < 1


@pytest.mark.slow  # 23 s each on a shared 2-core machine
@pytest.mark.parametrize("given", ["pixel_pitch", "focal_length"])
def test_calibrate_end_to_end(chart, tilted, given):
    """A photo of the tilted chart through f/2 focused at 0.5 m (circles up to 2.2 px, noise
    0.002): the focus distance within 2 %, the blur scale within 5 %, the camera's focal length
    in pixels from the markers within 3 %, or, with the focal length given too, the image
    distance's at the fitted focus (`_focused`, within `_tuning.CHART_REFOCUS`) with the focus's
    error in its own. The fit's choices are fixed (a photo from `jaxdof.render` needs none of
    them) to keep the test short."""
    from jaxdof import _tuning
    from jaxdof._chart._calibrate import _focal_px, _focused

    c, raster = chart
    _, _, scene = tilted
    truth = _lens(2.0, 0.5)
    photo = _photo(scene, truth, noise=0.002)
    options = dict(
        exposure=False,
        vignetting=False,
        illumination=False,
        registration=False,
        footprint=False,
        edge_weight=False,
    )
    pitch = float(truth.pixel_pitch)
    if given == "focal_length":
        options["focal_length"] = FOCAL
    cal = jaxdof.calibrate(photo, c, raster, pixel_pitch=pitch, **options)
    assert cal.fit.success
    d_f = float(cal.lens.focus_distance)
    if given == "focal_length":
        assert cal.intrinsics == "focal length and pixel pitch"
        assert cal.focal_px == pytest.approx(F_PX, rel=0.01)
        # a fixed point: the f_px that the fitted focus gives is the one the scene was made with
        at_focus = _focal_px(cal.views[0], *_focused((FOCAL, pitch, None), d_f, cal.focal_px))
        assert abs(at_focus / cal.focal_px - 1) <= _tuning.CHART_REFOCUS
        # sigma(f_px) = f_px s sigma(P), and the reported sigma(P) holds it: times
        # sqrt(1 + (s / d_f)^2) (`_with_scale_error`)
        s = cal.focal_px * pitch
        power_se = float(cal.fit.focus_power_stderr) / math.hypot(1, s / d_f)
        assert cal.focal_px_stderr == pytest.approx(cal.focal_px * s * power_se, rel=1e-6)
    else:
        assert cal.intrinsics == "homographies"
        assert cal.focal_px == pytest.approx(F_PX, rel=0.03)
        assert abs(cal.focal_px - F_PX) < 3 * cal.focal_px_stderr
    assert d_f == pytest.approx(0.5, rel=0.02)
    # the focus distance's error holds the depth scale's, the focal length's in pixels
    se = float(cal.fit.stderr["focus_distance"])
    assert se >= d_f * cal.focal_px_stderr / cal.focal_px
    assert abs(d_f - 0.5) < 3 * se
    assert float(cal.lens.blur_scale) == pytest.approx(float(truth.blur_scale), rel=0.05)
    out = cal.to_dict()
    assert len(out["aligned_px"]) == 1 and out["aligned_px"][0] < 1.0
    assert out["photos"][0]["markers"] == cal.views[0].markers
    assert 30 < out["photos"][0]["tilt_deg"] < 45
