"""Finding the chart in a photo: its ArUco markers (OpenCV) in a sharp photo, its dark frame's
outline in a blurred one, then the homography from the chart's plane (m) to the photo's pixels
refined against the photo itself."""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
from jaxtyping import Float, Int
from scipy import ndimage

from .._io import srgb_to_linear
from ._design import _QUIET, Chart, _cv2, raster_of
from ._geometry import ChartError, _hom4


# Dictionaries tried when none of the chart's is found, to say which one the photo shows.
_OTHERS = ("DICT_4X4_1000", "DICT_5X5_1000", "DICT_6X6_1000", "DICT_APRILTAG_36h11")
_RANSAC_PX = 4.0  # a corner this far (photo pixels) from the homography's is an outlier
_MIN_COVER = 0.02  # the chart's smallest share of the frame
_PROBE_PIXELS = 4_000_000  # the other dictionaries are looked for at most at this size
# The circles of confusion (diameters, photo pixels) the chart's raster is blurred with to match
# a photo: uniform discs, as a thin lens blurs (the smallest stand for a sharp photo's pixel
# footprint and optics).
_BLURS = (1.0, 2.0, 3.2, 4.8, 6.8, 9.4, 12.6, 16.6, 21.6)
# The chart's inside (markers and texture) must correlate with the photo at least this well at
# the frame's best orientation; another chart's or a mere dark rectangle's stay far below.
_MIN_CORRELATION = 0.5
_MIN_INSIDE = 500  # pixels of the frame's inside, at least, to tell the chart by
_QUADS = 6  # frame candidates tried at most, largest first
_PROFILES = 24  # profiles across each side of the frame in its sub-pixel fit
_ECC_ITERATIONS = 60
_ROUNDS = 5  # of ECC, each from the light evened out about the last
# The frame is looked for, and the homography refined, in the photo reduced to at most this many
# pixels: their accuracy is a share of the blur, which shrinks with the photo.
_WORK_PIXELS = 1_500_000


@dataclasses.dataclass(frozen=True)
class ChartView:
    """The chart as found in one photo.

    **Fields:**

    - `ids`: the chart's markers decoded, `(n,)` (none may be, where the frame was found).
    - `corners`: their corners in the photo `(n, 4, 2)` (pixels `(u, v)`: column, row; pixel
      centres at integers), in OpenCV's order.
    - `points`: the same corners on the chart `(n, 4, 2)` (m).
    - `homography`: `(3, 3)`, chart metres `(x, y, 1)` to photo pixels (homogeneous), refined
      against the photo.
    - `error`: the root-mean-square distance (pixels) between the corners found (the markers',
      or the frame's) and the refined homography's image of them, over the inliers.
    - `inliers`: how many of those corners the homography fits within 4 pixels.
    - `shape`: the photo's `(H, W)`.
    - `cover`: the share of the frame the chart covers.
    - `method`: how the chart was found: `"markers"` (at least `min_markers` decoded) or
      `"outline"` (its dark frame, oriented by the markers decoded or by the texture).
    - `coc_px`: the diameter (pixels) of the uniform disc blur of the chart's raster that
      matched the photo best: a typical circle of confusion on the chart.
    - `correlation`: the correlation of the photo with the chart's raster warped and blurred so,
      over the chart (1: a perfect match up to gain and offset).
    - `size_m`: the chart's `(width, height)` (m).
    """

    ids: Int[np.ndarray, " n"]
    corners: Float[np.ndarray, "n 4 2"]
    points: Float[np.ndarray, "n 4 2"]
    homography: Float[np.ndarray, "3 3"]
    error: float
    inliers: int
    shape: tuple[int, int]
    cover: float
    method: str = "markers"
    coc_px: float = math.nan
    correlation: float = math.nan
    size_m: tuple[float, float] = (math.nan, math.nan)

    @property
    def markers(self) -> int:
        """The number of the chart's markers decoded."""
        return int(self.ids.size)

    @property
    def outline_m(self) -> Float[np.ndarray, "4 2"]:
        """The chart's corners on the chart (m), clockwise from its top-left."""
        w, h = self.size_m
        return np.array([[0, 0], [w, 0], [w, h], [0, h]], float)

    @property
    def outline(self) -> Float[np.ndarray, "4 2"]:
        """The chart's corners in the photo (pixels), clockwise from its top-left."""
        return _project(self.homography, self.outline_m)

    def grid(self, n: int = 5) -> tuple[Float[np.ndarray, "m 2"], Float[np.ndarray, "m 2"]]:
        """`(points, pixels)`: an `n x n` grid over the chart (m) and its image by the
        homography (pixels): the correspondences the pose is solved from."""
        w, h = self.size_m
        x, y = np.meshgrid(np.linspace(0, w, n), np.linspace(0, h, n))
        points = np.column_stack([x.ravel(), y.ravel()])
        return points, _project(self.homography, points)


