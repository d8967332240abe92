"""The `jaxdof` argument parser: commands, options, and the option types (lengths, positives).

A usage error is one line on stderr and exit status 2 (`Parser`). Option types check syntax and
sign only; the physics of the values (a focus beyond the focal length, depths beyond it) is the
library's to check, and `commands` reports its `ValueError` as the same kind of one-line error.
"""

from __future__ import annotations

import argparse
import math
import re


FIELDS = ("focal_length", "f_number", "focus_distance")
DEFAULT_MEMORY = 3 * 2**30  # bytes: `render --memory`
_UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}
_LENGTH = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(mm|cm|m)?\s*$")


def method_names() -> tuple[str, ...]:
    """The names `--method` accepts: the library's string aliases of its filter methods that run
    in their default configuration (`jitter` needs a random key, which the CLI does not take).

    The one place the CLI learns them (`render` and `fit_lens` take the alias as `method=`).
    """
    from .._filters import METHOD_ALIASES, as_method

    def runs_by_default(name: str) -> bool:
        try:
            as_method(name)
        except ValueError:
            return False
        return True

    return tuple(n for n in METHOD_ALIASES if runs_by_default(n))


class Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line on stderr (and exit status 2), not a usage block."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


# ----------------------------------------------------------------------------------------------
# Option types


def _length(text: str) -> tuple[float, str | None]:
    """`text` as `(metres, unit or None)`; positive and finite."""
    match = _LENGTH.match(text)
    if match is None:
        raise argparse.ArgumentTypeError(
            f"bad length {text!r}: give a number with a unit mm, cm or m (e.g. 50mm, 3m)"
        )
    unit = match.group(2)
    value = float(match.group(1)) * _UNITS[unit or "m"]
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"bad length {text!r}: must be positive and finite")
    return value, unit


def parse_length(text: str) -> float:
    """`"50mm"`, `"3.5 cm"`, `"3m"` or a bare number (metres) to metres; positive and finite."""
    return _length(text)[0]


_INFINITY = ("inf", "+inf", "infinity", "+infinity")


def parse_focus(text: str) -> float:
    """As `parse_length`, and `inf` or `infinity` (any case): focused at infinity (`math.inf`).

    Only the focus distance may be infinite; every other length stays finite.
    """
    if text.strip().lower() in _INFINITY:
        return math.inf
    return parse_length(text)


def parse_border(text: str) -> str | int:
    """`fit --border`: `auto` (the window's band), `off` (0: keep every pixel) or a width >= 0."""
    word = text.strip().lower()
    if word in ("auto", "off"):
        return "auto" if word == "auto" else 0
    try:
        value = int(word)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(
            f"bad border {text!r}: give auto, off or a width in photo pixels (an integer >= 0)"
        )
    return value


def parse_edge_weight(text: str) -> bool | float | None:
    """`fit --edge-weight`: `auto` (None: the fit decides), `on`, `off` or a width > 0 (px)."""
    word = text.strip().lower()
    if word in ("auto", "on", "off"):
        return {"auto": None, "on": True, "off": False}[word]
    try:
        value = float(word)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(
            f"bad edge weight {text!r}: give auto, on, off or a width in photo pixels (> 0)"
        )
    return value


def parse_tiles(text: str) -> str | int | None:
    """`fit --tiles`: `auto` (tiles for photos over 1 MP), `off` (the whole frame) or a budget
    of photo pixels > 0."""
    word = text.strip().lower()
    if word in ("auto", "off"):
        return "auto" if word == "auto" else None
    try:
        value = int(word)
    except ValueError:
        value = 0
    if value <= 0:
        raise argparse.ArgumentTypeError(
            f"bad tiles {text!r}: give auto, off or a budget of photo pixels (an integer > 0)"
        )
    return value


def parse_focal_length(text: str) -> float:
    """As `parse_length`, but a bare number of 1 or more (`50`) is refused: it is surely mm."""
    value, unit = _length(text)
    if unit is None and value >= 1:
        raise argparse.ArgumentTypeError(
            f"bare number {text!r} would be {value:g} metres; give a unit, e.g. {text.strip()}mm"
        )
    return value


