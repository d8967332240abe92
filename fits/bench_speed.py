"""Benchmark: how the soft filter's time and memory scale with image size and blur radius.

Question (issue 7): time per megapixel of `coc_filter(method="soft")` forward and forward+grad
against image size (256^2 .. 2048^2) and max radius (2 .. 64 px), compile time apart; the memory the
compiled forward and reverse passes need; and the exponent of time against radius.

Method (float32, jit, radii uniform in `[0, max_radius]`, RGB):

- time: one warm-up call, then `--repeats` calls timed in turns (forward, fwd+grad, forward, ...)
  so both see the same drift of a shared machine's load; medians of wall time and of CPU time
  (`time.process_time`, all threads), in seconds per megapixel. fwd+grad is `value_and_grad` of
  `sum(out^2)` with respect to the image and the radius map.
- memory: XLA's own buffer assignment for the compiled program (`compiled.memory_analysis()`:
  arguments + outputs + temporaries - aliased), i.e. the peak of device buffers the program
  allocates. Deterministic and immune to the load. (It leaves out the Python process and compiler,
  which `/usr/bin/time -v` would add on top.)

Paths (issue 7, deliverable 2): the exact soft filter has two implementations with the same
numbers, the dense gather over the window (`path="dense"`, cost ~ R^2) and row spans plus boundary
taps (`path="spans"`, `jaxdof/_filters/spans.py`, cost ~ R), both reachable through
`jaxdof.internal.exact_soft_filter(..., path=...)`. `--paths` times both, forced, against max
radius at one image size, in turns (dense fwd, dense fwd+grad, spans fwd, spans fwd+grad, ...),
checks they agree, fits the log-log exponent of CPU time between max radius 8 and 64, and reads off
the crossover that `SPANS_MIN_RADIUS` (`jaxdof/_tuning.py`) is set from. Alone (`--paths-only`) it rewrites only its own
section of `speed.md` and keeps the others.

Writes `fits/results/speed.md` and `fits/results/speed.png`.

Run: `python fits/bench_speed.py` (defaults below; `--quick` for a smoke run).
"""

from __future__ import annotations

import argparse
import pathlib
import statistics

import jax
import jax.numpy as jnp
import numpy as np
from _common import (
    RESULTS,
    command,
    compile_all,
    git_state,
    load_average,
    load_json,
    machine_info,
    save_json,
    timed_in_turns,
    write_markdown,
)

import jaxdof

# Semi-internal: the soft filter forced onto one path, and the tuning table that holds the
# crossover between the paths (`SPANS_MIN_RADIUS`).
from jaxdof.internal import exact_soft_filter, tuning


def program_bytes(compiled) -> int:
    m = compiled.memory_analysis()
    return (
        m.argument_size_in_bytes
        + m.output_size_in_bytes
        + m.temp_size_in_bytes
        - m.alias_size_in_bytes
    )


def measure(size: int, max_radius: float, repeats: int, *, run: bool = True) -> dict:
    """Compile (and unless `run=False`, time) forward and fwd+grad at one image size and radius."""
    rng = np.random.default_rng(0)
    image = jnp.asarray(rng.uniform(size=(size, size, 3)), jnp.float32)
    radius = jnp.asarray(rng.uniform(0, max_radius, (size, size)), jnp.float32)
    f = lambda i, r: jaxdof.coc_filter(i, r, max_radius=max_radius)
    g = jax.value_and_grad(lambda i, r: jnp.sum(f(i, r) ** 2), argnums=(0, 1))
    res = {"size": size, "R": max_radius}
    compiled, seconds = compile_all({"fwd": f, "grad": g}, image, radius, warm_up=False)
    for name, c in compiled.items():
        res[f"compile_{name}"] = seconds[name]
        res[f"mem_{name}"] = program_bytes(c)
    if not run:
        return res
    for fn in compiled.values():
        jax.block_until_ready(fn(image, radius))
    runs = timed_in_turns(compiled, (image, radius), repeats)
    mpix = size * size / 1e6
    for name, rs in runs.items():
        res[f"wall_{name}"] = statistics.median(r[0] for r in rs) / mpix
        res[f"cpu_{name}"] = statistics.median(r[1] for r in rs) / mpix
    return res


