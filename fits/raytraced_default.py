"""The default call of `jaxdof.fit_lens` on ray-traced scenes, half of them held out (issue 20,
item 7).

Question: on physically ray-traced photos, does `fit_lens(image, depth, photo, init)` with every
default (free focus distance and f-number, the default starts, border and forward model) come
back within 2 % in focus distance and 5 % in blur scale K, and when it does not, does it say so
(`success=False`) or report a standard error that covers its actual error? No exception may
escape. Reported per half: the tuning scenes and the held-out ones (`HELD_OUT` in
`_raytraced_scenes.py`: no constant in jaxdof was tuned on them).

Run (Mitsuba, the optional `validate` extra, only to render what is not cached yet):

    python fits/raytraced_default.py                 # render what is missing, fit, report
    python fits/raytraced_default.py --render-only
    python fits/raytraced_default.py --x64           # the same fits in float64 (tag _x64)
    python fits/raytraced_default.py --scenes slant  # a subset (tag _partial)
    python fits/raytraced_default.py --tag _v1 --note "..."  # another copy of jaxdof (PYTHONPATH)

Renders are cached in `fits/.cache/raytraced/` (as `raytraced.py`'s; the new ones take about
6 min on 2 shared cores); fits in `fits/.cache/raytraced/default/<fingerprint>_<precision>/`,
keyed by a hash of the imported jaxdof's source and this study's scene and fit code: after a
library change every fit runs again (32 fits, about 6 min on 2 shared cores), without one only
the report is rewritten. Writes `fits/results/raytraced_default.md` and `_raw.json`.

Precision: float32 with JAX's default `jax_enable_x64=False`, as a new user calls it (the
renders are float32); `--x64` for float64. Start: f-number 1.5x the truth's, focus 20 % short
(20 m for a lens focused at infinity); focal length and pixel pitch the truth's (fixed).
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
import time

import jax


jax.config.update("jax_enable_x64", True)  # as the modules below; main() sets the run's precision

from _common import FITS, git_state, result_path, save_json, write_markdown  # noqa: E402
from _raytraced_fits import fingerprint, library_dir, run_default  # noqa: E402
from _raytraced_report import (  # noqa: E402
    default_conditions,
    default_fit_table,
    default_method_lines,
    default_scene_lines,
    psnr_default_section,
    sum_check_lines,
)
from _raytraced_scenes import DEFAULT_SCENES, HELD_OUT, TUNING, render_default_study  # noqa: E402
from _raytraced_summary import default_summary_lines  # noqa: E402


def main(args) -> None:
    jax.config.update("jax_enable_x64", args.x64)
    # the code the fits run with, read first: others may edit the checkout meanwhile
    fp = fingerprint()
    ours = library_dir() == FITS.parent / "jaxdof"
    git = git_state() if ours else "a copy outside this checkout (see the note)"
    render_secs = render_default_study()
    if args.render_only:
        return
    scenes = args.scenes or list(DEFAULT_SCENES)
    psnr_lines = psnr_default_section(scenes)
    t0 = time.perf_counter()
    records = run_default(scenes, args.x64, fp)
    fit_s = time.perf_counter() - t0
    halves = {
        "tuning": [s for s in TUNING if s in scenes],
        "held out": [s for s in HELD_OUT if s in scenes],
    }
    conditions = default_conditions(args.x64, render_secs, fp, git, args.note)
    lines = [
        "# The default call on ray-traced scenes, half held out (issue 20, item 7)",
        "",
        f"Produced by `{shlex.join(['python', 'fits/raytraced_default.py', *sys.argv[1:]])}` "
        "(the script's docstring gives the question, the method and how to re-run it).",
        "",
        *conditions,
        "",
        *default_method_lines(),
        "## Summary, per half",
        "",
        *default_summary_lines(records, halves),
        f"Fitting: {sum(r['seconds'] for r in records):.0f} s in all, as each fit was made "
        f"(this run {fit_s:.0f} s; cached fits are reused).",
        "",
        *default_scene_lines(),
        *sum_check_lines(),
        *psnr_lines,
    ]
    for half, names in halves.items():
        lines += [f"## Fits, {half} half", "", *default_fit_table(records, names)]
    tag = ("_x64" if args.x64 else "") + ("" if args.scenes is None else "_partial") + args.tag
    write_markdown(result_path("raytraced_default", tag=tag), lines)
    raw = dict(conditions=conditions, records=records)
    save_json(result_path("raytraced_default", "_raw.json", tag=tag), finite(raw), indent=1)
    print("\n".join(lines))


def finite(x):
    """JSON-safe: `inf` as the string "inf", NaN as null (a fit's record holds both)."""
    if isinstance(x, dict):
        return {k: finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [finite(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None if math.isnan(x) else ("inf" if x > 0 else "-inf")
    return x


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--x64", action="store_true", help="fit in float64")
    ap.add_argument("--render-only", action="store_true")
    ap.add_argument("--scenes", nargs="+", choices=list(DEFAULT_SCENES), metavar="SCENE")
    ap.add_argument("--tag", default="", help="suffix of the report's names, e.g. _pre_adequacy")
    ap.add_argument("--note", default="", help="a line for the report's conditions")
    return ap.parse_args(argv)


if __name__ == "__main__":
    main(parse_args())