def grey8(photo: np.ndarray) -> np.ndarray:
    """A photo as OpenCV's detector takes it: 8-bit grey. Floats are linear light (encoded to
    sRGB for contrast in the shadows); integers are taken as stored (encoded)."""
    photo = np.asarray(photo)
    if photo.ndim == 3:
        kind = photo.dtype
        photo = photo[..., :3].mean(axis=-1)
        photo = photo if kind.kind == "f" else photo.astype(kind)
    if photo.ndim != 2:
        raise ChartError(f"a photo is (H, W) or (H, W, C), got shape {photo.shape}")
    if photo.dtype == np.uint8:
        return photo
    if photo.dtype.kind in "ui":
        top = 65535 if photo.max() > 255 else 255
        return np.round(photo.astype(np.float64) * (255 / top)).astype(np.uint8)
    # round(255 sRGB(x)) as the count of the codes' half-way points at or below x: exact, and
    # several times faster than the power law over a 24 MP photo
    return np.searchsorted(_SRGB8_HALFWAY, photo.astype(np.float64), side="right").astype(np.uint8)


#: The linear light at which 8-bit sRGB codes `k - 1` and `k` meet (`k = 1 .. 255`).
_SRGB8_HALFWAY = srgb_to_linear((np.arange(1, 256) - 0.5) / 255)


def _detector(dictionary: str):
    cv2 = _cv2()
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    # larger thresholding windows than the default (3 to 23 px) find markers whose edges a
    # strong defocus has spread over tens of pixels
    params.adaptiveThreshWinSizeMax = 63
    params.adaptiveThreshWinSizeStep = 10
    aruco = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    return cv2.aruco.ArucoDetector(aruco, params)


def _markers(grey: np.ndarray, dictionary: str) -> tuple[list[np.ndarray], np.ndarray]:
    corners, ids, _ = _detector(dictionary).detectMarkers(grey)
    ids = np.zeros(0, int) if ids is None else ids.reshape(-1).astype(int)
    return [np.asarray(c, np.float64).reshape(4, 2) for c in corners], ids