def _parse_number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"bad number {text!r}") from None


def parse_positive(text: str) -> float:
    value = _parse_number(text)
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r} must be positive and finite")
    return value


_BYTES = re.compile(r"^\s*(\d+\.?\d*|\.\d+)\s*(?:([kmgt])i?b?|(b))?\s*$", re.IGNORECASE)


def parse_memory(text: str) -> int:
    """`render --memory`: `3GB`, `2.5G`, `800MB`, `800M`, `1.5GiB` (binary units: 1 GB = 2^30
    bytes), `100B`, or a bare number of GB; positive. Returns bytes."""
    match = _BYTES.match(text)
    value = float(match.group(1)) if match else 0.0
    if match is None or value <= 0:
        raise argparse.ArgumentTypeError(
            f"bad memory size {text!r}: give a positive size with a unit, e.g. 3GB or 800MB"
        )
    prefix, plain_bytes = match.group(2), match.group(3)
    power = 0 if plain_bytes else "kmgt".index(prefix.lower()) + 1 if prefix else 3
    return int(value * 1024**power)


def parse_nonnegative(text: str) -> float:
    value = _parse_number(text)
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number >= 0")
    return value


# ----------------------------------------------------------------------------------------------
# Option groups


def _add_lens_options(p: argparse.ArgumentParser, *, start: bool) -> None:
    what = "starting " if start else ""
    exif = "the first TARGET's EXIF " if start else ""
    g = p.add_argument_group(
        "lens" + (" (the starting point of the fit)" if start else ""),
        "Lengths take a unit: mm, cm or m (a bare number is metres; --focal-length 50 is refused).\n"
        "--focus also takes inf (or infinity): focused at infinity, printed as inf in text and\n"
        "as null in --json."
        + (
            "\nUnset, each comes from the first TARGET's EXIF metadata where it has it (FocalLength,\n"
            "FNumber, SubjectDistance, and the sensor width from FocalPlaneXResolution or\n"
            "FocalLengthIn35mmFilm), else from its default; --no-exif ignores the metadata."
            if start
            else ""
        ),
    )
    g.add_argument(
        "--focal-length",
        type=parse_focal_length,
        required=not start,
        default=None,
        metavar="LEN",
        help=f"{what}focal length, e.g. 50mm" + (f" (default: {exif}FocalLength)" if start else ""),
    )
    g.add_argument(
        "--f-number",
        type=parse_positive,
        required=not start,
        default=None,
        metavar="N",
        help=f"{what}f-number N = f/D, e.g. 2"
        + (f" (default: {exif}FNumber, else 4)" if start else ""),
    )
    g.add_argument(
        "--focus",
        type=parse_focus,
        required=not start,
        default=None,
        metavar="LEN",
        help=f"{what}focus distance, e.g. 3m, or inf"
        + (
            f" (default: {exif}SubjectDistance, else the median depth of the scene)"
            if start
            else ""
        ),
    )
    g.add_argument(
        "--sensor-width",
        type=parse_length,
        default=None,
        metavar="LEN",
        help="sensor width spanned by the image's columns (default "
        + (f"from {exif}where it says, else " if start else "")
        + "36mm, full frame)",
    )


def _add_cache_option(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--no-cache",
        dest="cache",
        action="store_false",
        help="trace and compile every program anew: do not keep them in (or load them from) "
        "the cache folder ($JAXDOF_CACHE_DIR, else $XDG_CACHE_HOME/jaxdof, else "
        "~/.cache/jaxdof), which makes the same command on photos of the same size start in "
        "seconds",
    )


