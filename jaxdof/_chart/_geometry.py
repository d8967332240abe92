r"""The chart's plane in the camera: intrinsics from homographies, the pose, and the scene (the
chart's appearance and z-depth at every photo pixel).

Conventions (OpenCV's): camera coordinates `x` right, `y` down, `z` forward along the optical
axis; photo pixel `(row i, column j)` has its centre at `(u, v) = (j, i)`. A chart point `(x, y)`
(m, on the chart's plane `z = 0`) is at `R (x, y, 0) + t` in the camera, and at `G (x, y, 1)`
in the photo, with the homography `G = K [r_1\ r_2\ t]`.
"""

from __future__ import annotations

import dataclasses
import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from jaxtyping import Float

from ._design import Chart


# Samples per photo pixel and axis at most, and photo-plane samples per chunk (memory: about
# 60 bytes each).
_MAX_SAMPLES = 16
_CHUNK = 2**21
_BLOCK_ROWS = 64


class ChartError(ValueError):
    """A photo the chart cannot calibrate from: no chart found (neither its frame nor enough
    markers), the chart too small in the frame or too close to facing the camera, another
    chart's sidecar."""


@dataclasses.dataclass(frozen=True)
class ChartPose:
    """The chart's pose in the camera: chart point `X` (m, `z = 0`) at `rotation @ X +
    translation` (m, camera coordinates: `x` right, `y` down, `z` along the optical axis)."""

    rotation: Float[np.ndarray, "3 3"]
    translation: Float[np.ndarray, " 3"]

    @property
    def tilt(self) -> float:
        """The angle (degrees) between the chart's normal and the optical axis: 0 facing the
        camera."""
        return math.degrees(math.acos(min(1.0, abs(float(self.rotation[2, 2])))))

    def homography(self, camera: Float[np.ndarray, "3 3"]) -> np.ndarray:
        """`G = K [r_1 r_2 t]`: chart metres `(x, y, 1)` to photo pixels (homogeneous)."""
        r = self.rotation
        return camera @ np.column_stack([r[:, 0], r[:, 1], self.translation])


def camera_matrix(f_px: float, shape: tuple[int, ...]) -> np.ndarray:
    """`K` with focal length `f_px` (pixels), square pixels, zero skew and the principal point at
    the centre of an image of `shape` `(H, W, ...)`."""
    h, w = shape[:2]
    return np.array([[f_px, 0, (w - 1) / 2], [0, f_px, (h - 1) / 2], [0, 0, 1]], np.float64)


def focal_from_homographies(homographies: list[np.ndarray], shape: tuple[int, ...]) -> float | None:
    r"""The focal length (pixels) that makes the homographies' planes rotations, or `None`.

    With `K = diag(f, f, 1)` about the centre, `K^{-1} H = \lambda [r_1\ r_2\ t]`: its first two
    columns are orthogonal and of equal length (Zhang, "A flexible new technique for camera
    calibration", IEEE TPAMI 2000). For `h_i` the columns of `H` (centred), with `w = 1/f^2`:

    $$w (h_{11} h_{12} + h_{21} h_{22}) + h_{31} h_{32} = 0, \qquad
      w (h_{11}^2 + h_{21}^2 - h_{12}^2 - h_{22}^2) + h_{31}^2 - h_{32}^2 = 0,$$

    solved for `w` by least squares over every homography. A chart facing the camera has
    `h_{31} = h_{32} = 0` and says nothing about `f`: `None` when `w` is not positive.
    """
    h, w = shape[:2]
    shift = np.array([[1, 0, -(w - 1) / 2], [0, 1, -(h - 1) / 2], [0, 0, 1]])
    a, b = [], []
    for hom in homographies:
        g = shift @ np.asarray(hom, np.float64)
        # scale: the image-plane columns in units of the image's size, the third row to match
        g = np.diag([1 / w, 1 / w, 1.0]) @ g
        g = g / np.linalg.norm(g[:, :2])
        (h11, h12), (h21, h22), (h31, h32) = g[0, :2], g[1, :2], g[2, :2]
        a += [h11 * h12 + h21 * h22, h11**2 + h21**2 - h12**2 - h22**2]
        b += [h31 * h32, h31**2 - h32**2]
    a, b = np.array(a), np.array(b)
    if not np.any(a):
        return None
    omega = -float(a @ b) / float(a @ a)  # 1 / (f / w)^2
    return None if not omega > 0 else w / math.sqrt(omega)