def detect_chart(
    photo: np.ndarray,
    chart: Chart,
    *,
    min_markers: int = 4,
    name: str = "photo",
    image: Float[np.ndarray, "ch cw"] | None = None,
) -> ChartView:
    """Find `chart` in `photo`: the homography from the chart's plane to the photo.

    **Arguments:**

    - `photo`: `(H, W)` or `(H, W, C)`: floats as linear light, or 8/16-bit sRGB codes.
    - `chart`: the `Chart` photographed.
    - `min_markers`: the fewest of the chart's markers decoded to rely on them alone.
    - `name`: the photo's name in error messages (a file name).
    - `image`: the chart's raster (default: the one `make_chart` or `read_chart` gave with
      `chart`, else drawn again).

    **Returns:** a `ChartView`.

    **Method.** OpenCV's ArUco detector (`cv2.aruco.ArucoDetector`, sub-pixel corners) on the
    photo's 8-bit sRGB grey; markers of other ids are ignored. With `min_markers` of the chart's
    decoded, the start is the robust homography of their corners (`cv2.findHomography`, RANSAC
    with a 4-pixel threshold). Otherwise, the chart's dark frame: dark regions of the grey
    (Otsu's and adaptive thresholds), the outer contours simplified to convex quadrilaterals
    (`cv2.approxPolyDP`), each side refitted as the line through its edge's mid-level crossings
    (the mid level between the frame and the white zone outside it, in linear light: unbiased
    under a symmetric blur), the corners where the lines meet. Of the 4 ways the chart can lie
    in that outline, the one that fits the markers decoded, else the one whose raster, warped
    and blurred, correlates best with the photo inside the frame (high-passed; under 0.5: not
    this chart). The start is then refined against the photo: the raster warped by it and
    blurred by the uniform disc (a thin lens's circle of confusion) that matches the photo best,
    the photo's light evened out (a gain quadratic in the position and an offset, fitted), then
    aligned over the chart's pixels by maximising their enhanced correlation coefficient over
    homographies (`cv2.findTransformECC`; Evangelidis & Psarakis, "Parametric image alignment
    using enhanced correlation coefficient maximization", IEEE TPAMI 2008); a few rounds, the
    best kept.

    **Raises:** `ChartError` (a `ValueError`), in one line, when neither `min_markers` markers
    nor the frame is found (naming the dictionary found instead, if any), when the frame's
    inside is not this chart's (with more of another chart's markers than of this one's: the
    sidecar is another chart's), or when the chart covers under 2 % of the frame.
    """
    grey = grey8(photo)
    h, w = grey.shape
    found, ids = _markers(grey, chart.dictionary)
    mine = [k for k, i in enumerate(ids) if int(i) in chart.markers]
    foreign = ids.size - len(mine)
    another = ChartError(
        f"{name}: {ids.size} {chart.dictionary} markers found, {len(mine) or 'none'} of "
        f"them of this chart's (found ids {sorted(int(i) for i in ids)[:8]}, the chart's "
        f"{sorted(chart.markers)[:8]}): is the sidecar the photographed chart's?"
    )
    ids = ids[mine]
    corners = np.stack([found[k] for k in mine]) if mine else np.zeros((0, 4, 2))
    points = chart.marker_points(ids)
    # the frame and the refinement work on the photo reduced to at most `_WORK_PIXELS`
    light, grey_w, to_work = _working(_linear(photo), grey)
    if len(mine) >= min_markers:
        method = "markers"
        start, inl = _from_markers(points, corners)
        if start is None:
            raise ChartError(f"{name}: the chart's markers do not fit one plane")
        src, dst = points.reshape(-1, 2)[inl], corners.reshape(-1, 2)[inl]
        start = to_work @ start
        template = _Template(chart, image, start, light.shape)
    else:
        method = "outline"
        best = None
        if chart.frame is not None:
            raster = raster_of(chart) if image is None else image
            seen = _project(to_work, corners.reshape(-1, 2)).reshape(-1, 4, 2)
            best = _from_outline(light, grey_w, chart, raster, points, seen)
        if best is None or best[2] < _MIN_CORRELATION:
            if foreign > len(mine):  # a blurred photo may show one false decode, not more
                raise another
            if best is None:
                raise ChartError(_not_found(name, chart, grey, len(mine), min_markers))
            raise ChartError(
                f"{name}: a dark frame found, but its inside does not match this chart's "
                f"(correlation {best[2]:.2f}, {_MIN_CORRELATION} needed): another chart's "
                "sidecar, or no chart"
            )
        start, template, _, src, dst = best
        dst = _project(np.linalg.inv(to_work), dst)
    hom, coc, corr = _refine(light, template, start)
    found = (ids, corners, points, (src, dst))
    return _view(
        chart, name, found, np.linalg.inv(to_work) @ hom, coc / to_work[0, 0], corr, method, (h, w)
    )


def _view(chart: Chart, name: str, found, hom, coc: float, corr: float, method: str, shape):
    """`detect_chart`'s `ChartView` from the refined homography `hom` (photo pixels), or a
    `ChartError` where the chart covers too little of the frame. `found`: the markers decoded
    (`ids`, `corners`), their chart points, and the point pairs `(src, dst)` the start came from
    (the markers' corners, or the frame's), whose fit the view reports."""
    ids, corners, points, (src, dst) = found
    h, w = shape
    cover = _area(np.clip(_project(hom, chart.corners), [0, 0], [w, h])) / (w * h)
    if cover < _MIN_COVER:
        raise ChartError(
            f"{name}: the chart covers {cover:.1%} of the frame, under {_MIN_COVER:.0%}; "
            "come closer or zoom in"
        )
    err = np.sqrt(np.sum((dst - _project(hom, src)) ** 2, axis=1))
    return ChartView(
        ids=ids,
        corners=corners,
        points=points,
        homography=hom / hom[2, 2],
        error=float(np.sqrt(np.mean(err**2))),
        inliers=int(np.sum(err <= _RANSAC_PX)),
        shape=(h, w),
        cover=float(cover),
        method=method,
        coc_px=float(coc),
        correlation=float(corr),
        size_m=(chart.width_m, chart.height_m),
    )


