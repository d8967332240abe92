"""Validate jaxdof against ray-traced thin-lens truth (Mitsuba 3), and cut the CI fixtures.

Question: how close is the post-process model (`jaxdof.render` of a pinhole image + z-depth) to a
real thin lens, as ray traced by a renderer nobody on the project wrote, overall and near depth
edges; does `jaxdof.fit_lens` recover the lens from ray-traced targets (focus distance within 2%,
blur scale within 5%); what do the edge treatment and the pixel-footprint correction change?

Run (Mitsuba is an optional extra: `pip install -e ".[validate]"`):

    python fits/raytraced.py            # render what is not cached yet, then analyse
    python fits/raytraced.py --fixtures # also rewrite tests/data/raytraced_*.npz

Renders are cached in `fits/.cache/raytraced/` (not committed; about 10 MB) so analysis re-runs
are cheap. The Mitsuba variant is `llvm_ad_rgb` when LLVM 19 (Debian: `libllvm19`) is
found, else `scalar_rgb` (same scenes, slower; an older system LLVM can abort on AVX-512).
Writes `fits/results/raytraced.md` and `.png`.

Layout: `_raytraced_scenes.py` (Mitsuba scenes, renders, lens mapping, CI fixtures),
`_raytraced_fits.py` (forward-model treatments and fits), `_raytraced_report.py` (the measured
sections), `_raytraced_summary.py` (the summary written from them); this file runs them in order.
`raytraced_default.py` uses the same modules for the default call of `fit_lens` on these scenes
and nine more, half of them held out of any tuning (`HELD_OUT` in `_raytraced_scenes.py`).

Every scene is self-emitting (textured area emitters, `path` integrator with `max_depth=1`), so a
pixel's value is the pixel- and aperture-average of the emitted radiance: the only noise is the
Monte Carlo estimate of that average, measured from two seeds and reported.
"""

from __future__ import annotations

import argparse
import sys

import jax


jax.config.update("jax_enable_x64", True)

from _common import result_path, write_markdown  # noqa: E402
from _raytraced_fits import TREATMENTS, run_fits  # noqa: E402
from _raytraced_report import (  # noqa: E402
    depth_lines,
    emitter_lines,
    figure,
    fine_input_section,
    fit_section,
    gap_section,
    intro_lines,
    psnr_section,
    smallest_k_section,
)
from _raytraced_scenes import SCENES, load_scene, mitsuba, noise_pair, write_fixtures  # noqa: E402
from _raytraced_summary import FitCounts, summary_lines  # noqa: E402


def main(fixtures=False):
    """Every section in order (each asserts its claims), the summary put first; the report, the
    figure and (with `fixtures`) the CI fixtures written."""
    intro = intro_lines(mitsuba())
    lines = depth_lines()
    lines += emitter_lines()
    section, psnr = psnr_section()
    lines += section
    section, closed_all = gap_section(psnr)
    lines += section
    section, fine_med = fine_input_section()
    lines += section
    fits = run_fits()
    section, summary = fit_section(fits)
    lines += section
    section, kgrid = smallest_k_section()
    lines += section
    head = summary_lines(psnr, closed_all, fine_med, FitCounts(fits, summary), kgrid)
    lines = intro + head + lines
    write_markdown(result_path("raytraced"), lines)
    figure(psnr)
    if fixtures:
        write_fixtures()
    print("\n".join(lines))


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser()
    ap.add_argument("--fixtures", action="store_true")
    ap.add_argument("--render-only", action="store_true")
    ap.add_argument(
        "--fits",
        nargs="+",
        metavar="TREATMENT",
        help="only run (and cache) the fits of these treatments, then stop",
    )
    args = ap.parse_args(argv)
    if args.fits:
        unknown = set(args.fits) - set(TREATMENTS)
        if unknown:
            ap.error(f"unknown treatments {sorted(unknown)}; known: {sorted(TREATMENTS)}")
    return args


if __name__ == "__main__":
    args = parse_args()
    if args.fits:
        run_fits(only=set(args.fits))
        sys.exit(0)
    for name in (*SCENES, "emitters"):
        print(name, flush=True)
        load_scene(name)
    for name in SCENES:
        noise_pair(name, 0.06, 1.8)
    if args.render_only:
        sys.exit(0)
    main(fixtures=args.fixtures)
