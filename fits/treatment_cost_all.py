"""Issue 21's cost goal on every ray-traced lens without depth edges: the default fit (`auto`)
against the previous default forced (`plain`: soft, no footprint, no edge weight), each as a
whole process (`treatment_cost.py`: import, compile, fit), in turns.

Question: does the default call cost at most 1.2x what the previous default costs, on scenes
whose depth map has no edge (`EDGE_FREE`: planes seen whole, with and without vignetting, a
pentagonal aperture, a texture near the sampling limit, light from outside the frame)?

Run from the checkout's root:

    python fits/treatment_cost_all.py               # 2 rounds, both variants per lens per round
    python fits/treatment_cost_all.py --rounds 3

Each round runs every lens's `plain` then `auto` process (alternating which comes first from
round to round, so that a drift in the machine's speed falls on both); per lens the ratio of the
medians. Writes `fits/results/treatment_cost_all.md` and `_raw.json`. About 20 s per lens and
round on 2 shared cores.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time

from _common import FITS, command, git_state, load_average, result_path, save_json, write_markdown
from _raytraced_scenes import default_lenses


# The scenes of `_raytraced_scenes.DEFAULT_SCENES` whose depth map has no edge in the frame
# (the default call's treatment on them: footprint and border only, `raytraced_default.md`).
EDGE_FREE = ("slant", "vignette", "outside", "pentagon", "texture")
GOAL = 1.2


def _one(scene: str, a: float, d: float, variant: str) -> dict:
    """One whole process: its wall time as seen from here, and what it printed."""
    args = [sys.executable, str(FITS / "treatment_cost.py"), scene, str(a), str(d), variant]
    t = time.perf_counter()
    out = subprocess.run(args, cwd=FITS, capture_output=True, text=True, check=True)
    wall = time.perf_counter() - t
    return {**json.loads(out.stdout.strip().splitlines()[-1]), "process_s": wall}


def main(rounds: int) -> None:
    lenses = [(s, a, d) for s in EDGE_FREE for a, d in default_lenses(s)]
    start_load = load_average()
    runs: list[dict] = []
    for k in range(rounds):
        for scene, a, d in lenses:
            order = ("plain", "auto") if k % 2 == 0 else ("auto", "plain")
            for variant in order:
                r = _one(scene, a, d, variant)
                runs.append({**r, "round": k})
                print(f"round {k} {scene} {a} {d} {variant}: {r['process_s']:.2f} s", flush=True)
    rows, ratios = [], []
    for scene, a, d in lenses:
        mine = [r for r in runs if (r["scene"], r["a"], r["d"]) == (scene, a, d)]
        med = {
            v: statistics.median(r["process_s"] for r in mine if r["variant"] == v)
            for v in ("plain", "auto")
        }
        steps = {v: [r["steps"] for r in mine if r["variant"] == v][0] for v in med}
        ratio = med["auto"] / med["plain"]
        ratios.append(ratio)
        treat = [r["treatment"] for r in mine if r["variant"] == "auto"][0]
        rows.append(
            f"| {scene} | {a:g} | {d:g} | {med['plain']:.2f} | {med['auto']:.2f} | "
            f"**{ratio:.2f}x** | {steps['plain']} / {steps['auto']} | {treat} |"
        )
    worst = max(ratios)
    lines = [
        "# The default fit's cost on scenes without depth edges (issue 21)",
        "",
        f"`{command('treatment_cost_all.py')}` at {git_state()}; load average at start "
        f"{start_load}, at end {load_average()}. {rounds} rounds; each cell is the median "
        "wall time of whole processes (`python fits/treatment_cost.py SCENE A D VARIANT`: "
        "import, compile, fit), `plain` the previous default forced (`method='soft', "
        "footprint=False, edge_weight=False`) with this library, `auto` the default call.",
        "",
        f"Goal: auto at most {GOAL}x plain on every lens. Median ratio "
        f"**{statistics.median(ratios):.2f}x**, worst **{worst:.2f}x**; "
        f"{sum(r <= GOAL for r in ratios)} of {len(ratios)} lenses within the goal.",
        "",
        "| scene | A (m) | d_f (m) | plain (s) | auto (s) | auto / plain | steps (plain / auto) "
        "| auto's treatment |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
    ]
    print(write_markdown(result_path("treatment_cost_all"), lines))
    save_json(result_path("treatment_cost_all", "_raw.json"), {"runs": runs}, indent=1)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=2)
    main(parser.parse_args().rounds)