def _not_found(name, chart, grey, mine, min_markers) -> str:
    """The message when neither enough markers nor the frame is found."""
    total = len(chart.markers)
    if mine:
        return (
            f"{name}: {mine} of the chart's {total} markers found, {min_markers} needed, and "
            "not its frame; bring the whole chart into the frame, closer or less defocused"
        )
    other = _other_dictionary(grey, chart.dictionary)
    if other:
        return (
            f"{name}: no {chart.dictionary} marker found, but {other}: the sidecar is not the "
            "photographed chart's"
        )
    return (
        f"{name}: no chart found (neither its frame nor any of its {total} {chart.dictionary} "
        "markers); the whole chart must be in the frame, lit, with a margin around it"
    )


def _working(light: np.ndarray, grey: np.ndarray):
    """`(light, grey, to_work)`: the photo's linear and 8-bit grey reduced (area averages) to at
    most `_WORK_PIXELS`, and the map of photo pixels to theirs (`(3, 3)`; pixel centres at
    integers in both)."""
    cv2 = _cv2()
    h, w = light.shape
    step = math.ceil(math.sqrt(h * w / _WORK_PIXELS))
    if step <= 1:
        return light, grey, np.eye(3)
    size = (max(1, w // step), max(1, h // step))
    sx, sy = size[0] / w, size[1] / h
    to_work = np.array([[sx, 0, (sx - 1) / 2], [0, sy, (sy - 1) / 2], [0, 0, 1]])
    light = cv2.resize(light, size, interpolation=cv2.INTER_AREA)
    return light, cv2.resize(grey, size, interpolation=cv2.INTER_AREA), to_work


def _linear(photo: np.ndarray) -> np.ndarray:
    """A photo's grey in linear light, float32: floats as they are, integers decoded (sRGB)."""
    photo = np.asarray(photo)
    kind = photo.dtype
    if photo.ndim == 3:
        photo = photo[..., :3].astype(np.float64).mean(axis=-1)
    if kind.kind == "f":
        return np.asarray(photo, np.float32)
    top = 65535 if kind.itemsize > 1 and photo.max() > 255 else 255
    return srgb_to_linear(np.asarray(photo, np.float64) / top).astype(np.float32)


def _from_markers(points, corners):
    """The robust homography of the markers' corners, and the inliers (`None, None` if none)."""
    cv2 = _cv2()
    src, dst = points.reshape(-1, 2), corners.reshape(-1, 2)
    hom, mask = cv2.findHomography(src, dst, cv2.RANSAC, _RANSAC_PX)
    if hom is None:
        return None, None
    inl = mask.reshape(-1).astype(bool)
    hom, _ = cv2.findHomography(src[inl], dst[inl], 0)
    return hom, inl


def _from_outline(light, grey, chart, raster, points, corners):
    """The frame's outline: `(homography, template, correlation, frame corners (m), their
    pixels)` of the best candidate, or `None` where no quadrilateral is found."""
    assert chart.frame is not None
    frame = np.asarray(chart.frame, np.float64)
    best = None
    for quad in _quads(grey):
        quad = _fit_sides(light, quad, chart)
        if quad is None:
            continue
        homs = [_hom4(frame, np.roll(quad, -k, axis=0)) for k in range(4)]
        template = _Template(chart, raster, homs[0], light.shape)
        if len(points):  # the markers decoded say which way round
            errs = [_max_distance(g, points, corners) for g in homs]
            k = int(np.argmin(errs))
            if errs[k] > 2 * _RANSAC_PX:
                continue
            corr = template.identity(light, homs[k], template.blur(light, homs[k]))
        else:  # the texture does
            scores = [template.identity(light, g, template.blur(light, g)) for g in homs]
            k = int(np.argmax(scores))
            corr = scores[k]
        if best is None or corr > best[2]:
            best = (homs[k], template, corr, frame, np.roll(quad, -k, axis=0))
    return best


def _max_distance(hom, points, corners) -> float:
    """The largest distance (pixels) between `corners` and the image of `points` by `hom`."""
    return float(np.abs(_project(hom, points.reshape(-1, 2)) - corners.reshape(-1, 2)).max())


def _quads(grey: np.ndarray) -> list[np.ndarray]:
    """Convex quadrilaterals `(4, 2)` (pixels, clockwise on the photo) outlining dark regions:
    the outer contours of the darker than Otsu's level and of the darker than their
    surroundings (adaptive thresholds of two sizes), largest first, without repeats."""
    cv2 = _cv2()
    h, w = grey.shape
    g = cv2.GaussianBlur(grey, (0, 0), 1.0)
    masks = [cv2.threshold(g, 0, 255, cv2.THRESH_BINARY_INV + cv2.THRESH_OTSU)[1]]
    for frac in (1 / 8, 1 / 4):
        block = max(3, int(max(h, w) * frac) // 2 * 2 + 1)
        masks.append(
            cv2.adaptiveThreshold(
                g, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY_INV, block, 5
            )
        )
    quads: list[np.ndarray] = []
    for mask in masks:
        contours, hier = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
        if hier is None:
            continue
        for c, link in zip(contours, hier[0]):
            if link[3] != -1 or cv2.contourArea(c) < _MIN_COVER * h * w / 2:
                continue
            hull = cv2.convexHull(c)
            q = cv2.approxPolyDP(hull, 0.02 * cv2.arcLength(hull, True), True).reshape(-1, 2)
            if len(q) != 4:
                continue
            q = q.astype(np.float64)
            if _signed_area(q) < 0:
                q = q[::-1]
            # a quadrilateral touching the photo's border is cut by it: not the frame
            if q.min() < 1 or np.any(q.max(0) > [w - 2, h - 2]):
                continue
            if all(np.abs(np.roll(q, k, axis=0) - p).max() > 3 for p in quads for k in range(4)):
                quads.append(q)
    quads.sort(key=lambda q: -_signed_area(q))
    return quads[:_QUADS]


def _signed_area(q: np.ndarray) -> float:
    """The signed area of a polygon: positive when clockwise on the photo (y down)."""
    x, y = q[:, 0], q[:, 1]
    return float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) / 2


def _fit_sides(light, quad, chart) -> np.ndarray | None:
    """The frame's outer corners (pixels) from `quad`: each side refitted as the line through
    its edge's crossings of the mid level between the dark band inside and the white zone
    outside (profiles along the side's normal), the corners where adjacent lines meet."""
    assert chart.frame is not None
    frame = np.asarray(chart.frame, np.float64)
    # the band's and the white zone's widths in the photo, roughly (any orientation will do)
    hom = _hom4(frame, quad)
    band_px = np.linalg.norm(_project(hom, _frame_inner(chart)) - quad, axis=1).min()
    zone_px = np.linalg.norm(_project(hom, chart.corners) - quad, axis=1).min()
    band_px, zone_px = band_px / math.sqrt(2), zone_px / math.sqrt(2)  # corner to corner
    steps_in = np.arange(-max(2.0, 0.9 * band_px), 0, 0.25)
    steps_out = np.arange(0.25, max(2.0, 0.9 * zone_px), 0.25)
    steps = np.concatenate([steps_in, [0.0], steps_out])
    lines = []
    for i in range(4):
        a, b = quad[i], quad[(i + 1) % 4]
        length = float(np.linalg.norm(b - a))
        d = (b - a) / length
        n = np.array([d[1], -d[0]])  # outward: the inside is on the right, going clockwise
        pts = []
        for t in np.linspace(0.15, 0.85, _PROFILES):
            base = a + t * (b - a)
            xy = (
                base[None, None, :]
                + np.array([-1, 0, 1])[:, None, None] * d
                + steps[None, :, None] * n
            )
            prof = ndimage.map_coordinates(light, [xy[..., 1], xy[..., 0]], order=1, mode="nearest")
            prof = prof.mean(axis=0)
            dark = np.percentile(prof[: steps_in.size], 10)
            white = np.percentile(prof[-steps_out.size :], 90)
            if not white - dark > 0.2 * white:
                continue
            above = prof > (dark + white) / 2
            flips = np.nonzero(above[1:] != above[:-1])[0]
            if flips.size == 0:
                continue
            j = flips[np.argmin(np.abs(steps[flips]))]
            mid = (dark + white) / 2
            s = steps[j] + (mid - prof[j]) / (prof[j + 1] - prof[j]) * (steps[j + 1] - steps[j])
            pts.append(base + s * n)
        if len(pts) < 5:
            return None
        lines.append(_line(np.array(pts)))
    out = []
    for i in range(4):
        (p1, d1), (p2, d2) = lines[i - 1], lines[i]
        m = np.column_stack([d1, -d2])
        if abs(np.linalg.det(m)) < 1e-6:
            return None
        s, _ = np.linalg.solve(m, p2 - p1)
        out.append(p1 + s * d1)
    out = np.array(out)
    if np.abs(out - quad).max() > max(4.0, band_px):
        return None
    return out


def _frame_inner(chart: Chart) -> np.ndarray:
    """The frame band's inner corners `(4, 2)` (m), clockwise from the top-left."""
    assert chart.frame is not None
    inward = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]])
    return np.asarray(chart.frame, np.float64) + inward * chart.frame_width_m


