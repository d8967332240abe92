"""The `jaxdof` command line: `demo`, `render` and `fit`, a thin layer over `_io` and the library.

Every problem with the user's files or options ends in one line on stderr that names the file or
option and the problem, and exit status 2 (`InputError`, raised by `_io` and by the checks here).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
import time
from collections.abc import Sequence

import numpy as np

from ._allocator import retain_freed_memory
from ._io import (
    InputError,
    atomic_write,
    check_output,
    linear_to_srgb,
    read_depth,
    read_image,
    write_image,
)


FIELDS = ("focal_length", "f_number", "focus_distance")
_UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}
_LENGTH = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(mm|cm|m)?\s*$")


# ----------------------------------------------------------------------------------------------
# Option parsing


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line on stderr (and exit status 2), not a usage block."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def parse_length(text: str) -> float:
    """`"50mm"`, `"3.5 cm"`, `"3m"` or a bare number (metres) to metres; positive and finite."""
    match = _LENGTH.match(text)
    if match is None:
        raise argparse.ArgumentTypeError(
            f"bad length {text!r}: give a number with a unit mm, cm or m (e.g. 50mm, 3m)"
        )
    value = float(match.group(1)) * _UNITS[match.group(2) or "m"]
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"bad length {text!r}: must be positive and finite")
    return value


def parse_focal_length(text: str) -> float:
    """As `parse_length`, but a bare number of 1 or more (`50`) is refused: it is surely mm."""
    value = parse_length(text)
    if _LENGTH.match(text).group(2) is None and value >= 1:
        raise argparse.ArgumentTypeError(
            f"bare number {text!r} would be {value:g} metres; give a unit, e.g. {text.strip()}mm"
        )
    return value


def parse_positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"bad number {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r} must be positive and finite")
    return value


def parse_nonnegative(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"bad number {text!r}") from None
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number >= 0")
    return value


def _mm(x: float) -> str:
    return f"{x * 1e3:g}mm"


def _add_lens_options(p: argparse.ArgumentParser, *, start: bool) -> None:
    what = "starting " if start else ""
    g = p.add_argument_group(
        "lens" + (" (the starting point of the fit)" if start else ""),
        "Lengths take a unit: mm, cm or m (a bare number is metres; --focal-length 50 is refused).",
    )
    g.add_argument(
        "--focal-length",
        type=parse_focal_length,
        required=True,
        metavar="LEN",
        help=f"{what}focal length, e.g. 50mm",
    )
    g.add_argument(
        "--f-number",
        type=parse_positive,
        required=not start,
        default=4.0 if start else None,
        metavar="N",
        help=f"{what}f-number N = f/D, e.g. 2" + (" (default 4)" if start else ""),
    )
    g.add_argument(
        "--focus",
        type=parse_length,
        required=not start,
        default=None,
        metavar="LEN",
        help=f"{what}focus distance, e.g. 3m"
        + (" (default: the median depth of the scene)" if start else ""),
    )
    g.add_argument(
        "--sensor-width",
        type=parse_length,
        default=0.036,
        metavar="LEN",
        help="sensor width spanned by the image's columns (default 36mm, full frame)",
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


def _add_filter_options(p: argparse.ArgumentParser) -> None:
    from ._filters.coc_filter import METHODS

    g = p.add_argument_group("filter")
    g.add_argument("--method", choices=METHODS, default="soft", help="filter (default: soft)")
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
    _add_footprint_option(g)


def _add_footprint_option(g) -> None:
    g.add_argument(
        "--footprint",
        action="store_true",
        help="correct for the pixel footprint (blur variance r^2/4 at every radius; off by default)",
    )
    g.add_argument(
        "--downsample",
        type=int,
        default=1,
        metavar="S",
        help="IMAGE and DEPTH are S times the photo's resolution in each axis (e.g. a pixel-shift "
        "capture): blur there, then average S x S blocks into the photo's pixels (default 1)",
    )


def _photo_width(args, image_shape) -> int:
    """The photo's width in pixels (the lens's pixel pitch is the photo's): IMAGE's / --downsample."""
    from ._render import _check_downsample

    try:
        s = _check_downsample(args.downsample, image_shape)
    except ValueError as err:
        raise InputError(f"--downsample {args.downsample}: {err} (IMAGE)") from None
    return image_shape[1] // s


_EPILOG_RENDER = """\
examples:
  jaxdof render sharp.png depth.tif -o blurred.png --focal-length 50mm --f-number 2 --focus 3m
  jaxdof render sharp.tif depth.png --depth-scale 1mm -o out.tif \\
      --focal-length 85mm --f-number 1.4 --focus 2.5m --sensor-width 23.5mm
  jaxdof render sharp.npy zbuf.npy --zbuffer --near 0.1m --far 100m -o out.npy \\
      --focal-length 35mm --f-number 2.8 --focus 4m
