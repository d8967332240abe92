"""How often the photo's say in the treatment (`jaxdof/_fit/select.py`) chooses wrongly, and how
often it chooses rightly (issue 33).

Question: with the default call `fit_lens(image, depth, photo, init)`, on noisy renders of a scene
by a known model, how often does the selection keep the model that made the photo?

- **false choice**: renders *with* the footprint correction (what the scene rule chooses for these
  circles) plus Gaussian noise: the share of fits that drop it (`footprint off` chosen);
- **power**: renders by `render`'s default (the plain soft scatter, no footprint) plus the same
  noise: the share of fits that drop it, as they should.

Scene: a 40 x 56 random texture over a depth ramp 1-5 m (the tests' round-trip scene), 50 mm on a
4.8 mm sensor, f/2.8 focused at 2.5 m (circles 0.7-2.7 px); start f/4.2 at 2 m; noise sigma a
share of the photo's mean. float32, as a new user calls it.

    python fits/select_rate.py [--draws 10] [--noise 0.003 0.01]

Writes `fits/results/select_rate.md`.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
from _common import command, git_state, machine_info, result_path, write_markdown

import jaxdof


def _scene():
    rng = np.random.default_rng(0)
    image = rng.uniform(0.05, 1.0, size=(40, 56, 3)).astype(np.float32)
    depth = np.linspace(1.0, 5.0, 56, dtype=np.float32)[None, :].repeat(40, 0)
    return image, depth


def _lens(n, d_f):
    return jaxdof.ThinLens.from_sensor(0.05, n, d_f, sensor_width=0.0048, image_width=56)


def run(draws: int, noise: float, footprint: bool) -> dict:
    image, depth = _scene()
    truth, start = _lens(2.8, 2.5), _lens(4.2, 2.0)
    clean = np.asarray(jaxdof.render(image, depth, truth, footprint=footprint))
    dropped, errs, secs = 0, [], []
    for k in range(draws):
        rng = np.random.default_rng(1000 + k)
        photo = (clean + rng.normal(0, noise * clean.mean(), clean.shape)).astype(np.float32)
        t = time.perf_counter()
        fit = jaxdof.fit_lens(image, depth, photo, start)
        secs.append(time.perf_counter() - t)
        dropped += int(not fit.treatment.footprint)
        errs.append(abs(float(fit.lenses.f_number[0]) / 2.8 - 1))
    return dict(dropped=dropped, draws=draws, median_n_err=float(np.median(errs)), secs=secs)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=10)
    parser.add_argument("--noise", type=float, nargs="+", default=[0.003, 0.01])
    args = parser.parse_args(argv)
    lines = [
        "# The photo's say in the treatment: false choices and power (issue 33)",
        "",
        "Produced by `" + command("select_rate.py", argv) + "` (the script's docstring gives the "
        "question and the method).",
        "",
        *(f"- {k}: {v}" for k, v in machine_info().items()),
        f"- jaxdof source: {git_state()}",
        "",
        "| noise (share of mean) | photo made with | footprint dropped | median abs N error | "
        "median s per fit |",
        "|---|---|---|---|---|",
    ]
    for noise in args.noise:
        for footprint, label in (
            (True, "footprint (false choice if dropped)"),
            (False, "plain soft (right if dropped)"),
        ):
            r = run(args.draws, noise, footprint)
            lines.append(
                f"| {noise:g} | {label} | {r['dropped']} of {r['draws']} | "
                f"{100 * r['median_n_err']:.3f} % | {np.median(r['secs']):.1f} |"
            )
            print(lines[-1], flush=True)
    path = write_markdown(result_path("select_rate"), lines)
    print(f"wrote {path}", file=sys.stderr)


if __name__ == "__main__":
    main()
