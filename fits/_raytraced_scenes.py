"""Ray-traced truth for `raytraced.py`: the Mitsuba 3 scenes, their renders (cached on disk), the
lens and depth mapping to jaxdof, the blur-disc measurement, and the CI fixtures cut from them.

Mitsuba is imported only when something has to be rendered (or its version reported): with every
render cached, nothing here needs it.
"""

from __future__ import annotations

import math
import os

import jax


jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from _common import CACHE as _CACHE_ROOT, FITS, cached_npz  # noqa: E402

from jaxdof import lens_from_raytracer, ray_distance_to_z  # noqa: E402


CACHE = _CACHE_ROOT / "raytraced"
DATA = FITS.parent / "tests" / "data"

W = H = 128  # film size (px)
FOV_X = 40.0  # horizontal field of view (degrees)
NEAR_CLIP = 0.01  # Mitsuba's default, passed explicitly so the depth conversion can use it
F_PX = (W / 2) / math.tan(math.radians(FOV_X) / 2)  # focal length in pixels, 175.8
SPP_PINHOLE = 512
SPP_THIN = 1024
SPP_EMITTERS = 8192  # emitters: few samples per pixel hit the small disks
APERTURES = (0.03, 0.06, 0.1)  # aperture radius A (m)
FOCUS = (1.8, 3.0)  # focus distance d_f (m)
CONFIGS = [(a, d) for d in FOCUS for a in APERTURES]
SCENES = ("planes", "slant", "occluders")


# ----------------------------------------------------------------------------- Mitsuba scenes


def mitsuba():
    """The `mitsuba` module with a variant set: `llvm_ad_rgb` when the system LLVM is found, else
    `scalar_rgb`."""
    import mitsuba as mi

    if mi.variant() is None:
        for lib in (
            "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
            "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
        ):
            if os.path.exists(lib) and "DRJIT_LIBLLVM_PATH" not in os.environ:
                os.environ["DRJIT_LIBLLVM_PATH"] = lib
        try:
            mi.set_variant("llvm_ad_rgb")
        except Exception:  # no usable LLVM: the scalar variant renders the same images
            mi.set_variant("scalar_rgb")
    return mi


def texture(seed: int, n: int = 384) -> np.ndarray:
    """A colour texture with detail at several scales and hard-edged shapes, values in [0.04, 1]."""
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    out = np.zeros((n, n, 3))
    for sigma, amp in ((1.5, 0.8), (4.0, 1.0), (12.0, 1.2)):
        noise = gaussian_filter(rng.normal(size=(n, n, 3)), (sigma, sigma, 0))
        out += amp * noise / noise.std()
    yy, xx = np.mgrid[0:n, 0:n]
    for _ in range(40):  # hard edges: discs and bars of random colour
        cy, cx, rad = rng.uniform(0, n), rng.uniform(0, n), rng.uniform(6, 40)
        mask = (
            (yy - cy) ** 2 + (xx - cx) ** 2 < rad**2
            if rng.uniform() < 0.5
            else ((abs(yy - cy) < rad) & (abs(xx - cx) < rad / 4))
        )
        out[mask] = rng.normal(0, 2.5, size=3)
    out = 1 / (1 + np.exp(-out))  # squash to (0, 1)
    return (0.04 + 0.96 * out).astype(np.float32)


TEXTURE_PERIOD = 1.5  # metres of surface per texture repeat: similar detail on every object


def _emissive(mi, shape: dict, seed: int | None = None, value=None, uv_scale=(1.0, 1.0)) -> dict:
    radiance = (
        {"type": "rgb", "value": value}
        if value is not None
        else {
            "type": "bitmap",
            "bitmap": mi.Bitmap(texture(seed)),
            "raw": True,
            "to_uv": mi.ScalarTransform3f().scale(list(uv_scale)),
        }
    )
    return {
        **shape,
        "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}},
        "emitter": {"type": "area", "radiance": radiance},
    }


def _card(mi, cx, cy, z, sx, sy, seed, rot_y=0.0, rot_x=0.0):
    """A textured rectangle centred at (cx, cy, z), half-sizes (sx, sy), emitting toward -z."""
    T = mi.ScalarTransform4f
    to_world = (
        T()
        .translate([cx, cy, z])
        .rotate([0, 1, 0], rot_y)
        .rotate([1, 0, 0], rot_x)
        .rotate([0, 1, 0], 180.0)
        .scale([sx, sy, 1.0])
    )
    uv = (2 * sx / TEXTURE_PERIOD, 2 * sy / TEXTURE_PERIOD)
    return _emissive(mi, {"type": "rectangle", "to_world": to_world}, seed, uv_scale=uv)