def _hom4(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The homography of 4 point pairs (`(4, 2)` each), float64."""
    import cv2

    return cv2.getPerspectiveTransform(src.astype(np.float32), dst.astype(np.float32)).astype(
        np.float64
    )


def focal_stderr(views, sigma_px: float) -> float:
    """The standard error (pixels) of `focal_from_homographies` over `views`, were each corner of
    each chart's outline in the photo off by independent errors of `sigma_px` in each
    coordinate: `sigma_px` times the norm of the focal length's derivatives in the corners
    (central differences). `inf` where the focal length is undetermined."""
    homs = [v.homography for v in views]
    shape = views[0].shape
    if focal_from_homographies(homs, shape) is None:
        return math.inf
    step, grad2 = 0.01, 0.0
    for k, view in enumerate(views):
        for i in range(8):
            ends = []
            for sign in (1, -1):
                moved = view.outline.copy()
                moved.flat[i] += sign * step
                hom = _hom4(view.outline_m, moved)
                f = focal_from_homographies([*homs[:k], hom, *homs[k + 1 :]], shape)
                ends.append(math.inf if f is None else f)
            grad2 += ((ends[0] - ends[1]) / (2 * step)) ** 2
    return sigma_px * math.sqrt(grad2) if math.isfinite(grad2) else math.inf


def refine_focal(views, f_px: float) -> float:
    """The focal length (pixels) and poses that minimise the reprojection error of a grid over the
    chart (`ChartView.grid`, the refined homography's image) in every view
    (`cv2.calibrateCamera` from `f_px`: square pixels, the principal point at the centre, no
    distortion), which weighs the chart's extent as the linear solution does not."""
    import cv2

    shape = views[0].shape
    grids = [v.grid() for v in views]
    obj = [np.column_stack([p, np.zeros(len(p))]).astype(np.float32) for p, _ in grids]
    img = [q.astype(np.float32) for _, q in grids]
    flags = (
        cv2.CALIB_USE_INTRINSIC_GUESS
        | cv2.CALIB_FIX_PRINCIPAL_POINT
        | cv2.CALIB_FIX_ASPECT_RATIO
        | cv2.CALIB_ZERO_TANGENT_DIST
        | cv2.CALIB_FIX_K1
        | cv2.CALIB_FIX_K2
        | cv2.CALIB_FIX_K3
    )
    camera = camera_matrix(f_px, shape)
    size = (shape[1], shape[0])
    _, camera, _, _, _ = cv2.calibrateCamera(obj, img, size, camera, np.zeros(5), flags=flags)
    f = float(camera[0, 0])
    return f if math.isfinite(f) and f > 0 else f_px


def chart_pose(
    points: Float[np.ndarray, "n 2"], pixels: Float[np.ndarray, "n 2"], camera: np.ndarray
) -> ChartPose:
    """The pose of the chart from its points `(x, y)` (m) seen at `pixels` (photo pixels) through
    `camera`: OpenCV's planar solution (`SOLVEPNP_IPPE`; Collins & Bartoli, "Infinitesimal plane-
    based pose estimation", IJCV 2014), refined by Levenberg-Marquardt on the reprojection."""
    import cv2

    obj = np.column_stack([points, np.zeros(len(points))]).astype(np.float64)
    img = np.asarray(pixels, np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, img, camera, None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise ChartError("the chart's pose cannot be solved from its homography")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, camera, None, rvec, tvec)
    rotation, _ = cv2.Rodrigues(rvec)
    return ChartPose(rotation, tvec.reshape(3))


def chart_scene(
    chart: Chart,
    image: Float[np.ndarray, "ch cw"],
    pose: ChartPose,
    camera: Float[np.ndarray, "3 3"],
    shape: tuple[int, ...],
) -> tuple[Float[np.ndarray, "h w"], Float[np.ndarray, "h w"]]:
    r"""The chart as a camera of `camera` (`K`) sees it at `pose`: its all-in-focus image and
    z-depth at every pixel of a photo of `shape` `(H, W, ...)`.

    **Arguments:**

    - `chart`, `image`: the chart and its raster (`make_chart`, `read_chart`).
    - `pose`: a `ChartPose`; `camera`: the 3x3 intrinsic matrix (pixels).
    - `shape`: the photo's shape.

    **Returns:** `(sharp, depth)`, float32 `(H, W)`. `depth`: the z-depth (m) of the ray-plane
    intersection at each pixel's centre, `z = (n \cdot t) / (n \cdot K^{-1}(u, v, 1))` with `n` the
    chart's normal (the rotation's third column); NaN where the pixel's footprint (its square) is
    not wholly on the chart. `sharp`: each pixel's footprint, the mean of the chart's raster over
    the pixel's square mapped onto the chart: `s x s` samples per pixel, each a bilinear sample
    of the raster's box-filtered level `L` (a mip map), with `L` and `s` chosen per band of rows
    from the mapping's local scale (its Jacobian's singular values `sigma_min <= sigma_max`, in
    raster pixels per photo pixel): `2^L <= max(1, sigma_min)`, `s = ceil(sigma_max / 2^L)`, so
    the samples are at most one level-`L` texel apart and the raster is not aliased. Off the
    chart, `sharp` is the raster's mean.

    Work is in bands of rows (numpy, host memory of about 60 bytes per sample).
    """
    h, w = shape[:2]
    g = pose.homography(np.asarray(camera, np.float64))
    g_inv = np.linalg.inv(g)
    normal = pose.rotation[:, 2]
    k_inv = np.linalg.inv(camera)
    plane = float(normal @ pose.translation)
    levels = _Levels(np.asarray(image, np.float32))
    px, py = chart.pitch
    mean = float(levels[0].mean())
    sharp = np.full((h, w), mean, np.float32)
    depth = np.full((h, w), np.nan, np.float32)
    u = np.arange(w, dtype=np.float64)
    # the plane's depth along each pixel's ray: z = plane / (n . K^-1 (u, v, 1)), linear in u, v
    nk = normal @ k_inv

    def band(a: int) -> None:
        b = min(h, a + _BLOCK_ROWS)
        v = np.arange(a, b, dtype=np.float64)
        z = plane / (nk[0] * u[None, :] + (nk[1] * v + nk[2])[:, None])
        # the pixels' corners on the chart (raster pixels)
        cx, cy, front = _to_chart(g_inv, np.append(u, w) - 0.5, np.append(v, b) - 0.5)
        cx, cy = cx / px, cy / py
        inside = front & (cx >= 0) & (cx <= chart.texture_px[0])
        inside &= (cy >= 0) & (cy <= chart.texture_px[1])
        on = inside[:-1, :-1] & inside[1:, :-1] & inside[:-1, 1:] & inside[1:, 1:] & (z > 0)
        depth[a:b] = np.where(on, z, np.nan)
        if not on.any():
            return
        # the Jacobian (raster pixels per photo pixel) from the corners
        jxu = (cx[:-1, 1:] + cx[1:, 1:] - cx[:-1, :-1] - cx[1:, :-1]) / 2
        jxv = (cx[1:, :-1] + cx[1:, 1:] - cx[:-1, :-1] - cx[:-1, 1:]) / 2
        jyu = (cy[:-1, 1:] + cy[1:, 1:] - cy[:-1, :-1] - cy[1:, :-1]) / 2
        jyv = (cy[1:, :-1] + cy[1:, 1:] - cy[:-1, :-1] - cy[:-1, 1:]) / 2
        s_max, s_min = _singular_values(jxu[on], jxv[on], jyu[on], jyv[on])
        level = max(0, int(math.floor(math.log2(max(1.0, float(s_min.min()))))))
        samples = int(min(_MAX_SAMPLES, max(1, math.ceil(float(s_max.max()) / 2**level))))
        cols = np.flatnonzero(on.any(axis=0))  # sampled where the chart is
        lo, hi = int(cols[0]), int(cols[-1]) + 1
        inner = _footprint(levels[level], level, g_inv, u[lo:hi], v, samples, px, py)
        sharp[a:b, lo:hi] = np.where(on[:, lo:hi], inner, mean)

    # The bands write disjoint rows; numpy's gathers and arithmetic release the GIL, so they
    # share the host's cores.
    with ThreadPoolExecutor(max_workers=_workers()) as pool:
        for done in [pool.submit(band, a) for a in range(0, h, _BLOCK_ROWS)]:
            done.result()
    return sharp, depth


def _workers() -> int:
    """Threads for `chart_scene`'s bands: the cores this process may use, at most 4 (each band
    holds about `_CHUNK` samples of 60 bytes)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, min(4, cores or 1))


class _Levels:
    """The raster's mip levels (`_halve`), each made once when first asked for (thread-safe)."""

    def __init__(self, raster: np.ndarray):
        self._levels = [raster]
        self._lock = threading.Lock()

    def __getitem__(self, level: int) -> np.ndarray:
        with self._lock:
            while len(self._levels) <= level:
                self._levels.append(_halve(self._levels[-1]))
            return self._levels[level]


def _to_chart(g_inv: np.ndarray, u: np.ndarray, v: np.ndarray):
    """The photo points of the grid `v` (rows) x `u` (columns) on the chart (m), and whether
    the plane is in front of the camera there."""
    (a, b, c), (d, e, f), (g, h, k) = g_inv
    p2 = g * u[None, :] + (h * v + k)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (a * u[None, :] + (b * v + c)[:, None]) / p2
        y = (d * u[None, :] + (e * v + f)[:, None]) / p2
    # the camera's centre maps to the chart's side where the plane is in front: G's inverse
    # keeps the sign of the third coordinate positive for points in front (G = K [r1 r2 t]
    # with t_z > 0 for a chart in view)
    return x, y, p2 > 0


def _singular_values(a, b, c, d):
    """The singular values `(max, min)` of the 2x2 matrices `[[a, b], [c, d]]`."""
    s1 = np.hypot(a + d, b - c) / 2
    s2 = np.hypot(a - d, b + c) / 2
    return s1 + s2, np.abs(s1 - s2)


def _halve(img: np.ndarray) -> np.ndarray:
    """The next mip level: means of 2x2 blocks (an odd last row or column repeated)."""
    if img.shape[0] % 2:
        img = np.concatenate([img, img[-1:]], axis=0)
    if img.shape[1] % 2:
        img = np.concatenate([img, img[:, -1:]], axis=1)
    return (img[0::2, 0::2] + img[1::2, 0::2] + img[0::2, 1::2] + img[1::2, 1::2]) / 4


def _footprint(level_img, level, g_inv, u, v, s, px, py) -> np.ndarray:
    """The mean of `s x s` bilinear samples of `level_img` over each photo pixel of rows `v`
    (beyond the raster's edge, its edge texels: `scipy.ndimage.map_coordinates`'s `"nearest"`)."""
    w = u.size
    out = np.zeros((v.size, w), np.float32)
    offsets = (np.arange(s) + 0.5) / s - 0.5
    rows = max(1, _CHUNK // (w * s * s))
    scale = 2.0**level
    flat = np.ascontiguousarray(level_img, np.float32).reshape(-1)
    n_rows, n_cols = level_img.shape
    su = (u[None, :] + offsets[:, None]).reshape(-1)  # (s*w,) column-major in u
    for a in range(0, v.size, rows):
        vv = v[a : a + rows]
        sv = (vv[None, :] + offsets[:, None]).reshape(-1)
        x, y, _ = _to_chart(g_inv, su, sv)
        col, row = x / (px * scale) - 0.5, y / (py * scale) - 0.5
        c0, r0 = np.floor(col), np.floor(row)
        fc, fr = (col - c0).astype(np.float32), (row - r0).astype(np.float32)
        with np.errstate(invalid="ignore"):  # behind the camera (NaN): masked by the caller
            c0, r0 = c0.astype(np.intp), r0.astype(np.intp)
        c1 = np.clip(c0 + 1, 0, n_cols - 1)
        r1 = np.clip(r0 + 1, 0, n_rows - 1) * n_cols
        np.clip(c0, 0, n_cols - 1, out=c0)
        np.clip(r0, 0, n_rows - 1, out=r0)
        r0 *= n_cols
        top = flat[r0 + c0]
        top += fc * (flat[r0 + c1] - top)
        bottom = flat[r1 + c0]
        bottom += fc * (flat[r1 + c1] - bottom)
        top += fr * (bottom - top)
        # (s, rows, s, w): sub-row, row, sub-column, column
        out[a : a + rows] = top.reshape(s, vv.size, s, w).mean(axis=(0, 2), dtype=np.float64)
    return out
