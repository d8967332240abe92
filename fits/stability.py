"""Numerical stability at the extremes: float32 against float64, and the fit's conditioning.

Questions:

1. How large is the float32 error of `circle_pixel_overlap` at radii from 1e-8 to 1000 px, against
   the `2e-6 max(1, r)` (pixel areas) bound we promise, and against the textbook
   inclusion-exclusion of quadrant antiderivatives evaluated in float32?
2. How far are float32 values and gradients of `render`, and of a fit's loss, from float64 at the
   extremes (depth at the focus plane, at infinity, just beyond the focal length; focus distance
   just beyond the focal length; f/1e4; radii far above max_radius)?
3. How well conditioned is the fit's normal matrix `J^T J` (free focus distance and f-number, log
   coordinates, columns scaled to unit norm) as the focus distance approaches the focal length and
   as the scene's depth range shrinks?
4. What does the run-time input check (`equinox.error_if`) cost under jit?

Run: `python fits/stability.py` (about a minute on a laptop CPU). Writes
`fits/results/stability.md` and `fits/results/stability.png`, and asserts the overlap bound.
"""

from __future__ import annotations

import argparse
import math
import time

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402
import numpy as np  # noqa: E402


matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from _common import result_path, versions_line, write_markdown  # noqa: E402

# Semi-internal: the filter without the run-time input checks, and the textbook overlap formula.
from _textbook import textbook_overlap  # noqa: E402

import jaxdof  # noqa: E402
from jaxdof import ThinLens, circle_pixel_overlap, coc_filter, render  # noqa: E402
from jaxdof.internal import soft_filter  # noqa: E402


SEED = 0


# --------------------------------------------------------------------------------------------
# 1. circle_pixel_overlap in float32


def overlap_study(n_radii=45, n_squares=4000):
    rng = np.random.default_rng(SEED)
    radii = np.logspace(-8, 3, n_radii)
    ours = jax.jit(circle_pixel_overlap)  # one compile per dtype: float32 under test, float64 ref
    text32 = jax.jit(textbook_overlap)  # valid in the first quadrant: squares below
    rows = []
    for r in radii:
        r32 = np.float32(r)
        ang = rng.uniform(0, 2 * np.pi, n_squares)
        if r >= 1:  # squares whose centres lie within 1.2 px of the circle
            rho = r + rng.uniform(-1.2, 1.2, n_squares)
            dx, dy = rho * np.cos(ang), rho * np.sin(ang)
        else:  # tiny discs: squares with an edge or a corner through the disc, and any square
            half = n_squares // 2
            dx = np.concatenate(
                [
                    rng.choice([-0.5, 0.5], half) + rng.uniform(-1.2, 1.2, half) * r,
                    rng.uniform(-1.5, 1.5, n_squares - half),
                ]
            )
            dy = np.concatenate(
                [
                    rng.choice([-0.5, 0.5], half) + rng.uniform(-1.2, 1.2, half) * r,
                    rng.uniform(-1.5, 1.5, n_squares - half),
                ]
            )
        # the textbook form needs squares in the first quadrant: lower-left corner (cx, cy) >= 0
        # within reach of the circle
        reach = r + rng.uniform(-1.2, 1.2, n_squares) if r >= 1 else rng.uniform(0, r, n_squares)
        q_ang = rng.uniform(0, np.pi / 2, n_squares)
        qx = np.maximum(reach * np.cos(q_ang), 0) + 0.5
        qy = np.maximum(reach * np.sin(q_ang), 0) + 0.5
        errs = []
        for x, y in ((dx, dy), (qx, qy)):
            x32, y32, rr = x.astype(np.float32), y.astype(np.float32), np.full(x.shape, r32)
            # the float64 formula at the float32 inputs is the reference (it is validated against
            # 30-digit quadrature in tests/test_overlap.py)
            exact = np.asarray(ours(*(a.astype(np.float64) for a in (x32, y32, rr))))
            errs.append((np.asarray(ours(x32, y32, rr), np.float64), exact, (x32, y32, rr)))
        err = max(float(np.max(np.abs(a - b))) for a, b, _ in errs)
        _, exact_q, args_q = errs[1]
        with np.errstate(invalid="ignore"):
            t_err = np.abs(np.asarray(text32(*args_q), np.float64) - exact_q)
        rows.append(
            dict(
                r=float(r32),
                err=err,
                rel_area=err / (np.pi * float(r32) ** 2),
                bound=2e-6 * max(1.0, float(r32)),
                textbook=float(np.nanmax(t_err)) if not np.all(np.isnan(t_err)) else float("nan"),
                textbook_nan=int(np.isnan(t_err).sum()),
            )
        )
    return rows