def scene_shapes(mi, name: str) -> dict:
    t = math.tan(math.radians(FOV_X) / 2)  # half-width of the view per metre of depth
    m = 0.15  # margin beyond the frame (in x/z units) so defocus sees scene content, not void
    if name == "planes":
        # Three fronto-parallel planes as vertical strips at 1.5, 2.5, 4 m; each farther plane
        # extends behind its nearer neighbour, so a real aperture can see around the edge.
        u0, u1 = -0.12, 0.12
        shapes = {}
        for key, z, lo, hi, seed in (
            ("near", 1.5, -t - m, u0, 1),
            ("mid", 2.5, u0 - m, u1, 2),
            ("far", 4.0, u1 - m, t + m, 3),
        ):
            cx, sx = z * (lo + hi) / 2, z * (hi - lo) / 2
            shapes[key] = _card(mi, cx, 0.0, z, sx, z * (t + m), seed)
        return shapes
    if name == "slant":
        # One plane through (0, 0, 2.2), turned 55 deg about y and 12 deg about x: z from about
        # 1.3 to 6 m across the frame, no depth edge.
        return {"plane": _card(mi, 0.0, 0.0, 2.2, 8.0, 3.0, 4, rot_y=55.0, rot_x=12.0)}
    if name == "occluders":
        T = mi.ScalarTransform4f
        return {
            "wall": _card(mi, 0.0, 0.0, 4.5, 4.5 * (t + m), 4.5 * (t + m), 5),
            "card": _card(mi, 0.35, -0.15, 2.6, 0.35, 0.3, 6, rot_y=20.0),
            "ball": _emissive(
                mi,
                {"type": "sphere", "center": [-0.22, 0.12, 1.75], "radius": 0.22},
                seed=7,
                uv_scale=(2 * math.pi * 0.22 / TEXTURE_PERIOD, math.pi * 0.22 / TEXTURE_PERIOD),
            ),
            "pole": _emissive(
                mi,
                {
                    "type": "cylinder",
                    "p0": [0.05, -1.5, 2.0],
                    "p1": [0.05, 1.5, 2.0],
                    "radius": 0.04,
                    "to_world": T(),
                },
                seed=8,
                uv_scale=(2 * math.pi * 0.04 / TEXTURE_PERIOD, 3.0 / TEXTURE_PERIOD),
            ),
        }
    if name == "emitters":
        return emitter_shapes(mi)
    raise ValueError(name)


EMITTER_DEPTHS = (
    1.0,
    1.2,
    1.45,
    1.7,
    2.0,
    2.3,
    2.7,
    3.2,
    3.8,
    4.6,
    5.5,
    7.0,
    9.0,
    13.0,
    20.0,
    40.0,
)


def emitter_positions():
    """Screen positions (px, row/col of the pinhole image, roughly) and depths of 16 small disks."""
    rng = np.random.default_rng(11)
    out = []
    for k, z in enumerate(EMITTER_DEPTHS):
        i, j = divmod(k, 4)
        # grid spacing 32 px; sub-pixel jitter so the disks do not sit on the pixel lattice
        col, row = 16 + 32 * j + rng.uniform(-0.5, 0.5), 16 + 32 * i + rng.uniform(-0.5, 0.5)
        out.append((row, col, z))
    return out


def emitter_shapes(mi) -> dict:
    """Fronto-parallel emissive disks of radius 1 px (projected) on black."""
    T = mi.ScalarTransform4f
    shapes = {}
    for k, (row, col, z) in enumerate(emitter_positions()):
        # screen -> camera: Mitsuba's look_at camera has +x to the image left, +y up.
        x = -(col - W / 2) / F_PX * z
        y = -(row - H / 2) / F_PX * z
        rho = 1.0 * z / F_PX
        to_world = T().translate([x, y, z]).rotate([0, 1, 0], 180.0).scale([rho, rho, 1.0])
        shapes[f"e{k}"] = _emissive(
            mi, {"type": "disk", "to_world": to_world}, value=[1.0, 1.0, 1.0]
        )
    return shapes