def measure_paths(size: int, max_radius: float, repeats: int) -> dict:
    """Time the dense and span paths of the exact soft filter, forced, at one size and radius."""
    rng = np.random.default_rng(0)
    image = jnp.asarray(rng.uniform(size=(size, size, 3)), jnp.float32)
    radius = jnp.asarray(rng.uniform(0, max_radius, (size, size)), jnp.float32)
    res = {"size": size, "R": max_radius}
    fns = {}
    for path in ("dense", "spans"):
        f = lambda i, r, path=path: exact_soft_filter(i, r, max_radius=max_radius, path=path)  # noqa: E731
        g = jax.value_and_grad(lambda i, r, f=f: jnp.sum(f(i, r) ** 2), argnums=(0, 1))
        fns[f"{path}_fwd"], fns[f"{path}_grad"] = f, g
    compiled, seconds = compile_all(fns, image, radius, warm_up=False)
    res.update({f"compile_{k}": v for k, v in seconds.items()})
    outs = {k: jax.block_until_ready(fn(image, radius)) for k, fn in compiled.items()}
    # the two paths compute the same sum: record how far apart they are (float32)
    res["max_abs_diff_fwd"] = float(jnp.max(jnp.abs(outs["dense_fwd"] - outs["spans_fwd"])))
    gd, gs = outs["dense_grad"][1], outs["spans_grad"][1]
    res["max_rel_diff_grad"] = max(
        float(jnp.max(jnp.abs(a - b)) / jnp.max(jnp.abs(a))) for a, b in zip(gd, gs)
    )
    runs = timed_in_turns(compiled, (image, radius), repeats)
    for name, rs in runs.items():
        res[f"wall_{name}"] = statistics.median(r[0] for r in rs)
        res[f"cpu_{name}"] = statistics.median(r[1] for r in rs)
    return res


PATH_HEADER = [
    "| max_radius | dense fwd CPU (s) | spans fwd CPU (s) | dense fwd+grad CPU (s) "
    "| spans fwd+grad CPU (s) | dense fwd / fwd+grad wall (s) | spans fwd / fwd+grad wall (s) "
    "| compile spans fwd / fwd+grad (s) | max abs diff (fwd) | max rel diff (grad) |",
    "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
]


def fmt_path_row(r: dict) -> str:
    return (
        f"| {r['R']:g} | {r['cpu_dense_fwd']:.3f} | {r['cpu_spans_fwd']:.3f} | "
        f"{r['cpu_dense_grad']:.3f} | {r['cpu_spans_grad']:.3f} | "
        f"{r['wall_dense_fwd']:.3f} / {r['wall_dense_grad']:.3f} | "
        f"{r['wall_spans_fwd']:.3f} / {r['wall_spans_grad']:.3f} | "
        f"{r['compile_spans_fwd']:.1f} / {r['compile_spans_grad']:.1f} | "
        f"{r['max_abs_diff_fwd']:.1e} | {r['max_rel_diff_grad']:.1e} |"
    )


PATHS_BEGIN = "<!-- paths: begin -->"
PATHS_END = "<!-- paths: end -->"


