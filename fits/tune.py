"""Re-measure every tuning constant of `jaxdof/_tuning.py` on this machine (issue 19).

Question: each constant in `jaxdof/_tuning.py` picks between two ways of computing the same
numbers (a dense gather or row spans, FFTs or a direct sum, a chain of selects or a gather, a loop
written out or scanned) by a crossover or a cost ratio. Is its value still right on this machine,
with this jax? Each study asks the question that produced the constant, times both ways over a
sweep, and reads off the value; a constant that was never a measurement (a cap) prints why.

Method (every study): float32 (x64 off), RGB images uniform in [0, 1], jitted and compiled ahead of
time (compile time apart), one warm-up call, then rounds in which every candidate of a sweep point
is timed once, in alternating order (forward one round, backward the next), so that a shared
machine's drift of load shifts all of them alike. A sample is a batch of back-to-back calls lasting
at least `--sample` seconds (`block_until_ready` after each), divided by its calls. Medians over
the rounds of wall time (what a caller waits; `--clock cpu`: of the process's CPU time, all
threads, steadier on a machine busy with other jobs) decide; the ratio on the other clock is
printed beside ("other clock"). Radius maps: uniform in [R/2, R] with `max_radius=R` (the soft
filter, issue 19's question), a smooth field over [R/2, R] (jitter, supersample: the original
"smooth depth"), or a few levels drawn at random per pixel (layered, tabulated). The soft filter
is timed forward (the constant's question) or, with `--mode jvp`, as a JVP along the image and the
radius map (what a Levenberg-Marquardt fit evaluates).

Reading off a value:

- a radius crossover (the three `*SPANS_MIN_RADIUS`): the smallest swept radius from which the
  spans are not slower at every larger swept radius ("consistently not slower"); the jitter and
  supersample sweeps stop after two consecutive radii that the spans win (their cost grows
  linearly in R, the dense gather's quadratically). Not crossed within the sweep: `math.inf`.
- every other constant: the value whose rule makes the best choices on the swept points, scored
  by how much slower than the faster option the chosen one is (geometric mean over the points).
- in both cases the old value is kept when the sweep cannot tell it from the measured one: at
  every swept point where they choose differently, the old value's choice is at most `TIE` (1.1x)
  slower than the other option.

For every rule the summary gives that score, old and measured ("1.00x": every point chose the
faster option), and its worst point.

Constants without a `path=` switch are measured under `jaxdof.internal.tuning.override`, the
library's own way to replace a tuning constant while a candidate compiles (the filters read the
table at trace time).

Run:

    python fits/tune.py                          # every constant (~30 min on 2 busy cores)
    python fits/tune.py --quick                  # small frames, few rounds: a smoke run (~2 min)
    python fits/tune.py --only SPANS_MIN_RADIUS  # one or more constants, named as in _tuning.py
    python fits/tune.py --only SPANS_MIN_RADIUS --size 1024 --radii 16 32 48 64

Prints the conditions, one table per study, the summary (name, old value, measured value) and the
lines to paste into `jaxdof/_tuning.py`. A study script: not run by the tests.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import inspect
import math
import os
import platform
import statistics
import time
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from _common import command, cpu_model, git_state, load_average

import jaxdof

# The kernels with their `path=` switches and the tuning table, all semi-internal.
from jaxdof.internal import (
    exact_soft_filter,
    jitter_filter,
    layered_filter,
    level_index,
    supersample_filter,
    tabulated_filter,
    tap_offsets,
    tuning as _tuning,
    unique_with_index,
)


NEVER, ALWAYS = 0, 10**9  # a patched threshold that turns a branch off / on whatever the size


def patched(name: str, value):
    """The tuning constant `name` set to `value` for the duration (`tuning.override`)."""
    return _tuning.override(**{name: value})


# --------------------------------------------------------------------------------------------
# Timing
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Config:
    quick: bool
    rounds: int
    sample: float  # seconds: the least duration of one timed sample (a batch of calls)
    size: int | None  # overrides each study's frame size
    radii: list[float] | None  # overrides the SPANS_MIN_RADIUS sweep
    clock: str = "wall"  # which median decides: "wall" or "cpu"
    mode: str = "forward"  # SPANS_MIN_RADIUS: time the forward pass or a JVP

    def pick(self, quick, full):
        """A study's setting: `quick` under `--quick`, else `full`."""
        return quick if self.quick else full

    def frame(self, quick: int, full: int) -> int:
        """A study's frame size: `--size`, else `pick(quick, full)`."""
        return self.size or self.pick(quick, full)


@dataclasses.dataclass
class Timing:
    wall: float  # median seconds per call
    cpu: float
    compile: float = math.nan
    clock: str = "wall"

    @property
    def t(self) -> float:
        """The median that decides (`--clock`)."""
        return self.cpu if self.clock == "cpu" else self.wall

    @property
    def other(self) -> float:
        """The other clock's median (printed beside)."""
        return self.wall if self.clock == "cpu" else self.cpu


