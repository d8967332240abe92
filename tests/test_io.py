"""File reading and writing (`jaxdof._io`): formats, sRGB, depth encodings, atomic writes."""

import os
import struct
import zlib

import imageio.v3 as iio
import numpy as np
import pytest

from jaxdof import _io
from jaxdof._io import InputError, read_depth, read_image, write_image


def _png16(path, samples: np.ndarray, filters=(0,)) -> None:
    """A 16-bit grey/RGB/RGBA PNG written independently of `_io`, cycling the given PNG filter
    types over the rows (0 none, 1 Sub, 2 Up), as other encoders do."""
    s = samples if samples.ndim == 3 else samples[..., None]
    h, w, c = s.shape
    rows = s.astype(">u2").reshape(h, w * c).view(np.uint8).astype(np.int64)
    bpp = 2 * c
    out = []
    for y in range(h):
        kind = filters[y % len(filters)]
        if kind == 0:
            line = rows[y]
        elif kind == 1:  # Sub: minus the byte one pixel to the left
            line = rows[y] - np.concatenate([np.zeros(bpp, np.int64), rows[y, :-bpp]])
        else:  # Up: minus the byte above
            line = rows[y] - (rows[y - 1] if y else 0)
        out.append(bytes([kind]) + (line % 256).astype(np.uint8).tobytes())

    def chunk(kind, data):
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    ihdr = struct.pack(">IIBBBBB", w, h, 16, {1: 0, 3: 2, 4: 6}[c], 0, 0, 0)
    with open(path, "wb") as fh:
        fh.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr))
        fh.write(chunk(b"IDAT", zlib.compress(b"".join(out))) + chunk(b"IEND", b""))


# ---------------------------------------------------------------------------------------------
# sRGB


