"""EXIF: `jaxdof.read_exif` on files Pillow writes (JPEG, TIFF, PNG eXIf), `jaxdof info`, and the
start `jaxdof fit` takes from the photo's metadata.

All in-process and without a solve: the CLI runs through `jaxdof._cli.main` (the function the
`jaxdof` script calls) and `commands.fit_call` (what `fit` hands `fit_lens`); where `fit`'s output
is checked, `fit_lens` is a stub (the fit itself is tests/test_cli.py's and tests/test_fit.py's).
"""

import json
import math

import numpy as np
import pytest
from PIL import ExifTags, Image
from PIL.TiffImagePlugin import IFDRational

import jaxdof
from jaxdof import _io
from jaxdof._cli import commands, main
from jaxdof._cli.demo import demo_scene
from jaxdof._cli.parse import build_parser


H, W = 24, 32  # tests/test_cli.py's scene
IFD0 = ("Make", "Model")  # the rest go in the Exif sub-IFD, where cameras write them
PHONE = {  # a phone's main camera: 2.5 mm f/1.8, 1 um pixels
    "Make": "Phone",
    "Model": "Phone X1",
    "LensModel": "back camera 2.5mm f/1.8",
    "FocalLength": IFDRational(25, 10),
    "FNumber": IFDRational(18, 10),
    "SubjectDistance": IFDRational(3, 1),
    "FocalPlaneXResolution": IFDRational(10000, 1),  # pixels per cm
    "FocalPlaneYResolution": IFDRational(10000, 1),
    "FocalPlaneResolutionUnit": 3,  # cm
    "FocalLengthIn35mmFilm": 26,
}


def _exif(tags: dict) -> bytes:
    exif = Image.Exif()
    for name in IFD0:
        if name in tags:
            exif[ExifTags.Base[name]] = tags[name]
    exif[ExifTags.IFD.Exif] = {ExifTags.Base[k]: v for k, v in tags.items() if k not in IFD0}
    return exif.tobytes()


def _photo(path, tags: dict | None = None, pixels=None):
    """An 8-bit RGB `H x W` photo at `path` (format from its suffix) with `tags` as its EXIF."""
    pixels = np.full((H, W, 3), 128, np.uint8) if pixels is None else pixels
    extra = {} if tags is None else {"exif": _exif(tags)}
    Image.fromarray(pixels).save(path, **extra)
    return str(path)


def _info(path, capsys) -> dict:
    assert main(["info", str(path), "--json"]) == 0
    return json.loads(capsys.readouterr().out)  # exactly one JSON object on stdout


def _one_line(stderr: str) -> str:
    assert "Traceback" not in stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    return lines[0]


# ---------------------------------------------------------------------------------------------
# read_exif


@pytest.mark.parametrize("suffix", [".jpg", ".tif", ".png"])
def test_read_exif_formats(suffix, tmp_path):
    """JPEG (APP1), TIFF (its own tag directory) and PNG (eXIf): the same fields, in SI units."""
    exif = jaxdof.read_exif(_photo(tmp_path / f"photo{suffix}", PHONE))
    assert exif.focal_length == pytest.approx(2.5e-3)
    assert exif.f_number == pytest.approx(1.8)
    assert exif.focus_distance == pytest.approx(3.0)
    assert exif.pixel_pitch == pytest.approx(1e-6)  # 1 cm / 10000
    assert exif.focal_length_35mm == pytest.approx(0.026)
    assert (exif.make, exif.model, exif.lens_model) == ("Phone", "Phone X1", PHONE["LensModel"])
    assert exif.source["FocalLength"] == 2.5 and exif.source["FNumber"] == 1.8
    assert exif.has_lens and exif.notes == ()
    # the focal-plane resolution wins over the 35 mm equivalent: 1 um times the photo's width
    assert exif.sensor_width(W, H) == pytest.approx(W * 1e-6)
    obj = exif.to_dict()
    json.dumps(obj, allow_nan=False)  # JSON-ready
    assert obj["focal_length"] == pytest.approx(2.5e-3) and obj["focus_power"] == pytest.approx(
        1 / 3
    )