def _add_file_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group(
        "files",
        "Integer images (8/16-bit PNG, TIFF, JPEG) are sRGB: decoded to linear light, encoded\n"
        "back on output. Float files (float TIFF, .npy, .npz) are linear. EXR is not readable\n"
        "here (no imageio backend for it): convert to float32 TIFF or .npy.\n"
        "Depth is z-depth along the optical axis, in metres.",
    )
    g.add_argument(
        "--linear", action="store_true", help="take integer image files as linear light too"
    )
    g.add_argument(
        "--depth-scale",
        type=parse_length,
        metavar="LEN",
        help="metres per count of an integer depth file (e.g. 1mm for millimetre PNGs); with "
        "--inverse-depth, 1/m per count (a bare number)",
    )
    g.add_argument(
        "--zbuffer",
        action="store_true",
        help="depth file is an OpenGL depth buffer in [0, 1] (needs --near, --far)",
    )
    g.add_argument("--near", type=parse_length, metavar="LEN", help="near clip plane for --zbuffer")
    g.add_argument("--far", type=parse_length, metavar="LEN", help="far clip plane for --zbuffer")
    g.add_argument(
        "--inverse-depth", action="store_true", help="depth file holds 1/depth (1/m; 0 = infinity)"
    )


def _add_method_option(g, help: str, default: str | None = "soft") -> None:
    g.add_argument("--method", choices=method_names(), default=default, help=help)


def _add_footprint_options(g, *, fit: bool = False) -> None:
    if fit:
        g.add_argument(
            "--footprint",
            action=argparse.BooleanOptionalAction,
            default=None,
            help="force the pixel-footprint correction on (--footprint) or off (--no-footprint); "
            "default: on where the starting lens's median circle is under a few pixels",
        )
    else:
        g.add_argument(
            "--footprint",
            action=argparse.BooleanOptionalAction,
            default=None,
            help="correct for the pixel footprint (blur variance r^2/4 at every radius) or not "
            "(--no-footprint); default off, except with --method auto, where the scene decides",
        )
    g.add_argument(
        "--downsample",
        type=int,
        default=1,
        metavar="S",
        help="IMAGE and DEPTH are S times the photo's resolution in each axis (e.g. a pixel-shift "
        "capture): blur there, then average S x S blocks into the photo's pixels (default 1)",
    )


def _add_filter_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("filter")
    _add_method_option(g, "filter (default: soft)")
    g.add_argument(
        "--max-radius",
        type=parse_nonnegative,
        metavar="PX",
        help="largest circle of confusion in pixels; larger ones are clamped (default: the "
        "largest in the scene)",
    )
    g.add_argument(
        "--normalize",
        action="store_true",
        help="keep brightness at the borders (divide by the filtered image of ones)",
    )
    g.add_argument(
        "--fill-holes",
        action="store_true",
        help="fill depth holes (0, negative or NaN: no data) from their nearest pixel; "
        "without it a depth map with holes is refused (fit leaves the pixels they reach out)",
    )
    _add_footprint_options(g)


# ----------------------------------------------------------------------------------------------
# Commands

_EPILOG_RENDER = """\
examples:
  jaxdof render sharp.png depth.tif -o blurred.png --focal-length 50mm --f-number 2 --focus 3m
  jaxdof render sharp.tif depth.png --depth-scale 1mm -o out.tif \\
      --focal-length 85mm --f-number 1.4 --focus 2.5m --sensor-width 23.5mm
  jaxdof render sharp.npy zbuf.npy --zbuffer --near 0.1m --far 100m -o out.npy \\
      --focal-length 35mm --f-number 2.8 --focus 4m
  jaxdof render sharp24mp.tif depth.npy -o out.tif --memory 2GB \\
      --focal-length 50mm --f-number 1.8 --focus 3m

A frame whose render would need more than --memory is rendered in bands of rows, each with a
halo of the largest circle's reach, which gives the same pixels; when even a band of one row
cannot fit, the command says what it needs (exit status 2).
"""

_EPILOG_FIT = """\
examples:
  jaxdof fit sharp.png depth.tif photo.png --focal-length 50mm --f-number 4 --focus 5m
  jaxdof fit sharp.png depth.tif a.png b.png c.png --focal-length 50mm \\
      --free focal_length f_number focus_distance --shared focal_length f_number --json
  jaxdof fit sharp.tif depth.npy photo.tif --focal-length 85mm --plot fit.png
  jaxdof fit sharp.png depth.tif photo.png --focal-length 24mm --focus inf \
      --weight mask.png --border off --json

From one photo only the blur scale K = f^2/(2N(d_f - f))/pitch and the focus distance can be
measured, so by default --free is f_number focus_distance with the focal length held; a focus
bracket (several photos, --shared focal_length f_number) also determines the focal length.

A camera's photo says its lens in its EXIF metadata: the lens options left unset come from the
first TARGET's (focal length, f-number, focus distance, sensor width), and a line on stderr (and
"exif" in --json) says what was read and used; options given override it, --no-exif ignores it.
  jaxdof fit sharp.png depth.tif photo.jpg          # the focal length from EXIF, held
"""

