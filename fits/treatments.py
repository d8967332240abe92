"""The automatic treatment against each forced one, on every ray-traced scene (issue 21, item 4).

Question: `fit_lens(image, depth, photo, init)` chooses per scene whether to render occlusion,
weight the depth edges down and correct the pixel footprint (`jaxdof/_scene.py`). Is
its choice as good as the best forced choice on each scene, and better than the plain model?
Reported per half (`HELD_OUT` in `_raytraced_scenes.py`: no rule was tuned on them).

Method: the default-call study's scenes, lenses and start (`raytraced_default.py`: f-number 1.5x
the truth's, focus 20 % short), fitted with every default (`auto`) and with the treatment
forced through `fit_lens`'s `method`, `footprint` and `edge_weight` (the border is always left
out). Per scene and variant: lenses within (2 %, 5 %), silent misses (success, outside, an
error beyond 3 reported standard errors), median |errors| and the median wall time per fit
(compiling included). Fits are cached per library fingerprint and variant
(`fits/.cache/raytraced/default/`; the `auto` ones are `raytraced_default.py`'s).

Run: `python fits/treatments.py [--variants auto plain ...] [--scenes ...] [--lenses 2 ...]`. Writes
`fits/results/treatments.md` and `_raw.json`.
"""

from __future__ import annotations

import argparse
import shlex
import sys

import jax


jax.config.update("jax_enable_x64", True)  # as the modules below; main() sets float32

import numpy as np  # noqa: E402
from _common import git_state, result_path, save_json, write_markdown  # noqa: E402
from _raytraced_fits import fingerprint, run_default  # noqa: E402
from _raytraced_report import default_conditions  # noqa: E402
from _raytraced_scenes import DEFAULT_SCENES, HELD_OUT, TUNING, render_default_study  # noqa: E402
from raytraced_default import finite  # noqa: E402


VARIANTS = {
    "auto": {},
    "plain": dict(method="soft", footprint=False, edge_weight=False),
    "footprint": dict(method="soft", footprint=True, edge_weight=False),
    "edge + footprint": dict(method="soft", footprint=True, edge_weight=True),
    # the occlusion model the automatic choice uses (`jaxdof.LocalOcclusion`)
    "occlusion + footprint": dict(method="local_occlusion", footprint=True, edge_weight=False),
    "occlusion + edge + footprint": dict(
        method="local_occlusion", footprint=True, edge_weight=True
    ),
    # the global depth layers (`jaxdof.Occlusion`), the earlier occlusion model
    "layers + edge + footprint": dict(method="occlusion", footprint=True, edge_weight=True),
}


def _tag(name: str) -> str:
    return "" if name == "auto" else "_" + name.replace(" + ", "+").replace(" ", "")


def cell(recs) -> str:
    """`within / lenses (silent) med|focus| med|K| s`."""
    ok = [r for r in recs if "exception" not in r]
    n_in = sum(bool(r["within"]) for r in ok)
    silent = sum(bool(r["silent"]) for r in ok)
    exc = len(recs) - len(ok)
    f = np.median([abs(r["focus_err"]) for r in ok]) if ok else np.nan
    k = np.median([abs(r["k_err"]) for r in ok]) if ok else np.nan
    s = np.median([r["seconds"] for r in recs])
    extra = (f", {silent} silent" if silent else "") + (f", {exc} exc" if exc else "")
    return f"{n_in}/{len(recs)}{extra}; {f:.1%}, {k:.1%}; {s:.0f} s"


def main(args) -> None:
    jax.config.update("jax_enable_x64", False)
    fp = fingerprint()
    render_secs = render_default_study()
    scenes = args.scenes or list(DEFAULT_SCENES)
    results = {}
    for name in args.variants:
        print(name, flush=True)
        results[name] = run_default(
            scenes, False, fp, _tag(name), VARIANTS[name] or None, args.lenses
        )
    lines = [
        "# The automatic treatment against each forced one (issue 21, item 4)",
        "",
        f"Produced by `{shlex.join(['python', 'fits/treatments.py', *sys.argv[1:]])}` (the "
        "script's docstring gives the question and the method).",
        "",
        *default_conditions(False, render_secs, fp, git_state(), ""),
        "",
        "Each cell: lenses within (focus 2 %, K 5 %) / lenses (silent misses, exceptions); median "
        "|focus error|, median |K error|; median seconds per fit. Variants: `auto` is the "
        "default call; the others force `fit_lens(method=..., footprint=..., edge_weight=...)` "
        "(`local_occlusion` is the occlusion model the default chooses, `occlusion` the global "
        "depth layers): " + "; ".join(f"**{k}** `{v}`" for k, v in VARIANTS.items() if v) + ".",
        "",
        "Lenses fitted per scene: "
        + (
            "all four."
            if args.lenses is None
            else f"indices {args.lenses} of each scene's four (`default_lenses`), one run's "
            "time on a shared 2-core machine being what it is."
        ),
        "",
    ]
    for half, names in (("tuning", TUNING), ("held out", HELD_OUT)):
        names = [s for s in names if s in scenes]
        lines += [
            f"## {half.capitalize()} half",
            "",
            "| scene | " + " | ".join(args.variants) + " | auto's treatment (per lens) |",
            "|---|" + "---|" * (len(args.variants) + 1),
        ]
        for scene in [*names, "all"]:
            row = []
            for name in args.variants:
                recs = [r for r in results[name] if r["scene"] == scene or scene == "all"]
                recs = [r for r in recs if r["scene"] in names]
                row.append(cell(recs))
            chosen = ""
            if scene != "all" and "auto" in results:
                chosen = "; ".join(
                    r.get("treatment", "") for r in results["auto"] if r["scene"] == scene
                )
            lines.append(f"| {scene} | " + " | ".join(row) + f" | {chosen} |")
        lines.append("")
    write_markdown(result_path("treatments", tag=args.tag), lines)
    save_json(result_path("treatments", "_raw.json", tag=args.tag), finite(results), indent=1)
    print("\n".join(lines))


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    ap.add_argument("--scenes", nargs="+", choices=list(DEFAULT_SCENES), metavar="SCENE")
    ap.add_argument(
        "--lenses",
        nargs="+",
        type=int,
        metavar="I",
        help="indices into each scene's lenses (`default_lenses`: 0-3) to fit; default all",
    )
    ap.add_argument("--tag", default="")
    return ap.parse_args(argv)


if __name__ == "__main__":
    main(parse_args())