def paths_section(rows: list, size: int, repeats: int, info: dict, command_line: str) -> list[str]:
    """Markdown for the dense-vs-spans comparison: table, exponents, crossover."""
    lines = [
        PATHS_BEGIN,
        f"## Dense gather vs row spans against max radius ({size}^2 RGB float32)",
        "",
        f"Produced by `{command_line}`: the exact soft filter forced onto each path "
        "(`jaxdof.internal.exact_soft_filter(..., path=...)`), radii uniform in "
        f"[0, max_radius], jit, medians of {repeats} calls timed in turns (dense fwd, dense "
        "fwd+grad, spans fwd, spans fwd+grad) after a warm-up, seconds per call; compile apart. "
        "CPU = this process's CPU time (all threads), the steadier figure on a shared machine. "
        "Last two columns: how far the paths' outputs (image range [0, 1]) and gradients "
        "(relative to the largest) are apart in float32.",
        "",
        *PATH_HEADER,
        *[fmt_path_row(r) for r in rows],
        "",
    ]
    span = [r for r in rows if 8 <= r["R"] <= 64]
    if len(span) >= 2:
        xs = [r["R"] for r in span]
        ex = {
            k: slope(xs, [r[k] for r in span])
            for k in ("cpu_dense_fwd", "cpu_spans_fwd", "cpu_dense_grad", "cpu_spans_grad")
        }
        exw = {k: slope(xs, [r[k] for r in span]) for k in ("wall_spans_fwd", "wall_spans_grad")}
        lines += [
            f"Exponent of CPU time against max radius, least squares over max radius "
            f"{', '.join(f'{x:g}' for x in xs)}: **spans forward {ex['cpu_spans_fwd']:.2f}, "
            f"fwd+grad {ex['cpu_spans_grad']:.2f}** (wall time: {exw['wall_spans_fwd']:.2f}, "
            f"{exw['wall_spans_grad']:.2f}); dense forward {ex['cpu_dense_fwd']:.2f}, fwd+grad "
            f"{ex['cpu_dense_grad']:.2f}. Issue 7's goal: at most 1.3 on the fast path.",
            "",
        ]
    wins = [
        r["R"]
        for r in rows
        if r["cpu_spans_fwd"] < r["cpu_dense_fwd"] and r["cpu_spans_grad"] < r["cpu_dense_grad"]
    ]
    # the crossover: the smallest swept radius from which spans wins both, at every larger one
    cross = next(
        (r["R"] for i, r in enumerate(rows) if all(x["R"] in wins for x in rows[i:])), None
    )
    lines += [
        "Crossover (CPU time, forward and fwd+grad both faster on spans from this max radius on, "
        f"among those swept): **{cross if cross is None else f'{cross:g}'}**. "
        f"`SPANS_MIN_RADIUS` in `jaxdof/_tuning.py` is {tuning.SPANS_MIN_RADIUS:g}: "
        '`coc_filter(method="soft")` takes the span path from there on.',
        "",
        "Machine for this section: "
        + "; ".join(f"{k}: {v}" for k, v in info.items() if k != "jaxdof")
        + ".",
        PATHS_END,
    ]
    return lines


def slope(xs, ys) -> float:
    """Least-squares exponent `k` of `y ~ x^k`."""
    return float(np.polyfit(np.log(xs), np.log(ys), 1)[0])


def fmt_row(r: dict) -> str:
    mib = 2.0**20
    return (
        f"| {r['size']}^2 | {r['R']:g} | {r['wall_fwd']:.3f} | {r['wall_grad']:.3f} | "
        f"{r['cpu_fwd']:.3f} | {r['cpu_grad']:.3f} | {r['cpu_grad'] / r['cpu_fwd']:.2f} | "
        f"{r['compile_fwd']:.1f} / {r['compile_grad']:.1f} | {r['mem_fwd'] / mib:.0f} / "
        f"{r['mem_grad'] / mib:.0f} |"
    )


HEADER = [
    "| image | max_radius | forward wall (s/MP) | fwd+grad wall (s/MP) | forward CPU (s/MP) "
    "| fwd+grad CPU (s/MP) | fwd+grad / forward (CPU) | compile fwd / fwd+grad (s) "
    "| memory fwd / fwd+grad (MiB) |",
    "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
]


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024, 2048])
    parser.add_argument(
        "--size-radius", type=float, default=4.0, help="max_radius of the size sweep"
    )
    parser.add_argument("--radii", type=float, nargs="+", default=[2, 4, 8, 16, 32, 64])
    parser.add_argument(
        "--radius-size", type=int, default=256, help="image side of the radius sweep"
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--path-radii",
        type=float,
        nargs="+",
        default=[4, 8, 12, 16, 24, 32, 64],
        help="max radii of the dense-vs-spans comparison",
    )
    parser.add_argument("--path-size", type=int, default=256, help="image side of that comparison")
    parser.add_argument(
        "--paths-only",
        action="store_true",
        help="run only the dense-vs-spans comparison and rewrite only its section of speed.md",
    )
    parser.add_argument("--quick", action="store_true", help="tiny smoke run")
    parser.add_argument("--out", type=pathlib.Path, default=RESULTS / "speed.md")
    parser.add_argument("--replot", action="store_true", help="redraw the plot from the saved JSON")
    args = parser.parse_args(argv)
    if args.quick:
        args.sizes, args.radii, args.radius_size, args.repeats = [64, 128], [2, 4], 64, 1
        args.path_radii, args.path_size = [4, 8], 64
    return args