"""

_EPILOG_FIT = """\
examples:
  jaxdof fit sharp.png depth.tif photo.png --focal-length 50mm --f-number 4 --focus 5m
  jaxdof fit sharp.png depth.tif a.png b.png c.png --focal-length 50mm \\
      --free focal_length f_number focus_distance --shared focal_length f_number --json
  jaxdof fit sharp.tif depth.npy photo.tif --focal-length 85mm --plot fit.png

From one photo only the blur scale K = f^2/(2N(d_f - f))/pitch and the focus distance can be
measured, so by default --free is f_number focus_distance with the focal length held; a focus
bracket (several photos, --shared focal_length f_number) also determines the focal length.
"""

_EPILOG_DEMO = """\
examples:
  jaxdof demo
  jaxdof demo --out blurred_scene.png
"""


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    parser = _Parser(
        prog="jaxdof",
        description="Differentiable thin-lens depth of field: render defocus blur from an "
        "all-in-focus image and a depth map, or calibrate a lens from photos.",
        epilog="Run 'jaxdof COMMAND --help' for each command's options and examples.\n"
        "Exit status: 0 done, 1 the fit did not converge, 2 bad input (one line on stderr).",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"jaxdof {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    fmt = argparse.RawDescriptionHelpFormatter

    demo = sub.add_parser(
        "demo",
        help="render a built-in scene through a known lens and fit the lens back (no files needed)",
        description="Render a built-in procedural scene through a known lens (85mm f/1.4 at 3m), "
        "fit the lens back from a wrong start (f/4 at 5m), print truth beside the recovered values "
        "with standard errors, and write a figure (sharp, target, refit, residual, CoC map).",
        epilog=_EPILOG_DEMO,
        formatter_class=fmt,
    )
    demo.add_argument("--out", default="demo.png", metavar="PNG", help="figure path (demo.png)")
    demo.set_defaults(run=run_demo)

    render = sub.add_parser(
        "render",
        help="render depth of field from an all-in-focus image and a depth map",
        description="Blur IMAGE as a thin lens would, given the z-depth of every pixel in DEPTH.",
        epilog=_EPILOG_RENDER,
        formatter_class=fmt,
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
    _add_lens_options(render, start=False)
    _add_filter_options(render)
    _add_file_options(render)
    render.set_defaults(run=run_render)

    fit = sub.add_parser(
        "fit",
        help="calibrate a lens: fit it to photos of the scene (TARGETs)",
        description="Fit the lens that turns IMAGE (all in focus) with DEPTH into each TARGET "
        "photo (Levenberg-Marquardt on the rendered residual).",
        epilog=_EPILOG_FIT,
        formatter_class=fmt,
    )
    fit.add_argument("image", metavar="IMAGE", help="all-in-focus image")
    fit.add_argument("depth", metavar="DEPTH", help="depth map, same height and width")
    fit.add_argument("targets", metavar="TARGET", nargs="+", help="photo(s) taken through the lens")
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
    _add_footprint_option(fit)
    fit.add_argument(
        "--max-radius",
        type=parse_nonnegative,
        metavar="PX",
        help="filter window in pixels (default: chosen by the fit)",
    )
    fit.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    fit.add_argument("--plot", metavar="PNG", help="write a comparison figure (needs matplotlib)")
    fit.add_argument("--quiet", action="store_true", help="no progress on stderr")
    _add_lens_options(fit, start=True)
    _add_file_options(fit)
    fit.set_defaults(run=run_fit)
    return parser


# ----------------------------------------------------------------------------------------------
# Shared steps


def _note(msg: str) -> None:
    print(msg, file=sys.stderr)


def _read_inputs(args) -> tuple:
    img = read_image(args.image, linear=args.linear, option="IMAGE")
    for n in img.notes:
        _note(n)
    depth = read_depth(
        args.depth,
        scale=args.depth_scale,
        zbuffer=args.zbuffer,
        near=args.near,
        far=args.far,
        inverse=args.inverse_depth,
        option="DEPTH",
    )
    if depth.shape != img.array.shape[:2]:
        raise InputError(
            f"{args.depth}: depth is {depth.shape[0]}x{depth.shape[1]} (HxW) but image "
            f"{args.image} is {img.array.shape[0]}x{img.array.shape[1]}; they must match"
        )
    return img, depth


def _check_lens(f: float, n: float | None, d_f: float | None, depth: np.ndarray, depth_path: str):
    """Physical sense of the options before any JAX work; errors name the option."""
    if d_f is not None and d_f <= f:
        raise InputError(
            f"--focus {d_f:g} m must exceed --focal-length {_mm(f)} (a lens cannot focus closer "
            "than its focal length)"
        )
    nearest = float(np.min(depth))
    if nearest <= f:
        raise InputError(
            f"{depth_path}: nearest depth {nearest:g} m is not beyond the focal length {_mm(f)}; "
            "depth must be in metres (see --depth-scale)"
        )


def _check_plot(path: str | None, inputs: list[str], option: str) -> None:
    if path is None:
        return
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise InputError(f"{option} needs matplotlib: pip install 'jaxdof[plot]'") from None
    check_output(path, inputs, option)
    if os.path.splitext(path)[1].lower() != ".png":
        raise InputError(f"{option} {path}: the figure is written as PNG; name it *.png")


def _display(image: np.ndarray) -> np.ndarray:
    return linear_to_srgb(image)


def _plot(path: str, columns: list[tuple[str, np.ndarray, str]], rows: int, inputs, option) -> None:
    """A grid figure: `columns` is a flat list of `(title, array, kind)` with kind in
    {"image", "residual", "coc"}, laid out `rows` by `len(columns) // rows`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ncols = len(columns) // rows
    fig, axes = plt.subplots(rows, ncols, figsize=(2.6 * ncols, 2.3 * rows), squeeze=False)
    for ax, (title, array, kind) in zip(axes.ravel(), columns):
        if kind == "image":
            ax.imshow(_display(array), cmap="gray" if array.ndim == 2 else None, vmin=0, vmax=1)
        elif kind == "residual":
            res = array if array.ndim == 2 else array.mean(axis=-1)
            lim = float(np.max(np.abs(res))) or 1.0
            im = ax.imshow(res, cmap="RdBu", vmin=-lim, vmax=lim)
            fig.colorbar(im, ax=ax, fraction=0.046)
        else:
            im = ax.imshow(array, cmap="viridis")
            fig.colorbar(im, ax=ax, fraction=0.046)
        ax.set_title(title, fontsize=8)
        ax.axis("off")
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=90, format="png"), list(inputs), option)
    plt.close(fig)


