"""Speed against accuracy for every `coc_filter` method, measured side by side (issue 4).

Question: for each method of the seeds' family and each value of its knob, how far is it from the
analytic soft filter (max abs error, RMSE, PSNR), what does it cost (forward, and forward + gradient,
per megapixel), and how well does it recover a lens when it is the forward model of a fit to targets
rendered by the soft reference? Is every method near the Pareto front, is soft the most accurate at no
more than the cost of supersampling at n = 8, and is `auto` >= 3x faster than soft on a scene of at
most 4 depth levels?

Run:

    python fits/tradeoff.py            # 48 x 48 scenes, max radius 2, 8, 24 (about 10-15 min on 2 cores)
    python fits/tradeoff.py --quick    # 32 x 32, radius 2 and 8, fewer knobs (a few minutes)

Writes `fits/results/tradeoff.md`, `fits/results/tradeoff.png` and the measured rows in
`fits/results/tradeoff_raw.json` (`--quick` adds `_quick`, `--tag T` adds `T`, e.g.
`python fits/tradeoff.py --size 256 --tag _gpu` on a GPU machine);
`python fits/tradeoff.py --rewrite fits/results/tradeoff_raw.json` rewrites the report and plot
from those rows without timing anything.

Method. float32 (x64 off), 3-channel textured images, radii from a thin lens and a depth map:

- `smooth`: a smooth inverse-depth field (every pixel its own radius);
- `steps`: eight vertical bands of depth (eight radius levels, depth edges between them);
- `planes`: a background, an in-focus rectangle and a near disc (three levels, one of them sharp).

The f-number is set per scene so that the largest radius is `R` in {2, 8, 24} px, and the window
is `max_radius=R`. Errors are against `method="soft"` on the same inputs, in units of the image
range (1). Timings: `jax.jit`, one call to compile (reported apart), then the per-call time
(`block_until_ready`) as the median of several samples, each a batch of back-to-back calls lasting
about `SAMPLE_S` (a fit or a batch of renders calls the filter back to back; single sub-millisecond
calls mostly time the runtime waking up), with every row of one radius sampled round by round so
that the shared machine's load shifts all of them alike; divided by the megapixels; forward+grad is `jax.value_and_grad` of a squared
error with respect to the image and the radius map (`auto` with respect to the image only: its radius
map must be concrete, so it is closed over; for the `auto` ratio `soft` is timed both that way and
with the radius map as an argument, as in `render` and `fit_lens`, in the same run, on the study's
frame and on larger frames where per-call overhead matters less, beside an empty call, a jitted
`image + 1`, the floor). Lens fit: the f-number (log coordinate; it sets the blur scale, the focus distance is
known) by optimistix Levenberg-Marquardt through `jaxdof.render(..., method=...)`, from a start 15 %
off, on targets rendered by `soft` with the true lens, at R = 8; the error is its relative error.
Methods with no gradient in the radius (`method.differentiable_in_radius` false) are not fitted,
except `Layered`, whose gradient flows through its level means. The fit is a minimal optimistix LM
over the f-number alone, written before `jaxdof.fit_lens` took a forward model (`model=`), and
kept so that the rows stay comparable. (Fitting the focus distance too from one photo converged
slowly from 15 % off in a first trial, 40 steps, so it was left out.) Each row's method is a
method object (`knob_table`: `jaxdof.Supersample(samples=n)`, `jaxdof.Layered(layers=L)`, ...).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
import timeit
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", False)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402
from _common import (  # noqa: E402
    SAMPLE_S,
    batched_medians_in_turns,
    calls_per_sample,
    command,
    load_average,
    load_json,
    result_path,
    save_json,
    versions_line,
    write_markdown,
)

import jaxdof  # noqa: E402
from jaxdof import ThinLens, choose_method, coc_filter, coc_radius, render  # noqa: E402


KEY = jax.random.key(0)
F, D_F, PITCH = 0.05, 2.5, 1e-5  # 50 mm lens focused at 2.5 m, 10 um pixels


def knob_table(quick: bool, radius: float) -> list[tuple[str, str, jaxdof.AbstractMethod]]:
    """`(name, knob label, method object)` rows; one curve per method over its knob."""
    rows = [("soft", "", jaxdof.Soft()), ("hard", "", jaxdof.Hard()), ("auto", "", jaxdof.Auto())]
    ss = (2, 4, 8) if quick else ((2, 4, 8, 16) if radius <= 8 else (2, 4, 8))
    rows += [("supersample", f"n={n}", jaxdof.Supersample(samples=n)) for n in ss]
    rows += [
        ("jitter", f"n={n}", jaxdof.Jitter(samples=n, key=KEY))
        for n in ((4, 16) if quick else (4, 16, 64))
    ]
    ap = (16, 64, 256) if quick else (16, 64, 256, 1024)
    rows += [("aperture", f"N={n}", jaxdof.Aperture(samples=n)) for n in ap]
    rows += [
        ("layered", f"L={n}", jaxdof.Layered(layers=n))
        for n in ((2, 4, 8) if quick else (2, 4, 8, 16))
    ]
    return rows


def texture(size: int, seed: int = 0) -> np.ndarray:
    """Checker of random colours, soft blobs and fine noise: edges at every scale, values in [0, 1]."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    cells = rng.uniform(size=(8, 8, 3))[(y * 8).astype(int), (x * 8).astype(int)]
    blobs = 0.5 + 0.5 * np.sin(2 * np.pi * (3 * x + 2 * y))[..., None] * np.array([1.0, 0.5, -0.7])
    img = 0.5 * cells + 0.3 * blobs + 0.2 * rng.uniform(size=(size, size, 3))
    return np.clip(img, 0, 1)