_EPILOG_INFO = """\
examples:
  jaxdof info photo.jpg
  jaxdof info photo.tif --json
  jaxdof info photo.nef            # a camera RAW file, as LibRaw decodes it (needs rawpy)
"""

_EPILOG_DEMO = """\
examples:
  jaxdof demo
  jaxdof demo --out blurred_scene.png
"""

_FORMAT = argparse.RawDescriptionHelpFormatter


def _add_demo(sub) -> None:
    demo = sub.add_parser(
        "demo",
        help="render a built-in scene through a known lens and fit the lens back (no files needed)",
        description="Render a built-in procedural scene through a known lens (85mm f/1.4 at 3m), "
        "fit the lens back from a wrong start (f/4 at 5m), print truth beside the recovered values "
        "with standard errors, and write a figure (sharp, target, refit, residual, CoC map).",
        epilog=_EPILOG_DEMO,
        formatter_class=_FORMAT,
    )
    demo.add_argument("--out", default="demo.png", metavar="PNG", help="figure path (demo.png)")
    demo.add_argument("--quiet", action="store_true", help="no progress on stderr")
    _add_cache_option(demo)


def _add_render(sub) -> None:
    render = sub.add_parser(
        "render",
        help="render depth of field from an all-in-focus image and a depth map",
        description="Blur IMAGE as a thin lens would, given the z-depth of every pixel in DEPTH.",
        epilog=_EPILOG_RENDER,
        formatter_class=_FORMAT,
    )
    render.add_argument("image", metavar="IMAGE", help="all-in-focus image")
    render.add_argument("depth", metavar="DEPTH", help="depth map, same height and width")
    render.add_argument(
        "-o",
        "--out",
        required=True,
        metavar="OUT",
        help="output (.png, .tif, .jpg, .npy, .npz); integer formats keep the input's bit depth",
    )
    render.add_argument(
        "--memory",
        type=parse_memory,
        default=DEFAULT_MEMORY,
        metavar="SIZE",
        help="memory budget, e.g. 3GB or 800MB (default 3GB): a frame whose render would need "
        "more is rendered in bands of rows (the same pixels), as high as the budget allows",
    )
    render.add_argument("--quiet", action="store_true", help="no progress on stderr")
    _add_cache_option(render)
    _add_lens_options(render, start=False)
    _add_filter_options(render)
    _add_file_options(render)


def _add_fit_pixels(fit) -> None:
    """`fit`'s options that choose which photo pixels are fitted: weights, border, tiles."""
    fit.add_argument(
        "--weight",
        metavar="FILE",
        help="per-pixel weights >= 0 (an inverse variance) or a 0/1 mask, (H, W) at the photo's "
        "pixels (the TARGETs'), the same for every TARGET: grayscale, or RGB with equal channels "
        "(one is taken); integer files scale to [0, 1] (no sRGB decoding), float files are as "
        "they are; 0 leaves a pixel out of the fit",
    )
    fit.add_argument(
        "--border",
        type=parse_border,
        default="auto",
        metavar="{auto,off,N}",
        help="the band along the photo's edges left out of the fit, where light from outside the "
        "frame lands: auto (default: the filter window's reach), off (keep every pixel) or N "
        "photo pixels",
    )
    fit.add_argument(
        "--edge-weight",
        type=parse_edge_weight,
        default=None,
        metavar="{auto,on,off,PX}",
        help="weight the photo pixels near depth edges down: auto (default: where the edges "
        "matter at the starting circles), on (the automatic width), off, or a width in photo "
        "pixels",
    )
    fit.add_argument(
        "--tiles",
        type=parse_tiles,
        default="auto",
        metavar="{auto,off,N}",
        help="fit on informative tiles of the photo: auto (default: 2^17 pixels of tiles for "
        "photos over 2^20 pixels), off (the whole frame) or a budget of N photo pixels",
    )
    _add_fit_camera(fit)
    fit.add_argument(
        "--memory",
        type=parse_memory,
        default=None,
        metavar="SIZE",
        help="memory the fit may use besides the files as read, e.g. 8GB (default: what the "
        "machine has available once they are read): a fit "
        "estimated to need more stops before it starts, saying what would fit",
    )


