"""The spoiled captures of `captures.py` (issue 34, part 5): each default-study scene's inputs
spoiled as a real capture spoils them, one way at a time, and the default fit of each.

- The conditions (`CONDITIONS`) and the lens fitted per scene (`CAPTURE_LENSES`).
- Photos re-rendered with the camera turned (`SHIFT_PX`) or with a narrower field of view
  (`MAGNIFICATION`): `posed_photo`, Mitsuba's thin lens or the aperture sum of
  `_raytraced_scenes.render_aperture_sum`, posed; cached beside the other renders.
- The spoils of the depth and the photo that need no render (`holes_depth`, `coarse_depth`,
  `camera_jpeg`, `radial_falloff`, `noisy`), seeded per scene and condition.
- `measured_motion`: the shift and scale of a re-rendered photo against the unspoiled one.
- `capture_fit`: `fit_lens(image, depth, photo, init)` with nothing else, judged as
  `raytraced_default.py` judges it (`_raytraced_fits.default_record`).

Mitsuba is imported only when something has to be rendered.
"""

from __future__ import annotations

import hashlib
import math
import time
import traceback
import zlib

import jax


jax.config.update(
    "jax_enable_x64", True
)  # as the modules below; the study sets the fit's precision

import numpy as np  # noqa: E402
from _common import CACHE as _CACHE_ROOT, FITS  # noqa: E402
from _raytraced_fits import default_init, default_record, fingerprint, no_paths  # noqa: E402
from _raytraced_scenes import (  # noqa: E402
    APERTURE_VIEWS,
    DEFAULT_SCENES,
    F_PX,
    FOV_X,
    LIGHTFIELD_GRID,
    LIGHTFIELD_SPP,
    SPP_THIN,
    H,
    W,
    _sensor,
    aperture_points,
    cached,
    default_inputs,
    mitsuba,
    pinhole_and_depth,
    scene_shapes,
    vignetting,
)

import jaxdof  # noqa: E402
from jaxdof._io import linear_to_srgb, read_image  # noqa: E402
from jaxdof.internal import release_compiled_code  # noqa: E402


FIT_CACHE = _CACHE_ROOT / "captures"

CONDITIONS = {
    "clean": "the study's inputs as rendered",
    "holes": "depth: 3 % of pixels NaN in random blobs, NaN on a 1-2 px band along every depth "
    "edge, and 0.1 % of pixels 0 (isolated)",
    "coarse-depth": "depth 4x coarser (4x4 blocks averaged in inverse depth), 1 % multiplicative "
    "Gaussian noise, passed at its coarse shape",
    "shift": "photo re-rendered with the camera turned by the angle of (0.4, -0.6) px",
    "breathing": "photo re-rendered with tan(fov/2) / 1.01 (image scale 1.01x)",
    "exposure": "photo x 0.85",
    "jpeg": "photo to sRGB 8 bit, Pillow JPEG quality 90, 4:2:0, read back to linear",
    "vignetting": "photo x (1 - 0.25 (rho / rho_corner)^2)",
    "noise": "photo + Gaussian noise, sigma 2 % of its mean",
}

# One lens per scene (the study's budget: ~100 fits on 2 shared cores). (0.06, 3.0): the middle
# blur scale of `DEFAULT_LENSES` (K 3.5 px); landscape focused at infinity (an aperture sum);
# fgbg focused on its foreground card, the background blurred (K 9.8 px).
CAPTURE_LENSES = {name: (0.06, 3.0) for name in DEFAULT_SCENES} | {
    "landscape": (0.1, math.inf),
    "fgbg": (0.1, 1.8),
}

