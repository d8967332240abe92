"""Ray-traced truth without the ray tracer: fixtures cut from Mitsuba 3 renders (fits/raytraced.py).

The fixtures in tests/data/raytraced_*.npz were rendered by Mitsuba 3 (thin-lens camera, box pixel
filter, self-emitting textured scenes); regenerate them with `python fits/raytraced.py --fixtures`.
Nothing here imports Mitsuba.
"""

import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import jaxdof
from jaxdof import (
    depth_edges,
    edge_weight,
    footprint_prefilter,
    lens_from_raytracer,
    ray_distance_to_z,
)
from jaxdof.internal import (
    edge_distance,
    footprint_coefficient,
    fourth_order_coefficients,
    kernel_variance,
)

from .helpers import EXACT, fits_module


# The footprint corrections that lost to `footprint_prefilter`, kept by the study (`fits/`).
pixel_prefilter = fits_module("_footprint_candidates").pixel_prefilter
footprint_radius = fits_module("_footprint_candidates").footprint_radius


DATA = Path(__file__).parent / "data"


def load(name):
    with np.load(DATA / f"raytraced_{name}.npz", allow_pickle=False) as f:
        return {k: f[k] for k in f.files}


def fixture_scene(name):
    """`(true lens, pinhole image, z-depth, thin-lens target)` of a fixture, float64."""
    f = load(name)
    lens = lens_from_raytracer(
        float(f["aperture_radius"]),
        float(f["focus_distance"]),
        fov_x_deg=float(f["fov_x_deg"]),
        image_width=int(f["width"]),
    )
    return (lens, *(f[k].astype(np.float64) for k in ("image", "depth", "target")))


def f_px(fov_x_deg, width):
    return (width / 2) / math.tan(math.radians(fov_x_deg) / 2)


def pixel_directions(h, w, fov_x_deg):
    """Camera-space direction (x, y, 1) through every pixel centre, Mitsuba's orientation (x left)."""
    fp = f_px(fov_x_deg, w)
    x = -(np.arange(w) + 0.5 - w / 2) / fp
    y = -(np.arange(h) + 0.5 - h / 2) / fp
    return np.stack(np.broadcast_arrays(x[None, :], y[:, None], np.ones((h, 1))), -1)


# ------------------------------------------------------------------------- depth conversion


@pytest.mark.parametrize("near_clip", [0.0, 0.01, 0.3])
@pytest.mark.parametrize("shape", [(16, 16), (12, 20)])
def test_ray_distance_to_z_analytic_plane(near_clip, shape):
    # A tilted plane n . P = c. The hit along the pixel-centre direction v is at P = z v (v has
    # unit z), so z = c / (n . v); the renderer reports t = z |v| - near_clip |v| (its rays start
    # on the near plane). Converting back must give z to float64 rounding.
    h, w = shape
    v = pixel_directions(h, w, 50.0)
    n = np.array([0.3, -0.2, -1.0])
    z = -3.0 / (v @ n)
    t = (z - near_clip) * np.linalg.norm(v, axis=-1)
    out = np.asarray(ray_distance_to_z(t, fov_x_deg=50.0, near_clip=near_clip))
    np.testing.assert_allclose(out, z, rtol=1e-13)


def test_ray_distance_to_z_float32_and_inf():
    t = np.full((8, 10), 2.0, np.float32)
    t[0, 0] = np.inf  # no hit stays at infinity
    z = ray_distance_to_z(t, fov_x_deg=40.0)
    assert z.dtype == jnp.float32
    assert np.isinf(z[0, 0])
    # the centre pixels look almost along the axis: z just below t
    assert 1.99 < float(z[4, 5]) < 2.0