def _add_fit_camera(fit) -> None:
    """`fit`'s switches for what the camera added: the nuisances, the luma comparison and the
    JPEG blocks."""
    when = "where a score test at the fit without it asks for it"
    for name, what in (
        ("exposure", f"fit a gain and offset per TARGET: auto (default: {when})"),
        ("vignetting", f"fit a radial gain 1 + a r^2 + b r^4 per TARGET: auto (default: {when})"),
        (
            "illumination",
            f"fit a gain tilted across the frame 1 + c_x u + c_y v per TARGET: auto (default: "
            f"{when})",
        ),
        (
            "registration",
            f"fit a shift and magnification (focus breathing) per TARGET: auto (default: {when})",
        ),
        (
            "luma",
            "compare the photos in their sRGB luma: auto (default: on for a JPEG TARGET with "
            "half-resolution colour, 4:2:0 or 4:2:2, as cameras write; else where a TARGET has "
            "lost the all-in-focus image's colour detail)",
        ),
        (
            "jpeg",
            "with the luma, compare a JPEG TARGET in its 8x8 blocks to within half its "
            "quantisation steps (what the file holds): auto (default: where the decoded photo's "
            "coefficients lie on a quantisation lattice)",
        ),
    ):
        fit.add_argument(
            f"--{name}", choices=("auto", "on", "off"), default="auto", help=f"{what}, on or off"
        )


def _add_fit(sub) -> None:
    fit = sub.add_parser(
        "fit",
        help="calibrate a lens: fit it to photos of the scene (TARGETs)",
        description="Fit the lens that turns IMAGE (all in focus) with DEPTH into each TARGET "
        "photo (Levenberg-Marquardt on the rendered residual).",
        epilog=_EPILOG_FIT,
        formatter_class=_FORMAT,
    )
    fit.add_argument("image", metavar="IMAGE", help="all-in-focus image")
    fit.add_argument("depth", metavar="DEPTH", help="depth map, same height and width")
    fit.add_argument("targets", metavar="TARGET", nargs="+", help="photo(s) taken through the lens")
    _add_fit_fields(fit)
    _add_method_option(
        fit,
        "filter of the forward model (default: chosen by the fit: soft, or occlusion where depth "
        "edges matter at the starting circles); it must have a derivative in the radius",
        default=None,
    )
    _add_footprint_options(fit, fit=True)
    fit.add_argument(
        "--max-radius",
        type=parse_nonnegative,
        metavar="PX",
        help="filter window in pixels (default: chosen by the fit)",
    )
    _add_fit_pixels(fit)
    fit.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object on stdout (SI units; an infinite focus distance is null)",
    )
    fit.add_argument("--plot", metavar="PNG", help="write a comparison figure (needs matplotlib)")
    fit.add_argument("--quiet", action="store_true", help="no progress on stderr")
    _add_cache_option(fit)
    fit.add_argument(
        "--no-exif",
        action="store_true",
        help="ignore the first TARGET's EXIF metadata: start from the lens options and their "
        "defaults alone (--focal-length is then required)",
    )
    _add_lens_options(fit, start=True)
    _add_file_options(fit)


