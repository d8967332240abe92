"""What the studies in `fits/` share: the conditions of a run, timing, result files and caches.

A study run as `python fits/<study>.py` has `fits/` first on `sys.path`, so it imports this module
as `from _common import ...`. Nothing here imports jax or jaxdof at import time: a study sets
`jax_enable_x64` before anything creates an array, and importing this module must not come first.

- Conditions: `machine_info` (the benchmarks' list), `versions_line`, `load_average`,
  `accelerator`, `git_state`, `command`.
- Timing, two algorithms kept apart:
  `medians_in_turns` times *single* calls of several compiled functions in turns, round after
  round, and returns medians of wall and process CPU time (`timed_in_turns` keeps every sample,
  `median_time` is the one-function case after a warm-up); `batched_medians_in_turns` times
  *batches* of back-to-back calls (`calls_per_sample` sizes them to `SAMPLE_S`), wall time per
  call, for sub-millisecond calls where a single call mostly times the runtime waking up.
- Results: `RESULTS`, `result_path`, `write_markdown`, `save_json`, `load_json`.
- Disk caches: `cached_npz`, `cached_json` (under `CACHE`, which git ignores).
"""

from __future__ import annotations

import json
import os
import pathlib
import platform
import statistics
import subprocess
import sys
import time
import timeit
from collections.abc import Callable, Hashable, Mapping, Sequence
from typing import Any


FITS = pathlib.Path(__file__).resolve().parent
RESULTS = FITS / "results"
CACHE = FITS / ".cache"


# ------------------------------------------------------------------------------ conditions


def load_average() -> str:
    """`"1.0, 0.8, 0.5"`: the 1, 5 and 15 minute load averages, or `"?, ?, ?"` where unknown."""
    if not hasattr(os, "getloadavg"):
        return "?, ?, ?"
    return ", ".join(f"{x:.1f}" for x in os.getloadavg())


def cpu_model() -> str:
    """The CPU's model name from `/proc/cpuinfo`, else `platform.processor()`."""
    cpu = platform.processor() or "unknown"
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return cpu


def machine_info() -> dict[str, str]:
    """CPU model, core count, load, library versions and the JAX device: the conditions of a run."""
    import jax

    import jaxdof

    return {
        "cpu": f"{cpu_model()}, {os.cpu_count()} logical cores",
        "device": ", ".join(f"{d} ({d.device_kind})" for d in jax.devices()),
        "load average (1, 5, 15 min) at start": load_average(),
        "python": platform.python_version(),
        "jax / jaxlib": f"{jax.__version__} / {jax.lib.__version__}",
        "jaxdof": jaxdof.__version__,
        "XLA_FLAGS": os.environ.get("XLA_FLAGS", "(unset)"),
        # glibc's allocator settings change the soft filter's cost at megapixel sizes
        # (fits/results/README.md, filter cost)
        "glibc MALLOC_* environment": ", ".join(
            f"{k}={v}" for k, v in sorted(os.environ.items()) if k.startswith("MALLOC_")
        )
        or "(unset)",
    }


def versions_line() -> str:
    """`"jax 0.4.35, jaxdof 0.1.0, Python 3.11.7, x86_64 CPU"`: a report's one-line software."""
    import jax

    import jaxdof

    return (
        f"jax {jax.__version__}, jaxdof {jaxdof.__version__}, Python {platform.python_version()}, "
        f"{platform.machine()} CPU"
    )


def accelerator() -> dict[str, str]:
    """`{"machine": ...}` naming the accelerator when JAX runs on one, else `{}` (a CPU run)."""
    import jax

    device = jax.devices()[0]
    if device.platform == "cpu":
        return {}
    return dict(
        machine=f"one {device.device_kind} ({jax.default_backend()}, jax {jax.__version__})"
    )


def git_state() -> str:
    """Commit of the checkout and the library files with uncommitted edits (what was timed)."""
    root = FITS.parent
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "diff", "--name-only", "HEAD", "--", "jaxdof"],
            cwd=root,
            capture_output=True,
            text=True,
        ).stdout.split()
    except OSError:
        return "unknown"
    return head + (f" + uncommitted edits to {', '.join(dirty)}" if dirty else "")


def command(script: str, argv: Sequence[str] | None = None) -> str:
    """`"python fits/<script> <arguments>"`: the command line of this run (`argv`, else the
    process's own arguments), as a report quotes it."""
    args = sys.argv[1:] if argv is None else list(argv)
    return f"python fits/{script}" + "".join(f" {a}" for a in args)


# ------------------------------------------------------------------------------ timing


def compile_all(fns: Mapping[Hashable, Callable], *args, warm_up: bool = True) -> tuple[dict, dict]:
    """Compile every `fn` in `fns` on `args` ahead of time: `({name: compiled}, {name: compile
    seconds})`. With `warm_up`, each compiled function is called once right after compiling (the
    first touch of its buffers stays out of the timings)."""
    import jax

    compiled, seconds = {}, {}
    for name, fn in fns.items():
        t0 = time.perf_counter()
        compiled[name] = jax.jit(fn).lower(*args).compile()
        seconds[name] = time.perf_counter() - t0
        if warm_up:
            jax.block_until_ready(compiled[name](*args))
    return compiled, seconds