def depth_map(scene: str, size: int) -> np.ndarray:
    """z-depth (m) of the three scenes; the lens focuses at 2.5 m."""
    y, x = np.mgrid[0:size, 0:size] / size
    if scene == "smooth":  # inverse depth from 1/1.2 to 1/8 m^-1, smoothly varying
        inv = 1 / 8 + (1 / 1.2 - 1 / 8) * (
            0.5 + 0.5 * np.sin(2.5 * x + 1.5 * y - 1.2) * np.cos(2 * y)
        )
        return 1 / inv
    if scene == "steps":  # eight vertical bands
        levels = np.array([1.2, 1.6, 2.0, 2.5, 3.2, 4.0, 5.5, 8.0])
        return levels[np.minimum((x * 8).astype(int), 7)]
    if scene == "planes":  # background, an in-focus rectangle, a near disc
        d = np.full((size, size), 8.0)
        d[(x > 0.15) & (x < 0.6) & (y > 0.2) & (y < 0.8)] = D_F
        d[(x - 0.7) ** 2 + (y - 0.6) ** 2 < 0.2**2] = 1.3
        return d
    raise ValueError(scene)


def lens_for(depth: np.ndarray, radius: float) -> ThinLens:
    """The lens focused at `D_F` whose largest circle on this depth map is `radius` px."""
    r1 = float(np.max(np.asarray(coc_radius(jnp.asarray(depth), ThinLens(F, 1.0, D_F, PITCH)))))
    return ThinLens(F, r1 / radius, D_F, PITCH)


def fit_error(method, image, depth, lens, target, radius, steps=40):
    """Relative error of the f-number (the blur scale) fitted through `method` (a method object),
    focus known."""
    truth = float(lens.f_number)
    y0 = jnp.log(jnp.asarray([truth * 1.15], jnp.float32))

    def residual(y, args):
        img, dep, tgt = args
        trial = ThinLens(F, jnp.exp(y[0]), D_F, PITCH)
        out = render(img, dep, trial, method=method, max_radius=1.5 * radius)
        return (out - tgt).reshape(-1)

    solver = optx.LevenbergMarquardt(rtol=1e-5, atol=1e-5)  # float32: steps at its rounding floor
    sol = optx.least_squares(
        residual, solver, y0, args=(image, depth, target), max_steps=steps, throw=False
    )
    return abs(math.exp(float(sol.value[0])) / truth - 1)