def _line(pts: np.ndarray, trim: float = 1.0):
    """`(point, direction)` of the total-least-squares line through `pts`, refitted without the
    points farther than `trim` pixels (or 3 median deviations) from the first fit."""
    for _ in range(2):
        c = pts.mean(0)
        _, _, vt = np.linalg.svd(pts - c)
        d = vt[0]
        dist = np.abs((pts - c) @ np.array([d[1], -d[0]]))
        keep = dist <= max(trim, 3 * float(np.median(dist)))
        if keep.sum() < 5 or keep.all():
            break
        pts = pts[keep]
    return c, d


class _Template:
    """The chart's raster as a photo shows it: warped by a homography and blurred by a disc,
    from a copy of the raster reduced to about two texels per photo pixel."""

    def __init__(self, chart: Chart, raster, hom, shape):
        cv2 = _cv2()
        raster = np.asarray(raster_of(chart) if raster is None else raster, np.float32)
        self.chart = chart
        self.shape = shape[:2]
        nx, ny = chart.texture_px
        px, py = chart.pitch
        # photo pixels per raster pixel, on average over the chart
        area = _area(_project(hom, chart.corners))
        scale = math.sqrt(area / (nx * ny))
        f = min(1.0, 2 * scale)
        mx, my = max(8, round(nx * f)), max(8, round(ny * f))
        self.small = (
            raster if f == 1.0 else cv2.resize(raster, (mx, my), interpolation=cv2.INTER_AREA)
        )
        sx, sy = px * nx / self.small.shape[1], py * ny / self.small.shape[0]
        # small raster pixel (column, row), centres at integers, to chart metres
        self.to_chart = np.array([[sx, 0, sx / 2], [0, sy, sy / 2], [0, 0, 1]])
        self.fill = float(raster.mean())
        self._warped: tuple[bytes, np.ndarray] = (b"", raster)
        # the inside of the frame less the markers and their quiet zones
        self.inside = [chart.corners if chart.frame is None else _frame_inner(chart)]
        self.holes = []
        for c in chart.markers.values():
            half = float(c[1, 0] - c[0, 0]) * (0.5 + _QUIET)
            self.holes.append(c.mean(0) + np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * half)

    def render(self, hom, coc) -> np.ndarray:
        cv2 = _cv2()
        h, w = self.shape
        key = np.asarray(hom, np.float64).tobytes()
        if self._warped[0] != key:
            out = cv2.warpPerspective(
                self.small,
                hom @ self.to_chart,
                (w, h),
                flags=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=self.fill,
            )
            self._warped = (key, out)
        out = self._warped[1].copy()
        # blurred over the chart's box only: nothing outside it is compared
        r = int(math.ceil(coc / 2)) + 2
        seen = _project(hom, self.chart.corners)
        box = _box(seen, r, self.shape)
        x0, y0, x1, y1 = _box(seen, 2 * r, self.shape)
        part = cv2.filter2D(out[y0:y1, x0:x1], -1, _disc(coc), borderType=cv2.BORDER_REPLICATE)
        out[box[1] : box[3], box[0] : box[2]] = part[
            box[1] - y0 : box[3] - y0, box[0] - x0 : box[2] - x0
        ]
        return out

    def mask(self, hom, coc, inside=False) -> np.ndarray:
        """The pixels whose value blurred by a disc of `coc` pixels the chart alone decides
        (`inside`: within the frame, off the markers), boolean."""
        cv2 = _cv2()
        h, w = self.shape
        m = np.zeros((h, w), np.uint8)
        polys = self.inside if inside else [self.chart.corners]
        for p in polys:
            cv2.fillConvexPoly(
                m, np.round(_project(hom, p) * 16).astype(np.int32), 255, cv2.LINE_8, 4
            )
        if inside:
            for p in self.holes:
                cv2.fillConvexPoly(
                    m, np.round(_project(hom, p) * 16).astype(np.int32), 0, cv2.LINE_8, 4
                )
        r = int(math.ceil(coc / 2)) + 1
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        return cv2.erode(m, kernel) > 0

    def blur(self, light, hom) -> float:
        """The disc's diameter (pixels) whose template correlates best with the photo over the
        chart (each of `_BLURS` over one mask, then the peak of a parabola in its logarithm)."""
        mask = self.mask(hom, max(_BLURS))
        scores = [self.correlation(light, hom, c, mask=mask) for c in _BLURS]
        k = int(np.argmax(scores))
        if 0 < k < len(_BLURS) - 1:
            x = np.log(_BLURS[k - 1 : k + 2])
            y0, y1, y2 = scores[k - 1 : k + 2]
            den = y0 - 2 * y1 + y2
            if den < 0:
                t = 0.5 * (y0 - y2) / den  # in steps of the (near-uniform) log grid
                step = (x[2] - x[0]) / 2
                return float(np.exp(x[1] + np.clip(t, -0.5, 0.5) * step))
        return float(_BLURS[k])

    def identity(self, light, hom, coc) -> float:
        """How well the inside of the frame matches the photo at blur `coc`: high for this
        chart at its orientation, low for another chart's texture or another orientation."""
        mask = self.mask(hom, coc, inside=True)
        if np.count_nonzero(mask) < _MIN_INSIDE:
            return -1.0
        return self.correlation(light, hom, coc, mask=mask, high=True)

    def correlation(self, light, hom, coc, mask=None, high=False) -> float:
        """The correlation of the photo with the warped, blurred raster over `mask` (default:
        the chart's pixels; `high`: both high-passed first, which leaves more independent
        samples of the texture, so that another texture correlates little)."""
        cv2 = _cv2()
        m = self.mask(hom, coc) if mask is None else mask
        wide = 0.75 * coc + 3
        box = mask_box(m, int(3 * wide) + 2 if high else 0)
        if box is None or np.count_nonzero(m) < 64:
            return -1.0
        a, b = light[box], self.render(hom, coc)[box]
        if high:
            a = a - cv2.GaussianBlur(a, (0, 0), wide)
            b = b - cv2.GaussianBlur(b, (0, 0), wide)
        keep = m[box]
        a, b = a[keep].astype(np.float64), b[keep].astype(np.float64)
        a, b = a - a.mean(), b - b.mean()
        den = math.sqrt(float(a @ a) * float(b @ b))
        return float(a @ b) / den if den > 0 else -1.0


