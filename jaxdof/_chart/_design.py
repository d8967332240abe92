r"""The calibration chart: a thick dark frame, a ring of ArUco markers inside it, and a
dead-leaves texture within the ring.

The markers give the chart's pose in a sharp photo, the frame's outline in a blurred one
(`_detect`, `_geometry`); the texture, which has energy at every spatial frequency, is what the
fit measures the blur from and what the pose is refined against. The chart is a raster
of reflectances (linear light), a deterministic function of its parameters: the same parameters
give the same raster bit for bit (`numpy.random.default_rng(seed)` and OpenCV's integer disc
drawing), and the sidecar (`_files`) holds its SHA-256.
"""

from __future__ import annotations

import dataclasses
import weakref

import numpy as np
from jaxtyping import Float


DEFAULT_DICTIONARY = "DICT_4X4_250"
_INCH = 0.0254  # m
# Reflectances of the darkest and brightest print: clear of black crush and of clipping.
LOW, HIGH = 0.05, 0.95
# The marker's side as a fraction of the chart's short side, its white quiet zone as a fraction
# of its side, and the paper's unprinted margin (m).
MARKER_FRACTION = 1 / 8
_QUIET = 0.25
_PAPER_MARGIN = 0.005
# The frame's band and the white zone outside it, as fractions of the chart's short side: the
# band's outer edge stays a clean step under circles of confusion up to about the white zone's
# width plus the paper margin, and the band stays dark under circles up to its own width.
FRAME_FRACTION = 1 / 12
_FRAME_QUIET = 1 / 24
# Dead leaves: disc radii (raster pixels) with density ~ 1/r^3 from `_R_MIN` to the chart's short
# side times `_R_MAX`; painted until `_COVERED` of the raster is covered, then the gaps are
# filled by discs centred in them.
_R_MIN = 1.5
_R_MAX = 1 / 12
_COVERED = 0.995
_BATCH = 4096  # discs per batch, at least (one per 512 raster pixels)
_CELLS = 6  # a 4x4 marker's side in cells: 4 bits and a one-cell black border each side


@dataclasses.dataclass(frozen=True, eq=False)
class Chart:
    """A calibration chart's design. Lengths in metres, chart coordinates: `x` right, `y` down,
    origin at the chart's top-left corner (the raster's top-left pixel's outer corner).

    **Fields:**

    - `width_m`, `height_m`: the chart's size (m), a whole number of raster pixels.
    - `dictionary`: the OpenCV ArUco dictionary of the markers, e.g. `"DICT_4X4_250"`.
    - `markers`: marker id -> its 4 corners `(4, 2)` (m), in OpenCV's order (top-left,
      top-right, bottom-right, bottom-left of the upright marker).
    - `seed`: the texture's and the marker ids' random seed.
    - `texture_px`: the raster's `(width, height)` in pixels.
    - `monitor`: a chart shown on a screen (emissive, no print margin) rather than printed.
    - `dpi`: raster pixels per inch (for a screen, its pixel density).
    - `marker_fraction`: the markers' side asked for, over the chart's short side.
    - `frame`: the dark frame's outer corners `(4, 2)` (m; top-left, top-right, bottom-right,
      bottom-left), or `None` for a chart without one (a sidecar of an older version).
    - `frame_width_m`: the frame band's width (m).
    """

    width_m: float
    height_m: float
    dictionary: str
    markers: dict[int, np.ndarray]
    seed: int
    texture_px: tuple[int, int]
    monitor: bool = False
    dpi: float = 300.0
    marker_fraction: float = MARKER_FRACTION
    frame: np.ndarray | None = None
    frame_width_m: float = 0.0

    @property
    def pitch(self) -> tuple[float, float]:
        """The raster's pixel size `(x, y)` (m)."""
        return self.width_m / self.texture_px[0], self.height_m / self.texture_px[1]

    def marker_points(self, ids) -> np.ndarray:
        """The corners `(n, 4, 2)` (m) of the markers `ids`, in the order given."""
        pts = [self.markers[int(i)] for i in ids]
        return np.stack(pts).astype(np.float64) if pts else np.zeros((0, 4, 2))

    @property
    def corners(self) -> np.ndarray:
        """The chart's (the raster's) corners `(4, 2)` (m), clockwise from the top-left."""
        w, h = self.width_m, self.height_m
        return np.array([[0, 0], [w, 0], [w, h], [0, h]], np.float64)


