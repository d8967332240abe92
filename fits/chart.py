"""Calibration from one photo of a printed chart (issue 35), against an independent ray tracer.

Question: given one photo of the chart that `jaxdof.make_chart` draws, printed and lit
unevenly or shown on a monitor, tilted 25-60 degrees at 0.5-3 m, does
`jaxdof.calibrate(photo, chart, image, focal_length=f)` with the default options come back
within 2 % in focus distance and 5 % in blur scale K (`ThinLens.blur_scale`), and when it does
not, does it say so (`success=False`, or an exception) or miss silently (`success=True` and an
error beyond 3 reported standard errors)? Reported per half: the tuning cases and the held-out
ones (`HELD_OUT` in `_chart_scenes.py`, chosen before any fit). And does `jaxdof calibrate`
refuse a photo without the chart (exit status 2) in under 10 s?

Method: eight Mitsuba 3 thin-lens photos, 640x480 (`_chart_scenes.CASES`), each fitted twice:
the linear float32 photo and its 8-bit camera JPEG (sRGB, quality 90, 4:2:0, decoded to linear).
The focal length is the truth's, as EXIF would give it (a 36 mm wide sensor); nothing else is
passed. The truth lens is `lens_from_raytracer` of the case's aperture, focus and field of view.

Run (Mitsuba only to render what is not cached yet; about 12 s per photo):

    python fits/chart.py                      # every case, both inputs
    python fits/chart.py --cases print_front  # a subset (tag _partial)
    python fits/chart.py --inputs jpeg        # the JPEGs only (tag _partial)
    python fits/chart.py --render-only        # make the photos, fit nothing

Renders are cached in `fits/.cache/chart/`, fits in `fits/.cache/chart/fits/<fingerprint>/`
(a hash of the imported jaxdof's source and `_chart_scenes.py`: after a library change every fit
runs again). Writes `fits/results/chart.md` and `chart_raw.json`. Precision: float32, as a new
user calls it.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import shlex
import subprocess
import sys
import time
import traceback

import jax


jax.config.update("jax_enable_x64", True)  # as the modules below; main() sets the run's precision

import numpy as np  # noqa: E402
from _captures_scenes import verdict  # noqa: E402  (the capture study's verdicts)
from _chart_scenes import (  # noqa: E402
    CACHE,
    CASES,
    HELD_OUT,
    NO_CHART,
    SPP,
    TUNING,
    H,
    W,
    case_photo,
    chart_corners_px,
    coc_range,
    depth_check,
    f_px,
    focal_length,
    no_chart_photo,
    pinhole_photo,
    raster_hash,
)
from _common import FITS, cached_json, git_state, result_path, save_json, write_markdown  # noqa: E402
from _raytraced_fits import fingerprint, no_paths  # noqa: E402
from _raytraced_report import default_conditions  # noqa: E402
from raytraced_default import finite  # noqa: E402

import jaxdof  # noqa: E402
from jaxdof.internal import release_compiled_code  # noqa: E402


FOCUS_TOL = 0.02  # |d_f / d_f,true - 1|
K_TOL = 0.05  # |K / K_true - 1|
SIGMAS = 3.0  # an error beyond this many reported standard errors is a silent miss
INPUTS = ("jpeg", "linear", "cli")
# Where the chart is not found in a JPEG, the same JPEG again with the markers found in a sharp
# photo of the same pose (a pinhole render: as a photo stopped down from the tripod would give
# them), passed as `views`: the fit, apart from the detection.
GIVEN = "jpeg_markers"
INPUT_WORDS = {
    "jpeg": "jpeg",
    "linear": "linear",
    "cli": "jpeg file, `jaxdof calibrate`",
    GIVEN: "jpeg, markers from a sharp photo",
}
VERDICTS = ("within", "flagged", "silent", "raised", "covered")
CLI_LIMIT_S = 10.0


def chart_fingerprint() -> str:
    """12 hex digits of the library's source (`fingerprint`) and `_chart_scenes.py`."""
    h = hashlib.sha256(fingerprint().encode())
    h.update((FITS / "_chart_scenes.py").read_bytes())
    return h.hexdigest()[:12]


