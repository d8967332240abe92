"""A photo's lens metadata (EXIF), read with Pillow: focal length, f-number, focus distance, pitch.

Plain Python: no JAX, no pixels decoded (except a PNG whose eXIf chunk follows its image data,
which Pillow reaches only by decoding, and a camera RAW file read through LibRaw, which rawpy
unpacks before it gives the metadata). The command line starts `jaxdof fit` from these values and
prints them with `jaxdof info`.

**Where the tags are.** Cameras write the lens fields in the Exif sub-IFD (JPEG APP1, PNG eXIf,
WebP EXIF chunk, and the TIFF's own tag directory); TIFF/EP files (and raw-derived TIFFs) write
`FocalLength`, `FNumber` and `SubjectDistance` in IFD0 under the same tag numbers, so IFD0 is the
fallback. A TIFF whose pixels Pillow cannot decode (float32 RGB) still has readable tags: they are
read from its directory without opening the image.

**What the values mean** (EXIF 2.32, CIPA DC-008-2019; tag numbers in `PIL.ExifTags.Base`):

- `FocalLength` (0x920A), mm; `FocalLengthIn35mmFilm` (0xA405), mm; 0 means unknown (manual lenses).
- `FNumber` (0x829D); without it `ApertureValue` (0x9202), APEX `Av` with `N = 2^(Av/2)`.
- `SubjectDistance` (0x9206), m: numerator 0 means unknown, numerator 0xFFFFFFFF infinity.
  `SubjectDistanceRange` (macro/close/distant) is a category, not a distance, and is not read.
- `FocalPlaneXResolution` (0xA20E) pixels per `FocalPlaneResolutionUnit` (0xA210: 2 inch, the
  default when absent; 3 cm; 4 mm and 5 um as in TIFF/EP and DNG; 1 no unit) across the image's
  width, of the image `PixelXDimension` x `PixelYDimension` (0xA002, 0xA003) describes.

**Camera RAW files** (`jaxdof._io.RAW_SUFFIXES`). Most are TIFF inside (DNG, NEF, CR2, ARW, PEF,
SRW; ORF and RW2 under their own magic number): their tags are read as a TIFF's. When that gives
neither a focal length nor an f-number (CR3 and RAF are not TIFF-structured), LibRaw's (through
rawpy, the `raw` extra) are taken: the focal length, aperture and lens name it parses from the
EXIF and the maker's notes. LibRaw gives no focus distance and no focal-plane resolution; a note
says what came from it.

A rational with a zero denominator, a value of the wrong type, or an implausible pixel pitch is
left out with a note (`ExifLens.notes`), never guessed at.
"""

from __future__ import annotations

import dataclasses
import math
import mmap
import os
import warnings
from collections.abc import Mapping
from typing import Any

from ._io import RAW_SUFFIXES, InputError, open_camera_raw


_FULL_FRAME_DIAGONAL = math.hypot(0.036, 0.024)  # m: the 35 mm film frame, 36 x 24 mm
_UNIT = {2: 0.0254, 3: 0.01, 4: 1e-3, 5: 1e-6}  # FocalPlaneResolutionUnit -> metres
_PITCH_RANGE = (1e-7, 1e-4)  # m: 0.1 to 100 um; outside it a focal-plane resolution is bogus
_INFINITY = 0xFFFFFFFF  # SubjectDistance numerator meaning infinity
_TIFF = (b"II*\x00", b"MM\x00*")  # a classic TIFF's first four bytes
# Raw formats built as a TIFF under their own first four bytes: Olympus ORF, Panasonic RW2.
_TIFF_LIKE = (b"IIRO", b"IIRS", b"MMOR", b"IIU\x00")
# The tags read, by Pillow's name (PIL.ExifTags.Base), in the order `source` lists them.
_TAGS = (
    "Make",
    "Model",
    "LensMake",
    "LensModel",
    "FocalLength",
    "FocalLengthIn35mmFilm",
    "FNumber",
    "ApertureValue",
    "SubjectDistance",
    "FocalPlaneXResolution",
    "FocalPlaneYResolution",
    "FocalPlaneResolutionUnit",
    "ExifImageWidth",
    "ExifImageHeight",
)