def test_ray_distance_to_z_mitsuba_plane():
    # Mitsuba's own depth AOV (pixel-centre rays, near_clip 0.01) of the slanted plane, converted,
    # against the plane's analytic z. The tolerance is float32 storage and Mitsuba's float32
    # intersection (relative ~1e-7 each, a few ulps); a wrong near-clip term alone would be 5e-3.
    f = load("depth")
    h, w = int(f["height"]), int(f["width"])
    z = np.asarray(
        ray_distance_to_z(
            f["distance"].astype(np.float64),
            fov_x_deg=float(f["fov_x_deg"]),
            near_clip=float(f["near_clip"]),
        )
    )
    v = pixel_directions(h, w, float(f["fov_x_deg"]))
    n, p0 = f["plane_normal"], f["plane_point"]
    z_plane = (n @ p0) / (v @ n)
    np.testing.assert_allclose(z, z_plane, rtol=5e-6)


def test_ray_distance_to_z_rejects_bad_input():
    with pytest.raises(ValueError, match="fov_x_deg"):
        ray_distance_to_z(np.ones((4, 4)), fov_x_deg=180.0)
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        ray_distance_to_z(np.ones((4, 4, 1)), fov_x_deg=40.0)
    with pytest.raises(ValueError, match="floating"):
        ray_distance_to_z(np.ones((4, 4), np.int32), fov_x_deg=40.0)


# ------------------------------------------------------------------------- the lens mapping


@pytest.mark.parametrize(
    "focal_length,d_f", [(0.005, 2.0), (0.05, 2.0), (0.5, 2.0), (0.05, np.inf)]
)
def test_lens_from_raytracer_matches_ray_tracer_coc(focal_length, d_f):
    # The ray tracer's circle: A f_px |1/d_f - 1/d|. Exact for any focal length (the derivation has
    # no small-f approximation), so only float64 rounding is allowed; focus at infinity included.
    a, fov, w = 0.04, 40.0, 128
    lens = lens_from_raytracer(a, d_f, fov_x_deg=fov, image_width=w, focal_length=focal_length)
    fp = f_px(fov, w)
    np.testing.assert_allclose(float(lens.blur_scale), a * fp / d_f, rtol=1e-13)
    depth = np.array([[0.7, 1.0, 1.9], [2.0, 5.0, np.inf]])
    expect = a * fp * np.abs(1 / d_f - 1 / depth)
    np.testing.assert_allclose(
        np.asarray(jaxdof.coc_radius(depth, lens)), expect, rtol=1e-12, atol=1e-13
    )


def test_lens_from_raytracer_rejects_bad_input():
    with pytest.raises(ValueError, match="focal_length"):
        lens_from_raytracer(0.05, 0.04, fov_x_deg=40.0, image_width=64)
    with pytest.raises(ValueError, match="aperture_radius"):
        lens_from_raytracer(0.0, 2.0, fov_x_deg=40.0, image_width=64)


def test_lens_matches_mitsuba_blur_discs():
    # Blur-disc radii of 16 small emitters x 6 lenses, measured in Mitsuba thin-lens renders from
    # the second moment (thin-lens minus pinhole, so the disk's own size and the pixel box cancel).
    # Discs of >= 2.5 px must match the derived lens within 3%: the moment estimate's Monte Carlo
    # noise at 8192 spp is <= 1.7% between two seeds. Smaller discs are skipped: some emitters show
    # a seed-independent error of up to ~0.3 px^2 in r^2 (3.4% at 2 px), likely the pixel-sampled
    # second moment of the 1 px disk's pinhole image, which depends on its sub-pixel position.
    f = load("emitters")
    fov, w = float(f["fov_x_deg"]), int(f["width"])
    predicted = np.array(
        [
            float(jaxdof.coc_radius(z, lens_from_raytracer(a, d, fov_x_deg=fov, image_width=w)))
            for a, d, z in zip(f["aperture_radius"], f["focus_distance"], f["depth"])
        ]
    )
    big = predicted >= 2.5
    assert big.sum() >= 40
    np.testing.assert_allclose(f["measured_radius"][big], predicted[big], rtol=0.03)


# ------------------------------------------------------------------------- recovering the lens


