"""What the CLI prints: a fit as text or JSON, the demo's table, and the solver's progress."""

from __future__ import annotations

import json
import sys

import jax
import numpy as np

from .parse import FIELDS


def note(msg: str) -> None:
    """A remark for the user (a decoding note, a file written): stderr, keeping stdout clean."""
    print(msg, file=sys.stderr)


# ----------------------------------------------------------------------------------------------
# A fit's result


def _lens_dict(lens, index: int) -> dict:
    def value(name):
        v = np.asarray(getattr(lens, name))
        v = v if v.ndim == 0 else v.reshape(-1)[index]
        # The shortest decimal that round-trips the array's own precision (0.085, not
        # 0.08500000089406967 for a float32 value).
        return float(str(v.item() if v.dtype == np.float64 else np.float32(v)))

    return {name: value(name) for name in (*FIELDS, "pixel_pitch")}


def _stderr_dict(stderr: dict, index: int | None) -> dict:
    out = {}
    for name, v in stderr.items():
        v = np.asarray(v)
        v = v if v.ndim == 0 or index is None else v.reshape(-1)[min(index, v.size - 1)]
        out[name] = float(f"{float(v):.4g}") if np.isfinite(v) else None
    return out


def fit_summary(result, n_targets: int) -> dict:
    """The `fit --json` object of a `FitResult` with `n_targets` photos; the text output reads it too.

    Lens 0's fields and `stderr` at the top level (a single photo's fit reads as one lens), then
    `success`, `message`, `steps`, `loss`, and `lenses` with one entry (fields and `stderr`) per
    photo. SI units; a standard error the data cannot determine is `null`.
    """
    # TODO(lead): build from FitResult.to_dict()
    n = n_targets
    lenses = [_lens_dict(result.lenses, i) for i in range(n)]
    errors = [_stderr_dict(result.stderr, i if n > 1 else None) for i in range(n)]
    return {
        **lenses[0],
        "stderr": errors[0],
        "success": bool(result.success),
        "message": str(result.message),
        "steps": int(result.num_steps),
        "loss": float(result.loss),
        "lenses": [{**lens, "stderr": err} for lens, err in zip(lenses, errors)],
    }


def format_value(name: str, v, err=None) -> str:
    """`v` (SI) in the unit a photographer reads (mm, m), with `± err` when it is known."""
    if name in ("focal_length", "focus_distance", "pixel_pitch"):
        scale, unit = (1e3, "mm") if name != "focus_distance" else (1.0, "m")
        s = f"{v * scale:.5g} {unit}"
        return s + (f" ± {err * scale:.2g}" if err is not None else "")
    return f"{v:.5g}" + (f" ± {err:.2g}" if err is not None else "")


def print_fit(summary: dict, target_names: list[str], free, *, as_json: bool) -> None:
    """A `fit_summary` on stdout: one JSON object, or a block per lens and a verdict line."""
    if as_json:
        print(json.dumps(summary, indent=2))
        return
    several = len(summary["lenses"]) > 1
    for name_of_target, lens in zip(target_names, summary["lenses"]):
        print((f"target {name_of_target}" if several else "recovered lens") + ":")
        for name in FIELDS:
            state = "" if name in free else "  (held)"
            value = format_value(name, lens[name], lens["stderr"].get(name))
            print(f"  {name:15s} {value}{state}")
    verdict = "converged" if summary["success"] else "did NOT converge"
    print(
        f"{verdict} after {summary['steps']} steps, loss {summary['loss']:.4g}: {summary['message']}"
    )


def print_demo(truth, start, result) -> None:
    """The demo's table: truth, start and recovered value (± standard error) of each field."""
    err = _stderr_dict(result.stderr, None)
    print(f"{'':16s}{'truth':>12s}{'start':>12s}{'recovered':>24s}")
    for name in FIELDS:
        t, s, r = (float(np.asarray(getattr(x, name))) for x in (truth, start, result.lens))
        print(
            f"  {name:14s}{format_value(name, t):>12s}{format_value(name, s):>12s}"
            f"{format_value(name, r, err.get(name)):>24s}" + ("" if name in err else "  (held)")
        )
    verdict = "converged" if result.success else "did NOT converge"
    print(f"{verdict} in {int(result.num_steps)} steps, loss {float(result.loss):.3g}")


# ----------------------------------------------------------------------------------------------
# Progress


class Progress:
    """A `fit_lens` `verbose` callable: one stderr line per accepted step of each start.

    optimistix calls it inside the compiled solve, once per solver step, with `(description,
    value)` pairs as keywords; the values are traced, so they reach Python through
    `jax.debug.callback`. Two things make its raw calls repeat themselves, and are undone here:

    - It fires on every trial step, accepted or not; the loss it reports is the last accepted
      one. A line is printed only when the start's count of accepted steps grows.
    - `fit_lens` solves all starts at once under `vmap`, whose loop runs until the last start is
      done; the starts already done report their final state again at every step. JAX runs the
      callback once per start, in order of the batch (`ordered=True`; unordered ones are
      reordered), without saying which start it is: the calls of one solver step come as starts
      0, 1, ..., and a solve begins with every start at step 0, which counts the starts.

    `fit_lens` runs one solve per pyramid level (coarsest first) and per refit of a grown window;
    lines are tagged `solve k` (1, 2, ... in order) and `start i` within it.
    """

    def __init__(self):
        self._solve = 0
        self._starts = 0  # in the current solve
        self._calls = 0  # since the current solve's first step
        self._accepted: dict[int, int] = {}  # start -> accepted steps already printed
        self._stepping = True  # the last call was past step 0: a step-0 call begins a solve

    def __call__(self, **kwargs):
        # optimistix >= 0.1 passes (description, value) pairs; other solvers may pass fewer.
        names = ("num_steps", "accepted_steps", "loss_last_accepted_step")
        if all(name in kwargs for name in names):
            values = [kwargs[name][1] for name in names]
            jax.debug.callback(self._record, *values, ordered=True)

    def _record(self, step, accepted, loss) -> None:
        steps, accepted, loss = (np.reshape(np.asarray(x), -1) for x in (step, accepted, loss))
        batched = steps.size > 1  # one call for all starts (a JAX that does not unroll vmap)
        for i in range(steps.size):
            start = i if batched else None
            self._one(int(steps[i]), int(accepted[i]), float(loss[i]), start)

    def _one(self, step: int, accepted: int, loss: float, start: int | None) -> None:
        if step == 0:  # every start's first call; nothing is accepted yet (the loss is 0)
            if self._stepping:
                self._solve, self._starts, self._accepted = self._solve + 1, 0, {}
                self._stepping = False
            self._starts += 1
            return
        if not self._stepping:
            self._stepping, self._calls = True, 0
        if start is None:
            start = self._calls % max(self._starts, 1)
            self._calls += 1
        if accepted > self._accepted.get(start, 0):
            self._accepted[start] = accepted
            print(
                f"  solve {self._solve} start {start}  step {step:3d}  loss {loss:.6g}",
                file=sys.stderr,
                flush=True,
            )