# ----------------------------------------------------------------------------------------------
# render


def run_render(args) -> int:
    inputs = [args.image, args.depth]
    img, depth = _read_inputs(args)
    _check_lens(args.focal_length, args.f_number, args.focus, depth, args.depth)
    check_output(args.out, inputs)

    import jaxdof

    lens = jaxdof.ThinLens.from_sensor(
        args.focal_length,
        args.f_number,
        args.focus,
        sensor_width=args.sensor_width,
        image_width=_photo_width(args, img.array.shape),
    )
    t0 = time.perf_counter()
    try:
        out = jaxdof.render(
            img.array,
            depth,
            lens,
            method=args.method,
            max_radius=args.max_radius,
            normalize=args.normalize,
            footprint=args.footprint,
            downsample=args.downsample,
        )
    except ValueError as err:  # the library's own input checks (house style: ValueError)
        raise InputError(" ".join(str(err).split())) from None
    out = np.asarray(out)
    radius = float(np.max(np.asarray(jaxdof.coc_radius(depth, lens))))
    write_image(args.out, out, bits=img.bits, linear=args.linear, inputs=inputs)
    h, w = out.shape[:2]
    print(
        f"wrote {args.out} ({h}x{w}, blur scale K = {float(lens.blur_scale):.3g} px, largest circle "
        f"{radius:.3g} px, {time.perf_counter() - t0:.1f} s)"
    )
    return 0


