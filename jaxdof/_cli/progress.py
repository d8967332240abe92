"""What the CLI shows while it works: on stderr, as a live status line, as plain lines, or not.

`Display.for_stderr(quiet)` picks the mode once per command:

- `live` (stderr is a terminal): one status line, redrawn in place by `rich` and gone when the
  command ends: what is being done (reading a file, compiling; a fit's solve k, its step, the
  best of its n starts so far with its loss and lens; a render's band b of n), a bar where the
  amount of work is known, the elapsed time and the time left (`<=` when only a bound is
  known: a solve's `--max-steps`). A few lines stay: each solve's summary.
- `lines` (stderr is a file or a pipe: a log, a test): plain lines for the long loops only, one
  per accepted solver step and one per band of a banded render, each with the elapsed time;
  nothing for the stages, so a failing command still says one line.
- `off` (`--quiet`): nothing.

`FitProgress` turns what `jaxdof.fit_lens` hands its `verbose` callable into those lines.
"""

from __future__ import annotations

import sys
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from rich.console import Console
from rich.progress import BarColumn, Progress, ProgressColumn, SpinnerColumn, Task, TextColumn
from rich.table import Column
from rich.text import Text


class Display:
    """The command's progress on stderr in one of the modes above (`live`, `lines`, `off`).

    Use as a context manager around the command's work: the live line starts on entry and is
    cleared on exit, also when the command fails, so that an error is still one line.
    """

    def __init__(self, mode: str = "lines"):
        if mode not in ("live", "lines", "off"):
            raise ValueError(f"mode must be 'live', 'lines' or 'off', got {mode!r}")
        self.mode = mode
        self._t0 = time.monotonic()
        self._progress: Progress | None = None  # while live
        self._task: Any = None

    @classmethod
    def for_stderr(cls, quiet: bool = False) -> Display:
        """`off` with `quiet`, `live` when stderr is a terminal, else `lines`."""
        if quiet:
            return cls("off")
        return cls("live" if _is_terminal(sys.stderr) else "lines")

    @property
    def elapsed(self) -> float:
        """Seconds since the display was made (the command's start)."""
        return time.monotonic() - self._t0

    def __enter__(self) -> Display:
        if self.mode == "live":
            self._start_live()
        return self

    def __exit__(self, *exc) -> None:
        if self._progress is not None:
            self._progress.stop()
            self._progress = None

    def _start_live(self) -> None:
        progress = Progress(
            SpinnerColumn(),
            # the description takes the width the others leave, cut with an ellipsis: one line
            TextColumn(
                "{task.description}",
                table_column=Column(ratio=1, no_wrap=True, overflow="ellipsis"),
            ),
            BarColumn(bar_width=10),
            _Elapsed(self._t0),
            _Remaining(),
            console=Console(file=sys.stderr),
            transient=True,
            expand=True,
            redirect_stdout=False,  # stdout is the result (`--json`): never the live area's
        )
        progress.start()
        self._progress = progress
        self._task = progress.add_task("starting", total=None, bound=False)

    def status(
        self, text: str, *, completed: int = 0, total: int | None = None, bound: bool = False
    ) -> None:
        """What is being done now (live only): `text`, and `completed` of `total` units (a bar and
        the time left; `bound`: `total` is only an upper bound). A new `total` restarts the
        time-left estimate."""
        if self._progress is None:
            return
        task = self._progress.tasks[0]
        if task.total != total or completed < task.completed:
            self._progress.reset(self._task, total=total, completed=completed, bound=bound)
        self._progress.update(self._task, description=text, completed=completed, bound=bound)

    def print(self, text: str) -> None:
        """A line that stays, in the `live` and `lines` modes (above the live line when live)."""
        if self.mode == "off":
            return
        if self._progress is not None:
            self._progress.console.print(text, highlight=False, markup=False)
        else:
            print(text, file=sys.stderr, flush=True)

    def log(self, text: str) -> None:
        """A line of the record of a long loop: `lines` mode only (live shows it in `status`)."""
        if self.mode == "lines":
            print(text, file=sys.stderr, flush=True)


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # a closed or file-like stream without a terminal
        return False


def _clock(seconds: int | float) -> str:
    """`m:ss`, or `h:mm:ss` from an hour on."""
    h, rest = divmod(int(round(seconds)), 3600)
    return f"{h}:{rest // 60:02d}:{rest % 60:02d}" if h else f"{rest // 60}:{rest % 60:02d}"


