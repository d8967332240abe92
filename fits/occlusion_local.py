"""Occlusion treatments against ray-traced truth: `Soft`, `Occlusion` (global depth layers) and
`LocalOcclusion` (per-pair, local) side by side, overall and near depth edges, and their cost.

Question (issue 21, deliverable 1): which occlusion model is closest to a real thin lens where
depth edges are, including scenes whose depth histogram has no gap (a ground plane connecting
near and far), and what does it cost against the soft filter at the same window?

Every row renders the cached Mitsuba scene's pinhole image and z-depth through the true lens
(`_raytraced_scenes.true_lens`) with each method and compares with the ray-traced thin-lens photo
over the interior (a border of the largest circle + 2 px left out), overall and within 2 px of a
depth edge (`jaxdof.depth_edges`). `ground` is held out of any tuning (`HELD_OUT`): reported apart.
The cost is the median of 5 jitted renders per method at the row's window, as a ratio to `Soft`.

Run: `python fits/occlusion_local.py` (renders what is not cached yet; Mitsuba is the optional
`validate` extra). Writes `fits/results/occlusion_local.md`.
"""

from __future__ import annotations

import sys
import time

import jax
import numpy as np


jax.config.update("jax_enable_x64", False)

from _common import command, git_state, machine_info, result_path  # noqa: E402
from _raytraced_fits import interior  # noqa: E402
from _raytraced_report import edge_distance, psnr  # noqa: E402
from _raytraced_scenes import DEFAULT_LENSES, HELD_OUT, default_inputs, true_lens  # noqa: E402

import jaxdof  # noqa: E402
from jaxdof.internal import LocalOcclusion  # noqa: E402


METHODS = {
    "soft": jaxdof.Soft(),
    "occlusion": jaxdof.Occlusion(),
    "local": LocalOcclusion(),
}
SCENES = ("planes", "occluders", "ground")


def _timed(fn, *args, rounds: int = 5) -> float:
    jax.block_until_ready(fn(*args))  # compile
    times = []
    for _ in range(rounds):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def row(name: str, a: float, d: float, pin, z, target) -> dict:
    lens = true_lens(a, d)
    r = np.asarray(jaxdof.coc_radius(z, lens))
    window = float(np.ceil(r.max()) + 1)
    keep = interior(z.shape, int(np.ceil(r.max())) + 2)
    near = keep & (edge_distance(z) < 2)
    out = dict(scene=name, A=a, d_f=d, K=float(np.max(r)), edge_px=int(near.sum()))
    for key, method in METHODS.items():
        fn = jax.jit(
            lambda im, zz, m=method: jaxdof.render(im, zz, lens, method=m, max_radius=window)
        )
        img = np.asarray(fn(pin, z))
        out[f"{key}_all"] = psnr(img, target, keep[..., None].repeat(3, -1))
        out[f"{key}_edge"] = (
            psnr(img, target, near[..., None].repeat(3, -1)) if near.sum() else np.nan
        )
        out[f"{key}_s"] = _timed(fn, pin, z)
    return out


def _cell(r: dict, where: str) -> str:
    return " / ".join(f"{r[f'{k}_{where}']:.2f}" for k in METHODS)


def report(rows: list[dict], path) -> None:
    info = machine_info()
    lines = [
        "# Occlusion treatments against ray-traced truth",
        "",
        f"Command: `{command('occlusion_local.py')}` ({git_state()}). PSNR (dB, peak 1) of "
        "`render(pinhole, z, true lens, method=...)` against the Mitsuba thin-lens photo, over the "
        "interior and within 2 px of a depth edge; cost: median jitted render time as a ratio to "
        "`Soft` at the same window.",
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
        lines += [
            f"## {title}",
            "",
            "| scene | A | d_f | largest circle px | edge px | all: soft / occlusion / local | "
            "edge: soft / occlusion / local | cost occlusion / local (x soft) |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in rows:
            if r["scene"] not in names:
                continue
            lines.append(
                f"| {r['scene']} | {r['A']} | {r['d_f']} | {r['K']:.1f} | {r['edge_px']} | "
                f"{_cell(r, 'all')} | {_cell(r, 'edge')} | {r['occlusion_s'] / r['soft_s']:.2f} / "
                f"{r['local_s'] / r['soft_s']:.2f} |"
            )
        lines.append("")
    path.write_text("\n".join(lines) + "\n")


def main() -> None:
    rows = []
    for name in SCENES:
        for a, d in DEFAULT_LENSES:
            pin, z, target = default_inputs(name, a, d)
            rows.append(row(name, a, d, np.asarray(pin, np.float32), z, target))
            print(rows[-1], flush=True)
    report(rows, result_path("occlusion_local"))


if __name__ == "__main__":
    sys.exit(main())
