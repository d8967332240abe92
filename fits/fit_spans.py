"""Row spans against the dense gather inside the fit: the cost of one solver step's Jacobian.

**Question.** The soft filter switches from the dense gather (cost ~ pi R^2 taps per pixel) to row
spans (cost ~ R) at `jaxdof.internal.tuning.SPANS_MIN_RADIUS`, a crossover measured on the
*forward* render. A fit's step does not run the forward render: it builds the Jacobian of the
render with respect to the free lens fields (`P` forward-mode tangents sharing one primal, the
residual's JVP rule), on a mosaic of tiles. Which path is cheaper there, and from which window?
(Issue 37: "the forward model inside the fit picks the cheapest exact path for the window,
measured against the dense path at the fit's tile sizes and windows".)

**Method.** For each window `W` (px): a mosaic of 25 tiles as a fit on tiles lays them out
(interior `max(32, 2 halo)` px, halo `W`, in rows of 5), a random texture with `C` channels, and a
depth map over which one lens makes circles from 0 to `(W - 1) / 1.5` px (the fit sizes its window
1.5x the largest circle, plus 1 px). Timed, jitted: `jax.jacfwd` of `jaxdof.render(...,
method="soft", max_radius=W)` with respect to `(f_number, focus_distance)` (the two free fields of
a default fit), once on the dense path and once on the spans path (`tuning.override`), in turns
over `--repeats` rounds; medians of wall time. The forward render alone is timed the same way
for reference. Both paths give the same numbers to rounding (checked here: their largest
difference relative to the largest Jacobian entry is printed).

Run: `python fits/fit_spans.py` (five windows; the report's eight, `--windows 8 12 16 20 24 32 40
48`, took 11 minutes on 2 cores); `--windows 24 32`, `--channels 1`,
`--repeats 7`, `--tag _x`. Writes `fits/results/fit_spans<tag>.md`.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time

from _common import command, git_state, machine_info, result_path, write_markdown


def mosaic_shape(window: int, tiles: int = 25) -> tuple[int, int]:
    """`(H, W)` of a fit's mosaic of `tiles` tiles with halos of `window` px."""
    halo = window
    side = max(32, -(-2 * halo // 8) * 8)
    crop = side + 2 * halo
    cols = math.ceil(math.sqrt(tiles))
    return math.ceil(tiles / cols) * crop, cols * crop


def problem(window: int, channels: int, seed: int = 0):
    """Image, depth and the lens fields: circles from 0 to `(window - 1) / 1.5` px."""
    import numpy as np

    h, w = mosaic_shape(window)
    rng = np.random.default_rng(seed)
    image = rng.uniform(size=(h, w, channels)).astype(np.float32)
    f, n, d_f = 0.05, 2.8, 3.0
    near, far = 3.0, 30.0
    depth = np.broadcast_to(np.linspace(near, far, w, dtype=np.float32)[None, :], (h, w)).copy()
    k = f * f / (2 * n * (d_f - f))  # metres of circle per unit of |1 - d_f / d|
    r_max = (window - 1) / 1.5
    pitch = k * (1 - d_f / far) / r_max
    return image, depth, (f, n, d_f, pitch)


def measure(window: int, channels: int, repeats: int) -> dict:
    """One row: the Jacobian and the forward render on both paths, timed in turns."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from _common import timed_in_turns

    import jaxdof
    from jaxdof.internal import tuning

    image, depth, (f, n, d_f, pitch) = problem(window, channels)
    image, depth = jnp.asarray(image), jnp.asarray(depth)

    def render(theta):
        lens = jaxdof.ThinLens(f, theta[0], theta[1], pitch)
        return jaxdof.render(image, depth, lens, method="soft", max_radius=float(window))

    theta = jnp.asarray([n, d_f], jnp.float32)
    fns, compile_s = {}, {}
    for path, crossover in (("dense", math.inf), ("spans", 0.0)):
        with tuning.override(SPANS_MIN_RADIUS=crossover):
            for kind, fn in (("jacobian", jax.jacfwd(render)), ("forward", render)):
                t0 = time.perf_counter()
                fns[(path, kind)] = jax.jit(fn).lower(theta).compile()
                compile_s[(path, kind)] = time.perf_counter() - t0
                jax.block_until_ready(fns[(path, kind)](theta))
    # The constant is read when the filter is traced: the two programs must differ.
    texts = {p: fns[(p, "jacobian")].as_text() for p in ("dense", "spans")}
    assert texts["dense"] != texts["spans"], "the override did not reach the trace"
    jd, js = (np.asarray(fns[(p, "jacobian")](theta)) for p in ("dense", "spans"))
    times = timed_in_turns(fns, (theta,), repeats)
    med = {k: statistics.median(t[0] for t in v) for k, v in times.items()}
    return dict(
        channels=channels,
        window=window,
        shape=image.shape[:2],
        diff=float(np.max(np.abs(jd - js)) / np.max(np.abs(jd))),
        **{f"{p}_{k}": med[(p, k)] for p in ("dense", "spans") for k in ("jacobian", "forward")},
        compile_dense=compile_s[("dense", "jacobian")],
        compile_spans=compile_s[("spans", "jacobian")],
    )


def run(windows, channels_list, repeats: int) -> list[dict]:
    rows = []
    for channels in channels_list:
        for window in windows:
            row = measure(window, channels, repeats)
            rows.append(row)
            ratio = row["spans_jacobian"] / row["dense_jacobian"]
            print(
                f"C={channels} W={window} {row['shape']}: jacobian dense "
                f"{row['dense_jacobian']:.3f} s, spans {row['spans_jacobian']:.3f} s "
                f"({ratio:.2f}x); forward {row['spans_forward'] / row['dense_forward']:.2f}x; "
                f"diff {row['diff']:.1e}",
                flush=True,
            )
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--windows", type=int, nargs="+", default=[16, 24, 32, 40, 48])
    ap.add_argument("--channels", type=int, nargs="+", default=[1, 3])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--tag", default="")
    args = ap.parse_args(argv)
    info = machine_info()
    rows = run(args.windows, args.channels, args.repeats)
    lines = [
        "# Row spans against the dense gather inside the fit (one step's Jacobian)",
        "",
        f"Produced by `{command('fit_spans.py', argv)}` (the script's docstring gives the "
        "question and the method).",
        "",
        *[f"- {k}: {v}" for k, v in info.items()],
        f"- jaxdof source: {git_state()}",
        "",
        "Medians of wall time over "
        f"{args.repeats} rounds in turns; `ratio`: spans / dense (under 1: spans faster).",
        "",
        "| C | window px | mosaic | Jacobian dense s | Jacobian spans s | ratio | forward ratio "
        "| compile dense / spans s | max diff (rel) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['channels']} | {r['window']} | {r['shape'][0]} x {r['shape'][1]} "
            f"| {r['dense_jacobian']:.3f} | {r['spans_jacobian']:.3f} "
            f"| {r['spans_jacobian'] / r['dense_jacobian']:.2f} "
            f"| {r['spans_forward'] / r['dense_forward']:.2f} "
            f"| {r['compile_dense']:.1f} / {r['compile_spans']:.1f} | {r['diff']:.1e} |"
        )
    path = write_markdown(result_path("fit_spans", tag=args.tag), lines)
    print(f"wrote {path}", file=sys.stderr)


if __name__ == "__main__":
    main()
