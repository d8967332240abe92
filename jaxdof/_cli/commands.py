"""The commands `demo`, `render` and `fit`: read and check the files, call the library, report.

The CLI checks what only it can know: the files (paths, shapes, an output over an input), the
figure path, and combinations of its options. Everything about the values (a focus beyond the
focal length, depths beyond it, solver settings) is checked by `jaxdof.ThinLens`, `jaxdof.render`
and `jaxdof.fit_lens`, whose `ValueError` becomes the same one-line error (`library_checks`).
Each command returns the exit status.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from typing import Any

import numpy as np

import jaxdof

from .._io import InputError, check_output, read_depth, read_image, write_image
from .._render import _check_downsample
from . import plot, report
from .demo import demo_scene
from .report import note


@contextlib.contextmanager
def library_checks():
    """The library's own input checks (`ValueError`, house style) as the CLI's one-line error."""
    try:
        yield
    except ValueError as err:
        raise InputError(" ".join(str(err).split())) from None


def _read_inputs(args) -> tuple:
    img = read_image(args.image, linear=args.linear, option="IMAGE")
    for n in img.notes:
        note(n)
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
        raise InputError(
            f"{args.depth}: depth is {depth.shape[0]}x{depth.shape[1]} (HxW) but image "
            f"{args.image} is {img.array.shape[0]}x{img.array.shape[1]}; they must match"
        )
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


def _lens(args, focus: float, width: int):
    with library_checks():  # e.g. a focus distance not beyond the focal length
        return jaxdof.ThinLens.from_sensor(
            args.focal_length,
            args.f_number,
            focus,
            sensor_width=args.sensor_width,
            image_width=width,
        )


# ----------------------------------------------------------------------------------------------
# render


def run_render(args) -> int:
    inputs = [args.image, args.depth]
    img, depth = _read_inputs(args)
    check_output(args.out, inputs)
    lens = _lens(args, args.focus, _photo_width(args, img.array.shape))
    t0 = time.perf_counter()
    with library_checks():  # e.g. depths not beyond the focal length
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


def _read_targets(args, image_shape, photo_width: int) -> list[np.ndarray]:
    s = args.downsample
    photo = (image_shape[0] // s, photo_width, *image_shape[2:])
    targets = []
    for path in args.targets:
        t = read_image(path, linear=args.linear, option="TARGET")
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

    @property
    def positional(self) -> tuple:
        targets = self.targets[0] if len(self.targets) == 1 else np.stack(self.targets)
        return (self.image, self.depth, targets, self.init)


def _fit_inputs(args) -> list[str]:
    """`fit`'s input files, which no output may overwrite."""
    return [args.image, args.depth, *args.targets, *([args.weight] if args.weight else [])]


def fit_call(args) -> FitCall:
    """Read and check `fit`'s files and options into the arguments of `jaxdof.fit_lens` (no
    solve: what the library checks of the values, it checks when called)."""
    img, depth = _read_inputs(args)
    width = _photo_width(args, img.array.shape)
    targets = _read_targets(args, img.array.shape, width)
    weight = None if args.weight is None else _read_weight(args.weight, targets[0].shape)
    _check_free(args.free, args.shared, len(targets))
    plot.check_plot(args.plot, _fit_inputs(args), "--plot")
    focus = args.focus if args.focus is not None else float(np.median(depth))
    init = _lens(args, focus, width)
    model = dict(method=args.method, footprint=args.footprint, downsample=args.downsample)
    kwargs = dict(
        free=tuple(args.free),
        shared=tuple(args.shared),
        max_steps=args.max_steps,
        max_radius=args.max_radius,
        weight=weight,
        border=args.border,
        verbose=False if args.quiet else report.Progress(),
        **model,
    )
    return FitCall(img.array, depth, targets, init, kwargs, model)


def run_fit(args) -> int:
    call = fit_call(args)
    with library_checks():  # e.g. --shared not within --free, or the data cannot decide the lens
        result = jaxdof.fit_lens(*call.positional, **call.kwargs)
    summary = report.fit_summary(result)
    pixels = len(call.targets) * int(np.prod(call.targets[0].shape[:2]))
    report.print_fit(summary, args.targets, args.free, as_json=args.json, pixels=pixels)
    if args.plot:
        plot.plot_fit(
            args.plot,
            call.image,
            call.depth,
            call.targets,
            result,
            args.targets,
            _fit_inputs(args),
            render_options=call.model,
        )
        note(f"wrote {args.plot}")
    return 0 if summary["success"] else 1


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
    # Sensor noise (seeded): without it the fit is exact and every standard error is 0.
    noise = np.random.default_rng(1).normal(0.0, 0.005, size=image.shape).astype(np.float32)
    target = np.asarray(jaxdof.render(image, depth, truth)) + noise
    print(
        f"scene {h}x{w}, depths {depth.min():.2g}-{depth.max():.2g} m; truth 85mm f/1.4 focused at "
        f"3 m (blur scale {float(truth.blur_scale):.2f} px) + noise sigma 0.005; start f/4 at 5 m"
    )
    result = jaxdof.fit_lens(
        image, depth, target, start, free=("focus_distance", "f_number"), verbose=report.Progress()
    )
    report.print_demo(truth, start, result)
    if path:
        refit = np.asarray(jaxdof.render(image, depth, result.lens))
        radius = np.asarray(jaxdof.coc_radius(depth, truth))
        plot.plot_demo(path, image, target, refit, radius)
        print(f"wrote {path}")
    print(f"total {time.perf_counter() - t0:.1f} s")
    return 0 if result.success else 1