def make_chart(
    *,
    width_m: float | int = 0.297,
    height_m: float | int = 0.210,
    dpi: float | int = 300,
    seed: int = 0,
    monitor: bool = False,
    screen_px: tuple[int, int] | None = None,
    screen_width_m: float | int | None = None,
    dictionary: str = DEFAULT_DICTIONARY,
    marker_fraction: float | int = MARKER_FRACTION,
) -> tuple[Chart, Float[np.ndarray, "h w"]]:
    r"""Design a calibration chart and draw its raster.

    **Arguments:**

    - `width_m`, `height_m`: the printed chart's size (m; default A4 landscape), rounded to
      whole raster pixels.
    - `dpi`: the raster's pixels per inch when printed.
    - `seed`: the texture's and the marker ids' seed.
    - `monitor`: a chart for a screen: the raster is `screen_px` (width, height) pixels,
      `screen_width_m` (m) wide (square pixels), without a print margin; `width_m`, `height_m`
      and `dpi` are then not used.
    - `dictionary`: the OpenCV ArUco dictionary (a 4x4 one: `DICT_4X4_50` ... `DICT_4X4_1000`).
    - `marker_fraction`: each marker's side over the chart's short side; larger markers are
      found under stronger defocus.

    **Returns:** `(chart, raster)`: the `Chart` and its reflectance (linear light), float32
    `(height, width)` in `[0.05, 0.95]`: for a screen, the emitted linear light.

    **Layout.** From the outside in: a 5 mm unprinted margin on paper, a white zone of 1/24 of
    the short side, a black frame 1/12 of the short side wide (its outer edge and corners are
    found in photos too blurred for the markers' codes), a ring of markers (ids drawn from the
    dictionary by `seed`, so a chart of another seed is told apart) each in a white quiet zone
    of a quarter of its side; everything else is a dead-leaves texture: opaque discs of uniform
    random grey, radius density `p(r) ~ 1/r^3` from 1.5 raster pixels to 1/12 of the short side,
    stacked until they cover the chart. The model is scale invariant, with a power spectrum
    `~ 1/f^2` at every frequency up to the raster's Nyquist (Lee, Mumford & Huang, "Occlusion
    models for natural images", IJCV 2001; Cao, Guichard & Hornung, "Dead leaves model for
    measuring texture quality", SPIE 2010), so blur is measured at every scale.

    The raster's values are 16-bit sRGB codes decoded to linear light, so the PNG `write_chart`
    writes (16-bit sRGB, as a printer or a screen takes it) reads back to the same raster.
    """
    cv2 = _cv2()
    if monitor:
        nx, ny, pitch, margin = _screen(screen_px, screen_width_m)
        dpi = _INCH / pitch
    else:
        nx, ny, pitch, margin = _paper(width_m, height_m, dpi)
    side = _marker_side(nx, ny, dictionary, marker_fraction)
    band = max(1, round(min(nx, ny) * FRAME_FRACTION))
    outer = margin + max(1, round(min(nx, ny) * _FRAME_QUIET))  # the frame's outer edge (px)
    aruco = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    rng = np.random.default_rng(seed)
    places = _ring(nx, ny, side, outer + band)
    if places[-1][1] <= places[0][1] + side or places[-1][0] <= places[0][0] + side:
        raise ValueError(
            f"a {nx}x{ny}-pixel raster leaves no room inside its frame for markers of {side} px: "
            "lower marker_fraction"
        )
    n_ids = int(aruco.bytesList.shape[0])
    if len(places) > n_ids:
        raise ValueError(f"{dictionary} has {n_ids} markers, the layout needs {len(places)}")
    ids = sorted(int(i) for i in rng.choice(n_ids, size=len(places), replace=False))
    codes = _dead_leaves(rng, nx, ny)
    _draw_frame(codes, margin, outer, band)
    markers = _draw_markers(codes, aruco, ids, places, side, pitch)
    chart = Chart(
        width_m=nx * pitch,
        height_m=ny * pitch,
        dictionary=dictionary,
        markers=markers,
        seed=int(seed),
        texture_px=(nx, ny),
        monitor=bool(monitor),
        dpi=float(dpi),
        marker_fraction=float(marker_fraction),
        frame=np.array(
            [(outer, outer), (nx - outer, outer), (nx - outer, ny - outer), (outer, ny - outer)],
            np.float64,
        )
        * pitch,
        frame_width_m=band * pitch,
    )
    raster = decode(codes)
    remember(chart, raster)
    return chart, raster


