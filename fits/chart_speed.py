"""What a chart calibration costs at camera sizes (issue 35: 24 MP in at most 60 s and 4 GB).

Question: `jaxdof calibrate PHOTO --chart SIDECAR --focal-length 50mm --sensor-width 36mm` on a
chart photo of 0.3 to 24 megapixels: how long does the command take (wall clock, a fresh process,
interpreter start included), with an empty compilation cache (cold) and with the one the cold run
left (warm), how much memory does it hold at its peak (the process's maximum resident set), and
is the lens right?

Scene (the same at every size, scaled with the sensor's pixel count): the A4 chart of
`make_chart(dpi=300, seed=3)` tilted 35 degrees about the vertical and 10 about the horizontal,
its centre 0.6 m from a 50 mm lens on a 36 mm wide sensor (3:2), focused at 0.6 m, f/4 (circles
0 to 3.8 px on the chart at 1.5 MP, 0 to 19 px at 24 MP); behind it a grey backdrop at 3 m whose
circles (15 to 75 px) reach over the chart's edge. Rendered by `jaxdof.render` (not an
independent ray tracer: this is a benchmark, the accuracy studies are `fits/chart.py`), noise of
0.003 added, written as a 16-bit linear PNG (`--linear`). The focal length and the sensor width
are given as EXIF would give them; the f-number, the focus distance and the blur scale are
fitted.

Run (the photos are cached in `fits/.cache/chart_speed/`; rendering the 24 MP one takes minutes):

    python fits/chart_speed.py                       # 1.5 MP and 24 MP, cold and warm
    python fits/chart_speed.py --sizes 0.3 1.5 6 24 --repeats 2

Writes `fits/results/chart_speed.md`.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np
from _common import CACHE, command, git_state, machine_info, result_path, write_markdown


SIZES = {"0.3": (672, 448), "1.5": (1500, 1000), "6": (3000, 2000), "24": (6000, 4000)}
FOCAL, F_NUMBER, FOCUS, SENSOR = 0.05, 4.0, 0.6, 0.036  # m, -, m, m
TILT = (10.0, 35.0)  # degrees about the camera's x and y axes
BACKDROP = (3.0, 0.3)  # its distance (m) and reflectance
NOISE = 0.003
FOLDER = CACHE / "chart_speed"
_STAGE = re.compile(r"^  (.+): (\d+\.\d+) s \((\d+\.\d+) s\)$")


def _rotation(ax: float, ay: float) -> np.ndarray:
    a, b = math.radians(ax), math.radians(ay)
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    return ry @ rx


def truth(label: str):
    import jaxdof

    w, _ = SIZES[label]
    return jaxdof.ThinLens(FOCAL, F_NUMBER, FOCUS, SENSOR / w)


def make_files(label: str) -> dict[str, str]:
    """The chart's files and the photo of size `label` (made where not cached)."""
    import cv2

    import jaxdof
    from jaxdof._chart._geometry import camera_matrix

    FOLDER.mkdir(parents=True, exist_ok=True)
    stem = FOLDER / "chart"
    chart, raster = jaxdof.make_chart(dpi=300, seed=3)
    if not stem.with_suffix(".json").exists():
        jaxdof.write_chart(stem, chart, raster)
    photo = FOLDER / f"photo_{label}mp.png"
    if not photo.exists():
        w, h = SIZES[label]
        lens = truth(label)
        f_px = FOCAL * FOCUS / (FOCUS - FOCAL) / float(lens.pixel_pitch)
        r = _rotation(*TILT)
        centre = np.array([chart.width_m / 2, chart.height_m / 2, 0])
        pose = jaxdof.ChartPose(r, np.array([0, 0, FOCUS]) - r @ centre)
        sharp, depth = jaxdof.chart_scene(chart, raster, pose, camera_matrix(f_px, (h, w)), (h, w))
        on = np.isfinite(depth)
        depth = np.where(on, depth, BACKDROP[0]).astype(np.float32)
        sharp = np.where(on, sharp, BACKDROP[1]).astype(np.float32)
        t0 = time.perf_counter()
        out = np.asarray(jaxdof.render(sharp, depth, lens))
        out = out + np.random.default_rng(0).normal(0, NOISE, out.shape)
        codes = np.clip(np.round(out * 65535), 0, 65535).astype(np.uint16)
        cv2.imwrite(str(photo), codes)
        print(f"rendered {label} MP in {time.perf_counter() - t0:.0f} s", flush=True)
    return {"sidecar": str(stem.with_suffix(".json")), "photo": str(photo)}