SHIFT_PX = (0.4, -0.6)  # (columns, rows) the photo's content moves at the frame's centre (px)
MAGNIFICATION = 1.01  # the photo's image scale against the all-in-focus image's
HOLE_SHARE = 0.03  # the depth's NaN blobs, share of pixels
ZERO_SHARE = 0.001  # the depth's isolated zeros, share of pixels
COARSE = 4  # the depth sensor's pixel, in image pixels per side
DEPTH_NOISE = 0.01  # the coarse depth's multiplicative noise (sigma)
EXPOSURE = 0.85
JPEG_QUALITY = 90
FALLOFF = 0.25  # vignetting: the darkening in the corners
NOISE = 0.02  # sigma of the photo's noise, share of its mean


def seed_of(scene: str, condition: str) -> int:
    """A seed per scene and condition, the same on every run and machine."""
    return zlib.crc32(f"{scene}/{condition}".encode())


# ----------------------------------------------------------------------------- posed renders


def _rig(mi, shift_px):
    """The camera's turn as a transform: looking at `(shift / f_px, 1)`, so that the content at
    the frame's centre moves by `shift` px (columns right, rows down). Mitsuba's camera has +x
    to the image's left and +y up: turning toward +x moves the content right, toward +y down."""
    sx, sy = shift_px
    return mi.ScalarTransform4f().look_at(
        origin=[0, 0, 0], target=[sx / F_PX, sy / F_PX, 1], up=[0, 1, 0]
    )


def _fov(magnification: float) -> float:
    """The horizontal field of view (degrees) whose image scale is `magnification` times `FOV_X`'s."""
    return math.degrees(2 * math.atan(math.tan(math.radians(FOV_X) / 2) / magnification))


def render_thin_posed(geometry, a, d, shift_px=(0.0, 0.0), magnification=1.0, seed=0):
    """Mitsuba's thin lens (`render_scene`'s photo) with the camera turned about its centre by
    `_rig(shift_px)` and the field of view narrowed by `magnification`."""
    mi = mitsuba()
    sensor = _sensor(mi, "thinlens", SPP_THIN, a, d)
    sensor["to_world"] = _rig(mi, shift_px)
    sensor["fov"] = _fov(magnification)
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 1},
        "sensor": sensor,
        **scene_shapes(mi, geometry),
    }
    return np.array(mi.render(mi.load_dict(scene), seed=seed), dtype=np.float32)


def render_sum_posed(geometry, shape, a, d, shift_px=(0.0, 0.0), magnification=1.0, seed=0):
    """`render_aperture_sum` with its rig turned by `_rig(shift_px)` (every view's eye and
    direction with it) and the field of view narrowed by `magnification` (the principal-point
    offsets follow the longer focal length in pixels). At no turn and scale 1 it makes the same
    images as `render_aperture_sum` (same views, same seeds)."""
    mi = mitsuba()
    grid = shape == "grid"
    sensor = _sensor(mi, "perspective", LIGHTFIELD_SPP if grid else 1)
    sensor["fov"] = _fov(magnification)
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": 1},
            "sensor": sensor,
            **scene_shapes(mi, geometry),
        }
    )
    params = mi.traverse(scene)
    T = mi.ScalarTransform4f
    rig = _rig(mi, shift_px)
    f_px = F_PX * magnification
    power = 0.0 if math.isinf(d) else 1.0 / d
    points = aperture_points(shape, a, LIGHTFIELD_GRID**2 if grid else APERTURE_VIEWS)
    acc = np.zeros((H, W, 3))
    for k, (x, y) in enumerate(points):
        x, y = float(x), float(y)
        params["sensor.to_world"] = rig @ T().translate([x, y, 0])
        params["sensor.principal_point_offset_x"] = f_px * x * power / W
        params["sensor.principal_point_offset_y"] = f_px * y * power / H
        params.update()
        acc += np.asarray(mi.render(scene, seed=seed * len(points) + k), np.float64)
    return (acc / len(points)).astype(np.float32)


