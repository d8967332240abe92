"""What the nuisance decisions cost where the photo needs none (issue 34: "where no nuisance is
needed, the default fit costs at most 1.2x today's").

Question: on photos without exposure, vignetting or registration error (a render plus Gaussian
noise), how much longer does the default call `fit_lens(image, depth, photo, init)` take than the
same call with every nuisance forced off (`exposure=False, vignetting=False,
registration=False`: no score test, no refit; the fit as it was before the nuisances existed)?

Method: two scenes, each rendered through one lens, 1 % noise: the tests' round-trip scenes, a
random texture over a depth ramp (1-5 m) and over a step between two slanted planes (depth
edges: the occlusion render and the photo's say in the treatment), at 96 x 128 px, 50 mm on a
4.8 mm sensor, f/2.8 focused at 2.5 m; start f/4.2 at 2 m. Per scene: each call once (the first,
compiling), then the two calls alternated `--repeats` times (warm); medians and the ratio of
the medians. The stages of one warm default call (`jaxdof.internal.record_stages`) show where the
difference goes. float32, as a new user calls it.

    python fits/nuisance_cost.py [--repeats 5]

Writes `fits/results/nuisance_cost.md`.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
from _common import command, git_state, machine_info, result_path, write_markdown

import jaxdof
from jaxdof.internal import record_stages


OFF = dict(exposure=False, vignetting=False, registration=False)
H, W = 96, 128


def _lens(n: float, d_f: float) -> jaxdof.ThinLens:
    return jaxdof.ThinLens.from_sensor(0.05, n, d_f, sensor_width=0.0048, image_width=W)


def _scene(kind: str) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    image = rng.uniform(0.05, 1.0, size=(H, W, 3)).astype(np.float32)
    x = np.linspace(0.0, 1.0, W, dtype=np.float32)
    if kind == "ramp":
        row = np.linspace(1.0, 5.0, W, dtype=np.float32)
    else:
        row = np.where(x < 0.5, 1.2 + x, 3.0 + 2 * x).astype(np.float32)
    return image, np.repeat(row[None, :], H, 0)


def _timed(fn) -> tuple[float, object]:
    t = time.perf_counter()
    out = fn()
    return time.perf_counter() - t, out


def run(kind: str, repeats: int) -> dict:
    image, depth = _scene(kind)
    clean = np.asarray(jaxdof.render(image, depth, _lens(2.8, 2.5)), np.float64)
    rng = np.random.default_rng(1)
    photo = (clean + rng.normal(0, 0.01 * clean.mean(), clean.shape)).astype(np.float32)
    start = _lens(4.2, 2.0)
    default = lambda: jaxdof.fit_lens(image, depth, photo, start)  # noqa: E731
    off = lambda: jaxdof.fit_lens(image, depth, photo, start, **OFF)  # noqa: E731
    first_off, fit_off = _timed(off)
    first_default, fit = _timed(default)
    warm_default, warm_off = [], []
    for _ in range(repeats):
        warm_default.append(_timed(default)[0])
        warm_off.append(_timed(off)[0])
    with record_stages() as log:
        default()
    stages: dict[str, float] = {}
    for name, sec in log:
        stages[name] = stages.get(name, 0.0) + sec
    fitted = [k for k in OFF if fit.nuisances[k]["fitted"]]
    return {
        "scene": kind,
        "first_off": first_off,
        "first_default": first_default,
        "warm_off": statistics.median(warm_off),
        "warm_default": statistics.median(warm_default),
        "stages": stages,
        "fitted": fitted,
        "same_lens": bool(
            np.allclose(
                np.asarray(fit.lenses.f_number), np.asarray(fit_off.lenses.f_number), rtol=1e-6
            )
        ),
        "treatment": str(fit.treatment),
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = [run(kind, args.repeats) for kind in ("ramp", "step")]
    lines = [
        "# What the nuisance decisions cost where the photo needs none (issue 34)",
        "",
        f"Produced by `{command('nuisance_cost.py', argv)}` (the script's docstring gives the "
        f"question and the method); {time.perf_counter() - t0:.0f} s wall.",
        "",
        *(f"- {k}: {v}" for k, v in machine_info().items()),
        f"- jaxdof source: {git_state()}",
        "",
        f"Warm: medians of {args.repeats} calls each, alternated. First: the first call of each "
        "in this process, the forced-off call first (it compiles the programs both share, so "
        "the default's first call pays only what it adds).",
        "",
        "| scene | forced off, warm (s) | default, warm (s) | ratio | forced off, first (s) | "
        "default, first (s) | nuisances fitted | same lens | default's stages, warm (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        stages = ", ".join(f"{k} {v:.2f}" for k, v in r["stages"].items())
        lines.append(
            f"| {r['scene']} | {r['warm_off']:.2f} | {r['warm_default']:.2f} | "
            f"{r['warm_default'] / r['warm_off']:.2f} | {r['first_off']:.1f} | "
            f"{r['first_default']:.1f} | {', '.join(r['fitted']) or 'none'} | "
            f"{'yes' if r['same_lens'] else 'no'} | {stages} |"
        )
    lines += [
        "",
        "Treatments (default call): " + "; ".join(f"{r['scene']}: {r['treatment']}" for r in rows),
    ]
    path = write_markdown(result_path("nuisance_cost"), lines)
    print("\n".join(lines))
    print(f"wrote {path}", file=sys.stderr)


if __name__ == "__main__":
    main()
