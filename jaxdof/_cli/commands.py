"""The commands `demo`, `render`, `fit`, `info`, `chart` and `calibrate`: read and check the
files, call the library, report.

The CLI checks what only it can know: the files (paths, shapes, an output over an input), the
figure path, and combinations of its options. Everything about the values (a focus beyond the
focal length, depths beyond it, solver settings) is checked by `jaxdof.ThinLens`, `jaxdof.render`
and `jaxdof.fit_lens`, whose `ValueError` becomes the same one-line error (`library_checks`).
Each command returns the exit status.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import gc
import logging
import math
import re
import time
from typing import Any

import numpy as np

import jaxdof

from .. import _tuning
from .._allocator import _glibc, retain_freed_memory
from .._exif import ExifLens, read_exif
from .._fit.photo import NUISANCES
from .._fit.solve import watch_stages
from .._fit.tiles import SIDE, estimate_fit_memory, use_tiles
from .._io import (
    _FORMATS,
    RAW_SUFFIXES,
    InputError,
    _read_raw,
    _suffix,
    check_output,
    chroma_subsampled,
    jpeg_header,
    read_depth,
    read_image,
    write_image,
)
from .._render import _check_downsample, _needs_whole_frame, band_starts, estimate_memory
from .._upsample import depth_ratio
from . import plot, report
from .demo import demo_scene
from .progress import Display, FitProgress
from .report import note


FULL_FRAME_WIDTH = 0.036  # m: the default --sensor-width
# the readable files that hold EXIF
EXIF_SUFFIXES = (".jpg", ".jpeg", ".tif", ".tiff", ".png", *RAW_SUFFIXES)


@contextlib.contextmanager
def library_checks():
    """The library's own input checks (`ValueError`, house style) as the CLI's one-line error."""
    try:
        yield
    except ValueError as err:
        raise InputError(" ".join(str(err).split())) from None


def _read_inputs(args, display: Display) -> tuple:
    display.status(f"reading {args.image}")
    img = read_image(args.image, linear=args.linear, option="IMAGE")
    for n in img.notes:
        note(n)
    display.status(f"reading {args.depth}")
    depth = read_depth(
        args.depth,
        scale=args.depth_scale,
        zbuffer=args.zbuffer,
        near=args.near,
        far=args.far,
        inverse=args.inverse_depth,
        option="DEPTH",
    )
    if depth.shape != img.array.shape[:2]:  # the library would say so too, but not which files
        try:
            depth_ratio(depth.shape, img.array.shape)
        except ValueError:
            raise InputError(
                f"{args.depth}: depth is {depth.shape[0]}x{depth.shape[1]} (HxW) but image "
                f"{args.image} is {img.array.shape[0]}x{img.array.shape[1]}; they must match, "
                "or the depth be a coarser sensor's of the same frame"
            ) from None
        display.status(f"upsampling {args.depth} to the image, guided by it")
        note(
            f"{args.depth}: depth {depth.shape[0]}x{depth.shape[1]} upsampled to the image's "
            f"{img.array.shape[0]}x{img.array.shape[1]}, guided by it at depth edges"
        )
        depth = jaxdof.upsample_depth(depth, img.array)
    return img, depth


def _photo_width(args, image_shape) -> int:
    """The photo's width in pixels (the lens's pixel pitch is the photo's): IMAGE's / --downsample.

    The lens is built before the library sees `downsample`, so its check runs here first.
    """
    try:
        s = _check_downsample(args.downsample, image_shape)
    except ValueError as err:
        raise InputError(f"--downsample {args.downsample}: {err} (IMAGE)") from None
    return image_shape[1] // s


def _lens(focal_length: float, f_number: float, focus: float, sensor_width: float, width: int):
    with library_checks():  # e.g. a focus distance not beyond the focal length
        return jaxdof.ThinLens.from_sensor(
            focal_length, f_number, focus, sensor_width=sensor_width, image_width=width
        )


# ----------------------------------------------------------------------------------------------
# render


def run_render(args) -> int:
    with Display.for_stderr(args.quiet) as display:
        return _render(args, display)


def _render(args, display: Display) -> int:
    inputs = [args.image, args.depth]
    img, depth = _read_inputs(args, display)
    check_output(args.out, inputs)
    holes = int(jaxdof.depth_holes(depth).sum())
    if holes and not args.fill_holes:
        raise InputError(
            f"{args.depth}: depth has {holes} holes (0, negative or NaN: no data); --fill-holes "
            "fills each from its nearest pixel"
        )
    depth = jaxdof.fill_depth_holes(depth) if holes else depth
    width = _photo_width(args, img.array.shape)
    sensor_width = FULL_FRAME_WIDTH if args.sensor_width is None else args.sensor_width
    lens = _lens(args.focal_length, args.f_number, args.focus, sensor_width, width)
    with library_checks():  # e.g. depths not beyond the focal length
        radius = _largest_circle(depth, lens)
    window = radius if args.max_radius is None else args.max_radius
    rows = band_rows(args, img.array.shape, window)
    if rows is None:
        # Kept freed memory (`jaxdof.retain_freed_memory`) speeds up a frame that fits; a frame in
        # bands would keep every band's freed buffers besides the next band's (24 MP in three
        # bands: 3.4 GB peak with it, 2.0 GB without, in the same time).
        retain_freed_memory()
    photo = (img.array.shape[0] // args.downsample, width)
    bands = len(band_starts(photo[0], rows)) if rows else 1
    t0 = time.perf_counter()
    what = f"rendering {photo[0]}x{photo[1]}" + (
        f" in {bands} bands of {rows} rows" if rows else ""
    )
    display.status(what, total=bands if rows else None)
    with (
        library_checks(),
        out_of_memory("render", img.array.shape),
        _band_progress(display, what) as progress,
    ):
        out = jaxdof.render(
            img.array,
            depth,
            lens,
            method=args.method,
            max_radius=args.max_radius,
            normalize=args.normalize,
            footprint=args.footprint,
            downsample=args.downsample,
            band_rows=rows,
        )
        out = np.asarray(out)
    bits = img.bits
    del img, depth  # the frame's inputs go before the output is encoded (in float64)
    _give_back_freed_memory()
    display.status(f"writing {args.out}")
    write_image(args.out, out, bits=bits, linear=args.linear, inputs=inputs)
    h, w = out.shape[:2]
    in_bands = f", {bands} bands of {rows} rows" if rows else ""
    chose = f", treatment: {progress.treatment}" if progress.treatment else ""
    print(
        f"wrote {args.out} ({h}x{w}, blur scale K = {float(lens.blur_scale):.3g} px, largest circle "
        f"{radius:.3g} px{in_bands}{chose}, {time.perf_counter() - t0:.1f} s)"
    )
    return 0


def _give_back_freed_memory() -> None:
    """Return the memory the render freed to the system (glibc's `malloc_trim`; nothing
    elsewhere), so that encoding the output (float64 copies of the frame, in `_io`) does not come
    on top of it: a 6000 x 4000 frame in 3 bands kept 1.56 GB after the render, 1.08 GB after
    this, and the peak fell from 2.36 GB (writing) to 2.07 GB (rendering)."""
    gc.collect()  # arrays held only by reference cycles
    libc = _glibc()
    if libc is not None and hasattr(libc, "malloc_trim"):
        libc.malloc_trim(0)


def _largest_circle(depth: np.ndarray, lens: jaxdof.ThinLens, rows: int = 256) -> float:
    """The largest circle of confusion (photo pixels), computed `rows` rows at a time: the
    circles of a whole 24 MP frame at once are a gigabyte of temporaries."""
    return max(
        float(np.max(np.asarray(jaxdof.coc_radius(depth[a : a + rows], lens))))
        for a in range(0, depth.shape[0], rows)
    )


def _size(nbytes: int | float) -> str:
    """`nbytes` as `--memory` takes it: `850MB`, `3.2GB` (binary units)."""
    if nbytes < 2**30:
        return f"{math.ceil(nbytes / 2**20)}MB"
    return f"{math.ceil(nbytes / 2**30 * 10) / 10:g}GB"


def band_rows(args, shape: tuple[int, ...], window: float) -> int | None:
    """`render`'s band height (photo rows) under `--memory`: `None` (the whole frame at once)
    when the whole frame fits, else the highest band that fits.

    What the process needs: `jaxdof.internal.estimate_memory` of the render (whole frame or one
    band, with the output) plus what the command holds meanwhile (the runtime, and the image and
    depth as read: `_tuning.CLI_MEMORY`). Where even one row cannot fit, or the method cannot
    run in bands: `InputError` saying what the frame needs and what budget would do.
    """
    s, budget = args.downsample, args.memory
    # `--method auto` may turn the footprint correction on (`render`): planned as on
    footprint = args.method == "auto" if args.footprint is None else args.footprint
    options = dict(downsample=s, normalize=args.normalize, footprint=footprint)
    # the process (runtime, compiled code) and the command's whole-frame arrays
    cli = _tuning.CLI_MEMORY
    held = int(cli["process"] + cli["per_pixel"] * shape[0] * shape[1])

    def need(rows: int | None) -> int:
        return held + estimate_memory(shape, window, args.method, band_rows=rows, **options)

    whole = need(None)
    if whole <= budget:
        return None
    if _needs_whole_frame(args.method):
        raise InputError(
            f"--method {args.method} renders the whole frame at once (it reads the depth map or "
            f"decides from every pixel), which needs about {_size(whole)} for this "
            f"{shape[0]}x{shape[1]} image, over --memory {_size(budget)}: give --memory "
            f"{_size(whole * 1.1)}, another --method, or a smaller image"
        )
    if need(1) > budget:
        raise InputError(
            f"{args.image}: a {shape[0]}x{shape[1]} image with circles of {window:.3g} px needs "
            f"about {_size(need(1))} even in bands of one row (the whole frame {_size(whole)}), "
            f"over --memory {_size(budget)}: give --memory {_size(need(1) * 1.1)} or more, or a "
            "smaller image"
        )
    photo_rows = shape[0] // s
    lo, hi = 1, photo_rows  # need(lo) fits, need(hi) does not (the whole frame)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if need(mid) <= budget else (lo, mid)
    # as few bands as fit, of equal height (the last band overlaps the one before it: keep it
    # from redoing most of a band)
    bands = math.ceil(photo_rows / lo)
    return math.ceil(photo_rows / bands)


@contextlib.contextmanager
def out_of_memory(command: str, shape: tuple[int, ...]):
    """XLA's `RESOURCE_EXHAUSTED` (an allocation the machine could not make) as one line."""
    try:
        yield
    except (RuntimeError, MemoryError) as err:  # jax.errors.JaxRuntimeError is a RuntimeError
        text = str(err)
        if "RESOURCE_EXHAUSTED" not in text and not isinstance(err, MemoryError):
            raise  # not about memory: a bug, with its traceback
        asked = re.search(r"allocating (\d+) bytes", text)
        size = f" (an allocation of {_size(int(asked.group(1)))})" if asked else ""
        hint = (
            "give a smaller --memory (narrower bands) or a smaller image"
            if command == "render"
            else "give a smaller image (a crop, or resized files)"
        )
        raise InputError(f"out of memory{size} on a {shape[0]}x{shape[1]} image; {hint}") from None


