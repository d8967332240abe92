"""Camera RAW files: LibRaw (rawpy) decodes them in linear light, `read_exif` reads their lens
fields, `jaxdof info` prints both, and a damaged file is one line naming it.

The RAW file is a DNG written here (tifffile): a 12-bit RGGB mosaic with DNG's colour tags, an
identity colour matrix and a neutral as-shot white balance, so a grey patch stays grey, and the
TIFF/EP lens tags (FocalLength, FNumber, SubjectDistance) in IFD0. All in-process.
"""

import json
import pathlib
import re

import numpy as np
import pytest
import tifffile

import jaxdof
from jaxdof import _exif, _io
from jaxdof._cli import main


rawpy = pytest.importorskip("rawpy")

H, W = 32, 48
BLACK, WHITE = 256, 4095  # 12-bit counts
LENS_TAGS = [  # (tag, TIFF type, count, value): rationals as (numerator, denominator)
    (37386, "2I", 1, (50, 1)),  # FocalLength: 50 mm
    (33437, "2I", 1, (28, 10)),  # FNumber: 2.8
    (37382, "2I", 1, (3, 1)),  # SubjectDistance: 3 m
]


def _dng(path, counts: np.ndarray, *, lens: bool = True) -> str:
    """An uncompressed CFA DNG of `counts` (uint16, H x W) with the tags LibRaw needs."""
    tags = [
        (50706, "B", 4, (1, 4, 0, 0)),  # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0)),  # DNGBackwardVersion
        (50708, "s", 0, "jaxdof test camera"),  # UniqueCameraModel
        (33421, "H", 2, (2, 2)),  # CFARepeatPatternDim
        (33422, "B", 4, (0, 1, 1, 2)),  # CFAPattern: R G / G B
        (50710, "B", 3, (0, 1, 2)),  # CFAPlaneColor
        (50711, "H", 1, 1),  # CFALayout: rectangular
        (50714, "H", 1, BLACK),  # BlackLevel
        (50717, "H", 1, WHITE),  # WhiteLevel
        (50721, "2i", 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1)),  # ColorMatrix1
        (50778, "H", 1, 21),  # CalibrationIlluminant1: D65
        (50728, "2I", 3, (1, 1, 1, 1, 1, 1)),  # AsShotNeutral
        (271, "s", 0, "Maker"),  # Make
        (272, "s", 0, "Model 1"),  # Model
        *(LENS_TAGS if lens else []),
    ]
    tifffile.imwrite(path, counts.astype(np.uint16), photometric=32803, extratags=tags)
    return str(path)


def _grey(level: int) -> np.ndarray:
    return np.full((H, W), BLACK + level, np.uint16)


def _one_line(stderr: str) -> str:
    assert "Traceback" not in stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    return lines[0]


# ---------------------------------------------------------------------------------------------
# Decoding


def test_grey_patch_decodes_linearly(tmp_path):
    """Linear light: a uniform patch comes out grey at (counts - black) / (white - black), and
    twice the counts above black give twice the value; the white level gives 1."""
    one = _io.read_image(_dng(tmp_path / "one.dng", _grey(1000)))
    two = _io.read_image(_dng(tmp_path / "two.dng", _grey(2000)))
    full = _io.read_image(_dng(tmp_path / "full.dng", _grey(WHITE - BLACK)))
    assert one.array.shape == (H, W, 3) and one.array.dtype == np.float32 and one.bits == 16
    # LibRaw's output is 16-bit, its scaling and colour matrix rounded on the way (2 of 65535
    # seen): 4 output counts
    atol = 4 / 65535
    np.testing.assert_allclose(one.array, 1000 / (WHITE - BLACK), rtol=0, atol=atol)
    np.testing.assert_allclose(two.array, 2 * one.array, rtol=0, atol=atol)
    np.testing.assert_allclose(full.array, 1.0, rtol=0, atol=atol)
    assert "linear light" in one.notes[0] and "one.dng" in one.notes[0]
    facts = one.raw_decode
    assert facts is not None
    assert (facts["cfa"], facts["colours"], facts["white_level"]) == ("RG/GB", "RGBG", WHITE)
    assert facts["black_level"] == [BLACK] * 4 and facts["raw_size"] == [W, H]
    assert facts["white_balance_source"] == "as-shot" and facts["demosaic"] == "AHD"


def test_linear_option_does_not_apply(tmp_path):
    """A RAW file is linear already: `linear=True` changes nothing (no sRGB decode either way)."""
    path = _dng(tmp_path / "a.dng", _grey(1000))
    np.testing.assert_array_equal(
        _io.read_image(path).array, _io.read_image(path, linear=True).array
    )


