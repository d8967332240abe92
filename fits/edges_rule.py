"""The depth-edge rule on the ray-traced scenes' depth maps and on ramps (issue 33, item 2).

Question: does `jaxdof.depth_edges` (a step that neither surface beside it continues, in depth
and in inverse depth) keep the occlusion boundaries and drop the floors and ramps that the rule
before it (any relative step over 3 % between neighbours) called edges?

For every cached depth map of the ray-traced studies (`fits/.cache/raytraced/*_depth.npz`, made
by `python fits/raytraced_default.py --render-only`), the edge pixels of both rules, and how many
only the old one marks; then ramps of every steepness (linear in depth, and planes: linear in
inverse depth) of 8 to 1024 px spanning 1.1x to 1000x in depth, with and without a jump (depth
doubled) in the middle. Writes `fits/results/edges_rule.md`.

    python fits/edges_rule.py
"""

from __future__ import annotations

import pathlib

import numpy as np
from _common import CACHE, command, git_state, result_path, write_markdown

import jaxdof


def _old_rule(depth, jump: float = 0.03) -> np.ndarray:
    """The rule before issue 33: a relative step over `jump` between 4-neighbours."""
    d = np.asarray(depth, np.float64)
    edges = np.zeros(d.shape, bool)
    with np.errstate(invalid="ignore"):
        for lo, hi, a, b in (
            (d[:-1], d[1:], edges[:-1], edges[1:]),
            (d[:, :-1], d[:, 1:], edges[:, :-1], edges[:, 1:]),
        ):
            step = np.abs(lo - hi) > jump * np.minimum(lo, hi)
            a |= step
            b |= step
    return edges


def scenes() -> list[str]:
    lines = [
        "| depth map | pixels | old rule | new rule | both | old only | new only |",
        "|---|---|---|---|---|---|---|",
    ]
    for path in sorted(pathlib.Path(CACHE, "raytraced").glob("*_depth.npz")):
        with np.load(path) as z:
            d = z[z.files[0]]
        d = d[..., 0] if d.ndim == 3 else d
        old, new = _old_rule(d), jaxdof.depth_edges(d)
        lines.append(
            f"| {path.stem.removesuffix('_depth')} | {d.size} | {old.sum()} | {new.sum()} | "
            f"{(old & new).sum()} | {(old & ~new).sum()} | {(new & ~old).sum()} |"
        )
    return lines


def ramps() -> list[str]:
    lines = [
        "| ramp | width px | depth span | old rule: edges on the ramp | new rule: edges on the "
        "ramp | new rule: the jump found |",
        "|---|---|---|---|---|---|",
    ]
    for kind in ("linear in depth", "plane (linear in 1/depth)"):
        for n in (8, 32, 128, 1024):
            for span in (1.1, 3.0, 10.0, 1000.0):
                near, far = 1.0, span
                if kind.startswith("linear"):
                    ramp = np.linspace(near, far, n)
                else:
                    ramp = 1 / np.linspace(1 / near, 1 / far, n)
                x = np.arange(n)
                jump = np.where(x < n // 2, ramp, 2 * ramp)
                rows = lambda v: v[None].repeat(4, 0)  # noqa: E731
                old = int(_old_rule(rows(ramp))[0].sum())
                new = int(jaxdof.depth_edges(rows(ramp))[0].sum())
                e = jaxdof.depth_edges(rows(jump))[0]
                found = bool(e[n // 2 - 1] and e[n // 2])
                lines.append(
                    f"| {kind} | {n} | {span:g}x | {old} | {new} | {'yes' if found else 'no'} |"
                )
    return lines


def main() -> None:
    lines = [
        "# The depth-edge rule: jumps, not slopes (issue 33, item 2)",
        "",
        f"Produced by `{command('edges_rule.py')}` (the script's docstring gives the question "
        f"and the method); jaxdof source {git_state()}.",
        "",
        "## The ray-traced scenes' depth maps (128 x 128)",
        "",
        *scenes(),
        "",
        "## Ramps (per row; 'the jump found': both pixels of a doubling of depth in the middle)",
        "",
        *ramps(),
    ]
    path = write_markdown(result_path("edges_rule"), lines)
    print("\n".join(lines))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
