"""What the footprint correction costs beside the soft filter it feeds, per window.

    python fits/footprint_cost.py [--size 512] [--repeats 7]

For a float32 RGB image of `size^2` pixels and a circle map of radii up to the window, times (jit,
compiled once, medians of `repeats` calls, all in this one process):

- `soft`: `coc_filter` alone (the soft filter with that window);
- `table`: `footprint_prefilter` as the library runs it (`c(r)` read from its Hermite table);
- `closed`: the same correction with `c(r)` from the closed form, `kernel_variance`'s chord areas
  summed over the window's columns (what `footprint_prefilter` did before the table);

each as a value and as a Jacobian-vector product (`jax.jvp` in the radius: what a
Levenberg-Marquardt fit evaluates). Prints a markdown table of milliseconds and the ratios to
`soft`. The two corrections agree to the table's error (7.5e-9 px^2 in c).
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxdof
from jaxdof.internal import kernel_variance


def closed_form_prefilter(image, radius, window):
    """`footprint_prefilter` with `c(r)` from the chord sums (the previous implementation)."""
    p = jnp.pad(image, [(1, 1), (1, 1), (0, 0)], mode="edge")
    lap = p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:] - 4 * image
    c = (kernel_variance(radius, max_radius=window) - radius * radius / 4) / 2
    return image - c[..., None] * lap


def timed(fn, *args, repeats):
    jax.block_until_ready(fn(*args))  # compile
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return 1e3 * statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    n = args.size
    image = jnp.asarray(rng.uniform(size=(n, n, 3)), jnp.float32)
    print(f"# footprint correction cost, {n}x{n} RGB float32, {jax.devices()[0].platform}")
    print(
        "| window | soft ms | table ms | closed ms | table/soft | closed/soft | jvp: soft | "
        "table | closed |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for window in (2.0, 4.0, 8.0, 12.0):
        radius = jnp.asarray(rng.uniform(0.0, window, size=(n, n)), jnp.float32)
        soft = jax.jit(lambda r, w=window: jaxdof.coc_filter(image, r, max_radius=w))
        table = jax.jit(lambda r: jaxdof.footprint_prefilter(image, r))
        closed = jax.jit(lambda r, w=window: closed_form_prefilter(image, r, w))
        row = [timed(f, radius, repeats=args.repeats) for f in (soft, table, closed)]
        tangent = jnp.ones_like(radius)
        jvps = [
            timed(jax.jit(lambda r, f=f, t=tangent: jax.jvp(f, (r,), (t,))), radius,
                  repeats=args.repeats)
            for f in (soft, table, closed)
        ]  # fmt: skip
        print(
            f"| {window:g} | {row[0]:.1f} | {row[1]:.1f} | {row[2]:.1f} | "
            f"{row[1] / row[0]:.2f} | {row[2] / row[0]:.2f} | "
            f"{jvps[0]:.1f} | {jvps[1]:.1f} | {jvps[2]:.1f} |"
        )


if __name__ == "__main__":
    main()