def replot(out: pathlib.Path) -> None:
    """Redraw the plot from the saved JSON."""
    saved = load_json(out.with_suffix(".json"))
    paths = saved.get("paths", {}).get("rows")
    plot(saved["by_size"], saved["by_radius"], saved["info"], out.with_suffix(".png"), paths)


def rewrite_paths_section(
    out: pathlib.Path, by_path: list, args: argparse.Namespace, info: dict, command_line: str
) -> None:
    """`--paths-only`: replace the paths section of `out` (and the `paths` entry of its JSON),
    keeping the other sections; redraw the plot when the saved sweeps are there."""
    section = "\n".join(paths_section(by_path, args.path_size, args.repeats, info, command_line))
    text = out.read_text() if out.exists() else ""
    if PATHS_BEGIN in text:
        head, rest = text.split(PATHS_BEGIN, 1)
        text = head + section + rest.split(PATHS_END, 1)[1]
    else:
        text = text.rstrip("\n") + "\n\n" + section + "\n"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    saved_json = out.with_suffix(".json")
    saved = load_json(saved_json) if saved_json.exists() else {}
    saved["paths"] = {"rows": by_path, "info": info, "command": command_line}
    save_json(saved_json, saved, indent=1)
    if "by_size" in saved:
        plot(saved["by_size"], saved["by_radius"], saved["info"], out.with_suffix(".png"), by_path)
    print(f"wrote {out}")


def sweep_lines(by_size: list, by_radius: list, args: argparse.Namespace, command_line: str):
    """The report's head and its two sweeps (image size, max radius) with the radius exponent."""
    big = [r for r in by_radius if r["R"] >= 8]
    exps = {}
    if len(big) >= 2:
        for key in ("cpu_fwd", "cpu_grad"):
            exps[key] = slope([r["R"] for r in big], [r[key] for r in big])
    lines = [
        "# Speed and memory of the soft filter against image size and blur radius",
        "",
        f"Produced by `{command_line}`; float32, RGB, radii uniform in [0, max_radius], jit; medians of {args.repeats} calls "
        "(forward and fwd+grad timed in turns after a warm-up), per megapixel; compile time apart; "
        "memory from XLA's buffer assignment of the compiled program (arguments + outputs + "
        "temporaries). fwd+grad is `value_and_grad` of `sum(out^2)` in image and radius.",
        "",
        "**No GPU was available for this run**: every figure is CPU (see Machine). The code is "
        "device-agnostic and runs unchanged on a GPU.",
        "",
        f"## Against image size (max_radius {args.size_radius:g})",
        "",
        *HEADER,
        *[fmt_row(r) for r in by_size],
        "",
        f"## Against max radius ({args.radius_size}^2 image)",
        "",
        *HEADER,
        *[fmt_row(r) for r in by_radius],
        "",
    ]
    if exps:
        lines += [
            f"Exponent of CPU time against max radius between {big[0]['R']:g} and {big[-1]['R']:g} "
            f"(least squares, log-log): forward {exps['cpu_fwd']:.2f}, fwd+grad "
            f'{exps["cpu_grad"]:.2f}. `coc_filter(method="soft")` runs the dense gather below '
            "`SPANS_MIN_RADIUS` and row spans from there on, so this curve mixes the two; the "
            "section on the two paths below separates them.",
            "",
        ]
    return lines


def memory_lines(mem: dict) -> list[str]:
    ratio = mem["mem_grad"] / mem["mem_fwd"]
    return [
        f"## Memory, reverse vs forward ({mem['size']}^2 RGB, max_radius {mem['R']:g})",
        "",
        f"Forward program {mem['mem_fwd'] / 2**20:.1f} MiB, value_and_grad program "
        f"{mem['mem_grad'] / 2**20:.1f} MiB: ratio **{ratio:.2f}** (goal <= 4). The loop over "
        "offsets is a checkpointed `lax.scan`: reverse mode stores no per-offset weights and "
        "recomputes each step's weights in the backward pass.",
        "",
    ]


