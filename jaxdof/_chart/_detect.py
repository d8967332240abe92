"""Finding the chart in a photo: its ArUco markers (OpenCV), and the homography from the chart's
plane (m) to the photo's pixels."""

from __future__ import annotations

import dataclasses

import numpy as np
from jaxtyping import Float, Int

from .._io import linear_to_srgb
from ._design import Chart, _cv2
from ._geometry import ChartError


# Dictionaries tried when none of the chart's is found, to say which one the photo shows.
_OTHERS = ("DICT_4X4_1000", "DICT_5X5_1000", "DICT_6X6_1000", "DICT_APRILTAG_36h11")
_RANSAC_PX = 4.0  # a corner this far (photo pixels) from the homography's is an outlier
_MIN_COVER = 0.02  # the chart's smallest share of the frame
_PROBE_PIXELS = 4_000_000  # the other dictionaries are looked for at most at this size


@dataclasses.dataclass(frozen=True)
class ChartView:
    """The chart as found in one photo.

    **Fields:**

    - `ids`: the chart's markers found, `(n,)`.
    - `corners`: their corners in the photo `(n, 4, 2)` (pixels `(u, v)`: column, row; pixel
      centres at integers), in OpenCV's order.
    - `points`: the same corners on the chart `(n, 4, 2)` (m).
    - `homography`: `(3, 3)`, chart metres `(x, y, 1)` to photo pixels (homogeneous).
    - `error`: the root-mean-square distance (pixels) between the corners and the homography's
      image of their chart points, over the inliers.
    - `inliers`: how many of the `4 n` corners the homography fits within 4 pixels.
    - `shape`: the photo's `(H, W)`.
    - `cover`: the share of the frame the chart covers.
    """

    ids: Int[np.ndarray, " n"]
    corners: Float[np.ndarray, "n 4 2"]
    points: Float[np.ndarray, "n 4 2"]
    homography: Float[np.ndarray, "3 3"]
    error: float
    inliers: int
    shape: tuple[int, int]
    cover: float

    @property
    def markers(self) -> int:
        """The number of the chart's markers found."""
        return int(self.ids.size)


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
    return np.round(linear_to_srgb(photo) * 255).astype(np.uint8)


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
    photo: np.ndarray, chart: Chart, *, min_markers: int = 4, name: str = "photo"
) -> ChartView:
    """Find `chart` in `photo`: its markers and the homography from the chart's plane to the photo.

    **Arguments:**

    - `photo`: `(H, W)` or `(H, W, C)`: floats as linear light, or 8/16-bit sRGB codes.
    - `chart`: the `Chart` photographed.
    - `min_markers`: the fewest of the chart's markers to accept.
    - `name`: the photo's name in error messages (a file name).

    **Returns:** a `ChartView`.

    **Method.** OpenCV's ArUco detector (`cv2.aruco.ArucoDetector`, sub-pixel corner refinement)
    on the photo's 8-bit sRGB grey; the markers of other ids are ignored. The homography is
    `cv2.findHomography` of the corners' chart points (m) to their pixels, robust (RANSAC,
    4-pixel threshold) and refined on the inliers.

    **Raises:** `ChartError` (a `ValueError`), in one line, when no marker of the chart's
    dictionary is found (naming the dictionary found instead, if any), when the markers found are
    another chart's, when fewer than `min_markers` of the chart's are found, or when the chart
    covers under 2 % of the frame.
    """
    cv2 = _cv2()
    grey = grey8(photo)
    found, ids = _markers(grey, chart.dictionary)
    mine = [k for k, i in enumerate(ids) if int(i) in chart.markers]
    total = len(chart.markers)
    foreign = ids.size - len(mine)
    if len(mine) < min_markers and foreign > len(mine):
        raise ChartError(
            f"{name}: {ids.size} {chart.dictionary} markers found, {len(mine) or 'none'} of "
            f"them of this chart's (found ids {sorted(int(i) for i in ids)[:8]}, the chart's "
            f"{sorted(chart.markers)[:8]}): is the sidecar the photographed chart's?"
        )
    if not mine:
        if ids.size:
            raise ChartError(
                f"{name}: {ids.size} {chart.dictionary} markers found, none of this chart's "
                f"(ids {sorted(int(i) for i in ids)[:8]}, the chart's {sorted(chart.markers)[:8]}"
                "...): is the sidecar the photographed chart's?"
            )
        other = _other_dictionary(grey, chart.dictionary)
        if other:
            raise ChartError(
                f"{name}: no {chart.dictionary} marker found, but {other}: the sidecar is not "
                "the photographed chart's"
            )
        raise ChartError(
            f"{name}: no chart found (none of its {total} {chart.dictionary} markers); the "
            "chart must be in the frame, lit, and its markers no more blurred than about a "
            "third of their side"
        )
    if len(mine) < min_markers:
        raise ChartError(
            f"{name}: {len(mine)} of the chart's {total} markers found, {min_markers} needed; "
            "bring the whole chart into the frame, closer or less defocused"
        )
    ids = ids[mine]
    corners = np.stack([found[k] for k in mine])
    points = chart.marker_points(ids)
    src, dst = points.reshape(-1, 2), corners.reshape(-1, 2)
    hom, mask = cv2.findHomography(src, dst, cv2.RANSAC, _RANSAC_PX)
    if hom is None:
        raise ChartError(f"{name}: the chart's markers do not fit one plane")
    inl = mask.reshape(-1).astype(bool)
    hom, _ = cv2.findHomography(src[inl], dst[inl], 0)
    err = dst[inl] - _project(hom, src[inl])
    h, w = grey.shape
    outline = np.array(
        [[0, 0], [chart.width_m, 0], [chart.width_m, chart.height_m], [0, chart.height_m]]
    )
    cover = _area(np.clip(_project(hom, outline), [0, 0], [w, h])) / (w * h)
    if cover < _MIN_COVER:
        raise ChartError(
            f"{name}: the chart covers {cover:.1%} of the frame, under {_MIN_COVER:.0%}; "
            "come closer or zoom in"
        )
    return ChartView(
        ids=ids,
        corners=corners,
        points=points,
        homography=hom / hom[2, 2],
        error=float(np.sqrt(np.mean(np.sum(err**2, axis=1)))),
        inliers=int(inl.sum()),
        shape=(h, w),
        cover=float(cover),
    )


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
