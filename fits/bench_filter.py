"""Benchmark: what does the exact soft filter cost next to a gather with constant weights?

Question: how long do `coc_filter(method="soft")` and its gradient take per megapixel on a
1024 x 1024 RGB image at max_radius 2, 4, 8 and 16 px, and how does that compare with the floor of
any gather over the same window, the same taps with constant weights?

Measured (float32, jit, `block_until_ready`, one warm-up call, median of `--repeats` calls):

- `soft`: `jaxdof.coc_filter(image, radius, max_radius=R)`, radii uniform in `[0, R]`.
- `const gather`: the plain per-tap gather loop (`jaxdof.internal.gather`, one offset per
  checkpointed scan step) with a constant weight per tap: the floor the soft filter is compared
  with (issue 2's goal: soft <= 3x this).
- `const mirrored`: the soft filter's own loop (`symmetric_gather`: one weight per mirror class,
  scattered to the mirrored offsets) with constant weights: how much of `soft` is the loop and how
  much the exact coverage.

"forward" is the filter; "fwd+grad" is `value_and_grad` of `sum(out^2)` with respect to the image
and the radius map (the const rows: the image). Compile time is reported apart. Writes
`fits/results/bench_filter.md`.

Run: `python fits/bench_filter.py` (about 2-4 minutes on a 2-core CPU).
"""

from __future__ import annotations

import argparse
import math
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
from _common import (
    RESULTS,
    command,
    compile_all,
    load_average,
    machine_info,
    medians_in_turns,
    write_markdown,
)

import jaxdof

# The gather loops the soft filter is compared with (semi-internal).
from jaxdof.internal import gather, symmetric_gather, tap_offsets


