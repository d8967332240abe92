"""Occlusion treatments against ray-traced truth: `Soft`, `Occlusion` (global depth layers) and
`LocalOcclusion` (per-pair, local) without and with its fill of hidden surfaces, side by side,
overall and near depth edges, and their cost.

Question (issue 21, deliverable 1): which occlusion model is closest to a real thin lens where
depth edges are, including scenes whose depth histogram has no gap (a ground plane connecting
near and far), and what does it cost against the soft filter at the same window?

Every row renders the cached Mitsuba scene's pinhole image and z-depth through the true lens
(`_raytraced_scenes.true_lens`) with each method and compares with the ray-traced thin-lens photo
over the interior (a border of the largest circle + 2 px left out), overall and within 2 px of a
depth edge (`jaxdof.depth_edges`), each scene at its lenses (`default_lenses`). `ground` and `fgbg`
are held out of any tuning (`HELD_OUT`): reported apart.
The cost is the jitted render time per method at the row's window, as a ratio to `Soft`: the
methods are timed in turns (a change of the machine's load hits all alike), 25 rounds of one batch
of back-to-back calls each (`_common.per_call`), and the fastest round counts (on the shared
2-core machine a median of a few calls, as this study took before, put the same kernel at 1.0x to
5.2x the soft filter from one row to the next; the fastest round is the one least disturbed).

Run: `python fits/occlusion_local.py` (renders what is not cached yet; Mitsuba is the optional
`validate` extra). Writes `fits/results/occlusion_local.md`.
"""

from __future__ import annotations

import sys

import jax
import numpy as np


jax.config.update("jax_enable_x64", False)

from _common import (  # noqa: E402
    calls_per_sample,
    command,
    git_state,
    machine_info,
    per_call,
    result_path,
)
from _raytraced_fits import interior  # noqa: E402
from _raytraced_report import edge_distance, psnr  # noqa: E402
from _raytraced_scenes import HELD_OUT, default_inputs, default_lenses, true_lens  # noqa: E402

import jaxdof  # noqa: E402
from jaxdof import LocalOcclusion  # noqa: E402


METHODS = {
    "soft": jaxdof.Soft(),
    "occlusion": jaxdof.Occlusion(),
    "local": LocalOcclusion(fill=False),
    "local+fill": LocalOcclusion(),
}
# planes and occluders tune; ground (objects standing on a floor) and fgbg (a card before a wall,
# focused on either) are held out, fgbg added after every constant of the fill was chosen.
SCENES = ("planes", "occluders", "ground", "fgbg")
ROUNDS = 25  # timing rounds (each times every method once, in turns)


def fastest_in_turns(timers, rounds: int = ROUNDS) -> list[float]:
    """Seconds per call of each `(fn, args, calls)`: the fastest of `rounds` batched samples,
    taken in turns."""
    best = [float("inf")] * len(timers)
    for _ in range(rounds):
        for i, (fn, args, calls) in enumerate(timers):
            best[i] = min(best[i], per_call(fn, args, calls))
    return best


def row(name: str, a: float, d: float, pin, z, target) -> dict:
    lens = true_lens(a, d)
    r = np.asarray(jaxdof.coc_radius(z, lens))
    window = float(np.ceil(r.max()) + 1)
    keep = interior(z.shape, int(np.ceil(r.max())) + 2)
    near = keep & (edge_distance(z) < 2)
    out = dict(scene=name, A=a, d_f=d, K=float(np.max(r)), edge_px=int(near.sum()))
    timers = []
    for key, method in METHODS.items():
        fn = jax.jit(
            lambda im, zz, m=method: jaxdof.render(im, zz, lens, method=m, max_radius=window)
        )
        img = np.asarray(fn(pin, z))
        out[f"{key}_all"] = psnr(img, target, keep[..., None].repeat(3, -1))
        out[f"{key}_edge"] = (
            psnr(img, target, near[..., None].repeat(3, -1)) if near.sum() else np.nan
        )
        timers.append((fn, (pin, z), calls_per_sample(fn, pin, z)[1]))
    for key, secs in zip(METHODS, fastest_in_turns(timers)):
        out[f"{key}_s"] = secs
    return out


def _cell(r: dict, where: str) -> str:
    return " / ".join(f"{r[f'{k}_{where}']:.2f}" for k in METHODS)


def _cost(r: dict) -> str:
    return " / ".join(f"{r[f'{k}_s'] / r['soft_s']:.2f}" for k in METHODS if k != "soft")


def _mean_cell(rows: list[dict], where: str) -> str:
    return " / ".join(f"{np.mean([r[f'{k}_{where}'] for r in rows]):.2f}" for k in METHODS)


def report(rows: list[dict], path) -> None:
    info = machine_info()
    lines = [
        "# Occlusion treatments against ray-traced truth",
        "",
        f"Command: `{command('occlusion_local.py')}` ({git_state()}). PSNR (dB, peak 1) of "
        "`render(pinhole, z, true lens, method=...)` against the Mitsuba thin-lens photo, over the "
        "interior and within 2 px of a depth edge; cost: jitted render time as a ratio to `Soft` "
        "at the same window (the fastest of 25 rounds timed in turns). `occlusion`: "
        "`jaxdof.Occlusion()` (global depth layers, hidden background filled by the nearest "
        "visible pixel); `local`: `LocalOcclusion(fill=False)` (per-pair occlusion, only the light "
        "the pinhole image shows); `local+fill`: `LocalOcclusion()` (with the hidden surfaces "
        "filled, `jaxdof/_filters/local_occlusion.py`).",
        "",
        "| | |",
        "|---|---|",
        *[f"| {k} | {v} |" for k, v in info.items()],
        "",
    ]
    for title, names in (
        ("Tuning scenes", [s for s in SCENES if s not in HELD_OUT]),
        ("Held out (never tuned on)", [s for s in SCENES if s in HELD_OUT]),
    ):
        names_methods = " / ".join(METHODS)
        lines += [
            f"## {title}",
            "",
            f"| scene | A | d_f | largest circle px | edge px | all: {names_methods} | "
            f"edge: {names_methods} | edge: local+fill - occlusion (dB) | cost "
            f"{' / '.join(k for k in METHODS if k != 'soft')} (x soft) |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for r in rows:
            if r["scene"] not in names:
                continue
            lines.append(
                f"| {r['scene']} | {r['A']} | {r['d_f']} | {r['K']:.1f} | {r['edge_px']} | "
                f"{_cell(r, 'all')} | {_cell(r, 'edge')} | "
                f"{r['local+fill_edge'] - r['occlusion_edge']:+.2f} | {_cost(r)} |"
            )
        for name in names:
            mine = [r for r in rows if r["scene"] == name]
            gain = np.mean([r["local+fill_edge"] - r["occlusion_edge"] for r in mine])
            lines.append(
                f"| **{name} mean** | | | | | {_mean_cell(mine, 'all')} | "
                f"{_mean_cell(mine, 'edge')} | {gain:+.2f} | |"
            )
        lines.append("")
    path.write_text("\n".join(lines) + "\n")


def main() -> None:
    rows = []
    for name in SCENES:
        for a, d in default_lenses(name):
            pin, z, target = default_inputs(name, a, d)
            rows.append(row(name, a, d, np.asarray(pin, np.float32), z, target))
            print(rows[-1], flush=True)
    report(rows, result_path("occlusion_local"))


if __name__ == "__main__":
    sys.exit(main())