def _sensor(mi, kind: str, spp: int, aperture=None, focus=None, depth_pass=False, scale=1) -> dict:
    T = mi.ScalarTransform4f
    sensor = {
        "type": kind,
        "fov": FOV_X,
        "fov_axis": "x",
        "near_clip": NEAR_CLIP,
        "to_world": T().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, 1, 0]),
        # A box filter: each pixel is the average over its own square, as a sensor pixel is.
        "film": {
            "type": "hdrfilm",
            "width": W * scale,
            "height": H * scale,
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
            "sample_border": False,
        },
        # For depth, one unjittered stratified sample = the ray through the pixel centre.
        "sampler": {"type": "stratified", "sample_count": 1, "jitter": False}
        if depth_pass
        else {"type": "independent", "sample_count": spp},
    }
    if kind == "thinlens":
        sensor.update(aperture_radius=aperture, focus_distance=focus)
    return sensor


def render_scene(name: str, kind: str, *, spp: int = 0, aperture=None, focus=None, seed=0, scale=1):
    """One Mitsuba render of a scene; `scale` multiplies the film's width and height (same fov)."""
    mi = mitsuba()
    depth_pass = kind == "depth"
    scene = {
        "type": "scene",
        "integrator": {"type": "aov", "aovs": "dd.y:depth"}
        if depth_pass
        else {"type": "path", "max_depth": 1},
        "sensor": _sensor(
            mi, "perspective" if depth_pass else kind, spp, aperture, focus, depth_pass, scale
        ),
        **scene_shapes(mi, name),
    }
    img = np.array(mi.render(mi.load_dict(scene), seed=seed), dtype=np.float32)
    if depth_pass:
        img = img[..., 0]
        img[img <= 0] = np.inf  # no hit
    return img


def cached(key: str, fn):
    """`(array, seconds)` of a render, from the cache or rendered now (and cached)."""
    return cached_npz(CACHE / f"{key}.npz", fn, verb="rendered")


def load_scene(name: str):
    """Pinhole image, ray distance, and thin-lens renders {(A, d_f): image} of one scene."""
    pin, _ = cached(f"{name}_pinhole", lambda: render_scene(name, "perspective", spp=SPP_PINHOLE))
    dist, _ = cached(f"{name}_depth", lambda: render_scene(name, "depth"))
    thin, secs = {}, {}
    spp = SPP_EMITTERS if name == "emitters" else SPP_THIN
    for a, d in CONFIGS:
        key = f"{name}_thin_A{a}_df{d}"
        thin[(a, d)], secs[(a, d)] = cached(
            key, lambda a=a, d=d: render_scene(name, "thinlens", spp=spp, aperture=a, focus=d)
        )
    return pin, dist, thin, secs


def load_scene_fine(name: str, scale: int = 2):
    """The all-in-focus input at `scale` times the film's resolution: pinhole image (the same
    samples per photo pixel, `SPP_PINHOLE / scale^2` per fine pixel) and z-depth."""
    pin, _ = cached(
        f"{name}_pinhole_x{scale}",
        lambda: render_scene(
            name, "perspective", spp=max(16, SPP_PINHOLE // scale**2), scale=scale
        ),
    )
    dist, _ = cached(f"{name}_depth_x{scale}", lambda: render_scene(name, "depth", scale=scale))
    return pin, z_depth(dist)


def noise_pair(name: str, a: float, d: float):
    """A second seed of one thin-lens render, to measure the Monte Carlo noise."""
    img, _ = cached(
        f"{name}_thin_A{a}_df{d}_seed1",
        lambda: render_scene(name, "thinlens", spp=SPP_THIN, aperture=a, focus=d, seed=1),
    )
    return img


def z_depth(dist):
    return np.asarray(ray_distance_to_z(dist, fov_x_deg=FOV_X, near_clip=NEAR_CLIP))


def true_lens(a, d):
    return lens_from_raytracer(a, d, fov_x_deg=FOV_X, image_width=W)


def predicted_radius(z, a, d):
    """The ray tracer's circle of confusion (px), straight from the derivation."""
    return a * F_PX * np.abs(1 / d - 1 / z)


def emitter_table():
    """Measured vs predicted blur-disc radius of the 16 small emitters, for every (A, d_f)."""
    pin, dist, thin, _ = load_scene("emitters")
    lum_pin = pin.mean(-1)
    rows = []
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)

    def moments(img, row, col, half=15):
        sl = np.s_[
            max(int(row) - half, 0) : int(row) + half + 1,
            max(int(col) - half, 0) : int(col) + half + 1,
        ]
        i, y, x = img[sl].astype(np.float64), yy[sl], xx[sl]
        s = i.sum()
        cy, cx = (i * y).sum() / s, (i * x).sum() / s
        return cy, cx, (i * ((y - cy) ** 2 + (x - cx) ** 2)).sum() / s

    for (a, d), img in thin.items():
        lum = img.mean(-1)
        for row, col, z in emitter_positions():
            cy, cx, m_pin = moments(lum_pin, row, col)
            _, _, m_thin = moments(lum, cy, cx)
            # Variances add under convolution: thin = disk (x) CoC disc (x) pixel box, pinhole =
            # disk (x) box, so the CoC disc's E[x^2 + y^2] = r^2 / 2 is the difference.
            r_meas = math.sqrt(max(2 * (m_thin - m_pin), 0.0))
            rows.append((a, d, z, predicted_radius(z, a, d), r_meas))
    return np.array(rows)