@contextlib.contextmanager
def _band_progress(display: Display, what: str):
    """Each band the library finishes (its `"jaxdof"` logger, DEBUG) as the display's progress."""
    handler = _BandHandler(display, what)
    logger = logging.getLogger("jaxdof")
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    try:
        yield handler
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)


class _BandHandler(logging.Handler):
    def __init__(self, display: Display, what: str):
        super().__init__(logging.DEBUG)
        self.display, self.what = display, what
        self.treatment: str | None = None  # what `render(method="auto")` chose, in words

    def emit(self, record: logging.LogRecord) -> None:
        self.treatment = getattr(record, "treatment", self.treatment)
        band = getattr(record, "band", None)
        if band is None:
            return
        done, total = band
        self.display.status(self.what, completed=done, total=total)
        self.display.log(f"  band {done}/{total}  ({self.display.elapsed:.1f} s)")


# ----------------------------------------------------------------------------------------------
# fit


def _read_targets(args, image_shape, photo_width: int, display: Display, read) -> list[np.ndarray]:
    """The photos, from `read` (`_reading`'s futures, in order), checked against the image."""
    s = args.downsample
    photo = (image_shape[0] // s, photo_width, *image_shape[2:])
    targets = []
    for path, future in zip(args.targets, read):
        display.status(f"reading {path}")
        t = future.result()  # what reading raised, raised here, in the order of the files
        for n in t.notes:
            note(n)
        if t.array.shape != photo:  # the library would say so too, but not which file
            of = "" if s == 1 else f" / --downsample {s} = {photo}"
            raise InputError(
                f"{path}: target has shape {t.array.shape} but image {args.image} has "
                f"{tuple(image_shape)}{of}; targets must match the image (height, width, channels)"
            )
        targets.append(t.array)
    return targets


@contextlib.contextmanager
def _reading(paths, linear: bool):
    """The photos read in a thread of their own (futures, in order) while the image and depth
    are read: decoding a file (zlib, JPEG) and its conversion to linear light leave Python's
    lock, so the two overlap on two cores (a 24 MP 16-bit PNG takes seconds). On the way out
    the reads not started are dropped (an error in the image's file ends the command)."""
    pool = concurrent.futures.ThreadPoolExecutor(max_workers=1)
    try:
        yield [pool.submit(read_image, p, linear=linear, option="TARGET") for p in paths]
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _check_free(free, shared, n_targets: int) -> None:
    """The one combination of `--free`/`--shared` that no photos can determine, refused before
    the fit (`fit_lens` finds it only after solving, from the rank of the Jacobian)."""
    both = {"focal_length", "f_number"}
    if both <= set(free) and (n_targets == 1 or not both <= set(shared)):
        raise InputError(
            "--free focal_length f_number: one photo cannot tell them apart (its blur depends on "
            "the lens through K = f^2/(2N(d_f - f)) and d_f only); hold one, or fit a focus "
            "bracket of several TARGETs with --shared focal_length f_number"
        )


def _read_weight(path: str, photo: tuple[int, ...]) -> np.ndarray:
    """`--weight`: one weight per photo pixel, `(H, W)`, the same for every target.

    Read as data, not light: integer files scale to `[0, 1]` without sRGB decoding (a 0/255
    mask is 0/1), float files are as they are. An RGB file is taken when its channels agree (a
    mask saved in colour): one of them.
    """
    w = read_image(path, linear=True, option="--weight").array
    if w.ndim == 3:
        if not np.all(w == w[..., :1]):
            raise InputError(
                f"{path}: weight has {w.shape[-1]} different channels; give one weight per pixel "
                "(grayscale, or a mask whose channels are equal) (--weight)"
            )
        w = w[..., 0]
    if w.shape != tuple(photo[:2]):
        raise InputError(
            f"{path}: weight is {w.shape[0]}x{w.shape[1]} (HxW) but the photo (TARGET) is "
            f"{photo[0]}x{photo[1]}; it must match (--weight)"
        )
    if np.any(w < 0):
        raise InputError(f"{path}: weights must be >= 0 (0 leaves a pixel out) (--weight)")
    return w


def _photo_exif(args, path: str | None = None) -> ExifLens | None:
    """A photo's EXIF lens fields (`path`, by default the first TARGET's): `None` with
    `--no-exif`, for a file that holds no EXIF (`.npy`), or when it has no lens fields. Its pixels
    were read already, so metadata that cannot be parsed is a note, and the command goes on
    without it."""
    path = args.targets[0] if path is None else path
    if args.no_exif or _suffix(path) not in EXIF_SUFFIXES:
        return None
    try:
        exif = read_exif(path)
    except ValueError as err:
        note(f"{err}; its EXIF is not used")
        return None
    for n in exif.notes:
        note(n)
    return exif if exif.has_lens else None


def _start(
    args, depth: np.ndarray, photo: tuple[int, ...]
) -> tuple[dict[str, float], dict[str, Any] | None]:
    """The fit's starting lens, `{focal_length, f_number, focus_distance, sensor_width}` (SI), and
    the `--json` `"exif"` object (`None` when no EXIF lens fields were read).

    Each value is the option's when given, else the first TARGET's EXIF value where it has one,
    else the default (f/4, the median depth of the scene, a 36 mm sensor width); the focal length
    has no default. What EXIF said and what of it was used goes on stderr in one line.
    """
    exif = _photo_exif(args)
    given = {
        "focal_length": args.focal_length,
        "f_number": args.f_number,
        "focus_distance": args.focus,
        "sensor_width": args.sensor_width,
    }
    read = _exif_values(exif, photo)
    focal_length: float | None = given["focal_length"] or read.get("focal_length")
    if focal_length is None:
        why = "--no-exif" if args.no_exif else f"{args.targets[0]} has no EXIF FocalLength"
        raise InputError(
            f"the starting focal length is unknown ({why}): give --focal-length, e.g. 50mm"
        )
    focus = read.get("focus_distance")
    if given["focus_distance"] is None and focus is not None and focus <= focal_length:
        note(
            f"{args.targets[0]}: EXIF SubjectDistance {focus:g} m is not beyond the focal length "
            f"{focal_length * 1e3:g} mm; not used"
        )
        del read["focus_distance"]
    defaults: dict[str, float] = {
        "focal_length": focal_length,
        "f_number": 4.0,
        "sensor_width": FULL_FRAME_WIDTH,
    }
    if given["focus_distance"] is None and "focus_distance" not in read:
        # the scene's median depth (NaN: holes), found only where needed (24 MP: a second)
        defaults["focus_distance"] = float(np.nanmedian(depth))
    values = {
        name: value if value is not None else read[name] if name in read else defaults[name]
        for name, value in given.items()
    }
    if exif is None:
        return values, None
    return values, _exif_summary(args, exif, read, given, photo)


def _exif_values(exif, photo: tuple[int, ...]) -> dict[str, float]:
    """The lens fields EXIF holds (SI; the sensor width for a photo of shape `photo`)."""
    if exif is None:
        return {}
    found = {
        "focal_length": exif.focal_length,
        "f_number": exif.f_number,
        "focus_distance": exif.focus_distance,
        "sensor_width": exif.sensor_width(photo[1], photo[0]),
    }
    return {name: value for name, value in found.items() if value is not None}


def _exif_summary(args, exif, read: dict, given: dict, photo: tuple[int, ...]) -> dict[str, Any]:
    """The `--json` `"exif"` object; what EXIF said and what of it was used, on stderr."""
    used = [name for name in read if given[name] is None]
    overridden = [name for name in read if given[name] is not None]
    if "sensor_width" in used and exif.pixel_pitch is not None and exif.pixel_dimensions:
        if tuple(exif.pixel_dimensions) != (photo[1], photo[0]):
            w, h = exif.pixel_dimensions
            note(
                f"{args.targets[0]}: the EXIF describes a {w}x{h} (WxH) image, the file is "
                f"{photo[1]}x{photo[0]}: the sensor width assumes the photo was resized, not "
                "cropped (give --sensor-width for a crop)"
            )
    note(report.exif_line(args.targets[0], exif, read, used, overridden, args.free))
    return {
        "file": args.targets[0],
        **exif.to_dict(),
        "sensor_width": read.get("sensor_width"),
        "used": used,
        "overridden": overridden,
    }


@dataclasses.dataclass
class FitCall:
    """What `run_fit` hands `jaxdof.fit_lens`: `fit_lens(*positional, **kwargs)`, from the files
    and options, checked; `image`, `depth`, `targets` (one array per TARGET) and `model` for the figure."""

    image: np.ndarray
    depth: np.ndarray
    targets: list[np.ndarray]
    init: jaxdof.ThinLens
    kwargs: dict[str, Any]
    model: dict[str, Any]
    exif: dict[str, Any] | None = None  # the first TARGET's EXIF lens fields: `_start`
    progress: FitProgress | None = None  # what the fit shows on stderr (`None`: --quiet)

    @property
    def positional(self) -> tuple:
        targets = self.targets[0] if len(self.targets) == 1 else np.stack(self.targets)
        return (self.image, self.depth, targets, self.init)


def _fit_inputs(args) -> list[str]:
    """`fit`'s input files, which no output may overwrite."""
    return [args.image, args.depth, *args.targets, *([args.weight] if args.weight else [])]


def fit_call(args, display: Display | None = None) -> FitCall:
    """Read and check `fit`'s files and options into the arguments of `jaxdof.fit_lens` (no
    solve: what the library checks of the values, it checks when called). The solver's steps
    go to `display` (default: plain lines on stderr; none with `--quiet`)."""
    display = Display.for_stderr(args.quiet) if display is None else display
    with _reading(args.targets, args.linear) as read:
        img, depth = _read_inputs(args, display)
        width = _photo_width(args, img.array.shape)
        targets = _read_targets(args, img.array.shape, width, display, read)
    weight = None if args.weight is None else _read_weight(args.weight, targets[0].shape)
    _check_free(args.free, args.shared, len(targets))
    plot.check_plot(args.plot, _fit_inputs(args), "--plot")
    start, exif = _start(args, depth, targets[0].shape)
    init = _lens(
        start["focal_length"],
        start["f_number"],
        start["focus_distance"],
        start["sensor_width"],
        width,
    )
    model = dict(method=args.method, footprint=args.footprint, downsample=args.downsample)
    progress, verbose = None, False
    if not args.quiet:
        progress = FitProgress(display, fields=args.free, max_steps=args.max_steps)
        # each solver step: a host callback in the solve, whose programs are then not cached
        verbose = progress if args.steps else False
    kwargs = dict(
        free=tuple(args.free),
        shared=tuple(args.shared),
        max_steps=args.max_steps,
        max_radius=args.max_radius,
        weight=weight,
        border=args.border,
        tiles=args.tiles,
        edge_weight=args.edge_weight,
        verbose=verbose,
        luma=_luma(args),
        jpeg=_choice(args.jpeg),
        **{k: _choice(getattr(args, k)) for k in NUISANCES},
        **model,
    )
    return FitCall(img.array, depth, targets, init, kwargs, model, exif, progress)


def _choice(value: str) -> bool | None:
    """`auto`/`on`/`off` as `fit_lens` takes it: None (the fit decides), True, False."""
    return {"auto": None, "on": True, "off": False}[value]


def _luma(args) -> bool | None:
    """`--luma`: `auto` is on where a TARGET is a JPEG with half-resolution colour (its header
    says so), else the fit's own rule (None)."""
    if args.luma != "auto":
        return _choice(args.luma)
    return True if any(chroma_subsampled(path) for path in args.targets) else None


def _fitted_model(call: FitCall, result) -> dict[str, Any]:
    """The `jaxdof.render` options of the forward model the fit chose (`FitResult.treatment`)."""
    t = result.treatment
    method = call.model["method"] if call.model["method"] is not None else t.method
    return dict(method=method, footprint=t.footprint, downsample=call.model["downsample"])


def _available_memory() -> int | None:
    """Bytes the machine can still give (Linux's `MemAvailable`), or None where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def check_fit_memory(args, call: FitCall) -> None:
    """Stop, before it starts, a fit estimated (`jaxdof._fit.tiles.estimate_fit_memory`) to need
    more than `--memory` (default: what the machine has available once the files are read):
    `InputError` with the tile budget that would fit, or a smaller image where none would."""
    photo = call.targets[0].shape
    budget = use_tiles(args.tiles, photo)
    t = len(call.targets)
    need = estimate_fit_memory(call.image.shape, photo, t, budget)
    room = _available_memory() if args.memory is None else args.memory
    if room is None or need <= room:
        return
    table = _tuning.FIT_MEMORY
    frame = table["fixed"] + table["frame"] * call.image.shape[0] * call.image.shape[1]
    fits = int((room - frame) / (4 * table["fitted"] * t)) // SIDE**2 * SIDE**2  # whole tiles
    what = "the whole frame" if budget is None else f"on tiles of {budget} pixels"
    limit = "--memory" if args.memory is not None else "available"
    hint = (
        f"give --tiles {fits} or less"
        if fits >= 2 * SIDE**2
        else "give a smaller image (a crop, or resized files)"
    )
    raise InputError(
        f"a fit {what} of this {photo[0]}x{photo[1]} photo needs about {_size(need)}, over the "
        f"{_size(room)} {limit}: {hint}"
    )


def _watched(progress: FitProgress | None):
    """The fit's stages shown by `progress` (`watch_stages`), which keeps its programs free of
    host callbacks and so in the compilation cache; nothing with `--quiet`."""
    return contextlib.nullcontext() if progress is None else watch_stages(progress.watch)


def run_fit(args) -> int:
    with Display.for_stderr(args.quiet) as display:
        call = fit_call(args, display)
        check_fit_memory(args, call)
        if use_tiles(args.tiles, call.targets[0].shape) is None:
            # Kept freed memory (`jaxdof.retain_freed_memory`) speeds up a whole-frame fit. A fit
            # on tiles frees its full-size frames early, and keeping them raises the peak: 24 MP,
            # 3.75 GiB with the setting (the heap only grows), 3.33 GiB without.
            retain_freed_memory()
        # the first step is shown once the solve is compiled (tens of seconds on a megapixel)
        display.status("preparing and compiling the fit")
        with library_checks(), out_of_memory("fit", call.image.shape), _watched(call.progress):
            # library_checks: e.g. --shared not within --free, or the data cannot decide the lens
            result = jaxdof.fit_lens(*call.positional, **call.kwargs)
        if call.progress is not None:
            call.progress.close()
    summary = report.fit_summary(result)
    if call.exif is not None:
        summary["exif"] = call.exif
    pixels = len(call.targets) * int(np.prod(call.targets[0].shape[:2]))
    report.print_fit(summary, args.targets, args.free, as_json=args.json, pixels=pixels)
    if args.plot:
        with Display.for_stderr(args.quiet) as display, out_of_memory("fit", call.image.shape):
            display.status(f"drawing {args.plot}")
            plot.plot_fit(
                args.plot,
                call.image,
                jaxdof.fill_depth_holes(call.depth),  # what the fit rendered
                call.targets,
                result,
                args.targets,
                _fit_inputs(args),
                render_options=_fitted_model(call, result),
            )
        note(f"wrote {args.plot}")
    return 0 if summary["success"] else 1


# ----------------------------------------------------------------------------------------------
# info


def describe(path: str) -> dict[str, Any]:
    """`info`'s object for `path`: what `read_image` reads (the stored array: size, channels,
    type, the colour encoding it is decoded with) and the file's EXIF lens fields. A camera RAW
    file is described as LibRaw decodes it (16-bit linear RGB), with what LibRaw read under
    `"raw"` (`jaxdof._io.read_camera_raw`)."""
    suffix = _suffix(path)
    decoded = None
    if suffix in RAW_SUFFIXES:
        loaded = read_image(path, option="FILE")
        raw, decoded = loaded.array, loaded.raw_decode
        dtype, encoding, kind = "uint16", "linear", f"camera RAW ({suffix[1:].upper()})"
    else:
        raw = _read_raw(path, "image", "FILE")
        dtype = raw.dtype.name
        kind = suffix[1:].upper() if suffix in (".npy", ".npz") else _FORMATS[suffix][0]
        if raw.dtype in (np.uint8, np.uint16):
            encoding = "sRGB"
        elif raw.dtype.kind == "f":
            encoding = "linear"
        else:
            encoding = "unsupported"  # read_image refuses it
    h, w = raw.shape[:2]
    channels = 1 if raw.ndim == 2 else int(raw.shape[-1])
    out: dict[str, Any] = {
        "file": path,
        "format": kind,
        "width": int(w),
        "height": int(h),
        "channels": channels,
        "colour": {1: "grey", 2: "grey+alpha", 3: "RGB", 4: "RGBA"}.get(channels, "other"),
        "alpha": channels in (2, 4),
        "dtype": dtype,
        "bits": np.dtype(dtype).itemsize * 8,
        "encoding": encoding,
        "exif": None,
        **({} if decoded is None else {"raw": decoded}),
        **({} if (header := jpeg_header(path)) is None else {"jpeg": header}),
    }
    if suffix in EXIF_SUFFIXES:
        try:
            exif = read_exif(path)
        except ValueError as err:  # the pixels were read: the metadata alone is unreadable
            note(f"{err}; EXIF left out")
            return out
        for n in exif.notes:
            note(n)
        if exif.source:
            out["exif"] = {**exif.to_dict(), "sensor_width": exif.sensor_width(w, h)}
    return out


def run_info(args) -> int:
    info = describe(args.file)
    report.print_info(info, as_json=args.json)
    if "raw" in info and not args.json:
        _print_raw(info["raw"])
    return 0


def _print_raw(raw: dict[str, Any]) -> None:
    """What LibRaw read from a camera RAW file and how it decoded it, below `print_info`'s lines."""
    width, height = raw["raw_size"]
    mosaic = f"CFA {raw['cfa']}" if raw["cfa"] else "no colour mosaic"
    print(f"  {'RAW':16s}{raw['decoder']}: {width} x {height} stored pixels, {mosaic}")
    levels = "/".join(str(b) for b in raw["black_level"])
    print(f"  {'levels':16s}black {levels} (per {raw['colours']}), white {raw['white_level']}")
    gains = ", ".join(f"{c} {g:.4g}" for c, g in zip(raw["colours"], raw["white_balance"]))
    print(f"  {'white balance':16s}{raw['white_balance_source']}: {gains}")
    print(
        f"  {'decoded':16s}{raw['demosaic']} demosaic, sRGB primaries, linear light (no tone "
        "curve), 16-bit"
    )