def fixture_start(f):
    """`(truth, init, interior weight, r0)` of a fixture: the study's start (N 30% off, d_f 15%
    far) and its largest circle `r0`. Pixels within 1.6 r0 of the crop's border see scene content
    that is not in the crop: masked out, as fits/raytraced.py does for the full frame."""
    truth = lens_from_raytracer(
        float(f["aperture_radius"]),
        float(f["focus_distance"]),
        fov_x_deg=float(f["fov_x_deg"]),
        image_width=int(f["width"]),
    )
    init = jaxdof.ThinLens(
        truth.focal_length, truth.f_number * 1.3, truth.focus_distance * 1.15, truth.pixel_pitch
    )
    depth = f["depth"].astype(np.float64)
    r0 = float(np.max(np.asarray(jaxdof.coc_radius(depth, init))))
    b = int(math.ceil(1.6 * r0)) + 2
    weight = np.zeros(depth.shape)
    weight[b:-b, b:-b] = 1.0
    return truth, init, weight, r0


def fit_fixture(name, **options):
    """The fixture's fit from the study's start (one start), with `fit_lens`'s `options`."""
    f = load(name)
    truth, init, weight, _ = fixture_start(f)
    res = jaxdof.fit_lens(
        f["image"].astype(np.float64),
        f["depth"].astype(np.float64),
        f["target"].astype(np.float64),
        init,
        weight=weight,
        starts=1,
        **options,
    )
    return res, truth


def converged(res):
    """The fit converged to a lens: `successful`, or `inconsistent` with that lens's errors
    inflated. Ray-traced photos differ from the model by more than their Monte Carlo noise (the
    pixel footprint, occlusion at edges: the adequacy test fires at p < 1e-30 on these crops),
    so `inconsistent` is the honest verdict here; the lens and its inflated errors are what is
    under test (`covered`)."""
    return res.status in (jaxdof.RESULTS.successful, jaxdof.RESULTS.inconsistent)


def covered(res, truth):
    """The reported (where inconsistent, inflated) standard errors cover the actual errors of the
    free fields within 3."""
    z = [
        abs(float(getattr(res.lens, k)) - float(getattr(truth, k))) / float(res.stderr[k])
        for k in res.stderr
        if k in jaxdof.ThinLens.__dataclass_fields__  # not the gain and offset, if fitted
    ]
    return max(z) <= 3, z


def assert_recovered(res, truth):
    """Converged (`converged`), within the goal (`within_goal`) and covered (`covered`)."""
    assert converged(res), res.message
    ok, df_err, k_err = within_goal(res, truth)
    assert ok, (df_err, k_err)
    assert covered(res, truth)[0], covered(res, truth)


def within_goal(res, truth):
    """The issue's goal on ray-traced scenes: focus distance within 2%, blur scale within 5%."""
    fitted = res.lens
    df_err = abs(float(fitted.focus_distance) / float(truth.focus_distance) - 1)
    k_err = abs(float(fitted.blur_scale) / float(truth.blur_scale) - 1)
    return df_err < 0.02 and k_err < 0.05, df_err, k_err


def test_fit_recovers_raytraced_lens_without_depth_edges():
    # One slanted plane, circles 0.2-3.4 px (fits/raytraced.py: d_f +0.7%, K -0.1% on this crop).
    res, truth = fit_fixture("slant")
    assert_recovered(res, truth)