def compiled(fn: Callable, *args, patch: tuple[str, object] | None = None):
    """`(compiled fn, compile seconds)`: `jax.jit(fn)` lowered and compiled on `args`, with the
    constant `patch = (name, value)` set while it is traced."""
    with patched(*patch) if patch else contextlib.nullcontext():
        t0 = time.perf_counter()
        out = jax.jit(fn).lower(*args).compile()
    return out, time.perf_counter() - t0


def interleaved(candidates: dict[str, Callable[[], object]], cfg: Config) -> dict[str, Timing]:
    """Median wall and CPU seconds per call of each zero-argument callable, timed in turns."""
    per_sample = {}
    for name, fn in candidates.items():  # warm-up, then the calls a sample needs
        jax.block_until_ready(fn())
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        per_sample[name] = max(1, math.ceil(cfg.sample / max(time.perf_counter() - t0, 1e-6)))
    walls = {name: [] for name in candidates}
    cpus = {name: [] for name in candidates}
    names = list(candidates)
    for k in range(cfg.rounds):
        for name in names if k % 2 == 0 else names[::-1]:
            fn, n = candidates[name], per_sample[name]
            w0, c0 = time.perf_counter(), time.process_time()
            for _ in range(n):
                jax.block_until_ready(fn())
            walls[name].append((time.perf_counter() - w0) / n)
            cpus[name].append((time.process_time() - c0) / n)
    return {
        n: Timing(statistics.median(walls[n]), statistics.median(cpus[n]), clock=cfg.clock)
        for n in names
    }


def time_compiled(fns: dict[str, tuple], args: tuple, cfg: Config) -> dict[str, Timing]:
    """`fns`: `{name: (compiled, compile seconds)}`, all called on `args`."""
    out = interleaved({n: (lambda c=c: c(*args)) for n, (c, _) in fns.items()}, cfg)
    for n, (_, seconds) in fns.items():
        out[n].compile = seconds
    return out


def ms(t: float) -> str:
    return f"{t * 1e3:.3g}" if t < 1 else f"{t * 1e3:.0f}"


