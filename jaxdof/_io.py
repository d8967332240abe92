"""Image files in, float linear-light numpy arrays out (and back): the imageio/numpy boundary.

Everything here is plain numpy: no JAX. The command line (`jaxdof._cli`) reads files with
`read_image` and `read_depth`, filters them with the library, and writes with `write_image`.

**Conventions.**

- Integer files (8- and 16-bit PNG, TIFF, JPEG) hold sRGB-encoded values: they are decoded to
  linear light (IEC 61966-2-1 transfer curve) before any filtering, because blur mixes light, not
  encoded values, and encoded back when written. `linear=True` takes their values as linear.
- Float files (float TIFF, `.npy`, `.npz`) are linear already.
- Camera RAW files (DNG and the vendors' formats LibRaw reads, `RAW_SUFFIXES`) are decoded by
  LibRaw through rawpy (the `raw` extra) in linear light: the sensor's counts less the black
  level, scaled so the white level is 1, the camera's as-shot white balance, converted to sRGB
  (Rec. 709) primaries without the sRGB transfer curve, 16 bits per channel, the camera's
  orientation applied (`read_camera_raw`). They are the best input for a fit: no tone curve and no
  sharpening. `linear` does not apply to them.
- Depth is z-depth along the optical axis in metres: float files as they are, integer files
  times a scale (metres per count), an OpenGL depth buffer through `jaxdof.linearize_depth`, or
  inverse depth (1/m).
- `.npy`/`.npz` are always read with `allow_pickle=False`: a pickle can run code on load.
- Writes are atomic: a temporary file in the destination's folder, then `os.replace`, so a
  reader never sees half a file and a failed write leaves the old file as it was. An output
  path that names an input file is refused.

**Files imageio cannot read correctly here.** Pillow (imageio's PNG backend) reads 16-bit colour
PNGs as 8 bits per channel, silently. `_read_png16_colour` decodes them at full precision by
running Pillow's decoder twice, once for the high and once for the low byte of each sample.
EXR needs an imageio backend (opencv, pyav or freeimage) that is not a dependency of jaxdof (and
none of them is exercised here), so an EXR file gets a message that says so and suggests float32
TIFF or `.npy`, which are linear like EXR.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import struct
import sys
import tempfile
import zlib
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np


# Camera RAW formats LibRaw decodes, the common ten first (error messages list those): Adobe DNG,
# Canon, Nikon, Sony, Fujifilm, Olympus/OM, Panasonic, Pentax, Samsung; then older and rarer ones
# (Canon CRW, Nikon NRW, Sony SRF/SR2, Leica RWL, Hasselblad, Phase One, Leaf, Mamiya, Kodak,
# Sigma, Epson).
RAW_SUFFIXES = (
    ".dng", ".cr2", ".cr3", ".nef", ".arw", ".raf", ".orf", ".rw2", ".pef", ".srw",
    ".crw", ".nrw", ".srf", ".sr2", ".rwl", ".3fr", ".fff", ".iiq", ".mos", ".mef", ".kdc",
    ".dcr", ".x3f", ".erf",
)  # fmt: skip
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".exr", ".npy", ".npz", *RAW_SUFFIXES)
OUTPUT_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".npy", ".npz")
# suffix -> (format name, imageio plugin, leading bytes of a valid file)
_FORMATS = {
    ".png": ("PNG", "pillow", (b"\x89PNG\r\n\x1a\n",)),
    ".tif": ("TIFF", "tifffile", (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")),
    ".jpg": ("JPEG", "pillow", (b"\xff\xd8\xff",)),
    ".exr": ("EXR", None, (b"\x76\x2f\x31\x01",)),
}
_FORMATS[".tiff"] = _FORMATS[".tif"]
_FORMATS[".jpeg"] = _FORMATS[".jpg"]
_NPZ_KEYS = {"image": ("image", "target"), "depth": ("depth",)}


class InputError(Exception):
    """A problem with the user's files or options: the CLI prints `str(err)` and exits with 2."""


