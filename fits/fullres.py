"""Calibrating from full-resolution photos: wall time, peak memory and accuracy of `jaxdof fit`
against the tile budget, beside the whole-frame fit (issue 22, item 5).

Question: how long does the command a user runs (`jaxdof fit sharp.png depth.npy photo.png
--focal-length 50mm --f-number 5.6 --focus 2m --json`) take on 1.5, 6 and 24 MP photos, how
much memory does it hold, and what does fitting on informative tiles (`--tiles N`, default
`auto`) cost in accuracy against the whole frame (`--tiles off`)?

Scene (procedural, `scene`): a textured ground plane receding from 1.2 m (bottom edge) to a
wall at 12 m, two boxes standing on it at 1.8 m and 5 m; texture at 1 to 64 px scales, so every
resolution has detail to blur. Lens: 50 mm on a 36 mm-wide sensor focused at 3 m; the f-number
puts the largest circle near 9.5 px at 1.5 and 6 MP (f/2.8, f/5.6) and 13 px at 24 MP (f/8).
Photo: `jaxdof.render` (soft, the default), plus Gaussian noise of 0.003 (linear), stored as
16-bit sRGB PNG like the all-in-focus image; depth as float32 `.npy`. Start: f/5.6 at 2 m
(f/4 at 2 m for the f/5.6 truth).

Every fit is a fresh process (`python -m jaxdof fit ...`, reading and compiling included), timed
by wall clock, its peak resident memory from `wait4`. Errors are relative to the truth; `z` is
the error in reported standard errors.

Run:

    python fits/fullres.py              # 1.5 MP budgets and whole frame, 6 MP, 24 MP
    python fits/fullres.py --quick      # 1.5 MP only: default, two budgets, whole frame
    python fits/fullres.py --sizes 24   # only the 24 MP default
    python fits/fullres.py --report-only   # the table and plot again from the raw file

Scenes are cached in `fits/.cache/fullres/` (24 MP: 290 MB of files). Writes
`fits/results/fullres{tag}.md`, `_raw.json` and `.png`.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
from _common import (
    CACHE,
    RESULTS,
    command,
    git_state,
    load_average,
    load_json,
    machine_info,
    save_json,
)


# size label -> (height, width, true f-number, start f-number)
SIZES = {
    "1.5": (1000, 1500, 2.8, 5.6),
    "6": (2000, 3000, 5.6, 4.0),
    "24": (4000, 6000, 8.0, 5.6),
}
FOCAL, FOCUS, START_FOCUS, SENSOR, NOISE = 0.05, 3.0, 2.0, 0.036, 0.003
# the tile budgets of the 1.5 MP sweep (interior pixels), about 0.06 to 0.5 MP (a 1 MP budget
# leaves too few candidate tiles in 1.5 MP: the whole frame), and 1 MP at 6 MP
BUDGETS = [1 << 16, 1 << 17, 1 << 18, 1 << 19]
BUDGETS_6MP = [1 << 20]


def scene(h: int, w: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """`(image (h, w, 3) linear, depth (h, w) m)`: the module docstring's scene."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    inv = 1 / 12 + (1 / 1.2 - 1 / 12) * np.clip((yy - 0.3 * h) / (0.7 * h - 1), 0, 1)
    depth = (1 / inv).astype(np.float32)
    tex = np.zeros((h, w), np.float32)
    for s in (1, 4, 16, 64):  # value noise at four scales
        n = rng.uniform(size=(h // s + 2, w // s + 2)).astype(np.float32)
        tex += 0.25 * np.repeat(np.repeat(n, s, 0), s, 1)[:h, :w]
    s = max(6, w // 250)
    checker = ((yy // s + xx // s) % 2).astype(np.float32)
    base = 0.1 + 0.45 * checker + 0.36 * tex
    image = base[..., None] * np.stack(
        [np.ones_like(xx), 0.6 + 0.4 * xx / w, 0.5 + 0.5 * yy / h], -1
    )
    boxes = [
        ((0.25, 0.85), (0.10, 0.35), 1.8, (0.9, 0.3, 0.2)),
        ((0.15, 0.55), (0.55, 0.85), 5.0, (0.2, 0.4, 0.9)),
    ]
    for (r0, r1), (c0, c1), d, colour in boxes:
        rows, cols = slice(int(r0 * h), int(r1 * h)), slice(int(c0 * w), int(c1 * w))
        depth[rows, cols] = d
        image[rows, cols] = (0.3 + 0.7 * tex[rows, cols, None]) * np.asarray(colour, np.float32)
    return np.clip(image, 0, 1).astype(np.float32), depth


def make_scene(label: str) -> dict:
    """The scene's files (made once, cached) and its true lens."""
    import jax

    import jaxdof
    from jaxdof.internal import write_image

    h, w, n_true, n_start = SIZES[label]
    # The photo integrates over its pixels as a sensor does (`footprint=True`, which the default
    # fit models for circles of a few pixels); `_fp`: not the earlier caches' render without it.
    folder = CACHE / "fullres" / f"{h}x{w}_fp"
    files = {
        k: str(folder / f)
        for k, f in [("sharp", "sharp.png"), ("depth", "depth.npy"), ("photo", "photo.png")]
    }
    lens = jaxdof.ThinLens.from_sensor(FOCAL, n_true, FOCUS, sensor_width=SENSOR, image_width=w)
    k_px = FOCAL**2 / (2 * n_true * (FOCUS - FOCAL)) / (SENSOR / w)
    truth = dict(f_number=n_true, focus_distance=FOCUS, K_px=k_px, start_f_number=n_start)
    if all(os.path.exists(f) for f in files.values()):
        return dict(files=files, truth=truth, shape=(h, w))
    folder.mkdir(parents=True, exist_ok=True)
    image, depth = scene(h, w)
    band_rows = None if h * w <= 4_000_000 else 1000  # 24 MP in bands (under 4 GB)
    photo = jaxdof.render(image, depth, lens, footprint=True, band_rows=band_rows)
    photo = np.asarray(jax.device_get(photo))
    photo = photo + np.random.default_rng(1).normal(0, NOISE, photo.shape).astype(np.float32)
    np.save(files["depth"], depth, allow_pickle=False)
    write_image(files["sharp"], image, bits=16)
    write_image(files["photo"], photo, bits=16)
    return dict(files=files, truth=truth, shape=(h, w))


def make_scenes_apart(sizes) -> None:
    """Make the missing scenes in a process of their own: a timed `jaxdof fit` forked from a
    parent that rendered 24 MP would report the parent's resident set as its own peak
    (`ru_maxrss` is kept across exec)."""
    argv = [sys.executable, os.path.abspath(__file__), "--make-scenes", "--sizes", *sizes]
    subprocess.run(argv, check=True)


def run_fit(sc: dict, tiles: str) -> dict:
    """One `jaxdof fit` in a fresh process: wall time, peak memory, the JSON result."""
    f, t = sc["files"], sc["truth"]
    argv = [
        sys.executable,
        "-m",
        "jaxdof",
        "fit",
        f["sharp"],
        f["depth"],
        f["photo"],
        "--json",
        "--quiet",
    ]
    argv += ["--focal-length", "50mm", "--f-number", str(t["start_f_number"]), "--focus", "2m"]
    argv += ["--tiles", tiles]
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        t0 = time.perf_counter()
        proc = subprocess.Popen(argv, stdout=out, stderr=err, text=True)
        # wait4, not wait: the child's own peak resident set size (kB on Linux)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = rc = os.waitstatus_to_exitcode(status)
        out.seek(0), err.seek(0)
        stdout, stderr = out.read(), err.read()
    row = dict(tiles=tiles, wall_s=wall, rc=rc, peak_gb=usage.ru_maxrss / 2**20)  # kB -> GiB
    if rc not in (0, 1):
        row["error"] = stderr.strip().splitlines()[-1:] or ["?"]
        return row
    res = json.loads(stdout)
    k_fit = FOCAL**2 / (2 * res["f_number"] * (res["focus_distance"] - FOCAL)) / res["pixel_pitch"]
    se = res["stderr"]
    row.update(
        success=res["success"],
        status=res["status"],
        f_number=res["f_number"],
        focus_distance=res["focus_distance"],
        err_N=res["f_number"] / t["f_number"] - 1,
        err_d=res["focus_distance"] / t["focus_distance"] - 1,
        err_K=k_fit / t["K_px"] - 1,
        se_N=se["f_number"] / t["f_number"],
        se_d=se["focus_distance"] / t["focus_distance"],
        pixels=res["pixels_used"],
        n_tiles=len(res.get("tiles") or []),
        steps=res["steps"],
    )
    return row


def _fmt(x, spec):
    return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, spec)


def report(rows: list[dict], info: dict, argv_line: str, path) -> None:
    lines = [
        "# Full-resolution fits: time, memory and accuracy against the tile budget",
        "",
        f"Command: `{argv_line}` ({git_state()}). Every row is one fresh `jaxdof fit` process "
        "(reading, compiling and fitting; wall clock, peak RSS from `wait4`).",
        "",
        "| | |",
        "|---|---|",
        *[f"| {k} | {v} |" for k, v in info.items()],
        "",
        "Errors relative to the truth (%); `se` the reported standard error (%); K the blur scale.",
        "",
        "| photo | tiles | pixels fitted | wall s | peak GiB | status | N err % | d_f err % | K err % | se N % | se d_f % | steps |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "error" in r:
            lines.append(
                f"| {r['size']} MP | {r['tiles']} | | {r['wall_s']:.1f} | {_fmt(r['peak_gb'], '.2f')} | error: {r['error'][0]} | | | | | | |"
            )
            continue
        lines.append(
            f"| {r['size']} MP | {r['tiles']} | {r['pixels']:,} ({r['n_tiles']} tiles) | {r['wall_s']:.1f} | "
            f"{_fmt(r['peak_gb'], '.2f')} | {r['status']} | {100 * r['err_N']:+.4f} | {100 * r['err_d']:+.4f} | "
            f"{100 * r['err_K']:+.4f} | {100 * r['se_N']:.4f} | {100 * r['se_d']:.4f} | {r['steps']} |"
        )
    lines += ["", *_against_whole_frame(rows)]
    path.write_text("\n".join(lines) + "\n")


def _against_whole_frame(rows: list[dict]) -> list[str]:
    """Each size's default fit against its whole-frame fit: the standard errors' ratio and the
    difference of the answers in the default fit's own standard errors (issue 22's goals)."""
    out = []
    ok = [r for r in rows if "error" not in r]
    for size in SIZES:
        auto = [r for r in ok if r["size"] == size and r["tiles"] == "auto"]
        whole = [r for r in ok if r["size"] == size and r["tiles"] == "off"]
        if not auto or not whole:
            continue
        a, w = auto[0], whole[0]
        ratio = [a[k] / w[k] for k in ("se_N", "se_d")]
        diff = [abs(a[k] - w[k]) / a[s] for k, s in (("err_N", "se_N"), ("err_d", "se_d"))]
        out.append(
            f"- {size} MP, default against the whole frame: standard errors {ratio[0]:.2f}x (N) and "
            f"{ratio[1]:.2f}x (d_f); answers {diff[0]:.2f} and {diff[1]:.2f} of the default's "
            f"standard errors apart; wall time {a['wall_s']:.1f} s against {w['wall_s']:.1f} s."
        )
    return out


def plot(rows: list[dict], path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sub = [r for r in rows if r["size"] == "1.5" and "error" not in r]
    if not sub:
        return
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for r in sub:
        x = r["pixels"] / 1e6
        axes[0].plot(x, r["wall_s"], "o", color="C0" if r["tiles"] != "off" else "C3")
        axes[1].errorbar(
            x,
            100 * r["err_d"],
            yerr=100 * r["se_d"],
            fmt="o",
            color="C0" if r["tiles"] != "off" else "C3",
        )
    axes[0].set(
        xscale="log",
        xlabel="pixels fitted (MP)",
        ylabel="wall s (fresh process)",
        title="1.5 MP photo: time",
    )
    axes[1].set(
        xscale="log",
        xlabel="pixels fitted (MP)",
        ylabel="focus distance error % (+- 1 se)",
        title="accuracy (red: whole frame)",
    )
    axes[1].axhline(0, color="k", lw=0.5)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick", action="store_true", help="1.5 MP only: default, two budgets, whole frame"
    )
    parser.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    parser.add_argument(
        "--defaults-only", action="store_true", help="only the default fit (tiles=auto) per size"
    )
    parser.add_argument("--tag", default="")
    parser.add_argument("--make-scenes", action="store_true", help="only make the missing scenes")
    parser.add_argument(
        "--report-only", action="store_true", help="rewrite the table and plot from the raw file"
    )
    args = parser.parse_args(argv)
    base = RESULTS / f"fullres{args.tag}"
    if args.report_only:
        raw = load_json(base.with_name(base.name + "_raw.json"))
        report(
            raw["rows"],
            raw["info"],
            raw.get("command", command("fullres.py", argv)),
            base.with_suffix(".md"),
        )
        plot(raw["rows"], base.with_suffix(".png"))
        return
    info = machine_info()
    info["load average at start"] = load_average()
    sizes = ["1.5"] if args.quick else args.sizes
    budgets = [1 << 16, 1 << 18] if args.quick else BUDGETS
    plan = [(size, "auto") for size in sizes]
    if not args.defaults_only:
        plan += [("1.5", str(b)) for b in budgets if "1.5" in sizes]
        plan += [("6", str(b)) for b in BUDGETS_6MP if "6" in sizes and not args.quick]
        # the whole-frame fits last: the longest (6 MP: many minutes on 2 cores)
        plan += [(size, "off") for size in sizes if size != "24"]
    if args.make_scenes:
        for size in sizes:
            make_scene(size)
        return
    make_scenes_apart(sorted({size for size, _ in plan}))
    rows = []
    for size, tiles in plan:
        sc = make_scene(size)
        row = dict(size=size, **run_fit(sc, tiles))
        print(json.dumps(row), flush=True)
        rows.append(row)
        # written after every fit: a long whole-frame fit cut short keeps the rows before it
        raw = dict(rows=rows, info=info, command=command("fullres.py", argv))
        save_json(base.with_name(base.name + "_raw.json"), raw)
        report(rows, info, command("fullres.py", argv), base.with_suffix(".md"))
    plot(rows, base.with_suffix(".png"))


if __name__ == "__main__":
    main()