def table(header: list[str], rows: list[list]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---:|" * len(header)]
    return lines + ["| " + " | ".join(str(x) for x in row) + " |" for row in rows]


def say(lines) -> None:
    print("\n".join(lines) if isinstance(lines, list) else lines, flush=True)


# --------------------------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------------------------


def image_of(size: int, seed: int = 0) -> jax.Array:
    return jnp.asarray(np.random.default_rng(seed).uniform(size=(size, size, 3)), jnp.float32)


def uniform_radius(size: int, r: float, seed: int = 1) -> jax.Array:
    """Radii uniform in [R/2, R] (issue 19's question for the soft filter)."""
    rng = np.random.default_rng(seed)
    return jnp.asarray(rng.uniform(r / 2, r, (size, size)), jnp.float32)


def smooth_radius(size: int, r: float) -> jax.Array:
    """A smooth radius field over [R/2, R] (a smooth depth map's circles)."""
    y, x = np.mgrid[0:size, 0:size] / size
    f = 0.5 + 0.25 * np.sin(2 * np.pi * (1.3 * x + 0.4 * y)) + 0.25 * np.cos(2 * np.pi * 0.9 * y)
    return jnp.asarray(r / 2 + (r / 2) * f, jnp.float32)


def level_map(size: int, levels: np.ndarray, seed: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """`(radius map, index map)`: every pixel one of `levels` (ascending), drawn at random, each
    level used at least once."""
    rng = np.random.default_rng(seed)
    index = rng.integers(0, len(levels), size * size)
    index[: len(levels)] = np.arange(len(levels))
    index = rng.permutation(index).reshape(size, size).astype(np.int32)
    return levels[index].astype(np.float32), index


def spread_levels(n: int, r: float) -> np.ndarray:
    """`n` distinct radii spread over [R/2, R] (at least 0.6: all blur)."""
    return np.linspace(max(r / 2, 0.6), r, n).astype(np.float32)


def spread_level_map(size: int, n: int, r: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`(levels, radius map, index map)`: `spread_levels(n, r)` drawn at random per pixel
    (`level_map`)."""
    levels = spread_levels(n, r)
    return (levels, *level_map(size, levels))


# --------------------------------------------------------------------------------------------
# Reading off a value
# --------------------------------------------------------------------------------------------

# A swept point is `(key, ratio)`: `ratio` = time of the option a rule takes "below" (up to the
# threshold, under the crossover, while cheaper by the cost rule) / time of the other option.
Point = tuple[object, float]
Rule = Callable[[object, object], bool]  # rule(value, key): does `value` take the "below" option?


def slowdown(points: list[Point], rule: Rule, value) -> tuple[float, float]:
    """`(geometric mean, worst)` over the points of (time of the option `value` takes) / (time of
    the faster option): 1 where the rule always takes the faster one."""
    f = [max(x, 1.0) if rule(value, k) else max(1 / x, 1.0) for k, x in points]
    return math.exp(statistics.fmean(math.log(v) for v in f)), max(f)


#: Two options within this factor of each other at a point are a tie (the noise of one run on a
#: shared machine): the old value is not replaced over such points.
TIE = 1.1


def keep_old(points: list[Point], rule: Rule, old, new):
    """`old` where the sweep cannot tell it from `new`: at every point where they take different
    options, the two are within `TIE` of each other (or `old` is the faster there); else `new`."""
    old_loss = [x if rule(old, k) else 1 / x for k, x in points if rule(old, k) != rule(new, k)]
    return old if all(v <= TIE for v in old_loss) else new


def best_value(points: list[Point], rule: Rule, candidates: list, old):
    """The first of `[old, *candidates]` whose rule is least slow (geometric mean), within 1 %."""
    scores = [slowdown(points, rule, c)[0] for c in [old, *candidates]]
    return next(c for c, v in zip([old, *candidates], scores) if v <= min(scores) * 1.01)


def midpoints(flips: list[float]) -> list[float]:
    """One value inside each interval that the flip points cut (0, inf) into, 2 significant
    digits (the rule's choices change only at the flips)."""
    f = sorted(set(flips))
    mids = [f[0] / 2] + [math.sqrt(a * b) for a, b in zip(f, f[1:])] + [f[-1] * 2]
    return [float(f"{m:.2g}") for m in mids]


def geometric_mean(values: list[float]) -> float:
    """To two significant digits."""
    return float(f"{math.exp(statistics.fmean(math.log(v) for v in values)):.2g}")


def radius_crossover(spans_over_dense: dict[float, float]) -> float:
    """The smallest swept radius from which the spans are not slower at every larger one."""
    out = math.inf
    for r in sorted(spans_over_dense, reverse=True):
        if spans_over_dense[r] > 1:
            break
        out = r
    return out


def below_crossover(value: float, r: float) -> bool:
    """The crossover rule (`spans.use_spans`): the dense gather below `value`."""
    return r < value


def up_to(value, size) -> bool:
    """A threshold rule: the first option up to `value`."""
    return size <= value


def fmt(value) -> str:
    if isinstance(value, dict):
        return "{" + ", ".join(f"{fmt_key(k)}: {fmt(v)}" for k, v in value.items()) + "}"
    if isinstance(value, float):
        if math.isinf(value):
            return "math.inf"
        if value == round(value):
            return f"{value:.1f}"
        if 0 < value < 1 and (1 / value).is_integer():
            return f"1 / {1 / value:.0f}"
        return f"{value:g}"
    return str(value)


def fmt_key(k) -> str:
    return "math.inf" if k == math.inf else str(int(k))


@dataclasses.dataclass
class Result:
    name: str
    measured: object  # the value to paste; `None`: not re-measured
    note: str = ""
    old_score: tuple[float, float] | None = None  # slowdown() of the old and the measured value
    new_score: tuple[float, float] | None = None


def result(name: str, points: list[Point], rule: Rule, new, note: str, keep=True) -> Result:
    """The Result for a single-valued constant, the old value kept where `keep_old` says so
    (unless `keep=False`: the old value is not allowed)."""
    old = getattr(_tuning, name)
    value = keep_old(points, rule, old, new) if keep else new
    return Result(name, value, note, slowdown(points, rule, old), slowdown(points, rule, value))


# --------------------------------------------------------------------------------------------
# The studies, one per constant
# --------------------------------------------------------------------------------------------


def study_spans_min_radius(cfg: Config) -> Result:
    """`SPANS_MIN_RADIUS`: the soft filter's crossover from the dense gather to row spans."""
    size = cfg.frame(128, 256)
    default = cfg.pick([8, 16, 32], [8, 12, 16, 20, 24, 32, 40, 48, 64])
    radii = [float(r) for r in cfg.radii or default]
    say(
        f"Soft filter {cfg.mode}, {size}^2 RGB float32, radii uniform in [R/2, R], max_radius = R; "
        "`exact_soft_filter(..., path='dense' | 'spans')`; ms per call (median)."
    )
    image = image_of(size)
    header = ["R", "dense ms", "spans ms", "spans/dense", "other clock", "compile s"]
    runs, rows = {}, []
    for r in radii:
        radius = uniform_radius(size, r)

        def soft(i, q, p, r=r):
            if cfg.mode == "forward":
                return exact_soft_filter(i, q, max_radius=r, path=p)
            # the tangent along the image and the radius map (forward mode, as Levenberg-Marquardt)
            f = lambda i_, q_: exact_soft_filter(i_, q_, max_radius=r, path=p)
            return jax.jvp(f, (i, q), (jnp.ones_like(i), jnp.ones_like(q)))

        fns = {
            p: compiled(lambda i, q, p=p: soft(i, q, p), image, radius) for p in ("dense", "spans")
        }
        t = runs[r] = time_compiled(fns, (image, radius), cfg)
        d, s = t["dense"], t["spans"]
        rows.append(
            [f"{r:g}", ms(d.t), ms(s.t), f"{s.t / d.t:.2f}", f"{s.other / d.other:.2f}"]
            + [f"{d.compile:.1f} / {s.compile:.1f}"]
        )
        say(table(header, rows)[-1])
    say(["", *table(header, rows)])
    ratios = {r: t["spans"].t / t["dense"].t for r, t in runs.items()}
    points = [(r, 1 / x) for r, x in ratios.items()]
    res = result("SPANS_MIN_RADIUS", points, below_crossover, radius_crossover(ratios), "")
    if 16.0 in runs:
        t = runs[16.0]
        fastest = min(t["dense"].t, t["spans"].t)
        for crossover in dict.fromkeys([_tuning.SPANS_MIN_RADIUS, res.measured]):
            default = t["dense"] if below_crossover(crossover, 16.0) else t["spans"]
            say(
                f"With SPANS_MIN_RADIUS = {crossover:g}, R = 16 takes the "
                f"{'dense gather' if default is t['dense'] else 'spans'}: "
                f"{default.t / fastest:.2f}x the faster forced path."
            )
    res.note = f"{size}^2; spans/dense " + ", ".join(f"{r:g}: {x:.2f}" for r, x in ratios.items())
    return res


def _by_samples(kind: str, cfg: Config) -> Result:
    """A `{samples: radius}` crossover table (jitter or supersample): spans against dense by `n`."""
    is_jitter = kind == "jitter"
    name = "JITTER_SPANS_MIN_RADIUS" if is_jitter else "SUPERSAMPLE_SPANS_MIN_RADIUS"
    old: dict = getattr(_tuning, name)
    size = cfg.frame(64, 256)
    beyond = 64 if is_jitter else 32  # the `inf` key is measured at this many samples
    keys = cfg.pick(list(old)[1:2], list(old))
    sweep = [float(r) for r in cfg.pick([8, 16, 24], [8, 12, 16, 20, 24, 32, 40, 48, 64])]
    say(
        f"{kind}, forward, {size}^2 RGB float32, smooth radius field over [R/2, R]; "
        f"`{kind}_filter(..., path='dense' | 'spans')`, key `inf` measured at n = {beyond}; ms "
        "per call (median)."
    )
    image = image_of(size)
    key = jax.random.key(0)
    header = ["n", "R", "dense ms", "spans ms", "spans/dense", "other clock"]
    measured, rows, all_points = dict(old), [], []
    for k in keys:
        n = beyond if k == math.inf else int(k)
        ratios, wins = {}, 0
        for r in sweep:
            radius = smooth_radius(size, r)

            def fn(i, q, p, r=r, n=n):
                if is_jitter:
                    return jitter_filter(i, q, max_radius=r, samples=n, key=key, path=p)
                return supersample_filter(i, q, max_radius=r, samples=n, path=p)

            fns = {
                p: compiled(lambda i, q, p=p: fn(i, q, p), image, radius)
                for p in ("dense", "spans")
            }
            t = time_compiled(fns, (image, radius), cfg)
            d, s = t["dense"], t["spans"]
            ratios[r] = s.t / d.t
            rows.append(
                [n, f"{r:g}", ms(d.t), ms(s.t), f"{ratios[r]:.2f}", f"{s.other / d.other:.2f}"]
            )
            say(table(header, rows)[-1])
            wins = wins + 1 if ratios[r] <= 1 else 0
            if wins == 2:  # linear against quadratic cost: the spans keep winning from here
                break
        points = [(r, 1 / x) for r, x in ratios.items()]
        measured[k] = keep_old(points, below_crossover, old[k], radius_crossover(ratios))
        all_points += [((k, r), x) for r, x in points]
    say(["", *table(header, rows)])

    def rule(table_, key_r):
        return below_crossover(table_[key_r[0]], key_r[1])

    return Result(
        name,
        measured,
        f"{size}^2" + (" (quick: one key)" if cfg.quick else ""),
        slowdown(all_points, rule, old),
        slowdown(all_points, rule, measured),
    )


def study_jitter_spans_min_radius(cfg: Config) -> Result:
    """`JITTER_SPANS_MIN_RADIUS`: jitter's dense/spans crossover by the number of points."""
    return _by_samples("jitter", cfg)


def study_supersample_spans_min_radius(cfg: Config) -> Result:
    """`SUPERSAMPLE_SPANS_MIN_RADIUS`: supersample's dense/spans crossover by `n`."""
    return _by_samples("supersample", cfg)


def _threshold_study(
    name: str,
    sizes: list,
    build,
    cfg: Config,
    labels: tuple[str, str],
    unit: str,
    setting: str,
    allowed=None,
) -> Result:
    """The study of a threshold `name`: the sweep over `sizes` (`_threshold_sweep`), the value read
    off it (`_threshold_result`). `setting` (the frame and radius) is said first and noted;
    `allowed(value, {s: (first compile s, second compile s)})`: a further condition on a value."""
    note = f"{setting}, {unit} in {sizes}"
    say(f"Swept: {note}.")
    points, compile_s = _threshold_sweep(name, sizes, build, cfg, labels, unit)
    ok = None if allowed is None else (lambda value: allowed(value, compile_s))
    return _threshold_result(name, points, note, ok)


def _threshold_sweep(
    name: str, sizes: list[int], build, cfg: Config, labels: tuple[str, str], unit: str
) -> tuple[list[Point], dict[int, tuple[float, float]]]:
    """Time `build(s) -> (fn, args)` compiled with the constant `name` patched to `ALWAYS` (the
    first option, taken up to the threshold) and to `NEVER` at every size `s`:
    `(points, {s: (first compile s, second compile s)})`."""
    points, compile_s, rows = [], {}, []
    header = [unit, f"{labels[0]} ms", f"{labels[1]} ms", "ratio", "other clock", "compile s"]
    for s in sizes:
        fns, args = {}, ()
        for label, value in zip(labels, (ALWAYS, NEVER)):
            fn, args = build(s)
            fns[label] = compiled(fn, *args, patch=(name, value))
        t = time_compiled(fns, args, cfg)
        a, b = t[labels[0]], t[labels[1]]
        points.append((s, a.t / b.t))
        compile_s[s] = (a.compile, b.compile)
        rows.append(
            [s, ms(a.t), ms(b.t), f"{a.t / b.t:.2f}", f"{a.other / b.other:.2f}"]
            + [f"{a.compile:.1f} / {b.compile:.1f}"]
        )
        say(table(header, rows)[-1])
    say(["", *table(header, rows)])
    return points, compile_s


def _threshold_result(name: str, points: list[Point], note: str, allowed=None) -> Result:
    """A threshold read off `points` (`up_to`); `allowed(value)`: a further condition."""
    old = getattr(_tuning, name)
    sizes = [k for k, _ in points]
    candidates = sorted([0, *sizes], key=lambda c: abs(c - old))
    if allowed is not None:
        candidates = [c for c in candidates if allowed(c)]
    keep = allowed is None or allowed(old)
    new = best_value(points, up_to, candidates, old if keep else candidates[0])
    return result(name, points, up_to, new, note, keep)


def study_compare_all_max(cfg: Config) -> Result:
    """`COMPARE_ALL_MAX`: jitter's compare-every-threshold count against the binary search.

    Jitter, dense path, RGB float32, smooth radius, n points: compare against every threshold
    (COMPARE_ALL_MAX >= n) vs binary search.
    """
    size, r = cfg.frame(64, 256), 8.0
    image, radius, key = image_of(size), smooth_radius(size, r), jax.random.key(0)

    def build(n):
        fn = lambda i, q: jitter_filter(i, q, max_radius=r, samples=n, key=key, path="dense")
        return fn, (image, radius)

    ns, labels = cfg.pick([16, 64], [4, 16, 32, 64]), ("compare", "search")
    return _threshold_study("COMPARE_ALL_MAX", ns, build, cfg, labels, "n", f"{size}^2, R = {r:g}")


def study_unroll_rows(cfg: Config) -> Result:
    """`UNROLL_ROWS`: supersample's sub-rows written out against a `fori_loop`.

    Supersample, dense path, RGB float32, smooth radius, n x n samples: the sub-rows of a count
    written out (UNROLL_ROWS >= n) vs a fori_loop. A value is allowed only if every n it writes
    out compiles in at most 2x the loop's time (the reason for the constant).
    """
    size, r = cfg.frame(64, 128), 4.0
    image, radius = image_of(size), smooth_radius(size, r)

    def build(n):
        fn = lambda i, q: supersample_filter(i, q, max_radius=r, samples=n, path="dense")
        return fn, (image, radius)

    def allowed(value, compile_s):
        return all(first <= 2 * second for n, (first, second) in compile_s.items() if n <= value)

    ns, setting = cfg.pick([8, 16, 32], [4, 8, 16, 32, 64]), f"{size}^2, R = {r:g}"
    return _threshold_study(
        "UNROLL_ROWS", ns, build, cfg, ("unrolled", "loop"), "n", setting, allowed
    )


def study_unroll_levels(cfg: Config) -> Result:
    """`UNROLL_LEVELS`: the layered FFT level loop written out against a scan.

    Layered, FFT path, RGB float32, L levels (a concrete map, static levels): the level loop
    written out (UNROLL_LEVELS >= L) vs lax.scan.
    """
    size, r = cfg.frame(128, 256), 8.0
    image = image_of(size)

    def build(n):
        levels, radius, index = spread_level_map(size, n, r)
        radius = jnp.asarray(radius)
        fn = lambda i: layered_filter(
            i, radius, max_radius=r, layers=n, assignment=index, static_levels=levels, path="fft"
        )
        return fn, (image,)

    counts, labels = cfg.pick([3, 8], [3, 8, 12, 16]), ("unrolled", "scan")
    return _threshold_study(
        "UNROLL_LEVELS", counts, build, cfg, labels, "L", f"{size}^2, R = {r:g}"
    )


def study_fft_level_cost_in_taps(cfg: Config) -> Result:
    """`FFT_LEVEL_COST_IN_TAPS`: layered's direct sum against its FFTs (traced radius)."""
    size = cfg.frame(128, 256)
    radii = cfg.pick([2.0, 8.0, 16.0], [2.0, 4.0, 8.0, 12.0, 16.0])
    counts = cfg.pick([2, 8], [2, 4, 8, 16])
    say(
        f"layered, traced radius, {size}^2 RGB float32, L levels at random per pixel: "
        "path='direct' (tabulated gather, T taps) vs path='fft'. The rule takes the direct sum "
        "when T (1 + L/5) < C L; break-even C at a point: T (1 + L/5) / (L direct/fft)."
    )
    image = image_of(size)
    header = ["R", "taps", "L", "direct ms", "fft ms", "direct/fft", "other clock", "break-even C"]
    rows, points = [], []
    for r in radii:
        taps = len(tap_offsets(r))
        for n in counts:
            radius = jnp.asarray(spread_level_map(size, n, r)[1])
            fns = {
                p: compiled(
                    lambda i, q, p=p, r=r, n=n: layered_filter(
                        i, q, max_radius=r, layers=n, path=p
                    ),
                    image,
                    radius,
                )
                for p in ("direct", "fft")
            }
            t = time_compiled(fns, (image, radius), cfg)
            d, f = t["direct"], t["fft"]
            points.append(((taps, n), d.t / f.t))
            rows.append(
                [f"{r:g}", taps, n, ms(d.t), ms(f.t), f"{d.t / f.t:.2f}"]
                + [f"{d.other / f.other:.2f}", f"{taps * (1 + n / 5) * f.t / (n * d.t):.0f}"]
            )
            say(table(header, rows)[-1])
    say(["", *table(header, rows)])

    def rule(c, key):
        taps, n = key
        return taps * (1 + n / 5) < c * n

    model = geometric_mean([t * (1 + n / 5) / (n * x) for (t, n), x in points])
    flips = [t * (1 + n / 5) / n for (t, n), _ in points]
    new = best_value(points, rule, [model, *midpoints(flips)], _tuning.FFT_LEVEL_COST_IN_TAPS)
    note = f"{size}^2, R in {radii}, L in {counts}; break-even C (geometric mean): {model:g}"
    return result("FFT_LEVEL_COST_IN_TAPS", points, rule, new, note)


def study_layer_cost_in_taps(cfg: Config) -> Result:
    """`LAYER_COST_IN_TAPS`: `auto`'s FFT layers against the tabulated gather (concrete map)."""
    sizes = [cfg.size] if cfg.size else cfg.pick([64], [64, 256])
    radii = cfg.pick([8.0], [4.0, 8.0, 16.0, 24.0])
    n = 4
    say(
        f"auto's two candidates on a concrete map of {n} blurred levels (RGB float32): layered FFT "
        "(static levels, no sharp level) vs the tabulated gather. `auto` takes the FFTs when "
        "L <= T // C; the cost of one FFT layer in taps at a point: T (fft / tabulated) / L."
    )
    header = [
        "size",
        "R",
        "taps",
        "fft ms",
        "tabulated ms",
        "fft/tabulated",
        "other clock",
        "layer cost",
    ]
    rows, points = [], []
    for size in sizes:
        image = image_of(size)
        for r in radii:
            levels, radius, index = spread_level_map(size, n, r)
            radius = jnp.asarray(radius)
            taps = len(tap_offsets(r))
            fns = {
                "fft": compiled(
                    lambda i, q=radius, r=r, a=index, lv=levels: layered_filter(
                        i, q, max_radius=r, layers=n, assignment=a, static_levels=lv, path="fft"
                    ),
                    image,
                ),
                "tabulated": compiled(
                    lambda i, r=r, lv=levels, a=index: tabulated_filter(
                        i, max_radius=r, levels=lv, index=a
                    ),
                    image,
                ),
            }
            t = time_compiled(fns, (image,), cfg)
            f, g = t["fft"], t["tabulated"]
            points.append(((size, taps), f.t / g.t))
            rows.append(
                [size, f"{r:g}", taps, ms(f.t), ms(g.t), f"{f.t / g.t:.2f}"]
                + [f"{f.other / g.other:.2f}", f"{taps * f.t / (g.t * n):.0f}"]
            )
            say(table(header, rows)[-1])
    say(["", *table(header, rows)])

    def rule(c, key):  # auto.max_layers: FFT layers when L <= taps // c
        return n <= key[1] // c

    model = geometric_mean([taps * x / n for (_, taps), x in points])
    flips = [taps / n for (_, taps), _ in points]
    new = best_value(points, rule, [model, *midpoints(flips)], _tuning.LAYER_COST_IN_TAPS)
    note = f"{sizes}, R in {radii}, L = {n}; layer cost (geometric mean): {model:g}"
    return result("LAYER_COST_IN_TAPS", points, rule, new, note)


def study_table_levels_per_pixel(cfg: Config) -> Result:
    """`TABLE_LEVELS_PER_PIXEL`: `auto`'s tabulated gather against the soft filter, by the number
    of distinct radii per pixel."""
    size = cfg.frame(64, 256)
    r = 8.0
    fractions = cfg.pick([1 / 16, 1 / 4], [1 / 256, 1 / 32, 1 / 8, 1 / 2, 1.0])
    say(
        f"{size}^2 RGB float32, R = {r:g}, L = f H W distinct radii over [R/2, R] at random per "
        "pixel: tabulated gather (levels, index) vs the soft filter (its default path). The host's "
        "index map (`unique_with_index`, once per concrete map) is apart."
    )
    image = image_of(size)
    header = ["f", "L", "tabulated ms", "host index ms", "soft ms", "tabulated/soft", "other clock"]
    rows, points = [], []
    for f in fractions:
        levels, radius, index = spread_level_map(size, max(2, int(f * size * size)), r)
        radius_j = jnp.asarray(radius)
        t0 = time.perf_counter()
        unique_with_index(radius)
        host = time.perf_counter() - t0
        fns = {
            "tabulated": compiled(
                lambda i, lv=levels, a=index: tabulated_filter(i, max_radius=r, levels=lv, index=a),
                image,
            ),
            "soft": compiled(lambda i, q=radius_j: exact_soft_filter(i, q, max_radius=r), image),
        }
        t = time_compiled(fns, (image,), cfg)
        a, b = t["tabulated"], t["soft"]
        points.append((f, a.t / b.t))
        rows.append(
            [f"{f:g}", len(levels), ms(a.t), ms(host), ms(b.t), f"{a.t / b.t:.2f}"]
            + [f"{a.other / b.other:.2f}"]
        )
        say(table(header, rows)[-1])
    say(["", *table(header, rows)])
    old = _tuning.TABLE_LEVELS_PER_PIXEL
    new = best_value(points, up_to, sorted([0.0, *fractions], key=lambda c: abs(c - old)), old)
    return result("TABLE_LEVELS_PER_PIXEL", points, up_to, new, f"{size}^2, R = 8")


def study_select_max_levels(cfg: Config) -> Result:
    """`SELECT_MAX_LEVELS`: the tabulated look-up as a chain of selects against `jnp.take`.

    Tabulated gather, RGB float32, L levels: look-up by a chain of selects (SELECT_MAX_LEVELS >= L)
    vs jnp.take.
    """
    size, r = cfg.frame(128, 512), 2.0
    image = image_of(size)

    def build(n):
        levels, _, index = spread_level_map(size, n, r)
        return (lambda i: tabulated_filter(i, max_radius=r, levels=levels, index=index)), (image,)

    counts, labels = cfg.pick([3, 16], [3, 8, 16, 24, 32]), ("select", "take")
    return _threshold_study(
        "SELECT_MAX_LEVELS", counts, build, cfg, labels, "L", f"{size}^2, R = {r:g}"
    )


def study_fused_max_taps(cfg: Config) -> Result:
    """`FUSED_MAX_TAPS`: the tabulated gather's class loop written out against scanned.

    Tabulated gather, RGB float32, three levels (one sharp), by the window's taps: the class loop
    written out (FUSED_MAX_TAPS >= taps) vs scanned.
    """
    size, radii = cfg.frame(128, 256), cfg.pick([2.0, 2.9], [2.0, 2.5, 2.9, 3.0])
    by_taps = {len(tap_offsets(r)): r for r in radii}
    image = image_of(size)

    def build(taps):
        r = by_taps[taps]
        levels = np.asarray([0.0, r / 2, r], np.float32)
        _, index = level_map(size, levels)
        return (lambda i: tabulated_filter(i, max_radius=r, levels=levels, index=index)), (image,)

    setting = f"{size}^2, R = {', '.join(f'{r:g}' for r in radii)}"
    return _threshold_study(
        "FUSED_MAX_TAPS", list(by_taps), build, cfg, ("written out", "scan"), "taps", setting
    )


def study_compare_max_levels(cfg: Config) -> Result:
    """`COMPARE_MAX_LEVELS`: the index map by comparison passes against `np.unique`'s argsort."""
    size = cfg.frame(256, 1024)
    counts = cfg.pick([3, 16, 64], [3, 8, 16, 24, 32, 48, 64])
    say(
        f"index map of a {size}^2 float32 map with L distinct values (numpy, host): one comparison "
        "pass per value (COMPARE_MAX_LEVELS >= L) vs np.unique(return_inverse=True)."
    )
    header = ["L", "compare ms", "argsort ms", "ratio"]
    rows, points = [], []
    for n in counts:
        values, _ = level_map(size, spread_levels(n, 8.0))
        uniq = np.unique(values)

        def call(value, values=values, uniq=uniq):
            with patched("COMPARE_MAX_LEVELS", value):
                return level_index(values, uniq)

        t = interleaved({"compare": lambda: call(ALWAYS), "argsort": lambda: call(NEVER)}, cfg)
        a, b = t["compare"], t["argsort"]
        points.append((n, a.t / b.t))
        rows.append([n, ms(a.t), ms(b.t), f"{a.t / b.t:.2f}"])
        say(table(header, rows)[-1])
    say(["", *table(header, rows)])
    return _threshold_result("COMPARE_MAX_LEVELS", points, f"{size}^2, L in {counts}")


def not_measured(name: str, why: str) -> Callable[[Config], Result]:
    def study(cfg: Config) -> Result:
        say(f"Not re-measured: {why}")
        return Result(name, None, why)

    study.__doc__ = f"`{name}`: not re-measured."
    return study


STUDIES: dict[str, Callable[[Config], Result]] = {
    "SPANS_MIN_RADIUS": study_spans_min_radius,
    "JITTER_SPANS_MIN_RADIUS": study_jitter_spans_min_radius,
    "SUPERSAMPLE_SPANS_MIN_RADIUS": study_supersample_spans_min_radius,
    "SPANS_MIN_RADIUS_JACOBIAN": not_measured(
        "SPANS_MIN_RADIUS_JACOBIAN",
        "measured inside a fit's Jacobian by `python fits/fit_spans.py` (its own study).",
    ),
    "COMPARE_ALL_MAX": study_compare_all_max,
    "UNROLL_ROWS": study_unroll_rows,
    "UNROLL_LEVELS": study_unroll_levels,
    "FUSED_MAX_TAPS": study_fused_max_taps,
    "SELECT_MAX_LEVELS": study_select_max_levels,
    "COMPARE_MAX_LEVELS": study_compare_max_levels,
    "FFT_LEVEL_COST_IN_TAPS": study_fft_level_cost_in_taps,
    "LAYER_COST_IN_TAPS": study_layer_cost_in_taps,
    "MAX_LAYERS": not_measured(
        "MAX_LAYERS",
        "a cap on the number of FFT layers (the assignment's and the spectra's memory grow with "
        "it), never a timed crossover; LAYER_COST_IN_TAPS decides below it.",
    ),
    "TABLE_LEVELS_PER_PIXEL": study_table_levels_per_pixel,
}


# --------------------------------------------------------------------------------------------
# The run
# --------------------------------------------------------------------------------------------


def machine() -> list[str]:
    """The conditions of the run (with `fits/_common.py`'s helpers)."""
    return [
        f"- command: `{command('tune.py')}`, {datetime.datetime.now().isoformat(timespec='minutes')}",
        f"- {cpu_model()}, {os.cpu_count()} logical cores, load average {load_average()} at the "
        f"start; backend {jax.default_backend()} ({jax.devices()[0].device_kind})",
        f"- jax / jaxlib {jax.__version__} / {jax.lib.__version__}, jaxdof {jaxdof.__version__} "
        f"(git {git_state()}), Python {platform.python_version()}, "
        f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '(unset)')}",
    ]


def score(s: tuple[float, float] | None) -> str:
    return "-" if s is None else f"{s[0]:.2f}x / {s[1]:.2f}x"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small frames, few rounds")
    parser.add_argument(
        "--only", nargs="+", metavar="NAME", choices=list(STUDIES), help="only these constants"
    )
    parser.add_argument("--rounds", type=int, help="timed rounds (default 7; quick 3)")
    parser.add_argument("--sample", type=float, help="least seconds per sample (0.2; quick 0.05)")
    parser.add_argument("--size", type=int, help="the frame size of every study")
    parser.add_argument("--radii", type=float, nargs="+", help="the SPANS_MIN_RADIUS sweep")
    parser.add_argument(
        "--mode",
        choices=("forward", "jvp"),
        default="forward",
        help="SPANS_MIN_RADIUS: time the forward pass (the constant's question) or a JVP along the "
        "image and the radius map (what a Levenberg-Marquardt fit evaluates)",
    )
    parser.add_argument(
        "--clock",
        choices=("wall", "cpu"),
        default="wall",
        help="the median that decides: wall time (default) or the process's CPU time, steadier "
        "on a machine busy with other jobs",
    )
    args = parser.parse_args(argv)
    cfg = Config(
        quick=args.quick,
        rounds=args.rounds or (3 if args.quick else 7),
        sample=args.sample or (0.05 if args.quick else 0.2),
        size=args.size,
        radii=args.radii,
        clock=args.clock,
        mode=args.mode,
    )
    say(["# Tuning constants re-measured (`fits/tune.py`)", "", *machine(), ""])
    results, start = [], time.perf_counter()
    for name in args.only or list(STUDIES):
        say([f"## {name}", "", inspect.getdoc(STUDIES[name]) or "", ""])
        t0 = time.perf_counter()
        res = STUDIES[name](cfg)
        results.append(res)
        new = "-" if res.measured is None else fmt(res.measured)
        old = fmt(getattr(_tuning, name))
        say(["", f"{name}: old {old}, measured {new} ({time.perf_counter() - t0:.0f} s)", ""])
    rows = []
    for res in results:
        old = getattr(_tuning, res.name)
        new = "not re-measured" if res.measured is None else fmt(res.measured)
        changed = res.measured is not None and res.measured != old
        rows.append(
            [f"`{res.name}`", fmt(old), new, "**changed**" if changed else ""]
            + [score(res.old_score), score(res.new_score), res.note]
        )
    say(
        [
            "## Summary",
            "",
            "Old / new rule: how much slower than the faster option the choices of the old and of "
            "the measured value are over the swept points (geometric mean / worst point).",
            "",
            *table(["name", "old", "measured", "", "old rule", "new rule", "how"], rows),
            "",
        ]
    )
    load = load_average()
    stamp = f"fits/tune.py{' --quick' if cfg.quick else ''}, {datetime.date.today().isoformat()}"
    paste = [
        f"{r.name} = {fmt(r.measured)}  # {stamp}"
        for r in results
        if r.measured is not None and r.measured != getattr(_tuning, r.name)
    ]
    title = "To paste into `jaxdof/_tuning.py` (then update each provenance comment):"
    if cfg.quick:
        title = (
            "A --quick run (small frames, few rounds) checks the script; do not paste its values:"
        )
    say(
        [title, ""]
        + (["```python", *paste, "```"] if paste else ["(nothing changed)"])
        + ["", f"Total {time.perf_counter() - start:.0f} s; load average at the end {load}"]
    )


if __name__ == "__main__":
    main()
