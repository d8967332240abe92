"""`fit_lens(..., verbose=...)`: the solver's `verbose` callable, passed through to optimistix
with the lens each step reached."""

from __future__ import annotations

import equinox as eqx
import jax
import numpy as np

from .._lens import ThinLens
from .layout import _Layout
from .residual import _Model


def _with_verbose(solver, verbose, model: _Model, layout: _Layout, tag: str):
    """`solver` with its `verbose` set as `fit_lens`'s `verbose` asks (unchanged for `False`):
    a callable receives optimistix's `(description, value)` pairs and `lenses=("Lenses",
    ThinLens)`, the lens of every photo (a leading axis of photos) at the last accepted step,
    decoded from the solver's coordinates by the fit's own map; `True` prints them."""
    if verbose is False:
        return solver
    show = verbose if callable(verbose) else _printer(model.n_targets, tag)

    def with_lenses(**kwargs):
        y = kwargs.get("y_last_accepted_step")
        if y is not None:
            rows = model.natural(y[1].astype(layout.base.dtype), layout)  # (T, 4): f, N, d_f, p
            kwargs["lenses"] = ("Lenses", ThinLens(*(rows[..., k] for k in range(4))))
        show(**kwargs)

    return eqx.tree_at(lambda s: s.verbose, solver, with_lenses)


def _printer(n_targets: int, level: str = ""):
    """A `verbose` callable that prints step, loss and the lenses (prefixed by `level`, the
    pyramid level, when coarse-to-fine), one line per start."""

    def show(step, loss, f, n, d_f):
        steps, losses = np.reshape(step, -1), np.reshape(loss, -1)
        f, n, d_f = (np.reshape(x, (-1, n_targets)) for x in (f, n, d_f))
        for i in range(len(f)):
            parts = []
            for t in range(n_targets):
                tag = f"[{t}]" if n_targets > 1 else ""
                parts.append(
                    f"f{tag}={f[i, t] * 1e3:.5g} mm N{tag}={n[i, t]:.5g} d_f{tag}={d_f[i, t]:.6g} m"
                )
            head = level + (f"start {i} " if len(f) > 1 else "")
            st = int(steps[min(i, len(steps) - 1)])
            ls = float(losses[min(i, len(losses) - 1)])
            print(f"{head}step {st}: loss {ls:.6g}  " + "  ".join(parts), flush=True)

    def verbose(**kwargs):
        lens = kwargs["lenses"][1]
        jax.debug.callback(
            show,
            kwargs["num_steps"][1],
            kwargs["loss_last_accepted_step"][1],
            lens.focal_length,
            lens.f_number,
            lens.focus_distance,
        )

    return verbose