def main(argv=None) -> None:
    args = parse_args(argv)
    if args.replot:
        return replot(args.out)
    command_line = command("bench_speed.py", argv)
    info = machine_info()
    info["git"] = git_state()
    by_path = []
    for r in args.path_radii:
        by_path.append(measure_paths(args.path_size, r, args.repeats))
        print(fmt_path_row(by_path[-1]), flush=True)
    if args.paths_only:
        info["load average (1, 5, 15 min) at end"] = load_average()
        return rewrite_paths_section(args.out, by_path, args, info, command_line)
    by_size = []
    for size in args.sizes:
        by_size.append(measure(size, args.size_radius, args.repeats))
        print(fmt_row(by_size[-1]), flush=True)
    by_radius = []
    for r in args.radii:
        by_radius.append(measure(args.radius_size, r, args.repeats))
        print(fmt_row(by_radius[-1]), flush=True)
    # Issue 7's memory goal, on the image it names: compile only (XLA's buffer assignment).
    mem = measure(64 if args.quick else 1024, 16.0, 0, run=False)
    info["load average (1, 5, 15 min) at end"] = load_average()

    lines = sweep_lines(by_size, by_radius, args, command_line)
    lines += [*paths_section(by_path, args.path_size, args.repeats, info, command_line), ""]
    lines += [*memory_lines(mem), "## Machine", "", *[f"- {k}: {v}" for k, v in info.items()]]
    write_markdown(args.out, lines)
    print(f"wrote {args.out}")
    paths = {"rows": by_path, "info": info, "command": command_line}
    saved = {
        "by_size": by_size,
        "by_radius": by_radius,
        "memory": mem,
        "info": info,
        "paths": paths,
    }
    save_json(args.out.with_suffix(".json"), saved, indent=1)
    plot(by_size, by_radius, info, args.out.with_suffix(".png"), by_path)


def plot(
    by_size: list, by_radius: list, info: dict, png: pathlib.Path, paths: list | None = None
) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        from matplotlib.ticker import NullFormatter, ScalarFormatter
    except ImportError:
        print("matplotlib not installed: no plot")
        return
    fig, axes = plt.subplots(1, 3 if paths else 2, figsize=(15 if paths else 10, 4))
    for ax, rows, key, label in (
        (axes[0], by_size, "size", f"image side (px), max_radius {by_size[0]['R']:g}"),
        (axes[1], by_radius, "R", f"max radius (px), {by_radius[0]['size']}^2 image"),
    ):
        x = [r[key] for r in rows]
        for name, style in (("cpu_fwd", "o-"), ("cpu_grad", "s--")):
            ax.loglog(x, [r[name] for r in rows], style, label=name.replace("cpu_", "CPU "))
        ax.set_xlabel(label)
        ax.set_ylabel("CPU seconds per megapixel")
        ax.grid(True, which="both", alpha=0.3)
    if len(by_radius) >= 2:  # guide: the area law R^2 through the first point
        x = np.array([r["R"] for r in by_radius], float)
        axes[1].loglog(
            x, by_radius[0]["cpu_fwd"] * (x / x[0]) ** 2, ":", color="grey", label="~R^2"
        )
    for ax, rows, key in ((axes[0], by_size, "size"), (axes[1], by_radius, "R")):
        ax.set_xticks([r[key] for r in rows])  # after every loglog call, which resets the ticks
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.legend()
    if paths:
        ax = axes[2]
        x = [r["R"] for r in paths]
        for key, style in (
            ("cpu_dense_fwd", "o-"),
            ("cpu_dense_grad", "s--"),
            ("cpu_spans_fwd", "o-"),
            ("cpu_spans_grad", "s--"),
        ):
            label = key.replace("cpu_", "").replace("_", " ").replace("grad", "fwd+grad")
            ax.loglog(x, [r[key] for r in paths], style, label=label)
        ax.set_xlabel(f"max radius (px), {paths[0]['size']}^2 image, forced path")
        ax.set_ylabel("CPU seconds per call")
        ax.grid(True, which="both", alpha=0.3)
        ax.set_xticks(x)
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.legend()
    fig.suptitle("jaxdof soft filter on CPU (" + info["cpu"] + "); no GPU in this run")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    print(f"wrote {png}")


if __name__ == "__main__":
    main()