def test_srgb_known_values_and_round_trip():
    # Reference values of the IEC 61966-2-1 curve: sRGB 0.5 is 21.404% linear light, and the
    # linear segment meets the power segment at 0.04045 -> 0.0031308.
    np.testing.assert_allclose(
        _io.srgb_to_linear(np.array([0.0, 0.5, 1.0])), [0, 0.2140411, 1], atol=1e-7
    )
    np.testing.assert_allclose(_io.srgb_to_linear(0.04045), 0.04045 / 12.92, rtol=1e-12)
    x = np.linspace(0, 1, 1001)
    # Both directions are evaluated in float64: the round trip is exact to rounding.
    np.testing.assert_allclose(_io.linear_to_srgb(_io.srgb_to_linear(x)), x, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Images


def test_png8_is_decoded_from_srgb(tmp_path):
    codes = np.arange(256, dtype=np.uint8).reshape(16, 16)
    rgb = np.stack([codes, codes[::-1], codes.T], axis=-1)
    iio.imwrite(tmp_path / "a.png", rgb)
    img = read_image(str(tmp_path / "a.png"))
    assert img.bits == 8 and img.array.dtype == np.float32 and img.array.shape == (16, 16, 3)
    np.testing.assert_allclose(img.array, _io.srgb_to_linear(rgb / 255), rtol=1e-6, atol=1e-7)
    lin = read_image(str(tmp_path / "a.png"), linear=True)
    np.testing.assert_allclose(lin.array, rgb / 255, rtol=1e-6)


@pytest.mark.parametrize("channels", [1, 3, 4])
@pytest.mark.parametrize("filters", [(0,), (1, 2)])
def test_png16_full_precision(tmp_path, channels, filters):
    """16-bit PNGs keep all 16 bits (Pillow alone truncates colour ones to 8)."""
    rng = np.random.default_rng(channels)
    samples = rng.integers(0, 65536, size=(9, 7, channels), dtype=np.uint16)
    path = str(tmp_path / "a.png")
    _png16(path, samples[..., 0] if channels == 1 else samples, filters)
    img = read_image(path, linear=True)
    expect = samples[..., : 3 if channels != 1 else 1] / 65535
    assert img.bits == 16
    np.testing.assert_allclose(
        img.array, expect.squeeze(-1) if channels == 1 else expect, rtol=1e-6
    )
    assert bool(img.notes) == (channels == 4)  # the alpha channel is reported as dropped


@pytest.mark.parametrize("suffix", [".tif", ".npy", ".npz"])
@pytest.mark.parametrize("shape", [(5, 6), (5, 6, 3)])
def test_float_files_are_linear_and_round_trip(tmp_path, suffix, shape):
    x = np.random.default_rng(0).uniform(0, 2, size=shape).astype(np.float32)  # > 1 is fine
    path = str(tmp_path / f"x{suffix}")
    write_image(path, x, bits=None)
    img = read_image(path)
    assert img.bits is None
    np.testing.assert_array_equal(img.array, x)


@pytest.mark.parametrize("suffix,bits", [(".png", 8), (".png", 16), (".tif", 8), (".tif", 16)])
def test_integer_output_round_trip(tmp_path, suffix, bits):
    x = np.random.default_rng(1).uniform(size=(6, 5, 3)).astype(np.float32)
    path = str(tmp_path / f"x{suffix}")
    write_image(path, x, bits=bits)
    back = read_image(path)
    assert back.bits == bits
    # Quantisation to 2^bits - 1 levels in the sRGB domain; the largest slope of the decoding
    # curve is 1/12.92 near 0 and ~2.4 near 1, so the linear error is at most ~1.2 codes.
    np.testing.assert_allclose(back.array, x, atol=1.3 / (2**bits - 1))


def test_exr(tmp_path):
    """EXR gets a clear error: imageio has no EXR backend among jaxdof's dependencies (with
    tifffile installed it even writes a TIFF under an .exr name)."""
    path = tmp_path / "x.exr"
    path.write_bytes(b"\x76\x2f\x31\x01" + bytes(64))  # EXR magic number, then garbage
    with pytest.raises(InputError, match="cannot read EXR here"):
        read_image(str(path))
    iio.imwrite(tmp_path / "fake.tif", np.ones((2, 2), np.float32))
    os.replace(tmp_path / "fake.tif", tmp_path / "fake.exr")
    with pytest.raises(InputError, match="not a valid EXR file"):
        read_image(str(tmp_path / "fake.exr"))


@pytest.mark.parametrize(
    "make,match",
    [
        (lambda p: None, "no such file"),
        (lambda p: p.with_suffix(".png").write_bytes(b"not a png"), "not a valid PNG file"),
        (lambda p: p.with_suffix(".bmp").write_bytes(b"BM"), "unsupported format '.bmp'"),
        (lambda p: np.save(p.with_suffix(".npy"), np.array([{}], dtype=object)), "pickled"),
        (
            lambda p: np.savez(p.with_suffix(".npz"), a=np.ones((2, 2)), b=np.ones((2, 2))),
            "2 arrays",
        ),
        (lambda p: np.save(p.with_suffix(".npy"), np.ones(5)), r"shape \(5,\) is not an image"),
        (lambda p: np.save(p.with_suffix(".npy"), np.ones((3, 3, 5))), "5 channels"),
        (lambda p: np.save(p.with_suffix(".npy"), np.full((3, 3), np.nan)), "NaN"),
        (lambda p: np.save(p.with_suffix(".npy"), np.ones((3, 3), np.int32)), "int32"),
    ],
)
def test_bad_image_files(tmp_path, make, match):
    base = tmp_path / "x"
    make(base)
    made = [p for p in tmp_path.iterdir()]
    path = str(made[0]) if made else str(base.with_suffix(".png"))
    with pytest.raises(InputError, match=match) as info:
        read_image(path)
    assert path in str(info.value) and "\n" not in str(info.value)


# ---------------------------------------------------------------------------------------------
# Depth


def test_depth_encodings(tmp_path):
    metres = np.array([[0.5, 1.0], [2.0, 40.0]], np.float32)
    np.save(tmp_path / "d.npy", metres)
    np.testing.assert_array_equal(read_depth(str(tmp_path / "d.npy")), metres)

    iio.imwrite(tmp_path / "mm.png", np.round(metres * 1000).astype(np.uint16))
    np.testing.assert_allclose(read_depth(str(tmp_path / "mm.png"), scale=1e-3), metres, rtol=1e-6)
    with pytest.raises(InputError, match="--depth-scale"):
        read_depth(str(tmp_path / "mm.png"))

    inv = np.array([[2.0, 1.0], [0.5, 0.0]], np.float32)  # 1/m; 0 is infinitely far
    np.save(tmp_path / "inv.npy", inv)
    d = read_depth(str(tmp_path / "inv.npy"), inverse=True)
    np.testing.assert_array_equal(d, [[0.5, 1.0], [2.0, np.inf]])

    # OpenGL depth buffer: z = far (Z - near) / (Z (far - near)) inverts linearize_depth.
    near, far = 0.1, 100.0
    z = far * (metres.astype(np.float64) - near) / (metres * (far - near))
    np.save(tmp_path / "z.npy", z)
    d = read_depth(str(tmp_path / "z.npy"), zbuffer=True, near=near, far=far)
    # float32 result: z near 1 loses digits in 1 - z (cond ~ far/near at the far plane).
    np.testing.assert_allclose(d, metres, rtol=2e-5)


def test_depth_holes_are_nan_and_infinity_stays(tmp_path):
    """NaN, 0 and negative depths are holes (no data), read as NaN; `inf` is infinitely far; an
    integer file's 0 counts are holes, an inverse-depth file's 0 is infinity."""
    values = np.array([[1.0, 0.0, np.nan], [-2.0, np.inf, 2.0]])
    np.save(tmp_path / "d.npy", values)
    d = read_depth(str(tmp_path / "d.npy"))
    assert np.isnan(d[0, 1]) and np.isnan(d[0, 2]) and np.isnan(d[1, 0])
    assert d[1, 1] == np.inf and d[0, 0] == 1.0 and d[1, 2] == 2.0
    mm = np.array([[1500, 0], [2000, 2500]], np.uint16)
    np.save(tmp_path / "mm.npy", mm)
    d = read_depth(str(tmp_path / "mm.npy"), scale=1e-3)
    assert np.isnan(d[0, 1]) and np.allclose(d[[0, 1, 1], [0, 0, 1]], [1.5, 2.0, 2.5])
    inv = read_depth(str(tmp_path / "mm.npy"), scale=1e-3, inverse=True)
    assert inv[0, 1] == np.inf


@pytest.mark.parametrize(
    "values,kwargs,match",
    [
        (np.full((2, 2), np.nan), {}, "no data"),
        (np.zeros((2, 2)), {}, "no data"),
        (np.full((2, 2), -1.0), {}, "no data"),
        (np.array([[1.0, -2.0], [1.0, 1.0]]), {"inverse": True}, "inverse depth must be >= 0"),
        (
            np.array([[0.5, 1.5], [0.0, 1.0]]),
            {"zbuffer": True, "near": 0.1, "far": 9.0},
            r"\[0, 1\]",
        ),
        (np.array([[0.5, 0.5], [0.0, 1.0]]), {"zbuffer": True}, "--near and --far"),
        (
            np.array([[0.5, 0.5], [0.0, 1.0]]),
            {"zbuffer": True, "near": 5.0, "far": 1.0},
            "near < far",
        ),
        (np.ones((2, 2, 3)) * [1, 2, 3], {}, "3 different channels"),
    ],
)
def test_bad_depth(tmp_path, values, kwargs, match):
    path = str(tmp_path / "d.npy")
    np.save(path, values.astype(np.float32))
    with pytest.raises(InputError, match=match):
        read_depth(path, **kwargs)


# ---------------------------------------------------------------------------------------------
# Writing


def test_write_is_atomic_and_never_over_an_input(tmp_path):
    src = tmp_path / "in.npy"
    np.save(src, np.ones((3, 3), np.float32))
    before = src.read_bytes()
    with pytest.raises(InputError, match="is also an input"):
        write_image(str(src), np.zeros((3, 3)), bits=None, inputs=[str(src)])
    link = tmp_path / "link.npy"  # another name for the same file
    os.symlink(src, link)
    with pytest.raises(InputError, match="is also an input"):
        write_image(str(link), np.zeros((3, 3)), bits=None, inputs=[str(src)])
    assert src.read_bytes() == before

    out = tmp_path / "out.png"
    out.write_bytes(b"old")

    def failing(tmp):
        with open(tmp, "wb") as fh:
            fh.write(b"half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        _io.atomic_write(str(out), failing)
    assert out.read_bytes() == b"old"  # the old file is untouched, and no temporary is left
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.npy", "link.npy", "out.png"]

    write_image(str(out), np.zeros((3, 3)), bits=8)
    assert iio.imread(out).shape == (3, 3)
    umask = os.umask(0)
    os.umask(umask)
    new = tmp_path / "new.png"
    write_image(str(new), np.zeros((3, 3)), bits=8)
    assert new.stat().st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's private 0600


@pytest.mark.parametrize(
    "name,match", [("x.bmp", "unsupported output format"), ("nope/x.png", "does not exist")]
)
def test_bad_output_paths(tmp_path, name, match):
    with pytest.raises(InputError, match=match):
        write_image(str(tmp_path / name), np.zeros((2, 2)), bits=8)