# ----------------------------------------------------------------------------------------------
# fit


def _lens_dict(lens, index: int) -> dict:
    def value(name):
        v = np.asarray(getattr(lens, name))
        v = v if v.ndim == 0 else v.reshape(-1)[index]
        # The shortest decimal that round-trips the array's own precision (0.085, not
        # 0.08500000089406967 for a float32 value).
        return float(str(v.item() if v.dtype == np.float64 else np.float32(v)))

    return {name: value(name) for name in (*FIELDS, "pixel_pitch")}


def _stderr_dict(stderr: dict, index: int | None) -> dict:
    out = {}
    for name, v in stderr.items():
        v = np.asarray(v)
        v = v if v.ndim == 0 or index is None else v.reshape(-1)[min(index, v.size - 1)]
        out[name] = float(f"{float(v):.4g}") if np.isfinite(v) else None
    return out


def _progress(quiet: bool):
    """A solver `verbose` callable: step and loss of each start to stderr, ~4 lines a second.

    optimistix calls it inside the compiled solve with `(name, value)` pairs as keywords; the
    values are traced, so they reach Python through `jax.debug.callback`.
    """
    if quiet:
        return False
    import jax

    last = [0.0]

    def show(step, loss):
        now = time.perf_counter()
        if int(step) > 0 and now - last[0] > 0.25:
            last[0] = now
            print(f"  step {int(step):4d}  loss {float(loss):.6g}", file=sys.stderr, flush=True)

    def verbose(**kwargs):
        # optimistix >= 0.1 passes (description, value) pairs; other solvers may pass fewer.
        if "num_steps" in kwargs and "loss_last_accepted_step" in kwargs:
            jax.debug.callback(show, kwargs["num_steps"][1], kwargs["loss_last_accepted_step"][1])

    return verbose


def _format_value(name: str, v: float, err: float | None) -> str:
    if name in ("focal_length", "focus_distance", "pixel_pitch"):
        scale, unit = (1e3, "mm") if name != "focus_distance" else (1.0, "m")
        s = f"{v * scale:.5g} {unit}"
        return s + (f" ± {err * scale:.2g}" if err is not None else "")
    return f"{v:.5g}" + (f" ± {err:.2g}" if err is not None else "")