def plane_geometry():
    """The slant scene's plane as (point, unit normal) in world coordinates, from Mitsuba."""
    mi = mitsuba()
    T = mi.ScalarTransform4f
    to_world = (
        T()
        .translate([0.0, 0.0, 2.2])
        .rotate([0, 1, 0], 55.0)
        .rotate([1, 0, 0], 12.0)
        .rotate([0, 1, 0], 180.0)
    )
    n = np.array(to_world @ mi.ScalarNormal3f(0, 0, 1), np.float64)
    return np.array([0.0, 0.0, 2.2]), n / np.linalg.norm(n)


# ----------------------------------------------------------------------------- CI fixtures

FIXTURE_CROPS = {
    # name: (scene, A, d_f, row0, col0, size); crops small enough for a fast CI fit
    "slant": ("slant", 0.1, 1.8, 44, 44, 40),
    "occluders": ("occluders", 0.06, 1.8, 36, 30, 48),
}


# The smallest blur scale (K = 1.76 px) on slant: a crop with circles of 0.1-1.6 px where the 1x
# input misses the goal (+16% d_f, -31% K with the footprint prefilter) and a 2x input meets it.
FINE_FIXTURE = ("slant", 0.03, 3.0, 16, 16, 64)


def write_fine_fixture(common):
    """`tests/data/raytraced_slant_fine.npz`: the crop at 1x and, as `image_x2`/`depth_x2`, the
    all-in-focus input at twice the photo's resolution."""
    scene, a, d, r0, c0, n = FINE_FIXTURE
    pin, dist, thin, _ = load_scene(scene)
    pin2, z2 = load_scene_fine(scene, 2)
    sl = np.s_[r0 : r0 + n, c0 : c0 + n]
    sl2 = np.s_[2 * r0 : 2 * (r0 + n), 2 * c0 : 2 * (c0 + n)]
    np.savez_compressed(
        DATA / "raytraced_slant_fine.npz",
        image=pin[sl].astype(np.float32),
        depth=z_depth(dist)[sl].astype(np.float32),
        target=thin[(a, d)][sl].astype(np.float32),
        image_x2=pin2[sl2].astype(np.float32),
        depth_x2=z2[sl2].astype(np.float32),
        aperture_radius=np.float64(a),
        focus_distance=np.float64(d),
        crop=np.array([r0, c0, n]),
        **common,
    )


def write_fixtures():
    DATA.mkdir(parents=True, exist_ok=True)
    common = dict(
        fov_x_deg=np.float64(FOV_X),
        near_clip=np.float64(NEAR_CLIP),
        width=np.int64(W),
        height=np.int64(H),
    )
    for key, (scene, a, d, r0, c0, n) in FIXTURE_CROPS.items():
        pin, dist, thin, _ = load_scene(scene)
        z = z_depth(dist)
        sl = np.s_[r0 : r0 + n, c0 : c0 + n]
        np.savez_compressed(
            DATA / f"raytraced_{key}.npz",
            image=pin[sl].astype(np.float32),
            depth=z[sl].astype(np.float32),
            target=thin[(a, d)][sl].astype(np.float32),
            aperture_radius=np.float64(a),
            focus_distance=np.float64(d),
            crop=np.array([r0, c0, n]),
            **common,
        )
    _, dist, _, _ = load_scene("slant")
    p0, normal = plane_geometry()
    np.savez_compressed(
        DATA / "raytraced_depth.npz",
        distance=dist.astype(np.float32),
        plane_point=p0,
        plane_normal=normal,
        **common,
    )
    t = emitter_table()
    np.savez_compressed(
        DATA / "raytraced_emitters.npz",
        aperture_radius=t[:, 0],
        focus_distance=t[:, 1],
        depth=t[:, 2],
        measured_radius=t[:, 4],
        **common,
    )
    write_fine_fixture(common)
    for f in sorted(DATA.glob("raytraced_*.npz")):
        print(f"  wrote {f.relative_to(FITS.parent)} ({f.stat().st_size / 1e3:.0f} kB)")
