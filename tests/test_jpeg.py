"""A camera JPEG's luma compared in the file's own terms (`jaxdof/_fit/jpeg.py`, issue 34): the
quantisation table found from the decoded photo alone (and nothing found in a photo that never
was a JPEG), the block residual within half a step, its derivatives, and a fit that uses it."""

import io

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from PIL import Image

import jaxdof
from jaxdof._fit import jpeg, layout, photo, prepare, residual
from jaxdof._io import linear_to_srgb, srgb_to_linear


def _texture(h, w, seed):
    """Linear RGB detail at every scale: white noise, box-blurred to several sizes, summed."""
    rng = np.random.default_rng(seed)
    x = np.zeros((h, w, 3))
    for size in (1, 2, 4, 8):
        n = rng.uniform(size=(h // size + 1, w // size + 1, 3))
        x += np.repeat(np.repeat(n, size, 0), size, 1)[:h, :w] / 4
    return (0.05 + 0.8 * x).astype(np.float32)


def _encoded(linear, quality=90, subsampling=2):
    """`linear` as a camera JPEG at `quality` decoded back to linear light, and the file's table."""
    code = np.round(255 * linear_to_srgb(np.clip(linear, 0, 1))).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(code).save(buf, "JPEG", quality=quality, subsampling=subsampling)
    buf.seek(0)
    with Image.open(buf) as im:
        table = np.asarray(im.quantization[0], np.float64)
        decoded = np.asarray(im.convert("RGB")).astype(np.float64) / 255
    return srgb_to_linear(decoded).astype(np.float32), table


def _luma(rgb):
    return np.asarray(photo.luma(jnp.asarray(rgb)))[..., 0]


@pytest.mark.parametrize("quality", [50, 75, 90, 95])
def test_ijg_table_is_the_one_pillow_writes(quality):
    _, table = _encoded(_texture(16, 16, 0), quality)
    np.testing.assert_array_equal(jpeg.ijg_table(quality).reshape(-1), table)


@pytest.mark.parametrize("quality", [75, 90])
def test_the_table_and_grid_are_found_from_the_decoded_photo(quality):
    """A 4:2:0 JPEG of a textured photo: the table (the file's, every entry) and the grid at the
    origin; a crop of it 3 rows and 5 columns in: the grid at (5, 3)."""
    decoded, table = _encoded(_texture(96, 128, 1), quality)
    grid, record = jpeg.estimate(_luma(decoded)[None])
    assert grid is not None and record["found"] and record["quality"] == [quality], record
    assert grid.origin == (0, 0) and grid.shape == (96, 128)
    np.testing.assert_array_equal(grid.tables[0], table)
    crop, record = jpeg.estimate(_luma(decoded)[None, 3:, 5:])
    assert crop is not None and crop.origin == (5, 3), record
    np.testing.assert_array_equal(crop.tables[0], table)


def test_no_table_where_the_photo_never_was_a_jpeg():
    """The false-alarm rate, measured: none of 12 photos that never were JPEGs (linear float, the
    same rounded to 8-bit sRGB as a PNG holds it, and with 2 % noise) is taken for one; nor a
    JPEG resized by a factor of 1.5 (its blocks no longer on the grid)."""
    found = 0
    for seed in range(4):
        linear = _texture(48, 64, 10 + seed)
        png = srgb_to_linear(np.round(255 * linear_to_srgb(linear)) / 255).astype(np.float32)
        noisy = linear * (1 + 0.02 * np.random.default_rng(seed).normal(size=linear.shape))
        for x in (linear, png, noisy.astype(np.float32)):
            found += jpeg.estimate(_luma(x)[None])[0] is not None
    assert found == 0
    decoded, _ = _encoded(_texture(96, 96, 2))
    resized = np.asarray(
        Image.fromarray(np.round(255 * linear_to_srgb(decoded)).astype(np.uint8)).resize((64, 64))
    )
    assert jpeg.estimate(_luma(srgb_to_linear(resized / 255))[None])[0] is None


def _grid(shape, steps, origin=(0, 0), t=1):
    return jpeg.JpegGrid((tuple(map(float, np.ravel(steps))),) * t, origin, shape)


def test_block_residual_without_steps_is_the_pixel_residual():
    """With every step 0 the file-consistent photo nearest the render is the photo itself: the
    pixel residual, weighted (an origin of (2, 3), pixels outside whole blocks as well)."""
    rng = np.random.default_rng(0)
    pred, target = rng.uniform(0.1, 0.9, size=(2, 2, 21, 30, 1))
    weight = rng.uniform(size=(1, 21, 30, 1))
    grid = _grid((21, 30), np.zeros(64), origin=(2, 3), t=2)
    r = grid.residual(jnp.asarray(pred), jnp.asarray(target), jnp.asarray(weight))
    np.testing.assert_allclose(np.asarray(r), (pred - target) * weight, atol=1e-14)


def test_block_residual_is_what_the_file_cannot_hold():
    """A render whose coefficients are within half a step of the photo's has residual 0; one
    step beyond in one coefficient, half a step of that coefficient's pattern is left, weighted
    pixel by pixel; a block the file clipped keeps the plain pixel residual."""
    m = jpeg.dct_matrix()
    q = jpeg.ijg_table(90).astype(np.float64)
    rng = np.random.default_rng(1)
    c_photo = q * np.round(rng.normal(scale=20, size=(8, 8)) / q)
    c_photo[0, 0] = q[0, 0] * np.round(8 * 128 / q[0, 0])  # a mid-grey block: nothing clipped
    within = c_photo + rng.uniform(-0.49, 0.49, size=(8, 8)) * q
    target = (m.T @ c_photo @ m / 255)[None, :, :, None]
    pred = (m.T @ within @ m / 255)[None, :, :, None]
    grid = _grid((8, 8), q)
    ones = jnp.ones((1, 8, 8, 1))
    assert np.max(np.abs(grid.residual(jnp.asarray(pred), jnp.asarray(target), ones))) < 1e-12
    beyond = c_photo.copy()
    beyond[2, 3] += q[2, 3]
    pred = (m.T @ beyond @ m / 255)[None, :, :, None]
    weight = jnp.broadcast_to(jnp.linspace(0.0, 1.0, 8)[None, None, :, None], (1, 8, 8, 1))
    r = np.asarray(grid.residual(jnp.asarray(pred), jnp.asarray(target), weight))
    pattern = np.outer(m[2], m[3]) * 0.5 * q[2, 3] / 255
    np.testing.assert_allclose(r[0, :, :, 0], pattern * np.asarray(weight)[0, :, :, 0], atol=1e-12)
    clipped = target.copy()
    clipped[0, 4, 4, 0] = 1.0
    r = grid.residual(jnp.asarray(pred), jnp.asarray(clipped), ones)
    np.testing.assert_allclose(np.asarray(r), pred - clipped, atol=1e-15)


def test_residual_gradients_with_jpeg_blocks_and_nuisances():
    """The fit's residual with the luma compared in JPEG blocks (with exposure and registration):
    float64 finite differences of its derivatives in every coordinate, forward and reverse."""
    image = _texture(16, 16, 3).astype(np.float64)
    depth = np.where(np.arange(16) < 8, 1.5, 4.0)[None].repeat(16, 0)
    lens = jaxdof.ThinLens.from_sensor(0.05, 2.8, 2.5, sensor_width=0.0048, image_width=16)
    target = 0.9 * np.asarray(jaxdof.render(image, depth, lens)) + 0.02
    image, depth, targets, sqrt_w, base, _ = prepare._prepare(
        image, depth, target, lens, None, jaxdof.DefocusModel()
    )
    targets, sqrt_w = prepare.luma_targets(targets, sqrt_w)
    # Steps of 2 levels: some coefficients of the residual within half a step (derivative 0),
    # the others beyond.
    grid = _grid((16, 16), np.full(64, 2.0))
    every = ("exposure", "registration")
    spec = layout._Spec(("f_number", "focus_distance"), (), 1, every, luma=True)
    lay = spec.layout(base, depth)
    model = residual._Model(
        1, 4.0, every, jaxdof.DefocusModel(), len(spec.used), luma=True, jpeg=grid
    )
    args = (image, depth, targets, sqrt_w, lay)
    off = np.asarray(base).copy()
    off[:, 1] *= 1.2
    r = photo.half_diagonal(16, 16)
    y = model.pack(jnp.asarray(off), lay).at[3:].set(jnp.asarray([0.95, 0.01, 0.3 / r, 0, 0]))
    pixels = residual._Model(1, 4.0, every, jaxdof.DefocusModel(), len(spec.used), luma=True)
    in_blocks, in_pixels = np.asarray(model(y, args)), np.asarray(pixels(y, args))
    assert np.sum(in_blocks**2) < 0.9 * np.sum(in_pixels**2)  # what the file holds, less
    check_grads(jax.jit(lambda y: model(y, args)), (y,), order=1, modes=("fwd", "rev"), eps=1e-6)


# Every nuisance held off and the render's own treatment: the photos here are soft renders.
_HELD = dict(exposure=False, vignetting=False, illumination=False, registration=False)
_HELD.update(method="soft", footprint=False)


def _jpeg_scene(h, w, seed):
    """A textured two-plane scene, a quality-90 JPEG of its render at f/2.8 focused at 2.5 m
    (decoded to linear light), the file's table and a start at f/4, 2 m."""
    image = _texture(h, w, seed)
    x = np.linspace(0.0, 1.0, w)
    depth = np.where(x < 0.5, 1.2 + x, 3.0 + 2 * x)[None].repeat(h, 0).astype(np.float32)
    truth = jaxdof.ThinLens.from_sensor(0.05, 2.8, 2.5, sensor_width=0.0048, image_width=w)
    decoded, table = _encoded(np.asarray(jaxdof.render(image, depth, truth)))
    init = jaxdof.ThinLens.from_sensor(0.05, 4.0, 2.0, sensor_width=0.0048, image_width=w)
    return image, depth, decoded, table, init


def test_a_jpeg_of_a_render_is_fitted_in_its_blocks():
    """A 4:2:0 JPEG (quality 90) of a render: the fit finds the file's table, compares in its
    blocks and recovers the lens within 1 %; `jpeg=False` and the file's own table given are
    honoured and reported."""
    image, depth, decoded, table, init = _jpeg_scene(48, 64, 4)
    held = _HELD
    fit = jaxdof.fit_lens(image, depth, decoded, init, **held)
    entry = fit.nuisances["luma"]["jpeg"]
    assert entry["found"] and not entry["forced"] and entry["quality"] == [90], entry
    np.testing.assert_allclose(float(fit.lenses.f_number[0]), 2.8, rtol=0.01)
    np.testing.assert_allclose(float(fit.lenses.focus_distance[0]), 2.5, rtol=0.01)
    assert "in its JPEG blocks" in fit.summary(), fit.summary()
    off = jaxdof.fit_lens(image, depth, decoded, init, jpeg=False, **held)
    assert not off.nuisances["luma"]["jpeg"]["found"] and off.nuisances["luma"]["jpeg"]["forced"]
    given = jaxdof.fit_lens(image, depth, decoded, init, jpeg=table, **held)
    assert given.nuisances["luma"]["jpeg"]["forced"]
    np.testing.assert_allclose(given.lenses.focus_distance, fit.lenses.focus_distance, rtol=1e-3)


def test_jpeg_option_errors_name_the_problem():
    image = _texture(32, 32, 5)
    depth = np.full((32, 32), 2.0, np.float32)
    lens = jaxdof.ThinLens.from_sensor(0.05, 2.8, 2.5, sensor_width=0.0048, image_width=32)
    with pytest.raises(ValueError, match="64 steps"):
        jaxdof.fit_lens(image, depth, image, lens, luma=True, jpeg=np.ones(10))
    with pytest.raises(ValueError, match="no JPEG quantisation lattice"):
        jaxdof.fit_lens(image, depth, image, lens, luma=True, jpeg=True)
    with pytest.raises(ValueError, match="luma"):
        jaxdof.fit_lens(image, depth, image, lens, luma=False, jpeg=True)


@pytest.mark.parametrize("switch, want", [("auto", None), ("on", True), ("off", False)])
def test_cli_jpeg_switch_reaches_fit_lens(tmp_path, switch, want):
    """`jaxdof fit --jpeg auto|on|off` hands `fit_lens` `jpeg=None|True|False`."""
    import imageio.v3 as iio

    from jaxdof._cli.commands import fit_call
    from jaxdof._cli.parse import build_parser

    code = np.round(255 * linear_to_srgb(_texture(16, 24, 6))).astype(np.uint8)
    iio.imwrite(tmp_path / "sharp.png", code)
    Image.fromarray(code).save(tmp_path / "photo.jpg", quality=90)
    np.save(tmp_path / "depth.npy", np.full((16, 24), 2.0, np.float32))
    files = [str(tmp_path / n) for n in ("sharp.png", "depth.npy", "photo.jpg")]
    lens = ["--focal-length", "50mm", "--f-number", "4", "--focus", "2m", "--sensor-width", "5mm"]
    args = build_parser().parse_args(["fit", *files, *lens, "--jpeg", switch, "--quiet"])
    assert fit_call(args).kwargs["jpeg"] is want


@pytest.mark.slow
def test_a_jpeg_fitted_on_tiles_is_compared_in_its_blocks():
    """A fit on tiles (a budget of 4 tiles of 32 x 32) of a camera JPEG: the tiles lie on the
    file's 8 x 8 grid (corners and halos multiples of 8), the tile mosaic is compared in its
    blocks (the loss under the pixel comparison's on the same tiles) and the lens is right."""
    image, depth, decoded, _, init = _jpeg_scene(160, 192, 7)
    held = dict(_HELD, starts=1)
    fit = jaxdof.fit_lens(image, depth, decoded, init, tiles=4 * 32 * 32, **held)
    assert fit.tiles and all(r % 8 == 0 and c % 8 == 0 for r, c, _, _ in fit.tiles), fit.tiles
    np.testing.assert_allclose(float(fit.lenses.f_number[0]), 2.8, rtol=0.01)
    np.testing.assert_allclose(float(fit.lenses.focus_distance[0]), 2.5, rtol=0.01)
    pixels = jaxdof.fit_lens(image, depth, decoded, init, tiles=fit.tiles, jpeg=False, **held)
    assert pixels.tiles == fit.tiles
    assert float(np.sum(fit.loss)) < 0.9 * float(np.sum(pixels.loss))