def mask_box(mask: np.ndarray, pad: int) -> tuple[slice, slice] | None:
    """The rows and columns of the box around `mask`'s `True` pixels, `pad` more each side
    within the frame; None where it has none."""
    ys, xs = np.nonzero(mask.any(axis=1))[0], np.nonzero(mask.any(axis=0))[0]
    if ys.size == 0:
        return None
    return slice(max(0, ys[0] - pad), ys[-1] + 1 + pad), slice(
        max(0, xs[0] - pad), xs[-1] + 1 + pad
    )


def _box(points, pad, shape) -> tuple[int, int, int, int]:
    """`(x0, y0, x1, y1)`: the pixels' box around `points`, `pad` more each side, in `shape`."""
    lo = np.floor(points.min(0)).astype(int) - pad
    hi = np.ceil(points.max(0)).astype(int) + pad + 1
    h, w = shape
    return max(0, int(lo[0])), max(0, int(lo[1])), min(w, int(hi[0])), min(h, int(hi[1]))


@functools.lru_cache(maxsize=64)
def _disc(diameter: float) -> np.ndarray:
    """A uniform disc kernel of `diameter` pixels (its pixels' coverage, 8 x 8 samples each),
    summing to 1; under 1.5 pixels, a Gaussian of the same variance (a pixel's footprint)."""
    r = diameter / 2
    n = int(math.ceil(r)) + 1
    if diameter < 1.5:
        sigma = max(r / 2, 0.3)
        x = np.arange(-2, 3)
        k1 = np.exp(-(x**2) / (2 * sigma**2))
        k = np.outer(k1, k1)
    else:
        off = (np.arange(8) + 0.5) / 8 - 0.5
        y, x = np.mgrid[-n : n + 1, -n : n + 1].astype(np.float64)
        xx = (x[..., None, None] + off[:, None]) ** 2 + (y[..., None, None] + off[None, :]) ** 2
        k = (xx <= r * r).mean(axis=(-1, -2))
    return (k / k.sum()).astype(np.float32)