def test_a_finer_input_recovers_the_smallest_blur_scale():
    # The smallest blur scale of the study (K = 1.76 px) on a slant crop with circles of 0.1-1.6
    # px: the 1x pinhole image has lost the detail inside each photo pixel that blur this small
    # depends on. With the second-order footprint correction alone the 1x fit missed by d_f +16%,
    # K -31%; with its fourth-order terms (footprint_prefilter since 2026-12-03) it is off by
    # d_f 2.1 %, K 2.9 % (measured), and the all-in-focus input at twice the photo's resolution
    # (`downsample=2`) meets the goal (measured d_f 0.4 %, K 0.7 %). Both from the study's start
    # (N 30% off, d_f 15% far), one start.
    f = load("slant_fine")
    truth, init, weight, _ = fixture_start(f)
    depth = f["depth"].astype(np.float64)
    target = f["target"].astype(np.float64)
    fits = {}
    for s, image, z in ((1, f["image"], depth), (2, f["image_x2"], f["depth_x2"])):
        fits[s] = jaxdof.fit_lens(
            image.astype(np.float64),
            z.astype(np.float64),
            target,
            init,
            weight=weight,
            starts=1,
            footprint=True,
            downsample=s,
        )
    assert_recovered(fits[2], truth)
    _, df1, k1 = within_goal(fits[1], truth)
    _, df2, k2 = within_goal(fits[2], truth)
    assert max(df1, k1) < 0.05, (df1, k1)  # the fourth-order terms: no longer a 31 % miss
    assert max(df2, k2) < max(df1, k1), (df1, k1, df2, k2)  # the finer input is closer still


def test_soft_fit_is_biased_by_occlusion_and_says_so():
    # Occluders in front of a wall: the soft model without the edge weight, where the pixels next
    # to occlusion edges (which no single-layer image can model) pull the focus distance off by
    # ~13% (measured), not silently: the adequacy test flags it or its errors cover the miss.
    # (The bias that the default treatment removes: an extended test, tests/extended_tests.txt.)
    plain, truth = fit_fixture("occluders", **EXACT)
    _, df_plain, _ = within_goal(plain, truth)
    assert df_plain > 0.05  # the bias the treatment removes, well beyond the 2% goal
    assert not bool(plain.success) or covered(plain, truth)[0], plain.message


def test_default_treatment_removes_occlusion_bias():
    # The default call chooses the occlusion render, the edge weight and the footprint correction
    # on the occluders crop (measured d_f -0.7%; the soft fit misses by ~13%,
    # test_soft_fit_is_biased_by_occlusion_and_says_so) and meets the goal.
    res, truth = fit_fixture("occluders")
    t = res.treatment
    assert t.occlusion and t.edge_weight > 0 and t.footprint and not t.forced, t
    assert_recovered(res, truth)


def test_occlusion_render_closes_most_of_the_gap_at_depth_edges():
    # The occluders crop (48x48, circles up to 3.5 px) against Mitsuba: the soft render is 21.1 dB
    # over the interior and 16.6 dB within 2 px of a depth edge; method="occlusion" 32.5 and 28.4
    # dB (measured). A margin of 8 dB keeps the claim (most of the edge error removed) without
    # depending on round-off.
    lens, image, depth, target = fixture_scene("occluders")
    r_max = float(np.max(np.asarray(jaxdof.coc_radius(depth, lens))))
    b = int(math.ceil(r_max)) + 2  # the border sees content outside the crop
    inner = np.zeros(depth.shape, bool)
    inner[b:-b, b:-b] = True
    near = inner & (edge_distance(depth) < 2)

    def psnr(out, mask):
        return 10 * np.log10(1 / np.mean((np.asarray(out) - target)[mask] ** 2))

    soft = jaxdof.render(image, depth, lens)
    occ = jaxdof.render(image, depth, lens, method="occlusion")
    assert psnr(occ, inner) > psnr(soft, inner) + 8
    assert psnr(occ, near) > psnr(soft, near) + 8


# ------------------------------------------------------------------------- corrections


def test_edge_weight_is_all_ones_without_depth_edges():
    f = load("slant")  # one slanted plane: no depth edge
    assert not depth_edges(f["depth"]).any()
    np.testing.assert_array_equal(edge_weight(f["depth"], width=5.0), 1.0)


def test_edge_weight_ramps_from_an_edge():
    depth = np.full((9, 12), 4.0)
    depth[:, :5] = 1.5  # an occlusion edge between columns 4 and 5
    e = depth_edges(depth)
    assert e[:, 4].all() and e[:, 5].all() and e.sum() == 18
    dist = edge_distance(depth, limit=10.0)
    np.testing.assert_array_equal(dist[0], [4, 3, 2, 1, 0, 0, 1, 2, 3, 4, 5, 6])
    w = edge_weight(depth, width=4.0)
    np.testing.assert_allclose(w[3], (np.clip(dist[3] / 4.0, 0, 1)) ** 2)
    with pytest.raises(ValueError, match="width"):
        edge_weight(depth, width=0.0)