class _Elapsed(ProgressColumn):
    """Time since the command started (not since the current stage)."""

    def __init__(self, t0: float):
        super().__init__()
        self.t0 = t0

    def render(self, task: Task) -> Text:
        return Text(_clock(time.monotonic() - self.t0), style="progress.elapsed")


class _Remaining(ProgressColumn):
    """The current stage's time left, `<=` when its total is a bound; blank when unknown."""

    def render(self, task: Task) -> Text:
        left = task.time_remaining
        if left is None or task.total is None:
            return Text("")
        bound = "<= " if task.fields.get("bound") else ""
        return Text(f"{bound}{_clock(left)} left", style="progress.remaining")


# ----------------------------------------------------------------------------------------------
# A fit's solver steps


_FIELDS = ("focal_length", "f_number", "focus_distance")


def lens_text(rows: np.ndarray, fields=_FIELDS) -> str:
    """`(T, 4)` lens rows `(f, N, d_f, pitch)` (SI) as `f 50 mm  N 2.8  d_f 3 m`, the `fields`
    named only (the free ones: a held field does not move); a field that differs between targets
    lists each target's value (`d_f 3/2.5/2 m`)."""

    def values(column: np.ndarray, scale: float) -> str:
        v = [float(x) * scale for x in column]
        v = v[:1] if np.allclose(v, v[0], rtol=1e-6) else v
        return "/".join("inf" if not np.isfinite(x) else f"{x:.4g}" for x in v)

    rows = np.asarray(rows, np.float64).reshape(-1, 4)
    parts = {
        "focal_length": f"f {values(rows[:, 0], 1e3)} mm",
        "f_number": f"N {values(rows[:, 1], 1.0)}",
        "focus_distance": f"d_f {values(rows[:, 2], 1.0)} m",
    }
    return "  ".join(parts[name] for name in _FIELDS if name in fields)


# What the fit's compiled stages do (`jaxdof._fit.solve.run_stage`'s names), as `watch` shows them.
_STAGES = {
    "fit_starts": "solving",
    "restate": "restating the lens at focus infinity",
    "finish": "standard errors and the adequacy test",
    "nuisance scores": "testing for exposure, vignetting, illumination and registration",
    "rank at init": "checking the data's rank at the start",
}