def posed_photo(scene: str, a: float, d: float, shift_px=(0.0, 0.0), magnification=1.0):
    """`(photo, render seconds)` of a default-study scene and lens with the camera turned or its
    field of view narrowed (cached as `_raytraced_scenes.photo` caches the unposed ones); the
    `vignette` scene's falloff is the camera's, applied after."""
    geometry, kind = DEFAULT_SCENES[scene]
    pose = f"_turn{shift_px[0]:g}_{shift_px[1]:g}" if any(shift_px) else ""
    pose += f"_mag{magnification:g}" if magnification != 1.0 else ""
    if kind in ("pentagon", "lightfield") or (kind == "landscape" and math.isinf(d)):
        shape = {"pentagon": "pentagon", "lightfield": "grid"}.get(kind, "disc")
        return cached(
            f"{geometry}_sum_{shape}_A{a}_df{d}{pose}",
            lambda: render_sum_posed(geometry, shape, a, d, shift_px, magnification),
        )
    img, secs = cached(
        f"{geometry}_thin_A{a}_df{d}{pose}",
        lambda: render_thin_posed(geometry, a, d, shift_px, magnification),
    )
    return (img * vignetting()[..., None], secs) if kind == "vignette" else (img, secs)


def render_captures(scenes) -> dict:
    """Render (or load) every photo the study reads; `{scene: seconds}` of its new renders as
    they were made (cached renders keep theirs)."""
    secs = {}
    for scene in scenes:
        a, d = CAPTURE_LENSES[scene]
        pinhole_and_depth(DEFAULT_SCENES[scene][0])
        secs[scene] = posed_photo(scene, a, d, shift_px=SHIFT_PX)[1]
        secs[scene] += posed_photo(scene, a, d, magnification=MAGNIFICATION)[1]
    return secs


# ----------------------------------------------------------------------------- spoils


def measured_motion(ref, moved, margin: int = 16) -> tuple[float, float, float]:
    """`(columns, rows, scale)`: the shift (px, at the frame's centre) and the magnification
    about the centre that map `ref` onto `moved` best (least squares on the luminance over the
    pixels `margin` px or more inside the frame, cubic-spline resampling)."""
    from scipy.ndimage import map_coordinates
    from scipy.optimize import least_squares

    ref_l, moved_l = np.asarray(ref, np.float64).mean(-1), np.asarray(moved, np.float64).mean(-1)
    rows, cols = np.mgrid[margin : H - margin, margin : W - margin].astype(np.float64)
    cy, cx = H / 2 - 0.5, W / 2 - 0.5  # the frame's centre in pixel-centre coordinates
    target = moved_l[margin : H - margin, margin : W - margin].ravel()

    def residual(p):
        sx, sy, m = p
        r, c = cy + (rows - cy - sy) / m, cx + (cols - cx - sx) / m
        return map_coordinates(ref_l, [r.ravel(), c.ravel()], order=3) - target

    sx, sy, m = least_squares(residual, [0.0, 0.0, 1.0], x_scale=[1.0, 1.0, 0.01]).x
    return float(sx), float(sy), float(m)


def holes_depth(z, seed: int):
    """`(depth, counts)`: `z` with NaN in random blobs over `HOLE_SHARE` of it (smooth noise,
    sigma 3 px, above its quantile), NaN on a 1-2 px band along every depth edge (the far side's
    pixel of every edge of `jaxdof.depth_edges`, and the near side's at random half the time: what
    a depth sensor loses at a discontinuity) and 0 at `ZERO_SHARE` of the other pixels."""
    from scipy.ndimage import gaussian_filter, minimum_filter

    rng = np.random.default_rng(seed)
    noise = gaussian_filter(rng.normal(size=z.shape), 3.0)
    blobs = noise > np.quantile(noise, 1 - HOLE_SHARE)
    edges = jaxdof.depth_edges(z)
    # the far side: an edge pixel with a nearer edge pixel among its 4-neighbours
    nearest = minimum_filter(
        np.where(edges, z, np.inf), footprint=[[0, 1, 0], [1, 0, 1], [0, 1, 0]], mode="nearest"
    )
    far = edges & (nearest < z)
    band = far | (edges & ~far & (rng.uniform(size=z.shape) < 0.5))
    out = np.array(z, np.float32)
    out[blobs | band] = np.nan
    free = np.flatnonzero(~(blobs | band))
    zeros = rng.choice(free, size=max(1, round(ZERO_SHARE * z.size)), replace=False)
    out.flat[zeros] = 0.0
    counts = dict(blobs=int(blobs.sum()), band=int((band & ~blobs).sum()), zeros=len(zeros))
    return out, counts