def test_pixel_prefilter_moments():
    # The prefilter's impulse response sums to one (a constant image is unchanged) and has second
    # moment -1/12 per axis: it removes exactly the variance one pixel box adds.
    img = np.zeros((9, 9))
    img[4, 4] = 1.0
    k = np.asarray(pixel_prefilter(img))
    yy, xx = np.mgrid[-4:5, -4:5]
    np.testing.assert_allclose(k.sum(), 1.0, rtol=1e-14)
    np.testing.assert_allclose((k * xx**2).sum(), -1 / 12, rtol=1e-13)
    np.testing.assert_allclose((k * yy**2).sum(), -1 / 12, rtol=1e-13)
    const = np.full((5, 6, 3), 0.25)
    np.testing.assert_allclose(np.asarray(pixel_prefilter(const)), const, rtol=1e-14)
    with pytest.raises(ValueError, match="floating"):
        pixel_prefilter(np.ones((4, 4), np.int32))


@pytest.mark.parametrize("r", [0.3, 0.7, 1.0, 1.6, 2.5, 4.2])
def test_footprint_radius_matches_disc_variance(r):
    # The filter kernel at the corrected radius has the lens disc's per-axis variance r^2/4. The
    # tolerance is the table's linear interpolation (step 0.01 px in radius): < 1e-3 px^2.
    rho = float(footprint_radius(np.float64(r)))
    o = np.arange(-8.0, 9.0)
    dx, dy = np.meshgrid(o, o, indexing="ij")
    area = np.asarray(jaxdof.circle_pixel_overlap(dx, dy, np.full(dx.shape, rho)))
    w = area / area.sum()
    np.testing.assert_allclose((w * dx**2).sum(), r * r / 4, atol=1e-3)


def test_footprint_radius_limits():
    r = np.array([0.0, 0.1, 0.5, 1.0, 2.0, 5.0, 8.0, 30.0])
    rho = np.asarray(footprint_radius(r))
    assert rho[0] == 0.5  # no blur: the filter's copy
    assert np.all(np.diff(rho) > 0)
    # large circles: the pixel box's 1/12 per axis (plus the sampled kernel's ~0.02) comes off
    np.testing.assert_allclose(rho[-3:], np.sqrt(r[-3:] ** 2 - 1 / 3), rtol=4e-3)


def overlap_kernel(r, half=8):
    """The soft filter's kernel overlap(o, r) / (pi r^2) on offsets -half..half, and the offsets."""
    o = np.arange(-float(half), half + 1.0)
    dx, dy = np.meshgrid(o, o, indexing="ij")
    area = np.asarray(jaxdof.circle_pixel_overlap(dx, dy, np.full(dx.shape, r)))
    return area / (np.pi * r * r), dx, dy


@pytest.mark.parametrize("r", [0.3, 0.5, 0.52, 0.8, 1.0, 1.5, 2.37, 5.0, 7.9])
def test_kernel_variance_matches_the_overlap_kernel(r):
    # The closed form against the per-axis second moment of the kernel built from
    # circle_pixel_overlap (float64): both exact, so only rounding differs.
    k, dx, _ = overlap_kernel(r, half=9)
    np.testing.assert_allclose(float(kernel_variance(np.float64(r))), (k * dx**2).sum(), atol=1e-12)


