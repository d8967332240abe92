"""The default call on ray-traced scenes spoiled as real captures spoil them (issue 34, part 5).

Question: when the depth map or the photo is spoiled the way a real capture spoils it (holes in
the depth, a coarser depth sensor, a photo off by a fraction of a pixel, focus breathing, an
exposure error, a camera JPEG, vignetting, noise; one at a time), does
`fit_lens(image, depth, photo, init)` with nothing else passed still come back within 2 % in
focus distance and 5 % in blur scale K, and when it does not, does it say so (`success=False`,
or an exception) or miss silently (`success=True`, its error beyond 3 reported standard errors)?
Reported per half: the tuning scenes and the held-out ones (`HELD_OUT` in
`_raytraced_scenes.py`: no constant in jaxdof was tuned on them).

Method: the scenes of `raytraced_default.py` (`DEFAULT_SCENES`), one lens each
(`CAPTURE_LENSES` in `_captures_scenes.py`), the same start as that study (`default_init`:
f-number 1.5x the truth's, focus 20 % short or 20 m for a lens focused at infinity) and the same
verdicts (`default_record`); the spoils are in `_captures_scenes.py` (`CONDITIONS`). The shifted
and magnified photos are rendered again by Mitsuba (or the aperture sum) with the camera turned
or its field of view narrowed, never resampled.

Run (Mitsuba only to render what is not cached yet):

    python fits/captures.py                                   # every scene and condition
    python fits/captures.py --quick                           # slant and outside (tag _quick)
    python fits/captures.py --scenes slant --conditions jpeg  # a subset (tag _partial)
    python fits/captures.py --from-cache 780d1016f000 --tag _x  # report stored fits only

Renders are cached in `fits/.cache/raytraced/` beside the default study's; fits in
`fits/.cache/captures/<fingerprint>_f32/`, keyed by a hash of the imported jaxdof's source and
the scene and fit code: after a library change every fit runs again (108 fits), without one only
the report is rewritten. Writes `fits/results/captures.md` and `captures_raw.json`. Precision:
float32, as a new user calls it.
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
import time

import jax


jax.config.update("jax_enable_x64", True)  # as the modules below; main() sets the run's precision

import numpy as np  # noqa: E402
from _captures_scenes import (  # noqa: E402
    CAPTURE_LENSES,
    CONDITIONS,
    FIT_CACHE,
    capture_fingerprint,
    capture_fit,
    render_captures,
    verdict,
)
from _common import cached_json, git_state, result_path, save_json, write_markdown  # noqa: E402
from _raytraced_report import default_conditions, df_label, k_label  # noqa: E402
from _raytraced_scenes import DEFAULT_SCENES, HELD_OUT, TUNING  # noqa: E402
from raytraced_default import finite  # noqa: E402


QUICK_SCENES = ("slant", "outside")  # one scene of each half, both without depth edges: cheap
VERDICTS = ("within", "flagged", "silent", "raised", "covered")


def run(scenes, conditions, fp: str, fit: bool = True) -> list[dict]:
    """Every fit (cached per fingerprint), scene by scene: a scene's conditions share most of
    their compiled code. `fit=False`: only the cached fits, nothing fitted."""
    folder = FIT_CACHE / f"{fp}_f32"
    out = []
    for scene in scenes:
        for condition in conditions:
            if not fit and not (folder / f"{condition}__{scene}.json").exists():
                continue
            rec, computed = cached_json(
                folder / f"{condition}__{scene}.json",
                lambda c=condition, s=scene: capture_fit(c, s),
            )
            if computed:
                what = rec.get("exception") or (
                    f"{rec['status']}, focus {rec['focus_err']:+.2%}, K {rec['k_err']:+.2%}"
                )
                print(
                    f"  {condition} {scene}: {verdict(rec)}: {what[:160]} ({rec['seconds']:.0f} s)",
                    flush=True,
                )
            out.append(rec)
    return out


# ----------------------------------------------------------------------------- report


def counts(records) -> dict:
    c = {v: 0 for v in VERDICTS}
    for r in records:
        c[verdict(r)] += 1
    c["refused"] = sum(1 for r in records if verdict(r) == "within" and not r["success"])
    return c


def med_abs(records, key) -> str:
    """The median absolute error over the fits that returned, as a percentage ("-" if none)."""
    vals = [abs(r[key]) for r in records if "exception" not in r and math.isfinite(r[key])]
    return f"{np.median(vals):.2%}" if vals else "-"


def summary_lines(records, conditions, halves) -> list[str]:
    """Per condition a row per half and one for both: the verdicts' counts and median errors."""
    out = [
        "| condition | half | fits | within | flagged | silent | raised | covered | "
        "median abs focus err | median abs K err |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for condition in conditions:
        rows = [(h, names) for h, names in halves.items() if names]
        rows.append(("all", [s for names in halves.values() for s in names]))
        for half, names in rows:
            recs = [r for r in records if r["condition"] == condition and r["scene"] in names]
            c = counts(recs)
            within = f"{c['within']}" + (f" ({c['refused']} refused)" if c["refused"] else "")
            cells = [within] + [str(c[v]) for v in VERDICTS[1:]]
            label = f"**{half}**" if half == "all" else half
            out.append(
                f"| {condition} | {label} | {len(recs)} | {' | '.join(cells)} | "
                f"{med_abs(recs, 'focus_err')} | {med_abs(recs, 'k_err')} |"
            )
    return out + [""]


def compact_lines(records, conditions, halves) -> list[str]:
    """The summary in one row per condition: within / flagged / silent / raised (+ covered)."""
    halves = {h: names for h, names in halves.items() if names}
    head = " | ".join(f"{h} W/F/S/R (+C)" for h in [*halves, "all"])
    out = [f"| condition | {head} |", "|---" * (len(halves) + 2) + "|"]
    for condition in conditions:
        cells = []
        for names in [*halves.values(), [s for n in halves.values() for s in n]]:
            c = counts([r for r in records if r["condition"] == condition and r["scene"] in names])
            cells.append("/".join(str(c[v]) for v in VERDICTS[:4]) + f" (+{c['covered']})")
        out.append(f"| {condition} | {' | '.join(cells)} |")
    return out + [""]


def nuisance_text(nuisances) -> str:
    """Every entry of `FitResult.nuisances`, whatever it holds, as `name: key=value, ...`."""
    if not nuisances:
        return ""

    def value(v) -> str:
        if isinstance(v, float):
            return f"{v:.3g}"
        if isinstance(v, dict):
            return "{" + ", ".join(f"{k}={value(x)}" for k, x in v.items()) + "}"
        if isinstance(v, list):
            return value(v[0]) if len(v) == 1 else "[" + ", ".join(map(value, v)) + "]"
        return str(v)

    return "; ".join(
        f"{name}: " + ", ".join(f"{k}={value(v)}" for k, v in entry.items())
        if isinstance(entry, dict)
        else f"{name}: {entry}"
        for name, entry in nuisances.items()
    )


def fit_rows(records, scenes) -> list[str]:
    out = [
        "| condition | scene | A m | d_f m | K px | spoil | success / status | focus err | K err | "
        "se (focus power 1/m, K px) | abs err / se (focus, K) | inside 3 se | verdict | "
        "treatment | nuisances | s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in records:
        if r["scene"] not in scenes:
            continue
        a, d = r["a"], float(r["d"])
        head = (
            f"| {r['condition']} | {r['scene']} | {a} | {df_label(d)} | {k_label(a, d)} | "
            f"{r['spoil']} |"
        )
        if "exception" in r:
            out.append(
                head + f" raised: `{r['exception'][:200]}` | | | | | | **raised** | | | "
                f"{r['seconds']:.0f} |"
            )
            continue
        focus = f"u/u_near {r['focus_err']:+.2%}" if math.isinf(d) else f"{r['focus_err']:+.2%}"
        inside = max(r["focus_z"], r["k_z"]) <= 3
        out.append(
            head + f" {r['success']} / {r['status']} | {focus} | {r['k_err']:+.2%} | "
            f"{r['focus_power_se']:.3g}, {r['k_se']:.3g} | {r['focus_z']:.2g}, {r['k_z']:.2g} | "
            f"{'yes' if inside else 'no'} | {verdict(r)} | {r['treatment']} | "
            f"{nuisance_text(r['nuisances'])} | {r['seconds']:.0f} |"
        )
    return out + [""]


def findings(records) -> list[str]:
    """Every silent miss and every exception by name (exceptions grouped by message)."""
    out = []
    for r in records:
        if "exception" not in r and verdict(r) == "silent":
            out.append(
                f"- silent: {r['condition']} on {r['scene']}: focus {r['focus_err']:+.1%}, K "
                f"{r['k_err']:+.1%}, {r['focus_z']:.1f} and {r['k_z']:.1f} reported standard "
                f"errors off, success=True ({r['status']})"
            )
    raised: dict[str, list[str]] = {}
    for r in records:
        if "exception" in r:
            raised.setdefault(r["exception"][:200], []).append(f"{r['condition']}/{r['scene']}")
    for message, where in raised.items():
        out.append(f"- raised on {len(where)} ({', '.join(where)}): `{message}`")
    return out + [""] if out else []


def method_lines() -> list[str]:
    lenses = ", ".join(f"{s} ({a}, {df_label(d)})" for s, (a, d) in CAPTURE_LENSES.items())
    return [
        "The call: `jaxdof.fit_lens(image, depth, photo, init)`, nothing else, float32, on the "
        "128x128 RGB ray-traced scenes of `raytraced_default.py`, one lens each (A m, d_f m): "
        f"{lenses}. The start is that study's (f-number 1.5x the truth's, focus 20 % short; "
        "20 m for a lens focused at infinity), and so is the judgement: **within** focus "
        "distance within 2 % and K = f^2 / (2 N (d_f - f)) within 5 % (at infinity the focus "
        "power as a share of the nearest depth's and S = K d_f); **flagged** outside and "
        "success=False; **silent** outside, success=True and the focus power or K beyond 3 "
        "reported standard errors; **raised** an exception escaped `fit_lens` (caught here); "
        "**covered** (a fifth case the four do not name) outside, success=True and both errors "
        "within 3 reported standard errors. `refused`: within but success=False. The spoils, "
        "one at a time (seeded per scene and condition):",
        "",
        *[f"- **{k}**: {v}" for k, v in CONDITIONS.items()],
        "",
        "Details: the depth-edge band is placed by the library's own `jaxdof.depth_edges` (its "
        "far-side pixel of every edge, its near-side pixel at random half the time), the NaN "
        "blobs are smooth noise (sigma 3 px) above its 97th percentile, the zeros are isolated "
        "pixels outside both. The coarse depth is block-averaged in inverse depth (not sampled). "
        "The shift turns the camera about its centre (Mitsuba `look_at` target at (0.4, -0.6) "
        "/ f_px): 0.4 px right and 0.6 px up at the frame's centre, a little more towards the "
        "edges (a rotation, not a translation of the film); the magnified photo has "
        "tan(fov_x / 2) divided by 1.01. Both are Mitsuba thin-lens renders (1024 spp), or for "
        "`pentagon`, `lightfield` and `landscape` at infinity the aperture sum posed the same "
        "way (every view's eye turned with the rig; the principal-point offsets follow the "
        "longer focal length in pixels); with no turn and scale 1 both renderers reproduce the "
        "cached photos bit for bit. The `vignette` scene's photo keeps its cos^4 falloff in "
        "every condition (the `vignetting` condition multiplies it by the radial falloff too). "
        "The JPEG clips at 1 (the `outside` scene's bright strips exceed it). The 'spoil' "
        "column of the fits gives what each spoil did, and for the re-rendered photos the "
        "shift and scale measured against the unspoiled photo (least squares, cubic "
        "resampling, 16 px in from the frame).",
        "",
    ]


def main(args) -> None:
    jax.config.update("jax_enable_x64", False)  # float32, as a new user calls it
    t_start = time.perf_counter()
    # read first: others may edit the checkout meanwhile
    fp = args.from_cache or capture_fingerprint()
    git = git_state()
    if args.from_cache:
        git = f"the checkout now: {git}; the fits were made earlier, by the library of {fp}"
    scenes = list(QUICK_SCENES) if args.quick else (args.scenes or list(DEFAULT_SCENES))
    conditions = args.conditions or list(CONDITIONS)
    render_secs = render_captures(scenes)
    records = run(scenes, conditions, fp, fit=args.from_cache is None)
    scenes = [s for s in scenes if any(r["scene"] == s for r in records)]
    halves = {
        "tuning": [s for s in TUNING if s in scenes],
        "held out": [s for s in HELD_OUT if s in scenes],
    }
    wall = time.perf_counter() - t_start
    conds = default_conditions(False, render_secs, fp, git, args.note)
    cmd = shlex.join(["python", "fits/captures.py", *sys.argv[1:]])
    lines = [
        "# The default call on spoiled captures, half held out (issue 34, part 5)",
        "",
        f"Produced by `{cmd}` (the script's docstring gives the question, the method and how "
        f"to re-run it). This run: {wall:.0f} s wall; fitting {sum(r['seconds'] for r in records):.0f} "
        "s in all, as each fit was made (cached fits are reused).",
        "",
        *conds,
        "",
        *method_lines(),
        "## Summary",
        "",
        "Per condition, per half (W/F/S/R (+C): within / flagged / silent / raised, + covered):",
        "",
        *compact_lines(records, conditions, halves),
        *summary_lines(records, conditions, halves),
        *findings(records),
    ]
    for half, names in halves.items():
        if names:
            lines += [f"## Fits, {half} half", "", *fit_rows(records, names)]
    quick = args.quick
    full = quick or (args.scenes is None and args.conditions is None)
    tag = ("" if full else "_partial") + args.tag
    write_markdown(result_path("captures", quick=quick, tag=tag), lines)
    raw = dict(command=cmd, conditions=conds, records=records)
    save_json(result_path("captures", "_raw.json", quick=quick, tag=tag), finite(raw), indent=1)
    print("\n".join(compact_lines(records, conditions, halves)))
    print("\n".join(summary_lines(records, conditions, halves)))
    print("\n".join(findings(records)))
    print(f"wrote {result_path('captures', quick=quick, tag=tag)} ({wall:.0f} s)")


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--conditions", nargs="+", choices=list(CONDITIONS), metavar="CONDITION")
    ap.add_argument("--scenes", nargs="+", choices=list(DEFAULT_SCENES), metavar="SCENE")
    ap.add_argument("--quick", action="store_true", help=f"only {', '.join(QUICK_SCENES)}")
    ap.add_argument(
        "--from-cache",
        metavar="FINGERPRINT",
        help="report the fits cached under this fingerprint (another library's), fitting nothing",
    )
    ap.add_argument("--tag", default="", help="suffix of the report's names, e.g. _outside")
    ap.add_argument("--note", default="", help="a line for the report's conditions")
    return ap.parse_args(argv)


if __name__ == "__main__":
    main(parse_args())