def run_fit(args) -> int:
    inputs = [args.image, args.depth, *args.targets]
    img, depth = _read_inputs(args)
    photo_width = _photo_width(args, img.array.shape)
    s = args.downsample
    photo = (img.array.shape[0] // s, photo_width, *img.array.shape[2:])
    targets = []
    for path in args.targets:
        t = read_image(path, linear=args.linear, option="TARGET")
        for n in t.notes:
            _note(n)
        if t.array.shape != photo:
            of = "" if s == 1 else f" / --downsample {s} = {photo}"
            raise InputError(
                f"{path}: target has shape {t.array.shape} but image {args.image} has "
                f"{img.array.shape}{of}; targets must match the image (height, width, channels)"
            )
        targets.append(t.array)
    bad = set(args.shared) - set(args.free)
    if bad:
        raise InputError(f"--shared {' '.join(sorted(bad))}: only free fields can be shared")
    both = {"focal_length", "f_number"}
    if both <= set(args.free) and (len(targets) == 1 or not both <= set(args.shared)):
        raise InputError(
            "--free focal_length f_number: one photo cannot tell them apart (its blur depends on "
            "the lens through K = f^2/(2N(d_f - f)) and d_f only); hold one, or fit a focus "
            "bracket of several TARGETs with --shared focal_length f_number"
        )
    if args.max_steps < 1:
        raise InputError(f"--max-steps {args.max_steps}: must be at least 1")
    focus = args.focus if args.focus is not None else float(np.median(depth))
    _check_lens(args.focal_length, args.f_number, focus, depth, args.depth)
    _check_plot(args.plot, inputs, "--plot")

    import jaxdof

    from ._fit import fit_lens

    init = jaxdof.ThinLens.from_sensor(
        args.focal_length,
        args.f_number,
        focus,
        sensor_width=args.sensor_width,
        image_width=photo_width,
    )
    target_arg = targets[0] if len(targets) == 1 else np.stack(targets)
    try:
        result = fit_lens(
            img.array,
            depth,
            target_arg,
            init,
            free=tuple(args.free),
            shared=tuple(args.shared),
            max_steps=args.max_steps,
            max_radius=args.max_radius,
            footprint=args.footprint,
            downsample=s,
            verbose=_progress(args.quiet),
        )
    except ValueError as err:  # e.g. a free set one photo cannot determine
        raise InputError(" ".join(str(err).split())) from None
    n = len(targets)
    lenses = [_lens_dict(result.lenses, i) for i in range(n)]
    errors = [_stderr_dict(result.stderr, i if n > 1 else None) for i in range(n)]
    summary = {
        "success": bool(result.success),
        "message": str(result.message),
        "steps": int(result.num_steps),
        "loss": float(result.loss),
    }
    if args.json:
        obj = {**lenses[0], "stderr": errors[0], **summary}
        obj["lenses"] = [{**lens, "stderr": err} for lens, err in zip(lenses, errors)]
        print(json.dumps(obj, indent=2))
    else:
        for i, (lens, err) in enumerate(zip(lenses, errors)):
            head = f"target {args.targets[i]}" if n > 1 else "recovered lens"
            print(head + ":")
            for name in FIELDS:
                state = "" if name in args.free else "  (held)"
                print(f"  {name:15s} {_format_value(name, lens[name], err.get(name))}{state}")
        verdict = "converged" if summary["success"] else "did NOT converge"
        print(
            f"{verdict} after {summary['steps']} steps, loss {summary['loss']:.4g}: {summary['message']}"
        )
    if args.plot:
        _plot_fit(
            args.plot, img.array, depth, targets, result, args.targets, inputs, s, args.footprint
        )
        _note(f"wrote {args.plot}")
    return 0 if summary["success"] else 1


def _lens_at(lens, index: int):
    import jax

    return jax.tree_util.tree_map(lambda v: v if np.ndim(v) == 0 else v.reshape(-1)[index], lens)


def _plot_fit(path, image, depth, targets, result, names, inputs, s=1, footprint=False) -> None:
    import jax.numpy as jnp

    import jaxdof

    from ._render import box_downsample

    full_image, full_depth = image, depth  # the fit's inputs; shown at the photo's pixels
    if s > 1:
        image = np.asarray(box_downsample(jnp.asarray(image), s))
        depth = 1 / np.asarray(box_downsample(1 / jnp.asarray(depth), s))
    n = len(targets)
    columns = []
    for i, target in enumerate(targets):
        lens = _lens_at(result.lenses, i)
        refit = np.asarray(
            jaxdof.render(full_image, full_depth, lens, downsample=s, footprint=footprint)
        )
        radius = np.asarray(jaxdof.coc_radius(depth, lens))
        name = os.path.basename(names[i])
        columns += [
            ("sharp" if i == 0 else "", image, "image"),
            (f"target {name}", target, "image"),
            ("refit", refit, "image"),
            ("residual (refit - target)", refit - target, "residual"),
            ("CoC radius (px)", radius, "coc"),
        ]
    _plot(path, columns, n, inputs, "--plot")


# ----------------------------------------------------------------------------------------------
# demo


def demo_scene(h: int = 72, w: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """A procedural all-in-focus scene: `(image (h, w, 3) linear, depth (h, w) metres)`.

    A textured ground plane recedes from 1.2 m at the bottom edge to a wall at 12 m, with two
    boxes standing on it at 1.8 m and 5 m, so the depths straddle a 3 m focus on both sides.
    The texture (a checker plus seeded noise) has detail at every scale for the blur to remove.
    """
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    # Ground: inverse depth linear in the row (a plane seen in perspective), capped by the wall.
    inv = 1 / 12 + (1 / 1.2 - 1 / 12) * np.clip((yy - 0.3 * h) / (0.7 * h - 1), 0, 1)
    depth = 1 / inv
    checker = ((yy // 6 + xx // 6) % 2).astype(np.float64)
    base = 0.15 + 0.5 * checker + 0.3 * rng.uniform(size=(h, w))
    image = base[..., None] * np.stack([1.0 + 0 * xx, 0.6 + 0.4 * xx / w, 0.5 + 0.5 * yy / h], -1)
    boxes = [  # (rows, cols, depth m, colour): a near red box and a far blue one
        (
            slice(int(0.25 * h), int(0.85 * h)),
            slice(int(0.10 * w), int(0.35 * w)),
            1.8,
            (0.9, 0.3, 0.2),
        ),
        (
            slice(int(0.15 * h), int(0.55 * h)),
            slice(int(0.55 * w), int(0.85 * w)),
            5.0,
            (0.2, 0.4, 0.9),
        ),
    ]
    stripes = 0.35 + 0.65 * ((xx + yy) // 3 % 2)  # finer texture on the boxes
    for rows, cols, d, colour in boxes:
        depth[rows, cols] = d
        image[rows, cols] = stripes[rows, cols, None] * np.asarray(colour)
    image = np.clip(image, 0, 1)
    return image.astype(np.float32), depth.astype(np.float32)


def run_demo(args) -> int:
    plot = args.out
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        _note("matplotlib is not installed, so no figure is written (pip install 'jaxdof[plot]')")
        plot = None
    if plot:
        check_output(plot, [], "--out")
        if os.path.splitext(plot)[1].lower() != ".png":
            raise InputError(f"--out {plot}: the figure is written as PNG; name it *.png")

    import jaxdof

    from ._fit import fit_lens

    t0 = time.perf_counter()
    image, depth = demo_scene()
    h, w = depth.shape
    truth = jaxdof.ThinLens.from_sensor(0.085, 1.4, 3.0, sensor_width=0.036, image_width=w)
    start = jaxdof.ThinLens.from_sensor(0.085, 4.0, 5.0, sensor_width=0.036, image_width=w)
    # Sensor noise (seeded): without it the fit is exact and every standard error is 0.
    noise = np.random.default_rng(1).normal(0.0, 0.005, size=image.shape).astype(np.float32)
    target = np.asarray(jaxdof.render(image, depth, truth)) + noise
    print(
        f"scene {h}x{w}, depths {depth.min():.2g}-{depth.max():.2g} m; truth 85mm f/1.4 focused at "
        f"3 m (blur scale {float(truth.blur_scale):.2f} px) + noise sigma 0.005; start f/4 at 5 m"
    )
    result = fit_lens(
        image, depth, target, start, free=("focus_distance", "f_number"), verbose=_progress(False)
    )
    err = _stderr_dict(result.stderr, None)
    print(f"{'':16s}{'truth':>12s}{'start':>12s}{'recovered':>24s}")
    for name in FIELDS:
        t, s, r = (float(np.asarray(getattr(x, name))) for x in (truth, start, result.lens))
        print(
            f"  {name:14s}{_format_value(name, t, None):>12s}{_format_value(name, s, None):>12s}"
            f"{_format_value(name, r, err.get(name)):>24s}" + ("" if name in err else "  (held)")
        )
    verdict = "converged" if result.success else "did NOT converge"
    print(f"{verdict} in {int(result.num_steps)} steps, loss {float(result.loss):.3g}")
    if plot:
        refit = np.asarray(jaxdof.render(image, depth, result.lens))
        radius = np.asarray(jaxdof.coc_radius(depth, truth))
        _plot(
            plot,
            [
                ("sharp (all in focus)", image, "image"),
                ("target: 85mm f/1.4 @ 3 m", target, "image"),
                ("refit", refit, "image"),
                ("residual (refit - target)", refit - target, "residual"),
                ("true CoC radius (px)", radius, "coc"),
            ],
            1,
            [],
            "--out",
        )
        print(f"wrote {plot}")
    print(f"total {time.perf_counter() - t0:.1f} s")
    return 0 if result.success else 1


# ----------------------------------------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `jaxdof` script and of `python -m jaxdof`; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(None if argv is None else list(argv))
    except SystemExit as exc:  # --help, --version, or a one-line usage error
        return int(exc.code or 0)
    # the application's call (see `jaxdof.retain_freed_memory`): XLA's per-call scratch is then
    # reused instead of faulted in anew, up to 2x on megapixel images
    retain_freed_memory()
    try:
        return args.run(args)
    except InputError as err:
        print(f"jaxdof {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jaxdof: interrupted", file=sys.stderr)
        return 130