def _screen(screen_px, screen_width_m) -> tuple[int, int, float, int]:
    """A monitor chart's raster `(nx, ny)`, its pitch (m) and margin (none)."""
    if screen_px is None or screen_width_m is None:
        raise ValueError(
            "a monitor chart needs screen_px=(width, height) in pixels and screen_width_m"
        )
    nx, ny = (int(v) for v in screen_px)
    if nx < 64 or ny < 64 or not screen_width_m > 0:
        raise ValueError(f"bad screen: {screen_px=} (>= 64 px each), {screen_width_m=} m")
    return nx, ny, float(screen_width_m) / nx, 0


def _paper(width_m, height_m, dpi) -> tuple[int, int, float, int]:
    """A printed chart's raster `(nx, ny)`, its pitch (m) and its unprinted margin (px)."""
    if not (width_m > 0 and height_m > 0 and dpi > 0):
        raise ValueError(
            f"the chart's size and dpi must be positive, got {width_m=}, {height_m=}, {dpi=}"
        )
    pitch = _INCH / dpi
    return round(width_m / pitch), round(height_m / pitch), pitch, round(_PAPER_MARGIN / pitch)


def _marker_side(nx: int, ny: int, dictionary: str, marker_fraction) -> int:
    """The markers' side (raster px, whole cells) on an `nx x ny` raster; `ValueError` for a
    dictionary that is not a 4x4 ArUco one, a fraction out of range or markers too small."""
    if not hasattr(_cv2().aruco, dictionary) or not dictionary.startswith("DICT_4X4"):
        raise ValueError(f"dictionary must be an OpenCV 4x4 ArUco dictionary, got {dictionary!r}")
    if not 0.05 <= marker_fraction <= 0.3:
        raise ValueError(f"marker_fraction must be within [0.05, 0.3], got {marker_fraction}")
    side = int(min(nx, ny) * marker_fraction) // _CELLS * _CELLS
    if side < 4 * _CELLS:
        raise ValueError(
            f"a {nx}x{ny}-pixel raster makes markers of {side} px: raise dpi or the chart's size"
        )
    return side


def _draw_markers(codes: np.ndarray, aruco, ids, places, side: int, pitch: float) -> dict:
    """Into the raster's codes: marker `ids[k]` (`side` px) at `places[k]` (its top-left pixel)
    in a white quiet zone; returns each marker's corners on the chart (m)."""
    cv2 = _cv2()
    white, black = (encode(v) for v in (HIGH, LOW))
    quiet = round(side * _QUIET)
    markers = {}
    for i, (x0, y0) in zip(ids, places):
        codes[y0 - quiet : y0 + side + quiet, x0 - quiet : x0 + side + quiet] = white
        bits = cv2.aruco.generateImageMarker(aruco, i, side, borderBits=1)
        codes[y0 : y0 + side, x0 : x0 + side] = np.where(bits > 127, white, black)
        corners = np.array([(x0, y0), (x0 + side, y0), (x0 + side, y0 + side), (x0, y0 + side)])
        markers[i] = corners * pitch
    return markers


def _draw_frame(codes: np.ndarray, margin: int, outer: int, band: int) -> None:
    """Into the raster's codes `(ny, nx)`: the white margin and zone out to `outer` px, then the
    black frame `band` px wide."""
    ny, nx = codes.shape
    white, black = (encode(v) for v in (HIGH, LOW))
    if margin:
        codes[:margin], codes[-margin:], codes[:, :margin], codes[:, -margin:] = (white,) * 4
    codes[margin:outer, margin : nx - margin] = white
    codes[ny - outer : ny - margin, margin : nx - margin] = white
    codes[margin : ny - margin, margin:outer] = white
    codes[margin : ny - margin, nx - outer : nx - margin] = white
    inner = outer + band
    codes[outer:inner, outer : nx - outer] = black
    codes[ny - inner : ny - outer, outer : nx - outer] = black
    codes[outer : ny - outer, outer:inner] = black
    codes[outer : ny - outer, nx - inner : nx - outer] = black


# Each chart's raster, while the chart lives: `make_chart` and `read_chart` put it here, so that a
# photo can be matched against it (`_detect`) without drawing it again.
_RASTERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def remember(chart: Chart, raster: np.ndarray) -> None:
    _RASTERS[chart] = raster