def test_kernel_variance_limits_and_gradients():
    r = np.array([0.0, 0.2, 0.5, 24.5, 30.0])
    v = np.asarray(kernel_variance(r))
    np.testing.assert_array_equal(v[:3], 0.0)  # the disc stays inside its pixel: a copy
    # beyond the exact range the excess over r^2/4 is held at its last value (~1/12 + sampling)
    np.testing.assert_allclose(v[4] - r[4] ** 2 / 4, v[3] - r[3] ** 2 / 4, rtol=1e-12)
    assert 0.07 < v[3] - r[3] ** 2 / 4 < 0.1
    # C^1 but not C^2 where the disc's edge crosses a pixel boundary (r = k + 1/2: Var grows like
    # (r - k - 1/2)^(3/2)), so the finite-difference check uses radii away from those points.
    check_grads(
        jax.jit(kernel_variance),
        (np.array([0.0, 0.3, 0.62, 1.1, 1.8, 3.3, 9.7, 31.0]),),
        order=1,
        modes=["fwd", "rev"],
    )


def test_footprint_coefficient_matches_the_closed_form():
    # The tabulated c(r) = (Var - r^2/4)/2 that footprint_prefilter uses, against the closed form
    # (kernel_variance) on 20000 radii over 0-30 px, densest at the column boundaries k + 1/2
    # where Var's (r - k - 1/2)^(3/2) term is: measured 7.5e-9 px^2 (float64; c is ~0.03-0.04),
    # and float32's own rounding (8.7e-8) in float32. Its derivative is C^1 and finite at 0.
    rng = np.random.default_rng(11)
    boundaries = np.arange(25)[:, None] + 0.5 + np.array([0.0, 1e-6, 1e-4, 1e-3, 1e-2])[None]
    r = np.concatenate([rng.uniform(0.0, 30.0, 20000), boundaries.ravel(), [0.0, 0.5, 24.5, 30.0]])
    exact = (np.asarray(kernel_variance(r)) - r * r / 4) / 2
    np.testing.assert_allclose(np.asarray(footprint_coefficient(r)), exact, rtol=0, atol=1e-8)
    c32 = footprint_coefficient(r.astype(np.float32))
    assert c32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(c32), exact, rtol=0, atol=2e-7)
    check_grads(
        jax.jit(footprint_coefficient),
        (np.array([0.0, 0.3, 0.62, 1.1, 1.8, 3.3, 9.7, 31.0]),),
        order=1,
        modes=["fwd", "rev"],
    )