def _refine(light, template: _Template, hom):
    """`(homography, circle, correlation)`: `hom` aligned with the photo by ECC against the
    raster warped by it and blurred by the disc that matches best, the photo's light evened
    out about it (`_flatten`), in rounds (each from the last's homography, light and disc)
    until it stops moving; of the rounds' homographies, the one that matches best (`hom`
    where ECC fails or strays)."""
    cv2 = _cv2()
    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, _ECC_ITERATIONS, 1e-7)
    corners = template.chart.corners

    def measure(hom, coc):
        flat = _flatten(light, template, hom, coc)
        coc = template.blur(flat, hom)
        return flat, coc, template.correlation(flat, hom, coc)

    flat, coc, corr = measure(hom, template.blur(light, hom))
    best = (hom, coc, corr)
    for _ in range(_ROUNDS):
        # over the chart's box only (a shift to its corner and back)
        x0, y0, x1, y1 = _box(_project(hom, corners), 8, light.shape)
        moving = template.render(hom, coc)[y0:y1, x0:x1]
        mask = template.mask(hom, coc)[y0:y1, x0:x1].astype(np.uint8)
        try:
            _, warp = cv2.findTransformECC(
                np.ascontiguousarray(flat[y0:y1, x0:x1]),
                moving,
                np.eye(3, dtype=np.float32),
                cv2.MOTION_HOMOGRAPHY,
                criteria,
                mask,
                1,
            )
        except cv2.error:  # no convergence: the best so far stands
            break
        shift = np.array([[1, 0, x0], [0, 1, y0], [0, 0, 1]], np.float64)
        new = np.linalg.inv(shift @ warp.astype(np.float64) @ np.linalg.inv(shift)) @ hom
        step = float(np.abs(_project(new, corners) - _project(hom, corners)).max())
        if not np.isfinite(step) or step > max(8.0, coc):
            break
        hom = new
        flat, coc, corr = measure(hom, coc)
        if corr > best[2]:
            best = (hom, coc, corr)
        if step < 0.02:
            break
    return best


