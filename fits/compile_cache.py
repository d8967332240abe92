"""What the persistent compilation cache saves a user of the command line (issue 37, item 1).

Question: `jaxdof fit` on the same files run again (a user calibrating a series of photos of one
size): how long does a fresh process take with the cache off (`--no-cache`, every program
compiled), with an empty cache (cold: compiled and written), and with the cache the cold run left
(warm: loaded)? And how long does each stage of the fit take (the stage lines the command prints
on stderr: "solving", "standard errors and the adequacy test", ...)?

Scene: `fullres.py`'s procedural ground plane, wall and boxes (16-bit PNG, float32 depth), at the
sizes asked (default 1.5 MP), with its lens and start; each run a fresh process (`python -m jaxdof
fit ... --json`), timed by wall clock. The runs go in turns (off, cold, warm; off, cold, warm;
...), each cold run with a new empty cache folder and the warm run after it on that folder, so a
shared machine's drift hits every mode alike; medians over `--repeats`.

Run:

    python fits/compile_cache.py                 # 1.5 MP, 3 repeats
    python fits/compile_cache.py --sizes 1.5 6 --repeats 2

Writes `fits/results/compile_cache.md`.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time

from _common import command, git_state, machine_info, result_path, write_markdown
from fullres import SIZES, make_scene, make_scenes_apart


_STAGE = re.compile(r"^  (.+): (\d+\.\d+) s \((\d+\.\d+) s\)$")


def run(sc: dict, cache: str | None) -> dict:
    """One `jaxdof fit` in a fresh process, with the cache folder `cache` (`None`: off)."""
    f, t = sc["files"], sc["truth"]
    argv = [sys.executable, "-m", "jaxdof", "fit", f["sharp"], f["depth"], f["photo"], "--json"]
    argv += ["--focal-length", "50mm", "--f-number", str(t["start_f_number"]), "--focus", "2m"]
    env = dict(os.environ)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    if cache is None:
        argv.append("--no-cache")
    else:
        env["JAXDOF_CACHE_DIR"] = cache
    t0 = time.perf_counter()
    proc = subprocess.run(argv, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    row: dict = dict(wall_s=wall, rc=proc.returncode, stages={})
    for line in proc.stderr.splitlines():
        m = _STAGE.match(line)
        if m:
            row["stages"][m.group(1)] = row["stages"].get(m.group(1), 0.0) + float(m.group(2))
    if proc.returncode in (0, 1):
        res = json.loads(proc.stdout)
        row.update(status=res["status"], err_d=res["focus_distance"] / t["focus_distance"] - 1)
    else:
        row["error"] = (proc.stderr.strip().splitlines() or ["?"])[-1]
    return row


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", nargs="+", default=["1.5"], choices=list(SIZES))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--tag", default="", help="suffix of the report's name")
    args = ap.parse_args(argv)
    lines = [
        "# The persistent compilation cache: `jaxdof fit` again on files of the same size",
        "",
        f"Produced by `{command('compile_cache.py', argv)}` (the script's docstring gives the "
        "question and the method).",
        "",
        *(f"- {k}: {v}" for k, v in machine_info().items()),
        f"- jaxdof source: {git_state()}",
        "",
        "| size | mode | median wall s | runs (s) | solving s (median) | other stages s | "
        "status | focus error |",
        "|---|---|---|---|---|---|---|---|",
    ]
    make_scenes_apart(args.sizes)
    for label in args.sizes:
        sc = make_scene(label)
        rows: dict[str, list[dict]] = {"off": [], "cold": [], "warm": []}
        for _ in range(args.repeats):
            rows["off"].append(run(sc, None))
            with tempfile.TemporaryDirectory() as folder:
                rows["cold"].append(run(sc, folder))
                rows["warm"].append(run(sc, folder))
            print(label, {k: round(v[-1]["wall_s"], 1) for k, v in rows.items()}, flush=True)
        medians = {}
        for mode, rs in rows.items():
            walls = [r["wall_s"] for r in rs]
            medians[mode] = statistics.median(walls)
            solving = statistics.median([r["stages"].get("solving", float("nan")) for r in rs])
            other = statistics.median(
                [sum(v for k, v in r["stages"].items() if k != "solving") for r in rs]
            )
            last = rs[-1]
            status = last.get("status", last.get("error", "?"))
            err = f"{100 * last['err_d']:+.3f} %" if "err_d" in last else "-"
            lines.append(
                f"| {label} MP | {mode} | {medians[mode]:.1f} | "
                + ", ".join(f"{w:.1f}" for w in walls)
                + f" | {solving:.1f} | {other:.1f} | {status} | {err} |"
            )
        lines.append(
            f"| {label} MP | warm / off | {medians['warm'] / medians['off']:.2f} | | | | | |"
        )
    lines += [
        "",
        "The stage times are those the command prints (`solving`: the compiled solves, "
        "compiling included where the cache has none; the others: the statistics, the nuisance "
        "tests); the rest of a run is reading the files, tracing and the host's choices.",
    ]
    path = write_markdown(result_path("compile_cache", tag=args.tag), lines)
    print(f"wrote {path}", file=sys.stderr)


if __name__ == "__main__":
    main()