def test_fourth_order_table_is_its_least_squares_fit():
    # The shipped tables (jaxdof/_footprint_table.py, 7 significant digits) against the fit that
    # wrote them, at nodes (0.01 px apart), where the Hermite interpolant is the node value; zero
    # from 3 px on; continuously differentiable in between.
    from jaxdof import _footprint_table

    nodes = np.array([0.0, 0.25, 0.5, 0.73, 1.21, 1.9, 2.62, 3.0])
    c2, c3 = _footprint_table.compute(nodes)
    got2, got3 = (np.asarray(c) for c in fourth_order_coefficients(nodes))
    np.testing.assert_allclose(got2, c2, rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(got3, c3, rtol=1e-6, atol=1e-10)
    far = fourth_order_coefficients(np.array([3.0, 3.5, 40.0]))
    assert all(np.all(np.asarray(c) == 0) for c in far)
    check_grads(
        jax.jit(lambda r: fourth_order_coefficients(r)[0] + 10 * fourth_order_coefficients(r)[1]),
        (np.array([0.021, 0.137, 0.504, 0.8123, 1.3377, 2.7051, 3.4]),),
        order=1,
        modes=["fwd", "rev"],
    )


def test_footprint_prefilter_brings_the_transfer_function_to_the_disc():
    # The corrected filter's transfer function against the disc's 2 J1(r|w|)/(r|w|), root mean
    # square over the band |w| <= pi of a 64 x 64 grid: with the fourth-order terms against the
    # second-order correction alone (c_1, the Laplacian). Measured (float64): 0.0229 -> 0.0051 at
    # r = 0.3, 0.0749 -> 0.0176 at 0.6, 0.0667 -> 0.0363 at 1.0, 0.0471 -> 0.0392 at 1.3,
    # 0.0220 -> 0.0140 at 2.0. Bounds: those ratios plus 0.05.
    from scipy.special import j1

    n = 64
    delta = np.zeros((n, n))
    delta[n // 2, n // 2] = 1.0
    w = 2 * np.pi * np.fft.fftfreq(n)
    wx, wy = np.meshgrid(w, w, indexing="ij")
    rho = np.hypot(wx, wy)
    band = rho <= np.pi

    @jax.jit
    def responses(r):
        radius = jnp.full((n, n), r)
        second = delta - footprint_coefficient(radius) * jnp.asarray(
            np.roll(delta, 1, 0)
            + np.roll(delta, -1, 0)
            + np.roll(delta, 1, 1)
            + np.roll(delta, -1, 1)
            - 4 * delta
        )
        spread = lambda x: jaxdof.coc_filter(x, radius, max_radius=4.0)  # noqa: E731
        return spread(second), spread(footprint_prefilter(delta, radius))

    def error(kernel, r):
        k = np.real(np.fft.fft2(np.fft.ifftshift(np.asarray(kernel))))
        x = np.maximum(r * rho, 1e-12)
        disc = np.where(r * rho > 1e-9, 2 * j1(x) / x, 1.0)
        return float(np.sqrt(np.mean((k - disc)[band] ** 2)))

    for r, ratio in ((0.3, 0.22), (0.6, 0.24), (1.0, 0.54), (1.3, 0.83), (2.0, 0.64)):
        second, fourth = responses(r)
        e2, e4 = error(second, r), error(fourth, r)
        assert e4 < (ratio + 0.05) * e2, (r, e2, e4)


def test_footprint_prefilter_gives_the_lens_variance():
    # Spreading the corrected image with the filter's kernel must give the lens disc's per-axis
    # variance r^2/4 exactly (the prefilter matches the second moment by construction), including
    # under half a pixel, where coc_filter copies and the prefilter does all of the blur; and it
    # must conserve the light. Impulse response on a 33x33 frame, uniform radius; float64 rounding.
    n = 33
    img = np.zeros((n, n))
    img[n // 2, n // 2] = 1.0
    yy, xx = np.mgrid[0:n, 0:n] - n // 2

    @jax.jit  # one window for every r: one compilation
    def impulse_response(r):
        radius = jnp.full((n, n), r)
        return jaxdof.coc_filter(footprint_prefilter(img, radius), radius, max_radius=4.0)

    for r in (0.0, 0.3, 0.45, 0.7, 1.0, 1.3, 2.2, 3.7):
        out = np.asarray(impulse_response(r))
        np.testing.assert_allclose(out.sum(), 1.0, rtol=1e-13)
        # To the tabulated coefficient's error (2 c: 1.5e-8 px^2, the test above); exact
        # (float64 rounding) under half a pixel, where c = -r^2/8 is computed, not read.
        tol = 1e-12 if r < 0.5 else 3e-8
        np.testing.assert_allclose((out * xx**2).sum(), r * r / 4, atol=tol)
        np.testing.assert_allclose((out * yy**2).sum(), r * r / 4, atol=tol)


def test_pixel_prefilter_inverts_the_box_on_a_band_limited_signal():
    # Box-averaged samples of cos(w x) have amplitude sinc(w/2) = sin(w/2)/(w/2); the 5-point
    # prefilter multiplies them by 1 + (1 - cos w)/12 per axis, the inverse of the box to 2nd order.
    # At w = pi/4 (a quarter of the Nyquist frequency pi) the 4th-order remainder is
    # |sinc(pi/8) (1 + (1 - cos(pi/4))/12) - 1| = 1.72e-3 of the amplitude, against 2.55e-2 without
    # the prefilter: the tolerance 2e-3 is that remainder. footprint_prefilter for large circles is
    # this filter with c = (Var - r^2/4)/2 instead of 1/24 (the sampled kernel's own excess).
    w = np.pi / 4
    x = np.arange(40.0)
    box = np.sin(w / 2) / (w / 2)
    img = np.broadcast_to((box * np.cos(w * x))[None, :, None], (40, 40, 2)).copy()
    truth = np.broadcast_to(np.cos(w * x)[None, 2:-2, None], (40, 36, 2))
    out = np.asarray(pixel_prefilter(img))[:, 2:-2]  # edge columns see the repeated border
    np.testing.assert_allclose(out, truth, atol=2e-3)
    assert np.max(np.abs(img[:, 2:-2] - truth)) > 2.5e-2


def test_footprint_prefilter_gradients_and_checks():
    rng = np.random.default_rng(3)
    img = rng.uniform(size=(6, 7, 2))
    # radii away from k + 1/2 (see test_kernel_variance_limits_and_gradients), under and over 1/2
    radius = np.array([0.1, 0.33, 0.71, 1.17, 2.13, 3.07, 6.21])[None, :]
    radius = radius + np.linspace(0.0, 0.18, 6)[:, None]
    check_grads(jax.jit(footprint_prefilter), (img, radius), order=1, modes=["fwd", "rev"])
    with pytest.raises(ValueError, match="one circle per pixel"):
        footprint_prefilter(img, radius[:, :5])
    with pytest.raises(ValueError, match="floating"):
        footprint_prefilter(np.ones((4, 4), np.int32), np.ones((4, 4)))


def test_footprint_prefilter_removes_the_blur_scale_bias_on_raytraced_slant():
    # The slant crop (circles 0.2-3.4 px, no depth edge) against Mitsuba: at the true focus
    # distance, scale every circle by s and find the s that best explains the ray-traced target
    # (parabola in log s through 5 losses). Measured: plain model s - 1 = -3.4% (the extra pixel
    # box), footprint_prefilter -0.6% (footprint_radius: +2.4%). Bounds: the plain bias must stay
    # beyond 2.5% (the effect is real on this crop) and the corrected one within 1.5% (its
    # measured residual plus margin for the parabola's and the target's noise, ~0.5%).
    lens, image, depth, target = fixture_scene("slant")
    r = np.asarray(jaxdof.coc_radius(depth, lens))
    b = int(math.ceil(1.6 * r.max())) + 2  # the border sees content outside the crop
    inner = np.zeros(depth.shape + (1,))
    inner[b:-b, b:-b] = 1.0
    scales = np.array([0.9, 0.95, 1.0, 1.05, 1.1])

    def best_scale(model):
        loss_at = jax.jit(lambda s: jnp.sum(inner * (model(r * s) - target) ** 2))
        loss = [float(loss_at(s)) for s in scales]
        c2, c1, _ = np.polyfit(np.log(scales), loss, 2)
        assert c2 > 0
        return math.exp(-c1 / (2 * c2)) - 1

    mr = float(np.ceil(r.max() * scales[-1]))  # one window for every scale: one compilation
    plain = best_scale(lambda rr: jaxdof.coc_filter(image, rr, max_radius=mr))
    corrected = best_scale(
        lambda rr: jaxdof.coc_filter(footprint_prefilter(image, rr), rr, max_radius=mr)
    )
    assert plain < -0.025, plain
    assert abs(corrected) < 0.015, corrected


def test_footprint_prefilter_float32():
    # float32 in, float32 out, and the gradient in the radius is finite at the dead zone's edge
    # (r = 1/2, where kernel_variance's chord terms reach u = 1) and at r = 0.
    rng = np.random.default_rng(4)
    img = rng.uniform(size=(5, 6, 3)).astype(np.float32)
    radius = np.linspace(0.0, 3.0, 30, dtype=np.float32).reshape(5, 6)
    radius[0, :2] = (0.0, 0.5)
    out = footprint_prefilter(img, radius)
    assert out.dtype == jnp.float32
    g = jax.grad(lambda r: jnp.sum(footprint_prefilter(img, r) ** 2))(jnp.asarray(radius))
    assert g.dtype == jnp.float32 and bool(jnp.all(jnp.isfinite(g)))
    # against the float64 result: float32 rounding of O(1) values through a 5-point stencil
    ref = footprint_prefilter(img.astype(np.float64), radius.astype(np.float64))
    assert ref.dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(out), np.asarray(ref), atol=2e-6)