@dataclasses.dataclass(frozen=True, kw_only=True)
class ExifLens:
    """The lens fields of a photo's EXIF metadata, in SI units; `None` where absent or unknown.

    **Fields.**

    - `focal_length`: m (`FocalLength`).
    - `f_number`: `FNumber`, or from `ApertureValue` when only that is there.
    - `focus_distance`: m (`SubjectDistance`); `math.inf` when the camera recorded infinity.
    - `pixel_pitch`: m, of the image `pixel_dimensions` describes (`FocalPlaneXResolution` and
      `FocalPlaneResolutionUnit`).
    - `focal_length_35mm`: m, the 35 mm-equivalent focal length (`FocalLengthIn35mmFilm`).
    - `pixel_dimensions`: `(width, height)` in pixels of the image the EXIF describes
      (`PixelXDimension`, `PixelYDimension`), which a resized copy may not have updated.
    - `make`, `model`, `lens_model`: the camera's and lens's names.
    - `source`: the raw tags read, by Pillow's tag name (`PIL.ExifTags.Base`): numbers (a
      rational as a float, or `"n/0"` for a zero denominator) and strings; from a camera RAW
      file, also LibRaw's values as `"LibRaw focal_len"` (mm), `"LibRaw aperture"` and
      `"LibRaw lens"` when they were used. Empty: the file has none of these tags.
    - `notes`: one line per tag left out (a zero denominator, a wrong type, an implausible value)
      and per warning Pillow gave while reading.
    """

    focal_length: float | None = None
    f_number: float | None = None
    focus_distance: float | None = None
    pixel_pitch: float | None = None
    focal_length_35mm: float | None = None
    pixel_dimensions: tuple[int, int] | None = None
    make: str | None = None
    model: str | None = None
    lens_model: str | None = None
    source: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    notes: tuple[str, ...] = ()

    @property
    def has_lens(self) -> bool:
        """Whether any lens field (focal length, f-number, focus, pitch, 35 mm equivalent) is known."""
        fields = (self.focal_length, self.f_number, self.focus_distance, self.pixel_pitch)
        return any(v is not None for v in (*fields, self.focal_length_35mm))

    def sensor_width(self, width: int, height: int) -> float | None:
        """The width (m) of the sensor area an image of `width` x `height` pixels spans, or `None`.

        From the focal-plane resolution when known: `pixel_pitch` times the width the EXIF
        describes (`pixel_dimensions`, else `width`): a photo resized after the EXIF was written
        spans the same sensor. Otherwise from the crop factor `c = focal_length_35mm /
        focal_length`: the sensor's diagonal is the 35 mm frame's (43.27 mm) over `c` (the
        diagonal definition of the equivalent focal length, CIPA DC-008; cameras that scale by the
        width instead differ by a few percent), split in the image's aspect ratio. Then the
        photo's pixel pitch is `sensor_width / width`.
        """
        if self.pixel_pitch is not None:
            spanned = self.pixel_dimensions[0] if self.pixel_dimensions else width
            return self.pixel_pitch * spanned
        if self.focal_length is not None and self.focal_length_35mm is not None:
            diagonal = _FULL_FRAME_DIAGONAL * self.focal_length / self.focal_length_35mm
            return diagonal * width / math.hypot(width, height)
        return None

    def to_dict(self) -> dict[str, Any]:
        """The fields as a JSON-ready dict (SI units). A focus distance at infinity is `None`, as
        in `FitResult.to_dict()`, and `focus_power` (1/m) tells it apart: 0 at infinity, `None`
        when the distance is unknown."""
        focus = self.focus_distance
        out = {}
        for f in dataclasses.fields(self):
            out[f.name] = getattr(self, f.name)
            if f.name == "focus_distance":
                out[f.name] = None if focus is None or math.isinf(focus) else focus
                out["focus_power"] = None if focus is None else 1.0 / focus
        out["pixel_dimensions"] = (
            None if self.pixel_dimensions is None else list(self.pixel_dimensions)
        )
        out["source"] = dict(self.source)
        out["notes"] = list(self.notes)
        return out


