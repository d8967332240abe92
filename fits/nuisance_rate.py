"""How often the default fit adds a nuisance the photo does not have, and how often it finds one
that the photo has (issue 34: "its detection has a measured false-alarm rate").

Question: with the default call `fit_lens(image, depth, photo, init)`, on noisy renders of a
scene, how often is each nuisance (`exposure`, `vignetting`, `illumination`, `registration`)
fitted

- **false alarm**: photos rendered without any (only Gaussian noise): the share of fits that fit
  each one;
- **power**: photos with one of them (exposure x 0.85; vignetting `1 - 0.25 rho^2`, 25 % darker
  in the corners; illumination `1 + 0.25 u`, `u` across the frame over its half diagonal, 30 %
  brighter on the right than the left; a shift of (0.4, -0.6) px and a 1 % magnification,
  resampled with `scipy.ndimage.map_coordinates`, quintic splines, an interpolant the fit does
  not use): the share that fit it, and the lens error.

Scene: a 40 x 56 random texture over a depth ramp 1-5 m (the tests' round-trip scene, as
`select_rate.py`), 50 mm on a 4.8 mm sensor, f/2.8 focused at 2.5 m (circles 0.7-2.7 px); start
f/4.2 at 2 m; noise sigma a share of the photo's mean. float32, as a new user calls it.

    python fits/nuisance_rate.py [--draws 10] [--power-draws 4] [--noise 0.01]

Writes `fits/results/nuisance_rate.md`.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import scipy.ndimage
from _common import command, git_state, machine_info, result_path, write_markdown
from select_rate import _lens, _scene  # the same scene and lenses

import jaxdof


NUISANCES = ("exposure", "vignetting", "illumination", "registration")


def spoil(clean: np.ndarray, what: str) -> np.ndarray:
    """The photo with one nuisance (`"none"`: as rendered)."""
    h, w = clean.shape[:2]
    v = (np.arange(h) + 0.5 - h / 2)[:, None]
    u = (np.arange(w) + 0.5 - w / 2)[None, :]
    rho2 = (u**2 + v**2) / (0.25 * (h * h + w * w))
    if what == "exposure":
        return 0.85 * clean
    if what == "vignetting":
        return clean * (1 - 0.25 * rho2)[..., None]
    if what == "illumination":
        return clean * (1 + 0.25 * u / np.sqrt(0.25 * (h * h + w * w)))[..., None]
    if what == "registration":
        m, sx, sy = 0.01, 0.4, -0.6
        rows = (np.arange(h)[:, None] + 0.5 - h / 2 - sy) / (1 + m) + h / 2 - 0.5
        cols = (np.arange(w)[None, :] + 0.5 - w / 2 - sx) / (1 + m) + w / 2 - 0.5
        rr, cc = np.broadcast_arrays(rows, cols)
        return np.stack(
            [
                scipy.ndimage.map_coordinates(clean[..., k], [rr, cc], order=5, mode="nearest")
                for k in range(clean.shape[-1])
            ],
            axis=-1,
        )
    return clean


def _first(x) -> float:
    return float(np.asarray(x).ravel()[0])


def run(draws: int, noise: float, what: str) -> dict:
    image, depth = _scene()
    truth, start = _lens(2.8, 2.5), _lens(4.2, 2.0)
    clean = spoil(np.asarray(jaxdof.render(image, depth, truth), np.float64), what)
    fitted = {k: 0 for k in NUISANCES}
    n_err, d_err, secs, success, silent = [], [], [], 0, 0
    for k in range(draws):
        rng = np.random.default_rng(1000 + k)
        photo = (clean + rng.normal(0, noise * clean.mean(), clean.shape)).astype(np.float32)
        t = time.perf_counter()
        fit = jaxdof.fit_lens(image, depth, photo, start)
        secs.append(time.perf_counter() - t)
        for name in NUISANCES:
            fitted[name] += int(fit.nuisances[name]["fitted"])
        success += int(bool(fit.success))
        n_err.append(abs(float(fit.lenses.f_number[0]) / 2.8 - 1))
        d_err.append(abs(float(fit.lenses.focus_distance[0]) / 2.5 - 1))
        # Silent: a lens reported as trustworthy whose error exceeds 3 of its standard errors.
        z = max(
            abs(float(fit.lenses.f_number[0]) - 2.8) / _first(fit.stderr["f_number"]),
            abs(float(fit.lenses.focus_distance[0]) - 2.5) / _first(fit.stderr["focus_distance"]),
        )
        silent += int(bool(fit.success) and not z <= 3)
    return dict(
        fitted=fitted,
        draws=draws,
        success=success,
        silent=silent,
        n_err=float(np.median(n_err)),
        d_err=float(np.median(d_err)),
        secs=secs,
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=10, help="photos without a nuisance")
    parser.add_argument("--power-draws", type=int, default=4, help="photos with each one")
    parser.add_argument("--noise", type=float, nargs="+", default=[0.01])
    args = parser.parse_args(argv)
    lines = [
        "# What the camera added: false alarms and power of its detection (issue 34)",
        "",
        "Produced by `" + command("nuisance_rate.py", argv) + "` (the script's docstring gives "
        "the question and the method).",
        "",
        *(f"- {k}: {v}" for k, v in machine_info().items()),
        f"- jaxdof source: {git_state()}",
        "",
        "| noise (share of mean) | photo has | exposure fitted | vignetting fitted | "
        "illumination fitted | registration fitted | success | silent (success, error over 3 se) | median abs N error | median abs d_f error | "
        "median s per fit |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for noise in args.noise:
        for what in ("none", *NUISANCES):
            draws = args.draws if what == "none" else args.power_draws
            r = run(draws, noise, what)
            f = r["fitted"]
            lines.append(
                f"| {noise:g} | {what} | "
                + " | ".join(f"{f[k]} of {r['draws']}" for k in NUISANCES)
                + f" | {r['success']} of {r['draws']} | {r['silent']} of {r['draws']} | {100 * r['n_err']:.2f} % | "
                f"{100 * r['d_err']:.2f} % | {np.median(r['secs']):.1f} |"
            )
            print(lines[-1], flush=True)
    path = write_markdown(result_path("nuisance_rate"), lines)
    print(f"wrote {path}", file=sys.stderr)


if __name__ == "__main__":
    main()