def _first(x) -> float:
    return float(np.asarray(x, np.float64).reshape(-1)[0])


def k_stderr(res, lens) -> float:
    """The standard error of `K = f^2 / (2 N (d_f - f) p)` by the delta method over the fitted
    fields' covariance (`res.names`, in their own units): `K sqrt(g' C g)`, `g` the gradient of
    `ln K` in the fields that were free."""
    f, n, d, p = (
        float(getattr(lens, k))
        for k in ("focal_length", "f_number", "focus_distance", "pixel_pitch")
    )
    grad = {
        "focal_length": 2 / f + 1 / (d - f),
        "f_number": -1 / n,
        "focus_distance": -1 / (d - f),
        "pixel_pitch": -1 / p,
    }
    names = list(res.names)
    g = np.array([grad.get(k, 0.0) for k in names])
    cov = np.asarray(res.covariance, np.float64)
    if cov.shape != (len(names), len(names)):
        return math.nan
    return float(lens.blur_scale) * math.sqrt(max(float(g @ cov @ g), 0.0))


def _status(res) -> str:
    try:
        return str(res.to_dict()["status"])
    except Exception as err:  # a result the report cannot read is itself a finding
        return f"unreadable ({type(err).__name__})"


def fit_of(cal):
    """The calibration's `FitResult` (`result`, or `fit`)."""
    res = getattr(cal, "result", None)
    return cal.fit if res is None else res


def pose_error(cal, data) -> dict:
    """The calibration's pose of the (first) photo against the truth: the angle of the rotation
    between them (degrees) and the translation's error as a share of the true distance; the
    focal length in pixels against the truth's; empty where the calibration reports no pose."""
    try:
        pose = cal.poses[0]
        r, t = np.asarray(pose.rotation, np.float64), np.asarray(pose.translation, np.float64)
        r_true, t_true = data.pose
        cos = (np.trace(r.T @ r_true) - 1) / 2
        w, h = data.case.size
        outline = np.array([[0, 0, 0], [w, 0, 0], [w, h, 0], [0, h, 0]], float) @ r.T + t
        seen = outline @ np.asarray(cal.camera, np.float64).T
        truth = chart_corners_px(data.case) - 0.5  # the library's pixel centres are integers
        return dict(
            outline_px=float(np.abs(seen[:, :2] / seen[:, 2:] - truth).max()),
            pose_deg=math.degrees(math.acos(min(1.0, max(-1.0, cos)))),
            pose_t=float(np.linalg.norm(t - t_true) / np.linalg.norm(t_true)),
            focal_px=float(cal.focal_px),
            focal_px_err=float(cal.focal_px) / f_px(data.case) - 1,
            intrinsics=str(getattr(cal, "intrinsics", "")),
            markers=int(cal.views[0].markers),
            aligned_px=[float(m) for m in getattr(cal, "aligned_px", ())],
        )
    except Exception as err:  # a calibration without a readable pose is itself a finding
        return dict(pose_unreadable=f"{type(err).__name__}: {err}"[:200])


def record(cal, data) -> dict:
    """A calibration against its case's truth: errors, standard errors, verdict."""
    res = fit_of(cal)
    lens, truth = res.lens, data.lens
    d, d_true = float(lens.focus_distance), float(truth.focus_distance)
    k, k_true = float(lens.blur_scale), float(truth.blur_scale)
    u, u_true = _first(res.focus_power), 1 / d_true
    se_u, se_k = _first(res.focus_power_stderr), k_stderr(res, lens)
    focus_err, k_err = d / d_true - 1, k / k_true - 1
    focus_z = abs(u - u_true) / se_u if se_u > 0 else math.inf
    k_z = abs(k - k_true) / se_k if se_k > 0 else math.inf
    within = abs(focus_err) < FOCUS_TOL and abs(k_err) < K_TOL
    success = bool(res.success)
    inside = max(focus_z, k_z) <= SIGMAS
    return dict(
        success=success,
        status=_status(res),
        message=no_paths(res.message)[:600],
        lens={
            k: float(getattr(lens, k))
            for k in ("focal_length", "f_number", "focus_distance", "pixel_pitch")
        },
        focus_distance=d,
        focus_err=focus_err,
        k=k,
        k_true=k_true,
        k_err=k_err,
        focus_power_se=se_u,
        k_se=se_k,
        focus_z=focus_z,
        k_z=k_z,
        inside=inside,
        within=within,
        silent=success and not within and not inside,
        stderr_kind=str(res.stderr_kind),
        pixels_used=int(res.pixels_used),
        **pose_error(cal, data),
    )