def coarse_depth(z, seed: int):
    """`z` as a depth sensor `COARSE` times coarser sees it: each `COARSE` x `COARSE` block's
    mean in inverse depth (infinite depths count as 0), times `1 + DEPTH_NOISE n`, n standard
    normal; shape `(H / COARSE, W / COARSE)`."""
    rng = np.random.default_rng(seed)
    h, w = z.shape
    inv = (1 / np.asarray(z, np.float64)).reshape(h // COARSE, COARSE, w // COARSE, COARSE)
    with np.errstate(divide="ignore"):
        coarse = 1 / inv.mean((1, 3))
    return (coarse * (1 + DEPTH_NOISE * rng.normal(size=coarse.shape))).astype(np.float32)


def camera_jpeg(photo, path):
    """`(photo, clipped share)`: `photo` encoded to sRGB in 8 bits (clipped to [0, 1]), written
    to `path` by Pillow as JPEG (quality `JPEG_QUALITY`, 4:2:0 chroma subsampling) and read back
    with `jaxdof._io.read_image` (decoded from sRGB to linear light)."""
    from PIL import Image

    codes = np.round(255 * linear_to_srgb(photo)).astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(codes, "RGB").save(path, "JPEG", quality=JPEG_QUALITY, subsampling=2)
    return read_image(str(path)).array, float(np.mean(np.asarray(photo) > 1))


def radial_falloff() -> np.ndarray:
    """`1 - FALLOFF (rho / rho_corner)^2`, rho the distance of a pixel's centre from the frame's
    centre: 1 there, `1 - FALLOFF` at the corner pixels' centres."""
    x = np.arange(W) + 0.5 - W / 2
    y = np.arange(H) + 0.5 - H / 2
    rho2 = x[None, :] ** 2 + y[:, None] ** 2
    return (1 - FALLOFF * rho2 / rho2.max()).astype(np.float32)


def noisy(photo, seed: int):
    """`photo` plus Gaussian noise of sigma `NOISE` times its mean (every pixel and channel)."""
    rng = np.random.default_rng(seed)
    return photo + NOISE * float(np.mean(photo)) * rng.normal(size=photo.shape)


def spoiled_inputs(condition: str, scene: str, a: float, d: float):
    """`(image, depth, photo, what)`: the scene's inputs spoiled by `condition` (float32; the
    depth of `coarse depth` at its coarse shape) and a line saying what the spoil did."""
    image, z, photo = default_inputs(scene, a, d)
    seed = seed_of(scene, condition)
    depth, what = z, ""
    if condition == "holes":
        depth, n = holes_depth(z, seed)
        what = f"{n['blobs']} px NaN in blobs, {n['band']} more on edge bands, {n['zeros']} zeros"
    elif condition == "coarse-depth":
        depth = coarse_depth(z, seed)
        what = f"depth {depth.shape[1]}x{depth.shape[0]}"
    elif condition in ("shift", "breathing"):
        shift, mag = (SHIFT_PX, 1.0) if condition == "shift" else ((0.0, 0.0), MAGNIFICATION)
        moved = posed_photo(scene, a, d, shift_px=shift, magnification=mag)[0]
        sx, sy, m = measured_motion(photo, moved)
        photo, what = (
            moved,
            f"measured on the photo: shift ({sx:+.3f}, {sy:+.3f}) px, scale {m:.4f}",
        )
    elif condition == "exposure":
        photo = photo * EXPOSURE
    elif condition == "jpeg":
        path = FIT_CACHE / "jpeg" / f"{scene}_A{a}_df{d}.jpg"
        decoded, clipped = camera_jpeg(photo, path)
        rms = float(np.sqrt(np.mean((decoded - np.clip(photo, 0, 1)) ** 2)))
        what = f"{clipped:.2%} of values clipped at 1; rms error {rms / np.mean(photo):.2%} of the mean"
        photo = decoded
    elif condition == "vignetting":
        photo = photo * radial_falloff()[..., None]
    elif condition == "noise":
        photo = noisy(photo, seed)
    elif condition != "clean":
        raise ValueError(f"{condition=}; one of {list(CONDITIONS)}")
    return image, depth, photo, what


# ----------------------------------------------------------------------------- the fit


def capture_fingerprint() -> str:
    """12 hex digits of the library's source, the default study's scene and fit code, and this
    file: the fits are cached per fingerprint."""
    h = hashlib.sha256(fingerprint().encode())
    h.update((FITS / "_captures_scenes.py").read_bytes())
    return h.hexdigest()[:12]


def _plain(x):
    """JSON-ready: numpy scalars and arrays as Python numbers and lists, recursively."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, (np.ndarray, np.generic, jax.Array)):
        a = np.asarray(x)
        return a.item() if a.ndim == 0 else a.tolist()
    return x


def capture_fit(condition: str, scene: str) -> dict:
    """`fit_lens(image, depth, photo, init)` with nothing else passed, on one scene's inputs
    spoiled by `condition`; the init as `raytraced_default.py`'s (`default_init`). An exception is
    caught and recorded (`raised`)."""
    a, d = CAPTURE_LENSES[scene]
    image, depth, photo, what = spoiled_inputs(condition, scene, a, d)
    z_true = default_inputs(scene, a, d)[1]  # the truth's nearest depth judges focus at infinity
    dtype = jnp_dtype()
    image, depth, photo = (np.asarray(x, dtype) for x in (image, depth, photo))
    head = dict(condition=condition, scene=scene, a=a, d=d, spoil=what)
    release_compiled_code()  # a long study would reach the kernel's limit of memory maps
    t0 = time.perf_counter()
    try:
        res = jaxdof.fit_lens(image, depth, photo, default_init(a, d))
        jax.block_until_ready(res.lenses.focus_distance)
    except Exception as err:
        first = (str(err).splitlines() or [""])[0][:300]
        return dict(
            **head,
            seconds=time.perf_counter() - t0,
            exception=no_paths(f"{type(err).__name__}: {first}"),
            traceback=[no_paths(line) for line in traceback.format_exc().splitlines()][-25:],
        )
    seconds = time.perf_counter() - t0
    rec = default_record(res, a, d, z_true)
    rec.pop("result")  # the parts kept below; the covariance and per-target copies are not
    return dict(
        **head,
        seconds=seconds,
        **rec,
        stderr={k: _plain(np.asarray(v).reshape(-1)[0]) for k, v in res.stderr.items()},
        stderr_kind=res.stderr_kind,
        treatment=str(res.treatment),
        treatment_choices=None if res.treatment is None else _plain(res.treatment.to_dict()),
        nuisances=_plain(res.nuisances),
    )


def jnp_dtype():
    """float64 where `jax_enable_x64` is on, else float32: the inputs in the run's precision."""
    return np.float64 if jax.config.read("jax_enable_x64") else np.float32


def verdict(rec) -> str:
    """`raised` (an exception), `within` (focus and K inside the goals), `flagged` (outside,
    success=False), `silent` (outside, success=True and the focus power or K beyond 3 reported
    standard errors), or `covered` (outside, success=True, both within 3 standard errors)."""
    if "exception" in rec:
        return "raised"
    if rec["within"]:
        return "within"
    if not rec["success"]:
        return "flagged"
    return "silent" if rec["silent"] else "covered"