def _add_fit_fields(fit) -> None:
    """`jaxdof fit`'s free and shared lens fields and its solver's steps."""
    fit.add_argument(
        "--free",
        nargs="+",
        choices=FIELDS,
        default=["focus_distance", "f_number"],
        metavar="FIELD",
        help="lens fields to fit (default: focus_distance f_number); one of " + ", ".join(FIELDS),
    )
    fit.add_argument(
        "--shared",
        nargs="+",
        choices=FIELDS,
        default=[],
        metavar="FIELD",
        help="free fields shared by all targets (the others get one value per target)",
    )
    fit.add_argument("--max-steps", type=int, default=100, metavar="N", help="solver steps (100)")
    fit.add_argument(
        "--steps",
        action="store_true",
        help="show every solver step and the lens it reached (a host callback in each solve: "
        "its programs are then compiled anew each run, not loaded from the cache)",
    )


def _add_info(sub) -> None:
    info = sub.add_parser(
        "info",
        help="print what jaxdof reads from an image file: size, channels, encoding, EXIF lens",
        description="Print what jaxdof reads from FILE: its size, channels, bit depth and type, "
        "the colour encoding it is read with (integers as sRGB, floats as linear light), and "
        "the lens fields of its EXIF metadata (focal length, f-number, focus distance, pixel "
        "pitch), which `fit` starts from. A camera RAW file (DNG, CR2, CR3, NEF, ARW, RAF, ORF, "
        "RW2, PEF, SRW, ...) is decoded by LibRaw in linear light; info adds its mosaic, black "
        "and white levels and the white balance used.",
        epilog=_EPILOG_INFO,
        formatter_class=_FORMAT,
    )
    info.add_argument(
        "file", metavar="FILE", help="image file (PNG, TIFF, JPEG, .npy, .npz, camera RAW)"
    )
    info.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object on stdout (SI units; an infinite focus distance is null, "
        "with focus_power 0)",
    )


PAPERS = {"a4": (0.297, 0.210), "a3": (0.420, 0.297), "letter": (0.2794, 0.2159)}  # landscape
_SIZE = re.compile(r"^\s*(\d+\.?\d*|\.\d+)\s*[xX]\s*(\d+\.?\d*|\.\d+)\s*(mm|cm|m)\s*$")
_PIXELS = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*$")


def parse_size(text: str) -> tuple[float, float]:
    """`chart --size`: `WxH` with a unit, e.g. `297x210mm`, to metres."""
    match = _SIZE.match(text)
    if match is None:
        raise argparse.ArgumentTypeError(
            f"bad size {text!r}: give width x height with a unit, e.g. 297x210mm"
        )
    w, h = (float(match.group(k)) * _UNITS[match.group(3)] for k in (1, 2))
    if not (w > 0 and h > 0):
        raise argparse.ArgumentTypeError(f"bad size {text!r}: must be positive")
    return w, h


def parse_pixels(text: str) -> tuple[int, int]:
    """`chart --screen-px`: `WxH` in pixels, e.g. `3840x2160`."""
    match = _PIXELS.match(text)
    if match is None or min(int(match.group(1)), int(match.group(2))) < 64:
        raise argparse.ArgumentTypeError(
            f"bad screen size {text!r}: give width x height in pixels, e.g. 3840x2160"
        )
    return int(match.group(1)), int(match.group(2))


_EPILOG_CHART = """\
examples:
  jaxdof chart a4chart                       # a4chart.png, a4chart.pdf, a4chart.json
  jaxdof chart big --paper a3 --dpi 300 --seed 7
  jaxdof chart screen --monitor --screen-px 3840x2160 --screen-width 0.6m

Print the PDF at 100 % (actual size) on matte paper and check its size with a ruler; a
screen's chart is shown from the PNG full screen, one image pixel per screen pixel.
Then photograph it tilted by 10 degrees or more, and run jaxdof calibrate.
"""

_EPILOG_CALIBRATE = """\
examples:
  jaxdof calibrate photo.jpg --chart a4chart.json               # lens from EXIF
  jaxdof calibrate photo.tif --chart a4chart.json --focal-length 50mm --sensor-width 36mm
  jaxdof calibrate a.jpg b.jpg c.jpg --chart a4chart.json --json  # a focus bracket

The chart gives the fit its all-in-focus image and depth map: its black frame and markers give
its pose (the frame's edges survive strong defocus; the pose is refined against the photo), its
texture the blur. The chart must be tilted by 10 degrees or more (a depth range), and every
photo of one run taken from where the first was (a tripod). From one photo the blur scale and
the focus distance are measured; the f-number follows from the focal length held.
"""