def run(
    quick: bool, size: int | None = None, tag: str = "", auto_sizes: tuple[int, ...] = (256,)
) -> None:
    size = size or (32 if quick else 48)
    radii = (2.0, 8.0) if quick else (2.0, 8.0, 24.0)
    repeat = 3 if quick else 5
    scenes = ("smooth", "steps", "planes")
    image = jnp.asarray(texture(size), jnp.float32)
    rows = []
    auto_rows = []
    t_start = time.perf_counter()
    for R in radii:
        rows += measure_radius(R, image, scenes, quick, repeat, t_start)
        for sz in dict.fromkeys((size, *auto_sizes)):
            auto_rows += auto_vs_soft(R, scenes, sz, repeat)
    meta = dict(
        quick=quick,
        size=size,
        radii=list(radii),
        repeat=repeat,
        elapsed=time.perf_counter() - t_start,
    )
    raw = dict(meta=meta, measured=measured_here(), rows=rows, auto_rows=auto_rows)
    raw_path = result_path("tradeoff", "_raw.json", quick=quick, tag=tag)
    save_json(raw_path, raw, indent=1, final_newline=True)
    write(rows, auto_rows, raw["measured"], **meta, tag=tag)


def measure_radius(R: float, image, scenes, quick: bool, repeat: int, t_start: float) -> list:
    """Every row (scene, method, knob) at max radius `R`: accuracy and fit first, then the
    forward and fwd+grad times of all of them sampled round by round."""
    size = image.shape[0]
    mp = size * size / 1e6
    setup = {}
    for scene in scenes:
        depth = depth_map(scene, size)
        lens = lens_for(depth, R)
        radius = np.asarray(coc_radius(jnp.asarray(depth, jnp.float32), lens), np.float32)
        ref = np.asarray(coc_filter(image, jnp.asarray(radius), max_radius=R))
        setup[scene] = (depth, lens, radius, ref)
    rows = []
    timers = []  # (fwd, args, calls), (grad, gargs, calls) of every row of this R, in order
    for name, label, method in knob_table(quick, R):
        # one compiled function per (R, method, knob), shared by the scenes (same shapes)
        def fwd_fn(img, r, m=method, R=R):
            return coc_filter(img, r, method=m, max_radius=R)

        def loss(img, r, tgt, m=method, R=R):
            return 0.5 * jnp.sum((coc_filter(img, r, method=m, max_radius=R) - tgt) ** 2)

        shared = (jax.jit(fwd_fn), jax.jit(jax.value_and_grad(loss, argnums=(0, 1))))
        for scene in scenes:
            row, row_timers = measure_row(
                scene, R, name, label, method, image, setup[scene], fwd_fn, loss, shared
            )
            rows.append(row)
            timers += row_timers
            fit = row["fit_err"]
            print(
                f"{scene:7s} R={R:4.0f} {name:11s} {label:7s} max={row['max_err']:.2e} "
                f"rmse={row['rmse']:.2e} fit={'' if fit is None else f'{fit:.1e}'} "
                f"{row['choice']} [{time.perf_counter() - t_start:.0f}s]",
                flush=True,
            )
    timed = batched_medians_in_turns(timers, repeat)
    for row, t_f, t_g in zip(rows, timed[::2], timed[1::2]):
        row["fwd_ms_per_mp"], row["grad_ms_per_mp"] = 1e3 * t_f / mp, 1e3 * t_g / mp
        print(
            f"{row['scene']:7s} R={R:4.0f} {row['method']:11s} {row['knob']:7s} "
            f"fwd={row['fwd_ms_per_mp']:9.1f} ms/MP grad={row['grad_ms_per_mp']:9.1f}",
            flush=True,
        )
    return rows