# ----------------------------------------------------------------------------------------------
# demo


def _demo_figure(path: str) -> str | None:
    """`--out`, checked; `None` (with a note) without matplotlib: the demo runs without it."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        note("matplotlib is not installed, so no figure is written (pip install 'jaxdof[plot]')")
        return None
    plot.check_plot(path, [], "--out")
    return path


def run_demo(args) -> int:
    path = _demo_figure(args.out)
    t0 = time.perf_counter()
    image, depth = demo_scene()
    h, w = depth.shape
    truth = jaxdof.ThinLens.from_sensor(0.085, 1.4, 3.0, sensor_width=0.036, image_width=w)
    start = jaxdof.ThinLens.from_sensor(0.085, 4.0, 5.0, sensor_width=0.036, image_width=w)
    # The photo as a camera takes it: occlusion at the depth edges, each pixel integrating the light
    # over its area (the footprint), and sensor noise (seeded: without it every standard error is 0).
    noise = np.random.default_rng(1).normal(0.0, 0.005, size=image.shape).astype(np.float32)
    photo = jaxdof.render(image, depth, truth, method="local_occlusion", footprint=True)
    target = np.asarray(photo) + noise
    print(
        f"scene {h}x{w}, depths {depth.min():.2g}-{depth.max():.2g} m; truth 85mm f/1.4 focused at "
        f"3 m (blur scale {float(truth.blur_scale):.2f} px), rendered with occlusion and the pixel "
        "footprint, + noise sigma 0.005; start f/4 at 5 m"
    )
    free = ("focus_distance", "f_number")
    with Display.for_stderr(args.quiet) as display:
        display.status("preparing and compiling the fit")
        progress = FitProgress(display, fields=free)
        with _watched(progress):
            result = jaxdof.fit_lens(image, depth, target, start, free=free)
        progress.close()
    report.print_demo(truth, start, result)
    if path:
        t = result.treatment
        assert t is not None  # fit_lens always reports its treatment
        refit = np.asarray(
            jaxdof.render(image, depth, result.lens, method=t.method, footprint=t.footprint)
        )
        radius = np.asarray(jaxdof.coc_radius(depth, truth))
        plot.plot_demo(path, image, target, refit, radius)
        print(f"wrote {path}")
    print(f"total {time.perf_counter() - t0:.1f} s")
    return 0 if result.success else 1


# ----------------------------------------------------------------------------------------------
# chart and calibrate


def run_chart(args) -> int:
    """`jaxdof chart`: design a chart and write its PNG, PDF (printed charts) and sidecar."""
    from .parse import PAPERS

    if args.monitor:
        if args.screen_px is None or args.screen_width is None:
            raise InputError("--monitor needs --screen-px (e.g. 3840x2160) and --screen-width")
        if args.paper or args.size:
            raise InputError("--monitor takes the screen's size, not --paper or --size")
        options: dict[str, Any] = dict(
            monitor=True, screen_px=args.screen_px, screen_width_m=args.screen_width
        )
    else:
        if args.screen_px is not None or args.screen_width is not None:
            raise InputError("--screen-px and --screen-width go with --monitor")
        w, h = args.size if args.size else PAPERS[args.paper or "a4"]
        options = dict(width_m=w, height_m=h, dpi=args.dpi)
    with library_checks():
        chart, raster = jaxdof.make_chart(seed=args.seed, **options)
        paths = jaxdof.write_chart(args.stem, chart, raster, overwrite=args.overwrite)
    nx, ny = chart.texture_px
    where = "a screen" if chart.monitor else f"{chart.dpi:g} dpi"
    print(
        f"wrote {', '.join(str(p) for p in paths)} ({chart.width_m * 1e3:.1f} x "
        f"{chart.height_m * 1e3:.1f} mm, {nx} x {ny} px for {where}, {len(chart.markers)} "
        f"{chart.dictionary} markers, seed {chart.seed})"
    )
    return 0


def run_calibrate(args) -> int:
    """`jaxdof calibrate`: find the chart in each photo (before anything is compiled), then fit."""
    with library_checks():
        chart, raster = jaxdof.read_chart(args.chart)
    plot.check_plot(args.plot, [args.chart, *args.photos], "--plot")
    with Display.for_stderr(args.quiet) as display:
        photos, views = _photos_with_chart(args, chart, display)
        exifs = [_photo_exif(args, p) for p in args.photos]
        shape = photos[0].shape
        pitch = None if args.sensor_width is None else args.sensor_width / shape[1]
        luma = True if any(chroma_subsampled(p) for p in args.photos) else None
        display.status("preparing and compiling the fit")
        progress = (
            None if args.quiet else FitProgress(display, fields=("focus_distance", "f_number"))
        )
        with library_checks(), out_of_memory("fit", shape), _watched(progress):
            cal = jaxdof.calibrate(
                photos if len(photos) > 1 else photos[0],
                chart,
                raster,
                focal_length=args.focal_length,
                pixel_pitch=pitch,
                exif=exifs,
                views=views,
                luma=luma,
            )
        if progress is not None:
            progress.close()
    summary = report.fit_summary(cal.fit)
    summary["chart"] = cal.to_dict()
    if not args.json:
        _print_chart(args.photos, cal, summary["chart"]["photos"])
    pixels = len(photos) * int(np.prod(shape[:2]))
    report.print_fit(
        summary, args.photos, ("focus_distance", "f_number"), as_json=args.json, pixels=pixels
    )
    if args.plot:
        _plot_calibration(args, chart, raster, photos, cal)
    return 0 if summary["success"] else 1


def _photos_with_chart(args, chart, display) -> tuple[list[np.ndarray], list]:
    """`jaxdof calibrate`'s photos, read, and the chart found in each (one line and exit 2 where
    a photo's shape differs or the chart is not found)."""
    photos, views = [], []
    for path in args.photos:
        display.status(f"reading {path}")
        photo = read_image(path, linear=args.linear, option="PHOTO").array
        if photos and photo.shape != photos[0].shape:
            raise InputError(
                f"{path}: shape {photo.shape}, the first PHOTO's is {photos[0].shape}; "
                "the photos must match"
            )
        display.status(f"finding the chart in {path}")
        with library_checks():
            views.append(jaxdof.detect_chart(photo, chart, name=path))
        photos.append(photo)
    return photos, views