def raster_of(chart: Chart) -> np.ndarray:
    """The raster of `chart`: the one it was made or read with, else drawn again from its
    parameters (deterministic; seconds at 300 dpi)."""
    raster = _RASTERS.get(chart)
    if raster is None:
        nx, ny = chart.texture_px
        again, raster = make_chart(
            width_m=chart.width_m,
            height_m=chart.height_m,
            dpi=chart.dpi,
            seed=chart.seed,
            monitor=chart.monitor,
            screen_px=(nx, ny) if chart.monitor else None,
            screen_width_m=chart.width_m if chart.monitor else None,
            dictionary=chart.dictionary,
            marker_fraction=chart.marker_fraction,
        )
        if again.texture_px != chart.texture_px or again.markers.keys() != chart.markers.keys():
            raise ValueError("the chart's raster cannot be drawn again from its parameters")
        remember(chart, raster)
    return raster


def _cv2():
    """OpenCV, imported when a chart is made or found (it takes a while to import)."""
    import cv2

    return cv2


def encode(reflectance):
    """16-bit sRGB codes of linear reflectances (`decode`'s inverse on its codes)."""
    from .._io import linear_to_srgb

    return np.round(linear_to_srgb(reflectance) * 65535).astype(np.uint16)


def decode(codes: np.ndarray) -> np.ndarray:
    """16-bit sRGB codes to linear light, float32 (one float64 decode per code value)."""
    from .._io import srgb_to_linear

    levels = srgb_to_linear(np.arange(65536) / 65535).astype(np.float32)
    return levels[codes]


def _ring(nx: int, ny: int, side: int, inset: int) -> list[tuple[int, int]]:
    """Top-left corners (raster px) of markers in a ring `inset` pixels inside the chart's
    edges: a marker in each corner and more spaced about one marker's cell apart along each
    side."""
    quiet = round(side * _QUIET)
    cell = side + 2 * quiet
    lo = inset + quiet
    xs = _spread(lo, nx - lo - side, cell)
    ys = _spread(lo, ny - lo - side, cell)
    top = [(x, ys[0]) for x in xs]
    bottom = [(x, ys[-1]) for x in xs]
    sides = [(x, y) for y in ys[1:-1] for x in (xs[0], xs[-1])]
    return top + sides + bottom


def _spread(a: int, b: int, cell: int) -> list[int]:
    """Positions from `a` to `b` (inclusive) about two cells apart: at least the two ends."""
    n = max(2, round((b - a) / (2 * cell)) + 1)
    return [round(a + (b - a) * k / (n - 1)) for k in range(n)]


def _dead_leaves(rng: np.random.Generator, nx: int, ny: int) -> np.ndarray:
    """A dead-leaves raster of 16-bit sRGB codes `(ny, nx)`: discs of uniform random reflectance
    in `[LOW, HIGH]`, the first drawn on top, radius density `~ 1/r^3`."""
    cv2 = _cv2()
    r_min, r_max = _R_MIN, max(_R_MIN * 2, min(nx, ny) * _R_MAX)
    a, b = r_min**-2, r_max**-2
    codes = np.zeros((ny, nx), np.uint16)
    free = np.ones((ny, nx), bool)  # not yet covered by a disc
    layer = np.zeros((ny, nx), np.uint16)
    mask = np.zeros((ny, nx), np.uint8)
    shift = 4  # OpenCV's fractional bits of centres and radii
    batch = max(_BATCH, nx * ny // 512)
    while True:
        left = int(free.sum())
        if left == 0:
            return codes
        radius = (a - rng.uniform(size=batch) * (a - b)) ** -0.5
        grey = encode(rng.uniform(LOW, HIGH, size=batch))
        if left > (1 - _COVERED) * nx * ny:
            centre = rng.uniform(0, 1, size=(batch, 2)) * (nx, ny)
        else:  # the last gaps: discs centred in them (uncovered pixels in raster order)
            rows, cols = np.nonzero(free)
            pick = rng.integers(0, rows.size, size=batch)
            centre = np.stack([cols[pick] + 0.5, rows[pick] + 0.5], axis=1)
        layer[:] = 0
        mask[:] = 0
        fixed = np.round(centre * 2**shift - 2 ** (shift - 1)).astype(np.int64)
        rad = np.round(radius * 2**shift).astype(np.int64)
        for k in range(batch - 1, -1, -1):  # the batch's first disc ends on top
            c = (int(fixed[k, 0]), int(fixed[k, 1]))
            cv2.circle(layer, c, int(rad[k]), int(grey[k]), -1, cv2.LINE_8, shift)
            cv2.circle(mask, c, int(rad[k]), 1, -1, cv2.LINE_8, shift)
        new = free & (mask > 0)
        codes[new] = layer[new]
        free &= ~new