def variants(max_radius: float, mirrored_grad: bool = True):
    """`{name: (forward(image, radius), fwd+grad(image, radius))}` for one window (`fwd+grad` None
    when not timed)."""
    offsets = tap_offsets(max_radius)
    n = len(offsets)

    def const_weight(ax, bx, ay, by, m, centre, r):
        return jnp.full_like(r, 1.0 / n)

    filters = {
        "soft": lambda i, r: jaxdof.coc_filter(i, r, max_radius=max_radius),
        "const gather": lambda i, r: gather(i, r, offsets, const_weight),
        "const mirrored": lambda i, r: symmetric_gather(i, r, offsets, const_weight),
    }
    out = {}
    for name, f in filters.items():
        argnums = (0, 1) if name == "soft" else 0
        loss = lambda i, r, f=f: jnp.sum(f(i, r) ** 2)
        out[name] = (f, jax.value_and_grad(loss, argnums=argnums))
    if not mirrored_grad:
        out["const mirrored"] = (out["const mirrored"][0], None)
    return out


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=1024, help="image side, pixels")
    parser.add_argument("--radii", type=float, nargs="+", default=[2.0, 4.0, 8.0, 16.0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=pathlib.Path, default=RESULTS / "bench_filter.md")
    parser.add_argument(
        "--retain-memory",
        action="store_true",
        help="call jaxdof.retain_freed_memory() first (glibc keeps freed memory for reuse)",
    )
    parser.add_argument(
        "--no-mirrored-grad",
        action="store_true",
        help="skip fwd+grad of `const mirrored` (JAX's own transpose of the mirrored loop; on an "
        "H100 with jax 0.11.2 it fails with an illegal memory access at 1024^2 and R = 4)",
    )
    return parser.parse_args(argv)


def measure(size: int, radii, repeats: int, mirrored_grad: bool) -> list[tuple]:
    """One row per (max radius, variant): `(R, taps, name, wall fwd, wall fwd+grad, CPU fwd, CPU
    fwd+grad, compile fwd, compile fwd+grad)`, times in seconds per megapixel."""
    rng = np.random.default_rng(0)
    h = w = size
    mpix = h * w / 1e6
    image = jnp.asarray(rng.uniform(size=(h, w, 3)), jnp.float32)
    rows = []
    for max_radius in radii:
        radius = jnp.asarray(rng.uniform(0, max_radius, (h, w)), jnp.float32)
        taps = len(tap_offsets(max_radius))
        fns = {}
        for name, (fwd, both) in variants(max_radius, mirrored_grad).items():
            fns[(name, "fwd")] = fwd
            if both is not None:
                fns[(name, "grad")] = both
        compiled, compile_s = compile_all(fns, image, radius)
        t = medians_in_turns(compiled, (image, radius), repeats)
        for name in variants(max_radius):
            (wf, cf), (wg, cg) = t[(name, "fwd")], t.get((name, "grad"), (math.nan, math.nan))
            compile_s.setdefault((name, "grad"), math.nan)
            rows.append(
                (
                    max_radius,
                    taps,
                    name,
                    wf / mpix,
                    wg / mpix,
                    cf / mpix,
                    cg / mpix,
                    compile_s[(name, "fwd")],
                    compile_s[(name, "grad")],
                )
            )
            print(
                f"R={max_radius:<5g} taps={taps:<4d} {name:<15s} forward {wf / mpix:8.4f} s/MP "
                f"fwd+grad {wg / mpix:8.4f} s/MP wall; CPU {cf / mpix:8.4f} / {cg / mpix:8.4f} "
                f"s/MP (compile {compile_s[(name, 'fwd')]:.1f} s / {compile_s[(name, 'grad')]:.1f} s)",
                flush=True,
            )
    return rows


def report_lines(rows: list[tuple], size: int, repeats: int, info: dict, argv=None) -> list[str]:
    """The report: conditions, the table of `measure`'s rows, the variants, the machine."""
    by = {(r[0], r[2]): r for r in rows}
    on_cpu = jax.default_backend() == "cpu"
    clock = "CPU" if on_cpu else "wall"
    lines = [
        "# Soft filter vs a constant-weight gather over the same window",
        "",
        f"Image {size} x {size} x 3, float32, radii uniform in [0, max_radius], jit. Variants are "
        f"timed in turns, {repeats} rounds after a warm-up; medians, in seconds per megapixel; "
        "compile time apart. Wall time and CPU time (all threads of this process) are both shown: "
        "on a shared machine CPU time is the steadier of the two.",
        f"Produced by `{command('bench_filter.py', argv)}`. All rows come from one run."
        + (
            ""
            if on_cpu
            else f" On the accelerator ({jax.default_backend()}) the process CPU time is the host's "
            "alone, so the ratios are of wall time."
        ),
        "",
        "| max_radius | taps | method | forward wall | fwd+grad wall | forward CPU | fwd+grad CPU "
        f"| fwd+grad / forward ({clock}) | soft / const gather, forward ({clock}) "
        "| compile fwd / fwd+grad (s) |",
        "|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r, taps, name, wf, wg, cf, cg, kf, kg in rows:
        const = by[(r, "const gather")]
        f, g, f_const = (cf, cg, const[5]) if on_cpu else (wf, wg, const[3])
        ratio = f"{f / f_const:.2f}" if name == "soft" else ""
        lines.append(
            f"| {r:g} | {taps} | {name} | {wf:.4g} | {wg:.4g} | {cf:.4g} | {cg:.4g} | "
            f"{g / f:.2f} | {ratio} | {kf:.1f} / {kg:.1f} |"
        )
    return lines + [
        "",
        "- `soft`: `jaxdof.coc_filter` (exact analytic coverage); fwd+grad with respect to image and radius.",
        "- `const gather`: the plain one-tap-per-step gather with constant weights (the floor of "
        "issue 2's goal, soft <= 3x); fwd+grad with respect to the image.",
        "- `const mirrored`: the soft filter's own mirrored loop with constant weights.",
        "",
        "## Machine",
        "",
        *[f"- {k}: {v}" for k, v in info.items()],
    ]


def main(argv=None) -> None:
    args = parse_args(argv)
    retained = jaxdof.retain_freed_memory() if args.retain_memory else False
    info = machine_info()
    info["jaxdof.retain_freed_memory()"] = "called, accepted" if retained else "not called"
    rows = measure(args.size, args.radii, args.repeats, not args.no_mirrored_grad)
    info["load average (1, 5, 15 min) at end"] = load_average()
    write_markdown(args.out, report_lines(rows, args.size, args.repeats, info, argv))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