def calibrate_case(data, which: str) -> dict:
    """`jaxdof.calibrate(photo, chart, image, focal_length=f)`, default options, on the case's
    JPEG or linear photo (float32); an exception is caught and recorded. `cli`: the command
    line on the JPEG file instead (`cli_case`)."""
    if which == "cli":
        return cli_case(data)
    photo = data.photo if which == "linear" else data.jpeg
    photo = np.asarray(photo, np.float32)
    head = dict(case=data.case.name, input=which)
    views = None
    if which == GIVEN:
        views = [jaxdof.detect_chart(pinhole_photo(data.case), data.chart)]
        head["markers_given"] = views[0].markers
    release_compiled_code()  # a long study would reach the kernel's limit of memory maps
    t0 = time.perf_counter()
    try:
        cal = jaxdof.calibrate(
            photo, data.chart, data.image, focal_length=focal_length(data.case), views=views
        )
        jax.block_until_ready(fit_of(cal).lenses.focus_distance)
    except Exception as err:
        first = (str(err).splitlines() or [""])[0][:300]
        return dict(
            **head,
            seconds=time.perf_counter() - t0,
            exception=no_paths(f"{type(err).__name__}: {first}"),
            traceback=[no_paths(line) for line in traceback.format_exc().splitlines()][-25:],
        )
    return dict(**head, seconds=time.perf_counter() - t0, **record(cal, data))


def _sidecar(chart, image):
    """The chart's sidecar file (written once, beside the renders)."""
    stem = CACHE / "cli" / f"chart_{raster_hash(image)}"
    stem.parent.mkdir(parents=True, exist_ok=True)
    if not stem.with_suffix(".json").exists():
        jaxdof.write_chart(stem, chart, image)
    return stem.with_suffix(".json")


class _FromJson:
    """A `FitResult`'s parts that `record` reads, from `jaxdof calibrate --json`'s output."""

    def __init__(self, out: dict):
        first = out["lenses"][0]
        self.lens = jaxdof.ThinLens(
            *(first[k] for k in ("focal_length", "f_number", "focus_distance", "pixel_pitch"))
        )
        self.focus_power = first["focus_power"]
        self.focus_power_stderr = first["focus_power_stderr"] or math.nan
        self.names = out["names"]
        self.covariance = np.array(
            [[math.nan if x is None else x for x in row] for row in out["covariance"]]
        )
        self.success, self.message = out["success"], out["message"]
        self.stderr_kind, self.pixels_used = out["stderr_kind"], out["pixels_used"]
        self._out = out

    def to_dict(self):
        return self._out


def cli_case(data) -> dict:
    """`jaxdof calibrate JPEG --chart SIDECAR --focal-length F --json` as a user runs it on the
    case's camera JPEG file (which reads its chroma subsampling from the file: luma), scored as
    the library's calls are; the pose is not compared (`pose_error` needs the library's
    objects)."""
    head = dict(case=data.case.name, input="cli")
    cmd = [sys.executable, "-m", "jaxdof", "calibrate", str(data.jpeg_path), "--json", "--quiet"]
    cmd += ["--chart", str(_sidecar(data.chart, data.image))]
    cmd += ["--focal-length", f"{focal_length(data.case) * 1000:.4f}mm"]
    t0 = time.perf_counter()
    out = subprocess.run(
        cmd, capture_output=True, text=True, env={**os.environ, "JAX_PLATFORMS": "cpu"}
    )
    secs = time.perf_counter() - t0
    if out.returncode not in (0, 1):
        last = (out.stderr.strip().splitlines() or [""])[-1]
        return dict(**head, seconds=secs, exception=no_paths(f"exit {out.returncode}: {last}"))
    summary = json.loads(out.stdout)

    class Cal:  # what `record` reads of a calibration
        fit = _FromJson(summary)

    return dict(**head, seconds=secs, exit=out.returncode, **record(Cal, data))


