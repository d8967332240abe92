"""`fit_lens(..., verbose=...)`: the solver's `verbose` callable, passed through to optimistix."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .layout import _Layout
from .residual import _Model


def _with_verbose(solver, verbose, model: _Model, layout: _Layout, tag: str):
    """`solver` with its `verbose` set as `fit_lens`'s `verbose` asks (unchanged for `False`)."""
    if verbose is False:
        return solver
    fn = verbose if callable(verbose) else _verbose_printer(model, layout, tag)
    return eqx.tree_at(lambda s: s.verbose, solver, fn)


def _verbose_printer(model: _Model, layout: _Layout, level: str = ""):
    """An optimistix `verbose` callable that prints step, loss and the current lens (prefixed by
    `level`, the pyramid level, when coarse-to-fine)."""
    layout = jax.tree_util.tree_map(np.asarray, layout)

    def show(step, loss, y):
        ys = np.asarray(y).reshape(-1, np.shape(y)[-1])
        steps, losses = np.reshape(step, -1), np.reshape(loss, -1)
        for i, yi in enumerate(ys):
            rows = np.asarray(
                model.natural(jnp.asarray(yi), jax.tree_util.tree_map(jnp.asarray, layout))
            )
            parts = []
            for t, (f, n, d_f, _) in enumerate(rows):
                tag = f"[{t}]" if model.n_targets > 1 else ""
                parts.append(f"f{tag}={f * 1e3:.5g} mm N{tag}={n:.5g} d_f{tag}={d_f:.6g} m")
            head = level + (f"start {i} " if len(ys) > 1 else "")
            st = int(steps[min(i, len(steps) - 1)])
            ls = float(losses[min(i, len(losses) - 1)])
            print(f"{head}step {st}: loss {ls:.6g}  " + "  ".join(parts), flush=True)

    def verbose(**kwargs):
        jax.debug.callback(
            show,
            kwargs["num_steps"][1],
            kwargs["loss_last_accepted_step"][1],
            kwargs["y_last_accepted_step"][1],
        )

    return verbose