def test_read_exif_special_values(tmp_path):
    """SubjectDistance 0xFFFFFFFF is infinity (`null` in JSON, focus power 0) and 0 unknown; a
    zero denominator is left out with a note (0/0 silently: unknown); without FNumber, the APEX
    ApertureValue gives it; FocalLength 0 is unknown; the focal-plane unit defaults to inches;
    the 35 mm equivalent gives the sensor width when the focal-plane resolution does not."""
    tags = {
        "FocalLength": IFDRational(0, 1),
        "ApertureValue": IFDRational(3, 1),  # Av 3: N = 2^1.5
        "SubjectDistance": IFDRational(0xFFFFFFFF, 1),
        "FocalPlaneXResolution": IFDRational(4000, 1),  # per inch (the default unit)
        "FocalLengthIn35mmFilm": 50,
    }
    exif = jaxdof.read_exif(_photo(tmp_path / "a.jpg", tags))
    assert exif.focal_length is None and exif.f_number == pytest.approx(2**1.5)
    assert exif.focus_distance == math.inf
    assert exif.to_dict()["focus_distance"] is None and exif.to_dict()["focus_power"] == 0.0
    assert exif.pixel_pitch == pytest.approx(0.0254 / 4000)

    tags = {
        "FocalLength": IFDRational(50, 1),
        "FNumber": IFDRational(18, 0),
        "SubjectDistance": IFDRational(0, 1),
        "FocalPlaneXResolution": IFDRational(0, 0),
        "FocalLengthIn35mmFilm": 75,  # crop factor 1.5
    }
    exif = jaxdof.read_exif(_photo(tmp_path / "b.jpg", tags))
    assert exif.f_number is None and exif.focus_distance is None and exif.pixel_pitch is None
    assert exif.source["FNumber"] == "18/0"
    assert len(exif.notes) == 1 and "FNumber 18/0 has a zero denominator" in exif.notes[0]
    # the 35 mm frame's diagonal over the crop factor, split in the photo's 4:3 aspect ratio
    diagonal = math.hypot(36e-3, 24e-3) / 1.5
    assert exif.sensor_width(W, H) == pytest.approx(diagonal * 0.8)

    # a focal-plane resolution giving 1 mm pixels (72 per inch: a screen resolution) is bogus
    tags = {"FocalPlaneXResolution": IFDRational(72, 1), "FocalPlaneResolutionUnit": 2}
    exif = jaxdof.read_exif(_photo(tmp_path / "c.jpg", tags))
    assert exif.pixel_pitch is None and "outside 0.1-100 um" in exif.notes[0]
    assert not exif.has_lens


def test_read_exif_float_tiff_ifd0(tmp_path):
    """A float32 RGB TIFF (which Pillow cannot open as an image) with TIFF/EP lens tags in IFD0:
    read from its tag directory."""
    import tifffile

    path = tmp_path / "linear.tif"
    tags = [(0x010F, "s", 0, "Cam", True), (0x920A, "2I", 1, (85, 1), True)]
    tifffile.imwrite(path, np.ones((H, W, 3), np.float32), photometric="rgb", extratags=tags)
    exif = jaxdof.read_exif(path)
    assert exif.focal_length == pytest.approx(0.085) and exif.make == "Cam"
    assert exif.f_number is None


def test_read_exif_without_exif_and_bad_files(tmp_path):
    exif = jaxdof.read_exif(_photo(tmp_path / "plain.png"))
    assert exif == jaxdof.ExifLens() and not exif.has_lens and exif.sensor_width(W, H) is None
    (tmp_path / "garbage.jpg").write_bytes(b"\xff\xd8\xff this is not a JPEG")
    with pytest.raises(ValueError, match="garbage.jpg: not an image whose metadata"):
        jaxdof.read_exif(tmp_path / "garbage.jpg")
    with pytest.raises(ValueError, match="missing.jpg: no such file"):
        jaxdof.read_exif(tmp_path / "missing.jpg")
    with pytest.raises(ValueError, match="is a folder"):
        jaxdof.read_exif(tmp_path)


# ---------------------------------------------------------------------------------------------
# jaxdof info


def test_info_json_reports_the_lens(tmp_path, capsys):
    """The goal: a phone's JPEG with EXIF focal length 2.5 mm and f/1.8; `info --json` reports
    both (SI units), beside what the reader makes of the pixels."""
    obj = _info(_photo(tmp_path / "phone.jpg", PHONE), capsys)
    assert obj["exif"]["focal_length"] == pytest.approx(2.5e-3)
    assert obj["exif"]["f_number"] == pytest.approx(1.8)
    assert obj["exif"]["focus_distance"] == pytest.approx(3.0)
    assert obj["exif"]["sensor_width"] == pytest.approx(W * 1e-6)
    assert obj["exif"]["source"]["FocalLengthIn35mmFilm"] == 26
    assert (obj["format"], obj["width"], obj["height"], obj["channels"]) == ("JPEG", W, H, 3)
    assert (obj["dtype"], obj["bits"], obj["encoding"], obj["alpha"]) == ("uint8", 8, "sRGB", False)

    assert main(["info", str(tmp_path / "phone.jpg")]) == 0
    text = capsys.readouterr().out
    assert "32 x 24 pixels" in text and "2.5 mm (35 mm equivalent 26 mm)" in text
    assert "f-number        1.8" in text and "Phone X1, lens back camera" in text