def _print_chart(paths, cal, entries) -> None:
    """What the chart told: per photo its markers, fit and pose; the camera and the depths."""
    moved = cal.aligned_px or (None,) * len(paths)
    for path, entry, m in zip(paths, entries, moved):
        again = "" if m is None else f", aligned again with the fitted blur (moved {m:.2f} px)"
        print(
            f"{path}: {entry['markers']} markers, homography error "
            f"{entry['reprojection_error_px']:.2f} px{again}, tilt {entry['tilt_deg']:.1f} "
            f"deg, chart at {entry['distance_m']:.3g} m"
        )
    near, far = cal.depth_range
    pm = f" +- {cal.focal_px_stderr:.2g}" if cal.focal_px_stderr > 0 else ""
    print(
        f"camera: focal length {cal.focal_px:.1f}{pm} px (from the {cal.intrinsics}), chart "
        f"depths {near:.3g}-{far:.3g} m"
    )


def _plot_calibration(args, chart, raster, photos, cal) -> None:
    """`--plot`: photo, render and residual over the chart as the first photo shows it."""
    shape = photos[0].shape
    sharp, depth = jaxdof.chart_scene(chart, raster, cal.poses[0], cal.camera, shape)
    if len(shape) == 3:
        sharp = np.repeat(sharp[..., None], shape[2], axis=-1)
    t = cal.fit.treatment
    assert t is not None  # fit_lens always reports its treatment
    with Display.for_stderr(args.quiet) as display, out_of_memory("fit", shape):
        display.status(f"drawing {args.plot}")
        plot.plot_fit(
            args.plot,
            sharp,
            jaxdof.fill_depth_holes(depth),
            photos,
            cal.fit,
            args.photos,
            [args.chart, *args.photos],
            render_options=dict(method=t.method, footprint=t.footprint, downsample=1),
        )
    note(f"wrote {args.plot}")