def cli_no_chart(chart, image) -> dict:
    """`jaxdof calibrate` on the photo without the chart: exit status and wall time (the
    subprocess's, interpreter start included). Skipped when the CLI has no `calibrate`."""
    photo, path = no_chart_photo()
    help_text = subprocess.run(
        [sys.executable, "-m", "jaxdof", "--help"], capture_output=True, text=True
    ).stdout
    if "calibrate" not in help_text.split("positional arguments")[-1].split("options")[0]:
        return dict(skipped="the CLI has no `calibrate` command")
    cmd = [sys.executable, "-m", "jaxdof", "calibrate", str(path)]
    cmd += ["--chart", str(_sidecar(chart, image))]
    cmd += ["--focal-length", f"{focal_length(NO_CHART) * 1000:.1f}mm"]
    t0 = time.perf_counter()
    out = subprocess.run(
        cmd, capture_output=True, text=True, env={**os.environ, "JAX_PLATFORMS": "cpu"}
    )
    secs = time.perf_counter() - t0
    shown = ["jaxdof", "calibrate", path.name, "--chart", "chart.json", *cmd[7:]]
    return dict(
        command=shlex.join(shown),
        exit=out.returncode,
        seconds=secs,
        stderr=no_paths(out.stderr.strip())[-800:],
        stdout=no_paths(out.stdout.strip())[-400:],
    )


def markers_found(photo, chart) -> int:
    """How many of the chart's markers `jaxdof.detect_chart` finds in `photo` (0 if none)."""
    try:
        return jaxdof.detect_chart(np.asarray(photo, np.float32), chart, min_markers=1).markers
    except jaxdof.ChartError:
        return 0


def marker_sides(data) -> np.ndarray:
    """Every marker's mean side in the photo (px), from the true pose."""
    r, t = data.pose
    fp = f_px(data.case)
    sides = []
    for m in data.chart.markers.values():
        p = np.column_stack([m, np.zeros(4)]) @ r.T + t
        q = fp * p[:, :2] / p[:, 2:]
        sides.append(np.mean(np.linalg.norm(q - np.roll(q, 1, axis=0), axis=1)))
    return np.array(sides)


def diagnose(data) -> dict:
    """What the library sees of a case, at the truth: markers found by `detect_chart` in the
    JPEG, the linear photo and a pinhole render of the same pose (every depth sharp); the
    markers' sides (px) and their largest circle of confusion over side; and
    `jaxdof.chart_scene` at the true pose and focal length in pixels against Mitsuba: its
    z-depth against the depth AOV's (largest relative difference where both see the chart),
    and its sharp image against the pinhole render (correlation on the chart 2 px inside its
    outline; the sub-pixel shift, in quarter pixels up to 1 px, that maximises it; for a
    monitor, where no light varies, the spread of pinhole / sharp)."""
    from scipy.ndimage import binary_erosion, shift

    case = data.case
    pin = pinhole_photo(case)
    sides = marker_sides(data)
    out = dict(
        found_jpeg=markers_found(data.jpeg, data.chart),
        found_linear=markers_found(data.photo, data.chart),
        found_pinhole=markers_found(pin, data.chart),
        markers=len(data.chart.markers),
        side_px=(float(sides.min()), float(sides.max())),
    )
    # the largest circle over the side, marker by marker (circle at the marker's centre)
    r, t = data.pose
    centres = np.array([m.mean(0) for m in data.chart.markers.values()])
    z = (np.column_stack([centres, np.zeros(len(centres))]) @ r.T + t)[:, 2]
    coc = case.aperture * f_px(case) * np.abs(1 / case.focus - 1 / z)
    out["coc_over_side"] = (float((coc / sides).min()), float((coc / sides).max()))
    fp = f_px(case)
    camera = np.array([[fp, 0, (W - 1) / 2], [0, fp, (H - 1) / 2], [0, 0, 1]])
    sharp, depth = jaxdof.chart_scene(
        data.chart, data.image, jaxdof.ChartPose(r, t), camera, (H, W)
    )
    on = np.isfinite(depth) & np.isfinite(data.z)
    out["scene_z_max_rel"] = float(np.max(np.abs(depth[on] / data.z[on] - 1)))
    inner = binary_erosion(np.isfinite(depth), iterations=2)
    lum = pin.mean(-1)
    best = (-2.0, 0.0, 0.0)
    for dy in np.arange(-1, 1.01, 0.25):
        for dx in np.arange(-1, 1.01, 0.25):
            moved = shift(sharp, (dy, dx), order=1) if dy or dx else sharp
            corr = float(np.corrcoef(lum[inner], moved[inner])[0, 1])
            best = max(best, (corr, float(dy), float(dx)))
    out["scene_corr"], out["scene_shift"] = best[0], best[1:]
    if case.monitor:
        ratio = lum[inner] / sharp[inner]
        out["monitor_ratio_p5_p95"] = tuple(
            float(v / np.median(ratio)) for v in np.percentile(ratio, [5, 95])
        )
    return out