def _flatten(light, template: _Template, hom, coc) -> np.ndarray:
    """The photo with its light evened out over the chart: `(photo - o) / g(u, v)` where the
    gain `g`, a quadratic in the pixel's position, and the offset `o` fit `photo = g T + o`
    (least squares over the chart's pixels) to the raster warped and blurred (`T`); so that
    the alignment is not pulled by light that falls off across the chart."""
    m = template.mask(hom, coc)
    ys, xs = np.nonzero(m)
    if ys.size < 64:
        return light
    h, w = light.shape
    u, v = (xs - w / 2) / w, (ys - h / 2) / w
    t = template.render(hom, coc)[ys, xs].astype(np.float64)
    basis = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v])
    a = np.column_stack([(basis * t).T, np.ones_like(t)])
    coef, *_ = np.linalg.lstsq(a, light[ys, xs].astype(np.float64), rcond=None)
    uu, vv = np.meshgrid((np.arange(w) - w / 2) / w, (np.arange(h) - h / 2) / w)
    gain = np.einsum(
        "k,kij->ij", coef[:6], np.stack([np.ones_like(uu), uu, vv, uu * uu, uu * vv, vv * vv])
    )
    low = 0.05 * max(float(np.abs(gain[ys, xs]).max()), 1e-30)
    if not np.all(gain[ys, xs] > low):  # a fit gone astray: the photo as it is
        return light
    return ((light - coef[6]) / np.maximum(gain, low)).astype(np.float32)


def _project(hom: np.ndarray, xy: np.ndarray) -> np.ndarray:
    p = np.column_stack([xy, np.ones(len(xy))]) @ np.asarray(hom).T
    return p[:, :2] / p[:, 2:]


def _area(poly: np.ndarray) -> float:
    """The area of a simple polygon (shoelace)."""
    x, y = poly[:, 0], poly[:, 1]
    return float(abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) / 2)


def _other_dictionary(grey: np.ndarray, dictionary: str) -> str | None:
    """`"N markers of DICT"` for the first other common dictionary with markers in `grey`."""
    cv2 = _cv2()
    h, w = grey.shape
    step = int(np.ceil(np.sqrt(h * w / _PROBE_PIXELS)))
    small = (
        grey
        if step == 1
        else cv2.resize(grey, (w // step, h // step), interpolation=cv2.INTER_AREA)
    )
    for other in _OTHERS:
        if other == dictionary:
            continue
        _, ids = _markers(small, other)
        if ids.size:
            return f"{ids.size} of {other}"
    return None