# --------------------------------------------------------------------------------------------
# 2. render and a fit's loss, float32 against float64


def _scene(h=16, w=16):
    rng = np.random.default_rng(SEED)
    image = rng.uniform(size=(h, w, 3))
    depth = np.where(np.arange(w)[None, :] < w // 2, 1.5, 6.0) + np.zeros((h, 1))
    return image, depth


EXTREMES = {
    # name: (depth map transform, lens (f, N, d_f, pitch))
    "ordinary": (lambda d: d, (0.05, 2.0, 3.0, 6e-5)),
    "depth at focus plane": (lambda d: np.full_like(d, 3.0), (0.05, 2.0, 3.0, 6e-5)),
    "half at focus plane": (lambda d: np.where(d < 3, 3.0, d), (0.05, 2.0, 3.0, 6e-5)),
    "depth = inf": (lambda d: np.where(d > 3, np.inf, d), (0.05, 2.0, 3.0, 6e-5)),
    "depth just beyond f": (
        lambda d: np.where(d < 3, 0.05 * (1 + 1e-4), d),
        (0.05, 2.0, 3.0, 6e-5),
    ),
    "focus just beyond f": (lambda d: d, (0.05, 2.0, 0.05 * (1 + 1e-4), 6e-5)),
    "f/1e4": (lambda d: d, (0.05, 1e4, 3.0, 6e-5)),
    "radii >> max_radius": (lambda d: d, (0.05, 0.5, 3.0, 1e-6)),
}
MAX_RADIUS = 4.0


def _log_params(lens):
    return jnp.log(jnp.asarray(lens, jnp.float64))


def _lens_from_log(p, dtype):
    p = jnp.exp(p).astype(dtype)
    return ThinLens(p[0], p[1], p[2], p[3])


def _render_all(image, depth, p, target):
    """Render, the loss, its gradient in log-lens, a render JVP and a gradient in the image."""
    dtype = image.dtype

    def out_fn(p, image=image):
        return render(image, depth, _lens_from_log(p, dtype), max_radius=MAX_RADIUS)

    def loss(p):
        return jnp.mean((out_fn(p) - target) ** 2)

    out = out_fn(p)
    val, grad = jax.value_and_grad(loss)(p)
    jvp = jax.jvp(out_fn, (p,), (jnp.ones_like(p),))[1]  # along every parameter at once
    g_img = jax.grad(lambda im: jnp.sum(out_fn(p, im) ** 2))(image)
    return out, val, grad, jvp, g_img


def render_study():
    image64, base_depth = _scene()
    target64 = render(image64, base_depth, ThinLens(0.05, 2.2, 2.8, 6e-5), max_radius=MAX_RADIUS)
    run = jax.jit(_render_all)  # compiled once per dtype
    rows = []
    for name, (transform, lens) in EXTREMES.items():
        depth64 = transform(base_depth)
        res = {}
        for dtype in (np.float32, np.float64):
            args = (
                jnp.asarray(image64, dtype),
                jnp.asarray(depth64, dtype),
                _log_params(lens),  # log-parameters in float64; the lens is cast to dtype inside
                jnp.asarray(target64, dtype),
            )
            res[dtype] = [np.asarray(x, np.float64) for x in run(*args)]
        a, b = res[np.float32], res[np.float64]
        finite32 = all(np.all(np.isfinite(x)) for x in a)
        finite64 = all(np.all(np.isfinite(x)) for x in b)

        def rel(x, y):
            scale = np.max(np.abs(y))
            return float(np.max(np.abs(x - y)) / scale) if scale > 0 else float(np.max(np.abs(x)))

        r = np.asarray(jaxdof.coc_radius(jnp.asarray(depth64), ThinLens(*lens)))
        rows.append(
            dict(
                case=name,
                r_max=float(np.max(r)),
                out=rel(a[0], b[0]),
                loss=rel(a[1], b[1]),
                grad=rel(a[2], b[2]),
                grad_norm=float(np.max(np.abs(b[2]))),
                jvp=rel(a[3], b[3]),
                g_img=rel(a[4], b[4]),
                finite=finite32 and finite64,
            )
        )
        print(f"render {name}: done", flush=True)
    return rows


# --------------------------------------------------------------------------------------------
# 3. Conditioning of the fit's normal matrix


@jax.jit
def _jacobian(depth, lens, image):
    """d(render) / d(log focus_distance, log f_number) at `lens = (f, N, d_f, pitch)`."""
    f, n, d_f, p = lens

    def residual(q):
        lens = ThinLens(f, jnp.exp(q[1]), jnp.exp(q[0]), p)
        return render(image, depth, lens, max_radius=4.0).ravel()

    return jax.jacfwd(residual)(jnp.log(jnp.stack([d_f, n])))


def normal_cond(depth, lens, image):
    """cond(D J^T J D) for J = d(render - target) / d(log d_f, log N), D scaling columns to 1."""
    jac = np.asarray(_jacobian(depth, jnp.asarray(lens), image))
    norms = np.linalg.norm(jac, axis=0)
    if np.any(norms == 0):
        return float("inf"), norms
    js = jac / norms
    return float(np.linalg.cond(js.T @ js)), norms


def conditioning_study(h=20, w=20):
    rng = np.random.default_rng(SEED + 1)
    image = jnp.asarray(rng.uniform(size=(h, w)))
    ramp = np.linspace(0, 1, w)[None, :] + np.zeros((h, 1))
    f, n, p = 0.05, 2.0, 6e-5
    eps32 = float(np.finfo(np.float32).eps)
    # (a) focus distance -> focal length with the scene's blur held fixed in pixels: depths
    # d = d_f / (1 - t / K) for signed radii t in [-3, 3] (a scene straddling the focus plane) or
    # t in [0.6, 3] (all behind it); the depth range shrinks with d_f - f as well.
    rows_a = []
    for e in np.logspace(0, -5, 11):
        d_f = f * (1 + e)
        k = f * f / (2 * n * (d_f - f) * p)
        row = dict(gap=e, d_f=d_f, K=k)
        for name, (lo, hi) in (("straddle", (-3, 3)), ("behind", (0.6, 3))):
            depth = jnp.asarray(d_f / (1 - (lo + (hi - lo) * ramp) / k))
            c, norms = normal_cond(depth, (f, n, d_f, p), image)
            row[name] = c
            if name == "straddle":
                row["depth_range"] = float(np.ptp(np.asarray(depth)))
        # |dr / d log d_f| ~ K d_f / d: a float32 rounding step of d_f (relative eps32) moves the
        # radii by about K eps32 pixels
        row["px_per_ulp"] = k * eps32
        rows_a.append(row)
    # (b) fixed lens (focused at 3 m, K = 3.5 px), the depth range around 1.5 m shrinks: one
    # plane makes N and d_f degenerate (both only scale the one radius)
    rows_b = []
    d_f = 3.0
    for width in np.logspace(0, -4, 9):
        depth = jnp.asarray(1.5 - width / 2 + width * ramp)
        c, _ = normal_cond(depth, (f, n, d_f, p), image)
        rows_b.append(dict(width=width, cond=c))
    return rows_a, rows_b


# --------------------------------------------------------------------------------------------
# 4. Cost of the run-time checks


def check_cost(h, w, repeats=7, number=5):
    rng = np.random.default_rng(SEED + 2)
    image = jnp.asarray(rng.uniform(size=(h, w, 3)), jnp.float32)
    radius = jnp.asarray(rng.uniform(0, 4, (h, w)), jnp.float32)
    checked = jax.jit(lambda i, r: coc_filter(i, r, max_radius=4.0))
    bare = jax.jit(lambda i, r: soft_filter(i, jnp.minimum(r, 4.0), max_radius=4.0))
    out = {}
    for name, fn in (("coc_filter (checked)", checked), ("soft_filter (no checks)", bare)):
        fn(image, radius).block_until_ready()
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            for _ in range(number):
                fn(image, radius).block_until_ready()
            ts.append((time.perf_counter() - t0) / number)
        out[name] = float(np.median(ts))
    np.testing.assert_array_equal(
        np.asarray(checked(image, radius)), np.asarray(bare(image, radius))
    )
    return out


# --------------------------------------------------------------------------------------------


def _fmt(x, spec=".1e"):
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def overlap_lines(overlap) -> list[str]:
    """Section 1: the float32 error of `circle_pixel_overlap` per radius, against the bound."""
    worst = max(row["err"] / row["bound"] for row in overlap)
    lines = [
        "## 1. `circle_pixel_overlap` in float32 (r log-spaced 1e-8 .. 1000 px)",
        "",
        "Max of |float32 - float64| (float64 at the same float32 inputs), in pixel areas, over "
        "8000 unit squares per radius: 4000 within 1.2 px of the circle (for r < 1: squares with "
        "an edge or corner through the disc, and squares anywhere around it) and 4000 "
        "first-quadrant squares whose corner is within reach of the circle. Bound: "
        "`2e-6 max(1, r)`. Textbook: inclusion-exclusion of the quadrant antiderivative "
        "`(t sqrt(r^2 - t^2) + r^2 asin(t/r)) / 2` in float32, on the first-quadrant squares.",
        "",
        "| r (px) | our float32 error | error / bound | error / (pi r^2) | textbook float32 error |",
        "|---:|---:|---:|---:|---:|",
    ]
    for row in overlap[::4] + ([overlap[-1]] if (len(overlap) - 1) % 4 else []):
        tb = _fmt(row["textbook"]) + (
            f" ({row['textbook_nan']} NaN)" if row["textbook_nan"] else ""
        )
        lines.append(
            f"| {row['r']:.3g} | {_fmt(row['err'])} | {row['err'] / row['bound']:.3f} | "
            f"{_fmt(row['rel_area'])} | {tb} |"
        )
    return lines + [
        "",
        f"Worst error / bound over all {len(overlap)} radii: **{worst:.3f}** (must be <= 1).",
        "",
    ]


def render_lines(rend) -> list[str]:
    """Section 2: float32 against float64 renders, losses and gradients at the extremes."""
    lines = [
        "## 2. `render` and a fit's loss: float32 against float64",
        "",
        "16x16x3 random texture, depth planes at 1.5 m and 6 m (then transformed per row), "
        f"`max_radius={MAX_RADIUS}`. Loss: mean squared difference to a float64 render with another "
        "lens, gradient in log(f, N, d_f, pitch). Entries: max |float32 - float64| / max |float64| "
        "(relative to the largest component); `r max`: the largest unclamped radius.",
        "",
        "| case | r max (px) | render | loss | d loss / d log-lens | render JVP | d/d image | "
        "all finite |",
        "|---|---:|---:|---:|---:|---:|---:|:---:|",
    ]
    for row in rend:
        lines.append(
            f"| {row['case']} | {row['r_max']:.3g} | {_fmt(row['out'])} | {_fmt(row['loss'])} | "
            f"{_fmt(row['grad'])} | {_fmt(row['jvp'])} | {_fmt(row['g_img'])} | "
            f"{'yes' if row['finite'] else '**no**'} |"
        )
    return lines + [""]


def conditioning_lines(cond_a, cond_b) -> list[str]:
    """Section 3: the condition number of the fit's normal matrix, (a) and (b)."""
    lines = [
        "## 3. Conditioning of the fit's normal matrix",
        "",
        "`cond(D J^T J D)`, `J` = Jacobian of the rendered 20x20 image with respect to "
        "(log focus_distance, log f_number) at the truth (`jax.jacfwd`), `D` scaling the columns to "
        "unit norm; f = 50 mm, N = 2, pitch 60 um. Values near 1: the two parameters are separately "
        "identifiable; large values: only a combination of them is.",
        "",
        "(a) Focus distance approaching the focal length, the scene blur held fixed in pixels "
        "(depths `d_f / (1 - t/K)` for signed radii t in [-3, 3], straddling the focus plane, "
        "or t in [0.6, 3], all behind it):",
        "",
        "| (d_f - f) / f | d_f (m) | K (px) | depth range (m) | cond, blur -3..3 px | "
        "cond, blur 0.6..3 px | px per float32 step of d_f |",
        "|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in cond_a:
        lines.append(
            f"| {row['gap']:.0e} | {row['d_f']:.6g} | {row['K']:.3g} | {row['depth_range']:.3g} | "
            f"{_fmt(row['straddle'], '.3g')} | {_fmt(row['behind'], '.3g')} | "
            f"{row['px_per_ulp']:.2g} |"
        )
    lines += [
        "",
        "(b) Fixed lens (focused at 3 m), scene depths a ramp of shrinking width around 1.5 m:",
        "",
        "| depth range (m) | cond |",
        "|---:|---:|",
    ]
    for row in cond_b:
        lines.append(f"| {row['width']:.0e} | {_fmt(row['cond'], '.3g')} |")
    return lines + [""]


def cost_lines(cost) -> list[str]:
    """Section 4: what the run-time input check costs under jit."""
    lines = [
        "## 4. Cost of the run-time input checks under jit",
        "",
        "float32, radii 0..4 px, `max_radius=4`, median of 7 x 5 calls; `coc_filter` runs the "
        "`equinox.error_if` radius check, the bare `soft_filter` none (same output, asserted). "
        "Measured on a shared, busy CPU: the ratio is the number to read.",
        "",
        "| image | coc_filter, checked (ms) | soft_filter, no checks (ms) | ratio |",
        "|---|---:|---:|---:|",
    ]
    for size, c in cost.items():
        a, b = c["coc_filter (checked)"], c["soft_filter (no checks)"]
        lines.append(f"| {size}x{size}x3 | {a * 1e3:.2f} | {b * 1e3:.2f} | {a / b:.2f} |")
    return lines


def main(argv=None):
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args(argv)  # --help only
    t_start = time.perf_counter()
    overlap = overlap_study()
    print(f"overlap study done ({time.perf_counter() - t_start:.0f} s)", flush=True)
    rend = render_study()
    print(f"render study done ({time.perf_counter() - t_start:.0f} s)", flush=True)
    cond_a, cond_b = conditioning_study()
    print(f"conditioning study done ({time.perf_counter() - t_start:.0f} s)", flush=True)
    cost = {size: check_cost(size, size) for size in (64, 256)}
    elapsed = time.perf_counter() - t_start

    worst = max(row["err"] / row["bound"] for row in overlap)
    lines = [
        "# Numerical stability at the extremes",
        "",
        f"Written by `fits/stability.py` (seed 0). {versions_line()} "
        f"({jax.devices()[0].platform}); run time {elapsed:.0f} s.",
        "",
        *overlap_lines(overlap),
        *render_lines(rend),
        *conditioning_lines(cond_a, cond_b),
        *cost_lines(cost),
    ]
    write_markdown(result_path("stability"), lines)
    _plot(overlap, cond_a, cond_b)
    print("\n".join(lines + [""]))
    assert worst <= 1.0, f"float32 overlap error exceeds the 2e-6 max(1, r) bound: {worst}"
    assert all(row["finite"] for row in rend), "NaN or inf in render/loss values or gradients"


def _plot(overlap, cond_a, cond_b):
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    r = np.array([row["r"] for row in overlap])
    ax = axes[0]
    ax.loglog(r, [row["err"] for row in overlap], "o-", ms=3, label="jaxdof float32")
    ax.loglog(r, [row["textbook"] for row in overlap], "s-", ms=3, label="textbook float32")
    ax.loglog(r, [row["bound"] for row in overlap], "k--", label="bound 2e-6 max(1, r)")
    ax.set_xlabel("radius r (px)")
    ax.set_ylabel("max |float32 - float64| (pixel areas)")
    ax.set_title("circle_pixel_overlap in float32")
    ax.legend()
    ax = axes[1]
    ax.loglog(
        [row["gap"] for row in cond_a],
        [row["behind"] for row in cond_a],
        "o-",
        label="(a) x = (d_f - f)/f, blur fixed at 0.6..3 px",
    )
    ax.loglog(
        [row["width"] for row in cond_b],
        [row["cond"] for row in cond_b],
        "s-",
        label="(b) x = depth range (m) at 1.5 m",
    )
    ax.set_xlabel("x")
    ax.set_ylabel("cond of column-scaled J^T J")
    ax.set_title("fit conditioning (free d_f, N)")
    ax.invert_xaxis()
    ax.legend()
    fig.tight_layout()
    fig.savefig(result_path("stability", ".png"), dpi=90)


if __name__ == "__main__":
    main()