def diagnosis_lines(diags) -> list[str]:
    out = [
        "| case | markers found: jpeg / linear / pinhole (of) | marker side px | circle / side | "
        "chart_scene z vs Mitsuba (max rel) | chart_scene vs pinhole: corr, best shift (rows, "
        "cols) px |",
        "|---|---|---|---|---|---|",
    ]
    for name, g in diags.items():
        mon = g.get("monitor_ratio_p5_p95")
        extra = f"; pinhole/sharp p5-p95 {mon[0]:.3f}-{mon[1]:.3f} of its median" if mon else ""
        out.append(
            f"| {name} | {g['found_jpeg']} / {g['found_linear']} / {g['found_pinhole']} "
            f"({g['markers']}) | {g['side_px'][0]:.0f}-{g['side_px'][1]:.0f} | "
            f"{g['coc_over_side'][0]:.2f}-{g['coc_over_side'][1]:.2f} | "
            f"{g['scene_z_max_rel']:.1e} | {g['scene_corr']:.4f}, "
            f"({g['scene_shift'][0]:+.2f}, {g['scene_shift'][1]:+.2f}){extra} |"
        )
    return out + [""]


# ----------------------------------------------------------------------------- report


def counts(records) -> dict:
    c = {v: 0 for v in VERDICTS}
    for r in records:
        c[verdict(r)] += 1
    c["refused"] = sum(1 for r in records if verdict(r) == "within" and not r["success"])
    return c