def measure_row(scene, R, name, label, method, image, setup, fwd_fn, loss, shared):
    """One row's errors against soft, compile time and fit error (times left NaN), and its two
    timers `(fn, args, calls)`: forward and fwd+grad. `name` is the method's row name, `method`
    the object."""
    depth, lens, radius, ref = setup
    rad, target = jnp.asarray(radius), jnp.asarray(ref)
    if name == "auto":  # the radius map must be concrete: closed over, compiled per scene
        fwd = jax.jit(lambda img, r=radius: fwd_fn(img, r))
        grad = jax.jit(jax.value_and_grad(lambda img, r=radius, t=target: loss(img, r, t)))
        args, gargs = (image,), (image,)
    else:
        (fwd, grad), args, gargs = shared, (image, rad), (image, rad, target)
    out = np.asarray(fwd(*args))
    err = np.abs(out.astype(np.float64) - ref)
    rmse = float(np.sqrt(np.mean(err**2)))
    compile_f, calls_f = calls_per_sample(fwd, *args)
    compile_g, calls_g = calls_per_sample(grad, *gargs)
    fit = None
    fitted = method.differentiable_in_radius or name == "layered"
    if R == 8.0 and fitted and name != "auto":  # auto fits through soft (traced radius)
        fit = fit_error(method, image, jnp.asarray(depth, jnp.float32), lens, target, R)
    row = dict(
        scene=scene,
        R=R,
        method=name,
        knob=label,
        max_err=float(err.max()),
        rmse=rmse,
        psnr=float(20 * np.log10(1 / rmse)) if rmse > 0 else math.inf,
        fwd_ms_per_mp=math.nan,  # timed by the caller, interleaved with the other rows
        grad_ms_per_mp=math.nan,
        compile_s=compile_f + compile_g,
        fit_err=fit,
        choice=choose_method(radius, max_radius=R) if name == "auto" else "",
    )
    return row, [(fwd, args, calls_f), (grad, gargs, calls_g)]


def auto_vs_soft(R: float, scenes, size: int, repeat: int) -> list[dict]:
    """`auto` and `soft`, the radius map closed over (concrete), timed interleaved in one run."""
    image = jnp.asarray(texture(size), jnp.float32)
    soft, auto = jaxdof.Soft(), jaxdof.Auto()
    out = []
    for scene in scenes:
        depth = depth_map(scene, size)
        radius = np.asarray(
            coc_radius(jnp.asarray(depth, jnp.float32), lens_for(depth, R)), np.float32
        )
        soft_c = jax.jit(lambda img, r=radius: coc_filter(img, r, method=soft, max_radius=R))
        auto_c = jax.jit(lambda img, r=radius: coc_filter(img, r, method=auto, max_radius=R))
        # soft as it runs inside render/fit_lens: the radius map an argument, not a constant that
        # XLA may fold (with it closed over, the weight maps can be computed at compile time).
        soft_t = jax.jit(lambda img, r: coc_filter(img, r, method=soft, max_radius=R))
        # the per-call floor: one elementwise pass over the same frame, dispatch included
        empty = jax.jit(lambda img: img + 1)
        radius_t = jnp.asarray(radius)
        ref = np.asarray(soft_c(image), np.float64)
        calls = [
            (f, a, calls_per_sample(f, *a)[1])
            for f, a in (
                (soft_c, (image,)),
                (soft_t, (image, radius_t)),
                (auto_c, (image,)),
                (empty, (image,)),
            )
        ]
        ts, tt, ta, te = batched_medians_in_turns(calls, 3 * repeat)
        t_inspect = timeit.repeat(
            lambda r=radius: choose_method(r, max_radius=R), number=1, repeat=5
        )
        out.append(
            dict(
                scene=scene,
                R=R,
                size=size,
                levels=int(np.unique(np.where(radius <= 0.5, 0, radius)).size),
                choice=choose_method(radius, max_radius=R),
                soft_ms=1e3 * ts,
                soft_traced_ms=1e3 * tt,
                auto_ms=1e3 * ta,
                empty_ms=1e3 * te,
                inspect_ms=1e3 * float(np.median(t_inspect)),
                max_err=float(np.abs(np.asarray(auto_c(image), np.float64) - ref).max()),
            )
        )
        print(out[-1], flush=True)
    return out