@dataclasses.dataclass
class Loaded:
    """An array read from a file, with what is needed to write a result back alike.

    `bits` is 8 or 16 for integer files (16 for camera RAW files) and `None` for float files.
    `notes` are one-line remarks for the user (e.g. a dropped alpha channel). `raw_decode`: for a
    camera RAW file, what LibRaw read and how it decoded it (`read_camera_raw`); else `None`.
    """

    array: np.ndarray
    bits: int | None
    notes: list[str] = dataclasses.field(default_factory=list)
    raw_decode: dict[str, Any] | None = None


# ----------------------------------------------------------------------------------------------
# sRGB transfer curve


def srgb_to_linear(encoded: np.ndarray | float) -> np.ndarray:
    """sRGB-encoded values in `[0, 1]` to linear light (IEC 61966-2-1).

    `c / 12.92` for `c <= 0.04045`, else `((c + 0.055) / 1.055)^2.4`.
    """
    c = np.asarray(encoded, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((np.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(linear: np.ndarray | float) -> np.ndarray:
    """Linear light to sRGB-encoded values, clipped to `[0, 1]` (the inverse of `srgb_to_linear`)."""
    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(
        x <= 0.0031308, 12.92 * x, 1.055 * np.maximum(x, 0.0031308) ** (1 / 2.4) - 0.055
    )


# ----------------------------------------------------------------------------------------------
# Reading


def _suffix(path: str) -> str:
    return os.path.splitext(path)[1].lower()


def _read_npy(path: str, role: str) -> np.ndarray:
    try:
        if _suffix(path) == ".npy":
            return np.load(path, allow_pickle=False)
        with np.load(path, allow_pickle=False) as npz:
            keys = list(npz.keys())
            if len(keys) == 1:
                return npz[keys[0]]
            for key in _NPZ_KEYS[role]:
                if key in keys:
                    return npz[key]
            raise InputError(
                f"{path}: .npz holds {len(keys)} arrays {keys}; keep one, or name the {role} "
                f"array {_NPZ_KEYS[role][0]!r}"
            )
    except ValueError as err:
        if "allow_pickle" in str(err):
            raise InputError(
                f"{path}: holds pickled Python objects, which are never loaded (they can run "
                "code); save a plain numeric array with numpy.save"
            ) from None
        raise InputError(f"{path}: not a readable .npy/.npz file ({err})") from None
    except (OSError, EOFError, zlib.error) as err:
        raise InputError(f"{path}: not a readable .npy/.npz file ({err})") from None


def _png_header(path: str) -> tuple[int, int] | None:
    """`(bit_depth, colour_type)` from a PNG's IHDR chunk, or `None` if it is not a PNG."""
    with open(path, "rb") as fh:
        head = fh.read(29)
    if len(head) < 29 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return head[24], head[25]


def _read_png16_colour(path: str) -> np.ndarray:
    """Decode a 16-bit RGB/RGBA PNG at full precision with Pillow.

    Pillow's PNG decoder undoes the PNG filters on the whole 16-bit stream and then unpacks each
    sample with a "raw mode". Its RGB image modes hold 8 bits, so the default raw mode (`;16B`,
    big-endian) keeps the high byte; asking for `;16L` (little-endian) keeps the other, low, byte.
    Two decodes give both bytes.
    """
    from PIL import Image

    halves = []
    for order in ("16B", "16L"):
        with Image.open(path) as im:
            (tile,) = im.tile
            codec, extents, offset, rawmode = tile[:4]
            if not (isinstance(rawmode, str) and rawmode in ("RGB;16B", "RGBA;16B")):
                raise InputError(
                    f"{path}: this 16-bit PNG layout ({rawmode}) is not supported; save it as "
                    "16-bit RGB PNG, 16-bit TIFF or .npy"
                )
            rawmode = rawmode[:-3] + order
            # Pillow >= 11 keeps tiles as a named tuple, older versions as a plain tuple.
            im.tile = [
                tile._replace(args=rawmode)
                if hasattr(tile, "_replace")
                else (codec, extents, offset, rawmode)
            ]
            halves.append(np.asarray(im))
    return (halves[0].astype(np.uint16) << 8) | halves[1].astype(np.uint16)


@contextlib.contextmanager
def _collect_fd2(lines: list[str]) -> Iterator[None]:
    """Collect in `lines` what is written to file descriptor 2 (standard error) meanwhile.

    LibRaw reports damaged data ("Unexpected end of file") by printing it there from C, beside
    its return codes. It is collected so that the user sees one line, ours.
    """
    sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:  # no standard error to redirect: nothing to collect
        yield
        return
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            lines.extend(sink.read().decode("utf-8", "replace").splitlines())


def _import_rawpy(path: str):
    try:
        import rawpy
    except ImportError:
        raise InputError(
            f"{path}: reading camera RAW files needs rawpy: pip install rawpy (or pip install "
            '"jaxdof[raw]")'
        ) from None
    return rawpy


@contextlib.contextmanager
def open_camera_raw(path: str, option: str | None = None) -> Iterator[Any]:
    """`rawpy.imread(path)`, open for the `with` block; what fails in LibRaw becomes one
    `InputError` naming the file: an unsupported or damaged file, and data errors LibRaw only
    prints (what it prints about this file is collected and told in the message; anything else
    written to standard error meanwhile, e.g. a progress line, is passed on afterwards).

    **Raises:** `InputError` also when rawpy is not installed (`pip install "jaxdof[raw]"`).
    """
    rawpy = _import_rawpy(path)
    lines: list[str] = []
    failure = None
    try:
        with _collect_fd2(lines), rawpy.imread(path) as raw:
            yield raw
    except rawpy.LibRawError as err:
        arg = err.args[0] if err.args else type(err).__name__
        failure = arg.decode("utf-8", "replace") if isinstance(arg, bytes) else str(arg)
    ours = [line for line in lines if line.startswith(f"{path}:")]
    others = [line for line in lines if line not in ours]
    if others:
        sys.stderr.write("\n".join(others) + "\n")
    if ours:  # what LibRaw printed says more than its return code ("Input/output error")
        failure = ours[0][len(path) + 1 :].strip()
    if failure is not None:
        where = f" ({option})" if option else ""
        raise InputError(f"{path}: not a readable camera RAW file (LibRaw: {failure}){where}")


def read_camera_raw(path: str, *, option: str = "IMAGE") -> tuple[np.ndarray, dict[str, Any]]:
    """Decode a camera RAW file with LibRaw (rawpy) to linear-light sRGB-primary RGB.

    LibRaw subtracts the black level, scales the white level to 65535, applies the camera's
    as-shot white balance (the daylight balance from the camera's colour matrix if the file
    records none), demosaics, converts the camera's colours to sRGB (Rec. 709) primaries with
    the file's colour matrix, and rotates the frame as the camera recorded it, with gamma 1 and
    without auto-brightening: a count twice as far above black gives twice the value (until it
    clips at the white level).

    The demosaic is AHD (Hirakawa and Parks, "Adaptive homogeneity-directed demosaicing
    algorithm", IEEE TIP 14(3), 2005; LibRaw's default, in every build): it interpolates along edges, where a
    bilinear demosaic would soften every edge by about a pixel, blur the fit would take for
    defocus. (AMaZE needs LibRaw's GPL demosaic pack, which rawpy's wheels leave out.)

    **Returns:** `(rgb, facts)`: `uint16` `(H, W, 3)`, and what LibRaw read, JSON-ready:
    `decoder`, `raw_size` (the stored `[width, height]`, margins included), `colours` (LibRaw's
    colour letters, e.g. `"RGBG"`), `cfa` (the mosaic's repeating pattern by rows, e.g.
    `"RG/GB"`; `None` for a sensor without one), `black_level` (per colour), `white_level`,
    `white_balance` (the multipliers used, one per letter of `colours`) and
    `white_balance_source` (`"as-shot"` or `"daylight"`), `demosaic`.

    **Raises:** `InputError` naming the file when rawpy is missing or LibRaw cannot decode it.
    """
    rawpy = _import_rawpy(path)
    with open_camera_raw(path, option) as raw:
        colours = raw.color_desc.decode("ascii", "replace")
        try:
            pattern = raw.raw_pattern
        except NotImplementedError:  # a layout rawpy does not describe (it still decodes)
            pattern = None
        as_shot = [float(x) for x in raw.camera_whitebalance]
        shot = all(x > 0 for x in as_shot[:3])  # LibRaw falls back to daylight without it
        balance = as_shot if shot else [float(x) for x in raw.daylight_whitebalance]
        balance[3:] = [x or balance[1] for x in balance[3:]]  # a second green of 0: as the first
        facts: dict[str, Any] = {
            "decoder": f"LibRaw {'.'.join(map(str, rawpy.libraw_version))}",
            "raw_size": [int(raw.sizes.raw_width), int(raw.sizes.raw_height)],
            "colours": colours,
            "cfa": None
            if pattern is None or pattern.size < 4
            else "/".join("".join(colours[i] for i in row) for row in pattern.tolist()),
            "black_level": [int(x) for x in raw.black_level_per_channel],
            "white_level": int(raw.white_level),
            "white_balance": balance,
            "white_balance_source": "as-shot" if shot else "daylight",
            "demosaic": "AHD",
        }
        rgb = raw.postprocess(
            demosaic_algorithm=rawpy.DemosaicAlgorithm.AHD,
            use_camera_wb=True,
            output_color=rawpy.ColorSpace.sRGB,
            gamma=(1, 1),
            no_auto_bright=True,
            output_bps=16,
        )
    return np.ascontiguousarray(rgb), facts


def _check_file(path: str, option: str) -> str:
    """The file's suffix, after checking that it exists, is a file jaxdof reads, and is readable."""
    suffix = _suffix(path)
    if not os.path.exists(path):
        raise InputError(f"{path}: no such file ({option})")
    if os.path.isdir(path):
        raise InputError(f"{path}: is a folder, not an image file ({option})")
    if suffix not in IMAGE_SUFFIXES:
        raise InputError(
            f"{path}: unsupported format {suffix or '(no extension)'!r} ({option}); use one of "
            + ", ".join(s for s in IMAGE_SUFFIXES if s not in RAW_SUFFIXES)
            + f", or a camera RAW file ({', '.join(RAW_SUFFIXES[:10])}, ...)"
        )
    if not os.access(path, os.R_OK):
        raise InputError(f"{path}: cannot be read (permission denied) ({option})")
    return suffix


def _read_raw(path: str, role: str, option: str) -> np.ndarray:
    """Read a file as it is stored (integers stay integers). Errors name the file."""
    suffix = _check_file(path, option)
    if suffix in RAW_SUFFIXES:  # read_image decodes them; nothing else reads them
        raise InputError(f"{path}: a camera RAW file is a photo, not a {role} map ({option})")
    if suffix in (".npy", ".npz"):
        array = _read_npy(path, role)
    else:
        import imageio.v3 as iio

        try:
            with open(path, "rb") as fh:
                magic = fh.read(8)
            kind, plugin, signatures = _FORMATS[suffix]
            if not any(magic.startswith(sig) for sig in signatures):
                raise InputError(
                    f"{path}: not a valid {kind} file (it does not start with the {kind} "
                    f"signature) ({option})"
                )
            if suffix == ".exr":
                raise InputError(
                    f"{path}: cannot read EXR here: imageio has no EXR backend among jaxdof's "
                    "dependencies; convert it to float32 TIFF or .npy (both linear, like EXR)"
                )
            header = _png_header(path) if suffix == ".png" else None
            if header is not None and header[0] == 16 and header[1] in (2, 6):
                array = _read_png16_colour(path)
            else:
                # A named plugin: imageio's search over every plugin leaks file handles.
                array = iio.imread(path, plugin=plugin) if plugin else iio.imread(path)
        except InputError:
            raise
        except Exception as err:  # imageio raises many types; all mean "could not decode"
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise InputError(f"{path}: not a readable {suffix} image ({first})") from None
    array = np.asarray(array)
    if array.dtype == object or array.dtype.kind not in "uif":
        raise InputError(f"{path}: unsupported data type {array.dtype} ({option}); need numbers")
    if array.ndim == 3 and array.shape[-1] == 1:
        array = array[..., 0]
    if array.ndim not in (2, 3) or 0 in array.shape[:2]:
        raise InputError(
            f"{path}: shape {array.shape} is not an image ({option}); need (H, W) or (H, W, C)"
        )
    return array


def read_image(path: str, *, linear: bool = False, option: str = "IMAGE") -> Loaded:
    """Read an image as float32 linear light, `(H, W)` or `(H, W, C)` with `C` in {1, 3}.

    8/16-bit integers are scaled to `[0, 1]` and decoded from sRGB (unless `linear`); float files
    are taken as linear. An alpha channel is dropped (noted in `Loaded.notes`). Camera RAW files
    (`RAW_SUFFIXES`) are decoded in linear light by `read_camera_raw`, whatever `linear` says.
    """
    if _suffix(path) in RAW_SUFFIXES:
        _check_file(path, option)
        rgb, facts = read_camera_raw(path, option=option)
        image = rgb.astype(np.float32)
        image /= 65535
        note = (
            f"{path}: camera RAW read in linear light by {facts['decoder']} ({facts['demosaic']} "
            f"demosaic, {facts['white_balance_source']} white balance, sRGB primaries)"
        )
        return Loaded(image, 16, [note], facts)
    raw = _read_raw(path, "image", option)
    notes = []
    if raw.ndim == 3:
        if raw.shape[-1] in (2, 4):
            raw = raw[..., :-1]
            notes.append(f"{path}: alpha channel ignored")
            if raw.shape[-1] == 1:
                raw = raw[..., 0]
        elif raw.shape[-1] != 3:
            raise InputError(
                f"{path}: {raw.shape[-1]} channels; need 1 (grey), 3 (RGB) or 4 (RGBA)"
            )
    if raw.dtype == np.uint8 or raw.dtype == np.uint16:
        bits = 8 * raw.dtype.itemsize
        # One float64 decode per code value (at most 2^16), then a float32 look-up: the same
        # values as decoding every pixel in float64, without a float64 copy of the frame
        # (24 MP RGB: 0.6 GB).
        levels = np.arange(2**bits, dtype=np.float64) / (2**bits - 1)
        image = (levels if linear else srgb_to_linear(levels)).astype(np.float32)[raw]
    elif raw.dtype.kind == "f":
        bits = None
        image = raw
        if not np.all(np.isfinite(image)):
            raise InputError(f"{path}: contains NaN or infinite values ({option})")
    else:
        raise InputError(
            f"{path}: {raw.dtype} pixels are not supported ({option}); images are 8/16-bit "
            "unsigned integers or floats"
        )
    return Loaded(np.ascontiguousarray(image, dtype=np.float32), bits, notes)


#: A JPEG's colour samplings that store Cb, Cr at lower resolution than the luma
#: (`jpeg_header`'s `chroma`).
SUBSAMPLED = ("4:2:0", "4:2:2")


def chroma_subsampled(path: str) -> bool:
    """Whether `path` is a JPEG whose colour (Cb, Cr) is stored at lower resolution than its luma
    (4:2:0 or 4:2:2, what cameras and Pillow write by default), from its header (no decoding)."""
    header = jpeg_header(path)
    return header is not None and header["chroma"] in SUBSAMPLED


def jpeg_header(path: str) -> dict | None:
    """A JPEG file's colour sampling (`"4:4:4"`, `"4:2:2"`, `"4:2:0"`, or None for grey or
    another) and the IJG quality its luma table is (None for a table of the camera's own), from
    its header; None for another file."""
    if _suffix(path) not in (".jpg", ".jpeg"):
        return None
    from PIL import Image, JpegImagePlugin

    from ._fit.jpeg import ijg_table

    try:
        with Image.open(path) as im:
            if not isinstance(im, JpegImagePlugin.JpegImageFile):
                return None
            sampling = JpegImagePlugin.get_sampling(im)
            table = np.asarray(im.quantization.get(0, ()), np.int64)
    except Exception:  # unreadable: read_image has said so already
        return None
    quality = next(
        (q for q in range(100, 0, -1) if np.array_equal(ijg_table(q).reshape(-1), table)), None
    )
    chroma = {0: "4:4:4", 1: "4:2:2", 2: "4:2:0"}.get(sampling)
    return {"chroma": chroma, "quality": quality}


def read_depth(
    path: str,
    *,
    scale: float | None = None,
    zbuffer: bool = False,
    near: float | None = None,
    far: float | None = None,
    inverse: bool = False,
    option: str = "DEPTH",
) -> np.ndarray:
    """Read a depth map as float32 z-depth in metres, `(H, W)`.

    - float file: metres, times `scale` if given;
    - integer file: counts times `scale` (metres per count), which must be given;
    - `zbuffer`: OpenGL window depth in `[0, 1]` (integer files: counts / (2^bits - 1)) mapped
      through `jaxdof.linearize_depth(z, near, far)`;
    - `inverse`: the (scaled) values are inverse depth in 1/m; `0` means infinitely far.

    Pixels without a depth (NaN in a float file; 0 or negative after scaling, except 0 in an
    inverse-depth file, which is infinitely far) are returned as NaN: holes (`jaxdof.depth_holes`).

    Raises `InputError` for several different channels, or a depth map without any data.
    """
    raw = _one_channel(_read_raw(path, "depth", option), path, option)
    if zbuffer and inverse:
        raise InputError("--zbuffer and --inverse-depth cannot be combined")
    if raw.dtype.kind == "f":
        # NaN: no data (a hole); inf: infinitely far. float32 metres stay as they are (the
        # result is float32: a float64 copy adds nothing but 24 MP x 8 bytes of memory).
        plain = raw.dtype == np.float32 and scale is None and not (zbuffer or inverse)
        values = raw if plain else raw.astype(np.float64)
    elif raw.dtype.kind in "ui":
        values = raw.astype(np.float64)
        if zbuffer:
            if raw.dtype not in (np.uint8, np.uint16):
                raise InputError(
                    f"{path}: a {raw.dtype} depth buffer is not supported; use 8/16-bit or float"
                )
            values = values / (np.iinfo(raw.dtype).max)
        elif scale is None:
            raise InputError(
                f"{path}: integer depth needs --depth-scale (metres per count, e.g. 1mm), "
                "or --zbuffer --near --far for an OpenGL depth buffer"
            )
    else:
        raise InputError(f"{path}: {raw.dtype} depth is not supported ({option})")

    if zbuffer:
        depth = _from_zbuffer(values, path, scale, near, far, option)
    else:
        if near is not None or far is not None:
            raise InputError("--near/--far only apply with --zbuffer")
        values = values if scale is None else values * scale
        if inverse:
            if values.min() < 0:
                raise InputError(
                    f"{path}: inverse depth must be >= 0 (found {values.min():g}) ({option})"
                )
            with np.errstate(divide="ignore"):
                depth = np.where(values > 0, 1.0 / np.where(values > 0, values, 1.0), np.inf)
        else:
            depth = values
    # 0 or negative metres (and NaN) are no data, as depth sensors write it: holes, kept as NaN
    # (`jaxdof.depth_holes`); `fit` leaves the photo pixels they reach out, `render` fills them
    # when asked (--fill-holes).
    with np.errstate(invalid="ignore"):
        depth = np.where(depth > 0, depth, np.nan)
    if np.all(np.isnan(depth)):
        raise InputError(f"{path}: depth has no data: every pixel is 0, negative or NaN ({option})")
    return np.ascontiguousarray(depth, dtype=np.float32)


def _one_channel(raw: np.ndarray, path: str, option: str) -> np.ndarray:
    """A depth file's samples `(H, W)`: an alpha channel dropped, equal channels made one."""
    if raw.ndim != 3:
        return raw
    if raw.shape[-1] in (2, 4):  # grey+alpha / RGBA: drop alpha
        raw = raw[..., :-1]
    if not np.all(raw == raw[..., :1]):
        raise InputError(
            f"{path}: depth has {raw.shape[-1]} different channels ({option}); a depth map has one"
        )
    return raw[..., 0]


def _from_zbuffer(values, path: str, scale, near, far, option: str) -> np.ndarray:
    """z-depth (m, float64) from OpenGL window depths `values` in `[0, 1]` and the clip planes."""
    if scale is not None:
        raise InputError("--depth-scale cannot be combined with --zbuffer (use --near/--far)")
    if near is None or far is None:
        raise InputError("--zbuffer needs both --near and --far (clip planes, e.g. 0.1m 100m)")
    if not 0 < near < far:
        raise InputError(f"--near {near} m and --far {far} m must satisfy 0 < near < far")
    if values.min() < 0 or values.max() > 1:
        raise InputError(
            f"{path}: depth-buffer values must lie in [0, 1] (found {values.min():g} .. "
            f"{values.max():g}) ({option})"
        )
    import jaxdof

    return np.asarray(jaxdof.linearize_depth(values, near, far), dtype=np.float64)


# ----------------------------------------------------------------------------------------------
# Writing


def _png_bytes_16(samples: np.ndarray) -> bytes:
    """A 16-bit PNG (grey, or RGB) from uint16 samples `(H, W)` or `(H, W, 3)`, filter type 0."""
    samples = samples if samples.ndim == 3 else samples[..., None]
    h, w, c = samples.shape
    colour_type = {1: 0, 3: 2}[c]
    rows = samples.astype(">u2").reshape(h, w * c).view(np.uint8)
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rows], axis=1).tobytes()

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    header = struct.pack(">IIBBBBB", w, h, 16, colour_type, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw, 6))
        + chunk(b"IEND", b"")
    )


