r"""The fit's treatment of the scene, chosen from the scene and the starting lens.

The rules themselves (`Treatment`, `choose_treatment`, their thresholds) are `jaxdof/_scene.py`'s,
shared with `jaxdof.render(method="auto")`; here they meet the fit's problem: its weights, its
forward model and its reduced copies.

On a large photo fitted on tiles, the scout that solves the starts renders soft (with the edge
weight), the tiles keep clear of depth edges while they can (`tiles.choose_tiles`), and the
occlusion render is used only where a chosen tile holds an edge (`Treatment` says which).

Each choice can be forced (`fit_lens(method=..., footprint=..., edge_weight=...)`); a forced
choice is reported as such. `Treatment` is what `FitResult.treatment` holds.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from .._filters import LocalOcclusion, as_method
from .._filters.common import tap_offsets
from .._scene import (
    EDGE_KEEP_MIN as EDGE_KEEP_MIN,
    EDGE_MIN_SHARE as EDGE_MIN_SHARE,
    FOOTPRINT_BELOW as FOOTPRINT_BELOW,
    OCCLUSION_METHOD as OCCLUSION_METHOD,
    Treatment as Treatment,
    choose_treatment as choose_treatment,
    start_circles as start_circles,
)
from .forward import AbstractForwardModel, DefocusModel
from .prepare import Problem, scene_edges
from .strategies import COMPILE_WORK


def check_edge_weight(edge_weight) -> None:
    """`fit_lens(edge_weight=...)`: `None`, a bool or a positive width in pixels."""
    if edge_weight is None or isinstance(edge_weight, bool):
        return
    if not (
        isinstance(edge_weight, (int, float)) and math.isfinite(edge_weight) and edge_weight > 0
    ):
        raise ValueError(
            f"edge_weight must be None (decide), True, False or a width > 0 in photo pixels, "
            f"got {edge_weight!r}"
        )


def treat_scene(
    p: Problem, forward: AbstractForwardModel, model, method, footprint, edge_weight
) -> tuple[Problem, AbstractForwardModel, Treatment]:
    """`fit_lens`'s treatment: the problem with the edge weight multiplied in, the forward model
    (the default one with the chosen method and footprint; a caller's `model` as it is) and the
    `Treatment` that says what was chosen."""
    if model is None:
        occlusion = None if method is None else bool(as_method(method).uses_depth)
    else:
        # The caller's model is what it is: nothing chosen here, the edge weight only if asked.
        occlusion, footprint = False, False
        edge_weight = False if edge_weight is None else edge_weight
    w = p.sqrt_w
    fitted = np.any(w > 0, axis=(0, 3)) if w.ndim == 4 else np.any(w > 0, axis=0)
    treatment, weight = choose_treatment(
        p.depth,
        p.b,
        fitted,
        p.ratio,
        occlusion=occlusion,
        footprint=footprint,
        edge_weight=edge_weight,
        edges=scene_edges(p.depth),
    )
    if model is None:
        chosen = (
            method if method is not None else (OCCLUSION_METHOD if treatment.occlusion else "soft")
        )
        assert isinstance(forward, DefocusModel)  # the default model (no `model` given)
        # The footprint as data: the photo's say tries it on and off with one compiled solve.
        on = jnp.asarray(treatment.footprint)
        forward = dataclasses.replace(forward, method=chosen, footprint=on)
        name = chosen if isinstance(chosen, str) else type(chosen).__name__
        treatment = dataclasses.replace(treatment, method=name)
    else:
        uses_depth = isinstance(model, DefocusModel) and as_method(model.method).uses_depth
        treatment = dataclasses.replace(
            treatment,
            method="model",
            occlusion=bool(uses_depth),
            footprint=bool(getattr(model, "footprint", False)),
            forced=("model",) + (("edge_weight",) if treatment.edge_weight else ()),
        )
    if weight is not None:
        s = p.ratio
        h, wd = fitted.shape
        on_photo = weight.reshape(h, s, wd, s).min(axis=(1, 3))  # the photo pixel's worst
        root = np.sqrt(on_photo).astype(p.dtype)
        sqrt_w = p.sqrt_w * (root[None, ..., None] if w.ndim == 4 else root[None])
        if not np.any(sqrt_w > 0):
            raise ValueError(
                f"edge_weight={edge_weight!r} leaves no photo pixel with weight: every fitted "
                "pixel is near a depth edge; use a smaller width or edge_weight=False"
            )
        p = dataclasses.replace(p, sqrt_w=sqrt_w)
    return p, forward, treatment


def shared_render(forward: AbstractForwardModel, p, window: float) -> AbstractForwardModel:
    """The soft or occlusion render the fit chose as one `LocalOcclusion` with its occlusion
    on or off at run time (`occlude`; off it is the soft filter bit for bit), where the scene
    has depth edges (the photo's say then fits both) and the photo is small: its extra work per
    render (the occlusion sums cost 1-2 soft filters more) under `strategies.COMPILE_WORK`, so the
    compile it saves (seconds) is the larger. Otherwise `forward` as it is."""
    method = forward.method if isinstance(forward, DefocusModel) else None
    if not (isinstance(method, str) and method in ("soft", OCCLUSION_METHOD)):
        return forward
    work = p.args[2].size * len(tap_offsets(window))
    if work > COMPILE_WORK or not scene_edges(p.depth).any():
        return forward
    occlude = jnp.asarray(method == OCCLUSION_METHOD)
    return dataclasses.replace(forward, method=LocalOcclusion(occlude=occlude))