def test_info_reports_a_jpegs_quality_and_colour_sampling(tmp_path, capsys):
    """`info` on JPEGs: the IJG quality of the luma table and the colour sampling (what `fit`
    reads from the header), also for a 4:4:4 file and a table of the camera's own."""
    pixels = np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(tmp_path / "q90.jpg", quality=90, subsampling=2)
    Image.fromarray(pixels).save(tmp_path / "full.jpg", quality=75, subsampling=0)
    own = {0: list(range(1, 65)), 1: [50] * 64}
    Image.fromarray(pixels).save(tmp_path / "own.jpg", qtables=own, subsampling=2)
    assert _info(tmp_path / "q90.jpg", capsys)["jpeg"] == {"chroma": "4:2:0", "quality": 90}
    assert _info(tmp_path / "full.jpg", capsys)["jpeg"] == {"chroma": "4:4:4", "quality": 75}
    assert _info(tmp_path / "own.jpg", capsys)["jpeg"] == {"chroma": "4:2:0", "quality": None}
    assert main(["info", str(tmp_path / "q90.jpg")]) == 0
    text = capsys.readouterr().out
    assert "quality 90, colour 4:2:0: fit compares the luma in its 8 x 8 blocks" in text
    assert main(["info", str(tmp_path / "own.jpg")]) == 0
    assert "the camera's own table" in capsys.readouterr().out


def test_info_without_exif(tmp_path, capsys):
    """Files without EXIF: `exif` is null; float files are linear, 16-bit PNG 16-bit sRGB, an
    alpha channel is counted (and said to be ignored)."""
    np.save(tmp_path / "depth.npy", np.ones((H, W), np.float32))
    obj = _info(tmp_path / "depth.npy", capsys)
    assert obj["exif"] is None and obj["format"] == "NPY" and obj["channels"] == 1
    assert obj["dtype"] == "float32" and obj["encoding"] == "linear" and obj["colour"] == "grey"
    _io.write_image(str(tmp_path / "deep.png"), np.full((H, W, 3), 0.5), bits=16)
    obj = _info(tmp_path / "deep.png", capsys)
    assert obj["exif"] is None and (obj["dtype"], obj["bits"], obj["encoding"]) == (
        "uint16",
        16,
        "sRGB",
    )
    Image.fromarray(np.zeros((H, W, 4), np.uint8)).save(tmp_path / "rgba.png")
    assert main(["info", str(tmp_path / "rgba.png")]) == 0
    text = capsys.readouterr().out
    assert "4 channels (RGBA)" in text and "alpha ignored" in text and "none (no lens" in text