def test_damaged_raw_files(tmp_path, capfd):
    """An unsupported, a truncated and a cut-short RAW file: one `InputError` naming the file,
    and nothing of LibRaw's own printing left on standard error (it prints from C, on fd 2)."""
    good = _dng(tmp_path / "good.dng", _grey(1000))
    data = (tmp_path / "good.dng").read_bytes()
    (tmp_path / "garbage.nef").write_bytes(b"not a raw file at all" * 10)
    (tmp_path / "header.dng").write_bytes(data[:600])
    with tifffile.TiffFile(good) as tif:
        start = tif.pages[0].dataoffsets[0]  # pyright: ignore[reportAttributeAccessIssue]
    (tmp_path / "cut.dng").write_bytes(data[: start + 100])  # the pixels stop early
    for name, why in [
        ("garbage.nef", "Unsupported file format"),
        ("header.dng", "Unexpected end of file"),  # what LibRaw printed, not its return code
        ("cut.dng", "Unexpected end of file"),
    ]:
        path = str(tmp_path / name)
        with pytest.raises(
            _io.InputError, match=f"^{re.escape(path)}: not a readable camera RAW file"
        ) as err:
            _io.read_image(path)
        assert why in str(err.value) and "\n" not in str(err.value)
    assert capfd.readouterr().err == ""


def test_raw_is_not_a_depth_map_and_needs_rawpy(tmp_path, monkeypatch):
    path = _dng(tmp_path / "a.dng", _grey(1000))
    with pytest.raises(_io.InputError, match="camera RAW file is a photo, not a depth map"):
        _io.read_depth(path)
    monkeypatch.setitem(__import__("sys").modules, "rawpy", None)  # `import rawpy` fails
    with pytest.raises(_io.InputError, match=r'pip install rawpy.*pip install "jaxdof\[raw\]"'):
        _io.read_image(path)


# ---------------------------------------------------------------------------------------------
# EXIF


def test_exif_from_dng(tmp_path):
    exif = jaxdof.read_exif(_dng(tmp_path / "a.dng", _grey(1000)))
    assert exif.focal_length == pytest.approx(0.05)
    assert exif.f_number == pytest.approx(2.8)
    assert exif.focus_distance == pytest.approx(3.0)
    assert exif.pixel_pitch is None and exif.notes == ()  # not recorded, not guessed
    assert (exif.make, exif.model) == ("Maker", "Model 1")


def test_exif_from_tiff_structured_raw_with_its_own_magic(tmp_path):
    """ORF (and RW2) are TIFFs under their own first four bytes: the tags are read all the same,
    and the file is left as it was."""
    data = pathlib.Path(_dng(tmp_path / "a.dng", _grey(1000))).read_bytes()
    orf = tmp_path / "a.orf"
    orf.write_bytes(b"IIRO" + data[4:])
    exif = jaxdof.read_exif(orf)
    assert exif.focal_length == pytest.approx(0.05) and exif.f_number == pytest.approx(2.8)
    assert exif.focus_distance == pytest.approx(3.0)
    assert orf.read_bytes()[:4] == b"IIRO"


def test_exif_from_libraw(tmp_path):
    """Without TIFF tags (CR3, RAF) LibRaw's focal length and aperture are taken, with a note that
    it gives no focus distance or pixel pitch; a file without them gets neither."""
    path = _dng(tmp_path / "a.dng", _grey(1000))
    exif = _exif._with_libraw(path, _exif.ExifLens(), ValueError("no TIFF"))
    assert exif.focal_length == pytest.approx(0.05) and exif.f_number == pytest.approx(2.8)
    assert exif.focus_distance is None and exif.source["LibRaw focal_len"] == pytest.approx(50)
    assert len(exif.notes) == 1 and "no focus distance or pixel pitch" in exif.notes[0]
    bare = jaxdof.read_exif(_dng(tmp_path / "bare.dng", _grey(1000), lens=False))
    assert not bare.has_lens and bare.notes == ()


# ---------------------------------------------------------------------------------------------
# jaxdof info


def test_info_shows_lens_and_decode(tmp_path, capsys):
    path = _dng(tmp_path / "a.dng", _grey(1000))
    assert main(["info", path, "--json"]) == 0
    obj = json.loads(capsys.readouterr().out)
    assert (obj["format"], obj["width"], obj["height"], obj["channels"]) == (
        "camera RAW (DNG)",
        W,
        H,
        3,
    )
    assert (obj["dtype"], obj["bits"], obj["encoding"]) == ("uint16", 16, "linear")
    assert obj["exif"]["focal_length"] == pytest.approx(0.05)
    assert obj["exif"]["focus_distance"] == pytest.approx(3.0)
    assert obj["raw"]["cfa"] == "RG/GB" and obj["raw"]["white_level"] == WHITE

    assert main(["info", path]) == 0
    text = capsys.readouterr().out
    assert "50 mm" in text and "f-number        2.8" in text and "3 m" in text
    assert "CFA RG/GB" in text and "black 256/256/256/256 (per RGBG), white 4095" in text
    assert "white balance   as-shot: R 1, G 1, B 1, G 1" in text and "AHD demosaic" in text


def test_info_on_a_damaged_raw_is_one_line(tmp_path, capfd):
    (tmp_path / "bad.cr2").write_bytes(b"II*\x00" + b"\x00" * 64)
    assert main(["info", str(tmp_path / "bad.cr2")]) == 2
    captured = capfd.readouterr()
    assert captured.out == ""
    line = _one_line(captured.err)
    assert "bad.cr2: not a readable camera RAW file (LibRaw:" in line