def read_exif(path: str | os.PathLike[str]) -> ExifLens:
    """Read the lens fields of a photo's EXIF metadata (JPEG, TIFF, PNG eXIf, WebP, camera RAW)
    with Pillow; from a RAW file without them, LibRaw's focal length and aperture.

    **Arguments:**

    - `path`: the photo's file.

    **Returns:** an `ExifLens` (SI units; fields `None` where absent). A file without EXIF gives
    one with every field `None` and an empty `source`.

    **Raises:** `ValueError` naming the file and the problem when it does not exist, is not an
    image Pillow (or, for a camera RAW file, LibRaw) can read, or its metadata cannot be parsed.

    The tags and their meaning are in the module's docstring (EXIF 2.32, CIPA DC-008-2019).
    """
    name = os.fspath(path)
    if not os.path.exists(name):
        raise ValueError(f"{name}: no such file")
    if os.path.isdir(name):
        raise ValueError(f"{name}: is a folder, not an image file")
    raw = os.path.splitext(name)[1].lower() in RAW_SUFFIXES
    tiff_error = None
    # Pillow warns on damaged tags ("Possibly corrupt EXIF data"): each becomes a note.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            ifd0, sub = _read_ifds(name)
        except Exception as err:  # Pillow raises many types; all mean "cannot parse"
            tiff_error = (
                err
                if isinstance(err, ValueError)
                else ValueError(f"{name}: its metadata cannot be read ({_first_line(err)})")
            )
            if not raw:
                raise tiff_error from None
            ifd0, sub = {}, {}
    notes = [f"{name}: {_first_line(w.message)}" for w in caught]
    lens = _lens(name, ifd0, sub, notes)
    if raw and lens.focal_length is None and lens.f_number is None:
        return _with_libraw(name, lens, tiff_error)
    return lens


def _with_libraw(name: str, lens: ExifLens, tiff_error: ValueError | None) -> ExifLens:
    """`lens` with LibRaw's focal length, aperture and lens name where it has them, and a note.

    `tiff_error`: why no TIFF tags could be read, if none could; a file LibRaw cannot read either
    then raises `ValueError`, else the failure is a note.
    """
    try:
        with open_camera_raw(name) as raw:
            focal, aperture, model = raw.other.focal_length, raw.other.aperture, raw.lens.model
    except InputError as err:
        if tiff_error is not None:
            raise ValueError(str(err)) from None
        return dataclasses.replace(lens, notes=(*lens.notes, f"{err}; its lens fields left out"))
    found = {  # 0: unknown
        "LibRaw focal_len": float(focal) if focal > 0 else None,
        "LibRaw aperture": float(aperture) if aperture > 0 else None,
        "LibRaw lens": model.strip() or None,
    }
    found = {k: v for k, v in found.items() if v is not None}
    notes = lens.notes
    if tiff_error is not None:
        notes += (
            f"{name}: its metadata is not TIFF-structured: focal length, f-number and lens name "
            "are read through LibRaw, which gives no focus distance or pixel pitch",
        )
    elif found:
        notes += (f"{name}: its EXIF tags have no focal length or f-number; LibRaw's are used",)
    focal_mm = found.get("LibRaw focal_len")
    return dataclasses.replace(
        lens,
        focal_length=None if focal_mm is None else focal_mm / 1000,
        f_number=found.get("LibRaw aperture"),
        lens_model=lens.lens_model or found.get("LibRaw lens"),
        source={**lens.source, **found},
        notes=notes,
    )


def _first_line(err: object) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


def _read_ifds(path: str) -> tuple[dict[int, Any], dict[int, Any]]:
    """IFD0 and the Exif sub-IFD as `{tag number: value}` (Pillow's values)."""
    from PIL import ExifTags, Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            exif = im.getexif()
            return dict(exif), dict(exif.get_ifd(ExifTags.IFD.Exif))
    except UnidentifiedImageError:
        with open(path, "rb") as fh:
            head = fh.read(4)
        if head not in _TIFF + _TIFF_LIKE:
            raise ValueError(
                f"{path}: not an image whose metadata can be read (JPEG, TIFF, PNG, WebP or "
                "TIFF-structured camera RAW)"
            ) from None
    # A classic TIFF whose pixels Pillow cannot decode (float32 RGB, a DNG's mosaic): its tag
    # directory is read as Pillow reads a TIFF's EXIF, without the image. A TIFF-like raw is read
    # through a private copy-on-write mapping given the TIFF's first four bytes (the file is not
    # changed, nor read whole).
    exif = Image.Exif()
    with open(path, "rb") as fh:
        if head in _TIFF:
            exif.load_from_fp(fh)
            return dict(exif), dict(exif.get_ifd(ExifTags.IFD.Exif))
        with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_COPY) as view:
            view[:4] = _TIFF[0] if head.startswith(b"II") else _TIFF[1]
            exif.load_from_fp(view)  # pyright: ignore[reportArgumentType]
            return dict(exif), dict(exif.get_ifd(ExifTags.IFD.Exif))