def _same_file(a: str, b: str) -> bool:
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def check_output(path: str, inputs: Sequence[str], option: str = "-o") -> None:
    """Refuse an output that would overwrite an input, an unsupported suffix, or a missing folder."""
    for src in inputs:
        if _same_file(path, src):
            raise InputError(f"{option} {path}: is also an input file; choose another output path")
    suffix = _suffix(path)
    if suffix not in OUTPUT_SUFFIXES:
        raise InputError(
            f"{option} {path}: unsupported output format {suffix or '(no extension)'!r}; use one of "
            + ", ".join(OUTPUT_SUFFIXES)
        )
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise InputError(f"{option} {path}: folder {folder} does not exist")
    if os.path.isdir(path):
        raise InputError(f"{option} {path}: is a folder; give a file name")


def atomic_write(
    path: str, write: Callable[[str], None], inputs: Sequence[str] = (), option: str = "-o"
) -> None:
    """Call `write(tmp_path)` on a temporary file beside `path`, then rename it onto `path`."""
    for src in inputs:
        if _same_file(path, src):
            raise InputError(f"{option} {path}: is also an input file; choose another output path")
    folder = os.path.dirname(os.path.abspath(path))
    base, suffix = os.path.splitext(os.path.basename(path))
    fd, tmp = tempfile.mkstemp(prefix=f".{base}.", suffix=suffix, dir=folder)
    os.close(fd)
    try:
        write(tmp)
        # mkstemp makes the file private (0600); give it the mode a plain open() would have, or
        # the mode of the file it replaces.
        if os.path.exists(path):
            mode = os.stat(path).st_mode & 0o777
        else:
            umask = os.umask(0)
            os.umask(umask)
            mode = 0o666 & ~umask
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def encode_image(image: np.ndarray, *, suffix: str, bits: int | None, linear: bool = False):
    """Array in the stored form for `suffix`: float32 linear, or 8/16-bit (sRGB unless `linear`)."""
    image = np.asarray(image, dtype=np.float64)
    if suffix in (".npy", ".npz") or (suffix in (".tif", ".tiff") and bits is None):
        return image.astype(np.float32)
    if suffix in (".jpg", ".jpeg"):
        bits = 8
    bits = 16 if bits is None else bits
    encoded = np.clip(image, 0.0, 1.0) if linear else linear_to_srgb(image)
    dtype = np.uint8 if bits == 8 else np.uint16
    return np.round(encoded * (2**bits - 1)).astype(dtype)


def write_image(
    path: str,
    image: np.ndarray,
    *,
    bits: int | None,
    linear: bool = False,
    inputs: Sequence[str] = (),
    option: str = "-o",
) -> None:
    """Write a linear-light image atomically, encoded for its file type.

    `.npy`/`.npz` (key `image`) and TIFF with `bits=None` store float32 linear values; PNG, JPEG
    and TIFF with `bits` 8 or 16 store sRGB-encoded integers (`linear=True`: linear integers).
    PNG with `bits=None` is written at 16 bits.
    """
    check_output(path, list(inputs), option)
    suffix = _suffix(path)
    stored = encode_image(image, suffix=suffix, bits=bits, linear=linear)

    def write(tmp: str) -> None:
        if suffix == ".npy":
            with open(tmp, "wb") as fh:
                np.save(fh, stored, allow_pickle=False)
        elif suffix == ".npz":
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, image=stored)
        elif suffix == ".png" and stored.dtype == np.uint16:
            with open(tmp, "wb") as fh:  # Pillow cannot write 16-bit colour PNG
                fh.write(_png_bytes_16(stored))
        else:
            import imageio.v3 as iio

            iio.imwrite(tmp, stored, extension=suffix)

    atomic_write(path, write, list(inputs), option)
