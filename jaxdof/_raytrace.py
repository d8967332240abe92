"""Bridges to ray tracers' thin-lens cameras (Mitsuba 3, PBRT): their depth output and their lens.

A ray tracer's thin lens is given by an aperture radius `A` and a focus distance `d_f` in scene
units, with the field of view of a pinhole camera; it has no focal length or sensor. These helpers
convert its per-pixel ray distance to the z-depth `jaxdof` expects and build the `ThinLens` that
blurs exactly as that camera does, so ray-traced images can serve as ground truth.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ._custom_types import AnyFloatLike, Depth
from ._lens import ThinLens


def _focal_length_px(fov_x_deg: float, width: int) -> float:
    if not (0.0 < fov_x_deg < 180.0):
        raise ValueError(f"fov_x_deg must be in (0, 180) degrees, got {fov_x_deg}")
    return (width / 2) / math.tan(math.radians(fov_x_deg) / 2)


def ray_distance_to_z(distance: AnyFloatLike, *, fov_x_deg: float, near_clip: float = 0.0) -> Depth:
    r"""Distance along each pixel's central ray -> z-depth along the optical axis.

    **Arguments:**

    - `distance`: `(H, W)` distance `t` from the ray origin to the first hit, per pixel, sampled
      through the pixel centre (scene units; `inf` for no hit stays `inf`).
    - `fov_x_deg`: horizontal field of view in degrees (Mitsuba's `fov` with `fov_axis="x"`).
    - `near_clip`: the camera's near clip distance. Mitsuba's perspective and thin-lens cameras
      start each ray on the near plane, so their `depth` AOV is `t_hit - near_clip / cos(theta)`;
      pass the sensor's `near_clip` (Mitsuba's default is `0.01`). Use `0` for a renderer whose rays
      start at the centre of projection.

    **Returns:** `(H, W)` z-depth `z` (scene units), same dtype as `distance`.

    **Derivation.** With square pixels and `f_px = (W/2) / tan(fov_x/2)` the focal length in
    pixels, the centre of pixel `(i, j)` (row, column) sees the direction
    `(x_n, y_n, 1)` with `x_n = (j + 1/2 - W/2) / f_px` and `y_n = (i + 1/2 - H/2) / f_px`, which
    makes the angle `theta` with the optical axis, `cos(theta) = 1 / sqrt(1 + x_n^2 + y_n^2)`. A hit
    at true distance `t_hit` from the centre of projection has `z = t_hit cos(theta)`; a ray that
    starts on the near plane `z = near_clip` has travelled `near_clip / cos(theta)` less, so
    `z = t cos(theta) + near_clip`. The sign of `x_n`, `y_n` does not matter.

    The conversion is exact at pixel centres only: a depth averaged over the pixel's area (the AOV
    with many jittered samples and a box filter) mixes depths at occlusion edges. Render the depth
    with one sample at the pixel centre (Mitsuba's `stratified` sampler, `jitter=False`, 1 spp).
    """
    distance = jnp.asarray(distance)
    if distance.ndim != 2:
        raise ValueError(f"distance must be an (H, W) map, got shape {distance.shape}")
    if not jnp.issubdtype(distance.dtype, jnp.floating):
        raise ValueError(f"distance must be floating point, got dtype {distance.dtype}")
    h, w = distance.shape
    f_px = _focal_length_px(fov_x_deg, w)
    # Geometry in float64 numpy (exact to the last bit of the output dtype), cast once.
    xn = (np.arange(w) + 0.5 - w / 2) / f_px
    yn = (np.arange(h) + 0.5 - h / 2) / f_px
    cos_theta = 1.0 / np.sqrt(1.0 + xn[None, :] ** 2 + yn[:, None] ** 2)
    cos_theta = jnp.asarray(cos_theta, dtype=distance.dtype)
    return distance * cos_theta + jnp.asarray(near_clip, dtype=distance.dtype)


def lens_from_raytracer(
    aperture_radius: float,
    focus_distance: float,
    *,
    fov_x_deg: float,
    image_width: int,
    focal_length: float = 0.05,
) -> ThinLens:
    r"""The `ThinLens` that blurs exactly as a ray tracer's thin-lens camera (Mitsuba, PBRT).

    **Arguments:**

    - `aperture_radius`: the camera's aperture radius `A` (scene units, read as metres).
    - `focus_distance`: its focus distance `d_f`, a z-distance (metres); `inf` for a camera
      focused at infinity (the sensor at `f`; blur scale `0`, circles `A f_px / d`).
    - `fov_x_deg`: its horizontal field of view (degrees) and `image_width` its width (pixels).
    - `focal_length`: the focal length `f` to give the equivalent lens (metres). Any `f < d_f`
      gives the same blur; it only sets how the blur scale splits into `f_number` and
      `pixel_pitch`.

    **Returns:** `ThinLens(f, N = f / (2A), d_f, p = s / f_px)` with `s = f d_f / (d_f - f)` and
    `f_px = (W/2) / tan(fov_x/2)`. Its `blur_scale` is `A f_px / d_f` for every `f`.

    **Derivation.** The ray tracer sends the ray of a film point through the point of the focus
    plane `z = d_f` that a pinhole would see, from a point `u` of the aperture disc `|u| <= A` at
    `z = 0`. A scene point `P` at depth `d` is hit by the rays from `u` that cross the focus plane at
    `u + (P - u) d_f / d`, i.e. at the pinhole image `P d_f / d` of `P` shifted by
    `u (1 - d_f / d)`: a disc of radius `A |1 - d_f / d|` on the focus plane. The focus plane maps to
    the film with `f_px / d_f` pixels per unit length, so the circle of confusion is

    $$r = A f_\mathrm{px} \left|\frac{1}{d_f} - \frac{1}{d}\right|
        = \frac{A f_\mathrm{px}}{d_f} \left|1 - \frac{d_f}{d}\right| \text{ pixels.}$$

    `jaxdof.coc_radius` is `K |1 - d_f / d|` with `K = a f / ((d_f - f) p)` and aperture radius
    `a = f / (2N)`. A thin lens with focal length `f` focused at `d_f` has its sensor at
    `s = f d_f / (d_f - f)`; a pixel of pitch `p` there subtends `p / s` radians at the centre,
    matching the ray tracer's `1 / f_px` when `p = s / f_px`. Then
    `K = a f f_px (d_f - f) / ((d_f - f) f d_f) = a f_px / d_f`, which equals the ray tracer's blur
    scale when `a = A`, i.e. `N = f / (2A)`. The match is exact, not an approximation in `f / d_f`.
    """
    if not (aperture_radius > 0 and math.isfinite(aperture_radius)):
        raise ValueError(f"aperture_radius must be positive and finite, got {aperture_radius}")
    if not (focus_distance > focal_length > 0):
        raise ValueError(
            f"need focus_distance > focal_length > 0, got focus_distance={focus_distance}, "
            f"focal_length={focal_length}; pick a focal_length below the focus distance"
        )
    if int(image_width) != image_width or image_width < 1:
        raise ValueError(f"image_width must be a positive integer, got {image_width}")
    f_px = _focal_length_px(fov_x_deg, int(image_width))
    # The sensor distance f d_f / (d_f - f) = f / (1 - f / d_f): f at focus at infinity.
    s = focal_length / (1.0 - focal_length / focus_distance)
    return ThinLens(
        focal_length=focal_length,
        f_number=focal_length / (2.0 * aperture_radius),
        focus_distance=focus_distance,
        pixel_pitch=s / f_px,
    )
