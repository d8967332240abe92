"""The footprint correction's fourth-order terms: the transfer function, and the ray-traced fits.

    python fits/footprint_order.py                 # both sections (~10 s after the default study)

**Question.** `jaxdof.footprint_prefilter` used to match the lens's blur to second order only (the
variance, `c_1(r)` and the Laplacian). Does adding the two fourth-order terms fitted to the disc's
transfer function (`c_2`, `c_3`, `jaxdof/_footprint_table.py`) bring the render closer to the
lens, and does that move the default fit on ray-traced photos?

**Method.**
1. Transfer function, per radius: the impulse response of `coc_filter(prefilter(delta, r), r)` on
   a 64 x 64 frame, its discrete Fourier transform against the disc's `2 J_1(r|w|) / (r|w|)`:
   root mean square and largest error over the band `|w| <= pi`, for no correction, the
   second-order correction alone (built here from `jaxdof.internal.footprint_coefficient`) and
   `jaxdof.footprint_prefilter` (both orders). The fourth-order coefficients are least-squares
   fits of exactly this error, so section 1 shows what the fit achieved, not independent evidence.
2. The independent evidence: `fit_lens(image, depth, photo, init)`, every default, on the
   ray-traced scenes of `fits/raytraced_default.py`, before (`raytraced_default_second_order_raw.json`,
   that study's run at the last commit with the second-order correction) and after
   (`raytraced_default_raw.json`, run with the fourth-order terms). The tuning and held-out halves
   apart (`TUNING`, `HELD_OUT` in `_raytraced_scenes.py`); nothing about the coefficients was
   chosen from these scenes.
"""

from __future__ import annotations

import sys

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import RESULTS, command, git_state, load_json, versions_line, write_markdown  # noqa: E402
from _raytraced_scenes import HELD_OUT, TUNING  # noqa: E402
from scipy.special import j1  # noqa: E402

import jaxdof  # noqa: E402
from jaxdof.internal import footprint_coefficient  # noqa: E402


RADII = (0.1, 0.3, 0.5, 0.6, 0.8, 1.0, 1.2, 1.5, 2.0, 2.5, 3.0, 4.0, 6.0)
N = 64


def _laplacian(x):
    p = jnp.pad(x, 1, mode="edge")
    return p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:] - 4 * x


@jax.jit
def responses(r):
    """Impulse responses `(none, second order, both orders)` for a uniform circle `r`."""
    delta = jnp.zeros((N, N)).at[N // 2, N // 2].set(1.0)
    radius = jnp.full((N, N), r)

    def spread(x):
        return jaxdof.coc_filter(x, radius, max_radius=7.0)

    second = delta - footprint_coefficient(radius) * _laplacian(delta)
    return spread(delta), spread(second), spread(jaxdof.footprint_prefilter(delta, radius))


def transfer_rows() -> list[dict]:
    w = 2 * np.pi * np.fft.fftfreq(N)
    wx, wy = np.meshgrid(w, w, indexing="ij")
    rho = np.hypot(wx, wy)
    band = rho <= np.pi
    rows = []
    for r in RADII:
        x = np.maximum(r * rho, 1e-12)
        disc = np.where(r * rho > 1e-9, 2 * j1(x) / x, 1.0)
        row = dict(r=r)
        for name, kernel in zip(("none", "second", "fourth"), responses(r)):
            k = np.real(np.fft.fft2(np.fft.ifftshift(np.asarray(kernel))))
            err = (k - disc)[band]
            row[name] = (float(np.sqrt(np.mean(err**2))), float(np.max(np.abs(err))))
        rows.append(row)
    return rows


def _fits(path) -> dict:
    return {(r["scene"], r["a"], r["d"]): r for r in load_json(path)["records"]}


def fit_lines(before: dict, after: dict) -> list[str]:
    out = [
        "| scene | half | A m | d_f m | focus err before | after | K err before | after | within before | after |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    counts = {h: [0, 0, 0] for h in ("tuning", "held out")}
    for key in sorted(after, key=lambda k: k[0] in HELD_OUT):  # stable: the study's order
        if key not in before:
            continue
        b, a = before[key], after[key]
        half = "held out" if key[0] in HELD_OUT else "tuning"
        if key[0] not in TUNING + HELD_OUT:
            continue
        counts[half][0] += 1
        counts[half][1] += bool(b.get("within"))
        counts[half][2] += bool(a.get("within"))

        def pct(x):
            return "exception" if x is None else f"{100 * x:+.2f}%"

        out.append(
            f"| {key[0]} | {half} | {key[1]:g} | {key[2]} | {pct(b.get('focus_err'))} | "
            f"{pct(a.get('focus_err'))} | {pct(b.get('k_err'))} | {pct(a.get('k_err'))} | "
            f"{'yes' if b.get('within') else 'no'} | {'yes' if a.get('within') else 'no'} |"
        )
    summary = [
        f"- {h}: {c[1]} of {c[0]} lenses within (focus 2 %, K 5 %) before, {c[2]} after."
        for h, c in counts.items()
    ]
    return summary + [""] + out


def main() -> int:
    rows = transfer_rows()
    lines = [
        "# The footprint correction to fourth order",
        "",
        f"Produced by `{command('footprint_order.py')}` (its docstring gives the question and the "
        "method).",
        "",
        f"- {versions_line()}",
        f"- jaxdof source: {git_state()}",
        "",
        "## 1. Transfer function against the disc's (root mean square / largest error over |w| <= pi)",
        "",
        "| r px | no correction | second order (c_1) | both orders (footprint_prefilter) |",
        "|---|---|---|---|",
    ]
    for row in rows:
        cells = " | ".join(
            f"{row[k][0]:.4f} / {row[k][1]:.3f}" for k in ("none", "second", "fourth")
        )
        lines.append(f"| {row['r']:g} | {cells} |")
    before = RESULTS / "raytraced_default_second_order_raw.json"
    after = RESULTS / "raytraced_default_raw.json"
    lines += [
        "",
        "## 2. The default fit on the ray-traced scenes, before and after",
        "",
        f"Before: `{before.name}`; after: `{after.name}` (the full reports: "
        "`raytraced_default_second_order.md`, `raytraced_default.md`). Errors signed; "
        "**within**: focus distance within 2 % and blur scale K within 5 %.",
        "",
    ]
    lines += fit_lines(_fits(before), _fits(after))
    path = write_markdown(RESULTS / "footprint_order.md", lines)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