def run(files: dict, label: str, cache: str | None) -> dict:
    """One `jaxdof calibrate` in a fresh process: wall time, peak memory, stages, the lens."""
    argv = [sys.executable, "-m", "jaxdof", "calibrate", files["photo"], "--chart"]
    argv += [files["sidecar"], "--focal-length", "50mm", "--sensor-width", "36mm", "--linear"]
    argv += ["--json"] + (["--no-cache"] if cache is None else [])
    env = dict(os.environ)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    if cache is not None:
        env["JAXDOF_CACHE_DIR"] = cache
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(argv, stdout=out, stderr=err, text=True, env=env)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0), err.seek(0)
        stdout, stderr = out.read(), err.read()
    row: dict = dict(wall_s=wall, rc=proc.returncode, peak_gb=usage.ru_maxrss / 2**20, stages={})
    for line in stderr.splitlines():
        m = _STAGE.match(line)
        if m:
            row["stages"][m.group(1)] = row["stages"].get(m.group(1), 0.0) + float(m.group(2))
    if proc.returncode in (0, 1):
        res = json.loads(stdout)
        lens = truth(label)
        n, d = res["f_number"], res["focus_distance"]
        k = FOCAL**2 / (2 * n * (d - FOCAL)) / res["pixel_pitch"]
        row.update(
            success=res["success"],
            err_d=d / FOCUS - 1,
            se_d=(res["stderr"].get("focus_distance") or math.nan) / FOCUS,
            err_k=k / float(lens.blur_scale) - 1,
        )
    else:
        row["error"] = (stderr.strip().splitlines() or ["?"])[-1]
    return row


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="+", default=["1.5", "24"], choices=list(SIZES))
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--render-only", action="store_true", help="only make the missing photos")
    ap.add_argument("--tag", default="", help="suffix of the report's name, e.g. _s32")
    args = ap.parse_args(argv)
    if args.render_only:
        for label in args.sizes:
            make_files(label)
        return
    lines = [
        "# A chart calibration at camera sizes: `jaxdof calibrate` cold and warm",
        "",
        f"Produced by `{command('chart_speed.py', argv)}` (the script's docstring gives the "
        "question and the method). Goal (issue 35): 24 MP in at most 60 s and 4 GB.",
        "",
        *(f"- {k}: {v}" for k, v in machine_info().items()),
        f"- jaxdof source: {git_state()}",
        "",
        "| size | mode | median wall s | runs (s) | peak memory GB | slowest stages (s) | "
        "success | focus error (its stderr) | K error |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    # The photos are made in a process of their own: a timed child forked from a parent that
    # rendered 24 MP in-process reports the parent's resident set as its own peak (`ru_maxrss`
    # is kept across exec: 5.1 GB where the calibration alone holds 2.7 GB).
    subprocess.run([sys.executable, __file__, "--render-only", "--sizes", *args.sizes], check=True)
    for label in args.sizes:
        files = make_files(label)
        rows: dict[str, list[dict]] = {"cold": [], "warm": []}
        for _ in range(args.repeats):
            with tempfile.TemporaryDirectory() as folder:
                rows["cold"].append(run(files, label, folder))
                rows["warm"].append(run(files, label, folder))
            print(label, {k: round(v[-1]["wall_s"], 1) for k, v in rows.items()}, flush=True)
        for mode, rs in rows.items():
            walls = [r["wall_s"] for r in rs]
            last = rs[-1]
            stages = sorted(last["stages"].items(), key=lambda kv: -kv[1])[:3]
            if "err_d" in last:
                tail = (
                    f"{last['success']} | {100 * last['err_d']:+.3f} % "
                    f"({100 * last['se_d']:.3f} %) | "
                    f"{100 * last['err_k']:+.3f} % |"
                )
            else:
                tail = f"exit {last['rc']}: {last.get('error', '?')} | - | - |"
            lines.append(
                f"| {label} MP | {mode} | {statistics.median(walls):.1f} | "
                + ", ".join(f"{w:.1f}" for w in walls)
                + f" | {max(r['peak_gb'] for r in rs):.2f} | "
                + ", ".join(f"{k} {v:.0f}" for k, v in stages)
                + f" | {tail}"
            )
    lines += [
        "",
        "Wall time from the process's start to its exit; peak memory: the process's maximum "
        "resident set (`wait4`). The stages are those the command prints on stderr (the "
        "compiled solves, the statistics, ...); the rest is reading the files, finding the "
        "chart, building its scene and the host's choices.",
    ]
    path = write_markdown(result_path("chart_speed", tag=args.tag), lines)
    print("\n".join(lines))
    print(f"wrote {path}", file=sys.stderr)


if __name__ == "__main__":
    main()