def pareto_flags(rows):
    """A row is on the front of its (scene, R) panel if no other row is both faster and more accurate."""
    flags = []
    for r in rows:
        panel = [o for o in rows if o["scene"] == r["scene"] and o["R"] == r["R"]]
        dominated = any(
            o["fwd_ms_per_mp"] < r["fwd_ms_per_mp"] and o["rmse"] < r["rmse"]
            for o in panel
            if o is not r
        )
        flags.append(not dominated)
    return flags


def measured_here() -> list[str]:
    """The report's lines on the run itself: its command, the software and machine, the load."""
    device = jax.devices()[0]
    return [
        f"Generated by `{command('tradeoff.py')}` (see its docstring for the method).",
        f"- {versions_line()}, {os.cpu_count()} cores visible, backend {jax.default_backend()} "
        f"({device.device_kind})",
        f"- load average at the end: {load_average()} "
        "(the machine was shared with other jobs: timings are noisy, ratios within one panel are "
        "what to read)",
    ]


def write(rows, auto_rows, measured, quick, size, radii, repeat, elapsed, tag=""):
    """The report and plot from measured rows; `measured`: the run's `measured_here` lines."""
    png = result_path("tradeoff", ".png", quick=quick, tag=tag)
    front = pareto_flags(rows)
    lines = [
        "# Speed against accuracy of the `coc_filter` methods",
        "",
        measured[0],
        "",
        "## Conditions",
        "",
        f"- images {size} x {size} x 3, float32; max radius {', '.join(f'{r:g}' for r in radii)} px; "
        f"per-call times: medians of {repeat} samples (each a batch of back-to-back calls of about "
        f"{1e3 * SAMPLE_S:g} ms), all rows of one R timed interleaved, round by round; compile "
        f"apart; total run {elapsed / 60:.1f} min",
        *measured[1:],
        '- errors against `method="soft"`, image values in [0, 1]; PSNR = 20 log10(1 / RMSE)',
        "- fit: relative error of the f-number (blur scale; focus distance known) fitted through the "
        "method, start 15 % off, targets rendered by soft; only at R = 8; `-`: not fitted (no gradient "
        "in the radius; `auto` fits through `soft` because the radius is traced)",
        "- front: on the Pareto front of its panel (no other method/knob both faster and more accurate)",
        "",
        f"![Pareto plot]({png.name})",
        "",
        "## Every method and knob",
        "",
        "| scene | R | method | knob | max err | RMSE | PSNR dB | fwd ms/MP | fwd+grad ms/MP | compile s | fit err | front |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r, f in zip(rows, front):
        fit = "-" if r["fit_err"] is None else f"{r['fit_err']:.1e}"
        knob = r["knob"] + (f" ({r['choice']})" if r["choice"] else "")
        lines.append(
            f"| {r['scene']} | {r['R']:g} | {r['method']} | {knob} | {r['max_err']:.1e} | {r['rmse']:.1e} | "
            f"{r['psnr']:.1f} | {r['fwd_ms_per_mp']:.0f} | {r['grad_ms_per_mp']:.0f} | {r['compile_s']:.1f} | "
            f"{fit} | {'yes' if f else ''} |"
        )
    lines += [
        "",
        "## `auto` against `soft` (all timed interleaved in the same run)",
        "",
        "`soft traced`: the radius map passed as an argument, as inside `render` and `fit_lens`;",
        "`soft const`: closed over like `auto`'s (which must see concrete values), so that XLA may",
        "fold the weight maps into constants at compile time. Speed-ups are soft / auto for each.",
        "`empty ms`: a jitted `image + 1` on the same frame, timed alongside: the per-call floor",
        "(dispatch, the runtime's threads, one pass over the frame) that no method goes below.",
        "",
        "| scene | frame | R | distinct radii | auto chose | soft traced ms | soft const ms | auto ms | empty ms | speed-up (traced) | speed-up (const) | inspection ms | max err vs soft |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for a in auto_rows:
        lines.append(
            f"| {a['scene']} | {a['size']}^2 | {a['R']:g} | {a['levels']} | {a['choice']} | "
            f"{a['soft_traced_ms']:.2f} | {a['soft_ms']:.2f} | {a['auto_ms']:.2f} | "
            f"{a['empty_ms']:.2f} | {a['soft_traced_ms'] / a['auto_ms']:.1f}x | {a['soft_ms'] / a['auto_ms']:.1f}x | "
            f"{a['inspect_ms']:.2f} | {a['max_err']:.1e} |"
        )
    lines += ["", "## Goals (computed from the tables above)", ""]
    lines += goal_lines(rows, auto_rows, front)
    lines += [
        "",
        "## What holds by construction (and is tested in `tests/test_methods.py`)",
        "",
        "- `soft` is the reference; `auto` returns the soft result (exact FFT layers, the tabulated gather, or",
        "  the gather) and only changes the cost; `layered` equals `soft` when the map has at most `L`",
        "  distinct radii (the `planes` rows), and is quantised otherwise.",
        "- `supersample` and `jitter` converge to `soft` as the sample count grows; `hard` is",
        "  `supersample` with n = 1. None of the three has a gradient in the radius: they cannot fit a lens.",
        "- `aperture` converges to the disc convolved with the bilinear splat's tent, not to `soft`: its",
        "  error against `soft` has a floor that more lens samples do not remove (the `N` curves flatten).",
        "",
        "## Recommendations",
        "",
        "- Fitting a lens, or any gradient in the radius: `soft` (or `auto`, which is `soft` under tracing).",
        "- Rendering a scene whose radii repeat (depth planes, a quantised depth map): `auto` (FFT",
        "  layers for a few radii in a large window, else the tabulated gather; the soft filter's numbers).",
        "- Previews where accuracy does not matter: `hard` is the cheapest; `aperture` with few samples",
        "  is independent of the radius in cost but blotchy for large circles.",
        "- `supersample`/`jitter` exist to reproduce the 2006 paper and cannot fit a lens: at small n",
        "  they can cost less than `soft` but carry the coverage error in the tables; at n = 8 see the",
        "  goal line above for how supersampling compares with `soft`, which has no error.",
    ]
    write_markdown(result_path("tradeoff", quick=quick, tag=tag), lines)
    plot(rows, png, radii)
    print("\n".join(lines))


def goal_lines(rows, auto_rows, front):
    out = []
    panels = sorted({(r["scene"], r["R"]) for r in rows})
    # soft most accurate at <= the cost of supersample n = 8
    ok, detail = 0, []
    for scene, R in panels:
        soft = next(
            r for r in rows if r["scene"] == scene and r["R"] == R and r["method"] == "soft"
        )
        ss8 = next(
            (
                r
                for r in rows
                if r["scene"] == scene
                and r["R"] == R
                and r["method"] == "supersample"
                and r["knob"] == "n=8"
            ),
            None,
        )
        if ss8 is None:
            continue
        cheaper = soft["fwd_ms_per_mp"] <= ss8["fwd_ms_per_mp"]
        ok += cheaper
        detail.append(
            f"{scene}/R={R:g}: soft {soft['fwd_ms_per_mp']:.0f} vs supersample n=8 {ss8['fwd_ms_per_mp']:.0f} ms/MP (RMSE of n=8: {ss8['rmse']:.1e})"
        )
    out.append(
        f"- soft (the reference, error 0) costs no more than supersample n = 8 in {ok}/{len(detail)} panels: "
        + "; ".join(detail)
    )
    # every method near the front
    by_method = {}
    for r, f in zip(rows, front):
        by_method.setdefault(r["method"], []).append(f)
    out.append(
        "- rows on their panel's Pareto front, per method: "
        + ", ".join(f"{m} {sum(v)}/{len(v)}" for m, v in by_method.items())
    )

    # how near: a row's time over that of the fastest row of its panel at least as accurate (1 on
    # the front); per method its best knob in each panel, then the median and range over panels
    def near(eligible):
        gaps = {}
        for scene, R in panels:
            panel = [r for r in rows if r["scene"] == scene and r["R"] == R and eligible(r)]
            best = {}
            for r in panel:
                floor = min(o["fwd_ms_per_mp"] for o in panel if o["rmse"] <= r["rmse"])
                gap = max(r["fwd_ms_per_mp"] / floor, 1.0)
                best[r["method"]] = min(best.get(r["method"], np.inf), gap)
            for m, g in best.items():
                gaps.setdefault(m, []).append(g)
        return ", ".join(
            f"{m} {np.median(g):.1f}x ({min(g):.1f}-{max(g):.1f})" for m, g in gaps.items()
        )

    out.append(
        "- distance to the front (a row's forward time over that of the fastest row of its panel "
        "that is at least as accurate; 1.0 = on the front), each method's best knob per panel, "
        "median (range) over the panels: " + near(lambda r: True)
    )
    out.append(
        "- the same among the rows that take the radius map as a traced argument (what a fit "
        "differentiates through; `auto`, closed over a concrete map, left out): "
        + near(lambda r: r["method"] != "auto")
    )
    few = [a for a in auto_rows if a["levels"] <= 4]
    out.append(
        "- auto vs soft on scenes of <= 4 radius levels: "
        + "; ".join(
            f"{a['scene']}/{a['size']}^2/R={a['R']:g} ({a['levels']} levels, {a['choice']}): "
            f"{a['soft_traced_ms'] / a['auto_ms']:.1f}x (radius traced), "
            f"{a['soft_ms'] / a['auto_ms']:.1f}x (closed over); auto {a['auto_ms'] / a['empty_ms']:.1f}x "
            "the empty call"
            for a in few
        )
    )
    return out


def plot(rows, path, radii):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = ("smooth", "steps", "planes")
    fig, axes = plt.subplots(len(radii), 3, figsize=(13, 3.6 * len(radii)), squeeze=False)
    colours = dict(
        soft="k",
        hard="tab:red",
        supersample="tab:blue",
        jitter="tab:orange",
        aperture="tab:green",
        layered="tab:purple",
        auto="tab:gray",
    )
    floor = 1e-8  # soft and auto have zero or rounding-level error: drawn at the plot's floor
    for i, R in enumerate(radii):
        for j, scene in enumerate(scenes):
            ax = axes[i, j]
            for method, c in colours.items():
                pts = [
                    r for r in rows if r["scene"] == scene and r["R"] == R and r["method"] == method
                ]
                if not pts:
                    continue
                x = [p["fwd_ms_per_mp"] for p in pts]
                y = [max(p["rmse"], floor) for p in pts]
                ax.plot(x, y, "o-", color=c, label=method, ms=4)
                for p, xx, yy in zip(pts, x, y):
                    if p["knob"]:
                        ax.annotate(
                            p["knob"],
                            (xx, yy),
                            fontsize=6,
                            xytext=(2, 2),
                            textcoords="offset points",
                        )
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_title(f"{scene}, max radius {R:g} px", fontsize=9)
            ax.set_xlabel("forward time (ms per megapixel)", fontsize=8)
            ax.set_ylabel("RMSE vs soft", fontsize=8)
            ax.grid(True, which="both", alpha=0.3)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(
        "coc_filter methods: error against the analytic soft filter vs cost (lower-left is better)"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "--quick", action="store_true", help="32 px images, radius 2 and 8, fewer knobs"
    )
    parser.add_argument("--size", type=int, default=None, help="image side (default 48, quick 32)")
    parser.add_argument(
        "--auto-size",
        type=int,
        nargs="+",
        default=[256],
        help="the larger frame(s) of the auto-vs-soft timing (default 256)",
    )
    parser.add_argument("--tag", default="", help="suffix of the output names, e.g. _gpu")
    parser.add_argument(
        "--rewrite",
        metavar="RAW_JSON",
        help="rewrite the report and plot from a run's raw file (no timing), e.g. after editing them",
    )
    args = parser.parse_args(argv)
    if args.rewrite:
        raw = load_json(Path(args.rewrite))
        write(raw["rows"], raw["auto_rows"], raw["measured"], **raw["meta"], tag=args.tag)
    else:
        run(args.quick, args.size, args.tag, tuple(args.auto_size))


if __name__ == "__main__":
    main()
    sys.exit(0)