def test_info_and_fit_help(capsys):
    assert main(["info", "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: jaxdof info") and "--json" in out and "examples:" in out
    assert main(["fit", "--help"]) == 0
    out = capsys.readouterr().out
    assert "--no-exif" in out and "EXIF FocalLength" in out


def test_info_bad_files(tmp_path, capsys):
    """A corrupt or missing file: exit status 2 and one line on stderr naming it."""
    (tmp_path / "garbage.jpg").write_bytes(b"\xff\xd8\xff this is not a JPEG")
    (tmp_path / "text.png").write_text("not a png")
    for name, expect in [
        ("garbage.jpg", "garbage.jpg: not a readable .jpg image"),
        ("text.png", "text.png: not a valid PNG file"),
        ("missing.tif", "missing.tif: no such file"),
    ]:
        assert main(["info", str(tmp_path / name), "--json"]) == 2
        out, err = capsys.readouterr()
        assert out == ""
        line = _one_line(err)
        assert line.startswith("jaxdof info: error:") and expect in line, line


# ---------------------------------------------------------------------------------------------
# jaxdof fit: the start from EXIF


# An 85 mm f/1.4 lens focused at 3 m whose 35 mm equivalent (245 mm, crop factor 2.88) gives a
# 12 mm wide sensor across the 4:3 photo: tests/test_cli.py's lens (0.375 mm pixels, circles up
# to ~3.5 px on this scene).
CAMERA = {
    "Make": "Cam",
    "Model": "Cam 1",
    "FocalLength": IFDRational(85, 1),
    "FNumber": IFDRational(14, 10),
    "SubjectDistance": IFDRational(3, 1),
    "FocalLengthIn35mmFilm": 245,
}
SENSOR = math.hypot(36e-3, 24e-3) * 85 / 245 * 0.8  # m: 12.01 mm


@pytest.fixture
def scene(tmp_path, monkeypatch):
    """tests/test_cli.py's scene: `sharp.png`, `depth.npy`; the photo `photo.jpg` with
    `CAMERA`'s EXIF, `bare.jpg` without EXIF, `photo.npy` (no metadata)."""
    monkeypatch.chdir(tmp_path)
    image, depth = demo_scene(H, W)
    codes = np.round(_io.linear_to_srgb(image) * 255).astype(np.uint8)
    Image.fromarray(codes).save("sharp.png")
    np.save("depth.npy", depth)
    _photo(tmp_path / "photo.jpg", CAMERA, codes)
    _photo(tmp_path / "bare.jpg", None, codes)
    np.save("photo.npy", image)
    return depth


def _call(argv):
    return commands.fit_call(build_parser().parse_args(["fit", "sharp.png", "depth.npy", *argv]))


def _lens(lens):
    return tuple(
        float(getattr(lens, name)) for name in ("focal_length", "f_number", "focus_distance")
    )


def test_fit_starts_from_exif(scene, capsys):
    """No lens options: the start is the photo's EXIF (focal length held, f-number and focus the
    init, the sensor width from the 35 mm equivalent); stderr says so in one line."""
    call = _call(["photo.jpg"])
    assert _lens(call.init) == pytest.approx((0.085, 1.4, 3.0))
    assert float(call.init.pixel_pitch) == pytest.approx(SENSOR / W)
    assert "focal_length" not in call.kwargs["free"]  # held at the EXIF value
    assert call.exif is not None
    assert call.exif["used"] == ["focal_length", "f_number", "focus_distance", "sensor_width"]
    assert call.exif["overridden"] == [] and call.exif["file"] == "photo.jpg"
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("photo.jpg: EXIF Cam 1: focal length 85 mm (35 mm equivalent 245 mm)")
    assert "f/1.4" in line and "focus 3 m" in line and "(focal length held)" in line
    json.dumps(call.exif, allow_nan=False)


def test_fit_options_override_exif(scene, capsys):
    """Options given override the EXIF values one by one; the rest still come from EXIF."""
    call = _call(["photo.jpg", "--f-number", "4", "--focus", "5m", "--sensor-width", "12mm"])
    assert _lens(call.init) == pytest.approx((0.085, 4.0, 5.0))
    assert float(call.init.pixel_pitch) == pytest.approx(0.012 / W)
    assert call.exif is not None and call.exif["used"] == ["focal_length"]
    assert call.exif["overridden"] == ["f_number", "focus_distance", "sensor_width"]
    assert "overridden by --f-number, --focus, --sensor-width" in capsys.readouterr().err


def test_fit_no_exif(scene, capsys):
    """`--no-exif`, a JPEG without EXIF and a `.npy` photo start as before EXIF was read: the
    options and their defaults (f/4, the median depth, a 36 mm sensor), nothing said; without
    --focal-length the fit is refused in one line (exit 2) before any work."""
    depth = scene
    expected = (0.085, 4.0, float(np.median(depth)))
    for argv in (["photo.jpg", "--no-exif"], ["bare.jpg"], ["photo.npy"]):
        call = _call([*argv, "--focal-length", "85mm"])
        assert _lens(call.init) == pytest.approx(expected), argv
        assert float(call.init.pixel_pitch) == pytest.approx(0.036 / W)
        assert call.exif is None
    assert capsys.readouterr().err == ""
    for argv, why in [
        (["photo.jpg", "--no-exif"], "(--no-exif)"),
        (["bare.jpg"], "(bare.jpg has no EXIF FocalLength)"),
    ]:
        assert main(["fit", "sharp.png", "depth.npy", *argv]) == 2
        line = _one_line(capsys.readouterr().err)
        assert "the starting focal length is unknown" in line and why in line, line


def test_fit_output_says_what_exif_gave(scene, capsys, monkeypatch):
    """`fit --json` carries the EXIF it read under "exif" (a stub `fit_lens`: the solve is
    tested elsewhere); without EXIF there is no "exif" key."""
    calls = []

    def fit_lens(image, depth, target, init, **kwargs):
        calls.append(init)
        return _Result()

    monkeypatch.setattr(commands.jaxdof, "fit_lens", fit_lens)
    assert main(["fit", "sharp.png", "depth.npy", "photo.jpg", "--json", "--quiet"]) == 0
    out, err = capsys.readouterr()
    obj = json.loads(out)
    assert obj["exif"]["focal_length"] == pytest.approx(0.085) and obj["exif"]["make"] == "Cam"
    assert obj["exif"]["sensor_width"] == pytest.approx(SENSOR)
    assert _lens(calls[0]) == pytest.approx((0.085, 1.4, 3.0))
    assert "EXIF" in _one_line(err)
    assert (
        main(["fit", "sharp.png", "depth.npy", "photo.npy", "--focal-length", "85mm", "--json"])
        == 0
    )
    assert "exif" not in json.loads(capsys.readouterr().out)


class _Result:
    """The little of a `FitResult` that `fit --json` reads (`to_dict`)."""

    def to_dict(self):
        return {"success": True, "focal_length": 0.085}