def summary_lines(records, halves) -> list[str]:
    out = [
        "| input | half | fits | within | flagged | silent | raised | covered | "
        "median abs focus err | median abs K err |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for which in (*INPUTS, GIVEN):
        rows = [*halves.items(), ("all", [n for names in halves.values() for n in names])]
        for half, names in rows:
            recs = [r for r in records if r["input"] == which and r["case"] in names]
            if not recs:
                continue
            c = counts(recs)
            within = f"{c['within']}" + (f" ({c['refused']} refused)" if c["refused"] else "")
            med = []
            for key in ("focus_err", "k_err"):
                vals = [abs(r[key]) for r in recs if "exception" not in r]
                med.append(f"{np.median(vals):.2%}" if vals else "-")
            label = f"**{half}**" if half == "all" else half
            out.append(
                f"| {INPUT_WORDS[which]} | {label} | {len(recs)} | {within} | "
                + " | ".join(str(c[v]) for v in VERDICTS[1:])
                + f" | {med[0]} | {med[1]} |"
            )
    return out + [""]


def case_lines(datas) -> list[str]:
    out = [
        "| case | half | chart | distance m | turn (y, x) deg | fov deg (f mm) | A mm | N | "
        "d_f m | focus | K px | circle radii on the chart px | chart px | z check (max rel, off px) | "
        "clipped |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for data in datas:
        c, lens = data.case, data.lens
        lo, hi = coc_range(c)
        chk = depth_check(data)
        kind = f"monitor {c.size[0]:.3f}x{c.size[1]:.3f} m" if c.monitor else "printed A4"
        out.append(
            f"| {c.name} | {'held out' if c.name in HELD_OUT else 'tuning'} | {kind} | "
            f"{c.distance} | {c.rot_y:g}, {c.rot_x:g} | {c.fov:g} ({1000 * focal_length(c):.1f}) | "
            f"{1000 * c.aperture:g} | {float(lens.f_number):.2f} | {c.focus} | {c.where} | "
            f"{float(lens.blur_scale):.2f} | {lo:.1f}-{hi:.1f} | {chk['chart_px']} | "
            f"{chk['max_rel_z']:.1e}, {chk['off']} | {data.clipped:.2%} |"
        )
    return out + [""]


def fit_rows(records, names) -> list[str]:
    out = [
        "| case | input | success / status | d_f m | focus err | K px (truth) | K err | "
        "se (focus power 1/m, K px) | abs err / se (focus, K) | inside 3 se | pose: rotation deg, translation, f_px err, outline px, markers | "
        "verdict | s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in records:
        if r["case"] not in names:
            continue
        head = f"| {r['case']} | {INPUT_WORDS[r['input']]} |"
        if "exception" in r:
            out.append(
                head + f" raised: `{r['exception'][:200]}` | | | | | | | | | **raised** | "
                f"{r['seconds']:.0f} |"
            )
            continue
        pose = (
            f"{r['pose_deg']:.2f}, {r['pose_t']:.2%}, {r['focal_px_err']:+.2%}, "
            + (f"{r['outline_px']:.2f}" if "outline_px" in r else "-")
            + f", {r['markers']}"
            if "pose_deg" in r
            else r.get("pose_unreadable", "-")
        )
        out.append(
            head + f" {r['success']} / {r['status']} | {r['focus_distance']:.4g} | "
            f"{r['focus_err']:+.2%} | {r['k']:.3f} ({r['k_true']:.3f}) | {r['k_err']:+.2%} | "
            f"{r['focus_power_se']:.3g}, {r['k_se']:.3g} | {r['focus_z']:.2g}, {r['k_z']:.2g} | "
            f"{'yes' if r['inside'] else 'no'} | {pose} | {verdict(r)} | {r['seconds']:.0f} |"
        )
    return out + [""]


def findings(records) -> list[str]:
    out = []
    for r in records:
        if "exception" not in r and verdict(r) in ("silent", "flagged", "covered"):
            out.append(
                f"- {verdict(r)}: {r['case']} ({r['input']}): focus {r['focus_err']:+.1%}, K "
                f"{r['k_err']:+.1%}, {r['focus_z']:.1f} and {r['k_z']:.1f} reported standard "
                f"errors off, success={r['success']} ({r['status']}): ...{r['message'][-300:]}"
            )
    raised: dict[str, list[str]] = {}
    for r in records:
        if "exception" in r:
            raised.setdefault(r["exception"][:200], []).append(f"{r['case']}/{r['input']}")
    for message, where in raised.items():
        out.append(f"- raised on {len(where)} ({', '.join(where)}): `{message}`")
    return out + [""] if out else []


def cli_lines(cli: dict) -> list[str]:
    if not cli:
        return []
    if "skipped" in cli:
        return ["## The CLI on a photo without the chart", "", f"Not run: {cli['skipped']}.", ""]
    ok = cli["exit"] == 2 and cli["seconds"] < CLI_LIMIT_S
    return [
        "## The CLI on a photo without the chart",
        "",
        f"`{cli['command']}` (the room of `{NO_CHART.name}` without the chart, its JPEG): exit "
        f"status {cli['exit']} in {cli['seconds']:.1f} s wall (interpreter start included); "
        f"goal: exit 2 in under {CLI_LIMIT_S:g} s: **{'met' if ok else 'not met'}**.",
        "",
        "```",
        *(cli["stderr"] or cli["stdout"] or "(no output)").splitlines()[-12:],
        "```",
        "",
    ]


def method_lines() -> list[str]:
    return [
        f"The call: `jaxdof.calibrate(photo, chart, image, focal_length=f)`, default options, "
        f"float32, on {W}x{H} RGB photos rendered by Mitsuba 3's `thinlens` camera ({SPP} spp, "
        "box filter) of the chart of `jaxdof.make_chart` (printed: A4 at 300 dpi as a diffuse "
        "rectangle, its raster the reflectance, lit by a warm point light 0.9 m from it above "
        "and to one side plus a dim constant environment, before a textured wall 0.6 m behind "
        "it; monitor: `make_chart(monitor=True, ...)` as an area emitter of the raster's "
        "radiance in the dark). `f` is the truth's focal length as EXIF gives it (a 36 mm wide "
        "sensor: f = f_px 36 mm / 640). The truth lens is `lens_from_raytracer(A, d_f, fov, "
        "640, f)` (K = A f_px / d_f). Each photo is exposed so that its 99.5th percentile is "
        "0.9 and fitted as **linear** (the float32 render) and **jpeg** (sRGB 8 bit, Pillow "
        "quality 90, 4:2:0, decoded to linear: `_captures_scenes.camera_jpeg`), and its JPEG "
        "file through the command line as a user runs it (**jpeg file, `jaxdof calibrate`**: "
        "`jaxdof calibrate photo.jpg --chart chart.json --focal-length F --json --quiet`, which "
        "reads the 4:2:0 subsampling from the file and compares the photos' luma; its "
        "compilation cache is the user's).",
        "",
        f"Verdicts: **within** focus distance within {FOCUS_TOL:.0%} and K within "
        f"{K_TOL:.0%}; **flagged** outside and success=False; **silent** outside, "
        f"success=True and the focus power or K beyond {SIGMAS:g} reported standard errors; "
        "**raised** an exception escaped `calibrate` (caught here); **covered** outside, "
        f"success=True, both within {SIGMAS:g} standard errors. `refused`: within but "
        "success=False. K's standard error is the delta method over `FitResult.covariance` of "
        "the free fields; the focus power's is `focus_power_stderr`. Wall time per fit "
        "includes compiling.",
        "",
        f"**{INPUT_WORDS[GIVEN]}**: where `calibrate` found no chart in a JPEG, the same JPEG "
        "again with `views=[jaxdof.detect_chart(pinhole)]`, the markers found in a pinhole "
        "render of the same pose (as a stopped-down photo from the tripod would give them): "
        "the fit apart from the detection. Reported as a third input, not counted with the "
        "others.",
        "",
        "The cases' depth was checked against their pose: Mitsuba's depth AOV (one ray through "
        "each pixel centre, `ray_distance_to_z`) against the chart plane of the pose at every "
        "pixel 2 px or more inside the chart's outline ('z check': the largest relative "
        "difference, and the pixels where the two disagree on what is chart).",
        "",
    ]


def main(args) -> None:
    jax.config.update("jax_enable_x64", False)  # float32, as a new user calls it
    t_start = time.perf_counter()
    fp = args.from_cache or chart_fingerprint()
    git = git_state()
    if args.from_cache:
        git = f"the checkout now: {git}; the fits were made earlier, by the library of {fp}"
    if not args.no_compile_cache:
        # As the command line does: the photos share their shape, so their programs are shared
        # (the first fit compiles, the rest load; the seconds reported are a user's with a warm
        # cache after the first).
        jaxdof.enable_compilation_cache(path=CACHE / "xla")
    names = args.cases or [c.name for c in CASES]
    datas = [case_photo(c) for c in CASES if c.name in names]
    render_secs = {d.case.name: d.render_seconds for d in datas}
    no_chart_photo()
    if args.render_only:
        for d in datas:
            print(d.case.name, coc_range(d.case), depth_check(d), f"{d.clipped:.2%}")
        return
    if not hasattr(jaxdof, "calibrate"):
        sys.exit("jaxdof has no calibrate yet: nothing to fit")
    folder = CACHE / "fits" / fp
    records = []
    raised = set()  # the cases whose JPEG calibrate refused: no chart found
    inputs = tuple(args.inputs or INPUTS)
    for which in (*inputs, GIVEN):  # every JPEG first: the study's main input
        for data in datas:
            path = folder / f"{data.case.name}__{which}.json"
            if (args.from_cache and not path.exists()) or (
                which == GIVEN and data.case.name not in raised
            ):
                continue
            rec, computed = cached_json(path, lambda d=data, w=which: calibrate_case(d, w))
            if computed:
                what = rec.get("exception") or (
                    f"{rec['status']}, focus {rec['focus_err']:+.2%}, K {rec['k_err']:+.2%}"
                )
                print(
                    f"  {rec['case']} {which}: {verdict(rec)}: {what[:160]} ({rec['seconds']:.0f} s)",
                    flush=True,
                )
            records.append(rec)
            if which == "jpeg" and rec.get("exception", "").startswith("ChartError"):
                raised.add(data.case.name)
    diags = {d.case.name: diagnose(d) for d in datas}
    cli = {} if args.no_cli else cli_no_chart(datas[0].chart, datas[0].image) if datas else {}
    halves = {
        "tuning": [n for n in TUNING if n in names],
        "held out": [n for n in HELD_OUT if n in names],
    }
    halves = {h: v for h, v in halves.items() if v}
    wall = time.perf_counter() - t_start
    conds = default_conditions(False, render_secs, fp, git, args.note)
    cmd = shlex.join(["python", "fits/chart.py", *sys.argv[1:]])
    lines = [
        "# Calibration from one photo of a chart, against Mitsuba (issue 35)",
        "",
        f"Produced by `{cmd}` (the script's docstring gives the question, the method and how "
        f"to re-run it). This run: {wall:.0f} s wall; calibrating "
        f"{sum(r['seconds'] for r in records):.0f} s in all, as each fit was made (cached fits "
        "are reused).",
        "",
        *conds,
        "",
        *method_lines(),
        "## Cases",
        "",
        f"The held-out half (`HELD_OUT`, chosen before any fit): {', '.join(HELD_OUT)}.",
        "",
        *case_lines(datas),
        "## Summary",
        "",
        *summary_lines(records, halves),
        *findings(records),
        "## What the library sees at the truth",
        "",
        "Per case: the chart's markers `jaxdof.detect_chart` finds in the JPEG, the linear "
        "photo and a pinhole render of the same pose (`calibrate` needs 4); the markers' sides "
        "in the photo and the circle of confusion at each marker's centre over its side; and "
        "`jaxdof.chart_scene` at the true pose and focal length in pixels against Mitsuba "
        "(`diagnose` in `chart.py`).",
        "",
        *diagnosis_lines(diags),
    ]
    for half, hn in halves.items():
        lines += [f"## Fits, {half} half", "", *fit_rows(records, hn)]
    lines += cli_lines(cli)
    partial = args.cases is not None or set(inputs) != set(INPUTS)
    tag = ("_partial" if partial else "") + args.tag
    write_markdown(result_path("chart", tag=tag), lines)
    raw = dict(command=cmd, conditions=conds, records=records, diagnosis=diags, cli=cli)
    save_json(result_path("chart", "_raw.json", tag=tag), finite(raw), indent=1)
    print("\n".join(summary_lines(records, halves)))
    print("\n".join(findings(records)))
    print("\n".join(cli_lines(cli)))
    print(f"wrote {result_path('chart', tag=tag)} ({wall:.0f} s)")


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", choices=[c.name for c in CASES], metavar="CASE")
    ap.add_argument("--render-only", action="store_true", help="render the photos, fit nothing")
    ap.add_argument("--inputs", nargs="+", choices=INPUTS, help="the photos to fit (default: both)")
    ap.add_argument(
        "--from-cache",
        metavar="FINGERPRINT",
        help="report the fits cached under this fingerprint, fitting nothing",
    )
    ap.add_argument("--no-cli", action="store_true", help="skip timing the CLI")
    ap.add_argument(
        "--no-compile-cache",
        action="store_true",
        help="compile every fit's programs (default: a persistent cache beside the renders)",
    )
    ap.add_argument("--tag", default="", help="suffix of the report's names")
    ap.add_argument("--note", default="", help="a line for the report's conditions")
    return ap.parse_args(argv)


if __name__ == "__main__":
    main(parse_args())