def _is_number(value: Any) -> bool:
    """An int, a float or a rational (Pillow's `IFDRational`), not a bool."""
    number = isinstance(value, (int, float)) or hasattr(value, "denominator")
    return number and not isinstance(value, bool)


def _raw(value: Any) -> Any:
    """A tag's value as `source` holds it: a rational as a float (`"n/0"` for a zero
    denominator), bytes as text, tuples element by element."""
    if isinstance(value, (tuple, list)):
        return [_raw(v) for v in value]
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace").rstrip("\x00").strip()
    if isinstance(value, str):
        return value.rstrip("\x00").strip()
    if not _is_number(value):
        return repr(value)
    if getattr(value, "denominator", 1) == 0:
        return f"{value.numerator}/0"
    if isinstance(value, int):
        return int(value)
    x = float(value)
    return x if math.isfinite(x) else str(x)  # JSON holds finite numbers only


def _lens(name: str, ifd0: dict[int, Any], sub: dict[int, Any], notes: list[str]) -> ExifLens:
    from PIL import ExifTags

    found = {}
    for tag in _TAGS:
        code = int(ExifTags.Base[tag])
        value = sub.get(code, ifd0.get(code))
        if value is not None:
            found[tag] = value

    def number(tag: str) -> float | None:
        """The tag as a finite float, or `None` (absent; or left out, with a note)."""
        value = found.get(tag)
        if value is None:
            return None
        if not _is_number(value):
            notes.append(f"{name}: EXIF {tag} {_raw(value)!r} is not a number; left out")
            return None
        if getattr(value, "denominator", 1) == 0:
            if value.numerator != 0:  # 0/0: unknown, as 0 is
                notes.append(f"{name}: EXIF {tag} {_raw(value)} has a zero denominator; left out")
            return None
        x = float(value)
        if not math.isfinite(x) or x < 0:
            notes.append(f"{name}: EXIF {tag} {x:g} is not a finite number >= 0; left out")
            return None
        return x

    def text(tag: str) -> str | None:
        value = found.get(tag)
        return (_raw(value) or None) if isinstance(value, (str, bytes)) else None

    mm = number("FocalLength")
    focal_length = mm / 1000 if mm else None  # 0: unknown (a manual lens)
    f_number = number("FNumber") or None
    apex = None if f_number else number("ApertureValue")
    if apex is not None:
        f_number = 2.0 ** (apex / 2)
    mm35 = number("FocalLengthIn35mmFilm")
    focus = number("SubjectDistance")
    if getattr(found.get("SubjectDistance"), "numerator", None) == _INFINITY or focus == _INFINITY:
        focus = math.inf
    focus = focus or None  # 0: unknown
    return ExifLens(
        focal_length=focal_length,
        f_number=f_number,
        focus_distance=focus,
        pixel_pitch=_pixel_pitch(name, number, found.get("FocalPlaneResolutionUnit", 2), notes),
        focal_length_35mm=mm35 / 1000 if mm35 else None,
        pixel_dimensions=_dimensions(number("ExifImageWidth"), number("ExifImageHeight")),
        make=text("Make"),
        model=text("Model"),
        lens_model=text("LensModel"),
        source={tag: _raw(value) for tag, value in found.items()},
        notes=tuple(notes),
    )


def _pixel_pitch(name: str, number, unit: Any, notes: list[str]) -> float | None:
    """`unit / FocalPlaneXResolution` in metres, or `None` (absent, no unit, or implausible)."""
    resolution = number("FocalPlaneXResolution")
    if not resolution:
        return None
    if unit not in _UNIT:  # 1: no absolute unit; anything else is not defined
        notes.append(
            f"{name}: EXIF FocalPlaneResolutionUnit {_raw(unit)!r} is not a length unit; the "
            "pixel pitch is left out"
        )
        return None
    pitch = _UNIT[unit] / resolution
    if not _PITCH_RANGE[0] <= pitch <= _PITCH_RANGE[1]:
        notes.append(
            f"{name}: EXIF focal-plane resolution gives a pixel pitch of {pitch * 1e6:.4g} um, "
            "outside 0.1-100 um; left out"
        )
        return None
    return pitch


def _dimensions(width: float | None, height: float | None) -> tuple[int, int] | None:
    if width and height and width == int(width) and height == int(height):
        return int(width), int(height)
    return None