class FitProgress:
    """A `fit_lens` `verbose` callable: each accepted step of each start, once, on a `Display`.

    optimistix calls it inside the compiled solve, once per solver step, with `(description,
    value)` pairs as keywords; the values are traced, so they reach Python through
    `jax.debug.callback`. Two things make its raw calls repeat themselves, and are undone here:

    - It fires on every trial step, accepted or not; the loss it reports is the last accepted
      one. A step is shown only when the start's count of accepted steps grows.
    - `fit_lens` solves all starts at once under `vmap`, whose loop runs until the last start is
      done; the starts already done report their final state again at every step. JAX runs the
      callback once per start, in order of the batch (`ordered=True`; unordered ones are
      reordered), without saying which start it is: the calls of one solver step come as starts
      0, 1, ..., and a solve begins with every start at step 0, which counts the starts.

    `fit_lens` runs one solve per pyramid level (coarsest first) and per refit of a grown window;
    they are `solve k` (1, 2, ... in order), and the starts within one `start i/n` (from 1).
    Each step also shows the lens it reached (`fit_lens` passes it as `lenses`; its `fields`: the
    free ones). In `lines` mode every accepted step is a line; `live` shows the solve's step
    against `max_steps` and its best start so far (the starts run at once) on the status line,
    and keeps one summary line per solve.
    """

    def __init__(
        self,
        display: Display | None = None,
        *,
        fields=_FIELDS,
        max_steps: int | None = None,
    ):
        self.display = Display("lines") if display is None else display
        self.fields = tuple(fields)
        self.max_steps = max_steps
        self._solve = 0
        self._starts = 0  # in the current solve
        self._calls = 0  # since the current solve's first step
        self._accepted: dict[int, int] = {}  # start -> accepted steps already shown
        self._stepping = True  # the last call was past step 0: a step-0 call begins a solve
        self._best: tuple[float, str] | None = None  # the solve's lowest loss and its lens
        self._steps = 0  # the solve's steps so far (its slowest start's)
        self._solve_t0 = 0.0

    def __call__(self, **kwargs):
        # optimistix >= 0.1 passes (description, value) pairs; other solvers may pass fewer.
        names = ("num_steps", "accepted_steps", "loss_last_accepted_step")
        if all(name in kwargs for name in names):
            values = [kwargs[name][1] for name in names]
            lens = kwargs.get("lenses", (None, None))[1]
            if lens is None:
                jax.debug.callback(self._record, *values, ordered=True)
            else:
                fields = (lens.focal_length, lens.f_number, lens.focus_distance, lens.pixel_pitch)
                rows = jnp.stack(fields, -1)  # (T, 4), as `lens_text` reads them
                jax.debug.callback(self._record, *values, rows, ordered=True)

    def watch(self, name: str, seconds: float | None) -> None:
        """A stage of the fit (`jaxdof._fit.solve.watch_stages`): the status line as it starts
        (or a line of its own in `lines` mode for work outside the compiled stages), a line in
        `lines` mode as it ends, with its time."""
        what = _STAGES.get(name)
        if seconds is None:
            if what is None:  # work outside the compiled stages: "choosing tiles ..."
                self.stage(name)
            else:
                self.display.status(f"{what} (compiled once per shape)")
        elif what is not None:
            self.display.log(f"  {what}: {seconds:.1f} s ({self.display.elapsed:.1f} s)")

    def stage(self, text: str) -> None:
        """Work `fit_lens` does outside the solver (`"choosing tiles ..."`): the status line, or
        a line of its own in `lines` mode."""
        self.display.status(text)
        self.display.log(f"  {text} ({self.display.elapsed:.1f} s)")

    def close(self) -> None:
        """The last solve's summary (call when the fit has returned)."""
        self._summarise()

    def _record(self, step, accepted, loss, rows=None) -> None:
        steps, accepted, loss = (np.reshape(np.asarray(x), -1) for x in (step, accepted, loss))
        batched = steps.size > 1  # one call for all starts (a JAX that does not unroll vmap)
        ys = None if rows is None else np.reshape(np.asarray(rows), (steps.size, -1, 4))
        for i in range(steps.size):
            start = i if batched else None
            yi = None if ys is None else ys[i]
            self._one(int(steps[i]), int(accepted[i]), float(loss[i]), start, yi)

    def _one(self, step: int, accepted: int, loss: float, start: int | None, y) -> None:
        if step == 0:  # every start's first call; nothing is accepted yet (the loss is 0)
            if self._stepping:
                self._summarise()
                self._solve, self._starts, self._accepted = self._solve + 1, 0, {}
                self._stepping, self._best, self._steps = False, None, 0
                self._solve_t0 = self.display.elapsed
            self._starts += 1
            return
        if not self._stepping:
            self._stepping, self._calls = True, 0
        if start is None:
            start = self._calls % max(self._starts, 1)
            self._calls += 1
        if accepted <= self._accepted.get(start, 0):
            return
        self._accepted[start] = accepted
        self._steps = max(self._steps, step)
        lens = self._lens(y)
        if self._best is None or loss < self._best[0]:
            self._best = (loss, lens)
        if self.display.mode == "lines":
            tail = f"  {lens}" if lens else ""
            self.display.log(
                f"  solve {self._solve} start {start + 1}/{self._starts}  step {step:3d}  "
                f"loss {loss:.6g}{tail}  ({self.display.elapsed:.1f} s)"
            )
        else:  # the starts run at once: the solve's step, and its best start so far
            best, best_lens = self._best
            lens_part = f", {best_lens}" if best_lens else ""
            text = (
                f"solve {self._solve}, step {self._steps}: loss {best:.4g}{lens_part} "
                f"(best of {self._starts} starts)"
            )
            self.display.status(text, completed=self._steps, total=self.max_steps, bound=True)

    def _lens(self, rows) -> str:
        """`(T, 4)` lens rows as `lens_text` writes them ("" without)."""
        return "" if rows is None else lens_text(rows, self.fields)

    def _summarise(self) -> None:
        """`live`: one line that stays for the solve just done (the steps were on the status)."""
        if self.display.mode != "live" or self._solve == 0 or self._best is None:
            return
        loss, lens = self._best
        seconds = self.display.elapsed - self._solve_t0
        self.display.print(
            f"solve {self._solve}: {self._starts} start{'s' if self._starts > 1 else ''}, "
            f"{self._steps} steps, best loss {loss:.4g}"
            + (f" ({lens})" if lens else "")
            + f", {seconds:.1f} s"
        )
        self._best = None
