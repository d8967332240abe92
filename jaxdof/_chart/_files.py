"""A chart's files: the raster as a 16-bit PNG, a PDF at the printed size, and a JSON sidecar
that holds the design and the PNG's SHA-256."""

from __future__ import annotations

import hashlib
import io
import json
import os
from pathlib import Path

import numpy as np
from jaxtyping import Float

from .._io import atomic_write
from ._design import Chart, decode, encode, remember


_FORMAT = "jaxdof-chart"
_VERSION = 1


def write_chart(
    stem: str | os.PathLike[str],
    chart: Chart,
    image: Float[np.ndarray, "h w"],
    *,
    overwrite: bool = False,
) -> list[Path]:
    """Write a chart's files: `stem.png`, `stem.pdf` (printed charts only) and `stem.json`.

    **Arguments:**

    - `stem`: the files' path without a suffix.
    - `chart`, `image`: as `make_chart` returns them.
    - `overwrite`: replace files that exist (default: refuse, `ValueError`).

    **Returns:** the paths written.

    The PNG is 16-bit greyscale, sRGB-encoded (a printer or a screen decodes it to the raster's
    reflectance); the PDF holds it (8-bit) at the chart's physical size, `chart.dpi` pixels per
    inch: print it at 100 % ("actual size"), then measure it. A screen's chart is shown from the
    PNG at one image pixel per screen pixel. The sidecar holds the design (size, dictionary,
    marker corners, frame, seed, dpi, monitor), the PNG's name and its SHA-256, which `read_chart`
    checks.
    """
    stem = Path(stem)
    image = np.asarray(image)
    nx, ny = chart.texture_px
    if image.shape != (ny, nx):
        raise ValueError(
            f"image is {image.shape}, the chart's raster is {(ny, nx)} (rows, columns)"
        )
    paths = [stem.with_name(stem.name + s) for s in (".png", ".json")]
    if not chart.monitor:
        paths.insert(1, stem.with_name(stem.name + ".pdf"))
    if not overwrite:
        there = [str(p) for p in paths if p.exists()]
        if there:
            raise ValueError(f"{', '.join(there)} exists; pass overwrite=True to replace it")
    if not paths[0].parent.is_dir():
        raise ValueError(f"{stem}: folder {paths[0].parent} does not exist")
    codes = encode(image)
    png = _png_bytes(codes)
    _write(paths[0], png)
    if not chart.monitor:
        _write(paths[1], _pdf_bytes(codes, chart.dpi))
    side = {
        "format": _FORMAT,
        "version": _VERSION,
        "width_m": chart.width_m,
        "height_m": chart.height_m,
        "dictionary": chart.dictionary,
        "markers": {str(i): np.asarray(c).tolist() for i, c in sorted(chart.markers.items())},
        "seed": chart.seed,
        "texture_px": list(chart.texture_px),
        "dpi": chart.dpi,
        "monitor": chart.monitor,
        "marker_fraction": chart.marker_fraction,
        "frame": None if chart.frame is None else np.asarray(chart.frame).tolist(),
        "frame_width_m": chart.frame_width_m,
        "png": paths[0].name,
        "sha256": hashlib.sha256(png).hexdigest(),
    }
    _write(paths[-1], (json.dumps(side, indent=2) + "\n").encode())
    return paths


def read_chart(sidecar: str | os.PathLike[str]) -> tuple[Chart, Float[np.ndarray, "h w"]]:
    """Read a chart written by `write_chart` from its JSON sidecar.

    **Returns:** `(chart, raster)` as `make_chart` gave them (the raster from the PNG beside the
    sidecar, bit for bit).

    **Raises:** `ValueError` naming the file when the sidecar is not a chart's, or the PNG is
    missing, altered (its SHA-256 differs from the sidecar's) or of another size.
    """
    sidecar = Path(sidecar)
    try:
        side = json.loads(sidecar.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{sidecar}: not a readable chart sidecar ({err})") from None
    if not isinstance(side, dict) or side.get("format") != _FORMAT:
        raise ValueError(f'{sidecar}: not a jaxdof chart sidecar (no "format": "{_FORMAT}")')
    try:
        chart = Chart(
            width_m=float(side["width_m"]),
            height_m=float(side["height_m"]),
            dictionary=str(side["dictionary"]),
            markers={int(i): np.asarray(c, np.float64) for i, c in side["markers"].items()},
            seed=int(side["seed"]),
            texture_px=(int(side["texture_px"][0]), int(side["texture_px"][1])),
            monitor=bool(side["monitor"]),
            dpi=float(side["dpi"]),
            marker_fraction=float(side["marker_fraction"]),
            frame=None if side.get("frame") is None else np.asarray(side["frame"], np.float64),
            frame_width_m=float(side.get("frame_width_m", 0.0)),
        )
        png, digest = sidecar.with_name(side["png"]), str(side["sha256"])
    except (KeyError, TypeError, ValueError, IndexError) as err:
        raise ValueError(f"{sidecar}: chart sidecar lacks or garbles {err}") from None
    try:
        data = png.read_bytes()
    except OSError:
        raise ValueError(f"{png}: the chart's PNG (named in {sidecar}) cannot be read") from None
    if hashlib.sha256(data).hexdigest() != digest:
        raise ValueError(f"{png}: its SHA-256 differs from {sidecar}'s: not this chart's PNG")
    from PIL import Image

    with Image.open(io.BytesIO(data)) as im:
        codes = np.asarray(im).astype(np.uint16)
    nx, ny = chart.texture_px
    if codes.shape != (ny, nx):
        raise ValueError(f"{png}: {codes.shape} pixels, {sidecar} says {(ny, nx)} (rows, columns)")
    raster = decode(codes)
    remember(chart, raster)
    return chart, raster


def _png_bytes(codes: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(codes).save(buf, format="PNG")  # 16-bit greyscale ("I;16")
    return buf.getvalue()


def _pdf_bytes(codes: np.ndarray, dpi: float) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray((codes >> 8).astype(np.uint8)).save(buf, format="PDF", resolution=dpi)
    return buf.getvalue()


def _write(path: Path, data: bytes) -> None:
    def write(tmp: str) -> None:
        with open(tmp, "wb") as fh:
            fh.write(data)

    atomic_write(str(path), write)