def timed_in_turns(
    fns: Mapping[Hashable, Callable], args: tuple, repeats: int
) -> dict[Hashable, list[tuple[float, float]]]:
    """`{name: [(wall s, CPU s), ...]}`: each function called once per round, in turns, for
    `repeats` rounds (no warm-up here).

    Interleaving exposes every function to the same drift in the machine's load, so ratios between
    them stay meaningful on a shared machine. CPU time (`time.process_time`, all threads) is less
    sensitive than wall time to other processes' load.
    """
    import jax

    runs: dict[Hashable, list[tuple[float, float]]] = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            w0, c0 = time.perf_counter(), time.process_time()
            jax.block_until_ready(fn(*args))
            runs[name].append((time.perf_counter() - w0, time.process_time() - c0))
    return runs


def medians_in_turns(
    fns: Mapping[Hashable, Callable], args: tuple, repeats: int
) -> dict[Hashable, tuple[float, float]]:
    """`{name: (median wall s, median CPU s)}` of `timed_in_turns`."""
    return {
        name: (statistics.median(r[0] for r in rs), statistics.median(r[1] for r in rs))
        for name, rs in timed_in_turns(fns, args, repeats).items()
    }


def median_time(f: Callable[[], Any], repeats: int) -> tuple[float, float]:
    """Median wall and process CPU time of `f()`, after one warm-up call."""
    import jax

    jax.block_until_ready(f())
    return medians_in_turns({"f": f}, (), repeats)["f"]


#: A batched timing sample lasts about this long (per-call time = batch time / calls):
#: sub-millisecond calls are otherwise dominated by timer and wake-up noise.
SAMPLE_S = 5e-3


def calls_per_sample(fn: Callable, *args, sample_s: float = SAMPLE_S) -> tuple[float, int]:
    """`(seconds of the first call (compile included), calls per timing sample)`: the calls that
    fill about `sample_s`, from 1 to 64, measured on one warm call."""
    import jax

    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    warm = timeit.timeit(lambda: jax.block_until_ready(fn(*args)), number=1)
    return first, max(1, min(64, round(sample_s / max(warm, 1e-9))))


def per_call(fn: Callable, args: tuple, calls: int) -> float:
    """One batched timing sample: seconds per call over `calls` back-to-back calls."""
    import jax

    return timeit.timeit(lambda: jax.block_until_ready(fn(*args)), number=calls) / calls


def batched_medians_in_turns(
    timers: Sequence[tuple[Callable, tuple, int]], repeat: int
) -> list[float]:
    """Median per-call wall time of each `(fn, args, calls)`, sampled (`per_call`) in `repeat`
    rounds that visit every timer once (so a change of the machine's load hits all alike)."""
    samples: list[list[float]] = [[] for _ in timers]
    for _ in range(repeat):
        for i, (fn, args, calls) in enumerate(timers):
            samples[i].append(per_call(fn, args, calls))
    return [float(statistics.median(v)) for v in samples]


# ------------------------------------------------------------------------------ results


def result_path(
    stem: str, ending: str = ".md", *, quick: bool = False, tag: str = ""
) -> pathlib.Path:
    """`fits/results/<stem>[_quick]<tag><ending>` (the folder made if missing), e.g.
    `result_path("tradeoff", "_raw.json", tag="_gpu")`."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    return RESULTS / f"{stem}{'_quick' if quick else ''}{tag}{ending}"


def write_markdown(path: pathlib.Path, lines: Sequence[str]) -> pathlib.Path:
    """Write `lines` joined by newlines, plus a final newline; the folder is made if missing."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


def save_json(
    path: pathlib.Path, data: Any, *, indent: int | None = None, final_newline: bool = False
) -> pathlib.Path:
    """Write `data` as JSON (each study keeps the layout of its committed raw file)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=indent) + ("\n" if final_newline else ""))
    return path


def load_json(path: pathlib.Path) -> Any:
    return json.loads(path.read_text())


# ------------------------------------------------------------------------------ disk caches


def cached_npz(path: pathlib.Path, fn: Callable[[], Any], *, verb: str = "computed"):
    """`(array, seconds)`: `fn()` and the seconds it took, from `path` (`.npz`) when it exists,
    else computed, saved there and announced as `  <verb> <name> in <s> s`."""
    import numpy as np

    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists():
        with np.load(path, allow_pickle=False) as f:
            return f["a"], float(f["seconds"])
    t0 = time.perf_counter()
    a = fn()
    dt = time.perf_counter() - t0
    np.savez_compressed(path, a=a, seconds=dt)
    print(f"  {verb} {path.stem} in {dt:.1f} s", flush=True)
    return a, dt


def cached_json(path: pathlib.Path, fn: Callable[[], Any]) -> tuple[Any, bool]:
    """`(value, computed)`: `fn()` from `path` (JSON) when it exists, else computed and saved;
    `computed` says which."""
    if path.exists():
        return json.loads(path.read_text()), False
    path.parent.mkdir(parents=True, exist_ok=True)
    value = fn()
    path.write_text(json.dumps(value))
    return value, True