def _add_chart(sub) -> None:
    chart = sub.add_parser(
        "chart",
        help="make a calibration chart to print or show on a screen (PNG, PDF, JSON sidecar)",
        description="Write a calibration chart: a black frame and ArUco markers around a "
        "dead-leaves texture, as "
        "STEM.png (16-bit), STEM.pdf at its printed size, and STEM.json, the sidecar that "
        "jaxdof calibrate reads.",
        epilog=_EPILOG_CHART,
        formatter_class=_FORMAT,
    )
    chart.add_argument("stem", metavar="STEM", help="the files' path without a suffix")
    size = chart.add_mutually_exclusive_group()
    size.add_argument(
        "--paper", choices=sorted(PAPERS), default=None, help="paper, landscape (default a4)"
    )
    size.add_argument("--size", type=parse_size, metavar="WxH", help="size, e.g. 250x180mm")
    chart.add_argument("--dpi", type=parse_positive, default=300, help="print resolution (300)")
    chart.add_argument("--seed", type=int, default=0, help="the texture's seed (0)")
    chart.add_argument(
        "--monitor",
        action="store_true",
        help="a chart for a screen (needs --screen-px, --screen-width)",
    )
    chart.add_argument("--screen-px", type=parse_pixels, metavar="WxH", help="e.g. 3840x2160")
    chart.add_argument(
        "--screen-width",
        type=parse_length,
        metavar="LEN",
        help="the screen's visible width, e.g. 0.6m",
    )
    chart.add_argument("--overwrite", action="store_true", help="replace files that exist")


def _add_calibrate(sub) -> None:
    cal = sub.add_parser(
        "calibrate",
        help="calibrate a lens from photos of a chart made by jaxdof chart",
        description="Find the chart in each PHOTO, build its all-in-focus image and depth map, "
        "and fit the lens (focus distance and blur scale) as jaxdof fit does.",
        epilog=_EPILOG_CALIBRATE,
        formatter_class=_FORMAT,
    )
    cal.add_argument("photos", metavar="PHOTO", nargs="+", help="photo(s) of the chart")
    cal.add_argument("--chart", required=True, metavar="JSON", help="the chart's sidecar")
    cal.add_argument(
        "--focal-length",
        type=parse_focal_length,
        metavar="LEN",
        help="the lens's focal length, e.g. 50mm (default: the first PHOTO's EXIF)",
    )
    cal.add_argument(
        "--sensor-width",
        type=parse_length,
        metavar="LEN",
        help="the sensor width the photo spans, e.g. 36mm (default: from EXIF); with "
        "--focal-length it fixes the camera's focal length in pixels, else the markers do",
    )
    cal.add_argument("--linear", action="store_true", help="take integer photo files as linear")
    cal.add_argument("--no-exif", action="store_true", help="ignore the photos' EXIF metadata")
    cal.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object on stdout: fit's, with the chart's findings under \"chart\"",
    )
    cal.add_argument("--plot", metavar="PNG", help="write a comparison figure (needs matplotlib)")
    cal.add_argument("--quiet", action="store_true", help="no progress on stderr")
    _add_cache_option(cal)


def build_parser() -> argparse.ArgumentParser:
    """The `jaxdof` parser; `args.command` names the command (`demo`, `render`, `fit`, `info`,
    `chart`, `calibrate`)."""
    from .. import __version__

    parser = Parser(
        prog="jaxdof",
        description="Differentiable thin-lens depth of field: render defocus blur from an "
        "all-in-focus image and a depth map, or calibrate a lens from photos.",
        epilog="Run 'jaxdof COMMAND --help' for each command's options and examples.\n"
        "Exit status: 0 done, 1 the fit did not converge, 2 bad input (one line on stderr).",
        formatter_class=_FORMAT,
    )
    parser.add_argument("--version", action="version", version=f"jaxdof {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    _add_demo(sub)
    _add_render(sub)
    _add_fit(sub)
    _add_info(sub)
    _add_chart(sub)
    _add_calibrate(sub)
    return parser
